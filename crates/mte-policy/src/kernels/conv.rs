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
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
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

fn im2col<T: Copy + Default + Send + Sync>(x: &[T], b: usize, g: Geom) -> Vec<T> {
    let (ho, wo) = g.out_hw();
    let (l, ckk, img) = (ho * wo, g.ckk(), g.c * g.h * g.w);
    let mut out = vec![T::default(); b * l * ckk];
    out.par_chunks_mut(l * ckk)
        .zip(x.par_chunks(img))
        .for_each(|(cols, src)| {
            for oy in 0..ho {
                for ox in 0..wo {
                    let row = &mut cols[(oy * wo + ox) * ckk..][..ckk];
                    g.visit(oy, ox, |col, at| row[col] = src[at]);
                }
            }
        });
    out
}

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
            for oy in 0..ho {
                for ox in 0..wo {
                    let row = &src[(oy * wo + ox) * ckk..][..ckk];
                    g.visit(oy, ox, |col, at| dst[at] += row[col]);
                }
            }
        });
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
        let out = match storage {
            CpuStorage::F32(v) => CpuStorage::F32(im2col(contiguous(v, layout)?, b, g)),
            CpuStorage::F64(v) => CpuStorage::F64(im2col(contiguous(v, layout)?, b, g)),
            other => candle_core::bail!("im2col: unsupported dtype {:?}", other.dtype()),
        };
        Ok((out, shape))
    }

    fn bwd(&self, _arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(
            grad_res.contiguous()?.apply_op1_no_bwd(&Col2Im(self.0))?,
        ))
    }
}

/// `(B, L, C k_h k_w)` → `(B, C, H, W)`, summing overlapping taps (im2col's adjoint).
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
        let out = match storage {
            CpuStorage::F32(v) => CpuStorage::F32(col2im(contiguous(v, layout)?, b, g)),
            CpuStorage::F64(v) => CpuStorage::F64(col2im(contiguous(v, layout)?, b, g)),
            other => candle_core::bail!("col2im: unsupported dtype {:?}", other.dtype()),
        };
        Ok((out, shape))
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
    use crate::kernels::test_util::rand;
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
