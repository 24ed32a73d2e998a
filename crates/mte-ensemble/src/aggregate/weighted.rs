//! Weighted means: exp-weighted (ACT), uniform, and their shared kernel.

use super::{Candidates, WeightOrder, Workspace};

/// `out = sum_i w_i x_i / sum_i w_i` with `w = ws.score[..n]`, accumulated in f64.
fn weighted_mean(c: &Candidates<'_>, ws: &mut Workspace, out: &mut [f32]) {
    let (d, n) = (c.dim(), c.len());
    let acc = &mut ws.acc[..d];
    acc.fill(0.0);
    let mut total = 0.0;
    for (i, &w) in ws.score[..n].iter().enumerate() {
        total += w;
        for (a, &x) in acc.iter_mut().zip(c.row(i)) {
            *a += w * x as f64;
        }
    }
    for (o, a) in out.iter_mut().zip(acc.iter()) {
        *o = (a / total) as f32;
    }
}

/// Exp-weighted mean. With candidate `i` oldest-first and `n` candidates, the weight index is
/// `k = i` ([`WeightOrder::OldestFirst`]) or `k = n - 1 - i` ([`WeightOrder::NewestFirst`]),
/// and `w = exp(-m k)`. A negative `m` is evaluated as the opposite order with `|m|`: the
/// same normalised weights, without overflow.
pub(super) fn exp_weighted_mean(
    c: &Candidates<'_>,
    m: f64,
    order: WeightOrder,
    ws: &mut Workspace,
    out: &mut [f32],
) {
    let oldest_heavy = (order == WeightOrder::OldestFirst) == (m >= 0.0);
    ws.exp_weights(m, c.len(), oldest_heavy);
    weighted_mean(c, ws, out);
}

/// Uniform mean.
pub(super) fn mean(c: &Candidates<'_>, ws: &mut Workspace, out: &mut [f32]) {
    ws.score[..c.len()].fill(1.0);
    weighted_mean(c, ws, out);
}
