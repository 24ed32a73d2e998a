//! Activations as single graph nodes: Mish (the U-Net's) and ReLU (the image encoder's).
//!
//! **Mish**, `x · tanh(ln(1 + eˣ))`. `candle_nn::ops::mish` is five ops (exp, +1, ln, tanh,
//! ×), each a pass over the tensor through glibc's scalar `expf`, `logf` and `tanhf`; at batch
//! 64 they took 30% of the `cpu` U-Net's forward time (a `perf` profile of
//! `benches/unet.rs`). Here one pass computes the same function from one exponential:
//! with `e = eˣ` and `n = e (e + 2)`, `tanh(ln(1 + e)) = n / (n + 2)`, so
//! `mish(x) = x · n / (n + 2)`, and `mish(x) = x` above [`MISH_LINEAR`] (where `n / (n + 2)`
//! rounds to one and `n` would overflow further up). In f32 the exponential is [`exp_f32`], a
//! polynomial written so that the loop vectorises (compiled for AVX-512, AVX2 and the
//! baseline, the same operations in the same order on each: Rust never contracts `a · b + c`
//! into a fused multiply-add, so every CPU gets the same bits). The derivative,
//! `t + x · σ(x) · (1 - t²)` with `t = n / (n + 2)`, `σ(x) = e / (1 + e)` and
//! `1 - t² = 4 (n + 1) / (n + 2)²` (no cancellation where `t` → 1), is recomputed from `x` in
//! the backward pass: one exponential costs less than keeping three intermediates.
//!
//! The formula is more accurate than the composition, not bit-identical to it: values and
//! gradients are checked against a float64 evaluation to a few f32 ulps, and for very
//! negative `x` (below about -17, where `1 + eˣ` rounds to one) the composition returns zero
//! and this returns `x · eˣ`. Elsewhere than the CPU, candle's composition.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor};

/// Above this `x`, `mish(x) = x` in f32 and f64 alike (`1 - tanh(ln(1 + eˣ)) ≈ 2 e^(-2x)`,
/// below f64's half ulp from x = 19 on), and `n = e (e + 2)` is still finite in f32.
const MISH_LINEAR: f32 = 20.0;

/// `eˣ` in f32, as a loop body the compiler vectorises: `x = k ln 2 + r` with `k` rounded to
/// the nearest integer (the add-and-subtract of 1.5 · 2²³), `|r| ≤ ln 2 / 2`, `eʳ` by its
/// Taylor polynomial to degree 7 (truncation below 5e-9 relative), `2ᵏ` built in the exponent
/// bits. `x` is clamped to [-87, 88], where `2ᵏ` stays a normal number: below -87 the result
/// is e⁻⁸⁷ (1.6e-38) instead of smaller, above 88 e⁸⁸ instead of infinity. NaN stays NaN.
/// Relative error within 3 ulps of the exact value over the clamped range (tested).
#[inline(always)]
pub(crate) fn exp_f32(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5 · 2²³: adding it rounds to an integer
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_145_75; // ln 2 to 16 bits, so k · LN2_HI is exact
    const LN2_LO: f32 = 1.428_606_8e-6; // ln 2 - LN2_HI
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * LOG2E + MAGIC;
    let k = shifted - MAGIC;
    // The integer k sits in the low mantissa bits of `shifted`.
    let k_bits = shifted.to_bits().wrapping_sub(MAGIC.to_bits());
    let scale = f32::from_bits(k_bits.wrapping_add(127) << 23);
    let r = (x - k * LN2_HI) - k * LN2_LO;
    let mut p = 1.0 / 5040.0;
    for c in [
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
        1.0,
        1.0,
    ] {
        p = p * r + c;
    }
    p * scale
}

/// The scalar functions Mish needs, for f32 and f64.
trait ActFloat:
    super::Float
    + PartialOrd
    + std::ops::Mul<Output = Self>
    + std::ops::Add<Output = Self>
    + std::ops::Div<Output = Self>
{
    /// `eˣ`: [`exp_f32`] in f32, the standard library's in f64.
    fn exp(self) -> Self;
    /// `max(self, 0)` as candle's relu computes it (`f32::max`).
    fn max0(self) -> Self;
    const ZERO: Self;
    const ONE: Self;
    const TWO: Self;
    const FOUR: Self;
    const LINEAR: Self;
}

macro_rules! act_float {
    ($t:ty, $exp:expr) => {
        impl ActFloat for $t {
            #[inline(always)]
            fn exp(self) -> Self {
                $exp(self)
            }
            fn max0(self) -> Self {
                self.max(0.0)
            }
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            const TWO: Self = 2.0;
            const FOUR: Self = 4.0;
            const LINEAR: Self = MISH_LINEAR as $t;
        }
    };
}
act_float!(f32, exp_f32);
act_float!(f64, f64::exp);

/// `mish(x)`.
#[inline(always)]
fn mish_value<T: ActFloat>(x: T) -> T {
    let e = x.exp();
    let n = e * (e + T::TWO);
    let y = x * (n / (n + T::TWO));
    if x > T::LINEAR { x } else { y }
}

/// `g · mish'(x)`.
#[inline(always)]
fn mish_gradient<T: ActFloat>(x: T, g: T) -> T {
    let e = x.exp();
    let n = e * (e + T::TWO);
    let d = n + T::TWO;
    let t = n / d;
    let sigmoid = e / (e + T::ONE);
    let slope = t + x * sigmoid * (T::FOUR * (n + T::ONE) / (d * d));
    g * if x > T::LINEAR { T::ONE } else { slope }
}

/// [`mish_value`] of every element.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl",
    "x86_64+avx2+fma",
    "aarch64+neon"
))]
fn mish_all<T: ActFloat>(x: &[T]) -> Vec<T> {
    // The loop is written out here, not in `collect` (a generic function compiled without
    // this clone's target features, so 4-wide SSE).
    let mut out = vec![T::ZERO; x.len()];
    for (o, &v) in out.iter_mut().zip(x) {
        *o = mish_value(v);
    }
    out
}

/// [`mish_gradient`] of every element.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512vl",
    "x86_64+avx2+fma",
    "aarch64+neon"
))]
fn mish_gradient_all<T: ActFloat>(x: &[T], g: &[T]) -> Vec<T> {
    // Written out for the clone's target features, as in `mish_all`.
    let mut out = vec![T::ZERO; x.len()];
    for ((o, &v), &g) in out.iter_mut().zip(x).zip(g) {
        *o = mish_gradient(v, g);
    }
    out
}

/// Mish as one node; its backward pass recomputes the exponential from the input.
#[derive(Clone, Copy, Debug)]
struct Mish;

impl CustomOp1 for Mish {
    fn name(&self) -> &'static str {
        "mte-mish"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let out = float_storages!("mish", [(v, storage, layout)], mish_all(v));
        Ok((out, layout.shape().clone()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(
            arg.apply_op2_no_bwd(&grad.contiguous()?, &MishBackward)?,
        ))
    }
}

/// `(x, g)` → `g · mish'(x)`.
#[derive(Clone, Copy, Debug)]
struct MishBackward;

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
        let out = float_storages!(
            "mish backward",
            [(x, sx, lx), (g, sg, lg)],
            mish_gradient_all(x, g)
        );
        Ok((out, lx.shape().clone()))
    }
}

/// Mish of `x`: one node on the CPU (f32, f64), candle's composition elsewhere.
pub fn mish(x: &Tensor) -> Result<Tensor> {
    if super::fused_on(x) {
        x.contiguous()?.apply_op1(Mish)
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

    /// `mish` and its derivative in float64 the textbook way (`ln_1p` keeps the small `eˣ`).
    fn reference(x: f64) -> (f64, f64) {
        if x > 40.0 {
            return (x, 1.0);
        }
        let t = x.exp().ln_1p().tanh();
        let sigmoid = 1.0 / (1.0 + (-x).exp());
        (x * t, t + x * sigmoid * (1.0 - t * t))
    }

    /// Inputs: random ones over [-24, 24], a dense sweep, and the edges (zeros, tiny ones,
    /// the linear cut-off, values where eˣ overflows or underflows).
    fn inputs() -> Result<Vec<f64>> {
        let mut xs: Vec<f64> = crate::kernels::test_util::rand(&[400], 3)
            .to_vec1::<f64>()?
            .iter()
            .map(|v| v * 24.0)
            .collect();
        xs.extend((-3000..=3000).map(|i| f64::from(i) * 0.01));
        xs.extend([
            0.0, -0.0, 1e-30, -1e-30, 19.99, 20.0, 20.01, 60.0, 100.0, 800.0,
        ]);
        xs.extend([-17.0, -30.0, -87.5, -100.0, -800.0]);
        Ok(xs)
    }

    #[test]
    fn exp_f32_is_within_three_ulps() {
        let mut worst = 0.0f64;
        for i in -87_000..=88_000 {
            let x = (f64::from(i) * 1e-3) as f32;
            let want = f64::from(x).exp();
            let got = f64::from(exp_f32(x));
            // One ulp of the exact value, in f32.
            let ulp = f64::from(f32::EPSILON) * want;
            worst = worst.max((got - want).abs() / ulp);
        }
        assert!(worst <= 3.0, "{worst} ulps");
        assert!(exp_f32(f32::NAN).is_nan());
        assert_eq!(exp_f32(0.0), 1.0);
        assert!(exp_f32(200.0).is_finite() && exp_f32(-200.0) > 0.0);
    }

    /// Values and gradients against the float64 reference: f32 within 4 ulps of the value
    /// (plus 1e-30 absolute, for the clamped exponential far below zero) and 1e-5 of the
    /// derivative (whose terms cancel near its zero at x ≈ -1.19); f64 to 1e-13. NaN stays
    /// NaN. Against candle's composition where that is accurate, f32 within 2e-6 relative.
    #[test]
    fn mish_matches_a_float64_reference() -> Result<()> {
        let xs = inputs()?;
        let gs: Vec<f64> = crate::kernels::test_util::rand(&[xs.len()], 4).to_vec1::<f64>()?;
        let dev = candle_core::Device::Cpu;
        for (dtype, value_tol, grad_tol) in [
            (DType::F32, 4.0 * f64::from(f32::EPSILON), 1e-5),
            (DType::F64, 1e-13, 1e-13),
        ] {
            let x = Var::from_tensor(&Tensor::new(xs.as_slice(), &dev)?.to_dtype(dtype)?)?;
            let r = Tensor::new(gs.as_slice(), &dev)?.to_dtype(dtype)?;
            let y = mish(x.as_tensor())?;
            let (dx, _) = probe_gradient(&y, &r, &x);
            let as64 = |t: &Tensor| t.to_dtype(DType::F64).and_then(|t| t.to_vec1::<f64>());
            let (xv, yv, dv) = (as64(x.as_tensor())?, as64(&y)?, as64(&dx)?);
            for i in 0..xs.len() {
                let (want, slope) = reference(xv[i]);
                let tol = value_tol * want.abs() + 1e-30;
                assert!(
                    (yv[i] - want).abs() <= tol,
                    "{dtype:?} mish({}) = {} vs {want}",
                    xv[i],
                    yv[i]
                );
                let want_g = gs[i] * slope;
                let tol = grad_tol * want_g.abs().max(gs[i].abs());
                assert!(
                    (dv[i] - want_g).abs() <= tol,
                    "{dtype:?} mish'({}): {} vs {want_g}",
                    xv[i],
                    dv[i]
                );
            }
            // An untracked input gives the same values.
            assert_eq!(bits(&mish(&x.as_tensor().detach())?), bits(&y), "{dtype:?}");
            // The composition agrees to its own rounding: `ln(1 + eˣ)` carries an absolute
            // error of about half an ulp of one, which `x` multiplies.
            let mid = Tensor::new(&xs[..400], &dev)?
                .to_dtype(dtype)?
                .clamp(-12.0, 12.0)?;
            let (ours, theirs) = (as64(&mish(&mid)?)?, as64(&candle_nn::ops::mish(&mid)?)?);
            for ((a, b), x) in ours.iter().zip(&theirs).zip(as64(&mid)?) {
                let tol = 2e-6 * b.abs() + 1e-7 * (1.0 + x.abs());
                assert!((a - b).abs() <= tol, "mish({x}): {a} vs {b}");
            }
        }
        let nan = Tensor::new(&[f32::NAN, 1.0], &dev)?;
        let out = mish(&nan)?.to_vec1::<f32>()?;
        assert!(out[0].is_nan() && out[1].is_finite());
        Ok(())
    }

    /// The f64 gradient is the derivative of the f64 values (central differences).
    #[test]
    fn mish_gradient_is_the_derivative() -> Result<()> {
        let dev = candle_core::Device::Cpu;
        let xs = inputs()?;
        let x = Var::from_tensor(&Tensor::new(xs.as_slice(), &dev)?)?;
        let ones = Tensor::ones(xs.len(), DType::F64, &dev)?;
        let (dx, _) = probe_gradient(&mish(x.as_tensor())?, &ones, &x);
        let dx = dx.to_vec1::<f64>()?;
        let h = 1e-6;
        let at = |v: Vec<f64>| -> Result<Vec<f64>> {
            mish(&Tensor::new(v.as_slice(), &dev)?)?.to_vec1::<f64>()
        };
        let up = at(xs.iter().map(|v| v + h).collect())?;
        let down = at(xs.iter().map(|v| v - h).collect())?;
        for i in 0..xs.len() {
            if (xs[i] - f64::from(MISH_LINEAR)).abs() < 2.0 * h {
                continue; // the switch to the identity sits between the two probes
            }
            let fd = (up[i] - down[i]) / (2.0 * h);
            assert!(
                (fd - dx[i]).abs() <= 1e-7 * (1.0 + xs[i].abs()),
                "x {}: {fd} vs {}",
                xs[i],
                dx[i]
            );
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
