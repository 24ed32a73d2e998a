//! Weighted means: exp-weighted (ACT), uniform, and their shared kernel.

use super::{Candidates, WeightOrder, Workspace};

/// `out = sum_i w_i x_i / total` with `w = ws.score[..n]`, accumulated in f64, row by row in
/// candidate order (so every path gives the same bits). `total` is `sum_i w_i` summed in
/// candidate order from 0, which the callers know without summing at every step.
fn weighted_mean(c: &Candidates<'_>, w: &[f64], acc: &mut [f64], total: f64, out: &mut [f32]) {
    let d = c.dim();
    let w = &w[..c.len()];
    debug_assert_eq!(total, w.iter().fold(0.0, |t, &x| t + x));
    match c.stride() {
        4 => weighted_rows::<4>(c.values(), w, acc),
        8 => weighted_rows::<8>(c.values(), w, acc),
        16 => weighted_rows::<16>(c.values(), w, acc),
        _ => {
            let acc = &mut acc[..d];
            acc.fill(0.0);
            for (i, &wi) in w.iter().enumerate() {
                for (a, &x) in acc.iter_mut().zip(c.row(i)) {
                    *a += wi * x as f64;
                }
            }
        }
    }
    for (o, a) in out.iter_mut().zip(&acc[..d]) {
        *o = (a / total) as f32;
    }
}

/// The weighted row sum of rows `S` values wide into `acc[..S]` (`acc` at least `S` long),
/// whole rows at a time so the lanes vectorise; compiled for AVX-512, AVX2 and the baseline.
#[cfg_attr(
    not(feature = "cap-avx2"),
    multiversion::multiversion(targets(
        "x86_64+avx512f+avx512vl",
        "x86_64+avx2+fma",
        "aarch64+neon"
    ))
)]
#[cfg_attr(
    feature = "cap-avx2",
    multiversion::multiversion(targets("x86_64+avx2+fma", "aarch64+neon"))
)]
fn weighted_rows<const S: usize>(values: &[f32], w: &[f64], acc: &mut [f64]) {
    let mut sum = [0f64; S];
    let (rows, _) = values.as_chunks::<S>();
    for (row, &wi) in rows.iter().zip(w) {
        for l in 0..S {
            sum[l] += wi * f64::from(row[l]);
        }
    }
    acc[..S].copy_from_slice(&sum);
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
    let n = c.len();
    // Oldest-heavy weights are read where they are cached, not copied at every step.
    let total = if oldest_heavy {
        ws.decay_weights(m, n)
    } else {
        ws.exp_weights(m, n, false)
    };
    let w = if oldest_heavy { &ws.decay } else { &ws.score };
    weighted_mean(c, w, &mut ws.acc, total, out);
}

/// Uniform mean.
pub(super) fn mean(c: &Candidates<'_>, ws: &mut Workspace, out: &mut [f32]) {
    ws.score[..c.len()].fill(1.0);
    // A sum of n ones in f64 is exactly n (n is far below 2^53).
    weighted_mean(c, &ws.score, &mut ws.acc, c.len() as f64, out);
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
    /// stride) give the same bits for counts 1 to 13, ignore the padding, and stay within
    /// f32 rounding of a naive f64 sum.
    #[test]
    fn every_path_gives_the_same_bits_and_the_sum() {
        for (d, stride) in [(3, 4), (7, 8), (14, 16)] {
            for n in 1..=13 {
                let padded = rows(n, d, stride);
                let plain: Vec<f32> = padded
                    .chunks_exact(stride)
                    .flat_map(|r| r[..d].iter().copied())
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
