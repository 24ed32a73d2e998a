//! Sorting networks for small candidate sets.
//!
//! A comparator network applied row-wise (each comparator a branch-free `min`/`max` over all
//! `d` coordinates at once) finds the central order statistics of every coordinate together,
//! which is several times faster than a per-coordinate selection for the `M <= 32`
//! candidates seen in practice. Networks are built once, at workspace construction.

use wide::f32x4;

/// Largest candidate count served by a precomputed network; larger sets use selection.
pub(crate) const NETWORK_MAX: usize = 32;

/// Batcher's odd-even merge sort network on `n` wires, as `(lo, hi)` comparator pairs with
/// `lo < hi`: after applying them in order, wire `i` holds the `i`-th smallest value.
///
/// Generated for the next power of two and restricted to wires `< n`, which is exact because
/// every comparator moves the smaller value to the lower wire (absent wires act as `+inf`).
pub(crate) fn batcher(n: usize) -> Vec<(u16, u16)> {
    let size = n.next_power_of_two();
    let mut pairs = Vec::new();
    let mut p = 1;
    while p < size {
        let mut k = p;
        while k >= 1 {
            let mut j = k % p;
            while j + k < size {
                for i in 0..k.min(size - j - k) {
                    let (a, b) = (i + j, i + j + k);
                    if a / (2 * p) == b / (2 * p) && b < n {
                        pairs.push((a as u16, b as u16));
                    }
                }
                j += 2 * k;
            }
            k /= 2;
        }
        p *= 2;
    }
    pairs
}

/// The comparators of [`batcher`] that can influence the central wires `(n-1)/2` and `n/2`
/// (one wire when `n` is odd), found by walking the network backwards.
pub(crate) fn median_network(n: usize) -> Vec<(u16, u16)> {
    if n == 0 {
        return Vec::new();
    }
    let full = batcher(n);
    let mut needed = vec![false; n];
    needed[(n - 1) / 2] = true;
    needed[n / 2] = true;
    let mut kept: Vec<(u16, u16)> = Vec::with_capacity(full.len());
    for &(a, b) in full.iter().rev() {
        if needed[a as usize] || needed[b as usize] {
            needed[a as usize] = true;
            needed[b as usize] = true;
            kept.push((a, b));
        }
    }
    kept.reverse();
    kept
}

/// Applies `net` to rows of `dim` values stored row-major in `rows`, sorting every
/// coordinate independently (for the wires the network covers). Values must not be NaN.
///
/// Row widths 4, 8, 12 and 16 (the ensembler pads rows to a multiple of 4) take a path
/// specialised at compile time where each comparator is a few packed `minps`/`maxps`.
#[inline]
pub(crate) fn apply_rows(net: &[(u16, u16)], rows: &mut [f32], dim: usize) {
    match dim {
        4 => apply_fixed::<4>(net, rows),
        8 => apply_fixed::<8>(net, rows),
        12 => apply_fixed::<12>(net, rows),
        16 => apply_fixed::<16>(net, rows),
        _ => apply_any(net, rows, dim),
    }
}

/// [`apply_rows`] for a row width known at compile time, a multiple of 4: every comparator
/// is `S / 4` packed `minps`/`maxps` pairs on whole rows.
fn apply_fixed<const S: usize>(net: &[(u16, u16)], rows: &mut [f32]) {
    let (rows, _) = rows.as_chunks_mut::<S>();
    for &(a, b) in net {
        let (x, y) = (rows[a as usize], rows[b as usize]);
        let (mut lo, mut hi) = ([0.0f32; S], [0.0f32; S]);
        for k in (0..S).step_by(4) {
            let u = f32x4::from([x[k], x[k + 1], x[k + 2], x[k + 3]]);
            let v = f32x4::from([y[k], y[k + 1], y[k + 2], y[k + 3]]);
            lo[k..k + 4].copy_from_slice(&u.fast_min(v).to_array());
            hi[k..k + 4].copy_from_slice(&u.fast_max(v).to_array());
        }
        rows[a as usize] = lo;
        rows[b as usize] = hi;
    }
}

/// [`apply_rows`] for any row width, one coordinate at a time.
fn apply_any(net: &[(u16, u16)], rows: &mut [f32], dim: usize) {
    for &(a, b) in net {
        let (a, b) = (a as usize * dim, b as usize * dim);
        let (left, right) = rows.split_at_mut(b);
        let lo_row = &mut left[a..a + dim];
        let hi_row = &mut right[..dim];
        for (x, y) in lo_row.iter_mut().zip(hi_row.iter_mut()) {
            let (u, v) = (*x, *y);
            *x = if v < u { v } else { u };
            *y = if v < u { u } else { v };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 0-1 principle: a network sorts every input iff it sorts every 0/1 input.
    #[test]
    fn batcher_sorts_every_binary_input_up_to_16() {
        for n in 1..=16usize {
            let net = batcher(n);
            for bits in 0u32..(1 << n) {
                let mut rows: Vec<f32> = (0..n).map(|i| ((bits >> i) & 1) as f32).collect();
                apply_rows(&net, &mut rows, 1);
                assert!(
                    rows.windows(2).all(|w| w[0] <= w[1]),
                    "n = {n}, bits = {bits:b}"
                );
            }
        }
    }

    #[test]
    fn median_network_finds_central_values_up_to_network_max() {
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % 1000) as f32
        };
        for n in 1..=NETWORK_MAX {
            let net = median_network(n);
            assert!(net.len() <= batcher(n).len());
            for _ in 0..50 {
                let mut rows: Vec<f32> = (0..n).map(|_| next()).collect();
                let mut sorted = rows.clone();
                sorted.sort_by(f32::total_cmp);
                apply_rows(&net, &mut rows, 1);
                assert_eq!(rows[(n - 1) / 2], sorted[(n - 1) / 2], "n = {n}");
                assert_eq!(rows[n / 2], sorted[n / 2], "n = {n}");
            }
        }
    }
}
