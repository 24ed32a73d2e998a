//! Weighted means: exp-weighted (ACT), uniform, and their shared kernel.

use super::{Candidates, WeightOrder, Workspace};

/// Partial sums per coordinate: row `i` adds into partial `i mod PARTIALS`, and the
/// partials combine as `(p0 + p1) + (p2 + p3)`. Four independent chains of additions instead
/// of one: at ACT's M = 100 a single chain of 100 dependent f64 additions cost more than
/// the rest of the step.
const PARTIALS: usize = 4;

/// `out = sum_i w_i x_i / total` with `w = ws.score[..n]`, accumulated in f64 in
/// [`PARTIALS`] partial sums, each in candidate order (so every path, the lane-specialised
/// ones and the generic one, gives the same bits). `total` is `sum_i w_i` summed in
/// candidate order from 0, which the callers know without summing at every step.
fn weighted_mean(c: &Candidates<'_>, ws: &mut Workspace, total: f64, out: &mut [f32]) {
    let (d, n) = (c.dim(), c.len());
    let w = &ws.score[..n];
    debug_assert_eq!(total, w.iter().fold(0.0, |t, &x| t + x));
    match c.stride() {
        4 => weighted_rows::<4>(c.values(), w, &mut ws.acc),
        8 => weighted_rows::<8>(c.values(), w, &mut ws.acc),
        16 => weighted_rows::<16>(c.values(), w, &mut ws.acc),
        _ => {
            let parts = &mut ws.acc[..PARTIALS * d];
            parts.fill(0.0);
            for (i, &wi) in w.iter().enumerate() {
                let part = &mut parts[(i % PARTIALS) * d..][..d];
                for (a, &x) in part.iter_mut().zip(c.row(i)) {
                    *a += wi * f64::from(x);
                }
            }
            let (p01, p23) = parts.split_at_mut(2 * d);
            let ((p0, p1), (p2, p3)) = (p01.split_at_mut(d), p23.split_at(d));
            for (j, a) in p0.iter_mut().enumerate() {
                *a = (*a + p1[j]) + (p2[j] + p3[j]);
            }
        }
    }
    for (o, a) in out.iter_mut().zip(&ws.acc[..d]) {
        *o = (a / total) as f32;
    }
}

/// The weighted row sum of rows `S` values wide into `acc[..S]` (`acc` at least `S` long),
/// whole rows at a time so the lanes vectorise, in [`PARTIALS`] partial sums; compiled for
/// AVX-512, AVX2 and the baseline.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl",
    "x86_64+avx2+fma",
    "aarch64+neon"
))]
fn weighted_rows<const S: usize>(values: &[f32], w: &[f64], acc: &mut [f64]) {
    let (mut p0, mut p1, mut p2, mut p3) = ([0f64; S], [0f64; S], [0f64; S], [0f64; S]);
    let (rows, _) = values.as_chunks::<S>();
    let (mut rq, mut wq) = (rows.chunks_exact(PARTIALS), w.chunks_exact(PARTIALS));
    for (r, w) in rq.by_ref().zip(wq.by_ref()) {
        for l in 0..S {
            p0[l] += w[0] * f64::from(r[0][l]);
            p1[l] += w[1] * f64::from(r[1][l]);
            p2[l] += w[2] * f64::from(r[2][l]);
            p3[l] += w[3] * f64::from(r[3][l]);
        }
    }
    for (k, (row, &wi)) in rq.remainder().iter().zip(wq.remainder()).enumerate() {
        let p = match k {
            0 => &mut p0,
            1 => &mut p1,
            _ => &mut p2,
        };
        for l in 0..S {
            p[l] += wi * f64::from(row[l]);
        }
    }
    for l in 0..S {
        acc[l] = (p0[l] + p1[l]) + (p2[l] + p3[l]);
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
    let total = ws.exp_weights(m, c.len(), oldest_heavy);
    weighted_mean(c, ws, total, out);
}

/// Uniform mean.
pub(super) fn mean(c: &Candidates<'_>, ws: &mut Workspace, out: &mut [f32]) {
    ws.score[..c.len()].fill(1.0);
    // A sum of n ones in f64 is exactly n (n is far below 2^53).
    weighted_mean(c, ws, c.len() as f64, out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::aggregate::{Aggregate, Aggregator};

    /// `n` rows of `d` values, padded to `stride` with values that must not leak into the
    /// result (rows are read only up to `d` by the output).
    fn rows(n: usize, d: usize, stride: usize) -> Vec<f32> {
        let mut v = vec![7.5e3; n * stride];
        for i in 0..n {
            for j in 0..d {
                v[i * stride + j] = ((i * 31 + j * 17) as f32 * 0.613).sin() * 40.0 + i as f32;
            }
        }
        v
    }

    /// The lane-specialised sums (strides 4, 8, 16) and the generic one (an unpadded
    /// stride) give the same bits for every candidate count around the partial sums'
    /// period, and both stay within f32 rounding of a naive single-chain f64 sum.
    #[test]
    fn every_path_gives_the_same_bits_and_the_sum() {
        for (d, stride) in [(3, 4), (7, 8), (14, 16)] {
            for n in 1..=13 {
                let padded = rows(n, d, stride);
                let plain: Vec<f32> = padded
                    .chunks_exact(stride)
                    .flat_map(|r| r[..d].to_vec())
                    .collect();
                for agg in [Aggregator::default(), Aggregator::Mean] {
                    let mut ws = Workspace::new(n, d);
                    let (mut a, mut b) = (vec![0f32; d], vec![0f32; d]);
                    let c = Candidates::from_checked(&padded, d, stride);
                    agg.aggregate(&c, &mut ws, &mut a).unwrap();
                    let c = Candidates::new(&plain, d).unwrap();
                    agg.aggregate(&c, &mut ws, &mut b).unwrap();
                    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&a), bits(&b), "{agg} d {d} n {n}");
                    if agg == Aggregator::Mean {
                        for (j, &got) in a.iter().enumerate() {
                            let want =
                                (0..n).map(|i| f64::from(plain[i * d + j])).sum::<f64>() / n as f64;
                            assert!((f64::from(got) - want).abs() <= 1e-6 * want.abs().max(1.0));
                        }
                    }
                }
            }
        }
    }
}
