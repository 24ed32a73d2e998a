//! A per-channel affine map by constants, `y[b, c, …] = x[b, c, …] · s[c] + β[c]`: frozen
//! BatchNorm (ACT's ResNet-18), whose scale and shift are buffers that no gradient reaches.
//!
//! candle composes it as a broadcast multiplication and a broadcast addition, and its backward
//! pass then computes the gradient of both operands of each: besides `∂x = g · s`, a full-size
//! product `g · x` and two sums over the batch and the pixels, for a scale and a shift that are
//! detached and throw them away. Here the forward pass is one pass with the same two roundings
//! per element (the product, then the sum: no fused multiply-add), so the values are candle's
//! bits, and the backward pass is the one product `∂x = g · s`, again candle's bits. Elsewhere
//! than the CPU, or when the scale or shift is tracked for gradients, candle's composition.

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};

/// `x (B, C, …) · scale[c] + shift[c]`, with `scale` and `shift` of shape `(C)`, taken as
/// constants (no gradient reaches them, as for frozen BatchNorm's buffers).
pub fn frozen_affine(x: &Tensor, scale: &Tensor, shift: &Tensor) -> Result<Tensor> {
    let c = scale.elem_count();
    if x.rank() < 2 || x.dim(1)? != c || scale.dims() != [c] || shift.dims() != [c] {
        candle_core::bail!(
            "frozen_affine: x {:?} needs a scale and a shift ({c}) over its dimension 1, got {:?} and {:?}",
            x.dims(),
            scale.dims(),
            shift.dims()
        );
    }
    let tracked = scale.track_op() || shift.track_op();
    if !super::fused_on(x) || tracked || x.dtype() != scale.dtype() || x.dtype() != shift.dtype() {
        let mut shape = vec![1; x.rank()];
        shape[1] = c;
        return x
            .broadcast_mul(&scale.reshape(shape.as_slice())?)?
            .broadcast_add(&shift.reshape(shape.as_slice())?);
    }
    let f64s = |t: &Tensor| t.to_dtype(candle_core::DType::F64)?.to_vec1::<f64>();
    let op = FrozenAffine {
        scale: f64s(scale)?,
        shift: f64s(shift)?,
    };
    x.contiguous()?.apply_op1(op)
}

/// The fused node; the constants are held in f64, which holds f32 values exactly.
#[derive(Clone, Debug)]
struct FrozenAffine {
    scale: Vec<f64>,
    shift: Vec<f64>,
}

/// A float the map computes in (f32, f64).
trait AffineFloat: super::Float + std::ops::Mul<Output = Self> + std::ops::Add<Output = Self> {}
impl AffineFloat for f32 {}
impl AffineFloat for f64 {}

impl FrozenAffine {
    /// `x · s + β` (or, with `shift` false, `x · s`: the backward pass) over rows of `inner`
    /// values per (batch, channel), in `T`.
    fn map<T: AffineFloat>(&self, x: &[T], inner: usize, shift: bool) -> Vec<T> {
        let c = self.scale.len();
        let mut y = Vec::with_capacity(x.len());
        for (row, xs) in x.chunks(inner.max(1)).enumerate() {
            let s = T::from_f64(self.scale[row % c]);
            if shift {
                let beta = T::from_f64(self.shift[row % c]);
                y.extend(xs.iter().map(|&v| v * s + beta));
            } else {
                y.extend(xs.iter().map(|&v| v * s));
            }
        }
        y
    }

    /// The values per (batch, channel) row of a tensor of shape `dims`.
    fn inner(dims: &[usize]) -> usize {
        dims[2..].iter().product()
    }

    /// `∂x = g · s` in `T`, shaped as `x`.
    fn backward<T: AffineFloat + candle_core::WithDType>(
        &self,
        x: &Tensor,
        g: &Tensor,
    ) -> Result<Tensor> {
        let v = self.map(
            &g.flatten_all()?.to_vec1::<T>()?,
            Self::inner(x.dims()),
            false,
        );
        Tensor::from_vec(v, x.shape(), x.device())
    }
}

impl CustomOp1 for FrozenAffine {
    fn name(&self) -> &'static str {
        "mte-frozen-affine"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let inner = Self::inner(l.dims());
        let out = float_storages!("frozen_affine", [(x, s, l)], self.map(x, inner, true));
        Ok((out, l.shape().clone()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let g = grad.contiguous()?;
        let dx = match g.dtype() {
            candle_core::DType::F32 => self.backward::<f32>(x, &g)?,
            candle_core::DType::F64 => self.backward::<f64>(x, &g)?,
            d => candle_core::bail!("frozen_affine backward: unsupported dtype {d:?}"),
        };
        Ok(Some(dx))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::{bits, max_diff, probe_gradient, rand};
    use candle_core::{DType, Var};

    /// candle's composition, the reference.
    fn composed(x: &Tensor, s: &Tensor, b: &Tensor) -> Result<Tensor> {
        let c = s.elem_count();
        x.broadcast_mul(&s.reshape((1, c, 1, 1))?)?
            .broadcast_add(&b.reshape((1, c, 1, 1))?)
    }

    /// Values and the input's gradient are candle's composition's bits, in f32 and f64.
    #[test]
    fn frozen_affine_is_candles_composition_bit_for_bit() -> Result<()> {
        for dtype in [DType::F32, DType::F64] {
            let (b, c, h, w) = (3, 5, 4, 6);
            let x = Var::from_tensor(&rand(&[b, c, h, w], 1).to_dtype(dtype)?)?;
            let s = rand(&[c], 2).to_dtype(dtype)?;
            let beta = rand(&[c], 3).to_dtype(dtype)?;
            let r = rand(&[b, c, h, w], 4).to_dtype(dtype)?;
            let ours = frozen_affine(x.as_tensor(), &s, &beta)?;
            let theirs = composed(x.as_tensor(), &s, &beta)?;
            assert_eq!(bits(&ours), bits(&theirs), "values, {dtype:?}");
            let (dx, _) = probe_gradient(&ours, &r, &x);
            let (dx_ref, _) = probe_gradient(&theirs, &r, &x);
            assert_eq!(bits(&dx), bits(&dx_ref), "input gradient, {dtype:?}");
        }
        Ok(())
    }

    /// A tracked scale takes candle's composition, so its gradient is not lost; a scale of
    /// the wrong length is an error naming the shapes.
    #[test]
    fn a_tracked_scale_keeps_its_gradient_and_bad_shapes_are_refused() -> Result<()> {
        let x = rand(&[2, 3, 2, 2], 5);
        let s = Var::from_tensor(&rand(&[3], 6))?;
        let beta = rand(&[3], 7);
        let y = frozen_affine(&x, s.as_tensor(), &beta)?;
        let g = y.sum_all()?.backward()?;
        let ds = g.get(s.as_tensor()).expect("the scale's gradient");
        assert!(max_diff(ds, &x.sum((0, 2, 3))?) < 1e-12);
        let e = frozen_affine(&x, &rand(&[4], 8), &rand(&[4], 9)).unwrap_err();
        assert!(e.to_string().contains("[2, 3, 2, 2]"), "{e}");
        Ok(())
    }
}
