//! The U-Net's 1-D convolution for constant weights (a loaded checkpoint under evaluation or
//! attack) as one graph node, bit for bit the composed path of `diffusion::unet::Conv1dGemm`.
//!
//! The composed path pads the input, takes `k` shifted narrows, stacks them into columns
//! `(B, C k, T_out)`, multiplies each sample by the weight `(C_out, C k)` and adds the bias:
//! about `k + 6` graph nodes, each of which costs the backward pass a zero-filled buffer and
//! an addition. Here the forward builds the same columns and calls the same per-sample
//! product, which adds the bias as it stores each element (one addition, as `broadcast_add`
//! does); the backward multiplies by the
//! transposed weight (the product's own backward) and sums each input element's taps in the
//! order candle's backward pass adds the narrows' gradients (last tap first), so the input's
//! gradient is the same bits (checked against the composed path in the tests).
//!
//! Conventions: input `(B, C, T)`, weight `(C_out, C, k)` as torch stores it, zero padding
//! `pad` on both sides, output position `t` reads input `t · stride + j - pad` for tap `j`.

use super::batch::{PerSampleProduct, Side};
use super::contiguous;
use super::conv::taps_inside;
use super::product::{Dims, Shared, left_panels};
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, CustomOp3, Layout, Result, Shape, Tensor, WithDType};

/// Geometry of one 1-D convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Geom1 {
    c: usize,
    t: usize,
    k: usize,
    stride: usize,
    pad: usize,
}

impl Geom1 {
    fn t_out(&self) -> usize {
        (self.t_padded() - self.k) / self.stride + 1
    }

    /// The input's length with its zero padding on both sides.
    fn t_padded(&self) -> usize {
        self.t + 2 * self.pad
    }
}

/// `(B, C, T)` → the columns `(B, C k, T_out)` packed straight into
/// `kernels::product`'s vector panels: lane `r` of panel `p` is output position `g = 8 p + r`
/// of the batch (`g = b T_out + t`), depth `c k + j` reads input `t · stride + j - pad` of
/// channel `c` (zero outside), so no im2col copy is made. The input is first copied with its
/// zero padding, so every tap is a plain read; lanes past the batch's last position stay zero.
fn column_panels<T: Copy + Default>(x: &[T], b: usize, g: Geom1) -> Vec<T> {
    const LANES: usize = super::product::LANES;
    let (to, ck, tp) = (g.t_out(), g.c * g.k, g.t_padded());
    let padded = zero_padded(x, b * g.c, g);
    let count = b * to;
    let mut out = vec![T::default(); count.div_ceil(LANES) * ck * LANES];
    for (p, panel) in out.chunks_mut(ck * LANES).enumerate() {
        let g0 = p * LANES;
        let lanes = (count - g0).min(LANES);
        let (rows, _) = panel.as_chunks_mut::<LANES>();
        // Each lane's first padded input (channel 0, tap 0).
        let lane: [usize; LANES] = std::array::from_fn(|r| {
            let gl = g0 + r.min(lanes - 1);
            (gl / to) * g.c * tp + (gl % to) * g.stride
        });
        // Eight positions of one sample at stride 1: a tap's eight inputs are adjacent.
        let one_run = g.stride == 1 && lanes == LANES && lane[LANES - 1] == lane[0] + LANES - 1;
        for (c, taps) in rows.chunks_exact_mut(g.k).enumerate() {
            for (j, dst) in taps.iter_mut().enumerate() {
                let at = c * tp + j;
                if one_run {
                    if let Some(src) = padded[lane[0] + at..].first_chunk::<LANES>() {
                        *dst = *src;
                    }
                } else {
                    for (d, &base) in dst.iter_mut().zip(&lane).take(lanes) {
                        *d = padded[base + at];
                    }
                }
            }
        }
    }
    out
}

/// The `rows` rows of `T` values of `x` with `pad` zeros on both sides (rows of
/// [`Geom1::t_padded`]).
fn zero_padded<T: Copy + Default>(x: &[T], rows: usize, g: Geom1) -> Vec<T> {
    let tp = g.t_padded();
    let mut padded = vec![T::default(); rows * tp];
    for (dst, src) in padded.chunks_exact_mut(tp).zip(x.chunks_exact(g.t)) {
        dst[g.pad..g.pad + g.t].copy_from_slice(src);
    }
    padded
}

/// Columns' gradient `(B, C k, T_out)` → the input's `(B, C, T)`: each element sums its taps
/// from the last to the first, starting from zero.
fn uncolumns<T: Copy + Default + std::ops::AddAssign>(cols: &[T], b: usize, g: Geom1) -> Vec<T> {
    let to = g.t_out();
    let mut dx = vec![T::default(); b * g.c * g.t];
    for (dst, src) in dx.chunks_mut(g.c * g.t).zip(cols.chunks(g.c * g.k * to)) {
        for c in 0..g.c {
            let xs = &mut dst[c * g.t..][..g.t];
            for j in (0..g.k).rev() {
                let row = &src[(c * g.k + j) * to..][..to];
                let (lo, hi) = taps_inside(j, g.pad, g.stride, g.t, to);
                if g.stride == 1 {
                    let d = &mut xs[lo + j - g.pad..hi + j - g.pad];
                    for (a, &v) in d.iter_mut().zip(&row[lo..hi]) {
                        *a += v;
                    }
                } else {
                    for (o, &v) in row.iter().enumerate().take(hi).skip(lo) {
                        xs[o * g.stride + j - g.pad] += v;
                    }
                }
            }
        }
    }
    dx
}

/// `x (B, C, T)`, the weight packed by [`packed_weight`], `bias (C_out)` → `(B, C_out,
/// T_out)`; the weight itself `(C_out, C, k)` for the backward pass.
#[derive(Clone, Debug)]
struct ConstantWeightConv1d {
    g: Geom1,
    weight: Tensor,
    co: usize,
}

impl ConstantWeightConv1d {
    /// Each sample's product `W (C_out, C k) · cols_b` (the packed weight read in place),
    /// plus the bias.
    fn forward<T: WithDType + Default + super::product::Element>(
        &self,
        x: &[T],
        b: usize,
        packed: &[T],
        bias: &[T],
    ) -> Result<CpuStorage> {
        let (g, co) = (self.g, self.co);
        let to = g.t_out();
        let panels = column_panels(x, b, g);
        let mut y = vec![T::default(); b * co * to];
        let dims = Dims {
            m: co,
            k: g.c * g.k,
            n: to,
        };
        if packed.len() != panels_len(co, dims.k) {
            candle_core::bail!(
                "conv1d: a packed weight of {} values, expected {}",
                packed.len(),
                panels_len(co, dims.k)
            );
        }
        let packed = Shared::Panels(packed);
        super::product::left_products_packed(packed, &panels, dims, b, (&mut y, Some(bias)));
        Ok(T::to_cpu_storage_owned(y))
    }
}

impl CustomOp3 for ConstantWeightConv1d {
    fn name(&self) -> &'static str {
        "mte-constant-weight-conv1d"
    }

    fn cpu_fwd(
        &self,
        sx: &CpuStorage,
        lx: &Layout,
        sw: &CpuStorage,
        lw: &Layout,
        sb: &CpuStorage,
        lb: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let b = lx.dims()[0];
        let out = match (sx, sw, sb) {
            (CpuStorage::F32(x), CpuStorage::F32(w), CpuStorage::F32(bias)) => self.forward(
                contiguous(x, lx)?,
                b,
                contiguous(w, lw)?,
                contiguous(bias, lb)?,
            )?,
            (CpuStorage::F64(x), CpuStorage::F64(w), CpuStorage::F64(bias)) => self.forward(
                contiguous(x, lx)?,
                b,
                contiguous(w, lw)?,
                contiguous(bias, lb)?,
            )?,
            _ => candle_core::bail!(
                "conv1d: unsupported dtypes {:?}, {:?}, {:?}",
                sx.dtype(),
                sw.dtype(),
                sb.dtype()
            ),
        };
        Ok((out, Shape::from((b, self.co, self.g.t_out()))))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        _packed: &Tensor,
        _bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        // The product's backward: `Wᵀ g_b`, the same side with the weight read transposed.
        let back = PerSampleProduct {
            side: Side::Left,
            transpose: true,
        };
        let w = self.weight.reshape((self.co, self.g.c * self.g.k))?;
        let dcols = grad.contiguous()?.apply_op2_no_bwd(&w, &back)?;
        Ok((
            Some(dcols.apply_op1_no_bwd(&Uncolumns(self.g))?),
            None,
            None,
        ))
    }
}

/// [`uncolumns`] as an op on the columns' gradient.
#[derive(Clone, Copy, Debug)]
struct Uncolumns(Geom1);

impl CustomOp1 for Uncolumns {
    fn name(&self) -> &'static str {
        "mte-conv1d-uncolumns"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let b = layout.dims()[0];
        let out = float_storages!("conv1d", [(v, storage, layout)], uncolumns(v, b, g));
        Ok((out, Shape::from((b, g.c, g.t))))
    }
}

/// Whether [`conv1d_constant`] applies: CPU tensors, and neither weight nor bias tracked.
pub fn constant_weights(x: &Tensor, weight: &Tensor, bias: &Tensor) -> bool {
    x.device().is_cpu() && !weight.track_op() && !bias.track_op()
}

/// Values a weight `(C_out, C k)` packs into.
fn panels_len(co: usize, ck: usize) -> usize {
    co.div_ceil(super::product::WIDTH) * ck * super::product::WIDTH
}

/// A constant `weight (C_out, C, k)` packed for [`conv1d_constant`]'s products (a 1-D tensor;
/// compute it once per loaded weight).
pub fn packed_weight(weight: &Tensor) -> Result<Tensor> {
    let (co, ci, k) = weight.dims3()?;
    let flat = weight.flatten_all()?;
    let dev = weight.device();
    match weight.dtype() {
        candle_core::DType::F32 => {
            Tensor::new(left_panels(&flat.to_vec1::<f32>()?, co, ci * k), dev)
        }
        candle_core::DType::F64 => {
            Tensor::new(left_panels(&flat.to_vec1::<f64>()?, co, ci * k), dev)
        }
        other => candle_core::bail!("conv1d: unsupported weight dtype {other:?}"),
    }
}

/// `x (B, C, T)` convolved with a constant `weight (C_out, C, k)` (with `packed`, its
/// [`packed_weight`]) plus `bias (C_out)`, with per-sample products (batch-invariant): `(B,
/// C_out, T_out)`. Gradients flow to `x` only.
pub fn conv1d_constant(
    x: &Tensor,
    (weight, packed): (&Tensor, &Tensor),
    bias: &Tensor,
    stride: usize,
    pad: usize,
) -> Result<Tensor> {
    let (_, c, t) = x.dims3()?;
    let (co, ci, k) = weight.dims3()?;
    if ci != c || stride == 0 || t + 2 * pad < k || bias.dims() != [co] {
        candle_core::bail!(
            "conv1d: input (B, {c}, {t}) does not fit weight ({co}, {ci}, {k}) and bias {:?} with stride {stride}, padding {pad}",
            bias.dims()
        );
    }
    let g = Geom1 {
        c,
        t,
        k,
        stride,
        pad,
    };
    let op = ConstantWeightConv1d {
        g,
        weight: weight.clone(),
        co,
    };
    x.contiguous()?
        .apply_op3(&packed.contiguous()?, &bias.contiguous()?, op)
}
