//! Exact order statistics of large candidate sets, beyond the sorting networks (`M > 32`,
//! e.g. ACT's `M = 100` at `h = 1`).
//!
//! A coordinate's values become order-preserving integer keys, and the `k`-th smallest is
//! found by bisection on the key bits that vary: each pass counts the keys below a trial
//! threshold, a branch-free reduction over contiguous keys that the compiler vectorises; the
//! search stops once the bracket holds a single key. The result is the exact order
//! statistic (the value a sort would give; integer work only, so every instruction-set path
//! gives the same bits). The function is compiled for AVX-512, AVX2 and the baseline, and
//! the best the CPU has is chosen at run time.

use multiversion::multiversion;

/// Order-preserving key of a finite `f32`: `key(a) < key(b)` iff `a.total_cmp(&b)` is
/// `Less` (so `-0.0 < +0.0`).
#[inline]
pub(crate) fn key(x: f32) -> u32 {
    let b = x.to_bits();
    // Negative: flip every bit (larger magnitude, smaller key); positive: set the sign bit.
    b ^ ((((b as i32) >> 31) as u32) | 0x8000_0000)
}

/// Inverse of [`key`].
#[inline]
pub(crate) fn value(k: u32) -> f32 {
    let b = if k & 0x8000_0000 != 0 {
        k ^ 0x8000_0000
    } else {
        !k
    };
    f32::from_bits(b)
}

/// The `lo`-th and `hi`-th smallest key (0-based, `hi` is `lo` or `lo + 1`, both below
/// `col.len()`) of one column of keys.
///
/// Bisection on the key bits that vary: the answer is the largest `t` with at most `lo`
/// keys below it. A bracket `[t, t + 2^b)` known to hold the answer and exactly one key
/// ends the search early (after about `log2 n` passes instead of one per varying bit).
#[multiversion(targets = "simd")]
pub(crate) fn central_pair(col: &[u32], lo: usize, hi: usize) -> (u32, u32) {
    let (min, max) = col
        .iter()
        .fold((u32::MAX, 0u32), |(a, b), &x| (a.min(x), b.max(x)));
    let bits = 32 - (min ^ max).leading_zeros();
    let mut ans = if bits == 32 {
        0
    } else {
        min & !((1u32 << bits) - 1)
    };
    // Keys below `ans`, and keys below the top of the bracket.
    let (mut below_lo, mut below_hi) = (0usize, col.len());
    for bit in (0..bits).rev() {
        if below_hi - below_lo == 1 {
            break;
        }
        let t = ans | (1 << bit);
        let below = col.iter().fold(0u32, |a, &x| a + u32::from(x < t)) as usize;
        if below <= lo {
            (ans, below_lo) = (t, below);
        } else {
            below_hi = below;
        }
    }
    // The smallest key at or above `ans` is the answer (the bracket's only key, or `ans`
    // itself when every bit was resolved).
    let lower = col
        .iter()
        .fold(u32::MAX, |m, &x| if x >= ans { m.min(x) } else { m });
    if hi == lo {
        return (lower, lower);
    }
    // The next order statistic: the same key if it repeats, else the smallest key above.
    let (at_most, above) = col.iter().fold((0usize, u32::MAX), |(c, m), &x| {
        (
            c + usize::from(x <= lower),
            if x > lower { m.min(x) } else { m },
        )
    });
    (lower, if at_most > hi { lower } else { above })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_preserve_total_order_and_invert() {
        let xs = [
            f32::NEG_INFINITY,
            -3.0e38,
            -1.0,
            -1e-40,
            -0.0,
            0.0,
            1e-40,
            1.0,
            3.0e38,
            f32::INFINITY,
        ];
        for w in xs.windows(2) {
            assert!(key(w[0]) < key(w[1]), "{} < {}", w[0], w[1]);
        }
        for &x in &xs {
            assert_eq!(value(key(x)).to_bits(), x.to_bits());
        }
    }

    #[test]
    fn central_pairs_match_a_sort() {
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for n in [1usize, 2, 3, 33, 64, 99, 100, 101, 257] {
            for spread in [0.0f32, 1e-3, 1.0, 7.5, 1e30] {
                // Few distinct values (ties are common), both signs, both zeros.
                let col: Vec<u32> = (0..n)
                    .map(|_| {
                        let v = ((next() % 41) as f32 - 20.0) * spread;
                        key(if v == 0.0 && next() % 2 == 0 { -0.0 } else { v })
                    })
                    .collect();
                let (lo, hi) = ((n - 1) / 2, n / 2);
                let mut sorted = col.clone();
                sorted.sort_unstable();
                for (a, b) in [(lo, hi), (lo, lo), (0, 0), (n - 1, n - 1)] {
                    assert_eq!(
                        central_pair(&col, a, b),
                        (sorted[a], sorted[b]),
                        "n = {n}, spread {spread}, ({a}, {b})"
                    );
                }
            }
            // Continuous values: every bit matters.
            let col: Vec<u32> = (0..n)
                .map(|_| key(f32::from_bits(next() as u32 >> 2)))
                .collect();
            let mut sorted = col.clone();
            sorted.sort_unstable();
            let (lo, hi) = ((n - 1) / 2, n / 2);
            assert_eq!(
                central_pair(&col, lo, hi),
                (sorted[lo], sorted[hi]),
                "n = {n}"
            );
        }
    }
}
