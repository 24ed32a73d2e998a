//! 2-D convolution as im2col + one matrix product, with a backward pass (col2im) that
//! candle's CPU backend lacks in a fast form.
//!
//! candle 0.9's CPU `conv2d` backward goes through `conv_transpose2d`, a direct loop, and a
//! kernel-gradient convolution whose "kernel" is the whole gradient map; on the image
//! encoder that made a training step ~10x slower than its matrix products need
//! (measured: 3.6 s per batch-64 step of the width-16 encoder). Here the convolution is
//! `im2col(x) · Wᵀ`: the gather `im2col` is a custom op whose backward is the scatter-add
//! `col2im`, and everything else is candle's `matmul`, whose backward is again a matmul.
//! On non-CPU devices [`conv2d`] calls candle's own convolution (CUDA has fast kernels).
//!
//! Conventions: input `(B, C, H, W)`, weight `(C_out, C, k_h, k_w)`, zero padding, no
//! dilation or groups (ResNet needs none); column index `c · k_h k_w + k_y · k_w + k_x`, the
//! order of the weight's last three axes, so `W.reshape(C_out, C k_h k_w)` multiplies it.

use super::contiguous;
use candle_core::WithDType;
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

/// Geometry of one convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Geom {
    c: usize,
    h: usize,
    w: usize,
    kh: usize,
    kw: usize,
    stride: usize,
    pad: usize,
}

impl Geom {
    fn out_hw(&self) -> (usize, usize) {
        (
            (self.h + 2 * self.pad - self.kh) / self.stride + 1,
            (self.w + 2 * self.pad - self.kw) / self.stride + 1,
        )
    }

    fn ckk(&self) -> usize {
        self.c * self.kh * self.kw
    }

    #[cfg(test)]
    /// For output pixel (oy, ox) and column `col`, the input offset within one image, if the
    /// tap falls inside (else it reads the zero padding).
    #[inline]
    fn visit(&self, oy: usize, ox: usize, mut f: impl FnMut(usize, usize)) {
        let kk = self.kh * self.kw;
        for ci in 0..self.c {
            for ky in 0..self.kh {
                let iy = (oy * self.stride + ky) as isize - self.pad as isize;
                if iy < 0 || iy >= self.h as isize {
                    continue;
                }
                for kx in 0..self.kw {
                    let ix = (ox * self.stride + kx) as isize - self.pad as isize;
                    if ix < 0 || ix >= self.w as isize {
                        continue;
                    }
                    f(
                        ci * kk + ky * self.kw + kx,
                        (ci * self.h + iy as usize) * self.w + ix as usize,
                    );
                }
            }
        }
    }
}

/// The output positions `o` in `0..n_out` whose tap `k` reads inside the input, i.e. with
/// `0 <= o·stride + k - pad < n_in`, as a range.
pub(super) fn taps_inside(
    k: usize,
    pad: usize,
    stride: usize,
    n_in: usize,
    n_out: usize,
) -> (usize, usize) {
    let lo = pad.saturating_sub(k).div_ceil(stride);
    let hi = (n_in + pad).saturating_sub(k).div_ceil(stride);
    (lo.min(n_out), hi.min(n_out).max(lo.min(n_out)))
}

/// `(B, C, H, W)` → `(B, L, C k_h k_w)` columns (zero where a tap reads the padding).
fn im2col<T: Copy + Default + Send + Sync>(x: &[T], b: usize, g: Geom) -> Vec<T> {
    let (ho, wo) = g.out_hw();
    let (l, ckk, img, kk) = (ho * wo, g.ckk(), g.c * g.h * g.w, g.kh * g.kw);
    let mut out = vec![T::default(); b * l * ckk];
    out.par_chunks_mut(l * ckk)
        .zip(x.par_chunks(img))
        .for_each(|(cols, src)| {
            for oy in 0..ho {
                for ox in 0..wo {
                    let row = &mut cols[(oy * wo + ox) * ckk..][..ckk];
                    // The kernel columns kx whose input column ox·s + kx - pad is inside.
                    let x0 = ox * g.stride;
                    let kx_lo = g.pad.saturating_sub(x0);
                    let kx_hi = g.kw.min((g.w + g.pad).saturating_sub(x0));
                    if kx_lo >= kx_hi {
                        continue;
                    }
                    let ix_lo = x0 + kx_lo - g.pad;
                    let n = kx_hi - kx_lo;
                    for ky in 0..g.kh {
                        let iy = oy * g.stride + ky;
                        if iy < g.pad || iy - g.pad >= g.h {
                            continue;
                        }
                        let iy = iy - g.pad;
                        for ci in 0..g.c {
                            let at = (ci * g.h + iy) * g.w + ix_lo;
                            let col = ci * kk + ky * g.kw + kx_lo;
                            row[col..col + n].copy_from_slice(&src[at..at + n]);
                        }
                    }
                }
            }
        });
    out
}

/// `(B, C, H, W)` → `(B, C k_h k_w, L)`: [`im2col`]'s columns transposed, each column's
/// taps along the output positions (the layout the constant-weight convolution multiplies;
/// it packs them straight from the input, [`column_panels`], and the tests check the two
/// against each other).
#[cfg(test)]
fn im2col_t<T: Copy + Default + Send + Sync>(x: &[T], b: usize, g: Geom) -> Vec<T> {
    let (ho, wo) = g.out_hw();
    let (l, ckk, img, kk) = (ho * wo, g.ckk(), g.c * g.h * g.w, g.kh * g.kw);
    let mut out = vec![T::default(); b * ckk * l];
    out.par_chunks_mut(ckk * l)
        .zip(x.par_chunks(img))
        .for_each(|(cols, src)| {
            for ci in 0..g.c {
                for ky in 0..g.kh {
                    let (oy_lo, oy_hi) = taps_inside(ky, g.pad, g.stride, g.h, ho);
                    for kx in 0..g.kw {
                        let (ox_lo, ox_hi) = taps_inside(kx, g.pad, g.stride, g.w, wo);
                        let row = &mut cols[(ci * kk + ky * g.kw + kx) * l..][..l];
                        for oy in oy_lo..oy_hi {
                            let iy = oy * g.stride + ky - g.pad;
                            let srow = &src[(ci * g.h + iy) * g.w..][..g.w];
                            let drow = &mut row[oy * wo..][..wo];
                            if g.stride == 1 {
                                drow[ox_lo..ox_hi]
                                    .copy_from_slice(&srow[ox_lo + kx - g.pad..ox_hi + kx - g.pad]);
                            } else {
                                for (ox, d) in drow.iter_mut().enumerate().take(ox_hi).skip(ox_lo) {
                                    *d = srow[ox * g.stride + kx - g.pad];
                                }
                            }
                        }
                    }
                }
            }
        });
    out
}

/// `(B, C, H, W)` → the transposed columns `(B, C k_h k_w, L)` packed straight into
/// `kernels::product`'s vector panels, with no im2col copy: lane `r` of panel `p` is output
/// position `g = 8 p + r` of the batch (`g = b L + oy W_out + ox`), depth `(c, k_y, k_x)`
/// reads input `(c, oy · s + k_y - pad, ox · s + k_x - pad)`, zero outside. The input is
/// first copied with its zero padding, so every tap is a plain read; at stride 1, eight
/// positions in one output row read eight adjacent inputs. Lanes past the batch's last
/// position stay zero.
fn column_panels<T: Copy + Default + Send + Sync>(x: &[T], b: usize, g: Geom) -> Vec<T> {
    const LANES: usize = super::product::LANES;
    let (ho, wo) = g.out_hw();
    let (l, ckk) = (ho * wo, g.ckk());
    let (hp, wp) = (g.h + 2 * g.pad, g.w + 2 * g.pad);
    let padded = zero_padded(x, b * g.c, g);
    let count = b * l;
    let mut out = vec![T::default(); count.div_ceil(LANES) * ckk * LANES];
    out.par_chunks_mut(ckk * LANES)
        .enumerate()
        .for_each(|(p, panel)| {
            let g0 = p * LANES;
            let lanes = (count - g0).min(LANES);
            // Each lane's first padded input (channel 0, tap (0, 0)).
            let lane: [usize; LANES] = std::array::from_fn(|r| {
                let gl = g0 + r.min(lanes - 1);
                let (img, pos) = (gl / l, gl % l);
                img * g.c * hp * wp + (pos / wo) * g.stride * wp + (pos % wo) * g.stride
            });
            let one_run = g.stride == 1 && lanes == LANES && lane[LANES - 1] == lane[0] + LANES - 1;
            let (rows, _) = panel.as_chunks_mut::<LANES>();
            // Depth (c, k_y, k_x) in order: one row of `k_x` taps per input row read.
            for (r, dst) in rows.chunks_exact_mut(g.kw).enumerate() {
                let at = (r / g.kh) * hp * wp + (r % g.kh) * wp;
                if one_run {
                    let src = &padded[lane[0] + at..][..g.kw + LANES - 1];
                    for (kx, d) in dst.iter_mut().enumerate() {
                        if let Some(s) = src[kx..].first_chunk::<LANES>() {
                            *d = *s;
                        }
                    }
                } else {
                    // Each lane's `k_x` taps are adjacent in the padded input: one checked
                    // slice per lane, not one index per tap.
                    for (r, &base) in lane.iter().enumerate().take(lanes) {
                        for (d, &s) in dst.iter_mut().zip(&padded[base + at..][..g.kw]) {
                            d[r] = s;
                        }
                    }
                }
            }
        });
    out
}

/// The `planes` planes `(H, W)` of `x` with `pad` zeros on every side.
fn zero_padded<T: Copy + Default + Send + Sync>(x: &[T], planes: usize, g: Geom) -> Vec<T> {
    let (hp, wp) = (g.h + 2 * g.pad, g.w + 2 * g.pad);
    let mut padded = vec![T::default(); planes * hp * wp];
    for (dst, src) in padded
        .chunks_exact_mut(hp * wp)
        .zip(x.chunks_exact(g.h * g.w))
    {
        for (drow, srow) in dst[g.pad * wp..]
            .chunks_exact_mut(wp)
            .zip(src.chunks_exact(g.w))
        {
            drow[g.pad..g.pad + g.w].copy_from_slice(srow);
        }
    }
    padded
}

/// `(B, L, C k_h k_w)` → `(B, C, H, W)`, summing overlapping taps (im2col's adjoint).
///
/// Each input element starts at zero and adds its taps in the order of their output
/// positions `(oy, ox)`; that is the order a walk over the output positions gives, and it is
/// kept here (for a fixed input element, a larger `ky` means a smaller `oy`, so the taps are
/// walked with `ky` and `kx` descending), so the sums are the same bits whichever walk is
/// used. The columns are first transposed to `(C k_h k_w, L)`, so that the inner loop runs
/// along an output row on both sides.
fn col2im<T>(cols: &[T], b: usize, g: Geom) -> Vec<T>
where
    T: Copy + Default + Send + Sync + std::ops::AddAssign,
{
    let (ho, wo) = g.out_hw();
    let (l, ckk, img) = (ho * wo, g.ckk(), g.c * g.h * g.w);
    let mut out = vec![T::default(); b * img];
    out.par_chunks_mut(img)
        .zip(cols.par_chunks(l * ckk))
        .for_each(|(dst, src)| {
            // Transposed in blocks of 16 output positions, so that both sides stay in cache.
            let mut t = vec![T::default(); l * ckk];
            for p0 in (0..l).step_by(16) {
                let rows = &src[p0 * ckk..(p0 + 16).min(l) * ckk];
                for col in 0..ckk {
                    let dst = &mut t[col * l + p0..];
                    for (d, row) in dst.iter_mut().zip(rows.chunks_exact(ckk)) {
                        *d = row[col];
                    }
                }
            }
            col2im_image(&t, dst, g);
        });
    out
}

/// One image's columns, transposed `(C k_h k_w, L)`, summed into its input gradient `dst (C,
/// H, W)` in [`col2im`]'s order.
fn col2im_image<T: Copy + std::ops::AddAssign>(t: &[T], dst: &mut [T], g: Geom) {
    let (ho, wo) = g.out_hw();
    let (l, kk) = (ho * wo, g.kh * g.kw);
    for ci in 0..g.c {
        for ky in (0..g.kh).rev() {
            let (oy_lo, oy_hi) = taps_inside(ky, g.pad, g.stride, g.h, ho);
            for kx in (0..g.kw).rev() {
                let (ox_lo, ox_hi) = taps_inside(kx, g.pad, g.stride, g.w, wo);
                let taps = &t[(ci * kk + ky * g.kw + kx) * l..][..l];
                for oy in oy_lo..oy_hi {
                    let iy = oy * g.stride + ky - g.pad;
                    let drow = &mut dst[(ci * g.h + iy) * g.w..][..g.w];
                    let trow = &taps[oy * wo..][..wo];
                    if g.stride == 1 {
                        let d = &mut drow[ox_lo + kx - g.pad..ox_hi + kx - g.pad];
                        for (a, &v) in d.iter_mut().zip(&trow[ox_lo..ox_hi]) {
                            *a += v;
                        }
                    } else if ox_lo < ox_hi {
                        // Every `stride`-th input from the first tap inside: the first of
                        // each run of `stride` (a plain slice walk; `step_by` was slower).
                        let d = drow[ox_lo * g.stride + kx - g.pad..].chunks_mut(g.stride);
                        for (a, &v) in d.zip(&trow[ox_lo..ox_hi]) {
                            a[0] += v;
                        }
                    }
                }
            }
        }
    }
}

/// `(B, C k_h k_w, L)` → `(B, C, H, W)`: [`col2im`] of columns already transposed, one
/// [`col2im_image`] per image as [`ConvInputGrad`] calls it (the tests check it against
/// [`col2im`]).
#[cfg(test)]
fn col2im_t<T>(cols: &[T], b: usize, g: Geom) -> Vec<T>
where
    T: Copy + Default + Send + Sync + std::ops::AddAssign,
{
    let (ho, wo) = g.out_hw();
    let (l, ckk, img) = (ho * wo, g.ckk(), g.c * g.h * g.w);
    let mut out = vec![T::default(); b * img];
    out.par_chunks_mut(img)
        .zip(cols.par_chunks(l * ckk))
        .for_each(|(dst, src)| col2im_image(src, dst, g));
    out
}

/// `(B, C, H, W)` → `(B, H_out · W_out, C k_h k_w)`; backward: [`Col2Im`].
#[derive(Clone, Copy, Debug)]
struct Im2Col(Geom);

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "mte-im2col"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let b = layout.dims()[0];
        let (ho, wo) = g.out_hw();
        let shape = Shape::from((b, ho * wo, g.ckk()));
        let out = float_storages!("im2col", [(v, storage, layout)], im2col(v, b, g));
        Ok((out, shape))
    }

    fn bwd(&self, _arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(
            grad_res.contiguous()?.apply_op1_no_bwd(&Col2Im(self.0))?,
        ))
    }
}

/// Columns `(B, L, C k_h k_w)` as [`im2col`] makes them → `(B, C, H, W)`, summing
/// overlapping taps (im2col's adjoint).
#[derive(Clone, Copy, Debug)]
struct Col2Im(Geom);

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "mte-col2im"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let b = layout.dims()[0];
        let shape = Shape::from((b, g.c, g.h, g.w));
        let out = float_storages!("col2im", [(v, storage, layout)], col2im(v, b, g));
        Ok((out, shape))
    }
}

/// The per-image convolution of [`conv2d`] for a constant weight, as one graph node: the
/// transposed im2col `(C k_h k_w, L)` and each image's product `W · cols` straight into `(B,
/// C_out, H_out W_out)` in one forward, and the input's gradient (`Wᵀ · g`, then col2im) in
/// one backward. The composed path (im2col, reshape, per-sample product `cols · Wᵀ`,
/// transpose, copy) gives the same bits: `kernels::product` defines each element as the same
/// chain of fused multiply-adds whichever side the weight is on. What is saved is the
/// transposes and the backward pass's zero-filled gradient buffer and addition for each of the
/// five intermediate nodes (two of them of the columns' size, `k_h k_w` times the input's).
/// The weight gets no gradient: it is used only when it is not tracked.
#[derive(Clone, Copy, Debug)]
struct ConstantWeightConv(Geom);

impl ConstantWeightConv {
    /// The stored weight `(C_out, C k k)` times each image's transposed columns `(C k k, L)`,
    /// packed straight from the input ([`column_panels`]) and multiplied as
    /// [`super::batch`]'s per-sample product multiplies them (the same element definition):
    /// the output comes out as `(C_out, L)`, the convolution's own layout.
    fn forward<T>(&self, x: &[T], b: usize, w: &CpuStorage, lw: &Layout) -> Result<CpuStorage>
    where
        T: candle_core::WithDType + Default + super::product::Element,
    {
        let g = self.0;
        let (ho, wo) = g.out_hw();
        let dims = super::product::Dims {
            m: lw.dims()[0],
            k: g.ckk(),
            n: ho * wo,
        };
        let w = contiguous(w.as_slice::<T>()?, lw)?;
        if w.len() != dims.m * dims.k {
            candle_core::bail!(
                "conv2d: a weight of {} values, expected {} x {}",
                w.len(),
                dims.m,
                dims.k
            );
        }
        let packed = super::product::left_panels(w, dims.m, dims.k);
        let w = super::product::Shared::Panels(&packed);
        let mut y = vec![T::default(); b * dims.m * dims.n];
        let img = g.c * g.h * g.w;
        let per = images_per_chunk::<T>(dims.k * dims.n);
        for (xs, ys) in x[..b * img]
            .chunks(per * img)
            .zip(y.chunks_mut(per * dims.m * dims.n))
        {
            let nb = xs.len() / img;
            let panels = column_panels(xs, nb, g);
            super::product::left_products_packed(w, &panels, dims, nb, (ys, None));
        }
        Ok(T::to_cpu_storage_owned(y))
    }
}

/// Images per slice of a batch whose per-image working buffer holds `per_image` values:
/// enough to fill [`CHUNK_BYTES`], at least one. The products define every element alone
/// (`kernels::product`), so slicing a batch changes no bit; it keeps the columns' buffers
/// small enough for the heap to reuse (glibc serves requests above 32 MiB with fresh `mmap`s,
/// whose pages are faulted in and zeroed on every call) and warm in the cache.
fn images_per_chunk<T>(per_image: usize) -> usize {
    (CHUNK_BYTES / (per_image * std::mem::size_of::<T>()).max(1)).max(1)
}

/// The size a batch's column buffers are sliced to ([`images_per_chunk`]).
const CHUNK_BYTES: usize = 8 << 20;

/// The input's gradient of [`ConstantWeightConv`]: `dx_b = col2im(Wᵀ · g_b)` for each image
/// `b` of `grad (B, C_out, L)`, with `w (C_out, C k k)`, computed a slice of images at a time
/// ([`images_per_chunk`]) so that the columns' gradient never exists for the whole batch.
/// Each product is [`super::batch::PerSampleProduct`]'s (weight transposed, on the left) and
/// each image's col2im is [`col2im_image`], so the bits are theirs.
#[derive(Clone, Copy, Debug)]
struct ConvInputGrad(Geom);

impl ConvInputGrad {
    /// `grad` holds `b` images of `(co, L)`.
    fn backward<T>(&self, grad: &[T], (b, co): (usize, usize), w: &[T]) -> Result<Vec<T>>
    where
        T: Copy + Default + std::ops::AddAssign + super::product::Element,
    {
        let g = self.0;
        let (ho, wo) = g.out_hw();
        let (l, ckk, img) = (ho * wo, g.ckk(), g.c * g.h * g.w);
        if w.len() != co * ckk || grad.len() != b * co * l {
            candle_core::bail!(
                "conv2d backward: a weight of {} values and a gradient of {}, expected ({co}, {ckk}) and {b} images of ({co}, {l})",
                w.len(),
                grad.len()
            );
        }
        let dims = super::product::Dims {
            m: ckk,
            k: co,
            n: l,
        };
        let weight = super::product::Shared::Plain {
            data: w,
            transposed: true,
        };
        let per = images_per_chunk::<T>(ckk * l);
        let mut out = vec![T::default(); b * img];
        let mut dcols = vec![T::ZERO; per.min(b) * ckk * l];
        for (gs, os) in grad.chunks(per * co * l).zip(out.chunks_mut(per * img)) {
            let nb = gs.len() / (co * l);
            let dc = &mut dcols[..nb * ckk * l];
            super::product::products(super::batch::Side::Left, weight, gs, dims, nb, dc);
            for (src, dst) in dc.chunks(ckk * l).zip(os.chunks_mut(img)) {
                col2im_image(src, dst, g);
            }
        }
        Ok(out)
    }
}

impl CustomOp2 for ConvInputGrad {
    fn name(&self) -> &'static str {
        "mte-conv2d-input-grad"
    }

    fn cpu_fwd(
        &self,
        sg: &CpuStorage,
        lg: &Layout,
        sw: &CpuStorage,
        lw: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let &[b, co, _] = lg.dims() else {
            candle_core::bail!(
                "conv2d backward: a gradient of shape {:?}, expected (B, C_out, L)",
                lg.dims()
            );
        };
        let out =
            match (sg, sw) {
                (CpuStorage::F32(v), CpuStorage::F32(w)) => f32::to_cpu_storage_owned(
                    self.backward(contiguous(v, lg)?, (b, co), contiguous(w, lw)?)?,
                ),
                (CpuStorage::F64(v), CpuStorage::F64(w)) => f64::to_cpu_storage_owned(
                    self.backward(contiguous(v, lg)?, (b, co), contiguous(w, lw)?)?,
                ),
                _ => candle_core::bail!(
                    "conv2d backward: unsupported dtypes {:?} x {:?}",
                    sg.dtype(),
                    sw.dtype()
                ),
            };
        Ok((out, Shape::from((b, g.c, g.h, g.w))))
    }
}

impl CustomOp2 for ConstantWeightConv {
    fn name(&self) -> &'static str {
        "mte-constant-weight-conv2d"
    }

    fn cpu_fwd(
        &self,
        sx: &CpuStorage,
        lx: &Layout,
        sw: &CpuStorage,
        lw: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let b = lx.dims()[0];
        let co = lw.dims()[0];
        let (ho, wo) = g.out_hw();
        let out = match (sx, sw) {
            (CpuStorage::F32(v), CpuStorage::F32(_)) => {
                self.forward(contiguous(v, lx)?, b, sw, lw)?
            }
            (CpuStorage::F64(v), CpuStorage::F64(_)) => {
                self.forward(contiguous(v, lx)?, b, sw, lw)?
            }
            _ => candle_core::bail!(
                "conv2d: unsupported dtypes {:?} x {:?}",
                sx.dtype(),
                sw.dtype()
            ),
        };
        Ok((out, Shape::from((b, co, ho, wo))))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let g = self.0;
        let (b, co, ho, wo) = grad.dims4()?;
        // Wᵀ (C k k, C_out) times each image's gradient (C_out, L), then col2im.
        let grad = grad.reshape((b, co, ho * wo))?.contiguous()?;
        let w = w.reshape((co, g.ckk()))?.contiguous()?;
        Ok((Some(grad.apply_op2_no_bwd(&w, &ConvInputGrad(g))?), None))
    }
}

/// Convolution of `x (B, C, H, W)` with `weight (C_out, C, k_h, k_w)`, zero padding `pad`,
/// stride `stride`: im2col + matmul on the CPU (one product per image, or one for the batch:
/// `products`), candle's `conv2d` elsewhere.
pub fn conv2d(
    x: &Tensor,
    weight: &Tensor,
    stride: usize,
    pad: usize,
    products: super::Products,
) -> Result<Tensor> {
    if !x.device().is_cpu() {
        return x.conv2d(weight, pad, stride, 1, 1);
    }
    let (b, c, h, w) = x.dims4()?;
    let (co, ci, kh, kw) = weight.dims4()?;
    if ci != c || stride == 0 || h + 2 * pad < kh || w + 2 * pad < kw {
        candle_core::bail!(
            "conv2d: input (B, {c}, {h}, {w}) does not fit weight ({co}, {ci}, {kh}, {kw}) with stride {stride}, padding {pad}"
        );
    }
    let g = Geom {
        c,
        h,
        w,
        kh,
        kw,
        stride,
        pad,
    };
    if products == super::Products::PerSample && !weight.track_op() {
        // Constant weights (a loaded checkpoint under evaluation or attack): one node.
        return x
            .contiguous()?
            .apply_op2(&weight.contiguous()?, ConstantWeightConv(g));
    }
    let (ho, wo) = g.out_hw();
    let cols = x.contiguous()?.apply_op1(Im2Col(g))?;
    // (H_out W_out, C k k) x (C k k, C_out) per image, or for the batch at once.
    let y = super::right_shared(
        &cols.reshape((b, ho * wo, g.ckk()))?,
        &weight.reshape((co, g.ckk()))?.t()?,
        products,
    )?;
    y.transpose(1, 2)?.contiguous()?.reshape((b, co, ho, wo))
}

/// A convolution layer with candle_nn's parameter names (`weight`, optional `bias`) whose
/// forward is [`conv2d`].
#[derive(Clone, Debug)]
pub struct Conv2d {
    weight: Tensor,
    bias: Option<Tensor>,
    stride: usize,
    pad: usize,
}

impl Conv2d {
    /// Load/create a `k x k` convolution `cin -> cout` under `vb` (candle_nn's initialisation).
    pub fn new(
        cin: usize,
        cout: usize,
        k: usize,
        stride: usize,
        pad: usize,
        bias: bool,
        vb: VarBuilder,
    ) -> Result<Self> {
        let cfg = candle_nn::Conv2dConfig {
            padding: pad,
            stride,
            ..Default::default()
        };
        let inner = if bias {
            candle_nn::conv2d(cin, cout, k, cfg, vb)?
        } else {
            candle_nn::conv2d_no_bias(cin, cout, k, cfg, vb)?
        };
        Ok(Conv2d {
            weight: inner.weight().clone(),
            bias: inner.bias().cloned(),
            stride,
            pad,
        })
    }
}

impl Conv2d {
    /// `(B, C, H, W)` -> `(B, C_out, H_out, W_out)`.
    pub fn forward(&self, x: &Tensor, products: super::Products) -> Result<Tensor> {
        let y = conv2d(x, &self.weight, self.stride, self.pad, products)?;
        match &self.bias {
            Some(b) => y.broadcast_add(&b.reshape((1, b.dim(0)?, 1, 1))?),
            None => Ok(y),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::{bits, probe_gradient, rand};
    use candle_core::{DType, Device, Var};

    const CASES: [(usize, usize, usize, usize, usize, usize); 5] = [
        // (C, H, W, k, stride, pad): the ResNet stem, 3x3 blocks, strided 3x3, 1x1 downsample,
        // an odd size with no padding.
        (3, 20, 18, 7, 2, 3),
        (4, 9, 9, 3, 1, 1),
        (4, 9, 8, 3, 2, 1),
        (4, 9, 9, 1, 2, 0),
        (2, 7, 5, 2, 1, 0),
    ];

    /// Values agree with candle's direct convolution (f64: any difference beyond summation
    /// order, ~1e-15 here, is a wrong tap).
    #[test]
    fn matches_candles_conv2d() -> Result<()> {
        for (i, &(c, h, w, k, s, p)) in CASES.iter().enumerate() {
            let x = rand(&[2, c, h, w], i as u64);
            let wt = rand(&[3, c, k, k], 100 + i as u64);
            let ours = conv2d(&x, &wt, s, p, super::super::Products::PerSample)?;
            let fused = conv2d(&x, &wt, s, p, super::super::Products::Fused)?;
            let d = crate::kernels::test_util::max_diff(&ours, &fused);
            assert!(d < 1e-9, "fused and per-image agree in f64: {d}");
            let theirs = x.conv2d(&wt, p, s, 1, 1)?;
            assert_eq!(ours.dims(), theirs.dims(), "case {i}");
            let err = (ours - theirs)?.abs()?.max_all()?.to_scalar::<f64>()?;
            assert!(err < 1e-12, "case {i}: max |diff| {err}");
        }
        Ok(())
    }

    /// Gradients with respect to input and weight: against candle's backward pass, and
    /// against central differences on every case. The probe `sum(r ⊙ conv(x, w))` is linear
    /// in each argument, so a central difference is exact up to rounding whatever the step:
    /// a 1e-3 step keeps cancellation near 1e-12, under the 1e-8 bound. candle's own backward mis-sizes the input
    /// gradient when an odd width meets stride 2 (case 2: "shape mismatch in add"), so that
    /// case is checked by differences only.
    #[test]
    fn gradients_match_candle_and_finite_differences() -> Result<()> {
        for (i, &(c, h, w, k, s, p)) in CASES.iter().enumerate() {
            let x = Var::from_tensor(&rand(&[2, c, h, w], 7 + i as u64))?;
            let wt = Var::from_tensor(&rand(&[3, c, k, k], 200 + i as u64))?;
            let (ho, wo) = ((h + 2 * p - k) / s + 1, (w + 2 * p - k) / s + 1);
            // A non-uniform upstream gradient, so a transposed or shifted tap shows up.
            let r = rand(&[2, 3, ho, wo], 300 + i as u64);
            let probe = |x: &Tensor, wt: &Tensor| {
                (conv2d(x, wt, s, p, super::super::Products::Fused)? * &r)?.sum_all()
            };
            let ours = probe(x.as_tensor(), wt.as_tensor())?.backward()?;
            if i != 2 {
                let y = x.as_tensor().conv2d(wt.as_tensor(), p, s, 1, 1)?;
                let theirs = (y * &r)?.sum_all()?.backward()?;
                for v in [&x, &wt] {
                    let a = ours.get(v.as_tensor()).expect("ours has a gradient");
                    let b = theirs.get(v.as_tensor()).expect("candle's has a gradient");
                    let err = (a - b)?.abs()?.max_all()?.to_scalar::<f64>()?;
                    assert!(err < 1e-12, "case {i}: gradient max |diff| {err}");
                }
            }
            for (which, v) in [&x, &wt].into_iter().enumerate() {
                let g = ours.get(v.as_tensor()).expect("gradient").flatten_all()?;
                let g = g.to_vec1::<f64>()?;
                let base = v.as_tensor().flatten_all()?.to_vec1::<f64>()?;
                for j in (0..base.len()).step_by(base.len() / 7 + 1) {
                    let eps = 1e-3;
                    let at = |d: f64| -> Result<f64> {
                        let mut b = base.clone();
                        b[j] += d;
                        let t = Tensor::from_vec(b, v.as_tensor().dims(), &Device::Cpu)?;
                        let val = if which == 0 {
                            probe(&t, wt.as_tensor())?
                        } else {
                            probe(x.as_tensor(), &t)?
                        };
                        val.to_scalar::<f64>()
                    };
                    let fd = (at(eps)? - at(-eps)?) / (2.0 * eps);
                    assert!(
                        (fd - g[j]).abs() < 1e-8,
                        "case {i}, arg {which}, element {j}: autodiff {} vs differences {fd}",
                        g[j]
                    );
                }
            }
        }
        Ok(())
    }

    /// im2col and col2im against the plain walk over output positions and taps (the
    /// definition), bit for bit in f32: im2col is a gather, and col2im must add each input
    /// element's taps in the walk's order. Geometries: every case above, wide padding (pad >=
    /// k), stride 3 and a 1-pixel input.
    #[test]
    fn columns_match_the_walk_over_taps_bit_for_bit() {
        let mut cases = CASES.to_vec();
        cases.extend([(3, 5, 6, 3, 1, 3), (2, 11, 10, 3, 3, 1), (2, 1, 1, 3, 1, 1)]);
        for (i, &(c, h, w, k, s, p)) in cases.iter().enumerate() {
            let g = Geom {
                c,
                h,
                w,
                kh: k,
                kw: k,
                stride: s,
                pad: p,
            };
            let (ho, wo) = g.out_hw();
            let (l, ckk) = (ho * wo, g.ckk());
            let b = 2;
            let x: Vec<f32> = rand(&[b * c * h * w], 40 + i as u64)
                .to_vec1::<f64>()
                .expect("x")
                .into_iter()
                .map(|v| v as f32)
                .collect();
            let mut want = vec![0f32; b * l * ckk];
            for (bi, cols) in want.chunks_mut(l * ckk).enumerate() {
                for oy in 0..ho {
                    for ox in 0..wo {
                        g.visit(oy, ox, |col, at| {
                            cols[(oy * wo + ox) * ckk + col] = x[bi * c * h * w + at]
                        });
                    }
                }
            }
            assert_eq!(im2col(&x, b, g), want, "im2col, case {i}");
            // The transposed layout holds the same columns.
            let per_image = |v: &[f32]| -> Vec<f32> {
                v.chunks(l * ckk)
                    .flat_map(|m| {
                        (0..ckk).flat_map(move |col| (0..l).map(move |p| m[p * ckk + col]))
                    })
                    .collect()
            };
            assert_eq!(im2col_t(&x, b, g), per_image(&want), "im2col_t, case {i}");
            // The same columns packed for the product: lane r of panel p is the batch's
            // output position 8 p + r, zero past the last.
            let t = per_image(&want);
            let lanes = crate::kernels::product::LANES;
            let mut panels = vec![0f32; (b * l).div_ceil(lanes) * ckk * lanes];
            for gl in 0..b * l {
                let (bi, pos) = (gl / l, gl % l);
                for kk in 0..ckk {
                    panels[((gl / lanes) * ckk + kk) * lanes + gl % lanes] =
                        t[bi * ckk * l + kk * l + pos];
                }
            }
            assert_eq!(column_panels(&x, b, g), panels, "column panels, case {i}");
            let cols: Vec<f32> = rand(&[b * l * ckk], 50 + i as u64)
                .to_vec1::<f64>()
                .expect("cols")
                .into_iter()
                .map(|v| v as f32)
                .collect();
            let mut want = vec![0f32; b * c * h * w];
            for (dst, src) in want.chunks_mut(c * h * w).zip(cols.chunks(l * ckk)) {
                for oy in 0..ho {
                    for ox in 0..wo {
                        g.visit(oy, ox, |col, at| dst[at] += src[(oy * wo + ox) * ckk + col]);
                    }
                }
            }
            let got = col2im(&cols, b, g);
            let got_t = col2im_t(&per_image(&cols), b, g);
            assert!(
                got.iter()
                    .zip(&got_t)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "col2im_t, case {i}"
            );
            let same = got
                .iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same, "col2im, case {i}: {got:?} vs {want:?}");
        }
    }

    /// The constant-weight convolution (one node) gives the composed path's output and input
    /// gradient bit for bit in f32 (same products, same order), and no weight gradient.
    #[test]
    fn constant_weight_convolution_is_the_composed_path_bit_for_bit() -> Result<()> {
        use super::super::Products::PerSample;
        for (i, &(c, h, w, k, s, p)) in CASES.iter().enumerate() {
            let f = |t: Tensor| t.to_dtype(DType::F32);
            let x = Var::from_tensor(&f(rand(&[3, c, h, w], 60 + i as u64))?)?;
            let wt = f(rand(&[5, c, k, k], 70 + i as u64))?;
            let (ho, wo) = ((h + 2 * p - k) / s + 1, (w + 2 * p - k) / s + 1);
            let r = f(rand(&[3, 5, ho, wo], 80 + i as u64))?;
            // The composed path: the same weight as a variable (tracked), so conv2d takes it.
            let wv = Var::from_tensor(&wt)?;
            let composed = conv2d(x.as_tensor(), wv.as_tensor(), s, p, PerSample)?;
            let fused = conv2d(x.as_tensor(), &wt, s, p, PerSample)?;
            assert_eq!(bits(&composed), bits(&fused), "output, case {i}");
            let (dc, _) = probe_gradient(&composed, &r, &x);
            let (df, gf) = probe_gradient(&fused, &r, &x);
            assert_eq!(bits(&dc), bits(&df), "input gradient, case {i}");
            assert!(gf.get(&wt).is_none(), "a constant weight gets no gradient");
        }
        Ok(())
    }

    /// A batch larger than one slice ([`images_per_chunk`]: here 3 slices, the last partial)
    /// gives each image's output and input gradient exactly as that image alone does.
    #[test]
    fn sliced_batches_are_each_image_alone_bit_for_bit() -> Result<()> {
        use super::super::Products::PerSample;
        let (b, c, h, w, k) = (60, 8, 32, 32, 3);
        let per = images_per_chunk::<f32>(c * k * k * h * w);
        assert!(per < b && b.div_ceil(per) >= 3, "{per} images per slice");
        let f = |t: Tensor| t.to_dtype(DType::F32);
        let x = Var::from_tensor(&f(rand(&[b, c, h, w], 91))?)?;
        let wt = f(rand(&[4, c, k, k], 92))?;
        let r = f(rand(&[b, 4, h, w], 93))?;
        let y = conv2d(x.as_tensor(), &wt, 1, 1, PerSample)?;
        let (dx, _) = probe_gradient(&y, &r, &x);
        for i in [0, per - 1, per, 2 * per + 1, b - 1] {
            let xi = Var::from_tensor(&x.as_tensor().narrow(0, i, 1)?)?;
            let yi = conv2d(xi.as_tensor(), &wt, 1, 1, PerSample)?;
            let (dxi, _) = probe_gradient(&yi, &r.narrow(0, i, 1)?, &xi);
            assert_eq!(bits(&y.narrow(0, i, 1)?), bits(&yi), "output, image {i}");
            assert_eq!(
                bits(&dx.narrow(0, i, 1)?),
                bits(&dxi),
                "input gradient, image {i}"
            );
        }
        Ok(())
    }

    #[test]
    fn f32_and_layer_bias() -> Result<()> {
        let vm = candle_nn::VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 7, DType::F32, &Device::Cpu);
        let layer = Conv2d::new(3, 5, 3, 1, 1, true, vb.pp("c"))?;
        let x = rand(&[2, 3, 6, 6], 9).to_dtype(DType::F32)?;
        use candle_core::Module;
        let reference = candle_nn::Conv2d::new(
            layer.weight.clone(),
            layer.bias.clone(),
            candle_nn::Conv2dConfig {
                padding: 1,
                ..Default::default()
            },
        )
        .forward(&x)?;
        for products in [
            super::super::Products::PerSample,
            super::super::Products::Fused,
        ] {
            let y = layer.forward(&x, products)?;
            let err = (y - &reference)?.abs()?.max_all()?.to_scalar::<f32>()?;
            assert!(err < 1e-5, "f32 max |diff| {err}");
        }
        Ok(())
    }

    #[test]
    fn mismatched_channels_are_an_error() {
        let x = rand(&[1, 3, 8, 8], 1);
        let w = rand(&[4, 2, 3, 3], 2);
        let e = conv2d(&x, &w, 1, 1, super::super::Products::Fused)
            .expect_err("3 channels into a 2-channel kernel");
        assert!(e.to_string().contains("does not fit"), "{e}");
    }
}
