//! Rank statistics: coordinate-wise median, trimmed mean, recency-weighted median.

use super::{Candidates, MedianTie, Workspace, select};
use crate::network;

/// Midpoint of two finite f32 values without overflow.
#[inline]
fn midpoint(lo: f32, hi: f32) -> f32 {
    ((lo as f64 + hi as f64) * 0.5) as f32
}

/// Writes the central pair of order statistics of every coordinate of the candidates from
/// row `first` on to `emit(j, lower, upper)`, by selection (for sets beyond the networks).
fn central_pairs(
    c: &Candidates<'_>,
    first: usize,
    ws: &mut Workspace,
    mut emit: impl FnMut(usize, f32, f32),
) {
    let n = c.len() - first;
    let (lo, hi) = ((n - 1) / 2, n / 2);
    for j in 0..c.dim() {
        let col = &mut ws.col[..n];
        for (i, v) in col.iter_mut().enumerate() {
            *v = c.row(first + i)[j];
        }
        let (below, upper, _) = col.select_nth_unstable_by(hi, f32::total_cmp);
        let upper = *upper;
        let lower = if lo == hi {
            upper
        } else {
            // The largest below in total order (`f32::max` may pick -0.0 over 0.0).
            below
                .iter()
                .copied()
                .max_by(f32::total_cmp)
                .unwrap_or(upper)
        };
        emit(j, lower, upper);
    }
}

/// Coordinate-wise median with the given rule for an even count.
pub(super) fn median(c: &Candidates<'_>, tie: MedianTie, ws: &mut Workspace, out: &mut [f32]) {
    let n = c.len();
    let first = usize::from(tie == MedianTie::DropOldest && n.is_multiple_of(2));
    let (d, stride, m) = (c.dim(), c.stride(), n - first);
    let values = &c.values()[first * stride..];
    if let Some(net) = ws.median_nets.get(m) {
        // Fast path: sort all coordinates at once with the network, then read the central
        // rows.
        let rows = &mut ws.rows[..m * stride];
        rows.copy_from_slice(values);
        network::apply_rows(net, rows, stride);
        let lo = &rows[(m - 1) / 2 * stride..][..d];
        let hi = &rows[m / 2 * stride..][..d];
        write_median(tie, lo, hi, out);
    } else if select::supported(stride) {
        // Beyond the networks: select in SIMD lanes, all coordinates at once.
        let (lower, upper) = ws.central.split_at_mut(stride);
        select::central_pairs_lanes(values, stride, d, &mut ws.keys, lower, upper);
        write_median(tie, &lower[..d], &upper[..d], out);
    } else {
        central_pairs(c, first, ws, |j, lo, hi| {
            out[j] = match tie {
                MedianTie::Average | MedianTie::DropOldest => midpoint(lo, hi),
                MedianTie::Lower => lo,
                MedianTie::Upper => hi,
            };
        });
    }
}

/// The median from the central pair of every coordinate, by the tie rule.
fn write_median(tie: MedianTie, lo: &[f32], hi: &[f32], out: &mut [f32]) {
    match tie {
        MedianTie::Average | MedianTie::DropOldest => {
            for ((o, &a), &b) in out.iter_mut().zip(lo).zip(hi) {
                *o = midpoint(a, b);
            }
        }
        MedianTie::Lower => out.copy_from_slice(lo),
        MedianTie::Upper => out.copy_from_slice(hi),
    }
}

/// Per coordinate: sort, drop `min(k, (n - 1) / 2)` values from each end, average the rest.
pub(super) fn trimmed_mean(c: &Candidates<'_>, k: usize, ws: &mut Workspace, out: &mut [f32]) {
    let (n, d) = (c.len(), c.dim());
    let r = k.min((n - 1) / 2);
    for (j, o) in out.iter_mut().enumerate().take(d) {
        let col = &mut ws.col[..n];
        for (i, v) in col.iter_mut().enumerate() {
            *v = c.row(i)[j];
        }
        col.sort_unstable_by(f32::total_cmp);
        let kept = &col[r..n - r];
        let sum: f64 = kept.iter().map(|&v| v as f64).sum();
        *o = (sum / kept.len() as f64) as f32;
    }
}

/// Weighted coordinate-wise median with weights `exp(-m * age)`, age 0 = newest.
pub(super) fn recency_median(c: &Candidates<'_>, m: f64, ws: &mut Workspace, out: &mut [f32]) {
    let (n, d) = (c.len(), c.dim());
    // m >= 0 favours the newest: weight index k = age = n - 1 - i.
    ws.exp_weights(m, n, m < 0.0);
    let total: f64 = ws.score[..n].iter().sum();
    let half = 0.5 * total;
    for (j, o) in out.iter_mut().enumerate().take(d) {
        let pairs = &mut ws.pairs[..n];
        for (i, p) in pairs.iter_mut().enumerate() {
            *p = (c.row(i)[j], ws.score[i]);
        }
        pairs.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        let mut cum = 0.0;
        let mut value = pairs[n - 1].0;
        for (idx, &(v, w)) in pairs.iter().enumerate() {
            cum += w;
            if cum >= half {
                // Exactly half the weight on each side: average the two values, as the
                // unweighted median does for an even count.
                value = if (cum - half).abs() <= 1e-12 * total && idx + 1 < n {
                    midpoint(v, pairs[idx + 1].0)
                } else {
                    v
                };
                break;
            }
        }
        *o = value;
    }
}
