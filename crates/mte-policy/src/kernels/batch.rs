//! Matrix products that are *batch-invariant*: each sample of a batch gets the same
//! floating-point operations, in the same order, whatever else is in the batch.
//!
//! Why: the lockstep evaluation runner queries the policy once for every episode that
//! queries at that control step, so which episodes share a batch depends on the schedule of
//! the others. A result must not. One fused product `(C_out, C k) x (C k, B T)` is not
//! batch-invariant: the gemm kernel picks its blocking and even its algorithm (horizontal
//! kernels for small outputs, gemv for one column, the depth blocking `kc`) from the product's
//! shape, so an element's summation order can change with `B`. Here the products are
//! `super::product`'s, whose every output element is defined as one chain of fused
//! multiply-adds in the order of depth: a batch of `B` reproduces `B` single queries bit for
//! bit however the kernel tiles them. (Until 2026-11-28 each sample was its own gemm call of
//! a batch of one's shape: batch-invariant too, but gemm's edge kernels for a sample's 16
//! columns made the batch-64 U-Net 2.5-2.9x slower than PyTorch.) Elementwise ops, row
//! reductions (GroupNorm, softmax) and the DDPM step are per-sample already.
//!
//! The products are candle ops, so gradients flow through them as through any other.
//!
//! Training needs no batch invariance and is faster fused (one product with all samples'
//! columns: 2.1x faster for the `cpu` U-Net's training step at batch 64, `benches/unet.rs`),
//! so each function takes the [`Products`] to compute: evaluation paths (sampling, PGD,
//! evaluation-crop image features) ask for [`Products::PerSample`], training paths for
//! [`Products::Fused`].

use super::product::{Dims, Element, Shared};
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp2, Layout, Result, Shape, Tensor, WithDType};

/// How a batch's shared-weight products are computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Products {
    /// One product per sample, of a batch of one's shape: batch-invariant (evaluation).
    PerSample,
    /// One product for the whole batch: faster, and its rounding may depend on the batch
    /// (training).
    Fused,
}

/// `w (m, k)` times every sample of `x (B, k, n)`: `(B, m, n)`.
pub fn left_shared(w: &Tensor, x: &Tensor, products: Products) -> Result<Tensor> {
    match products {
        Products::PerSample => per_sample(x, w, Side::Left),
        Products::Fused => {
            // (m, k) x (k, B n), then back to (B, m, n).
            let (b, k, n) = x.dims3()?;
            let cols = x.transpose(0, 1)?.contiguous()?.reshape((k, b * n))?;
            let m = w.dim(0)?;
            w.matmul(&cols)?
                .reshape((m, b, n))?
                .transpose(0, 1)?
                .contiguous()
        }
    }
}

/// Every sample of `x (B, m, k)` times `w (k, n)`: `(B, m, n)`.
pub fn right_shared(x: &Tensor, w: &Tensor, products: Products) -> Result<Tensor> {
    match products {
        Products::PerSample => per_sample(x, w, Side::Right),
        Products::Fused => {
            let (b, m, k) = x.dims3()?;
            let n = w.dim(1)?;
            x.reshape((b * m, k))?.matmul(w)?.reshape((b, m, n))
        }
    }
}

/// Which side of the product the shared matrix is on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Side {
    /// `W x_b`.
    Left,
    /// `x_b W`.
    Right,
}

/// Each sample of `x (B, p, q)` times the shared `w` on `side`, as one custom op on the CPU
/// (`super::product`'s kernel, so the result is bit for bit the batch of one's); its
/// backward pass is the same op with `wᵀ`, linear in the batch (a
/// per-sample `narrow` would cost `O(B²)` in the backward pass). Gradients flow to `x` only:
/// per-sample products serve evaluation and attacks, where the weights are constants.
/// Elsewhere than the CPU, one candle product per sample.
fn per_sample(x: &Tensor, w: &Tensor, side: Side) -> Result<Tensor> {
    if !x.device().is_cpu() {
        let b = x.dim(0)?;
        let outs = (0..b)
            .map(|i| {
                let xb = x.get(i)?;
                match side {
                    Side::Left => w.matmul(&xb),
                    Side::Right => xb.matmul(w),
                }
            })
            .collect::<Result<Vec<_>>>()?;
        return Tensor::stack(&outs, 0);
    }
    // The weight as stored (contiguous), and whether the product reads it transposed.
    let (stored, transpose) = if w.is_contiguous() {
        (w.clone(), false)
    } else if w.t()?.is_contiguous() {
        (w.t()?, true)
    } else {
        (w.contiguous()?, false)
    };
    x.contiguous()?
        .apply_op2(&stored, PerSampleProduct { side, transpose })
}

/// The custom op of [`per_sample`]: `x (B, p, q)` and the stored weight.
#[derive(Clone, Copy, Debug)]
pub(super) struct PerSampleProduct {
    pub(super) side: Side,
    pub(super) transpose: bool,
}

impl PerSampleProduct {
    /// Each sample's product, read in place from the two storages through
    /// [`super::product`]'s kernel, whose every element's arithmetic is fixed (so a sample's
    /// result is the same bits whatever shares its batch). The weight is packed once per
    /// call, never per sample (at the `paper` preset a copy per product moved ~1 GB per
    /// U-Net forward).
    pub(super) fn products<T: WithDType + Element>(
        &self,
        x: &CpuStorage,
        lx: &Layout,
        w: &CpuStorage,
        lw: &Layout,
    ) -> Result<(Vec<T>, Shape)> {
        let [b, p, q] = *lx.dims() else {
            candle_core::bail!(
                "per-sample product: x must be (B, p, q), got {:?}",
                lx.dims()
            );
        };
        let (Some((x0, _)), Some((w0, _))) = (lx.contiguous_offsets(), lw.contiguous_offsets())
        else {
            candle_core::bail!("per-sample product: operands must be contiguous");
        };
        let &[s0, s1] = lw.dims() else {
            candle_core::bail!(
                "per-sample product: w must be a matrix, got {:?}",
                lw.dims()
            );
        };
        let xs = T::cpu_storage_as_slice(x)?.get(x0..x0 + b * p * q);
        let ws = T::cpu_storage_as_slice(w)?.get(w0..w0 + s0 * s1);
        let (Some(xs), Some(ws)) = (xs, ws) else {
            candle_core::bail!("per-sample product: a layout runs past its storage");
        };
        // The matrix multiplied is `(wr, wc)`: the stored one or its transpose.
        let (wr, wc) = if self.transpose { (s1, s0) } else { (s0, s1) };
        let (m, k, n, inner) = match self.side {
            Side::Left => (wr, wc, q, p),
            Side::Right => (p, q, wc, wr),
        };
        if inner != k {
            candle_core::bail!(
                "per-sample product: inner dimensions differ, x {:?} and w ({wr}, {wc}) on the {:?}",
                lx.dims(),
                self.side
            );
        }
        let dims = Dims { m, k, n };
        let weight = Shared::Plain {
            data: ws,
            transposed: self.transpose,
        };
        let mut out = vec![T::ZERO; b * m * n];
        super::product::products(self.side, weight, xs, dims, b, &mut out);
        Ok((out, Shape::from((b, m, n))))
    }

    /// [`PerSampleProduct::products`] as a storage.
    pub(super) fn forward<T: WithDType + Element>(
        &self,
        x: &CpuStorage,
        lx: &Layout,
        w: &CpuStorage,
        lw: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (out, shape) = self.products::<T>(x, lx, w, lw)?;
        Ok((T::to_cpu_storage_owned(out), shape))
    }
}

impl CustomOp2 for PerSampleProduct {
    fn name(&self) -> &'static str {
        "mte-per-sample-product"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        match (s1, s2) {
            (CpuStorage::F32(_), CpuStorage::F32(_)) => self.forward::<f32>(s1, l1, s2, l2),
            (CpuStorage::F64(_), CpuStorage::F64(_)) => self.forward::<f64>(s1, l1, s2, l2),
            _ => candle_core::bail!(
                "per-sample product: unsupported dtypes {:?} x {:?}",
                s1.dtype(),
                s2.dtype()
            ),
        }
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        // d/dx_b of (W' x_b) is W'ᵀ g_b, of (x_b W') is g_b W'ᵀ: the same side, W'
        // transposed.
        let back = PerSampleProduct {
            side: self.side,
            transpose: !self.transpose,
        };
        let grad = grad.contiguous()?;
        let dx = grad.apply_op2_no_bwd(w, &back)?;
        // The weight's gradient, summed over the batch, only where the weight is tracked.
        let dw = if w.track_op() {
            let (b, p, q) = x.dims3()?;
            let n = grad.dim(2)?;
            let dw_used = match self.side {
                // Σ_b g_b x_bᵀ: (m, B n) x (B n, k).
                Side::Left => {
                    let m = grad.dim(1)?;
                    let g = grad.transpose(0, 1)?.contiguous()?.reshape((m, b * n))?;
                    let xs = x.transpose(0, 1)?.contiguous()?.reshape((p, b * q))?;
                    g.matmul(&xs.t()?)?
                }
                // Σ_b x_bᵀ g_b: (q, B p) x (B p, n).
                Side::Right => x
                    .reshape((b * p, q))?
                    .t()?
                    .matmul(&grad.reshape((b * p, n))?)?,
            };
            Some(if self.transpose {
                dw_used.t()?.contiguous()?
            } else {
                dw_used
            })
        } else {
            None
        };
        Ok((Some(dx), dw))
    }
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
    pub fn forward(&self, x: &Tensor, products: Products) -> Result<Tensor> {
        let y = match products {
            Products::PerSample => {
                let (b, i) = x.dims2()?;
                right_shared(&x.reshape((b, 1, i))?, &self.weight.t()?, products)?.squeeze(1)?
            }
            Products::Fused => x.matmul(&self.weight.t()?)?,
        };
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
            let all = rows(&left_shared(&w, &x, Products::PerSample).expect("batch"));
            let xt = x.transpose(1, 2).expect("t").contiguous().expect("c");
            let wt = w.t().expect("t");
            let all_r = rows(&right_shared(&xt, &wt, Products::PerSample).expect("batch"));
            for i in 0..b {
                let one = x.narrow(0, i, 1).expect("one");
                assert_eq!(
                    rows(&left_shared(&w, &one, Products::PerSample).expect("one"))[0],
                    all[i]
                );
                let one = xt.narrow(0, i, 1).expect("one");
                assert_eq!(
                    rows(&right_shared(&one, &wt, Products::PerSample).expect("one"))[0],
                    all_r[i]
                );
            }
            // And it is the product: against a naive float64 loop, to float32 rounding
            // (candle 0.9's own batched matmul with a broadcast left operand folds the
            // batch into the columns and is wrong, one more reason for this module).
            let w64: Vec<Vec<f64>> = w.to_dtype(DType::F64).and_then(|t| t.to_vec2()).expect("w");
            let x64: Vec<Vec<Vec<f64>>> =
                x.to_dtype(DType::F64).and_then(|t| t.to_vec3()).expect("x");
            let fused = rows(&left_shared(&w, &x, Products::Fused).expect("fused"));
            let fused_r = rows(&right_shared(&xt, &wt, Products::Fused).expect("fused"));
            for (i, row) in all.iter().enumerate() {
                for r in 0..m {
                    for c in 0..n {
                        let want: f64 = (0..k).map(|j| w64[r][j] * x64[i][j][c]).sum();
                        for got in [row[r * n + c], fused[i][r * n + c]] {
                            let got = f64::from(got);
                            assert!((got - want).abs() < 1e-5 * k as f64, "{got} vs {want}");
                        }
                        // The right-shared product is the transpose: (n, k) x (k, m).
                        let got = f64::from(fused_r[i][c * m + r]);
                        assert!((got - want).abs() < 1e-5 * k as f64, "{got} vs {want}");
                    }
                }
            }
        }
    }

    /// `w (m, k) · x (k, n)` as `kernels::product` defines it: one fused multiply-add per
    /// term, in the order of `k`, from zero.
    fn fma_product(w: &[Vec<f32>], x: &[Vec<f32>]) -> Vec<f32> {
        let mut out = Vec::new();
        for row in w {
            let mut acc = vec![0f32; x[0].len()];
            for (&a, x_row) in row.iter().zip(x) {
                for (v, &b) in acc.iter_mut().zip(x_row) {
                    *v = a.mul_add(b, *v);
                }
            }
            out.extend(acc);
        }
        out
    }

    #[test]
    fn views_with_offsets_are_read_in_place() {
        // The products read both storages in place through their layouts: a weight and a
        // batch that start inside larger buffers (narrowed views, still contiguous), and a
        // transposed weight, give each sample's product as defined, bit for bit.
        let big_w = rand(&[40, 24], 11).to_dtype(DType::F32).expect("w");
        let big_x = rand(&[9, 24, 5], 12).to_dtype(DType::F32).expect("x");
        let w = big_w.narrow(0, 7, 16).expect("w view");
        let x = big_x.narrow(0, 3, 4).expect("x view");
        assert!(w.is_contiguous() && x.is_contiguous());
        assert!(w.layout().start_offset() > 0 && x.layout().start_offset() > 0);
        let left = rows(&left_shared(&w, &x, Products::PerSample).expect("left"));
        let xt = x.transpose(1, 2).expect("t").contiguous().expect("c");
        let right = rows(&right_shared(&xt, &w.t().expect("t"), Products::PerSample).expect("r"));
        let vec2 = |t: &Tensor| t.to_vec2::<f32>().expect("matrix");
        for i in 0..4 {
            let xi = vec2(&x.get(i).expect("sample"));
            assert_eq!(fma_product(&vec2(&w), &xi), left[i]);
            let xti = vec2(&xt.get(i).expect("sample"));
            let wt = vec2(&w.t().expect("t").contiguous().expect("c"));
            assert_eq!(fma_product(&xti, &wt), right[i]);
        }
    }

    #[test]
    fn per_sample_gradients_equal_the_fused_ones() {
        let w = rand(&[6, 10], 5);
        let r = rand(&[4, 6, 3], 6);
        let x = candle_core::Var::from_tensor(&rand(&[4, 10, 3], 7)).expect("var");
        let grad = |products| {
            let y = left_shared(&w, x.as_tensor(), products).expect("y");
            let g = (y * &r)
                .and_then(|v| v.sum_all())
                .and_then(|l| l.backward());
            g.expect("backward")
                .get(x.as_tensor())
                .expect("grad")
                .clone()
        };
        let d =
            crate::kernels::test_util::max_diff(&grad(Products::PerSample), &grad(Products::Fused));
        assert!(d < 1e-12, "{d}");
        // Right side, through a transposed weight (as nn.Linear reads it), the weight a
        // variable too: both gradients.
        let wv = candle_core::Var::from_tensor(&rand(&[10, 6], 10)).expect("var");
        let xr = candle_core::Var::from_tensor(&rand(&[4, 3, 6], 8)).expect("var");
        let rr = rand(&[4, 3, 10], 9);
        let grad_r = |products| {
            let wt = wv.as_tensor().t().expect("t");
            let y = right_shared(xr.as_tensor(), &wt, products).expect("y");
            let g = (y * &rr)
                .and_then(|v| v.sum_all())
                .and_then(|l| l.backward());
            let g = g.expect("backward");
            let get = |t: &Tensor| g.get(t).expect("grad").clone();
            (get(xr.as_tensor()), get(wv.as_tensor()))
        };
        let (a, b) = (grad_r(Products::PerSample), grad_r(Products::Fused));
        let d = crate::kernels::test_util::max_diff(&a.0, &b.0);
        assert!(d < 1e-12, "{d}");
        let d = crate::kernels::test_util::max_diff(&a.1, &b.1);
        assert!(d < 1e-12, "weight gradient: {d}");
        // Left side with a variable weight.
        let wl = candle_core::Var::from_tensor(&w).expect("var");
        let grad_w = |products| {
            let y = left_shared(wl.as_tensor(), x.as_tensor(), products).expect("y");
            let g = (y * &r)
                .and_then(|v| v.sum_all())
                .and_then(|l| l.backward());
            g.expect("backward")
                .get(wl.as_tensor())
                .expect("grad")
                .clone()
        };
        let d = crate::kernels::test_util::max_diff(
            &grad_w(Products::PerSample),
            &grad_w(Products::Fused),
        );
        assert!(d < 1e-12, "left weight gradient: {d}");
    }

    #[test]
    fn linear_matches_candle_nn_and_is_row_invariant() {
        let dev = candle_core::Device::Cpu;
        let vm = candle_nn::VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 3, DType::F32, &dev);
        let inner = candle_nn::linear(40, 24, vb).expect("init");
        let ours = Linear::new(inner.clone());
        let x = rand(&[7, 40], 4).to_dtype(DType::F32).expect("x");
        for products in [Products::PerSample, Products::Fused] {
            let d = crate::kernels::test_util::max_diff(
                &ours.forward(&x, products).expect("ours"),
                &inner.forward(&x).expect("candle"),
            );
            assert!(d < 1e-5, "{d}");
        }
        let all = rows(&ours.forward(&x, Products::PerSample).expect("all"));
        for (i, row) in all.iter().enumerate() {
            let one = ours
                .forward(&x.narrow(0, i, 1).expect("one"), Products::PerSample)
                .expect("one");
            assert_eq!(&rows(&one)[0], row);
        }
    }
}
