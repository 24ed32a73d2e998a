//! Exact order statistics of every coordinate at once, for candidate sets beyond the sorting
//! networks (ACT's `M = 100`).
//!
//! Each row of the padded candidate matrix is `S` coordinates wide (`S` in 4, 8, 12, 16), so
//! the coordinates sit in SIMD lanes. The values are mapped to unsigned keys whose integer
//! order is [`f32::total_cmp`]'s order, and the `k`-th smallest key of every lane is built
//! bit by bit from the top (a radix select): at each bit, one pass over the rows counts, per
//! lane, the keys below the candidate prefix. That is at most 32 branch-free
//! compare-and-count passes over `M` rows, in the lanes the CPU has (AVX-512, AVX2, SSE2 or
//! the portable loop, chosen at run time). The AVX-512 and AVX2 kernels stop early: once the
//! bucket of keys sharing the prefix holds a single key in every coordinate's lane (padding
//! lanes aside), one more pass reads those keys. At ACT's `M = 100` that halves the passes;
//! ties at the centre run all 32. The result is the same value `select_nth_unstable_by` with
//! `total_cmp` returns, bit for bit, whichever way the kernel finishes.

/// Maps `x` to a key whose unsigned order is the order of [`f32::total_cmp`].
#[inline(always)]
fn key(x: f32) -> u32 {
    let b = x.to_bits();
    // Negative values: flip every bit; others: set the sign bit.
    b ^ ((((b as i32) >> 31) as u32) | 0x8000_0000)
}

/// Inverse of [`key`].
#[inline(always)]
fn unkey(k: u32) -> f32 {
    f32::from_bits(k ^ (((!k as i32 >> 31) as u32) | 0x8000_0000))
}

/// Row widths served by [`central_pairs_lanes`].
pub(super) fn supported(stride: usize) -> bool {
    matches!(stride, 4 | 8 | 12 | 16)
}

/// The order statistics of ranks `(n - 1) / 2` and `n / 2` (0-based) of every lane of the
/// `n = values.len() / stride` rows, written to `lower[..stride]` and `upper[..stride]`;
/// exact in the first `lanes` lanes (the action's coordinates), while the padding lanes
/// after them may hold any key of their lane. `keys` is scratch of at least `values.len()`.
/// The stride must be [`supported`].
pub(super) fn central_pairs_lanes(
    values: &[f32],
    stride: usize,
    lanes: usize,
    keys: &mut [i32],
    lower: &mut [f32],
    upper: &mut [f32],
) {
    match stride {
        4 => central::<4>(values, lanes, keys, lower, upper),
        8 => central::<8>(values, lanes, keys, lower, upper),
        12 => central::<12>(values, lanes, keys, lower, upper),
        _ => central::<16>(values, lanes, keys, lower, upper),
    }
}

/// Maps `x` to an `i32` whose signed order is the order of [`f32::total_cmp`] (signed
/// compares are what every SIMD level has).
#[inline(always)]
fn signed_key(x: f32) -> i32 {
    (key(x) ^ 0x8000_0000) as i32
}

/// Inverse of [`signed_key`].
#[inline(always)]
fn unsigned_key(k: i32) -> u32 {
    k as u32 ^ 0x8000_0000
}

fn central<const S: usize>(
    values: &[f32],
    lanes: usize,
    keys: &mut [i32],
    lower: &mut [f32],
    upper: &mut [f32],
) {
    let (rows, _) = values.as_chunks::<S>();
    let n = rows.len();
    let (keys, _) = keys[..n * S].as_chunks_mut::<S>();
    for (k, row) in keys.iter_mut().zip(rows) {
        for l in 0..S {
            k[l] = signed_key(row[l]);
        }
    }
    let (lo, hi) = ((n - 1) / 2, n / 2);
    let below = (lo != hi).then_some(lo as u32);
    let (top, bottom) = select_dispatch::<S>(keys, hi as u32, below, lanes);
    for l in 0..S {
        upper[l] = unkey(top[l]);
        lower[l] = unkey(bottom[l]);
    }
}

/// The `u32` keys of rank `rank` (0-based) in the first `lanes` lanes of the signed-key
/// rows, and of rank `lower` when given (else the same keys again), on the best SIMD level
/// the CPU has.
fn select_dispatch<const S: usize>(
    keys: &[[i32; S]],
    rank: u32,
    lower: Option<u32>,
    lanes: usize,
) -> ([u32; S], [u32; S]) {
    #[cfg(target_arch = "x86_64")]
    {
        if let Some(out) = simd::select(keys, rank, lower, lanes) {
            return out;
        }
    }
    let _ = lanes;
    select_scalar(keys, rank, lower)
}

/// The portable selection: a bit of the key is set when at most `rank` keys lie below the
/// prefix with it set. The rank just below is then the largest key below the result when
/// `rank` keys lie below it, else the result itself (a tie across the centre).
fn select_scalar<const S: usize>(
    keys: &[[i32; S]],
    rank: u32,
    lower: Option<u32>,
) -> ([u32; S], [u32; S]) {
    let mut prefix = [0u32; S];
    for bit in (0..32).rev() {
        for l in 0..S {
            let trial = prefix[l] | 1 << bit;
            let t = (trial ^ 0x8000_0000) as i32;
            let count = keys.iter().filter(|k| k[l] < t).count();
            if count as u32 <= rank {
                prefix[l] = trial;
            }
        }
    }
    let mut bottom = prefix;
    if let Some(lo) = lower {
        for l in 0..S {
            let t = (prefix[l] ^ 0x8000_0000) as i32;
            let below = keys.iter().map(|k| k[l]).filter(|&k| k < t);
            if below.clone().count() as u32 > lo {
                let largest = below.max().unwrap_or(i32::MIN);
                bottom[l] = unsigned_key(largest);
            }
        }
    }
    (prefix, bottom)
}

/// The counting passes in explicit SIMD (x86_64): AVX-512 when a row is 16 lanes, AVX2 when
/// it is a multiple of 8, SSE2 (every x86_64 CPU) otherwise. The compiler, left to itself,
/// vectorises across rows with gathers, which is slower than scalar code.
///
/// Each kernel finds the key of rank `rank` by up to 32 counting passes (AVX-512 and AVX2
/// stop once every coordinate lane's bucket holds one key, and read it in one pass), then,
/// when asked, the key of rank `lower` by one more pass that counts the keys below it and
/// keeps their maximum.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod simd {
    use std::arch::x86_64::*;

    type Pair<const S: usize> = ([u32; S], [u32; S]);

    /// A SIMD level of the kernels.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub(super) enum Level {
        Avx512,
        Avx2,
        Sse2,
    }

    impl Level {
        /// Whether this CPU runs the level's kernel for rows of `s` lanes.
        pub(super) fn serves(self, s: usize) -> bool {
            match self {
                Self::Avx512 => {
                    !cfg!(feature = "cap-avx2")
                        && s == 16
                        && std::arch::is_x86_feature_detected!("avx512f")
                }
                Self::Avx2 => {
                    s.is_multiple_of(8) && s <= 16 && std::arch::is_x86_feature_detected!("avx2")
                }
                Self::Sse2 => s.is_multiple_of(4) && s <= 16,
            }
        }
    }

    /// The selection on the best level this CPU has; `None` when the row width has no SIMD
    /// path (never for the widths of [`super::supported`]).
    pub(super) fn select<const S: usize>(
        keys: &[[i32; S]],
        rank: u32,
        lower: Option<u32>,
        lanes: usize,
    ) -> Option<Pair<S>> {
        let level = [Level::Avx512, Level::Avx2, Level::Sse2]
            .into_iter()
            .find(|l| l.serves(S))?;
        Some(select_on(level, keys, rank, lower, lanes))
    }

    /// The selection on `level`, which must [`Level::serves`] rows of `S` lanes; exact in
    /// the first `lanes` lanes.
    pub(super) fn select_on<const S: usize>(
        level: Level,
        keys: &[[i32; S]],
        rank: u32,
        lower: Option<u32>,
        lanes: usize,
    ) -> Pair<S> {
        assert!(level.serves(S), "{level:?} cannot serve rows of {S} lanes");
        let (mut top, mut bottom) = ([0u32; S], [0u32; S]);
        let flat = keys.as_flattened();
        let lo = lower.map_or(-1, |l| l as i32);
        match level {
            // SAFETY (all three): `serves` checked that the CPU has the level's features and
            // that the row width fits the kernel.
            Level::Avx512 => unsafe {
                let active = if lanes >= 16 {
                    u16::MAX
                } else {
                    (1u16 << lanes) - 1
                };
                select_avx512(flat, rank, lo, active, &mut top, &mut bottom)
            },
            Level::Avx2 => unsafe { select_avx2(flat, S, rank, lo, lanes, &mut top, &mut bottom) },
            Level::Sse2 => unsafe { select_sse2(flat, S, rank, lo, &mut top, &mut bottom) },
        }
        if lower.is_none() {
            bottom = top;
        }
        (top, bottom)
    }

    /// Rows of 16 lanes in one AVX-512 register each. The counting passes stop early once
    /// every lane of `active` has narrowed its bucket (the keys that share the prefix built
    /// so far) to a single key, which is then the answer: one pass finds it as the smallest
    /// key not below the prefix. At ACT's `M = 100` that is typically after about half of
    /// the 32 passes; ties across the centre run all 32.
    #[target_feature(enable = "avx512f")]
    fn select_avx512(
        keys: &[i32],
        rank: u32,
        lo: i32,
        active: u16,
        top: &mut [u32],
        bottom: &mut [u32],
    ) {
        let sign = _mm512_set1_epi32(i32::MIN);
        let one = _mm512_set1_epi32(1);
        let limit = _mm512_set1_epi32(rank as i32);
        let mut prefix = _mm512_setzero_si512();
        // Keys below the prefix, and below the prefix plus the current bucket's width.
        let mut below = _mm512_setzero_si512();
        let mut upto = _mm512_set1_epi32((keys.len() / 16) as i32);
        for bit in (0..32).rev() {
            let trial = _mm512_or_si512(prefix, _mm512_set1_epi32((1u32 << bit) as i32));
            let t = _mm512_xor_si512(trial, sign);
            // Four independent counters, so the adds do not wait on each other.
            let mut c = [_mm512_setzero_si512(); 4];
            let blocks = keys.chunks_exact(64);
            let rest = blocks.remainder();
            for block in blocks {
                for (j, cj) in c.iter_mut().enumerate() {
                    // SAFETY: `block` holds 64 readable i32; the load is unaligned.
                    let k = unsafe { _mm512_loadu_si512(block[16 * j..].as_ptr().cast()) };
                    *cj = _mm512_mask_add_epi32(*cj, _mm512_cmplt_epi32_mask(k, t), *cj, one);
                }
            }
            for row in rest.chunks_exact(16) {
                // SAFETY: `row` holds 16 readable i32; the load is unaligned.
                let k = unsafe { _mm512_loadu_si512(row.as_ptr().cast()) };
                c[0] = _mm512_mask_add_epi32(c[0], _mm512_cmplt_epi32_mask(k, t), c[0], one);
            }
            let count =
                _mm512_add_epi32(_mm512_add_epi32(c[0], c[1]), _mm512_add_epi32(c[2], c[3]));
            let accept = _mm512_cmple_epi32_mask(count, limit);
            prefix = _mm512_mask_mov_epi32(prefix, accept, trial);
            below = _mm512_mask_mov_epi32(below, accept, count);
            upto = _mm512_mask_mov_epi32(count, accept, upto);
            let size = _mm512_sub_epi32(upto, below);
            if bit > 0 && _mm512_mask_cmpneq_epi32_mask(active, size, one) == 0 {
                prefix = _mm512_xor_si512(smallest_from_avx512(keys, prefix), sign);
                break;
            }
        }
        let t = _mm512_xor_si512(prefix, sign);
        let (mut count, mut largest) = (_mm512_setzero_si512(), sign);
        for row in keys.chunks_exact(16) {
            // SAFETY: as above.
            let k = unsafe { _mm512_loadu_si512(row.as_ptr().cast()) };
            let m = _mm512_cmplt_epi32_mask(k, t);
            count = _mm512_mask_add_epi32(count, m, count, one);
            largest = _mm512_mask_max_epi32(largest, m, largest, k);
        }
        let use_largest = _mm512_cmpgt_epi32_mask(count, _mm512_set1_epi32(lo));
        let low = _mm512_mask_mov_epi32(prefix, use_largest, _mm512_xor_si512(largest, sign));
        // SAFETY: `top` and `bottom` hold 16 writable u32.
        unsafe {
            _mm512_storeu_si512(top.as_mut_ptr().cast(), prefix);
            _mm512_storeu_si512(bottom.as_mut_ptr().cast(), low);
        }
    }

    /// Per lane, the smallest signed key not below the unsigned `prefix` (`i32::MAX` where
    /// there is none).
    #[target_feature(enable = "avx512f")]
    fn smallest_from_avx512(keys: &[i32], prefix: __m512i) -> __m512i {
        let t = _mm512_xor_si512(prefix, _mm512_set1_epi32(i32::MIN));
        let mut smallest = _mm512_set1_epi32(i32::MAX);
        for row in keys.chunks_exact(16) {
            // SAFETY: `row` holds 16 readable i32; the load is unaligned.
            let k = unsafe { _mm512_loadu_si512(row.as_ptr().cast()) };
            let m = _mm512_cmpge_epi32_mask(k, t);
            smallest = _mm512_mask_min_epi32(smallest, m, smallest, k);
        }
        smallest
    }

    /// Per lane of the `j`-th 8-lane group of rows `s` wide, the smallest signed key not
    /// below the unsigned `prefix` (`i32::MAX` where there is none).
    #[target_feature(enable = "avx2")]
    fn smallest_from_avx2(keys: &[i32], s: usize, j: usize, prefix: __m256i) -> __m256i {
        let t = _mm256_xor_si256(prefix, _mm256_set1_epi32(i32::MIN));
        let none = _mm256_set1_epi32(i32::MAX);
        let mut smallest = none;
        for row in keys.chunks_exact(s) {
            // SAFETY: `row` holds `s >= 8 (j + 1)` readable i32; the load is unaligned.
            let k = unsafe { _mm256_loadu_si256(row[8 * j..].as_ptr().cast()) };
            let below = _mm256_cmpgt_epi32(t, k);
            smallest = _mm256_min_epi32(smallest, _mm256_blendv_epi8(k, none, below));
        }
        smallest
    }

    /// Rows of `s` lanes, a multiple of 8 up to 16, in AVX2 registers.
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    fn select_avx2(
        keys: &[i32],
        s: usize,
        rank: u32,
        lo: i32,
        lanes: usize,
        top: &mut [u32],
        bottom: &mut [u32],
    ) {
        let v = s / 8;
        let sign = _mm256_set1_epi32(i32::MIN);
        let limit = _mm256_set1_epi32(rank as i32 + 1);
        let one = _mm256_set1_epi32(1);
        let mut prefix = [_mm256_setzero_si256(); 2];
        // As in `select_avx512`: keys below the prefix and below the bucket's end, to stop
        // once every coordinate lane's bucket holds one key; padding lanes never hold it up.
        let mut below = [_mm256_setzero_si256(); 2];
        let mut upto = [_mm256_set1_epi32((keys.len() / s) as i32); 2];
        let mut padding = [_mm256_setzero_si256(); 2];
        for (j, p) in padding.iter_mut().enumerate() {
            let lane = _mm256_add_epi32(
                _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
                _mm256_set1_epi32(8 * j as i32),
            );
            *p = _mm256_cmpgt_epi32(lane, _mm256_set1_epi32(lanes as i32 - 1));
        }
        for bit in (0..32).rev() {
            let b = _mm256_set1_epi32((1u32 << bit) as i32);
            let mut t = [_mm256_setzero_si256(); 2];
            for (ti, p) in t.iter_mut().zip(&prefix).take(v) {
                *ti = _mm256_xor_si256(_mm256_or_si256(*p, b), sign);
            }
            // Two rows per iteration, so the adds of one lane do not wait on each other.
            let mut c = [[_mm256_setzero_si256(); 2]; 2];
            let pairs = keys.chunks_exact(2 * s);
            let rest = pairs.remainder();
            for pair in pairs {
                for (r, cr) in c.iter_mut().enumerate() {
                    for j in 0..v {
                        // SAFETY: `pair` holds `2 s` readable i32; the load is unaligned.
                        let k =
                            unsafe { _mm256_loadu_si256(pair[r * s + 8 * j..].as_ptr().cast()) };
                        cr[j] = _mm256_sub_epi32(cr[j], _mm256_cmpgt_epi32(t[j], k));
                    }
                }
            }
            for j in 0..v.min(rest.len() / 8) {
                // SAFETY: `rest` holds one row of `8 v` readable i32.
                let k = unsafe { _mm256_loadu_si256(rest[8 * j..].as_ptr().cast()) };
                c[0][j] = _mm256_sub_epi32(c[0][j], _mm256_cmpgt_epi32(t[j], k));
            }
            let mut single = true;
            for j in 0..v {
                let count = _mm256_add_epi32(c[0][j], c[1][j]);
                let keep = _mm256_cmpgt_epi32(limit, count);
                prefix[j] = _mm256_or_si256(prefix[j], _mm256_and_si256(keep, b));
                below[j] = _mm256_blendv_epi8(below[j], count, keep);
                upto[j] = _mm256_blendv_epi8(count, upto[j], keep);
                let size = _mm256_sub_epi32(upto[j], below[j]);
                let done = _mm256_or_si256(_mm256_cmpeq_epi32(size, one), padding[j]);
                single &= _mm256_movemask_epi8(done) == -1;
            }
            if bit > 0 && single {
                for (j, p) in prefix.iter_mut().enumerate().take(v) {
                    *p = _mm256_xor_si256(smallest_from_avx2(keys, s, j, *p), sign);
                }
                break;
            }
        }
        let lo = _mm256_set1_epi32(lo);
        for j in 0..v {
            let t = _mm256_xor_si256(prefix[j], sign);
            let (mut count, mut largest) = (_mm256_setzero_si256(), sign);
            for row in keys.chunks_exact(s) {
                // SAFETY: as above.
                let k = unsafe { _mm256_loadu_si256(row[8 * j..].as_ptr().cast()) };
                let m = _mm256_cmpgt_epi32(t, k);
                count = _mm256_sub_epi32(count, m);
                largest = _mm256_max_epi32(largest, _mm256_blendv_epi8(sign, k, m));
            }
            let use_largest = _mm256_cmpgt_epi32(count, lo);
            let low = _mm256_blendv_epi8(prefix[j], _mm256_xor_si256(largest, sign), use_largest);
            // SAFETY: `top` and `bottom` hold `s = 8 v` writable u32.
            unsafe {
                _mm256_storeu_si256(top[8 * j..].as_mut_ptr().cast(), prefix[j]);
                _mm256_storeu_si256(bottom[8 * j..].as_mut_ptr().cast(), low);
            }
        }
    }

    /// `m ? a : b` lane by lane (`m` all ones or all zeros per lane), in SSE2.
    #[target_feature(enable = "sse2")]
    fn select_lanes(m: __m128i, a: __m128i, b: __m128i) -> __m128i {
        _mm_or_si128(_mm_and_si128(m, a), _mm_andnot_si128(m, b))
    }

    /// Rows of `s` lanes, a multiple of 4 up to 16, in SSE2 registers.
    #[target_feature(enable = "sse2")]
    fn select_sse2(
        keys: &[i32],
        s: usize,
        rank: u32,
        lo: i32,
        top: &mut [u32],
        bottom: &mut [u32],
    ) {
        let v = s / 4;
        let sign = _mm_set1_epi32(i32::MIN);
        let limit = _mm_set1_epi32(rank as i32 + 1);
        let mut prefix = [_mm_setzero_si128(); 4];
        for bit in (0..32).rev() {
            let b = _mm_set1_epi32((1u32 << bit) as i32);
            let mut t = [_mm_setzero_si128(); 4];
            for (ti, p) in t.iter_mut().zip(&prefix).take(v) {
                *ti = _mm_xor_si128(_mm_or_si128(*p, b), sign);
            }
            let mut count = [_mm_setzero_si128(); 4];
            for row in keys.chunks_exact(s) {
                for j in 0..v {
                    // SAFETY: `row` holds `4 v` readable i32; the load is unaligned.
                    let k = unsafe { _mm_loadu_si128(row[4 * j..].as_ptr().cast()) };
                    count[j] = _mm_sub_epi32(count[j], _mm_cmpgt_epi32(t[j], k));
                }
            }
            for j in 0..v {
                let keep = _mm_cmpgt_epi32(limit, count[j]);
                prefix[j] = _mm_or_si128(prefix[j], _mm_and_si128(keep, b));
            }
        }
        let lo = _mm_set1_epi32(lo);
        for j in 0..v {
            let t = _mm_xor_si128(prefix[j], sign);
            let (mut count, mut largest) = (_mm_setzero_si128(), sign);
            for row in keys.chunks_exact(s) {
                // SAFETY: as above.
                let k = unsafe { _mm_loadu_si128(row[4 * j..].as_ptr().cast()) };
                let m = _mm_cmpgt_epi32(t, k);
                count = _mm_sub_epi32(count, m);
                let candidate = select_lanes(m, k, sign);
                largest = select_lanes(_mm_cmpgt_epi32(candidate, largest), candidate, largest);
            }
            let use_largest = _mm_cmpgt_epi32(count, lo);
            let low = select_lanes(use_largest, _mm_xor_si128(largest, sign), prefix[j]);
            // SAFETY: `top` and `bottom` hold `s = 4 v` writable u32.
            unsafe {
                _mm_storeu_si128(top[4 * j..].as_mut_ptr().cast(), prefix[j]);
                _mm_storeu_si128(bottom[4 * j..].as_mut_ptr().cast(), low);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_preserve_total_order_and_invert() {
        let xs = [
            f32::NEG_INFINITY,
            -3.4e38,
            -1.0,
            -1e-40,
            -0.0,
            0.0,
            1e-40,
            1.0,
            3.4e38,
            f32::INFINITY,
        ];
        for w in xs.windows(2) {
            assert_eq!(w[0].total_cmp(&w[1]), key(w[0]).cmp(&key(w[1])), "{w:?}");
        }
        for &x in &xs {
            assert_eq!(unkey(key(x)).to_bits(), x.to_bits());
        }
    }

    /// With dispatch capped at AVX2 no row width reaches the AVX-512 kernel, and 16-lane
    /// rows go to AVX2 where the CPU has it (the feature's promise to its benchmarks).
    #[cfg(all(target_arch = "x86_64", feature = "cap-avx2"))]
    #[test]
    fn capped_dispatch_never_reaches_avx512() {
        for s in [4, 8, 12, 16] {
            assert!(!simd::Level::Avx512.serves(s), "{s} lanes");
        }
        assert_eq!(
            simd::Level::Avx2.serves(16),
            std::arch::is_x86_feature_detected!("avx2")
        );
    }

    /// Every SIMD level this CPU has, at every row width it serves, gives the portable
    /// selection's keys bit for bit (random keys with many ties, odd and even counts).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn every_simd_level_matches_the_portable_selection() {
        fn check<const S: usize>(state: &mut u64) -> usize {
            let mut checked = 0;
            for n in [1usize, 2, 3, 5, 8, 33, 64, 99, 100, 131] {
                let keys: Vec<[i32; S]> = (0..n)
                    .map(|_| {
                        std::array::from_fn(|_| {
                            *state ^= *state << 13;
                            *state ^= *state >> 7;
                            *state ^= *state << 17;
                            match *state % 3 {
                                0 => (*state >> 32) as i32,
                                1 => ((*state >> 59) as i32) - 16,
                                _ => i32::MIN + (*state >> 62) as i32,
                            }
                        })
                    })
                    .collect();
                let (lo, hi) = (((n - 1) / 2) as u32, (n / 2) as u32);
                let want = select_scalar(&keys, hi, Some(lo));
                for level in [simd::Level::Avx512, simd::Level::Avx2, simd::Level::Sse2] {
                    if level.serves(S) {
                        let got = simd::select_on(level, &keys, hi, Some(lo), S);
                        assert_eq!(got, want, "{level:?} S {S} n {n}");
                        checked += 1;
                    }
                }
            }
            checked
        }
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let checked = check::<4>(&mut state)
            + check::<8>(&mut state)
            + check::<12>(&mut state)
            + check::<16>(&mut state);
        // SSE2 serves every width on every x86_64 CPU.
        assert!(checked >= 40, "only {checked} kernel runs checked");
    }

    /// Rows of 16 lanes whose last 2 lanes are constant padding (as the ensembler pads 14
    /// coordinates): the coordinates' lanes stop early on distinct keys, and every level
    /// still gives the portable selection's keys there, bit for bit; also with ties at the
    /// centre in one lane, which runs every pass.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn early_exit_with_padding_lanes_matches_the_portable_selection() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x9E37_79B9_7F4A_7C15);
        let mut next = move || rng.random::<u64>();
        for n in [1usize, 2, 7, 8, 50, 99, 100] {
            for tie_lane in [None, Some(3)] {
                let keys: Vec<[i32; 16]> = (0..n)
                    .map(|i| {
                        std::array::from_fn(|l| match (l, tie_lane) {
                            (14 | 15, _) => 0,
                            (l, Some(t)) if l == t => (i % 3) as i32,
                            _ => signed_key(f32::from_bits(next() as u32 & 0xbfff_ffff)),
                        })
                    })
                    .collect();
                let (lo, hi) = (((n - 1) / 2) as u32, (n / 2) as u32);
                let want = select_scalar(&keys, hi, Some(lo));
                for level in [simd::Level::Avx512, simd::Level::Avx2, simd::Level::Sse2] {
                    if level.serves(16) {
                        let got = simd::select_on(level, &keys, hi, Some(lo), 14);
                        assert_eq!(got.0[..14], want.0[..14], "{level:?} n {n} top");
                        assert_eq!(got.1[..14], want.1[..14], "{level:?} n {n} bottom");
                    }
                }
            }
        }
    }

    #[test]
    fn lanes_match_selection_with_ties_and_signed_zeros() {
        // 5 rows x 4 lanes, odd and even counts, ties, and -0.0 beside 0.0.
        let cols: [[f32; 6]; 4] = [
            [3.0, 1.0, 2.0, 5.0, 4.0, 0.5],
            [1.0, 1.0, 1.0, 2.0, 2.0, 2.0],
            [-0.0, 0.0, -0.0, 0.0, 7.0, -7.0],
            [-1.0, -2.0, -3.0, -1.0, -2.0, -3.0],
        ];
        for n in 1..=6 {
            let mut values = vec![0.0; n * 4];
            for (l, col) in cols.iter().enumerate() {
                for i in 0..n {
                    values[i * 4 + l] = col[i];
                }
            }
            let (mut lower, mut upper, mut keys) = ([0.0; 4], [0.0; 4], vec![0i32; n * 4]);
            central_pairs_lanes(&values, 4, 4, &mut keys, &mut lower, &mut upper);
            for (l, col) in cols.iter().enumerate() {
                let mut sorted = col[..n].to_vec();
                sorted.sort_by(f32::total_cmp);
                let (lo, hi) = ((n - 1) / 2, n / 2);
                assert_eq!(lower[l].to_bits(), sorted[lo].to_bits(), "n {n} lane {l}");
                assert_eq!(upper[l].to_bits(), sorted[hi].to_bits(), "n {n} lane {l}");
            }
        }
    }
}
