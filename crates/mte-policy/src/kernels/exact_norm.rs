//! candle_nn's GroupNorm, bit for bit, as one graph node for constant γ and β (the U-Net's
//! normalisation under evaluation and attack).
//!
//! candle_nn composes GroupNorm from about thirteen ops (two row sums, affine scalings, a
//! broadcast subtraction and division, a square root, the scale and shift), and its backward
//! pass from about twenty more, each a full-size temporary plus a zero-filled gradient buffer.
//! Here the forward performs the same floating-point operations in the same order (the row
//! sums by candle's own reduction, so they are its bits whatever the build's target
//! features), and the backward replays candle's rules for each op, in the order its backward
//! pass visits the nodes (a node is visited after every reader of its value, so the centred
//! input receives the division's gradient before the square's, and the input receives the
//! subtraction's before the mean's), each accumulation starting from zero. The tests compare
//! values and input gradients bit for bit with candle_nn's layer.
//!
//! `kernels::norm` is a different GroupNorm (one pass, in f64) with other bits; the image
//! encoder uses that one, the U-Net this one, so that their checkpoints' outputs are what they
//! were.

use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor, WithDType};

/// The scalar operations the replay needs.
trait NormFloat:
    WithDType
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Div<Output = Self>
    + std::ops::AddAssign
{
    fn sqrt(self) -> Self;
}

impl NormFloat for f32 {
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
}

impl NormFloat for f64 {
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
}

/// The sums of the `rows` rows of `n` values as candle's reduction (`sum_keepdim` over the
/// last, contiguous dimension) computes them in a build without its SIMD sums (none of
/// `avx2`, `neon`, `simd128` enabled at compile time, as in a default x86-64 build): each row
/// in order from zero. Computed here, without copying the values into a tensor; the test
/// against candle_nn's layer checks it is still candle's rule.
#[cfg(not(any(
    target_feature = "avx2",
    target_feature = "neon",
    target_feature = "simd128"
)))]
fn row_sums<T: NormFloat>(v: &[T], rows: usize, n: usize) -> Result<Vec<T>> {
    if n == 0 {
        return Ok(vec![T::zero(); rows]);
    }
    Ok(v.chunks_exact(n)
        .take(rows)
        .map(|row| row.iter().fold(T::zero(), |a, &b| a + b))
        .collect())
}

/// The sums of the `rows` rows of `n` values, by candle's reduction (`sum_keepdim` over the
/// last, contiguous dimension), as the composition computes them (candle's SIMD sums, in
/// this build).
#[cfg(any(
    target_feature = "avx2",
    target_feature = "neon",
    target_feature = "simd128"
))]
fn row_sums<T: NormFloat>(v: &[T], rows: usize, n: usize) -> Result<Vec<T>> {
    Tensor::from_slice(v, (rows, n), &candle_core::Device::Cpu)?
        .sum_keepdim(1)?
        .flatten_all()?
        .to_vec1::<T>()
}

/// The shape of one normalisation.
#[derive(Clone, Copy, Debug)]
struct Dims {
    /// `B · G` rows of `n = (C / G) · L` values each: element `j` of row `r` is channel
    /// `(r mod G) · C / G + j / L`, so a row holds `C / G` channels' runs of `L` values.
    rows: usize,
    n: usize,
    groups: usize,
    /// Channels, and the values per channel (`L`).
    c: usize,
    per_channel: usize,
    eps: f64,
}

impl Dims {
    fn of(layout: &Layout, groups: usize, eps: f64) -> Result<Self> {
        let dims = layout.dims();
        if dims.len() < 3 || groups == 0 || !dims[1].is_multiple_of(groups) {
            candle_core::bail!("group norm: input {dims:?} does not split into {groups} groups");
        }
        let per_channel: usize = dims[2..].iter().product();
        Ok(Dims {
            rows: dims[0] * groups,
            n: dims[1] / groups * per_channel,
            groups,
            c: dims[1],
            per_channel,
            eps,
        })
    }

    /// `1 / n` as candle's `tensor / n` scales (`affine(1 / n, 0)` in `T`).
    fn inv_n<T: NormFloat>(&self) -> T {
        T::from_f64(1.0 / self.n as f64)
    }
}

/// The centred values `x - mean` and each row's `sqrt(var + eps)`, as the composition
/// computes them.
fn centred<T: NormFloat>(x: &[T], d: Dims) -> Result<(Vec<T>, Vec<T>)> {
    let (zero, one) = (T::zero(), T::one());
    let inv_n = d.inv_n::<T>();
    let s1 = row_sums(x, d.rows, d.n)?;
    let mut xc = Vec::with_capacity(x.len());
    for (row, &s) in x.chunks_exact(d.n).zip(&s1) {
        let mean = s * inv_n + zero;
        xc.extend(row.iter().map(|&v| v - mean));
    }
    let sq: Vec<T> = xc.iter().map(|&v| v * v).collect();
    let s2 = row_sums(&sq, d.rows, d.n)?;
    let eps = T::from_f64(d.eps);
    let sd = s2
        .iter()
        .map(|&s| ((s * inv_n + zero) * one + eps).sqrt())
        .collect();
    Ok((xc, sd))
}

fn forward<T: NormFloat>(x: &[T], gamma: &[T], beta: &[T], d: Dims) -> Result<Vec<T>> {
    // The centred values become the output in place, one channel's run at a time (see
    // [`Dims::rows`]).
    let (mut y, sd) = centred(x, d)?;
    let per_group = d.c / d.groups;
    for (r, (row, &s)) in y.chunks_exact_mut(d.n).zip(&sd).enumerate() {
        let first = (r % d.groups) * per_group;
        let affine = gamma[first..first + per_group]
            .iter()
            .zip(&beta[first..first + per_group]);
        for (run, (&g, &b)) in row.chunks_exact_mut(d.per_channel).zip(affine) {
            for v in run {
                *v = (*v / s) * g + b;
            }
        }
    }
    Ok(y)
}

/// The input's gradient, replaying candle's backward rules op by op (see the module docs).
fn backward<T: NormFloat>(x: &[T], gamma: &[T], g: &[T], d: Dims) -> Result<Vec<T>> {
    let (zero, one) = (T::zero(), T::one());
    let two = one + one;
    let half = T::from_f64(0.5);
    let inv_n = d.inv_n::<T>();
    let (xc, sd) = centred(x, d)?;
    let per_group = d.c / d.groups;
    // Scale and shift, reshape: the normalised value's gradient; then the division by the
    // broadcast standard deviation, both sides. One channel's run at a time (see
    // [`Dims::rows`]), so the loops carry no index arithmetic.
    let mut from_div = Vec::with_capacity(x.len());
    let mut to_sd = Vec::with_capacity(x.len());
    for (r, &s) in sd.iter().enumerate() {
        let first = (r % d.groups) * per_group;
        let runs = g[r * d.n..(r + 1) * d.n]
            .chunks_exact(d.per_channel)
            .zip(xc[r * d.n..(r + 1) * d.n].chunks_exact(d.per_channel));
        for ((g_run, xc_run), &gamma) in runs.zip(&gamma[first..first + per_group]) {
            for (&gi, &c) in g_run.iter().zip(xc_run) {
                let gxn = zero + (zero + (zero + gi) * gamma);
                from_div.push(gxn / s);
                to_sd.push(zero - (gxn * c) / (s * s));
            }
        }
    }
    // Broadcast (a row sum), sqrt, + eps, / n, the sum of squares: each row's gradient.
    let sd_grad = row_sums(&to_sd, d.rows, d.n)?;
    let s2_grad: Vec<T> = sd_grad
        .iter()
        .zip(&sd)
        .map(|(&gs, &s)| {
            let gs = zero + gs;
            let gve = zero + ((gs / s) * half + zero);
            let gvar = zero + (gve * one + zero);
            zero + (gvar * inv_n + zero)
        })
        .collect();
    // The square's contribution after the division's; then the subtraction's two sides.
    let mut xr = Vec::with_capacity(x.len());
    let mut to_mean = Vec::with_capacity(x.len());
    let rows = from_div.chunks_exact(d.n).zip(xc.chunks_exact(d.n));
    for ((fd, xcr), &gs2) in rows.zip(&s2_grad) {
        let gsq = zero + gs2;
        for (&f, &c) in fd.iter().zip(xcr) {
            let gxc = (zero + f) + ((c * gsq) * two + zero);
            xr.push(zero + gxc);
            to_mean.push(zero - gxc);
        }
    }
    // Broadcast of the mean (a row sum), / n, the row sum of the input: added last.
    let mean_grad = row_sums(&to_mean, d.rows, d.n)?;
    for (row, &gm) in xr.chunks_exact_mut(d.n).zip(&mean_grad) {
        let gs1 = zero + ((zero + gm) * inv_n + zero);
        for v in row {
            *v += gs1;
        }
    }
    Ok(xr)
}

/// `(x, γ, β)` → GroupNorm; backward: the input's gradient only.
#[derive(Clone, Copy, Debug)]
struct ExactGroupNorm {
    groups: usize,
    eps: f64,
}

impl CustomOp3 for ExactGroupNorm {
    fn name(&self) -> &'static str {
        "mte-exact-group-norm"
    }

    fn cpu_fwd(
        &self,
        sx: &CpuStorage,
        lx: &Layout,
        sg: &CpuStorage,
        lg: &Layout,
        sb: &CpuStorage,
        lb: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let d = Dims::of(lx, self.groups, self.eps)?;
        let out = float_storages!(
            "group norm",
            [(x, sx, lx), (g, sg, lg), (b, sb, lb)],
            forward(x, g, b, d)?
        );
        Ok((out, lx.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        gamma: &Tensor,
        _beta: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let dx = x.apply_op3_no_bwd(gamma, &grad.contiguous()?, &ExactGroupNormBackward(*self))?;
        Ok((Some(dx), None, None))
    }
}

/// `(x, γ, grad)` → the input's gradient.
#[derive(Clone, Copy, Debug)]
struct ExactGroupNormBackward(ExactGroupNorm);

impl CustomOp3 for ExactGroupNormBackward {
    fn name(&self) -> &'static str {
        "mte-exact-group-norm-backward"
    }

    fn cpu_fwd(
        &self,
        sx: &CpuStorage,
        lx: &Layout,
        sg: &CpuStorage,
        lg: &Layout,
        sd: &CpuStorage,
        ld: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let d = Dims::of(lx, self.0.groups, self.0.eps)?;
        let out = float_storages!(
            "group norm backward",
            [(x, sx, lx), (g, sg, lg), (dy, sd, ld)],
            backward(x, g, dy, d)?
        );
        Ok((out, lx.shape().clone()))
    }
}

/// candle_nn's GroupNorm of `x (B, C, ...)` with per-channel `gamma`, `beta`: one node with
/// its bits on the CPU (f32, f64) when neither γ nor β is tracked, candle_nn's layer
/// otherwise (training, other devices).
pub fn group_norm_exact(
    x: &Tensor,
    gamma: &Tensor,
    beta: &Tensor,
    groups: usize,
    eps: f64,
) -> Result<Tensor> {
    let fused = super::fused_on(x) && !gamma.track_op() && !beta.track_op();
    if !fused {
        use candle_core::Module;
        let c = x.dim(1)?;
        return candle_nn::GroupNorm::new(gamma.clone(), beta.clone(), c, groups, eps)?.forward(x);
    }
    x.contiguous()?.apply_op3(
        &gamma.contiguous()?,
        &beta.contiguous()?,
        ExactGroupNorm { groups, eps },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::test_util::{bits, probe_gradient, rand};
    use candle_core::{DType, Module, Var};

    /// Values and input gradients are candle_nn's GroupNorm's, bit for bit, in f32 and f64,
    /// for the U-Net's shapes (8 groups; rows of 16 to 256 values) and an odd one, with
    /// non-trivial γ and β.
    #[test]
    fn exact_group_norm_is_candle_nns_bit_for_bit() -> Result<()> {
        for (i, &(b, c, t, groups)) in [(3, 64, 16, 8), (2, 32, 8, 8), (2, 6, 5, 3), (1, 256, 4, 8)]
            .iter()
            .enumerate()
        {
            for dtype in [DType::F32, DType::F64] {
                let f = |t: Tensor| t.to_dtype(dtype);
                let x = Var::from_tensor(&f((rand(&[b, c, t], 90 + i as u64) * 3.0)?)?)?;
                let gamma = f((rand(&[c], 91 + i as u64) + 1.0)?)?;
                let beta = f(rand(&[c], 92 + i as u64))?;
                let theirs =
                    candle_nn::GroupNorm::new(gamma.clone(), beta.clone(), c, groups, 1e-5)?
                        .forward(x.as_tensor())?;
                let ours = group_norm_exact(x.as_tensor(), &gamma, &beta, groups, 1e-5)?;
                assert_eq!(bits(&ours), bits(&theirs), "values, case {i}, {dtype:?}");
                let r = f(rand(&[b, c, t], 93 + i as u64))?;
                let (go, _) = probe_gradient(&ours, &r, &x);
                let (gt, _) = probe_gradient(&theirs, &r, &x);
                assert_eq!(bits(&go), bits(&gt), "gradients, case {i}, {dtype:?}");
            }
        }
        Ok(())
    }

    #[test]
    fn groups_that_do_not_divide_the_channels_are_an_error() {
        let x = rand(&[1, 6, 4], 1);
        let (g, b) = (rand(&[6], 2), rand(&[6], 3));
        let e = group_norm_exact(&x, &g, &b, 4, 1e-5).expect_err("6 channels in 4 groups");
        assert!(e.to_string().contains("does not split"), "{e}");
    }
}
