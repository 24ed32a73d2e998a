//! The matrix product of the per-sample path ([`super::batch`]), with every output element's
//! arithmetic fixed by definition:
//!
//! `out[i, j] = fma(a[i, K-1], b[K-1, j], … fma(a[i, 1], b[1, j], fma(a[i, 0], b[0, j], 0)))`,
//!
//! one fused multiply-add per term, in the order of `k`, from zero. Nothing about the
//! element's neighbours (how many rows or columns the product has, which tile computes the
//! element, which samples share the call) enters its value, so a sample's result is the same
//! bits in a batch of one and in a batch of 64; and since a fused multiply-add is exactly
//! rounded by definition, the AVX2 and NEON builds of the tile loop (through `multiversion`),
//! the AVX-512 tile of two panels at once ([`Tiles::Pairs`], on CPUs that have it, for
//! products of at least 64 vector lines) and the scalar `mul_add` of the baseline build
//! (which, on an x86-64 CPU without FMA, is a slow library call) all give the same bits.
//!
//! Why not the `gemm` crate that candle calls: it picks its blocking and its microkernels
//! from the product's shape, so batch invariance needed one call per sample, and a sample of
//! the U-Net has 16 columns (the horizon), where `gemm` runs its narrow edge kernels: at
//! batch 64 they took 30% of the `cpu` U-Net's forward (a `perf` profile of
//! `benches/unet.rs`). Here the batch's free lines (columns on the left, rows on the right)
//! are tiled [`LANES`] at a time across sample boundaries against [`WIDTH`] lines of the
//! shared matrix, each register tile walking the whole depth `K`; cache blocks group vector
//! panels, never the depth.
//!
//! Layouts: every operand row-major and contiguous; the shared matrix may be stored
//! transposed, and is packed into panels once per call ([`Shared::Plain`]) or once per
//! weight ([`Shared::Panels`], from [`left_panels`]).

use super::batch::Side;

/// Vector lanes of a register tile (one AVX2 register of f32): output lines of the batch
/// operand.
pub(super) const LANES: usize = 8;
/// Scalar width of a register tile: output lines of the shared operand (12 accumulators, a
/// vector load and a broadcast fill 14 of AVX2's 16 registers).
pub(super) const WIDTH: usize = 12;

/// Vector panels per cache block: each block's panels (`k` × [`LANES`] elements apiece) are
/// reused by every scalar group while they sit in the L2 cache.
const BLOCK_BYTES: usize = 192 * 1024;

/// A float the product is defined for: `mul_add` is the fused multiply-add.
pub(super) trait Element:
    Copy + Send + Sync + 'static + std::ops::Add<Output = Self>
{
    const ZERO: Self;
    fn mul_add(self, b: Self, c: Self) -> Self;

    /// The tiling this type's products take on this CPU.
    fn best_tiles() -> Tiles {
        Tiles::Single
    }

    /// The paired register tile ([`portable_pair`]'s arithmetic), in the fastest form this
    /// type has on this CPU.
    #[inline(always)]
    fn pair_tile<const W: usize>(lo: &[Self], hi: &[Self], group: &[Self]) -> PairTile<Self, W> {
        portable_pair(lo, hi, group)
    }
}

impl Element for f32 {
    const ZERO: Self = 0.0;
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        f32::mul_add(self, b, c)
    }

    fn best_tiles() -> Tiles {
        #[cfg(target_arch = "x86_64")]
        if wide::available() {
            return Tiles::Pairs;
        }
        Tiles::Single
    }

    #[inline(always)]
    fn pair_tile<const W: usize>(lo: &[Self], hi: &[Self], group: &[Self]) -> PairTile<Self, W> {
        #[cfg(target_arch = "x86_64")]
        if let Some(t) = wide::pair(lo, hi, group) {
            return t;
        }
        portable_pair(lo, hi, group)
    }
}

impl Element for f64 {
    const ZERO: Self = 0.0;
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        f64::mul_add(self, b, c)
    }
}

/// Dimensions of one sample's product: `(m, K) · (K, n)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Dims {
    pub m: usize,
    pub k: usize,
    pub n: usize,
}

/// The shared operand as stored.
#[derive(Clone, Copy, Debug)]
pub(super) enum Shared<'a, T> {
    /// The matrix multiplied, row-major, or (`transposed`) its transpose, row-major: packed
    /// into [`Shared::Panels`] once per call.
    Plain { data: &'a [T], transposed: bool },
    /// Already packed by [`left_panels`] (a constant weight, packed once when loaded).
    Panels(&'a [T]),
}

/// The scalar side's lines packed for the register tiles: line group `q` (lines `q W ..`,
/// `W` = [`WIDTH`]), depth `kk`, line `c` at `[(q K + kk) W + c]`; lines past the last are
/// zero. `line(l, kk)` reads the unpacked matrix.
fn pack<T: Element>(count: usize, k: usize, line: impl Fn(usize, usize) -> T) -> Vec<T> {
    let mut out = vec![T::ZERO; count.div_ceil(WIDTH) * k * WIDTH];
    for (q, group) in out.chunks_mut(k * WIDTH).enumerate() {
        for (kk, row) in group.chunks_mut(WIDTH).enumerate() {
            for (c, v) in row.iter_mut().enumerate().take(count - q * WIDTH) {
                *v = line(q * WIDTH + c, kk);
            }
        }
    }
    out
}

/// A shared left operand `w (m, K)` (row-major) packed as [`Shared::Panels`].
pub(super) fn left_panels<T: Element>(w: &[T], m: usize, k: usize) -> Vec<T> {
    pack(m, k, |i, kk| w[i * k + kk])
}

/// Each sample's product with the shared matrix `w` on `side`: `Left`, `out_b (m, n) = w (m,
/// K) · x_b (K, n)`; `Right`, `out_b (m, n) = x_b (m, K) · w (K, n)`; `x` and `out` hold
/// `batch` row-major matrices back to back.
///
/// The samples' free lines (the columns of every `x_b` on the left, their rows on the right)
/// form one vector side, tiled [`LANES`] at a time across sample boundaries; the shared
/// matrix's free lines form the scalar side, packed into panels of [`WIDTH`] lines once per
/// call (or once per weight, [`Shared::Panels`]). Callers pass slices of the sizes `d` and `batch`
/// give (from storages they checked: a shorter slice is an internal error, and panics).
pub(super) fn products<T: Element>(
    side: Side,
    w: Shared<'_, T>,
    x: &[T],
    d: Dims,
    batch: usize,
    out: &mut [T],
) {
    let vector = VectorSide { side, x, d, batch };
    with_panels(vector, w, &vector.panels(), (out, None));
}

/// [`products`] on the left, with the batch's vector panels already packed (`panels`, in
/// [`VectorSide::panels`]' layout: `batch · n` lines, sample-major), e.g. straight from a
/// convolution's input without an im2col copy, plus `bias[i]`, if any, on every element of
/// row `i` (`out = product + bias`, one rounding, as a separate addition gives).
pub(super) fn left_products_packed<T: Element>(
    w: Shared<'_, T>,
    panels: &[T],
    d: Dims,
    batch: usize,
    (out, bias): (&mut [T], Option<&[T]>),
) {
    let vector = VectorSide {
        side: Side::Left,
        x: &[],
        d,
        batch,
    };
    with_panels(vector, w, panels, (out, bias));
}

/// The products of the batch's packed `panels` with `w`, in this CPU's best tiling.
fn with_panels<T: Element>(
    vector: VectorSide<'_, T>,
    w: Shared<'_, T>,
    panels: &[T],
    out: (&mut [T], Option<&[T]>),
) {
    let tiles = if vector.count() >= PAIRS_MIN_LINES {
        T::best_tiles()
    } else {
        Tiles::Single
    };
    with_panels_as(tiles, vector, w, panels, out);
}

/// The fewest vector lines for which a product takes the paired tiles: below it (a batch-1
/// U-Net, 16 columns) the AVX2 tiles were faster on an AVX-512 Xeon (the batch-1 forwards
/// about 40% slower with paired tiles in two rounds of three): short bursts of 512-bit
/// arithmetic between other work.
const PAIRS_MIN_LINES: usize = 64;

/// [`with_panels`] in the given tiling (the tests run both on any CPU).
fn with_panels_as<T: Element>(
    tiles: Tiles,
    vector: VectorSide<'_, T>,
    w: Shared<'_, T>,
    panels: &[T],
    (out, bias): (&mut [T], Option<&[T]>),
) {
    let (side, d, batch) = (vector.side, vector.d, vector.batch);
    let out = &mut out[..batch * d.m * d.n];
    if out.is_empty() {
        return;
    }
    if d.k == 0 {
        out.fill(T::ZERO);
        return;
    }
    // The scalar side's lines: the rows of `w` on the left, its columns on the right.
    let count = match side {
        Side::Left => d.m,
        Side::Right => d.n,
    };
    let packed;
    let scalars = match w {
        Shared::Panels(p) => &p[..count.div_ceil(WIDTH) * d.k * WIDTH],
        Shared::Plain { data, transposed } => {
            // Element (line l, depth kk) of the stored matrix.
            let (rows_are_lines, cols) = match side {
                Side::Left => (!transposed, if transposed { d.m } else { d.k }),
                Side::Right => (transposed, if transposed { d.k } else { d.n }),
            };
            packed = if rows_are_lines {
                pack(count, d.k, |l, kk| data[l * cols + kk])
            } else {
                pack(count, d.k, |l, kk| data[kk * cols + l])
            };
            &packed[..]
        }
    };
    let panels = &panels[..vector.count().div_ceil(LANES) * d.k * LANES];
    // An even number of panels per block, so that pairs never straddle two blocks.
    let per_block = (BLOCK_BYTES / (d.k * LANES * std::mem::size_of::<T>())).max(2) & !1;
    for (bi, block) in panels.chunks(per_block * d.k * LANES).enumerate() {
        let first = bi * per_block;
        let put = |p, c0, tile: &[[T; LANES]]| {
            vector.store(out, (first + p) * LANES, (c0, bias), tile);
        };
        match tiles {
            Tiles::Single => grid(block, scalars, (d.k, count), put),
            Tiles::Pairs => grid_pairs(block, scalars, (d.k, count), put),
        }
    }
}

/// How the register tiles cover the vector side: one panel ([`LANES`] lines) at a time, or
/// two neighbouring panels at once (`2 LANES` lines: one 512-bit register of f32). Both give
/// every element the same chain of fused multiply-adds, so the same bits; only the number
/// of instructions differs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Tiles {
    /// One panel per tile: 12 accumulators of one AVX2 (or NEON pair of) register(s).
    Single,
    /// Two panels per tile, for CPUs with AVX-512 (32 vector registers of 16 f32): twice the
    /// lanes per fused multiply-add, 12 accumulators of 16 lanes.
    Pairs,
}

/// The batch operand's lines.
#[derive(Clone, Copy, Debug)]
struct VectorSide<'a, T> {
    side: Side,
    x: &'a [T],
    d: Dims,
    batch: usize,
}

impl<T: Element> VectorSide<'_, T> {
    /// How many lines: every sample's columns (left) or rows (right).
    fn count(&self) -> usize {
        self.batch
            * match self.side {
                Side::Left => self.d.n,
                Side::Right => self.d.m,
            }
    }

    /// Where vector line `g`'s element `kk` sits in `x`: `base + kk · step`.
    fn line(&self, g: usize) -> (usize, usize) {
        let Dims { k, n, .. } = self.d;
        match self.side {
            // Column j of sample b: x[b K n + kk n + j].
            Side::Left => ((g / n) * k * n + g % n, n),
            // Row g of the stacked samples: x[g K + kk].
            Side::Right => (g * k, 1),
        }
    }

    /// Where vector line `g`'s output for scalar line `c` sits in `out`: `base + c · step`.
    fn output(&self, g: usize) -> (usize, usize) {
        let Dims { m, n, .. } = self.d;
        match self.side {
            Side::Left => ((g / n) * m * n + g % n, n),
            Side::Right => (g * n, 1),
        }
    }

    /// Panels of [`LANES`] lines, depth-major: panel `p`, depth `kk`, lane `r` at
    /// `[(p K + kk) LANES + r]`; lanes past the last line are zero.
    fn panels(&self) -> Vec<T> {
        let (k, count) = (self.d.k, self.count());
        let mut out = vec![T::ZERO; count.div_ceil(LANES) * k * LANES];
        for (p, panel) in out.chunks_mut(k * LANES).enumerate() {
            let lanes = (count - p * LANES).min(LANES);
            let lines: [(usize, usize); LANES] =
                std::array::from_fn(|r| self.line(p * LANES + r.min(lanes - 1)));
            let step = lines[0].1;
            // Eight neighbouring columns of one sample: one copy per depth.
            let adjacent =
                step > 1 && lanes == LANES && lines[LANES - 1].0 == lines[0].0 + LANES - 1;
            let (rows, _) = panel.as_chunks_mut::<LANES>();
            for (kk, dst) in rows.iter_mut().enumerate() {
                if adjacent {
                    // A fixed-size copy: inlined, where a slice copy calls `memmove`.
                    if let Some(src) = self.x[lines[0].0 + kk * step..].first_chunk::<LANES>() {
                        *dst = *src;
                    }
                } else {
                    for (d, &(base, step)) in dst.iter_mut().zip(&lines).take(lanes) {
                        *d = self.x[base + kk * step];
                    }
                }
            }
        }
        out
    }

    /// Writes a tile: lanes from vector line `g0`, columns from scalar line `c0`, each plus
    /// its scalar line's `bias`, if any.
    #[inline(always)]
    fn store(
        &self,
        out: &mut [T],
        g0: usize,
        (c0, bias): (usize, Option<&[T]>),
        tile: &[[T; LANES]],
    ) {
        let lanes = (self.count() - g0).min(LANES);
        let (base, step) = self.output(g0);
        // Eight neighbouring columns of one sample (left): each scalar line's eight outputs
        // are adjacent.
        if step > 1 && lanes == LANES && self.output(g0 + LANES - 1).0 == base + LANES - 1 {
            for (c, values) in tile.iter().enumerate() {
                let Some(dst) = out[base + (c0 + c) * step..].first_chunk_mut::<LANES>() else {
                    return;
                };
                for (d, &v) in dst.iter_mut().zip(values) {
                    *d = biased(v, bias, c0 + c);
                }
            }
            return;
        }
        for r in 0..lanes {
            let (base, step) = self.output(g0 + r);
            for (c, values) in tile.iter().enumerate() {
                out[base + (c0 + c) * step] = biased(values[r], bias, c0 + c);
            }
        }
    }
}

/// An output element `v` of scalar line `line` as stored: plus the line's bias if there is
/// one (one addition), else `v` itself (adding zero would turn -0 into +0).
#[inline(always)]
fn biased<T: Element>(v: T, bias: Option<&[T]>, line: usize) -> T {
    match bias {
        Some(b) => v + b[line],
        None => v,
    }
}

/// `$body` with `$w` the constant number of scalar lines a tile takes when `$left` lines are
/// still to do: [`WIDTH`], or `$left` itself below it (a tile's width is a const parameter).
// `by_width!` lists the widths below twelve.
const _: () = assert!(WIDTH == 12);

macro_rules! by_width {
    ($left:expr, $w:ident => $body:expr) => {
        by_width!(@arms $left, $w, $body; 11 10 9 8 7 6 5 4 3 2)
    };
    (@arms $left:expr, $w:ident, $body:expr; $($n:literal)*) => {
        match $left {
            l if l >= WIDTH => {
                const $w: usize = WIDTH;
                $body
            }
            $($n => {
                const $w: usize = $n;
                $body
            })*
            _ => {
                const $w: usize = 1;
                $body
            }
        }
    };
}

/// Every tile of one cache block: `panels` (vector panels, `k` deep) against every group of
/// [`WIDTH`] scalar lines in `scalars` (packed by [`pack`]; `count` lines); `put(p, c0,
/// tile)` receives panel `p`'s tile for the scalar lines from `c0`.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "aarch64+neon"))]
fn grid<T: Element, F: FnMut(usize, usize, &[[T; LANES]])>(
    panels: &[T],
    scalars: &[T],
    (k, count): (usize, usize),
    mut put: F,
) {
    for (q, group) in scalars.chunks(k * WIDTH).enumerate() {
        let c0 = q * WIDTH;
        for (p, panel) in panels.chunks(k * LANES).enumerate() {
            put_single(panel, group, count - c0, |t| put(p, c0, t));
        }
    }
}

/// [`grid`] with two neighbouring panels per register tile ([`Tiles::Pairs`]); a block's
/// odd last panel takes [`grid`]'s single tile. `put` receives each panel's half of a tile.
/// Compiled for AVX2, not AVX-512: the paired tile carries its own AVX-512 code
/// ([`Element::pair_tile`]), and LLVM's AVX-512 build of the single tile's loops used gathers
/// and scatters (7x slower at batch 1, where odd panels are common).
#[multiversion::multiversion(targets("x86_64+avx2+fma", "aarch64+neon"))]
fn grid_pairs<T: Element, F: FnMut(usize, usize, &[[T; LANES]])>(
    panels: &[T],
    scalars: &[T],
    (k, count): (usize, usize),
    mut put: F,
) {
    for (q, group) in scalars.chunks(k * WIDTH).enumerate() {
        let c0 = q * WIDTH;
        for (p2, pair) in panels.chunks(2 * k * LANES).enumerate() {
            let p = 2 * p2;
            if pair.len() < 2 * k * LANES {
                put_single(pair, group, count - c0, |t| put(p, c0, t));
                continue;
            }
            let (lo, hi) = pair.split_at(k * LANES);
            let mut put2 = |a: &[[T; LANES]], b: &[[T; LANES]]| {
                put(p, c0, a);
                put(p + 1, c0, b);
            };
            by_width!(count - c0, W => pair_into::<T, W>(lo, hi, group, &mut put2));
        }
    }
}

/// One panel's single tile for the `left` scalar lines still to do (at most [`WIDTH`]).
#[inline(always)]
fn put_single<T: Element>(panel: &[T], group: &[T], left: usize, put: impl FnOnce(&[[T; LANES]])) {
    by_width!(left, W => put(&tile::<T, W>(panel, group)));
}

/// A paired tile's two panels' tiles, `W` lines of [`LANES`] each.
pub(super) type PairTile<T, const W: usize> = ([[T; LANES]; W], [[T; LANES]; W]);

/// [`Element::pair_tile`] into `put`.
#[inline(always)]
fn pair_into<T: Element, const W: usize>(
    lo: &[T],
    hi: &[T],
    group: &[T],
    put: &mut impl FnMut(&[[T; LANES]], &[[T; LANES]]),
) {
    let (a, b) = T::pair_tile::<W>(lo, hi, group);
    put(&a, &b);
}

/// The paired register tile, portably: `W` scalar lines against the panels `lo` and `hi`,
/// each lane's chain [`tile`]'s (`acc[c][r] = fma(v[kk][r], s[kk][c], acc[c][r])` for `kk` in
/// order), as [`tile`] on each panel gives it.
#[inline(always)]
fn portable_pair<T: Element, const W: usize>(lo: &[T], hi: &[T], group: &[T]) -> PairTile<T, W> {
    (tile::<T, W>(lo, group), tile::<T, W>(hi, group))
}

/// The paired tile in AVX-512 registers: sixteen lanes (two panels) per fused multiply-add.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod wide {
    use super::{LANES, PairTile, WIDTH};
    use std::arch::x86_64::{
        __m512, _mm256_castps_pd, _mm256_loadu_ps, _mm512_castpd_ps, _mm512_castps_pd,
        _mm512_castps256_ps512, _mm512_fmadd_ps, _mm512_insertf64x4, _mm512_set1_ps,
        _mm512_setzero_ps, _mm512_storeu_ps,
    };

    /// Whether this CPU has AVX-512F (detected once, then a cached load).
    #[inline(always)]
    pub(super) fn available() -> bool {
        std::arch::is_x86_feature_detected!("avx512f")
    }

    /// [`super::portable_pair`] in AVX-512: the same fused multiply-adds in the same order
    /// (one rounding each, as `f32::mul_add`), so the same bits; `None` on a CPU without
    /// AVX-512F.
    #[inline(always)]
    pub(super) fn pair<const W: usize>(
        lo: &[f32],
        hi: &[f32],
        group: &[f32],
    ) -> Option<PairTile<f32, W>> {
        // SAFETY: AVX-512F (and the AVX it implies) is available, checked first.
        available().then(|| unsafe { pair_avx512::<W>(lo, hi, group) })
    }

    #[target_feature(enable = "avx512f")]
    fn pair_avx512<const W: usize>(lo: &[f32], hi: &[f32], group: &[f32]) -> PairTile<f32, W> {
        let mut acc: [__m512; W] = [_mm512_setzero_ps(); W];
        let (vl, _) = lo.as_chunks::<LANES>();
        let (vh, _) = hi.as_chunks::<LANES>();
        let (ss, _) = group.as_chunks::<WIDTH>();
        for ((a, b), sk) in vl.iter().zip(vh).zip(ss) {
            // SAFETY: `a` and `b` are arrays of eight f32: each load reads exactly one.
            let (a, b) = unsafe { (_mm256_loadu_ps(a.as_ptr()), _mm256_loadu_ps(b.as_ptr())) };
            let v = _mm512_castps_pd(_mm512_castps256_ps512(a));
            let v = _mm512_castpd_ps(_mm512_insertf64x4::<1>(v, _mm256_castps_pd(b)));
            for (c, acc) in acc.iter_mut().enumerate() {
                *acc = _mm512_fmadd_ps(v, _mm512_set1_ps(sk[c]), *acc);
            }
        }
        let mut out = ([[0f32; LANES]; W], [[0f32; LANES]; W]);
        for (c, acc) in acc.iter().enumerate() {
            let mut row = [0f32; 2 * LANES];
            // SAFETY: `row` holds sixteen f32, the store writes exactly those.
            unsafe { _mm512_storeu_ps(row.as_mut_ptr(), *acc) };
            out.0[c].copy_from_slice(&row[..LANES]);
            out.1[c].copy_from_slice(&row[LANES..]);
        }
        out
    }
}

/// The register tile: `W` scalar lines against one vector panel over the whole depth,
/// `acc[c][r] = fma(v[kk][r], s[kk][c], acc[c][r])` for `kk` in order.
#[inline(always)]
fn tile<T: Element, const W: usize>(panel: &[T], group: &[T]) -> [[T; LANES]; W] {
    let mut acc = [[T::ZERO; LANES]; W];
    let (vs, _) = panel.as_chunks::<LANES>();
    let (ss, _) = group.as_chunks::<WIDTH>();
    for (v, sk) in vs.iter().zip(ss) {
        for c in 0..W {
            let sv = sk[c];
            for r in 0..LANES {
                acc[c][r] = v[r].mul_add(sv, acc[c][r]);
            }
        }
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition, one element at a time, from row-major `a (m, k)` and `b (k, n)`.
    fn oracle<T: Element>(a: &[T], b: &[T], d: Dims) -> Vec<T> {
        let mut out = vec![T::ZERO; d.m * d.n];
        for i in 0..d.m {
            for j in 0..d.n {
                let mut acc = T::ZERO;
                for kk in 0..d.k {
                    acc = a[i * d.k + kk].mul_add(b[kk * d.n + j], acc);
                }
                out[i * d.n + j] = acc;
            }
        }
        out
    }

    /// `len` values in [-1, 1) from the kernels' shared test fill, as f32.
    fn fill(len: usize, seed: u64) -> Vec<f32> {
        let values = crate::kernels::test_util::rand(&[len], seed).to_vec1::<f64>();
        values.expect("fill").iter().map(|&v| v as f32).collect()
    }

    /// `(r, c)` row-major → its transpose, row-major.
    fn transpose(x: &[f32], r: usize, c: usize) -> Vec<f32> {
        (0..c)
            .flat_map(|j| (0..r).map(move |i| x[i * c + j]))
            .collect()
    }

    /// [`products`] in the tiling `tiles`, whatever this CPU's best.
    fn products_as<T: Element>(
        tiles: Tiles,
        side: Side,
        w: Shared<'_, T>,
        x: &[T],
        d: Dims,
        batch: usize,
        out: &mut [T],
    ) {
        let vector = VectorSide { side, x, d, batch };
        with_panels_as(tiles, vector, w, &vector.panels(), (out, None));
    }

    /// Both sides; tall and wide outputs, every tail of both tile sides (lanes across sample
    /// boundaries), a depth of one, blocks of several cache blocks, odd panel counts (a
    /// paired tiling's single last panel); the shared matrix stored plain and transposed;
    /// both tilings: each sample's result is the definition's, bit for bit.
    #[test]
    fn every_element_is_the_definition_bit_for_bit() {
        for tiles in [Tiles::Single, Tiles::Pairs] {
            definition_bit_for_bit(tiles);
        }
    }

    fn definition_bit_for_bit(tiles: Tiles) {
        let shapes = [
            (1, 1, 1, 1),
            (6, 7, 16, 3),
            (13, 33, 29, 2),
            (5, 1, 45, 4),
            (1, 40, 37, 3),
            (37, 40, 1, 3),
            (64, 320, 16, 9),
            (17, 9, 4, 2),
            (30, 1300, 16, 9),
            (3, 7000, 8, 3),
        ];
        for (m, k, n, batch) in shapes {
            let d = Dims { m, k, n };
            for side in [Side::Left, Side::Right] {
                let (wr, wc, xr, xc) = match side {
                    Side::Left => (m, k, k, n),
                    Side::Right => (k, n, m, k),
                };
                let (w, x) = (fill(wr * wc, 1), fill(batch * xr * xc, 2));
                for transposed in [false, true] {
                    let stored = if transposed {
                        transpose(&w, wr, wc)
                    } else {
                        w.clone()
                    };
                    let shared = Shared::Plain {
                        data: &stored,
                        transposed,
                    };
                    let mut out = vec![f32::NAN; batch * m * n];
                    products_as(tiles, side, shared, &x, d, batch, &mut out);
                    if matches!(side, Side::Left) {
                        // A weight packed once gives the same bits.
                        let panels = left_panels(&w, m, k);
                        let mut again = vec![f32::NAN; batch * m * n];
                        let packed = Shared::Panels(&panels);
                        products_as(tiles, side, packed, &x, d, batch, &mut again);
                        assert!(
                            again
                                .iter()
                                .zip(&out)
                                .all(|(a, b)| a.to_bits() == b.to_bits())
                        );
                    }
                    for s in 0..batch {
                        let x_b = &x[s * xr * xc..][..xr * xc];
                        let want = match side {
                            Side::Left => oracle(&w, x_b, d),
                            Side::Right => oracle(x_b, &w, d),
                        };
                        let got = &out[s * m * n..][..m * n];
                        let same = got
                            .iter()
                            .zip(&want)
                            .all(|(g, w)| g.to_bits() == w.to_bits());
                        assert!(
                            same,
                            "{m}x{k}x{n}, {side:?}, transposed {transposed}, sample {s}, {tiles:?}"
                        );
                    }
                }
            }
        }
    }

    /// The values are the product (against float64, to float32 rounding of a sum of `k`
    /// terms in [-1, 1]), in f32 and in f64.
    #[test]
    fn it_is_the_product() {
        let d = Dims { m: 9, k: 70, n: 21 };
        let (a, b) = (fill(d.m * d.k, 3), fill(d.k * d.n, 4));
        let plain = |data| Shared::Plain {
            data,
            transposed: false,
        };
        let mut out = vec![0f32; d.m * d.n];
        products(Side::Left, plain(&a), &b, d, 1, &mut out);
        let a64: Vec<f64> = a.iter().map(|&v| f64::from(v)).collect();
        let b64: Vec<f64> = b.iter().map(|&v| f64::from(v)).collect();
        let mut out64 = vec![0f64; d.m * d.n];
        let plain64 = |data| Shared::Plain {
            data,
            transposed: false,
        };
        products(
            Side::Right,
            plain64(&b64),
            &a64,
            Dims {
                m: d.m,
                k: d.k,
                n: d.n,
            },
            1,
            &mut out64,
        );
        for i in 0..d.m {
            for j in 0..d.n {
                let want: f64 = (0..d.k)
                    .map(|kk| a64[i * d.k + kk] * b64[kk * d.n + j])
                    .sum();
                let got = f64::from(out[i * d.n + j]);
                assert!((got - want).abs() < 1e-5 * d.k as f64, "{got} vs {want}");
                assert!((out64[i * d.n + j] - want).abs() < 1e-12, "f64");
            }
        }
    }
}
