//! Thresholds from clean calibration episodes, by each monitor's own rule.

use serde::{Deserialize, Serialize};

use super::MonitorError;

/// How a threshold is taken from calibration scores.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "rule", rename_all = "kebab-case")]
pub enum CalibrationRule {
    /// Split conformal over every per-query score of every episode, pooled (TIDE's rule as
    /// the spec reads it): the `k`-th smallest of `n` scores, `k = ⌈(n + 1)(1 − α)⌉`; `k > n`
    /// means the monitor can never fire. Alarm when a score exceeds it.
    PooledConformal {
        /// Miscoverage α (TIDE: 0.001).
        alpha: f64,
    },
    /// Split conformal over each episode's maximum score (the other reading of TIDE):
    /// the same rank over `n` episode maxima.
    EpisodeMaxConformal {
        /// Miscoverage α.
        alpha: f64,
    },
    /// ACC's rule: the `k`-th smallest of the `n` episode maxima, `k = min(n, ⌈(n + 1)(1 −
    /// δ)⌉)`. Alarm when a score reaches it.
    EpisodeMaxCapped {
        /// δ (ACC: 0.05).
        delta: f64,
    },
}

impl CalibrationRule {
    fn level(&self) -> f64 {
        match *self {
            Self::PooledConformal { alpha } | Self::EpisodeMaxConformal { alpha } => alpha,
            Self::EpisodeMaxCapped { delta } => delta,
        }
    }

    /// Whether an alarm needs a score strictly above the threshold (conformal rules) or at
    /// least the threshold (ACC's rule).
    fn strict(&self) -> bool {
        !matches!(self, Self::EpisodeMaxCapped { .. })
    }
}

/// A calibrated threshold, with what it was made from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Threshold {
    /// The rule.
    pub rule: CalibrationRule,
    /// Calibration scores the rank was taken over (per-query scores or episode maxima).
    pub n: usize,
    /// Calibration episodes.
    pub episodes: usize,
    /// The rank `k` (1-based) the rule asks for.
    pub k: usize,
    /// The threshold: the `k`-th smallest score, or `None` when `k > n`: the monitor can
    /// never fire at this level with this many calibration scores (reported, not clipped).
    pub value: Option<f64>,
}

impl Threshold {
    /// Whether `score` raises an alarm.
    pub fn fires(&self, score: f64) -> bool {
        match self.value {
            None => false,
            Some(v) if self.rule.strict() => score > v,
            Some(v) => score >= v,
        }
    }

    /// Index of the first alarming score of an episode's per-query scores.
    pub fn first_alarm(&self, scores: &[f64]) -> Option<usize> {
        scores.iter().position(|&s| self.fires(s))
    }
}

/// The threshold of `rule` over calibration `episodes` (each one episode's per-query scores,
/// in query order; an episode without scores counts as an episode but adds no score).
///
/// # Errors
/// A level outside (0, 1), no scores, or a non-finite score.
pub fn calibrate(rule: CalibrationRule, episodes: &[Vec<f64>]) -> Result<Threshold, MonitorError> {
    let level = rule.level();
    if !(level > 0.0 && level < 1.0) {
        return Err(MonitorError::Config {
            field: "calibration level (alpha or delta)",
            value: level,
            expected: "a level in (0, 1)",
        });
    }
    let mut scores: Vec<f64> = match rule {
        CalibrationRule::PooledConformal { .. } => episodes.iter().flatten().copied().collect(),
        _ => episodes
            .iter()
            .filter_map(|e| e.iter().copied().reduce(f64::max))
            .collect(),
    };
    if let Some(&bad) = scores.iter().find(|v| !v.is_finite()) {
        return Err(MonitorError::Config {
            field: "calibration score",
            value: bad,
            expected: "finite scores",
        });
    }
    let n = scores.len();
    if n == 0 {
        return Err(MonitorError::Config {
            field: "calibration scores",
            value: 0.0,
            expected: "at least one scored query",
        });
    }
    scores.sort_by(f64::total_cmp);
    let rank = ((n as f64 + 1.0) * (1.0 - level)).ceil() as usize;
    let k = match rule {
        CalibrationRule::EpisodeMaxCapped { .. } => rank.clamp(1, n),
        _ => rank.max(1),
    };
    Ok(Threshold {
        rule,
        n,
        episodes: episodes.len(),
        k,
        value: (k <= n).then(|| scores[k - 1]),
    })
}
