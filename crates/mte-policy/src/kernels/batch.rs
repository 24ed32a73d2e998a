//! Matrix products that are *batch-invariant*: each sample of a batch gets the same
//! floating-point operations, in the same order, whatever else is in the batch.
//!
//! Why: the lockstep evaluation runner queries the policy once for every episode that
//! queries at that control step, so which episodes share a batch depends on the schedule of
//! the others. A result must not. One fused product `(C_out, C k) x (C k, B T)` is not
//! batch-invariant: the gemm kernel picks its blocking and even its algorithm (horizontal
//! kernels for small outputs, gemv for one column, the depth blocking `kc`) from the product's
//! shape, so an element's summation order can change with `B`. Here every sample is one
//! product of the shape a batch of one has, so a batch of `B` reproduces `B` single queries
//! bit for bit, and a batch of one is exactly the product the policy computed before these
//! functions existed. Elementwise ops, row reductions (GroupNorm, softmax) and the DDPM
//! step are per-sample already.
//!
//! The products are candle ops, so gradients flow through them as through any other.

use candle_core::{Result, Tensor};

/// `w (m, k)` times every sample of `x (B, k, n)`: `(B, m, n)`, one `(m, k) x (k, n)`
/// product per sample.
pub fn left_shared(w: &Tensor, x: &Tensor) -> Result<Tensor> {
    per_sample(x, |xb| w.matmul(xb))
}

/// Every sample of `x (B, m, k)` times `w (k, n)`: `(B, m, n)`, one `(m, k) x (k, n)` product
/// per sample.
pub fn right_shared(x: &Tensor, w: &Tensor) -> Result<Tensor> {
    per_sample(x, |xb| xb.matmul(w))
}

/// `f` of each sample `(.., ..)` of `x (B, .., ..)`, stacked back to `(B, .., ..)`.
fn per_sample(x: &Tensor, f: impl Fn(&Tensor) -> Result<Tensor>) -> Result<Tensor> {
    let b = x.dim(0)?;
    if b == 1 {
        return f(&x.squeeze(0)?)?.unsqueeze(0);
    }
    let x = x.contiguous()?;
    let outs = (0..b).map(|i| f(&x.get(i)?)).collect::<Result<Vec<_>>>()?;
    Tensor::stack(&outs, 0)
}

/// `nn.Linear` (`y = x Wᵀ + b`, weight `(out, in)` as torch stores it) with one product per
/// row of `x (B, in)`, so each row's output is what a batch of one computes.
#[derive(Clone, Debug)]
pub struct Linear {
    weight: Tensor,
    bias: Option<Tensor>,
}

impl Linear {
    /// Wraps candle_nn's layer (same parameter names, shapes and initialisation).
    pub fn new(inner: candle_nn::Linear) -> Self {
        Linear {
            weight: inner.weight().clone(),
            bias: inner.bias().cloned(),
        }
    }

    /// `(out, in)`.
    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// `x (B, in)` -> `(B, out)`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, i) = x.dims2()?;
        let y = right_shared(&x.reshape((b, 1, i))?, &self.weight.t()?)?.squeeze(1)?;
        match &self.bias {
            Some(bias) => y.broadcast_add(bias),
            None => Ok(y),
        }
    }
}

/// `candle_nn::linear` as a batch-invariant [`Linear`].
pub fn linear(in_dim: usize, out_dim: usize, vb: candle_nn::VarBuilder) -> Result<Linear> {
    Ok(Linear::new(candle_nn::linear(in_dim, out_dim, vb)?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::rand;
    use candle_core::{DType, Module};

    fn rows(t: &Tensor) -> Vec<Vec<f32>> {
        t.to_dtype(DType::F32)
            .and_then(|t| t.flatten_from(1))
            .and_then(|t| t.to_vec2())
            .expect("rows")
    }

    #[test]
    fn each_sample_equals_its_batch_of_one() {
        // Sizes that cross the gemm's small-output and blocking thresholds when fused.
        for (m, k, n, b) in [(64, 96, 16, 9), (8, 600, 4, 17), (1, 300, 70, 5)] {
            let w = rand(&[m, k], 1).to_dtype(DType::F32).expect("w");
            let x = rand(&[b, k, n], 2).to_dtype(DType::F32).expect("x");
            let all = rows(&left_shared(&w, &x).expect("batch"));
            let xt = x.transpose(1, 2).expect("t").contiguous().expect("c");
            let wt = w.t().expect("t");
            let all_r = rows(&right_shared(&xt, &wt).expect("batch"));
            for i in 0..b {
                let one = x.narrow(0, i, 1).expect("one");
                assert_eq!(rows(&left_shared(&w, &one).expect("one"))[0], all[i]);
                let one = xt.narrow(0, i, 1).expect("one");
                assert_eq!(rows(&right_shared(&one, &wt).expect("one"))[0], all_r[i]);
            }
            // And it is the product: against a naive float64 loop, to float32 rounding
            // (candle 0.9's own batched matmul with a broadcast left operand folds the
            // batch into the columns and is wrong, one more reason for this module).
            let w64: Vec<Vec<f64>> = w.to_dtype(DType::F64).and_then(|t| t.to_vec2()).expect("w");
            let x64: Vec<Vec<Vec<f64>>> =
                x.to_dtype(DType::F64).and_then(|t| t.to_vec3()).expect("x");
            for (i, row) in all.iter().enumerate() {
                for r in 0..m {
                    for c in 0..n {
                        let want: f64 = (0..k).map(|j| w64[r][j] * x64[i][j][c]).sum();
                        let got = f64::from(row[r * n + c]);
                        assert!((got - want).abs() < 1e-5 * k as f64, "{got} vs {want}");
                    }
                }
            }
        }
    }

    #[test]
    fn linear_matches_candle_nn_and_is_row_invariant() {
        let dev = candle_core::Device::Cpu;
        let vm = candle_nn::VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 3, DType::F32, &dev);
        let inner = candle_nn::linear(40, 24, vb).expect("init");
        let ours = Linear::new(inner.clone());
        let x = rand(&[7, 40], 4).to_dtype(DType::F32).expect("x");
        let d = crate::kernels::test_util::max_diff(
            &ours.forward(&x).expect("ours"),
            &inner.forward(&x).expect("candle"),
        );
        assert!(d < 1e-5, "{d}");
        let all = rows(&ours.forward(&x).expect("all"));
        for (i, row) in all.iter().enumerate() {
            let one = ours.forward(&x.narrow(0, i, 1).expect("one")).expect("one");
            assert_eq!(&rows(&one)[0], row);
            // A batch of one is exactly candle_nn's product.
            let theirs = inner
                .forward(&x.narrow(0, i, 1).expect("one"))
                .expect("theirs");
            assert_eq!(rows(&theirs)[0], *row);
        }
    }
}
