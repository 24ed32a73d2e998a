//! Bracket diagnostics (protocol section 3): does the output stay inside the range of the
//! clean candidates, and by how much does it leave it?
//!
//! Conventions, fixed here once:
//! - The **bracket** of coordinate `j` is `[lo_j, hi_j]`, the min and max over the clean
//!   (not corrupted) candidates. Without a clean candidate there is no bracket.
//! - **Excess** of coordinate `j` is `max(lo_j - x_j, x_j - hi_j, 0) / (hi_j - lo_j)`, in
//!   units of the bracket width; a step's excess is the largest over coordinates.
//! - **Zero-width rule**: a coordinate whose clean candidates agree exactly (`hi_j = lo_j`)
//!   has no width to divide by. Its excursion `|x_j - lo_j|` is reported separately, in
//!   absolute action units, as [`BracketReport::zero_width_excess`], and counts as outside
//!   when positive; it never enters the relative excess.
//! - The output **coincides** with a candidate when every coordinate matches that
//!   candidate's within `1e-6 * max(1, |c_j|)` (an f32 rounding margin).
//! - **Nearest ratio**: distance from the output to its nearest candidate divided by the
//!   mean pairwise distance between candidates (Euclidean); undefined for fewer than two
//!   candidates or when all candidates coincide.

use serde::{Deserialize, Serialize};

use crate::aggregate::Candidates;
use crate::ensembler::{Regime, StepReport};

/// Bracket diagnostics of one output.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BracketReport {
    /// Clean candidates (the bracket is their range).
    pub clean: usize,
    /// Corrupted candidates.
    pub corrupted: usize,
    /// Whether any coordinate lies outside the bracket.
    pub outside: bool,
    /// Largest excursion beyond the bracket over coordinates of positive width, in widths.
    pub excess: f64,
    /// Largest excursion over zero-width coordinates, in absolute action units.
    pub zero_width_excess: f64,
    /// Whether the output equals one of the candidates.
    pub coincides: bool,
    /// Nearest-candidate distance over mean pairwise distance, when defined.
    pub nearest_ratio: Option<f64>,
}

/// Diagnoses `out` against candidates `c` whose corruption flags are `corrupted` (one per
/// candidate). Returns `None` when no candidate is clean. Allocation-free, `O(M^2 d)`.
pub fn diagnose(c: &Candidates<'_>, corrupted: &[bool], out: &[f32]) -> Option<BracketReport> {
    let n = c.len();
    debug_assert_eq!(corrupted.len(), n);
    let clean = corrupted.iter().filter(|&&x| !x).count();
    if clean == 0 {
        return None;
    }
    let (mut excess, mut zero_width_excess) = (0.0f64, 0.0f64);
    for (j, &x) in out.iter().enumerate() {
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for i in (0..n).filter(|&i| !corrupted[i]) {
            let v = c.row(i)[j];
            lo = lo.min(v);
            hi = hi.max(v);
        }
        let (x, lo, hi) = (x as f64, lo as f64, hi as f64);
        let dev = (lo - x).max(x - hi).max(0.0);
        if hi > lo {
            excess = excess.max(dev / (hi - lo));
        } else {
            zero_width_excess = zero_width_excess.max(dev);
        }
    }
    let coincides = (0..n).any(|i| {
        c.row(i)
            .iter()
            .zip(out)
            .all(|(&v, &x)| (v - x).abs() <= 1e-6 * v.abs().max(1.0))
    });
    let dist = |a: &[f32], b: &[f32]| -> f64 {
        a.iter()
            .zip(b)
            .map(|(&u, &v)| (u as f64 - v as f64).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let nearest = (0..n)
        .map(|i| dist(c.row(i), out))
        .fold(f64::INFINITY, f64::min);
    let (mut sum, mut pairs) = (0.0, 0usize);
    for i in 0..n {
        for j in (i + 1)..n {
            sum += dist(c.row(i), c.row(j));
            pairs += 1;
        }
    }
    let nearest_ratio = (pairs > 0 && sum > 0.0).then(|| nearest / (sum / pairs as f64));
    Some(BracketReport {
        clean,
        corrupted: n - clean,
        outside: excess > 0.0 || zero_width_excess > 0.0,
        excess,
        zero_width_excess,
        coincides,
        nearest_ratio,
    })
}

/// Per-regime tallies of [`BracketReport`]s.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RegimeTally {
    /// Timesteps recorded.
    pub steps: u64,
    /// Timesteps whose output left the bracket.
    pub outside: u64,
    /// Timesteps with a zero-width excursion.
    pub zero_width_outside: u64,
    /// Timesteps whose output coincided with a candidate.
    pub coincide: u64,
    /// Excess of every timestep (for medians and maxima).
    pub excess: Vec<f64>,
    /// Nearest ratios of the timesteps where it is defined.
    pub nearest: Vec<f64>,
}

/// Accumulates the paper's Table "mech": among timesteps with at least one corrupted
/// candidate, grouped by regime, how often the output leaves the clean bracket and by how
/// much.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BracketAccumulator {
    /// Tallies indexed by [`Regime::index`].
    pub tallies: [RegimeTally; 3],
}

/// One row of the bracket table.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BracketRow {
    /// The regime.
    pub regime: Regime,
    /// Timesteps with at least one corrupted candidate in this regime.
    pub steps: u64,
    /// Percentage of them whose output left the bracket.
    pub outside_pct: f64,
    /// Median excess over those timesteps (widths).
    pub median_excess: f64,
    /// Largest excess (widths).
    pub max_excess: f64,
    /// Timesteps with an excursion on a zero-width coordinate.
    pub zero_width_outside: u64,
    /// Percentage of timesteps whose output coincided with a candidate.
    pub coincide_pct: f64,
    /// Median nearest-candidate ratio.
    pub nearest_median: Option<f64>,
    /// 99th percentile of the nearest-candidate ratio (nearest rank).
    pub nearest_p99: Option<f64>,
}

/// Nearest-rank quantile `q` in `[0, 1]` of an ascending sample: the value at rank
/// `ceil(q n)` (at least 1). `None` when the sample is empty.
pub fn nearest_rank(sorted: &[f64], q: f64) -> Option<f64> {
    debug_assert!(sorted.windows(2).all(|w| w[0] <= w[1]));
    let n = sorted.len();
    let rank = ((q * n as f64).ceil() as usize).clamp(1, n.max(1));
    sorted.get(rank - 1).copied()
}

/// Median of an ascending sample, averaging the two central values for an even count.
fn sorted_median(sorted: &[f64]) -> Option<f64> {
    let n = sorted.len();
    (n > 0).then(|| 0.5 * (sorted[(n - 1) / 2] + sorted[n / 2]))
}

fn sorted_copy(values: &[f64]) -> Vec<f64> {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v
}

impl BracketAccumulator {
    /// Records one step; steps without a corrupted candidate are ignored (they cannot leave
    /// a bracket that includes every candidate).
    pub fn record(&mut self, report: &StepReport, b: &BracketReport) {
        if b.corrupted == 0 {
            return;
        }
        let t = &mut self.tallies[report.regime.index()];
        t.steps += 1;
        t.outside += u64::from(b.outside);
        t.zero_width_outside += u64::from(b.zero_width_excess > 0.0);
        t.coincide += u64::from(b.coincides);
        t.excess.push(b.excess);
        if let Some(r) = b.nearest_ratio {
            t.nearest.push(r);
        }
    }

    /// Adds another accumulator's tallies to this one.
    pub fn merge(&mut self, other: &BracketAccumulator) {
        for (a, b) in self.tallies.iter_mut().zip(&other.tallies) {
            a.steps += b.steps;
            a.outside += b.outside;
            a.zero_width_outside += b.zero_width_outside;
            a.coincide += b.coincide;
            a.excess.extend_from_slice(&b.excess);
            a.nearest.extend_from_slice(&b.nearest);
        }
    }

    /// The table, one row per regime that has steps, in the order `2q<M`, `2q=M`, `2q>M`.
    pub fn rows(&self) -> Vec<BracketRow> {
        Regime::ALL
            .iter()
            .zip(&self.tallies)
            .filter(|(_, t)| t.steps > 0)
            .map(|(&regime, t)| {
                let pct = |k: u64| 100.0 * k as f64 / t.steps as f64;
                let (excess, nearest) = (sorted_copy(&t.excess), sorted_copy(&t.nearest));
                BracketRow {
                    regime,
                    steps: t.steps,
                    outside_pct: pct(t.outside),
                    median_excess: sorted_median(&excess).unwrap_or(0.0),
                    max_excess: excess.last().copied().unwrap_or(0.0),
                    zero_width_outside: t.zero_width_outside,
                    coincide_pct: pct(t.coincide),
                    nearest_median: sorted_median(&nearest),
                    nearest_p99: nearest_rank(&nearest, 0.99),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cands(v: &[f32], d: usize) -> Candidates<'_> {
        Candidates::new(v, d).unwrap()
    }

    #[test]
    fn inside_output_has_zero_excess() {
        let v = [0.0, 0.0, 2.0, 4.0, 100.0, -100.0];
        let b = diagnose(&cands(&v, 2), &[false, false, true], &[1.0, 2.0]).unwrap();
        assert!(!b.outside);
        assert_eq!((b.clean, b.corrupted), (2, 1));
        assert_eq!(b.excess, 0.0);
        assert!(!b.coincides);
    }

    #[test]
    fn excess_is_in_bracket_widths_and_takes_the_worst_coordinate() {
        // Clean range x in [0, 2] (width 2), y in [0, 4] (width 4).
        let v = [0.0, 0.0, 2.0, 4.0, 9.0, 9.0];
        let b = diagnose(&cands(&v, 2), &[false, false, true], &[3.0, 6.0]).unwrap();
        assert!(b.outside);
        assert!((b.excess - 0.5).abs() < 1e-12, "{}", b.excess); // x: 1/2, y: 2/4
        let b = diagnose(&cands(&v, 2), &[false, false, true], &[-4.0, 2.0]).unwrap();
        assert!((b.excess - 2.0).abs() < 1e-12);
    }

    #[test]
    fn zero_width_coordinate_is_measured_in_absolute_units() {
        let v = [1.0, 0.0, 1.0, 4.0, 50.0, 50.0];
        let b = diagnose(&cands(&v, 2), &[false, false, true], &[1.5, 2.0]).unwrap();
        assert!(b.outside);
        assert_eq!(b.excess, 0.0);
        assert!((b.zero_width_excess - 0.5).abs() < 1e-12);
    }

    #[test]
    fn no_clean_candidate_means_no_bracket() {
        let v = [1.0, 2.0];
        assert!(diagnose(&cands(&v, 1), &[true, true], &[1.0]).is_none());
    }

    #[test]
    fn coincidence_and_nearest_ratio() {
        let v = [0.0, 0.0, 3.0, 4.0];
        let b = diagnose(&cands(&v, 2), &[false, false], &[3.0, 4.0]).unwrap();
        assert!(b.coincides);
        assert_eq!(b.nearest_ratio, Some(0.0));
        let b = diagnose(&cands(&v, 2), &[false, false], &[1.5, 2.0]).unwrap();
        assert!(!b.coincides);
        assert!((b.nearest_ratio.unwrap() - 0.5).abs() < 1e-12); // 2.5 / 5
        let same = [1.0, 1.0, 1.0, 1.0];
        let b = diagnose(&cands(&same, 2), &[false, false], &[1.0, 1.0]).unwrap();
        assert_eq!(b.nearest_ratio, None);
    }

    #[test]
    fn accumulator_groups_by_regime_and_ignores_clean_steps() {
        use crate::ensembler::StepReport;
        let mut acc = BracketAccumulator::default();
        let report = |m, q| StepReport::for_test(m, q);
        let inside = BracketReport {
            clean: 5,
            corrupted: 2,
            outside: false,
            excess: 0.0,
            zero_width_excess: 0.0,
            coincides: false,
            nearest_ratio: Some(0.1),
        };
        let out = BracketReport {
            outside: true,
            excess: 2.0,
            ..inside
        };
        acc.record(&report(7, 2), &inside);
        acc.record(&report(7, 2), &inside);
        acc.record(&report(8, 4), &out);
        acc.record(
            &report(8, 0),
            &BracketReport {
                corrupted: 0,
                ..out
            },
        );
        let rows = acc.rows();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].regime, Regime::Guaranteed);
        assert_eq!((rows[0].steps, rows[0].outside_pct), (2, 0.0));
        assert_eq!(rows[1].regime, Regime::Tie);
        assert_eq!(
            (rows[1].steps, rows[1].outside_pct, rows[1].median_excess),
            (1, 100.0, 2.0)
        );
        assert_eq!(nearest_rank(&[1.0, 2.0, 3.0, 4.0], 0.5), Some(2.0));
        assert_eq!(nearest_rank(&[1.0, 2.0, 3.0, 4.0], 0.99), Some(4.0));
        assert_eq!(nearest_rank(&[1.0, 2.0], 0.0), Some(1.0));
        assert_eq!(nearest_rank(&[], 0.5), None);
        let mut twice = acc.clone();
        twice.merge(&acc);
        assert_eq!(twice.rows()[0].steps, 4);
    }
}
