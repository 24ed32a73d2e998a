//! TIDE: the mean squared difference between the new chunk and what the earlier queries
//! planned for the overlap.

use serde::{Deserialize, Serialize};

use super::{Monitor, MonitorError, check_chunk, overlap, row_for};
use crate::error::EnsembleError;
use crate::geometry::ChunkGeometry;

/// What the new chunk is compared with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TideReference {
    /// The temporally ensembled plan of all earlier queries covering each control time (the
    /// paper's reading; the spec's default).
    #[default]
    EnsembledPlan,
    /// The previous query's raw chunk (another reading of Rewind-IL).
    PreviousChunk,
}

/// TIDE's settings. Defaults: the spec's (section 5).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TideConfig {
    /// The reference the new chunk is compared with.
    pub reference: TideReference,
    /// Decay `m` of the plan's weights `exp(−m · age)`, age 0 the most recent earlier query
    /// covering the control time (ACT's deployed 0.01).
    pub m: f64,
}

impl Default for TideConfig {
    fn default() -> Self {
        Self {
            reference: TideReference::EnsembledPlan,
            m: 0.01,
        }
    }
}

/// TIDE over a stream of chunks; see the module docs of [`crate::monitor`].
#[derive(Clone, Debug)]
pub struct Tide {
    geometry: ChunkGeometry,
    d: usize,
    config: TideConfig,
    /// The last `slots` chunks (ring), and their query times.
    ring: Vec<f32>,
    times: Vec<u64>,
    /// Chunks held, and the slot of the newest.
    held: usize,
    newest: usize,
    /// Per-coordinate plan accumulators.
    sum: Vec<f64>,
    /// `exp(−m · age)` for every age a plan can have.
    weights: Vec<f64>,
}

impl Tide {
    /// A monitor for chunks of `geometry` with `d` coordinates.
    ///
    /// # Errors
    /// An invalid geometry, `d = 0`, or a negative or non-finite `m`.
    pub fn new(
        geometry: ChunkGeometry,
        d: usize,
        config: TideConfig,
    ) -> Result<Self, MonitorError> {
        let geometry = ChunkGeometry::new(geometry.t_p, geometry.t_o, geometry.h)
            .map_err(EnsembleError::from)?;
        if d == 0 {
            return Err(EnsembleError::ZeroDimension.into());
        }
        if !(config.m.is_finite() && config.m >= 0.0) {
            return Err(MonitorError::Config {
                field: "tide.m",
                value: config.m,
                expected: "a finite decay >= 0",
            });
        }
        // Every chunk that can cover a control time of the next overlap: M_max of the
        // geometry, one more for the chunk being scored.
        let slots = geometry.m_max() + 1;
        Ok(Self {
            geometry,
            d,
            config,
            ring: vec![0.0; slots * geometry.t_p * d],
            times: vec![0; slots],
            held: 0,
            newest: 0,
            sum: vec![0.0; d],
            weights: (0..slots)
                .map(|age| (-config.m * age as f64).exp())
                .collect(),
        })
    }

    fn slots(&self) -> usize {
        self.times.len()
    }

    /// Slot of the `back`-th most recent held chunk (0 = newest).
    fn slot_back(&self, back: usize) -> usize {
        (self.newest + self.slots() - back) % self.slots()
    }

    /// Squared difference of `new_row` from the reference at control time `tau`, summed over
    /// the coordinates; `None` when no earlier chunk covers `tau`.
    fn squared_error(&mut self, tau: u64, new_row: &[f32]) -> Option<f64> {
        let (g, d) = (self.geometry, self.d);
        let depth = match self.config.reference {
            TideReference::EnsembledPlan => self.held,
            TideReference::PreviousChunk => self.held.min(1),
        };
        self.sum.iter_mut().for_each(|s| *s = 0.0);
        let (mut weight, mut age) = (0.0f64, 0usize);
        for back in 0..depth {
            let slot = self.slot_back(back);
            let Some(r) = row_for(&g, self.times[slot], tau) else {
                continue;
            };
            let w = self.weights[age];
            age += 1;
            weight += w;
            let start = slot * g.t_p * d + r * d;
            for (s, &v) in self.sum.iter_mut().zip(&self.ring[start..start + d]) {
                *s += w * f64::from(v);
            }
        }
        if age == 0 {
            return None;
        }
        Some(
            self.sum
                .iter()
                .zip(new_row)
                .map(|(s, &a)| (s / weight - f64::from(a)).powi(2))
                .sum(),
        )
    }

    /// Stores `chunk` as the newest.
    fn push(&mut self, t: u64, chunk: &[f32]) {
        let slot = if self.held == 0 {
            0
        } else {
            (self.newest + 1) % self.slots()
        };
        let n = self.geometry.t_p * self.d;
        self.ring[slot * n..(slot + 1) * n].copy_from_slice(chunk);
        self.times[slot] = t;
        self.newest = slot;
        self.held = (self.held + 1).min(self.slots() - 1);
    }
}

impl Monitor for Tide {
    fn observe(&mut self, t: u64, chunk: &[f32]) -> Result<Option<f64>, EnsembleError> {
        check_chunk(chunk, &self.geometry, self.d)?;
        if self.held == 0 {
            self.push(t, chunk);
            return Ok(None);
        }
        let prev = self.times[self.newest];
        if t <= prev {
            return Err(EnsembleError::NonMonotonicQuery {
                t_query: t,
                last: prev,
            });
        }
        let (g, d) = (self.geometry, self.d);
        let (mut total, mut count) = (0.0f64, 0usize);
        for tau in overlap(&g, prev, t) {
            let Some(r) = row_for(&g, t, tau) else {
                continue;
            };
            let new_row = &chunk[r * d..(r + 1) * d];
            if let Some(se) = self.squared_error(tau, new_row) {
                total += se;
                count += 1;
            }
        }
        self.push(t, chunk);
        Ok((count > 0).then(|| total / (count * d) as f64))
    }

    fn reset(&mut self) {
        self.held = 0;
    }
}
