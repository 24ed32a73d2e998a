//! Monitors on recorded runs: thresholds from clean calibration episodes, and per cell the
//! firing rate, the first alarm and the AUROC of the episode score against the clean cell.
//!
//! Episodes record every monitor score ([`crate::record::MonitorTrace`]); nothing here
//! reruns a policy. Calibrate on clean episodes that are *not* the ones evaluated (another
//! run on other seeds), so the clean firing rate is an honest false-alarm rate.

use std::collections::BTreeMap;

use mte_ensemble::MonitorKind;
use mte_ensemble::monitor::{CalibrationRule, MonitorError, Threshold, calibrate};
use serde::{Deserialize, Serialize};

use crate::record::{CellSpec, EpisodeRecord};

/// Thresholds for each monitor, with where they came from (the file `mte monitor
/// calibrate` writes and a control loop loads).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Thresholds {
    /// The calibration run and cell.
    pub source: String,
    /// The arm whose episodes calibrated (monitors see chunks, which every arm of a cell
    /// shares until the closed loop makes the episodes part).
    pub arm: String,
    /// Whether only successful episodes calibrated (both monitors' papers calibrate on
    /// successes).
    pub successful_only: bool,
    /// Per monitor name.
    pub monitors: BTreeMap<String, Threshold>,
}

/// Errors of calibration and evaluation.
#[derive(Debug, thiserror::Error)]
pub enum MonitoringError {
    /// No episode of the calibration cell carries this monitor's scores.
    #[error(
        "no {arm} episode of {cell} has {monitor} scores (run the sweep with monitors = [\"{monitor}\"])"
    )]
    NoScores {
        /// Monitor.
        monitor: String,
        /// Cell.
        cell: String,
        /// Arm.
        arm: String,
    },
    /// The rule or the scores were invalid.
    #[error(transparent)]
    Monitor(#[from] MonitorError),
}

/// The threshold of `kind` by `rule` from the `arm` episodes of `records` (one clean cell),
/// successful ones only if `successful_only`.
///
/// # Errors
/// No episode with this monitor's scores, or the rule's own errors.
pub fn calibrate_records(
    records: &[EpisodeRecord],
    kind: MonitorKind,
    rule: CalibrationRule,
    arm: &str,
    successful_only: bool,
) -> Result<Threshold, MonitoringError> {
    let episodes: Vec<Vec<f64>> = records
        .iter()
        .filter(|r| r.arm == arm && (r.success || !successful_only))
        .filter_map(|r| r.monitors.get(kind.name()))
        .map(|t| t.scores.clone())
        .collect();
    if episodes.is_empty() {
        return Err(MonitoringError::NoScores {
            monitor: kind.to_string(),
            cell: records.first().map_or_else(String::new, |r| r.cell.clone()),
            arm: arm.to_string(),
        });
    }
    Ok(calibrate(rule, &episodes)?)
}

/// One monitor on one arm of one cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MonitorRow {
    /// Cell id.
    pub cell: String,
    /// Arm.
    pub arm: String,
    /// Monitor name.
    pub monitor: String,
    /// Episodes with this monitor's scores.
    pub episodes: usize,
    /// Episodes with at least one alarm.
    pub fired: usize,
    /// Mean index of the first alarming query over the episodes that fired.
    pub first_alarm_mean: Option<f64>,
    /// The clean cell the AUROC compares with (same policy and stride), if any.
    pub reference: Option<String>,
    /// AUROC of the episode score (max over queries), this cell's episodes positive, the
    /// reference's negative; `None` for a clean cell or without a reference.
    pub auroc: Option<f64>,
    /// Hanley–McNeil 95% interval of the AUROC, clipped to [0, 1].
    pub auroc_ci: Option<(f64, f64)>,
    /// The ROC curve behind the AUROC, `(false positive rate, true positive rate)` points
    /// ([`mte_stats::roc_curve`]); empty where the AUROC is `None`.
    pub roc: Vec<(f64, f64)>,
}

impl MonitorRow {
    /// Fraction of episodes that fired.
    pub fn firing_rate(&self) -> f64 {
        self.fired as f64 / self.episodes.max(1) as f64
    }
}

/// Hanley and McNeil's (1982) standard error of an AUROC `a` from `n1` positives and `n0`
/// negatives.
pub fn auroc_se(a: f64, n1: usize, n0: usize) -> f64 {
    let (q1, q2) = (a / (2.0 - a), 2.0 * a * a / (1.0 + a));
    let (n1, n0) = (n1 as f64, n0 as f64);
    ((a * (1.0 - a) + (n1 - 1.0) * (q1 - a * a) + (n0 - 1.0) * (q2 - a * a)) / (n1 * n0))
        .max(0.0)
        .sqrt()
}

/// Rows for every cell, arm and thresholded monitor of a run (`records` grouped by cell).
pub fn evaluate(
    cells: &[CellSpec],
    records: &BTreeMap<String, Vec<EpisodeRecord>>,
    thresholds: &Thresholds,
) -> Vec<MonitorRow> {
    let mut rows = Vec::new();
    for c in cells {
        let reference = (!c.corruption.is_clean())
            .then(|| {
                cells
                    .iter()
                    .find(|r| r.corruption.is_clean() && r.same_policy(c) && r.h == c.h)
            })
            .flatten();
        let empty = Vec::new();
        let own = records.get(&c.id).unwrap_or(&empty);
        for arm in &c.arms {
            for (name, threshold) in &thresholds.monitors {
                let maxima = |recs: &[EpisodeRecord]| -> Vec<f64> {
                    recs.iter()
                        .filter(|r| &r.arm == arm)
                        .filter_map(|r| r.monitors.get(name)?.max())
                        .collect()
                };
                let traces: Vec<&crate::record::MonitorTrace> = own
                    .iter()
                    .filter(|r| &r.arm == arm)
                    .filter_map(|r| r.monitors.get(name))
                    .collect();
                if traces.is_empty() {
                    continue;
                }
                let alarms: Vec<usize> = traces
                    .iter()
                    .filter_map(|t| {
                        threshold
                            .first_alarm(&t.scores)
                            .map(|i| i + t.first_query as usize)
                    })
                    .collect();
                let (pos, neg) = (
                    maxima(own),
                    reference.map(|r| maxima(records.get(&r.id).unwrap_or(&empty))),
                );
                let auroc = neg.as_ref().and_then(|n| mte_stats::auroc(&pos, n).ok());
                let roc = neg
                    .as_ref()
                    .and_then(|n| mte_stats::roc_curve(&pos, n).ok())
                    .unwrap_or_default();
                let auroc_ci = auroc.zip(neg.as_ref()).map(|(a, n)| {
                    let se = auroc_se(a, pos.len(), n.len());
                    ((a - 1.96 * se).max(0.0), (a + 1.96 * se).min(1.0))
                });
                rows.push(MonitorRow {
                    cell: c.id.clone(),
                    arm: arm.clone(),
                    monitor: name.clone(),
                    episodes: traces.len(),
                    fired: alarms.len(),
                    first_alarm_mean: (!alarms.is_empty())
                        .then(|| alarms.iter().sum::<usize>() as f64 / alarms.len() as f64),
                    reference: reference.map(|r| r.id.clone()),
                    auroc,
                    auroc_ci,
                    roc,
                });
            }
        }
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hanley_mcneil_by_hand() {
        // By hand for A = 0.8 and 50 + 50: Q1 = 2/3, Q2 = 32/45, variance =
        // (0.16 + 49 (2/3 - 0.64) + 49 (32/45 - 0.64)) / 2500 = 4.95111 / 2500.
        let se = auroc_se(0.8, 50, 50);
        assert!((se - (4.951_111_f64 / 2500.0).sqrt()).abs() < 1e-6, "{se}");
        // A perfect separation has zero spread; a coin has the largest.
        assert_eq!(auroc_se(1.0, 50, 50), 0.0);
        assert!(auroc_se(0.5, 50, 50) > auroc_se(0.8, 50, 50));
    }
}
