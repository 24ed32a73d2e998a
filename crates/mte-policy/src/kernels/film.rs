//! FiLM, the U-Net's conditioning of a residual block: `y[b, c, t] = x[b, c, t] · s[b, c] +
//! β[b, c]` (or `x + β` without scale modulation), with `s` and `β` the two halves of the
//! condition's embedding `(B, 2 C)` (or `β = emb`, `(B, C)`).
//!
//! candle composes it as a narrow, an unsqueeze, a broadcast multiplication and a broadcast
//! addition, each a pass over the block's activations through candle's strided element-wise
//! closures; here it is one pass, with the same two roundings per element (the product, then
//! the sum: no fused multiply-add), so the values are candle's bits. The backward pass gives
//! `∂x = g · s`, `∂s = Σ_t g · x` and `∂β = Σ_t g`, each sum in the order of `t` (candle sums
//! the broadcast axis in its own order: the gradients agree to float rounding, tested).
//! Elsewhere than the CPU, candle's composition.

use candle_core::{CpuStorage, CustomOp2, D, Layout, Result, Shape, Tensor};

/// FiLM of `x (B, C, T)` by `emb`: `(B, 2 C)` with `scale` (scale then bias), `(B, C)`
/// without (bias only).
pub fn film(x: &Tensor, emb: &Tensor, scale: bool) -> Result<Tensor> {
    let (b, c, _) = x.dims3()?;
    let want = if scale { 2 * c } else { c };
    if emb.dims() != [b, want] {
        candle_core::bail!(
            "film: x {:?} needs an embedding ({b}, {want}), got {:?}",
            x.dims(),
            emb.dims()
        );
    }
    if !super::fused_on(x) || x.dtype() != emb.dtype() {
        let emb = emb.unsqueeze(D::Minus1)?;
        return if scale {
            let s = emb.narrow(1, 0, c)?;
            let beta = emb.narrow(1, c, c)?;
            x.broadcast_mul(&s)?.broadcast_add(&beta)
        } else {
            x.broadcast_add(&emb)
        };
    }
    x.contiguous()?
        .apply_op2(&emb.contiguous()?, Film { scale })
}

/// The fused node.
#[derive(Clone, Copy, Debug)]
struct Film {
    scale: bool,
}

/// A float FiLM computes in (f32, f64).
trait FilmFloat: super::Float + std::ops::Mul<Output = Self> + std::ops::Add<Output = Self> {}
impl FilmFloat for f32 {}
impl FilmFloat for f64 {}

/// `y` of each `(b, c)` row of `T` values.
fn forward<T: FilmFloat>(x: &[T], emb: &[T], c: usize, t: usize, scale: bool) -> Vec<T> {
    let e = if scale { 2 * c } else { c };
    let mut y = Vec::with_capacity(x.len());
    for (row, xs) in x.chunks(t).enumerate() {
        let (b, ch) = (row / c, row % c);
        let em = &emb[b * e..][..e];
        if scale {
            let (s, beta) = (em[ch], em[c + ch]);
            y.extend(xs.iter().map(|&v| v * s + beta));
        } else {
            let beta = em[ch];
            y.extend(xs.iter().map(|&v| v + beta));
        }
    }
    y
}

/// `(∂x, ∂emb)` from the output's gradient `g`.
fn backward<T: FilmFloat>(
    x: &[T],
    emb: &[T],
    g: &[T],
    (c, t): (usize, usize),
    scale: bool,
) -> (Vec<T>, Vec<T>) {
    let e = if scale { 2 * c } else { c };
    let mut dx = Vec::with_capacity(x.len());
    let mut demb = vec![T::default(); emb.len()];
    for (row, (xs, gs)) in x.chunks(t).zip(g.chunks(t)).enumerate() {
        let (b, ch) = (row / c, row % c);
        let mut sum_g = T::default();
        for &v in gs {
            sum_g += v;
        }
        if scale {
            let s = emb[b * e + ch];
            dx.extend(gs.iter().map(|&v| v * s));
            let mut sum_gx = T::default();
            for (&gv, &xv) in gs.iter().zip(xs) {
                sum_gx += gv * xv;
            }
            demb[b * e + ch] = sum_gx;
            demb[b * e + c + ch] = sum_g;
        } else {
            dx.extend_from_slice(gs);
            demb[b * e + ch] = sum_g;
        }
    }
    (dx, demb)
}

/// [`backward`] on tensors of one float type `T`: `(∂x, ∂emb)`, flat.
fn gradients<T: FilmFloat + candle_core::WithDType>(
    x: &Tensor,
    emb: &Tensor,
    grad: &Tensor,
    ct: (usize, usize),
    scale: bool,
) -> Result<(Tensor, Tensor)> {
    let flat = |t: &Tensor| t.flatten_all()?.to_vec1::<T>();
    let (dx, de) = backward(&flat(x)?, &flat(emb)?, &flat(grad)?, ct, scale);
    Ok((Tensor::new(dx, x.device())?, Tensor::new(de, x.device())?))
}

impl CustomOp2 for Film {
    fn name(&self) -> &'static str {
        "mte-film"
    }

    fn cpu_fwd(
        &self,
        sx: &CpuStorage,
        lx: &Layout,
        se: &CpuStorage,
        le: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let [_, c, t] = *lx.dims() else {
            candle_core::bail!("film: x must be (B, C, T), got {:?}", lx.dims());
        };
        let out = float_storages!(
            "film",
            [(x, sx, lx), (e, se, le)],
            forward(x, e, c, t, self.scale)
        );
        Ok((out, lx.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        emb: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (_, c, t) = x.dims3()?;
        let grad = grad.contiguous()?;
        let (dx, demb) = match (x.dtype(), emb.dtype()) {
            (candle_core::DType::F32, candle_core::DType::F32) => {
                gradients::<f32>(x, emb, &grad, (c, t), self.scale)?
            }
            (candle_core::DType::F64, candle_core::DType::F64) => {
                gradients::<f64>(x, emb, &grad, (c, t), self.scale)?
            }
            (a, b) => candle_core::bail!("film backward: unsupported dtypes {a:?}, {b:?}"),
        };
        Ok((
            Some(dx.reshape(x.shape())?),
            Some(demb.reshape(emb.shape())?),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::{bits, max_diff, rand};
    use candle_core::{DType, Var};

    /// Values are candle's composition's bits; gradients of `x` and of the embedding agree
    /// to float rounding (1e-12 in f64, 1e-5 in f32), with and without scale modulation.
    #[test]
    fn film_is_candles_composition() -> Result<()> {
        for scale in [true, false] {
            for dtype in [DType::F32, DType::F64] {
                let (b, c, t) = (3, 5, 7);
                let e = if scale { 2 * c } else { c };
                let x = Var::from_tensor(&rand(&[b, c, t], 1).to_dtype(dtype)?)?;
                let emb = Var::from_tensor(&rand(&[b, e], 2).to_dtype(dtype)?)?;
                let r = rand(&[b, c, t], 3).to_dtype(dtype)?;
                let ours = film(x.as_tensor(), emb.as_tensor(), scale)?;
                let em = emb.as_tensor().unsqueeze(D::Minus1)?;
                let theirs = if scale {
                    x.as_tensor()
                        .broadcast_mul(&em.narrow(1, 0, c)?)?
                        .broadcast_add(&em.narrow(1, c, c)?)?
                } else {
                    x.as_tensor().broadcast_add(&em)?
                };
                assert_eq!(bits(&ours), bits(&theirs), "values, {scale} {dtype:?}");
                let grads = |y: &Tensor| -> Result<(Tensor, Tensor)> {
                    let g = (y * &r)?.sum_all()?.backward()?;
                    let get = |v: &Var| g.get(v.as_tensor()).cloned().expect("gradient");
                    Ok((get(&x), get(&emb)))
                };
                let (a, bb) = (grads(&ours)?, grads(&theirs)?);
                let tol = if dtype == DType::F32 { 1e-5 } else { 1e-12 };
                assert!(max_diff(&a.0, &bb.0) < tol, "dx, {scale} {dtype:?}");
                assert!(max_diff(&a.1, &bb.1) < tol, "demb, {scale} {dtype:?}");
            }
        }
        let x = rand(&[2, 3, 4], 4);
        assert!(film(&x, &rand(&[2, 5], 5), true).is_err());
        Ok(())
    }
}
