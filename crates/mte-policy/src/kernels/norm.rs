//! GroupNorm in one pass forward and one pass backward.
//!
//! Input `(B, C, ...)`, `G` groups of `C / G` consecutive channels; per (sample, group):
//! `x̂ = (x - μ) / sqrt(σ² + ε)` with the biased variance (torch's convention), then
//! `y = γ_c x̂ + β_c`. Backward, with `n` elements per group and `ĝ = γ_c · dy`:
//! `dx = (ĝ - mean(ĝ) - x̂ · mean(ĝ x̂)) / sqrt(σ² + ε)`, `dγ_c = Σ dy x̂`, `dβ_c = Σ dy`.

use super::Float;
use candle_core::{CpuStorage, CustomOp3, Layout, Module, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

#[derive(Clone, Copy, Debug)]
struct Dims {
    c: usize,
    s: usize,
    groups: usize,
    eps: f64,
}

impl Dims {
    fn of(layout: &Layout, groups: usize, eps: f64) -> Result<Self> {
        let d = layout.dims();
        if d.len() < 2 || groups == 0 || !d[1].is_multiple_of(groups) {
            candle_core::bail!("group_norm: shape {d:?} does not split into {groups} groups")
        }
        Ok(Dims {
            c: d[1],
            s: d[2..].iter().product(),
            groups,
            eps,
        })
    }

    /// Elements of one (sample, group) block, and channels per group.
    fn block(&self) -> (usize, usize) {
        let cg = self.c / self.groups;
        (cg * self.s, cg)
    }
}

/// Blocks computed together: each block's sums stay sequential in index order, from `-0.0` (as
/// `f64`'s `Sum` does), but up to this many blocks' chains of additions interleave, so a
/// sum's latency no longer bounds the loop. The bits are each block's alone.
const INTERLEAVE: usize = 8;

/// Mean and 1 / sqrt(var + eps) of each of the `xs.len() / n` (at most [`INTERLEAVE`])
/// blocks of `n` values in `xs`.
fn moments<T: Float>(xs: &[T], n: usize, eps: f64) -> [(f64, f64); INTERLEAVE] {
    let k = xs.len() / n;
    let mut sum = [-0.0f64; INTERLEAVE];
    for i in 0..n {
        for (j, s) in sum.iter_mut().enumerate().take(k) {
            *s += xs[j * n + i].to_f64();
        }
    }
    let mean = sum.map(|s| s / n as f64);
    let mut sq = [-0.0f64; INTERLEAVE];
    for i in 0..n {
        for (j, s) in sq.iter_mut().enumerate().take(k) {
            let d = xs[j * n + i].to_f64() - mean[j];
            *s += d * d;
        }
    }
    std::array::from_fn(|j| (mean[j], 1.0 / (sq[j] / n as f64 + eps).sqrt()))
}

fn forward<T: Float>(x: &[T], gamma: &[T], beta: &[T], d: Dims) -> Vec<T> {
    let (n, cg) = d.block();
    let mut y = vec![T::default(); x.len()];
    y.par_chunks_mut(n * INTERLEAVE)
        .zip(x.par_chunks(n * INTERLEAVE))
        .enumerate()
        .for_each(|(chunk, (ys, xs))| {
            let m = moments(xs, n, d.eps);
            let blocks = ys.chunks_mut(n).zip(xs.chunks(n)).zip(m);
            for (j, ((yb, xb), (mean, rstd))) in blocks.enumerate() {
                let g = (chunk * INTERLEAVE + j) % d.groups;
                for ci in 0..cg {
                    let c = g * cg + ci;
                    let (ga, be) = (gamma[c].to_f64(), beta[c].to_f64());
                    let r = ci * d.s..(ci + 1) * d.s;
                    for (yv, xv) in yb[r.clone()].iter_mut().zip(&xb[r]) {
                        *yv = T::from_f64((xv.to_f64() - mean) * rstd * ga + be);
                    }
                }
            }
        });
    y
}

/// Per block of an interleaved chunk: its channels' `(Σ dy x̂, Σ dy)` and its `(mean(γ dy),
/// mean(γ dy x̂))`, each sum in index order.
type BlockSums = (Vec<(f64, f64)>, (f64, f64));

/// [`BlockSums`] of the `xs.len() / n` blocks (first block `first`) of one chunk; the
/// channels' sums only where `params` asks for γ's and β's gradients (each sum is its own
/// chain, so skipping them changes no other bit).
fn block_sums<T: Float>(
    (xs, dys): (&[T], &[T]),
    m: &[(f64, f64); INTERLEAVE],
    gamma: &[T],
    (first, n, d, params): (usize, usize, Dims, bool),
) -> Vec<BlockSums> {
    let (_, cg) = d.block();
    let k = xs.len() / n;
    let mut sums: Vec<BlockSums> =
        vec![(vec![(0.0, 0.0); if params { cg } else { 0 }], (0.0, 0.0)); k];
    for ci in 0..cg {
        let ga: [f64; INTERLEAVE] = std::array::from_fn(|j| {
            let g = (first + j) % d.groups;
            gamma.get(g * cg + ci).map_or(0.0, |v| v.to_f64())
        });
        for i in ci * d.s..(ci + 1) * d.s {
            for (j, (ch, (m_g, m_gx))) in sums.iter_mut().enumerate() {
                let (mean, rstd) = m[j];
                let xh = (xs[j * n + i].to_f64() - mean) * rstd;
                let dv = dys[j * n + i].to_f64();
                if let Some(ch) = ch.get_mut(ci) {
                    ch.0 += dv * xh;
                    ch.1 += dv;
                }
                *m_g += ga[j] * dv;
                *m_gx += ga[j] * dv * xh;
            }
        }
    }
    for (_, (m_g, m_gx)) in &mut sums {
        (*m_g, *m_gx) = (*m_g / n as f64, *m_gx / n as f64);
    }
    sums
}

/// `[dx (B·C·S) | dγ (C) | dβ (C)]` in one buffer; `dx` alone unless `params`.
fn backward<T: Float>(x: &[T], gamma: &[T], dy: &[T], d: Dims, params: bool) -> Vec<T> {
    let (n, cg) = d.block();
    let mut dx = vec![T::default(); x.len()];
    // Per block: its channels' (Σ dy x̂, Σ dy), summed over the batch afterwards.
    let partial: Vec<Vec<(f64, f64)>> = dx
        .par_chunks_mut(n * INTERLEAVE)
        .zip(
            x.par_chunks(n * INTERLEAVE)
                .zip(dy.par_chunks(n * INTERLEAVE)),
        )
        .enumerate()
        .flat_map_iter(|(chunk, (dxs, (xs, dys)))| {
            let first = chunk * INTERLEAVE;
            let m = moments(xs, n, d.eps);
            let sums = block_sums((xs, dys), &m, gamma, (first, n, d, params));
            let blocks = dxs.chunks_mut(n).zip(xs.chunks(n).zip(dys.chunks(n)));
            for (j, (dxb, (xb, dyb))) in blocks.enumerate() {
                let g = (first + j) % d.groups;
                let ((mean, rstd), (_, (m_g, m_gx))) = (m[j], &sums[j]);
                for ci in 0..cg {
                    let ga = gamma[g * cg + ci].to_f64();
                    let r = ci * d.s..(ci + 1) * d.s;
                    let each = dxb[r.clone()].iter_mut().zip(&xb[r.clone()]).zip(&dyb[r]);
                    for ((o, xv), dv) in each {
                        let xh = (xv.to_f64() - mean) * rstd;
                        *o = T::from_f64(rstd * (ga * dv.to_f64() - m_g - xh * m_gx));
                    }
                }
            }
            sums.into_iter().map(|(ch, _)| ch)
        })
        .collect();
    if !params {
        return dx;
    }
    let mut dgamma = vec![0.0; d.c];
    let mut dbeta = vec![0.0; d.c];
    for (blk, sums) in partial.iter().enumerate() {
        let g = blk % d.groups;
        for (ci, (sg, sb)) in sums.iter().enumerate() {
            dgamma[g * cg + ci] += sg;
            dbeta[g * cg + ci] += sb;
        }
    }
    dx.extend(dgamma.into_iter().map(T::from_f64));
    dx.extend(dbeta.into_iter().map(T::from_f64));
    dx
}

#[derive(Clone, Copy, Debug)]
struct GroupNormOp {
    groups: usize,
    eps: f64,
}

impl CustomOp3 for GroupNormOp {
    fn name(&self) -> &'static str {
        "mte-group-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let d = Dims::of(l1, self.groups, self.eps)?;
        let out = float_storages!(
            "group_norm",
            [(x, s1, l1), (g, s2, l2), (b, s3, l3)],
            forward(x, g, b, d)
        );
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gamma: &Tensor,
        beta: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        // A loaded checkpoint's γ and β are constants: then only `dx` is computed.
        let params = gamma.track_op() || beta.track_op();
        let op = GroupNormBwd(*self, params);
        let all = x.apply_op3_no_bwd(gamma, &grad.contiguous()?, &op)?;
        let (n, c) = (x.elem_count(), x.dim(1)?);
        if !params {
            return Ok((Some(all.reshape(x.shape())?), None, None));
        }
        Ok((
            Some(all.narrow(0, 0, n)?.reshape(x.shape())?),
            Some(all.narrow(0, n, c)?),
            Some(all.narrow(0, n + c, c)?),
        ))
    }
}

#[derive(Clone, Copy, Debug)]
/// The backward pass; `.1`: whether γ's and β's gradients are wanted.
struct GroupNormBwd(GroupNormOp, bool);

impl CustomOp3 for GroupNormBwd {
    fn name(&self) -> &'static str {
        "mte-group-norm-bwd"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let d = Dims::of(l1, self.0.groups, self.0.eps)?;
        let out = float_storages!(
            "group_norm backward",
            [(x, s1, l1), (g, s2, l2), (dy, s3, l3)],
            backward(x, g, dy, d, self.1)
        );
        let len = l1.shape().elem_count() + if self.1 { 2 * d.c } else { 0 };
        Ok((out, Shape::from(len)))
    }
}

/// GroupNorm of `x (B, C, ...)` with per-channel `gamma`, `beta` (C): the fused kernel on
/// the CPU, candle_nn's composed version elsewhere.
pub fn group_norm(
    x: &Tensor,
    groups: usize,
    gamma: &Tensor,
    beta: &Tensor,
    eps: f64,
) -> Result<Tensor> {
    if !x.device().is_cpu() {
        let c = x.dim(1)?;
        return candle_nn::GroupNorm::new(gamma.clone(), beta.clone(), c, groups, eps)?.forward(x);
    }
    x.contiguous()?.apply_op3(
        &gamma.contiguous()?,
        &beta.contiguous()?,
        GroupNormOp { groups, eps },
    )
}

/// A GroupNorm layer with candle_nn's parameter names (`weight` = γ, `bias` = β).
#[derive(Clone, Debug)]
pub struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    groups: usize,
    eps: f64,
}

impl GroupNorm {
    /// Load/create (γ = 1, β = 0) a GroupNorm over `channels` in `groups` groups.
    pub fn new(groups: usize, channels: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        if groups == 0 || !channels.is_multiple_of(groups) {
            candle_core::bail!("group_norm: {channels} channels do not split into {groups} groups")
        }
        Ok(GroupNorm {
            weight: vb.get_with_hints(channels, "weight", candle_nn::Init::Const(1.0))?,
            bias: vb.get_with_hints(channels, "bias", candle_nn::Init::Const(0.0))?,
            groups,
            eps,
        })
    }
}

impl Module for GroupNorm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        group_norm(x, self.groups, &self.weight, &self.bias, self.eps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::{max_diff, rand};
    use candle_core::Var;

    fn composed(x: &Tensor, groups: usize, g: &Tensor, b: &Tensor) -> Result<Tensor> {
        candle_nn::GroupNorm::new(g.clone(), b.clone(), x.dim(1)?, groups, 1e-5)?.forward(x)
    }

    /// Values and all three gradients agree with candle_nn's composed GroupNorm (f64: the
    /// two differ only in summation order, ~1e-14).
    #[test]
    fn matches_candles_composed_group_norm() -> Result<()> {
        for (i, (shape, groups)) in [
            (vec![2, 8, 5, 3], 4),
            (vec![3, 6, 7], 3),
            (vec![1, 4, 9, 9], 1),
        ]
        .into_iter()
        .enumerate()
        {
            let c = shape[1];
            let x = Var::from_tensor(&rand(&shape, i as u64))?;
            let g = Var::from_tensor(&(rand(&[c], 10 + i as u64) + 1.5)?)?;
            let b = Var::from_tensor(&rand(&[c], 20 + i as u64))?;
            let r = rand(&shape, 30 + i as u64);
            let ours = group_norm(x.as_tensor(), groups, g.as_tensor(), b.as_tensor(), 1e-5)?;
            let theirs = composed(x.as_tensor(), groups, g.as_tensor(), b.as_tensor())?;
            assert!(max_diff(&ours, &theirs) < 1e-12, "case {i}: values");
            let go = (ours * &r)?.sum_all()?.backward()?;
            let gt = (theirs * &r)?.sum_all()?.backward()?;
            for v in [&x, &g, &b] {
                let (a, t) = (go.get(v.as_tensor()), gt.get(v.as_tensor()));
                let (a, t) = (a.expect("ours"), t.expect("candle's"));
                let err = max_diff(a, t);
                assert!(err < 1e-11, "case {i}: gradient max |diff| {err}");
            }
        }
        Ok(())
    }

    /// One block at a time, each sum a plain sequential loop: the definition the interleaved
    /// kernels must reproduce bit for bit.
    fn one_block_at_a_time(x: &[f64], gamma: &[f64], dy: &[f64], d: Dims) -> (Vec<f64>, Vec<f64>) {
        let (n, cg) = d.block();
        let (mut y, mut dx) = (Vec::new(), Vec::new());
        for (blk, (xb, dyb)) in x.chunks(n).zip(dy.chunks(n)).enumerate() {
            let g = blk % d.groups;
            let mean = xb.iter().sum::<f64>() / n as f64;
            let var = xb.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n as f64;
            let rstd = 1.0 / (var + d.eps).sqrt();
            let (mut m_g, mut m_gx) = (0.0, 0.0);
            for i in 0..n {
                let (ga, xh) = (gamma[g * cg + i / d.s], (xb[i] - mean) * rstd);
                y.push(xh * ga + 0.25);
                m_g += ga * dyb[i];
                m_gx += ga * dyb[i] * xh;
            }
            let (m_g, m_gx) = (m_g / n as f64, m_gx / n as f64);
            for i in 0..n {
                let (ga, xh) = (gamma[g * cg + i / d.s], (xb[i] - mean) * rstd);
                dx.push(rstd * (ga * dyb[i] - m_g - xh * m_gx));
            }
        }
        (y, dx)
    }

    /// The interleaved forward and backward give each block's bits as computed alone, for
    /// block counts below, at and above the interleave width (B · G = 3, 8, 22).
    #[test]
    fn interleaved_blocks_are_each_blocks_bits() {
        for (i, &(b, c, sp, groups)) in [(3, 4, 5, 1), (2, 8, 9, 4), (11, 6, 7, 2)]
            .iter()
            .enumerate()
        {
            let d = Dims {
                c,
                s: sp,
                groups,
                eps: 1e-5,
            };
            let v = |shape: &[usize], seed: u64| -> Vec<f64> {
                rand(shape, seed).to_vec1::<f64>().expect("values")
            };
            let (x, dy) = (
                v(&[b * c * sp], 40 + i as u64),
                v(&[b * c * sp], 50 + i as u64),
            );
            let gamma: Vec<f64> = v(&[c], 60 + i as u64).iter().map(|g| g + 1.5).collect();
            let (y_want, dx_want) = one_block_at_a_time(&x, &gamma, &dy, d);
            let y = forward(&x, &gamma, &vec![0.25; c], d);
            let dx = backward(&x, &gamma, &dy, d, true);
            let bits = |v: &[f64]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&y), bits(&y_want), "values, case {i}");
            assert_eq!(
                bits(&dx[..x.len()]),
                bits(&dx_want),
                "input gradient, case {i}"
            );
            // Without γ's and β's gradients (constant parameters): `dx` alone, same bits.
            let dx_only = backward(&x, &gamma, &dy, d, false);
            assert_eq!(bits(&dx_only), bits(&dx_want), "dx alone, case {i}");
        }
    }

    /// Constant γ and β (a loaded checkpoint): the input's gradient through candle's backward
    /// is the one it has when they are variables, and they get none.
    #[test]
    fn constant_parameters_get_no_gradient_and_change_no_bit_of_dx() -> Result<()> {
        let (x, c) = (Var::from_tensor(&rand(&[2, 8, 5, 3], 7))?, 8);
        let (g, b) = (rand(&[c], 8), rand(&[c], 9));
        let r = rand(&[2, 8, 5, 3], 10);
        let grads = |g: &Tensor, b: &Tensor| -> Result<candle_core::backprop::GradStore> {
            (group_norm(x.as_tensor(), 4, g, b, 1e-5)? * &r)?
                .sum_all()?
                .backward()
        };
        let (gv, bv) = (Var::from_tensor(&g)?, Var::from_tensor(&b)?);
        let with_params = grads(gv.as_tensor(), bv.as_tensor())?;
        let constant = grads(&g, &b)?;
        let dx = |s: &candle_core::backprop::GradStore| -> Result<Vec<u64>> {
            let t = s.get(x.as_tensor()).expect("dx").flatten_all()?;
            Ok(t.to_vec1::<f64>()?.iter().map(|v| v.to_bits()).collect())
        };
        assert_eq!(dx(&with_params)?, dx(&constant)?);
        assert!(with_params.get(gv.as_tensor()).is_some());
        assert!(constant.get(&g).is_none() && constant.get(&b).is_none());
        Ok(())
    }

    #[test]
    fn channels_not_divisible_by_groups_is_an_error() {
        let x = rand(&[1, 6, 4], 1);
        let g = rand(&[6], 2);
        let e = group_norm(&x, 4, &g, &g, 1e-5).expect_err("6 channels in 4 groups");
        assert!(e.to_string().contains("4 groups"), "{e}");
    }
}
