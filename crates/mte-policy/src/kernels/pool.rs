//! Max pool, kernel 3, stride 2, padding 1 (torchvision ResNet's stem pool), with a backward
//! pass that routes each output's gradient to its window's arg-max (the first one in raster
//! order on ties, as torch does). Padding never wins: it is -inf, as in torch.
//!
//! Input `(B, C, H, W)`, output `(B, C, ⌊(H - 1) / 2⌋ + 1, ⌊(W - 1) / 2⌋ + 1)`.

use super::{Float, contiguous};
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

fn out_len(n: usize) -> usize {
    (n - 1) / 2 + 1
}

/// For output (oy, ox) of an `h x w` plane: the input offset of the window's arg-max.
#[inline]
fn argmax<T: Float>(plane: &[T], h: usize, w: usize, oy: usize, ox: usize) -> usize {
    let mut best = usize::MAX;
    let mut best_v = f64::NEG_INFINITY;
    for iy in (2 * oy).saturating_sub(1)..(2 * oy + 2).min(h) {
        for ix in (2 * ox).saturating_sub(1)..(2 * ox + 2).min(w) {
            let v = plane[iy * w + ix].to_f64();
            if best == usize::MAX || v > best_v {
                best = iy * w + ix;
                best_v = v;
            }
        }
    }
    best
}

fn pool<T: Float>(x: &[T], h: usize, w: usize) -> Vec<T> {
    let (ho, wo) = (out_len(h), out_len(w));
    let mut y = vec![T::default(); x.len() / (h * w) * ho * wo];
    y.par_chunks_mut(ho * wo)
        .zip(x.par_chunks(h * w))
        .for_each(|(yp, xp)| {
            for oy in 0..ho {
                for ox in 0..wo {
                    yp[oy * wo + ox] = xp[argmax(xp, h, w, oy, ox)];
                }
            }
        });
    y
}

fn unpool<T: Float>(x: &[T], dy: &[T], h: usize, w: usize) -> Vec<T> {
    let (ho, wo) = (out_len(h), out_len(w));
    let mut dx = vec![T::default(); x.len()];
    dx.par_chunks_mut(h * w)
        .zip(x.par_chunks(h * w).zip(dy.par_chunks(ho * wo)))
        .for_each(|(dxp, (xp, dyp))| {
            for oy in 0..ho {
                for ox in 0..wo {
                    dxp[argmax(xp, h, w, oy, ox)] += dyp[oy * wo + ox];
                }
            }
        });
    dx
}

fn plane(layout: &Layout) -> Result<(usize, usize, usize)> {
    match layout.dims() {
        &[b, c, h, w] if h > 0 && w > 0 => Ok((b * c, h, w)),
        d => candle_core::bail!("max_pool_3x3_s2: expected (B, C, H, W), got {d:?}"),
    }
}

struct MaxPool;

impl CustomOp1 for MaxPool {
    fn name(&self) -> &'static str {
        "mte-max-pool-3x3-s2"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (_, h, w) = plane(l)?;
        let d = l.dims();
        let out = match s {
            CpuStorage::F32(x) => CpuStorage::F32(pool(contiguous(x, l)?, h, w)),
            CpuStorage::F64(x) => CpuStorage::F64(pool(contiguous(x, l)?, h, w)),
            _ => candle_core::bail!("max pool: unsupported dtype {:?}", s.dtype()),
        };
        Ok((out, Shape::from((d[0], d[1], out_len(h), out_len(w)))))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(x.apply_op2_no_bwd(&grad.contiguous()?, &MaxUnpool)?))
    }
}

struct MaxUnpool;

impl CustomOp2 for MaxUnpool {
    fn name(&self) -> &'static str {
        "mte-max-unpool-3x3-s2"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (_, h, w) = plane(l1)?;
        let out = match (s1, s2) {
            (CpuStorage::F32(x), CpuStorage::F32(dy)) => {
                CpuStorage::F32(unpool(contiguous(x, l1)?, contiguous(dy, l2)?, h, w))
            }
            (CpuStorage::F64(x), CpuStorage::F64(dy)) => {
                CpuStorage::F64(unpool(contiguous(x, l1)?, contiguous(dy, l2)?, h, w))
            }
            _ => candle_core::bail!("max unpool: unsupported dtype {:?}", s1.dtype()),
        };
        Ok((out, l1.shape().clone()))
    }
}

/// Max pool 3x3, stride 2, padding 1 of `(B, C, H, W)`: the fused kernel on the CPU;
/// elsewhere strided views of the zero-padded input, which equal torch's -inf padding for
/// non-negative inputs (the encoder pools after a ReLU).
pub fn max_pool_3x3_s2(x: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() {
        return x.contiguous()?.apply_op1(MaxPool);
    }
    max_pool_3x3_s2_views(&x.pad_with_zeros(2, 1, 1)?.pad_with_zeros(3, 1, 1)?)
}

/// Max pool 3x3 with stride 2, no padding, as the maximum of nine strided views: the same
/// values as candle's `max_pool2d_with_stride(3, 2)`, but differentiable (candle's max-pool
/// backward only supports kernel = stride). The non-CPU path.
fn max_pool_3x3_s2_views(x: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let (oh, ow) = ((h - 3) / 2 + 1, (w - 3) / 2 + 1);
    // One spare zero row and column so every offset's strided view fits; the spare cells
    // are only ever read as the discarded half of a pair.
    let x = x.pad_with_zeros(2, 0, 1)?.pad_with_zeros(3, 0, 1)?;
    let mut out: Option<Tensor> = None;
    for dy in 0..3 {
        let rows = x
            .narrow(2, dy, 2 * oh)?
            .reshape((b, c, oh, 2, w + 1))?
            .narrow(3, 0, 1)?
            .squeeze(3)?;
        for dx in 0..3 {
            let v = rows
                .narrow(3, dx, 2 * ow)?
                .reshape((b, c, oh, ow, 2))?
                .narrow(4, 0, 1)?
                .squeeze(4)?;
            out = Some(match out {
                None => v,
                Some(m) => m.maximum(&v)?,
            });
        }
    }
    out.ok_or_else(|| candle_core::Error::Msg("empty max pool".into()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::{max_diff, rand};
    use candle_core::Var;

    /// torch's pool: pad with -inf, 3x3 windows at stride 2 (reference by brute force).
    fn reference(x: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        let v = x.flatten_all()?.to_vec1::<f64>()?;
        let (ho, wo) = (out_len(h), out_len(w));
        let mut out = Vec::new();
        for p in 0..b * c {
            for oy in 0..ho {
                for ox in 0..wo {
                    let mut m = f64::NEG_INFINITY;
                    for ky in 0..3 {
                        for kx in 0..3 {
                            let (iy, ix) = ((2 * oy + ky) as isize - 1, (2 * ox + kx) as isize - 1);
                            if iy >= 0 && ix >= 0 && (iy as usize) < h && (ix as usize) < w {
                                m = m.max(v[p * h * w + iy as usize * w + ix as usize]);
                            }
                        }
                    }
                    out.push(m);
                }
            }
        }
        Tensor::from_vec(out, (b, c, ho, wo), x.device())
    }

    /// Negative values too: padding must not win (the -inf convention).
    #[test]
    fn values_match_brute_force_and_the_view_version() -> Result<()> {
        for (i, (h, w)) in [(8, 8), (9, 7), (42, 42), (1, 3)].into_iter().enumerate() {
            let x = rand(&[2, 3, h, w], i as u64);
            let ours = max_pool_3x3_s2(&x)?;
            assert_eq!(max_diff(&ours, &reference(&x)?), 0.0, "case {i}");
            let relu = x.relu()?;
            let fused = max_pool_3x3_s2(&relu)?;
            let padded = relu.pad_with_zeros(2, 1, 1)?.pad_with_zeros(3, 1, 1)?;
            let views = max_pool_3x3_s2_views(&padded)?;
            assert_eq!(max_diff(&fused, &views), 0.0, "case {i}: view version");
            if h >= 3 && w >= 3 {
                let candle = x.max_pool2d_with_stride(3, 2)?;
                let unpadded = max_pool_3x3_s2_views(&x)?;
                assert_eq!(max_diff(&candle, &unpadded), 0.0, "case {i}: candle's pool");
            }
        }
        Ok(())
    }

    /// The gradient is each output's upstream gradient at its window's arg-max, summed where
    /// windows overlap: checked against finite differences (inputs are distinct, so the
    /// max is piecewise linear and a small step does not switch winners).
    #[test]
    fn gradient_matches_finite_differences() -> Result<()> {
        let x = Var::from_tensor(&rand(&[1, 2, 7, 6], 5))?;
        let r = rand(&[1, 2, 4, 3], 6);
        let probe = |x: &Tensor| (max_pool_3x3_s2(x)? * &r)?.sum_all();
        let g = probe(x.as_tensor())?.backward()?;
        let g = g.get(x.as_tensor()).expect("gradient").flatten_all()?;
        let g = g.to_vec1::<f64>()?;
        let base = x.as_tensor().flatten_all()?.to_vec1::<f64>()?;
        for j in 0..base.len() {
            let at = |d: f64| -> Result<f64> {
                let mut b = base.clone();
                b[j] += d;
                probe(&Tensor::from_vec(b, (1, 2, 7, 6), x.device())?)?.to_scalar::<f64>()
            };
            let fd = (at(1e-7)? - at(-1e-7)?) / 2e-7;
            assert!((fd - g[j]).abs() < 1e-6, "element {j}: {} vs {fd}", g[j]);
        }
        Ok(())
    }
}
