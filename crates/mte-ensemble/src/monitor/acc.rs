//! ACC: chunk-to-chunk mean absolute error over the overlap, per coordinate divided by the
//! new chunk's range there, smoothed.

use serde::{Deserialize, Serialize};

use super::{Monitor, MonitorError, check_chunk, overlap, row_for};
use crate::error::EnsembleError;
use crate::geometry::ChunkGeometry;

/// ACC's settings. Defaults: the spec's (section 5).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AccConfig {
    /// Floor of the per-coordinate range, in action units (the spec's 1e-3 in LeRobot's
    /// normalised units; PushT's actions span 512 px over [−1, 1], so 0.256 px there).
    pub v_min: f64,
    /// Weight of the previous smoothed score, `s_i = ema · s_{i−1} + (1 − ema) · raw_i`.
    pub ema: f64,
}

impl Default for AccConfig {
    fn default() -> Self {
        Self {
            v_min: 1e-3,
            ema: 0.9,
        }
    }
}

/// ACC over a stream of chunks; see the module docs of [`crate::monitor`].
#[derive(Clone, Debug)]
pub struct Acc {
    geometry: ChunkGeometry,
    d: usize,
    config: AccConfig,
    prev: Vec<f32>,
    prev_t: Option<u64>,
    smoothed: Option<f64>,
    lo: Vec<f32>,
    hi: Vec<f32>,
    /// Scored coordinates, and how many of them the floor bound.
    scored: u64,
    floored: u64,
}

impl Acc {
    /// A monitor for chunks of `geometry` with `d` coordinates.
    ///
    /// # Errors
    /// An invalid geometry, `d = 0`, `v_min` not finite and positive, `ema` outside [0, 1).
    pub fn new(geometry: ChunkGeometry, d: usize, config: AccConfig) -> Result<Self, MonitorError> {
        let geometry = ChunkGeometry::new(geometry.t_p, geometry.t_o, geometry.h)
            .map_err(EnsembleError::from)?;
        if d == 0 {
            return Err(EnsembleError::ZeroDimension.into());
        }
        if !(config.v_min.is_finite() && config.v_min > 0.0) {
            return Err(MonitorError::Config {
                field: "acc.v_min",
                value: config.v_min,
                expected: "a finite floor > 0 (action units)",
            });
        }
        if !(0.0..1.0).contains(&config.ema) {
            return Err(MonitorError::Config {
                field: "acc.ema",
                value: config.ema,
                expected: "a smoothing weight in [0, 1)",
            });
        }
        Ok(Self {
            geometry,
            d,
            config,
            prev: vec![0.0; geometry.t_p * d],
            prev_t: None,
            smoothed: None,
            lo: vec![0.0; d],
            hi: vec![0.0; d],
            scored: 0,
            floored: 0,
        })
    }

    /// The fraction of scored coordinates whose range the floor `v_min` replaced (the spec
    /// asks for it to be recorded).
    pub fn floor_fraction(&self) -> Option<f64> {
        (self.scored > 0).then(|| self.floored as f64 / self.scored as f64)
    }

    /// The raw (unsmoothed) score of `chunk` at `t` against the previous chunk at `prev`.
    fn raw(&mut self, prev: u64, t: u64, chunk: &[f32]) -> Option<f64> {
        let (g, d) = (self.geometry, self.d);
        let rows = || {
            overlap(&g, prev, t)
                .filter_map(move |tau| Some((row_for(&g, prev, tau)?, row_for(&g, t, tau)?)))
        };
        self.lo.iter_mut().for_each(|v| *v = f32::INFINITY);
        self.hi.iter_mut().for_each(|v| *v = f32::NEG_INFINITY);
        let mut n = 0usize;
        for (_, r) in rows() {
            for (k, &v) in chunk[r * d..(r + 1) * d].iter().enumerate() {
                self.lo[k] = self.lo[k].min(v);
                self.hi[k] = self.hi[k].max(v);
            }
            n += 1;
        }
        if n == 0 {
            return None;
        }
        let mut total = 0.0f64;
        for k in 0..d {
            let range = f64::from(self.hi[k]) - f64::from(self.lo[k]);
            self.scored += 1;
            let scale = if range < self.config.v_min {
                self.floored += 1;
                self.config.v_min
            } else {
                range
            };
            let mae: f64 = rows()
                .map(|(rp, r)| {
                    (f64::from(self.prev[rp * d + k]) - f64::from(chunk[r * d + k])).abs()
                })
                .sum();
            total += mae / scale;
        }
        Some(total / (n * d) as f64)
    }
}

impl Monitor for Acc {
    fn observe(&mut self, t: u64, chunk: &[f32]) -> Result<Option<f64>, EnsembleError> {
        check_chunk(chunk, &self.geometry, self.d)?;
        let score = match self.prev_t {
            Some(prev) if t <= prev => {
                return Err(EnsembleError::NonMonotonicQuery {
                    t_query: t,
                    last: prev,
                });
            }
            Some(prev) => self.raw(prev, t, chunk).map(|raw| {
                let s = match self.smoothed {
                    Some(s) => self.config.ema * s + (1.0 - self.config.ema) * raw,
                    None => raw,
                };
                self.smoothed = Some(s);
                s
            }),
            None => None,
        };
        self.prev.copy_from_slice(chunk);
        self.prev_t = Some(t);
        Ok(score)
    }

    fn reset(&mut self) {
        self.prev_t = None;
        self.smoothed = None;
    }
}
