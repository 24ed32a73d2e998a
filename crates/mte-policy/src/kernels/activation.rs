//! Activations as single graph nodes with the bits of candle's own ops: Mish (the U-Net's)
//! and ReLU (the image encoder's).
//!
//! **Mish**, `x · tanh(ln(1 + eˣ))`.
//! `candle_nn::ops::mish` is five ops (exp, +1, ln, tanh, ×); its backward pass is about
//! fifteen more, each a full-size temporary plus a zero-filled gradient buffer and an
//! addition. The U-Net applies Mish after every convolution block and to the conditioning
//! of every residual block, so at evaluation sizes this bookkeeping costs more than the
//! arithmetic. Here the forward computes the same functions in the same order (`f32::exp`,
//! `ln`, `tanh`, as candle's CPU ops do), and the backward replays candle's backward rules
//! for the five ops element by element, including its additions to zero, so values and
//! gradients are the same bits (checked against the composition in the tests). Elsewhere
//! than the CPU, the composition.
//!
//! Only for an input that nothing else reads: candle adds the product's and the
//! exponential's contributions to the input's gradient at two different points of its
//! backward pass, and a third reader's contribution could fall between them, which one
//! fused contribution cannot reproduce. The U-Net's conditioning vector, which every
//! residual block reads, keeps the composition.

use super::contiguous;
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor};
use std::sync::{Arc, OnceLock};

/// The scalar functions the activations need, for f32 and f64.
trait ActFloat: super::Float + std::ops::Mul<Output = Self> + std::ops::Add<Output = Self> {
    fn exp(self) -> Self;
    fn ln(self) -> Self;
    fn tanh(self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn div(self, o: Self) -> Self;
    /// `max(self, 0)` as candle's relu computes it (`f32::max`).
    fn max0(self) -> Self;
    const ZERO: Self;
    const ONE: Self;
}

macro_rules! mish_float {
    ($t:ty) => {
        impl ActFloat for $t {
            fn exp(self) -> Self {
                <$t>::exp(self)
            }
            fn ln(self) -> Self {
                <$t>::ln(self)
            }
            fn tanh(self) -> Self {
                <$t>::tanh(self)
            }
            fn sub(self, o: Self) -> Self {
                self - o
            }
            fn div(self, o: Self) -> Self {
                self / o
            }
            fn max0(self) -> Self {
                self.max(0.0)
            }
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
        }
    };
}
mish_float!(f32);
mish_float!(f64);

/// The forward intermediates: `e = exp(x)`, `s = e · 1 + 1` (candle's affine), `t =
/// tanh(ln s)`.
#[inline]
fn parts<T: ActFloat>(x: T) -> (T, T, T) {
    let e = x.exp();
    let s = e * T::ONE + T::ONE;
    (e, s, s.ln().tanh())
}

/// d mish / dx times `g`, from the forward's intermediates `(e, s, t)`, as candle's backward
/// pass computes it for the composition: the product's two sides, then tanh (`0 - grad ·
/// (t² · 1 - 1)`), ln (`0 + grad / s`), the affine (`0 + (grad · 1 + 0)`) and exp (`grad ·
/// e`), every accumulation starting from zero.
#[inline]
fn gradient<T: ActFloat>(x: T, g: T, (e, s, t): (T, T, T)) -> T {
    let gt = T::ZERO + g * x;
    let minus_dtanh = (t * t) * T::ONE + (T::ZERO.sub(T::ONE));
    let gl = T::ZERO.sub(gt * minus_dtanh);
    let gs = T::ZERO + gl.div(s);
    let ge = T::ZERO + (gs * T::ONE + T::ZERO);
    g * t + ge * e
}

/// The forward's intermediates `(e, s, t)` of every element, kept for the backward pass so
/// that it computes no transcendental function again.
#[derive(Debug)]
enum Saved {
    F32(Vec<(f32, f32, f32)>),
    F64(Vec<(f64, f64, f64)>),
}

/// Mish with its saved intermediates (each call of [`mish`] makes its own node, and the graph
/// keeps the node until the backward pass).
#[derive(Debug)]
struct Mish {
    saved: Arc<OnceLock<Saved>>,
    /// Whether to keep them: only where a backward pass can follow (a tracked input).
    keep: bool,
}

impl CustomOp1 for Mish {
    fn name(&self) -> &'static str {
        "mte-mish"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        // The intermediates are kept only where a backward pass can follow. One function per
        // pass, as candle's ops run them: interleaving glibc's `expf`, `logf` and `tanhf`
        // element by element measured 10% slower for the whole sampling loop (`tanhf`'s
        // inner `expm1f` alone 2.5x slower), the same values.
        fn run<T: ActFloat>(x: &[T], keep: bool) -> (Vec<T>, Vec<(T, T, T)>) {
            let e: Vec<T> = x.iter().map(|&v| v.exp()).collect();
            let s: Vec<T> = e.iter().map(|&v| v * T::ONE + T::ONE).collect();
            let l: Vec<T> = s.iter().map(|&v| v.ln()).collect();
            let t: Vec<T> = l.iter().map(|&v| v.tanh()).collect();
            let y = x.iter().zip(&t).map(|(&v, &t)| v * t).collect();
            let parts = if keep {
                e.into_iter()
                    .zip(s)
                    .zip(t)
                    .map(|((e, s), t)| (e, s, t))
                    .collect()
            } else {
                Vec::new()
            };
            (y, parts)
        }
        let (out, saved) = match storage {
            CpuStorage::F32(v) => {
                let (y, p) = run(contiguous(v, layout)?, self.keep);
                (CpuStorage::F32(y), Saved::F32(p))
            }
            CpuStorage::F64(v) => {
                let (y, p) = run(contiguous(v, layout)?, self.keep);
                (CpuStorage::F64(y), Saved::F64(p))
            }
            other => candle_core::bail!("mish: unsupported dtype {:?}", other.dtype()),
        };
        // A node's forward runs once; should it run again, the first intermediates stand
        // (the same input gives the same values).
        if self.keep {
            let _ = self.saved.set(saved);
        }
        Ok((out, layout.shape().clone()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let back = MishBackward {
            saved: self.saved.clone(),
        };
        Ok(Some(arg.apply_op2_no_bwd(&grad.contiguous()?, &back)?))
    }
}

/// `(x, g)` → `g · mish'(x)` as [`gradient`] computes it, from the saved intermediates (or
/// recomputed, should they be missing or of another size).
#[derive(Debug)]
struct MishBackward {
    saved: Arc<OnceLock<Saved>>,
}

impl CustomOp2 for MishBackward {
    fn name(&self) -> &'static str {
        "mte-mish-backward"
    }

    fn cpu_fwd(
        &self,
        sx: &CpuStorage,
        lx: &Layout,
        sg: &CpuStorage,
        lg: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        fn zip<T: ActFloat>(x: &[T], g: &[T], saved: Option<&Vec<(T, T, T)>>) -> Vec<T> {
            match saved.filter(|p| p.len() == x.len()) {
                Some(p) => x
                    .iter()
                    .zip(g)
                    .zip(p)
                    .map(|((&x, &g), &p)| gradient(x, g, p))
                    .collect(),
                None => x
                    .iter()
                    .zip(g)
                    .map(|(&x, &g)| gradient(x, g, parts(x)))
                    .collect(),
            }
        }
        let saved = self.saved.get();
        let out = match (sx, sg) {
            (CpuStorage::F32(x), CpuStorage::F32(g)) => {
                let p = match saved {
                    Some(Saved::F32(p)) => Some(p),
                    _ => None,
                };
                CpuStorage::F32(zip(contiguous(x, lx)?, contiguous(g, lg)?, p))
            }
            (CpuStorage::F64(x), CpuStorage::F64(g)) => {
                let p = match saved {
                    Some(Saved::F64(p)) => Some(p),
                    _ => None,
                };
                CpuStorage::F64(zip(contiguous(x, lx)?, contiguous(g, lg)?, p))
            }
            _ => candle_core::bail!(
                "mish backward: unsupported dtypes {:?}, {:?}",
                sx.dtype(),
                sg.dtype()
            ),
        };
        Ok((out, lx.shape().clone()))
    }
}

/// Mish of `x`: one fused node on the CPU (f32, f64), candle's composition elsewhere.
pub fn mish(x: &Tensor) -> Result<Tensor> {
    if super::fused_on(x) {
        x.contiguous()?.apply_op1(Mish {
            saved: Arc::default(),
            keep: x.track_op(),
        })
    } else {
        candle_nn::ops::mish(x)
    }
}

/// **ReLU**, whose backward is one pass: candle's builds a zero tensor, a comparison, a cast and
/// a product (`g · (x >= 0)`) before adding it to the input's gradient; this computes the
/// same product per element.
#[derive(Clone, Copy, Debug)]
struct Relu;

impl CustomOp1 for Relu {
    fn name(&self) -> &'static str {
        "mte-relu"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        fn relu<T: ActFloat + PartialOrd>(x: &[T]) -> Vec<T> {
            // candle's relu is `max(x, 0)`.
            x.iter().map(|&v| v.max0()).collect()
        }
        let out = float_storages!("relu", [(v, storage, layout)], relu(v));
        Ok((out, layout.shape().clone()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(
            arg.apply_op2_no_bwd(&grad.contiguous()?, &ReluBackward)?,
        ))
    }
}

/// `(x, g)` → `g · (x >= 0 ? 1 : 0)`.
#[derive(Clone, Copy, Debug)]
struct ReluBackward;

impl CustomOp2 for ReluBackward {
    fn name(&self) -> &'static str {
        "mte-relu-backward"
    }

    fn cpu_fwd(
        &self,
        sx: &CpuStorage,
        lx: &Layout,
        sg: &CpuStorage,
        lg: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        fn zip<T: ActFloat + PartialOrd>(x: &[T], g: &[T]) -> Vec<T> {
            let pass = |x: T| if x >= T::ZERO { T::ONE } else { T::ZERO };
            x.iter().zip(g).map(|(&x, &g)| g * pass(x)).collect()
        }
        let out = float_storages!("relu backward", [(x, sx, lx), (g, sg, lg)], zip(x, g));
        Ok((out, lx.shape().clone()))
    }
}

/// ReLU of `x`: one fused node on the CPU (f32, f64), candle's op elsewhere.
pub fn relu(x: &Tensor) -> Result<Tensor> {
    if super::fused_on(x) {
        x.contiguous()?.apply_op1(Relu)
    } else {
        x.relu()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::{bits, probe_gradient};
    use candle_core::{DType, Var};

    /// Values and gradients are candle's composition's, bit for bit, in f32 and f64, over
    /// ordinary values, large ones (where eˣ overflows and the composition gives NaN or
    /// infinity), small ones, and signed zeros.
    #[test]
    fn fused_mish_is_candles_composition_bit_for_bit() -> Result<()> {
        let mut xs: Vec<f64> = crate::kernels::test_util::rand(&[400], 3)
            .to_vec1::<f64>()?
            .iter()
            .map(|v| v * 12.0)
            .collect();
        xs.extend([0.0, -0.0, 1e-30, -1e-30, 60.0, 100.0, 800.0, -100.0, -800.0]);
        let gs: Vec<f64> = crate::kernels::test_util::rand(&[xs.len()], 4).to_vec1::<f64>()?;
        for dtype in [DType::F32, DType::F64] {
            let x = Var::from_tensor(
                &Tensor::new(xs.as_slice(), &candle_core::Device::Cpu)?.to_dtype(dtype)?,
            )?;
            let r = Tensor::new(gs.as_slice(), &candle_core::Device::Cpu)?.to_dtype(dtype)?;
            let ours = mish(x.as_tensor())?;
            let theirs = candle_nn::ops::mish(x.as_tensor())?;
            // An untracked input (no backward can follow) takes the path that keeps nothing.
            let untracked = mish(&x.as_tensor().detach())?;
            assert_eq!(bits(&ours), bits(&theirs), "values, {dtype:?}");
            assert_eq!(bits(&untracked), bits(&theirs), "untracked, {dtype:?}");
            let (go, _) = probe_gradient(&ours, &r, &x);
            let (gt, _) = probe_gradient(&theirs, &r, &x);
            assert_eq!(bits(&go), bits(&gt), "gradients, {dtype:?}");
            // Without saved intermediates the backward recomputes them: the same bits.
            let unsaved = MishBackward {
                saved: Arc::new(OnceLock::new()),
            };
            let again = x.as_tensor().apply_op2_no_bwd(&r, &unsaved)?;
            assert_eq!(bits(&again), bits(&gt), "recomputed, {dtype:?}");
        }
        Ok(())
    }

    /// ReLU: values and gradients are candle's, bit for bit, including at zero (where
    /// candle passes the gradient: `x >= 0`) and at negative zero.
    #[test]
    fn fused_relu_is_candles_bit_for_bit() -> Result<()> {
        let mut xs: Vec<f64> = crate::kernels::test_util::rand(&[200], 5).to_vec1::<f64>()?;
        xs.extend([0.0, -0.0, 1e-300, -1e-300]);
        let gs: Vec<f64> = crate::kernels::test_util::rand(&[xs.len()], 6).to_vec1::<f64>()?;
        for dtype in [DType::F32, DType::F64] {
            let dev = candle_core::Device::Cpu;
            let x = Var::from_tensor(&Tensor::new(xs.as_slice(), &dev)?.to_dtype(dtype)?)?;
            let r = Tensor::new(gs.as_slice(), &dev)?.to_dtype(dtype)?;
            let (ours, theirs) = (relu(x.as_tensor())?, x.as_tensor().relu()?);
            assert_eq!(bits(&ours), bits(&theirs), "values, {dtype:?}");
            let (go, _) = probe_gradient(&ours, &r, &x);
            let (gt, _) = probe_gradient(&theirs, &r, &x);
            assert_eq!(bits(&go), bits(&gt), "gradients, {dtype:?}");
        }
        Ok(())
    }
}
