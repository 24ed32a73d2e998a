//! How the candidates an aggregator combines are spread: an [`EpisodeObserver`] that
//! measures, per control step, what separates the mean from the median and from the newest
//! prediction. It is the instrument of the clean-data confound (why the mean of overlapping
//! chunks can lose on clean episodes): staleness (older candidates were planned from older
//! states) against multimodality (candidates from different modes of the policy).
//!
//! Units: distances are Euclidean over all action coordinates (PushT: pixels of the
//! 512 x 512 workspace). Candidates are oldest first (`mte_ensemble::Candidates`), so the
//! newest is the last and a candidate's *age* is its distance in queries from the newest.
//! Steps with fewer than two candidates are not counted.

use serde::Serialize;

use crate::episode::{EpisodeObserver, StepEvent};

/// The smallest separation (px) of two clusters that counts as a split, a twelfth of the
/// T block's 120 px bar: smaller gaps are sampling jitter, not a different plan.
pub const SPLIT_MIN_PX: f64 = 10.0;

/// Accumulates candidate-set statistics over the steps it observes (one or many episodes).
#[derive(Debug, Clone, Default)]
pub struct CandidateSpread {
    steps: u64,
    spread: f64,
    mean_to_median: f64,
    mean_to_nearest: f64,
    median_to_nearest: f64,
    newest_to_mean: f64,
    newest_to_median: f64,
    split_steps: u64,
    /// Per age `k >= 1`: the summed distance from the newest candidate, and the count.
    age: Vec<(f64, u64)>,
    /// Steps with a corrupted candidate and at least two clean ones.
    corrupted_steps: u64,
    /// Summed over those steps: the clean candidates' RMS distance from their median.
    clean_spread: f64,
    /// Per corrupted candidate at those steps: its distance from the clean candidates'
    /// coordinate-wise median, and whether it lies outside their bracket.
    corrupted: Vec<(f64, bool)>,
    /// Per corrupted candidate where the clean spread is not zero: distance over spread.
    outlyingness: Vec<f64>,
    scratch: Vec<f64>,
    mean: Vec<f64>,
    median: Vec<f64>,
}

/// Means over the observed steps (all distances in action units).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SpreadSummary {
    /// Steps with at least two candidates.
    pub steps: u64,
    /// Root-mean-square distance of the candidates from their coordinate-wise median.
    pub spread: f64,
    /// Distance between the uniform mean and the coordinate-wise median.
    pub mean_to_median: f64,
    /// Distance from the uniform mean to the nearest candidate (large when the mean falls
    /// between clusters).
    pub mean_to_nearest: f64,
    /// Distance from the coordinate-wise median to the nearest candidate.
    pub median_to_nearest: f64,
    /// Distance from the newest candidate to the uniform mean.
    pub newest_to_mean: f64,
    /// Distance from the newest candidate to the coordinate-wise median.
    pub newest_to_median: f64,
    /// Fraction of steps (with at least three candidates) whose candidates split into two
    /// groups: along the line through the two farthest candidates, a gap wider than half
    /// their distance and than [`SPLIT_MIN_PX`].
    pub split_fraction: f64,
    /// Mean distance of a candidate of age `k` (queries older than the newest) from the
    /// newest, for `k = 1, 2, ...` (entry `k - 1`).
    pub by_age: Vec<f64>,
    /// Steps with at least one candidate from a corrupted query and at least two clean
    /// ones: the steps where the corrupted candidates are measured against the clean.
    pub corrupted_steps: u64,
    /// At those steps, the clean candidates' RMS distance from their coordinate-wise median.
    pub clean_spread: f64,
    /// Mean distance of a corrupted candidate from the clean candidates' coordinate-wise
    /// median.
    pub corrupted_to_clean_median: f64,
    /// Median over corrupted candidates of that distance over the step's clean spread (steps
    /// whose clean spread is zero left out): how many clean spreads a corrupted candidate
    /// lies from the clean ones. Near 1 it hides among them; far above, a rank statistic can
    /// reject it and a mean is dragged by it.
    pub corrupted_outlyingness: f64,
    /// Fraction of corrupted candidates outside the clean candidates' coordinate-wise
    /// bracket on at least one coordinate.
    pub corrupted_outside_bracket: f64,
}

impl EpisodeObserver for CandidateSpread {
    fn on_step(&mut self, e: &StepEvent<'_>) {
        self.corrupted_against_clean(e);
        let m = e.candidates.len();
        if m < 2 {
            return;
        }
        let rows: Vec<&[f32]> = (0..m).map(|i| e.candidates.row(i)).collect();
        self.centres(&rows);
        let newest = rows[m - 1];
        let near = |p: &[f64]| {
            rows.iter()
                .map(|r| dist(r, p))
                .fold(f64::INFINITY, f64::min)
        };
        self.steps += 1;
        self.spread += rms_about(&rows, &self.median);
        self.mean_to_median += dist(&self.mean, &self.median);
        self.mean_to_nearest += near(&self.mean);
        self.median_to_nearest += near(&self.median);
        self.newest_to_mean += dist(newest, &self.mean);
        self.newest_to_median += dist(newest, &self.median);
        self.split_steps += u64::from(m >= 3 && splits(&rows, &mut self.scratch));
        for (k, r) in rows.iter().rev().enumerate().skip(1) {
            if self.age.len() < k {
                self.age.resize(k, (0.0, 0));
            }
            self.age[k - 1].0 += dist(r, newest);
            self.age[k - 1].1 += 1;
        }
    }
}

impl CandidateSpread {
    /// The coordinate-wise mean and median of `rows` into `self.mean`, `self.median`.
    fn centres(&mut self, rows: &[&[f32]]) {
        let d = rows[0].len();
        self.mean.clear();
        self.median.clear();
        for j in 0..d {
            self.scratch.clear();
            self.scratch.extend(rows.iter().map(|r| f64::from(r[j])));
            self.mean
                .push(self.scratch.iter().sum::<f64>() / rows.len() as f64);
            self.scratch.sort_by(f64::total_cmp);
            let n = self.scratch.len();
            self.median
                .push(0.5 * (self.scratch[(n - 1) / 2] + self.scratch[n / 2]));
        }
    }

    /// Measures each corrupted candidate of `e` against its clean ones (at least two).
    fn corrupted_against_clean(&mut self, e: &StepEvent<'_>) {
        let m = e.candidates.len();
        let flagged = |i: usize| e.corrupted.get(i).copied().unwrap_or(false);
        let clean: Vec<&[f32]> = (0..m)
            .filter(|&i| !flagged(i))
            .map(|i| e.candidates.row(i))
            .collect();
        if clean.len() < 2 || clean.len() == m {
            return;
        }
        self.centres(&clean);
        let spread = rms_about(&clean, &self.median);
        self.corrupted_steps += 1;
        self.clean_spread += spread;
        // The clean bracket, once per step: (lowest, highest) clean value per coordinate.
        let bracket: Vec<(f32, f32)> = (0..clean[0].len())
            .map(|j| {
                clean
                    .iter()
                    .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), r| {
                        (lo.min(r[j]), hi.max(r[j]))
                    })
            })
            .collect();
        for row in (0..m).filter(|&i| flagged(i)).map(|i| e.candidates.row(i)) {
            let d = dist(row, &self.median);
            let outside = row
                .iter()
                .zip(&bracket)
                .any(|(&v, &(lo, hi))| v < lo || v > hi);
            self.corrupted.push((d, outside));
            if spread > 0.0 {
                self.outlyingness.push(d / spread);
            }
        }
    }

    /// Adds what `other` observed to `self`, as if `self` had observed it too (a run's
    /// total from per-episode observers).
    pub fn merge(&mut self, other: &CandidateSpread) {
        self.steps += other.steps;
        self.spread += other.spread;
        self.mean_to_median += other.mean_to_median;
        self.mean_to_nearest += other.mean_to_nearest;
        self.median_to_nearest += other.median_to_nearest;
        self.newest_to_mean += other.newest_to_mean;
        self.newest_to_median += other.newest_to_median;
        self.split_steps += other.split_steps;
        if self.age.len() < other.age.len() {
            self.age.resize(other.age.len(), (0.0, 0));
        }
        for (a, b) in self.age.iter_mut().zip(&other.age) {
            a.0 += b.0;
            a.1 += b.1;
        }
        self.corrupted_steps += other.corrupted_steps;
        self.clean_spread += other.clean_spread;
        self.corrupted.extend_from_slice(&other.corrupted);
        self.outlyingness.extend_from_slice(&other.outlyingness);
    }

    /// The means so far.
    pub fn summary(&self) -> SpreadSummary {
        let n = self.steps.max(1) as f64;
        let k = self.corrupted.len().max(1) as f64;
        SpreadSummary {
            steps: self.steps,
            spread: self.spread / n,
            mean_to_median: self.mean_to_median / n,
            mean_to_nearest: self.mean_to_nearest / n,
            median_to_nearest: self.median_to_nearest / n,
            newest_to_mean: self.newest_to_mean / n,
            newest_to_median: self.newest_to_median / n,
            split_fraction: self.split_steps as f64 / n,
            by_age: self.age.iter().map(|&(s, c)| s / c.max(1) as f64).collect(),
            corrupted_steps: self.corrupted_steps,
            clean_spread: self.clean_spread / self.corrupted_steps.max(1) as f64,
            corrupted_to_clean_median: self.corrupted.iter().map(|c| c.0).sum::<f64>() / k,
            corrupted_outlyingness: median_of(&self.outlyingness),
            corrupted_outside_bracket: self.corrupted.iter().filter(|c| c.1).count() as f64 / k,
        }
    }
}

/// The median of `v` (the mean of the two middle values for an even count); 0 when empty.
fn median_of(v: &[f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    0.5 * (s[(s.len() - 1) / 2] + s[s.len() / 2])
}

/// Root-mean-square distance of `rows` from `centre`.
fn rms_about(rows: &[&[f32]], centre: &[f64]) -> f64 {
    (rows.iter().map(|r| dist(r, centre).powi(2)).sum::<f64>() / rows.len() as f64).sqrt()
}

/// Euclidean distance between two points (rows of `f32` or `f64`).
fn dist<A: Copy + Into<f64>, B: Copy + Into<f64>>(a: &[A], b: &[B]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| (x.into() - y.into()).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Whether the candidates split into two groups along the line through the two farthest
/// apart: a gap between consecutive projections wider than half their distance and than
/// [`SPLIT_MIN_PX`].
fn splits(rows: &[&[f32]], proj: &mut Vec<f64>) -> bool {
    let (mut a, mut b, mut far) = (0, 0, 0.0);
    for i in 0..rows.len() {
        for j in i + 1..rows.len() {
            let d = dist(rows[i], rows[j]);
            if d > far {
                (a, b, far) = (i, j, d);
            }
        }
    }
    if far < SPLIT_MIN_PX {
        return false;
    }
    let axis: Vec<f64> = rows[a]
        .iter()
        .zip(rows[b])
        .map(|(&x, &y)| (f64::from(y) - f64::from(x)) / far)
        .collect();
    proj.clear();
    proj.extend(rows.iter().map(|r| {
        r.iter()
            .zip(rows[a])
            .zip(&axis)
            .map(|((&x, &o), u)| (f64::from(x) - f64::from(o)) * u)
            .sum::<f64>()
    }));
    proj.sort_by(f64::total_cmp);
    let gap = proj.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
    gap > 0.5 * far && gap > SPLIT_MIN_PX
}

#[cfg(test)]
mod tests {
    use mte_ensemble::Candidates;

    use super::*;

    fn observe(spread: &mut CandidateSpread, flat: &[f32]) {
        observe_flagged(spread, flat, 2, &vec![false; flat.len() / 2]);
    }

    fn observe_flagged(spread: &mut CandidateSpread, flat: &[f32], d: usize, flags: &[bool]) {
        let c = Candidates::new(flat, d).expect("candidates");
        spread.on_step(&StepEvent {
            tau: 0,
            candidates: c,
            corrupted: flags,
            action: &flat[..d],
            m: c.len(),
            q: flags.iter().filter(|&&f| f).count(),
            report: None,
            bracket: None,
        });
    }

    #[test]
    fn two_clusters_split_and_the_mean_falls_between_them() {
        let mut s = CandidateSpread::default();
        // Three candidates at x = 0 and two at x = 100 (oldest first), y = 0.
        observe(&mut s, &[0., 0., 0., 0., 0., 0., 100., 0., 100., 0.]);
        let r = s.summary();
        assert_eq!(r.steps, 1);
        assert!((r.mean_to_median - 40.0).abs() < 1e-9, "{r:?}");
        assert!((r.mean_to_nearest - 40.0).abs() < 1e-9);
        assert_eq!(r.median_to_nearest, 0.0);
        assert!((r.newest_to_mean - 60.0).abs() < 1e-9);
        assert_eq!(r.split_fraction, 1.0);
        assert_eq!(r.by_age, vec![0.0, 100.0, 100.0, 100.0]);
        // RMS distance from the median (0, 0): sqrt((3 * 0 + 2 * 100^2) / 5).
        assert!((r.spread - (2.0e4f64 / 5.0).sqrt()).abs() < 1e-9);
    }

    #[test]
    fn an_even_spread_does_not_split_and_one_candidate_is_not_counted() {
        let mut s = CandidateSpread::default();
        observe(&mut s, &[0., 0., 25., 0., 50., 0., 75., 0., 100., 0.]);
        observe(&mut s, &[3., 4.]);
        let r = s.summary();
        assert_eq!(r.steps, 1);
        assert_eq!(r.split_fraction, 0.0);
        assert_eq!(r.mean_to_median, 0.0);
        assert_eq!(r.by_age, vec![25.0, 50.0, 75.0, 100.0]);
    }

    #[test]
    fn corrupted_candidates_are_measured_against_the_clean_ones_only() {
        let mut s = CandidateSpread::default();
        // 1-D. Clean 0, 2, 4 (median 2, RMS spread sqrt(8 / 3)); corrupted 10: 8 away,
        // outside the bracket [0, 4].
        observe_flagged(&mut s, &[0., 10., 2., 4.], 1, &[false, true, false, false]);
        // Clean 0, 2, 4 again; corrupted 3: 1 away, inside.
        observe_flagged(&mut s, &[3., 0., 2., 4.], 1, &[true, false, false, false]);
        // One clean candidate: nothing to measure against, not counted.
        observe_flagged(&mut s, &[7., 1.], 1, &[true, false]);
        // No corrupted candidate: not counted.
        observe_flagged(&mut s, &[0., 2., 4.], 1, &[false; 3]);
        let r = s.summary();
        let sd = (8.0f64 / 3.0).sqrt();
        assert_eq!(r.corrupted_steps, 2);
        assert!((r.clean_spread - sd).abs() < 1e-12, "{r:?}");
        assert!((r.corrupted_to_clean_median - 4.5).abs() < 1e-12);
        assert!((r.corrupted_outlyingness - 0.5 * (8.0 / sd + 1.0 / sd)).abs() < 1e-12);
        assert_eq!(r.corrupted_outside_bracket, 0.5);
        // The candidate statistics of the same steps still take every candidate.
        assert_eq!(r.steps, 4);
    }

    #[test]
    fn merging_per_episode_observers_equals_one_observer_of_all() {
        let steps: [(&[f32], &[bool]); 3] = [
            (&[0., 10., 2., 4.], &[false, true, false, false]),
            (&[3., 0., 2., 4., 9.], &[true, false, false, false, true]),
            (&[0., 1., 5.], &[false, false, false]),
        ];
        let mut all = CandidateSpread::default();
        let mut merged = CandidateSpread::default();
        for (flat, flags) in steps {
            observe_flagged(&mut all, flat, 1, flags);
            let mut one = CandidateSpread::default();
            observe_flagged(&mut one, flat, 1, flags);
            merged.merge(&one);
        }
        assert_eq!(merged.summary(), all.summary());
        assert_eq!(all.summary().corrupted_steps, 2);
    }
}
