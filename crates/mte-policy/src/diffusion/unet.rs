//! The conditional U-Net 1D with FiLM (LeRobot's `DiffusionConditionalUnet1d`, Diffusion
//! Policy's `ConditionalUnet1D` without local conditioning), as named structs whose
//! `VarBuilder` prefixes reproduce LeRobot's state-dict keys under `diffusion.unet.`.
//!
//! Tensors: the sample is `(B, T, D)` (time-major, as LeRobot passes it), transposed to
//! `(B, D, T)` inside; the timestep is an integer per batch row; the global conditioning is
//! `(B, n_obs_steps * per_step_dim)`.

use candle_core::{D, Device, Result, Tensor};
use candle_nn::VarBuilder;

use crate::kernels::{Linear, Products, linear};

use crate::config::DiffusionConfig;

/// GroupNorm epsilon (torch's default).
const GN_EPS: f64 = 1e-5;

/// `nn.Conv1d` computed as im2col plus one matrix product: candle's direct CPU convolution
/// (and its backward pass) is several times slower than its gemm for the short sequences
/// (T <= 16) and wide channels of the U-Net. Weights as torch stores them: `weight
/// (C_out, C_in, k)`, `bias (C_out)`.
#[derive(Clone, Debug)]
pub struct Conv1dGemm {
    weight: Tensor,
    bias: Tensor,
    stride: usize,
    pad: usize,
    /// The weight packed for the constant-weight path, made on its first use (a constant
    /// weight never changes: a trained one is a variable, which takes the composed path).
    packed: std::sync::OnceLock<Tensor>,
}

impl Conv1dGemm {
    fn new(
        cin: usize,
        cout: usize,
        k: usize,
        stride: usize,
        pad: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        // torch's default init: kaiming-uniform with a = sqrt(5), i.e. U(-1/sqrt(fan_in), ..).
        let bound = 1.0 / ((cin * k) as f64).sqrt();
        let init = candle_nn::Init::Uniform {
            lo: -bound,
            up: bound,
        };
        Ok(Conv1dGemm::from_parts(
            vb.get_with_hints((cout, cin, k), "weight", init)?,
            vb.get_with_hints(cout, "bias", init)?,
            stride,
            pad,
        ))
    }

    /// The layer of `weight (C_out, C_in, k)` and `bias (C_out)`.
    fn from_parts(weight: Tensor, bias: Tensor, stride: usize, pad: usize) -> Self {
        Conv1dGemm {
            weight,
            bias,
            stride,
            pad,
            packed: std::sync::OnceLock::new(),
        }
    }

    /// `(B, C_in, T)` -> `(B, C_out, T_out)`.
    pub fn forward(&self, x: &Tensor, products: Products) -> Result<Tensor> {
        if products == Products::PerSample
            && crate::kernels::constant_weights(x, &self.weight, &self.bias)
        {
            // The same bits in one graph node (`kernels::conv1d`).
            let packed = match self.packed.get() {
                Some(w) => w.clone(),
                None => {
                    let w = crate::kernels::packed_weight(&self.weight)?;
                    self.packed.get_or_init(|| w).clone()
                }
            };
            return crate::kernels::conv1d_constant(
                x,
                (&self.weight, &packed),
                &self.bias,
                self.stride,
                self.pad,
            );
        }
        let (b, c, t) = x.dims3()?;
        let (cout, _, k) = self.weight.dims3()?;
        let xp = if self.pad > 0 {
            x.pad_with_zeros(2, self.pad, self.pad)?
        } else {
            x.clone()
        };
        let full = t + 2 * self.pad - k + 1;
        let cols = if k == 1 {
            xp.unsqueeze(2)?
        } else {
            let taps: Vec<Tensor> = (0..k)
                .map(|j| xp.narrow(2, j, full))
                .collect::<Result<_>>()?;
            Tensor::stack(&taps, 2)?
        };
        // cols: (B, C, k, full) -> keep every `stride`-th output position.
        let (cols, t_out) = if self.stride > 1 {
            let t_out = (full - 1) / self.stride + 1;
            let padded = t_out * self.stride;
            let cols = if padded > full {
                cols.pad_with_zeros(3, 0, padded - full)?
            } else {
                cols
            };
            (
                cols.reshape((b, c, k, t_out, self.stride))?
                    .narrow(4, 0, 1)?
                    .squeeze(4)?,
                t_out,
            )
        } else {
            (cols, full)
        };
        // One (C_out, C k) x (C k, T) product per sample (batch-invariant; a batch of one is
        // the single product it always was), or one for the batch (`kernels::batch`).
        let cols = cols.reshape((b, c * k, t_out))?;
        let w = self.weight.reshape((cout, c * k))?;
        let y = crate::kernels::left_shared(&w, &cols, products)?;
        y.broadcast_add(&self.bias.reshape((1, cout, 1))?)
    }
}

/// candle_nn's GroupNorm (keys `weight`, `bias`; γ = 1, β = 0 when created), computed by
/// `kernels::group_norm_exact`: the same bits as candle_nn's layer, as one graph node when γ
/// and β are constants.
#[derive(Clone, Debug)]
struct UnetGroupNorm {
    weight: Tensor,
    bias: Tensor,
    groups: usize,
}

impl UnetGroupNorm {
    fn new(groups: usize, channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(UnetGroupNorm {
            weight: vb.get_with_hints(channels, "weight", candle_nn::Init::Const(1.))?,
            bias: vb.get_with_hints(channels, "bias", candle_nn::Init::Const(0.))?,
            groups,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        crate::kernels::group_norm_exact(x, &self.weight, &self.bias, self.groups, GN_EPS)
    }
}

/// Conv1d -> GroupNorm -> Mish (`DiffusionConv1dBlock`; keys `block.0`, `block.1`).
#[derive(Clone, Debug)]
pub struct Conv1dBlock {
    conv: Conv1dGemm,
    norm: UnetGroupNorm,
}

impl Conv1dBlock {
    fn new(cin: usize, cout: usize, k: usize, groups: usize, vb: VarBuilder) -> Result<Self> {
        let conv = Conv1dGemm::new(cin, cout, k, 1, k / 2, vb.pp("block.0"))?;
        if groups == 0 || !cout.is_multiple_of(groups) {
            candle_core::bail!("GroupNorm: {cout} channels do not split into {groups} groups");
        }
        let norm = UnetGroupNorm::new(groups, cout, vb.pp("block.1"))?;
        Ok(Conv1dBlock { conv, norm })
    }

    /// `(B, C_in, T)` -> `(B, C_out, T)`.
    pub fn forward(&self, x: &Tensor, products: Products) -> Result<Tensor> {
        // The normalised tensor has no other reader, so the fused Mish gives the same bits.
        crate::kernels::mish(&self.norm.forward(&self.conv.forward(x, products)?)?)
    }
}

/// FiLM-conditioned residual block (`DiffusionConditionalResidualBlock1d`).
#[derive(Clone, Debug)]
pub struct ResidualBlock {
    conv1: Conv1dBlock,
    cond_encoder: Linear,
    conv2: Conv1dBlock,
    residual_conv: Option<Conv1dGemm>,
    film_scale: bool,
}

impl ResidualBlock {
    fn new(
        cin: usize,
        cout: usize,
        cond_dim: usize,
        c: &DiffusionConfig,
        vb: VarBuilder,
    ) -> Result<Self> {
        let conv1 = Conv1dBlock::new(cin, cout, c.kernel_size, c.n_groups, vb.pp("conv1"))?;
        let cond_ch = if c.use_film_scale_modulation {
            2 * cout
        } else {
            cout
        };
        let cond_encoder = linear(cond_dim, cond_ch, vb.pp("cond_encoder.1"))?;
        let conv2 = Conv1dBlock::new(cout, cout, c.kernel_size, c.n_groups, vb.pp("conv2"))?;
        let residual_conv = if cin != cout {
            Some(Conv1dGemm::new(cin, cout, 1, 1, 0, vb.pp("residual_conv"))?)
        } else {
            None
        };
        Ok(ResidualBlock {
            conv1,
            cond_encoder,
            conv2,
            residual_conv,
            film_scale: c.use_film_scale_modulation,
        })
    }

    /// `x`: `(B, C_in, T)`, `cond`: `(B, cond_dim)` -> `(B, C_out, T)`.
    pub fn forward(&self, x: &Tensor, cond: &BlockCond, products: Products) -> Result<Tensor> {
        let out = self.conv1.forward(x, products)?;
        let emb = self.cond_encoder.forward(&cond.activated()?, products)?;
        // One pass (`kernels::film`): scale then bias, or bias only.
        let out = crate::kernels::film(&out, &emb, self.film_scale)?;
        let out = self.conv2.forward(&out, products)?;
        let res = match &self.residual_conv {
            Some(c) => c.forward(x, products)?,
            None => x.clone(),
        };
        out + res
    }
}

/// What every residual block reads: `mish(cond)`, `cond (B, cond_dim)`.
///
/// Computed once when no gradient flows to `cond` (evaluation). When one does (training,
/// attacks), each block applies candle's Mish to `cond` itself, as the composed path always
/// did: one shared node would sum the blocks' gradients before Mish's derivative, in another
/// order and so to other bits (`kernels::mish` is for single-reader inputs for the same
/// reason). The values are the same bits either way.
#[derive(Clone, Debug)]
pub enum BlockCond {
    /// `mish(cond)`, shared by every block.
    Once(Tensor),
    /// `cond`, activated by each block.
    PerBlock(Tensor),
}

impl BlockCond {
    /// The condition for `cond`, activated once unless a gradient flows to it.
    pub fn new(cond: Tensor) -> Result<Self> {
        Ok(if cond.track_op() {
            BlockCond::PerBlock(cond)
        } else {
            BlockCond::Once(candle_nn::ops::mish(&cond)?)
        })
    }

    /// `mish(cond)` for one block.
    fn activated(&self) -> Result<Tensor> {
        match self {
            BlockCond::Once(a) => Ok(a.clone()),
            BlockCond::PerBlock(c) => candle_nn::ops::mish(c),
        }
    }
}

/// One down level: two residual blocks and an optional stride-2 convolution.
#[derive(Clone, Debug)]
struct Down {
    res1: ResidualBlock,
    res2: ResidualBlock,
    downsample: Option<Conv1dGemm>,
}

/// One up level: two residual blocks on (x ++ skip) and a transposed convolution.
#[derive(Clone, Debug)]
struct Up {
    res1: ResidualBlock,
    res2: ResidualBlock,
    upsample: Option<Upsample>,
}

/// `nn.ConvTranspose1d(C, C, 4, stride 2, padding 1)` written as zero insertion plus an
/// ordinary convolution with the flipped, transposed kernel, because candle has no backward
/// pass for `conv_transpose1d` (training and observation gradients need one). Weights are
/// stored as torch stores them: `weight (C_in, C_out, 4)`, `bias (C_out)`.
#[derive(Clone, Debug)]
pub struct Upsample {
    weight: Tensor,
    bias: Tensor,
    k: usize,
    /// The equivalent convolution of constant weights, made once (with its packed weight):
    /// rebuilding it per forward repacked the weight every time.
    constant: std::sync::OnceLock<Conv1dGemm>,
}

impl Upsample {
    fn new(cin: usize, cout: usize, k: usize, vb: VarBuilder) -> Result<Self> {
        // Same initialisation bounds as torch's ConvTranspose1d (kaiming-uniform, a = sqrt 5).
        let bound = 1.0 / ((cout * k) as f64).sqrt();
        let init = candle_nn::Init::Uniform {
            lo: -bound,
            up: bound,
        };
        Ok(Upsample {
            weight: vb.get_with_hints((cin, cout, k), "weight", init)?,
            bias: vb.get_with_hints(cout, "bias", init)?,
            k,
            constant: std::sync::OnceLock::new(),
        })
    }

    /// The stride-1 convolution that equals this transposed convolution on a zero-stuffed
    /// input: the kernel flipped, in and out channels swapped (`W'[o, i, j] = W[i, o, k - 1 -
    /// j]`), padding `k - 1 - p = k - 2`.
    fn equivalent(&self) -> Result<Conv1dGemm> {
        let rev: Vec<u32> = (0..self.k as u32).rev().collect();
        let idx = Tensor::from_vec(rev, self.k, self.weight.device())?;
        let w = self
            .weight
            .transpose(0, 1)?
            .contiguous()?
            .index_select(&idx, 2)?;
        Ok(Conv1dGemm::from_parts(w, self.bias.clone(), 1, self.k - 2))
    }

    /// `(B, C_in, T)` -> `(B, C_out, 2T)`.
    pub fn forward(&self, x: &Tensor, products: Products) -> Result<Tensor> {
        let (b, c, t) = x.dims3()?;
        // Insert a zero after every sample: (B, C, 2T - 1).
        let z = Tensor::cat(&[&x.unsqueeze(3)?, &x.zeros_like()?.unsqueeze(3)?], 3)?
            .reshape((b, c, 2 * t))?
            .narrow(2, 0, 2 * t - 1)?;
        // Constant weights never change (trained ones are variables): build the equivalent
        // convolution once.
        if self.weight.track_op() || self.bias.track_op() {
            return self.equivalent()?.forward(&z, products);
        }
        let conv = match self.constant.get() {
            Some(conv) => conv,
            None => {
                let conv = self.equivalent()?;
                self.constant.get_or_init(|| conv)
            }
        };
        conv.forward(&z, products)
    }
}

/// The conditional U-Net.
#[derive(Clone, Debug)]
pub struct ConditionalUnet1d {
    embed_dim: usize,
    step_lin1: Linear,
    step_lin2: Linear,
    down: Vec<Down>,
    mid: Vec<ResidualBlock>,
    up: Vec<Up>,
    final_block: Conv1dBlock,
    final_conv: Conv1dGemm,
}

impl ConditionalUnet1d {
    /// Build (or load, depending on `vb`) the U-Net for `global_cond_dim` conditioning values.
    pub fn new(c: &DiffusionConfig, global_cond_dim: usize, vb: VarBuilder) -> Result<Self> {
        let e = c.diffusion_step_embed_dim;
        let action_dim = c
            .action_dim()
            .map_err(|err| candle_core::Error::Msg(err.to_string()))?;
        let step_lin1 = linear(e, 4 * e, vb.pp("diffusion_step_encoder.1"))?;
        let step_lin2 = linear(4 * e, e, vb.pp("diffusion_step_encoder.3"))?;
        let cond_dim = e + global_cond_dim;
        let mut in_out = vec![(action_dim, c.down_dims[0])];
        for w in c.down_dims.windows(2) {
            in_out.push((w[0], w[1]));
        }
        let mut down = Vec::new();
        for (i, &(cin, cout)) in in_out.iter().enumerate() {
            let vbi = vb.pp(format!("down_modules.{i}"));
            let is_last = i + 1 >= in_out.len();
            down.push(Down {
                res1: ResidualBlock::new(cin, cout, cond_dim, c, vbi.pp("0"))?,
                res2: ResidualBlock::new(cout, cout, cond_dim, c, vbi.pp("1"))?,
                downsample: if is_last {
                    None
                } else {
                    Some(Conv1dGemm::new(cout, cout, 3, 2, 1, vbi.pp("2"))?)
                },
            });
        }
        let last = *c.down_dims.last().unwrap_or(&1);
        let mid = (0..2)
            .map(|j| ResidualBlock::new(last, last, cond_dim, c, vb.pp(format!("mid_modules.{j}"))))
            .collect::<Result<Vec<_>>>()?;
        let mut up = Vec::new();
        for (i, &(cout, cin)) in in_out[1..].iter().rev().enumerate() {
            let vbi = vb.pp(format!("up_modules.{i}"));
            // LeRobot's `is_last` test never fires for the up path: every level upsamples.
            let is_last = i + 1 >= in_out.len();
            up.push(Up {
                res1: ResidualBlock::new(2 * cin, cout, cond_dim, c, vbi.pp("0"))?,
                res2: ResidualBlock::new(cout, cout, cond_dim, c, vbi.pp("1"))?,
                upsample: if is_last {
                    None
                } else {
                    Some(Upsample::new(cout, cout, 4, vbi.pp("2"))?)
                },
            });
        }
        let d0 = c.down_dims[0];
        // LeRobot builds this block without passing `n_groups`: it always has 8 groups.
        let final_block = Conv1dBlock::new(d0, d0, c.kernel_size, 8, vb.pp("final_conv.0"))?;
        let final_conv = Conv1dGemm::new(d0, action_dim, 1, 1, 0, vb.pp("final_conv.1"))?;
        Ok(ConditionalUnet1d {
            embed_dim: e,
            step_lin1,
            step_lin2,
            down,
            mid,
            up,
            final_block,
            final_conv,
        })
    }

    /// Sinusoidal embedding of integer timesteps: `(B,)` -> `(B, embed_dim)`, first half sin,
    /// second half cos, frequencies `exp(-ln(10000) k / (half - 1))`.
    pub fn timestep_embedding(&self, timesteps: &[usize], device: &Device) -> Result<Tensor> {
        let half = self.embed_dim / 2;
        let scale = (10000f64).ln() / (half as f64 - 1.0);
        let mut data = Vec::with_capacity(timesteps.len() * self.embed_dim);
        // torch computes the frequencies in float32; so do we.
        let freqs: Vec<f32> = (0..half)
            .map(|k| (k as f32 * -(scale as f32)).exp())
            .collect();
        for &t in timesteps {
            data.extend(freqs.iter().map(|f| (t as f32 * f).sin()));
            data.extend(freqs.iter().map(|f| (t as f32 * f).cos()));
        }
        Tensor::from_vec(data, (timesteps.len(), self.embed_dim), device)
    }

    /// The timestep encoder's output (`diffusion_step_encoder`: sinusoid, Linear, Mish,
    /// Linear): `(B, embed_dim)`.
    pub fn step_encoder(&self, timesteps: &[usize], device: &Device) -> Result<Tensor> {
        self.step_encoder_with(timesteps, device, Products::PerSample)
    }

    fn step_encoder_with(
        &self,
        timesteps: &[usize],
        device: &Device,
        products: Products,
    ) -> Result<Tensor> {
        let emb = self
            .timestep_embedding(timesteps, device)?
            .to_dtype(self.step_lin1.weight().dtype())?;
        let h = crate::kernels::mish(&self.step_lin1.forward(&emb, products)?)?;
        self.step_lin2.forward(&h, products)
    }

    /// Predict from `x` `(B, T, D)` at `timesteps` (one per row) with `global_cond`
    /// `(B, G)`; returns `(B, T, D)`. Batch-invariant: each row is computed exactly as a
    /// batch of one ([`Products::PerSample`]).
    pub fn forward(&self, x: &Tensor, timesteps: &[usize], global_cond: &Tensor) -> Result<Tensor> {
        self.forward_with(x, timesteps, global_cond, Products::PerSample)
    }

    /// [`ConditionalUnet1d::forward`] with the products computed as `products` says
    /// (training: [`Products::Fused`]).
    pub fn forward_with(
        &self,
        x: &Tensor,
        timesteps: &[usize],
        global_cond: &Tensor,
        products: Products,
    ) -> Result<Tensor> {
        let emb = self
            .step_encoder_with(timesteps, x.device(), products)?
            .to_dtype(x.dtype())?;
        let cond = BlockCond::new(Tensor::cat(&[&emb, global_cond], D::Minus1)?)?;
        let mut h = x.transpose(1, 2)?.contiguous()?;
        let mut skips = Vec::with_capacity(self.down.len());
        for d in &self.down {
            h = d.res1.forward(&h, &cond, products)?;
            h = d.res2.forward(&h, &cond, products)?;
            skips.push(h.clone());
            if let Some(ds) = &d.downsample {
                h = ds.forward(&h, products)?;
            }
        }
        for m in &self.mid {
            h = m.forward(&h, &cond, products)?;
        }
        for u in &self.up {
            let skip = skips
                .pop()
                .ok_or_else(|| candle_core::Error::Msg("U-Net skip underflow".into()))?;
            h = Tensor::cat(&[&h, &skip], 1)?;
            h = u.res1.forward(&h, &cond, products)?;
            h = u.res2.forward(&h, &cond, products)?;
            if let Some(us) = &u.upsample {
                h = us.forward(&h, products)?;
            }
        }
        let h = self.final_block.forward(&h, products)?;
        let h = self.final_conv.forward(&h, products)?;
        h.transpose(1, 2)?.contiguous()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::DType;

    #[test]
    fn upsample_equals_conv_transpose() {
        let dev = Device::Cpu;
        let vm = candle_nn::VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 5, DType::F32, &dev);
        let up = Upsample::new(3, 5, 4, vb).expect("init");
        let x = crate::kernels::test_util::rand(&[2, 3, 7], 6)
            .to_dtype(DType::F32)
            .expect("x");
        let native = x
            .conv_transpose1d(&up.weight, 1, 0, 2, 1, 1)
            .expect("native")
            .broadcast_add(&up.bias.reshape((1, 5, 1)).expect("b"))
            .expect("bias");
        let ours = up.forward(&x, Products::PerSample).expect("ours");
        assert_eq!(ours.dims(), &[2, 5, 14]);
        let d: f32 = (ours - native)
            .expect("diff")
            .abs()
            .expect("abs")
            .max_all()
            .expect("max")
            .to_scalar()
            .expect("s");
        assert!(d < 1e-5, "{d}");
    }

    /// A U-Net with constant weights (a loaded checkpoint: the condition activated once, the
    /// one-node convolutions) gives the bits of the same weights as variables (the condition
    /// activated per block, the composed convolutions), at batch 3.
    #[test]
    fn constant_weights_give_the_variables_bits() -> Result<()> {
        use crate::diffusion::config::ObsKind;
        let dev = Device::Cpu;
        let c = DiffusionConfig::cpu(ObsKind::Keypoints);
        let vm = candle_nn::VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 11, DType::F32, &dev);
        let tracked = ConditionalUnet1d::new(&c, 6, vb)?;
        let constants: std::collections::HashMap<String, Tensor> = vm
            .data()
            .lock()
            .map_err(|_| candle_core::Error::Msg("var map lock".into()))?
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
            .collect();
        let constant =
            ConditionalUnet1d::new(&c, 6, VarBuilder::from_tensors(constants, DType::F32, &dev))?;
        let rand = |shape: &[usize], seed: u64| {
            crate::kernels::test_util::rand(shape, seed).to_dtype(DType::F32)
        };
        let x = rand(&[3, c.horizon, 2], 1)?;
        let cond = rand(&[3, 6], 2)?;
        let steps = [3, 50, 99];
        let yt = tracked.forward(&x, &steps, &cond)?;
        let yc = constant.forward(&x, &steps, &cond)?;
        use crate::kernels::test_util::bits;
        assert_eq!(bits(&yc), bits(&yt));
        Ok(())
    }

    /// The constant-weight convolution (`kernels::conv1d`, one node) gives the composed
    /// path's output and input gradient bit for bit in f32, for the U-Net's geometries: its
    /// blocks (k = 5, pad 2), the downsample (k = 3, stride 2, pad 1), the residual 1x1, the
    /// upsample's convolution (k = 4, pad 2), an odd length, and outputs of 16, 8, 4 and 2
    /// positions (at batch 3 the kernel's panels cross samples and end in a tail). The
    /// composed path is taken by making the same weights variables.
    #[test]
    fn constant_weight_conv1d_is_the_composed_path_bit_for_bit() -> Result<()> {
        use candle_core::Var;
        let rand = |shape: &[usize], seed: u64| {
            crate::kernels::test_util::rand(shape, seed).to_dtype(DType::F32)
        };
        for (i, &(c, co, t, k, stride, pad)) in [
            (3, 8, 16, 5, 1, 2),
            (8, 8, 16, 3, 2, 1),
            (8, 4, 8, 1, 1, 0),
            (4, 4, 15, 4, 1, 2),
            (2, 3, 7, 3, 2, 1),
            (4, 6, 4, 5, 1, 2),
            (3, 5, 2, 3, 1, 1),
        ]
        .iter()
        .enumerate()
        {
            let x = Var::from_tensor(&rand(&[3, c, t], 10 + i as u64)?)?;
            let (w, b) = (
                rand(&[co, c, k], 20 + i as u64)?,
                rand(&[co], 30 + i as u64)?,
            );
            let constant = Conv1dGemm::from_parts(w.clone(), b.clone(), stride, pad);
            let tracked = Conv1dGemm::from_parts(
                Var::from_tensor(&w)?.as_tensor().clone(),
                Var::from_tensor(&b)?.as_tensor().clone(),
                stride,
                pad,
            );
            let yc = constant.forward(x.as_tensor(), Products::PerSample)?;
            let yt = tracked.forward(x.as_tensor(), Products::PerSample)?;
            use crate::kernels::test_util::{bits, probe_gradient};
            assert_eq!(bits(&yc), bits(&yt), "output, case {i}");
            let r = rand(yc.dims(), 40 + i as u64)?;
            let (dc, _) = probe_gradient(&yc, &r, &x);
            let (dt, _) = probe_gradient(&yt, &r, &x);
            assert_eq!(bits(&dc), bits(&dt), "input gradient, case {i}");
        }
        Ok(())
    }
}
