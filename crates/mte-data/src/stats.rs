//! Normalisation statistics (LeRobot's `meta/stats.json` semantics): per feature and per
//! coordinate min, max, mean and (population) standard deviation over all frames. Images are
//! reduced per channel, on values scaled to [0, 1], as LeRobot does.

/// Statistics of one feature; vectors have one entry per coordinate (per channel for images).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FeatureStats {
    /// Coordinate-wise minimum.
    pub min: Vec<f64>,
    /// Coordinate-wise maximum.
    pub max: Vec<f64>,
    /// Coordinate-wise mean.
    pub mean: Vec<f64>,
    /// Coordinate-wise population standard deviation.
    pub std: Vec<f64>,
    /// Number of values reduced per coordinate.
    pub count: u64,
}

impl FeatureStats {
    /// The statistics of the union of two disjoint sets of frames, from each set's own:
    /// extremes of the extremes, the count-weighted mean, and the population variance
    /// pooled through each set's second moment (`std^2 + mean^2`). `None` when the
    /// coordinate counts differ.
    pub fn pooled(&self, other: &FeatureStats) -> Option<FeatureStats> {
        let dim = self.mean.len();
        let same = |v: &[f64]| v.len() == dim;
        if !(same(&self.min) && same(&self.max) && same(&self.std))
            || !(same(&other.min) && same(&other.max) && same(&other.mean) && same(&other.std))
        {
            return None;
        }
        let n = self.count + other.count;
        let (wa, wb) = match n {
            0 => (0.5, 0.5),
            _ => (self.count as f64 / n as f64, other.count as f64 / n as f64),
        };
        let mut mean = Vec::with_capacity(dim);
        let mut std = Vec::with_capacity(dim);
        for k in 0..dim {
            let (ma, mb) = (self.mean[k], other.mean[k]);
            let m = wa * ma + wb * mb;
            let second =
                wa * (self.std[k].powi(2) + ma * ma) + wb * (other.std[k].powi(2) + mb * mb);
            mean.push(m);
            std.push((second - m * m).max(0.0).sqrt());
        }
        let zip = |a: &[f64], b: &[f64], f: fn(f64, f64) -> f64| {
            a.iter().zip(b).map(|(&x, &y)| f(x, y)).collect()
        };
        Some(FeatureStats {
            min: zip(&self.min, &other.min, f64::min),
            max: zip(&self.max, &other.max, f64::max),
            mean,
            std,
            count: n,
        })
    }
}

/// Streaming accumulator (sums in f64; values are bounded, so no cancellation trouble at the
/// sizes we handle: pixels <= 1, positions <= ~600 px).
#[derive(Clone, Debug)]
pub struct StatsAccumulator {
    dim: usize,
    min: Vec<f64>,
    max: Vec<f64>,
    sum: Vec<f64>,
    sum_sq: Vec<f64>,
    count: u64,
}

impl StatsAccumulator {
    /// For `dim` coordinates.
    pub fn new(dim: usize) -> Self {
        StatsAccumulator {
            dim,
            min: vec![f64::INFINITY; dim],
            max: vec![f64::NEG_INFINITY; dim],
            sum: vec![0.0; dim],
            sum_sq: vec![0.0; dim],
            count: 0,
        }
    }

    /// Add one row of `dim` values.
    pub fn push(&mut self, row: &[f64]) {
        for (k, &v) in row.iter().enumerate().take(self.dim) {
            self.min[k] = self.min[k].min(v);
            self.max[k] = self.max[k].max(v);
            self.sum[k] += v;
            self.sum_sq[k] += v * v;
        }
        self.count += 1;
    }

    /// Add an HWC u8 image: every pixel is a row of `dim` channels, scaled to [0, 1].
    pub fn push_image(&mut self, pixels: &[u8]) {
        let mut local_sum = vec![0u64; self.dim];
        let mut local_sq = vec![0u64; self.dim];
        let mut n = 0u64;
        for px in pixels.chunks_exact(self.dim) {
            for (k, &v) in px.iter().enumerate() {
                let f = f64::from(v) / 255.0;
                self.min[k] = self.min[k].min(f);
                self.max[k] = self.max[k].max(f);
                local_sum[k] += u64::from(v);
                local_sq[k] += u64::from(v) * u64::from(v);
            }
            n += 1;
        }
        for k in 0..self.dim {
            self.sum[k] += local_sum[k] as f64 / 255.0;
            self.sum_sq[k] += local_sq[k] as f64 / (255.0 * 255.0);
        }
        self.count += n;
    }

    /// Merge another accumulator of the same dimension.
    pub fn merge(&mut self, other: &StatsAccumulator) {
        for k in 0..self.dim.min(other.dim) {
            self.min[k] = self.min[k].min(other.min[k]);
            self.max[k] = self.max[k].max(other.max[k]);
            self.sum[k] += other.sum[k];
            self.sum_sq[k] += other.sum_sq[k];
        }
        self.count += other.count;
    }

    /// The statistics; `None` when nothing was added.
    pub fn finish(&self) -> Option<FeatureStats> {
        if self.count == 0 {
            return None;
        }
        let n = self.count as f64;
        let mean: Vec<f64> = self.sum.iter().map(|s| s / n).collect();
        let std = self
            .sum_sq
            .iter()
            .zip(&mean)
            .map(|(sq, m)| (sq / n - m * m).max(0.0).sqrt())
            .collect();
        Some(FeatureStats {
            min: self.min.clone(),
            max: self.max.clone(),
            mean,
            std,
            count: self.count,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_two_pass_computation() {
        let rows = [[1.0, -2.0], [3.0, 0.5], [2.0, 4.0], [10.0, -1.0]];
        let mut acc = StatsAccumulator::new(2);
        for r in &rows {
            acc.push(r);
        }
        let s = acc.finish().expect("non-empty");
        for k in 0..2 {
            let col: Vec<f64> = rows.iter().map(|r| r[k]).collect();
            let mean = col.iter().sum::<f64>() / 4.0;
            let var = col.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 4.0;
            assert!((s.mean[k] - mean).abs() < 1e-12);
            assert!((s.std[k] - var.sqrt()).abs() < 1e-12);
        }
        assert_eq!(s.min, vec![1.0, -2.0]);
        assert_eq!(s.max, vec![10.0, 4.0]);
    }

    #[test]
    fn image_channels_are_scaled_to_unit_range() {
        let mut acc = StatsAccumulator::new(3);
        acc.push_image(&[255, 0, 51, 255, 0, 153]);
        let s = acc.finish().expect("non-empty");
        assert_eq!(s.count, 2);
        assert_eq!(s.max[0], 1.0);
        assert_eq!(s.min[1], 0.0);
        assert!((s.mean[2] - 0.4).abs() < 1e-12);
        assert!((s.std[2] - 0.2).abs() < 1e-12);
    }

    #[test]
    fn pooled_stats_are_the_unions() {
        let rows = [
            [1.0, -2.0],
            [3.0, 0.5],
            [2.0, 4.0],
            [10.0, -1.0],
            [-4.0, 7.5],
        ];
        let stats_of = |rs: &[[f64; 2]]| {
            let mut acc = StatsAccumulator::new(2);
            rs.iter().for_each(|r| acc.push(r));
            acc.finish().expect("non-empty")
        };
        let whole = stats_of(&rows);
        let pooled = stats_of(&rows[..2])
            .pooled(&stats_of(&rows[2..]))
            .expect("same dimension");
        assert_eq!(pooled.count, 5);
        assert_eq!(pooled.min, whole.min);
        assert_eq!(pooled.max, whole.max);
        for k in 0..2 {
            assert!((pooled.mean[k] - whole.mean[k]).abs() < 1e-12, "{k}");
            assert!((pooled.std[k] - whole.std[k]).abs() < 1e-12, "{k}");
        }
        let one = stats_of(&[[1.0, 2.0]]);
        let three = FeatureStats {
            min: vec![0.0; 3],
            ..one.clone()
        };
        assert!(one.pooled(&three).is_none());
    }

    #[test]
    fn empty_has_no_stats() {
        assert!(StatsAccumulator::new(2).finish().is_none());
    }
}
