//! Runtime chunk-consistency monitors: TIDE and ACC, streaming one score per query beside
//! the [`TemporalEnsembler`](crate::TemporalEnsembler), and their calibration rules.
//!
//! Both compare the newest chunk with what earlier queries predicted for the same control
//! times, over the overlap `O_i = {τ : t_i ≤ τ ≤ t_{i−1} + T_p − T_o}` of query `i` with
//! query `i − 1` (`L = T_p − T_o − h + 1` control times at a fixed stride). The first query of
//! an episode has no score. Monitors are passive: they never change an action.
//!
//! - [`Tide`] (Rewind-IL's Temporal Inter-chunk Discrepancy Estimate): the mean squared
//!   difference between the new chunk and the temporally ensembled plan of the earlier
//!   queries (exponential weights `exp(−m · age)`, age 0 the most recent, `m = 0.01`), or,
//!   behind [`TideReference::PreviousChunk`], the previous raw chunk.
//! - [`Acc`] (VLA-FAIL's action-chunk consistency): the mean absolute difference between the
//!   previous raw chunk and the new one, per coordinate divided by the new chunk's range over
//!   the overlap (floored at `v_min`), smoothed by an exponential moving average (0.9).
//!
//! Units: the caller's action units (PushT: pixels). TIDE's scores and thresholds are in
//! squared action units; ACC's ratio is unit-free except through its floor `v_min`, given in
//! action units. Thresholds come from [`calibrate`] on clean episodes of the same
//! configuration. `../shared/specs/monitors.md` section 5 is the specification; the choices
//! it leaves open are documented on each type.
//!
//! Translation: adding the same vector to every candidate of every query leaves TIDE's score
//! exactly unchanged in exact arithmetic (both the plan and the new chunk move by it), which
//! is the common-mode blind spot; ACC's numerator is unchanged too, but its range is taken
//! across different control times of one chunk, so only a shift that is constant over the
//! chunk leaves it unchanged (property tests in `tests/monitor.rs`).
//!
//! Steady state allocates nothing: the rings are sized at construction.

mod acc;
mod calibrate;
mod tide;

pub use acc::{Acc, AccConfig};
pub use calibrate::{CalibrationRule, Threshold, calibrate};
pub use tide::{Tide, TideConfig, TideReference};

use serde::{Deserialize, Serialize};

use crate::error::EnsembleError;
use crate::geometry::ChunkGeometry;

/// A monitor's or a calibration's invalid input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum MonitorError {
    /// The geometry or the dimension.
    #[error(transparent)]
    Ensemble(#[from] EnsembleError),
    /// A setting or a calibration input out of range.
    #[error("monitor setting {field} = {value}: expected {expected}")]
    Config {
        /// The setting.
        field: &'static str,
        /// Its value.
        value: f64,
        /// What it must be.
        expected: &'static str,
    },
}

/// A streaming per-query monitor.
pub trait Monitor {
    /// Scores the chunk of the query made at control time `t` (`T_p x d`, row-major, row `r`
    /// is the action for `t − T_o + 1 + r`); `None` for an episode's first query.
    ///
    /// # Errors
    /// A chunk of the wrong length, a non-finite value, or a query time not after the last.
    fn observe(&mut self, t: u64, chunk: &[f32]) -> Result<Option<f64>, EnsembleError>;
    /// Forgets the episode (the next query is a first query).
    fn reset(&mut self);
}

/// The monitors mte implements, as sweep specs and records name them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MonitorKind {
    /// [`Tide`] with the ensembled-plan reference.
    Tide,
    /// [`Acc`].
    Acc,
}

impl MonitorKind {
    /// Its name in specs and records.
    pub fn name(self) -> &'static str {
        match self {
            Self::Tide => "tide",
            Self::Acc => "acc",
        }
    }

    /// The calibration rule of its own paper: TIDE split conformal at α = 0.001 over pooled
    /// per-query scores, ACC at δ = 0.05 over per-episode maxima.
    pub fn default_rule(self) -> CalibrationRule {
        match self {
            Self::Tide => CalibrationRule::PooledConformal { alpha: 0.001 },
            Self::Acc => CalibrationRule::EpisodeMaxCapped { delta: 0.05 },
        }
    }

    /// A boxed monitor of this kind with its default configuration, for `d` action
    /// dimensions with the floor `v_min` (action units, ACC only).
    ///
    /// # Errors
    /// An invalid geometry or `d = 0`.
    pub fn build(
        self,
        geometry: ChunkGeometry,
        d: usize,
        v_min: f64,
    ) -> Result<Box<dyn Monitor + Send>, MonitorError> {
        Ok(match self {
            Self::Tide => Box::new(Tide::new(geometry, d, TideConfig::default())?),
            Self::Acc => Box::new(Acc::new(
                geometry,
                d,
                AccConfig {
                    v_min,
                    ..AccConfig::default()
                },
            )?),
        })
    }
}

impl std::fmt::Display for MonitorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for MonitorKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "tide" => Ok(Self::Tide),
            "acc" => Ok(Self::Acc),
            other => Err(format!("unknown monitor {other:?}: expected tide or acc")),
        }
    }
}

/// The chunk check shared by the monitors.
fn check_chunk(chunk: &[f32], geometry: &ChunkGeometry, d: usize) -> Result<(), EnsembleError> {
    let expected = geometry.t_p * d;
    if chunk.len() != expected {
        return Err(EnsembleError::ChunkShape {
            expected,
            got: chunk.len(),
            t_p: geometry.t_p,
            dim: d,
        });
    }
    if let Some(i) = chunk.iter().position(|v| !v.is_finite()) {
        return Err(EnsembleError::NonFiniteChunk {
            row: i / d,
            col: i % d,
        });
    }
    Ok(())
}

/// The overlap of a query at `t` with the previous query at `prev`: control times
/// `t ..= prev + T_p − T_o` (empty when the previous chunk ends before `t`).
fn overlap(geometry: &ChunkGeometry, prev: u64, t: u64) -> std::ops::RangeInclusive<u64> {
    t..=prev + (geometry.t_p - geometry.t_o) as u64
}

/// Row of a chunk queried at `t_query` that covers control time `tau`, if any.
fn row_for(geometry: &ChunkGeometry, t_query: u64, tau: u64) -> Option<usize> {
    let age = tau.checked_sub(t_query)? as usize;
    (age <= geometry.t_p - geometry.t_o).then_some(age + geometry.t_o - 1)
}
