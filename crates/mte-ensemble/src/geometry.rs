//! Chunk geometry: which query covers which control time (protocol section 1).
//!
//! Time is counted in **control steps** (integers). Query `i` fires at `t_i = i * h` and
//! returns a chunk of `t_p` rows; row `r` is the action for control time `t_i - (t_o - 1) + r`.
//! Rows `0..t_o - 1` belong to observation steps already in the past, so the *executable*
//! rows are `t_o - 1 ..= t_p - 1`, covering control times `t_i ..= t_i + t_p - t_o`.

use serde::{Deserialize, Serialize};

use crate::error::GeometryError;

/// The shape of a chunked policy's time axis: horizon, observation steps and stride.
///
/// | field | meaning | Diffusion Policy (PushT) | ACT |
/// |---|---|---|---|
/// | `t_p` | rows per chunk (prediction horizon) | 16 | 100 |
/// | `t_o` | observation steps per query | 2 | 1 |
/// | `h` | control steps between queries (stride, `T_a` in DP) | 8 | 1 (with ensembling) |
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChunkGeometry {
    /// Prediction horizon `T_p`: rows per chunk.
    pub t_p: usize,
    /// Observation steps `T_o` seen by a query; the executable part starts at row `t_o - 1`.
    pub t_o: usize,
    /// Stride `h`: control steps between consecutive queries.
    pub h: usize,
}

impl ChunkGeometry {
    /// Builds and validates a geometry.
    ///
    /// ```
    /// # use mte_ensemble::ChunkGeometry;
    /// let g = ChunkGeometry::new(16, 2, 2)?;
    /// assert_eq!((g.m_min(), g.m_max()), (7, 8));
    /// # Ok::<(), mte_ensemble::GeometryError>(())
    /// ```
    pub fn new(t_p: usize, t_o: usize, h: usize) -> Result<Self, GeometryError> {
        let g = Self { t_p, t_o, h };
        g.validate()?;
        Ok(g)
    }

    /// Checks `t_p >= 1`, `1 <= t_o <= t_p`, and `1 <= h <= t_p - t_o + 1` (no uncovered time).
    pub fn validate(&self) -> Result<(), GeometryError> {
        if self.t_p == 0 {
            return Err(GeometryError::ZeroHorizon);
        }
        if self.t_o == 0 {
            return Err(GeometryError::ZeroObservationSteps);
        }
        if self.t_o > self.t_p {
            return Err(GeometryError::ObservationStepsExceedHorizon {
                t_o: self.t_o,
                t_p: self.t_p,
            });
        }
        if self.h == 0 {
            return Err(GeometryError::ZeroStride);
        }
        let max = self.t_p - self.t_o + 1;
        if self.h > max {
            return Err(GeometryError::StrideLeavesGaps { h: self.h, max });
        }
        Ok(())
    }

    /// Control steps one chunk covers: `t_p - t_o + 1` (its executable rows).
    pub fn span(&self) -> usize {
        self.t_p - self.t_o + 1
    }

    /// First executable row of a chunk, `t_o - 1`.
    pub fn first_executable_row(&self) -> usize {
        self.t_o - 1
    }

    /// Fewest candidates at a control time in steady state:
    /// `M_min = 1 + floor((t_p - t_o - (h - 1)) / h)`.
    pub fn m_min(&self) -> usize {
        1 + (self.t_p - self.t_o + 1 - self.h) / self.h
    }

    /// Most candidates at a control time: `M_max = floor((t_p - t_o) / h) + 1`.
    pub fn m_max(&self) -> usize {
        (self.t_p - self.t_o) / self.h + 1
    }

    /// Control time at which query `i` fires on the regular grid, `i * h`.
    pub fn query_time(&self, i: u64) -> u64 {
        i * self.h as u64
    }

    /// Indices `i` of the queries on the regular grid (`t_i = i * h`, `i >= 0`) whose chunks
    /// cover control time `tau`: the covering set `C(tau)`.
    ///
    /// ```
    /// # use mte_ensemble::ChunkGeometry;
    /// let g = ChunkGeometry::new(16, 2, 2)?;
    /// let times: Vec<u64> = g.covering_queries(100).map(|i| g.query_time(i)).collect();
    /// assert_eq!(times, vec![86, 88, 90, 92, 94, 96, 98, 100]);
    /// # Ok::<(), mte_ensemble::GeometryError>(())
    /// ```
    pub fn covering_queries(&self, tau: u64) -> std::ops::RangeInclusive<u64> {
        let h = self.h as u64;
        let reach = (self.span() - 1) as u64;
        let first_time = tau.saturating_sub(reach);
        let first = first_time.div_ceil(h);
        let last = tau / h;
        first..=last
    }

    /// `M(tau) = |C(tau)|` on the regular grid, counting only queries at `t >= 0`.
    pub fn m_at(&self, tau: u64) -> usize {
        let r = self.covering_queries(tau);
        (r.end() + 1 - r.start()) as usize
    }

    /// Row of the chunk from the query at `t_query` that holds the action for `tau`:
    /// `tau - t_query + t_o - 1`, or `None` when that chunk does not cover `tau`.
    pub fn candidate_row(&self, t_query: u64, tau: u64) -> Option<usize> {
        let offset = tau.checked_sub(t_query)?;
        (offset < self.span() as u64).then(|| offset as usize + self.first_executable_row())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_worked_example_t16_o2_h2() {
        let g = ChunkGeometry::new(16, 2, 2).unwrap();
        assert_eq!((g.m_min(), g.m_max()), (7, 8));
        let at = |tau| {
            g.covering_queries(tau)
                .map(|i| g.query_time(i))
                .collect::<Vec<_>>()
        };
        assert_eq!(at(100), (86..=100).step_by(2).collect::<Vec<_>>());
        assert_eq!(at(101), (88..=100).step_by(2).collect::<Vec<_>>());
        assert_eq!(g.m_at(100), 8);
        assert_eq!(g.m_at(101), 7);
        // Candidate rows: the newest query (t=100) supplies row t_o - 1 = 1, the oldest
        // (t=86) row 15 = t_p - 1.
        assert_eq!(g.candidate_row(100, 100), Some(1));
        assert_eq!(g.candidate_row(86, 100), Some(15));
        assert_eq!(g.candidate_row(84, 100), None);
        assert_eq!(g.candidate_row(102, 100), None);
    }

    #[test]
    fn paper_t10_gives_four_or_five() {
        let g = ChunkGeometry::new(10, 2, 2).unwrap();
        assert_eq!((g.m_min(), g.m_max()), (4, 5));
        let ms: std::collections::BTreeSet<usize> = (20..60).map(|t| g.m_at(t)).collect();
        assert_eq!(ms.into_iter().collect::<Vec<_>>(), vec![4, 5]);
    }

    #[test]
    fn stride_sweep_gives_m_from_fifteen_to_three() {
        // T_p = 16, T_o = 2: h = 1 -> 15, h = 4 -> {3, 4}.
        let expect = [(1, 15, 15), (2, 7, 8), (3, 5, 5), (4, 3, 4)];
        for (h, lo, hi) in expect {
            let g = ChunkGeometry::new(16, 2, h).unwrap();
            assert_eq!((g.m_min(), g.m_max()), (lo, hi), "h = {h}");
            let ms: Vec<usize> = (100..100 + 4 * h as u64).map(|t| g.m_at(t)).collect();
            assert_eq!(*ms.iter().min().unwrap(), lo, "h = {h}");
            assert_eq!(*ms.iter().max().unwrap(), hi, "h = {h}");
        }
    }

    #[test]
    fn steady_state_m_matches_closed_form_for_every_geometry() {
        for t_p in 1..40 {
            for t_o in 1..=t_p {
                for h in 1..=(t_p - t_o + 1) {
                    let g = ChunkGeometry::new(t_p, t_o, h).unwrap();
                    let start = 4 * t_p as u64;
                    let ms: Vec<usize> = (start..start + h as u64).map(|t| g.m_at(t)).collect();
                    assert_eq!(*ms.iter().min().unwrap(), g.m_min(), "{g:?}");
                    assert_eq!(*ms.iter().max().unwrap(), g.m_max(), "{g:?}");
                }
            }
        }
    }

    #[test]
    fn episode_start_has_fewer_candidates() {
        let g = ChunkGeometry::new(16, 2, 2).unwrap();
        assert_eq!(g.m_at(0), 1);
        assert_eq!(g.m_at(1), 1);
        assert_eq!(g.m_at(2), 2);
    }

    #[test]
    fn invalid_geometries_are_typed_errors() {
        assert_eq!(
            ChunkGeometry::new(16, 0, 2),
            Err(GeometryError::ZeroObservationSteps)
        );
        assert_eq!(
            ChunkGeometry::new(4, 5, 1),
            Err(GeometryError::ObservationStepsExceedHorizon { t_o: 5, t_p: 4 })
        );
        assert_eq!(ChunkGeometry::new(16, 2, 0), Err(GeometryError::ZeroStride));
        assert_eq!(
            ChunkGeometry::new(16, 2, 16),
            Err(GeometryError::StrideLeavesGaps { h: 16, max: 15 })
        );
        assert_eq!(ChunkGeometry::new(0, 0, 1), Err(GeometryError::ZeroHorizon));
        assert!(ChunkGeometry::new(16, 2, 15).is_ok());
        let msg = GeometryError::StrideLeavesGaps { h: 16, max: 15 }.to_string();
        assert!(
            msg.contains("h = 16") && msg.contains("at most 15"),
            "{msg}"
        );
    }
}
