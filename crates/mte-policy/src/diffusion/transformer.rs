//! Diffusion Policy's `TransformerForDiffusion` (Chi et al.), the noise network of the
//! Diffusion Transformer, on candle.
//!
//! Action tokens: `Linear(action_dim, n_emb)` of the noisy chunk plus a learned position
//! embedding. Condition tokens: `[sinusoidal time embedding, Linear(obs_dim, n_emb) of each of
//! the n_obs_steps observation features]` plus a learned position embedding, through an MLP
//! (`Linear 4x, Mish, Linear`) or `n_cond_layers` pre-LN encoder layers. Then `n_layer`
//! pre-LN decoder layers (PyTorch's `nn.TransformerDecoderLayer` with `norm_first`, GELU,
//! feed-forward 4 x `n_emb`): causal self-attention over the actions when `causal_attn`, and
//! cross-attention in which action `t` sees condition token `s` iff `t >= s - 1`. A final
//! LayerNorm and a linear head give the noise (or sample) prediction.
//!
//! State-dict names are Diffusion Policy's (`input_emb`, `pos_emb`, `cond_obs_emb`,
//! `cond_pos_emb`, `encoder.0` / `encoder.2`, `decoder.layers.{i}.self_attn`,
//! `.multihead_attn`, `.linear1`, `.linear2`, `.norm1..3`, `ln_f`, `head`), under
//! `diffusion.transformer.` in mte's checkpoints. Tensors are batch-first `(B, L, D)`, as
//! Diffusion Policy builds its layers (`batch_first=True`).

use candle_core::{Device, Result, Tensor};
use candle_nn::{Init, Linear, VarBuilder};

use crate::attention::{Attention, Dropout, FeedForward, LayerNorm, drop, linear3};
use crate::config::TransformerConfig;
use crate::kernels::Products;

fn layer_norm(d: usize, vb: VarBuilder) -> Result<LayerNorm> {
    LayerNorm::new(d, vb)
}

/// `nn.TransformerEncoderLayer(norm_first=True, activation="gelu", batch_first=True)`.
struct EncoderLayer {
    attn: Attention,
    ff: FeedForward,
    norm1: LayerNorm,
    norm2: LayerNorm,
}

impl EncoderLayer {
    fn new(c: &TransformerConfig, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            attn: Attention::new(c.n_emb, c.n_head, vb.pp("self_attn"))?,
            ff: FeedForward::new(c.n_emb, 4 * c.n_emb, true, &vb)?,
            norm1: layer_norm(c.n_emb, vb.pp("norm1"))?,
            norm2: layer_norm(c.n_emb, vb.pp("norm2"))?,
        })
    }

    fn forward(&self, x: &Tensor, d: Option<&Dropout<'_>>, p: Products) -> Result<Tensor> {
        let h = self.norm1.forward(x)?;
        let a = self.attn.forward_masked(&h, &h, &h, None, None, d, p)?;
        let x = (x + drop(&a, d)?)?;
        let h = self.norm2.forward(&x)?;
        &x + drop(&self.ff.forward(&h, d, p)?, d)?
    }
}

/// `nn.TransformerDecoderLayer(norm_first=True, activation="gelu", batch_first=True)`.
struct DecoderLayer {
    self_attn: Attention,
    cross_attn: Attention,
    ff: FeedForward,
    norms: [LayerNorm; 3],
}

impl DecoderLayer {
    fn new(c: &TransformerConfig, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            self_attn: Attention::new(c.n_emb, c.n_head, vb.pp("self_attn"))?,
            cross_attn: Attention::new(c.n_emb, c.n_head, vb.pp("multihead_attn"))?,
            ff: FeedForward::new(c.n_emb, 4 * c.n_emb, true, &vb)?,
            norms: [
                layer_norm(c.n_emb, vb.pp("norm1"))?,
                layer_norm(c.n_emb, vb.pp("norm2"))?,
                layer_norm(c.n_emb, vb.pp("norm3"))?,
            ],
        })
    }

    fn forward(
        &self,
        x: &Tensor,
        memory: &Tensor,
        masks: &Masks,
        d: Option<&Dropout<'_>>,
        p: Products,
    ) -> Result<Tensor> {
        let h = self.norms[0].forward(x)?;
        let tgt = masks.tgt.as_ref();
        let a = self.self_attn.forward_masked(&h, &h, &h, tgt, None, d, p)?;
        let x = (x + drop(&a, d)?)?;
        let h = self.norms[1].forward(&x)?;
        let mem = masks.memory.as_ref();
        let a = self
            .cross_attn
            .forward_masked(&h, memory, memory, mem, None, d, p)?;
        let x = (x + drop(&a, d)?)?;
        let h = self.norms[2].forward(&x)?;
        &x + drop(&self.ff.forward(&h, d, p)?, d)?
    }
}

/// The additive attention masks of a causal transformer (`None` when not causal).
struct Masks {
    tgt: Option<Tensor>,
    memory: Option<Tensor>,
}

/// Large negative standing for -inf in additive masks (softmax gives exactly 0 weight, and
/// no `inf - inf` can arise).
const MASKED: f32 = -1e30;

impl Masks {
    fn new(causal: bool, t: usize, s: usize, dev: &Device) -> Result<Self> {
        if !causal {
            return Ok(Self {
                tgt: None,
                memory: None,
            });
        }
        let tgt: Vec<f32> = (0..t)
            .flat_map(|i| (0..t).map(move |j| if j <= i { 0.0 } else { MASKED }))
            .collect();
        let memory: Vec<f32> = (0..t)
            .flat_map(|i| (0..s).map(move |j| if i + 1 >= j { 0.0 } else { MASKED }))
            .collect();
        Ok(Self {
            tgt: Some(Tensor::from_vec(tgt, (t, t), dev)?),
            memory: Some(Tensor::from_vec(memory, (t, s), dev)?),
        })
    }
}

/// The condition encoder: an MLP or pre-LN encoder layers.
enum CondEncoder {
    Mlp(Linear, Linear),
    Layers(Vec<EncoderLayer>),
}

/// The Diffusion Transformer's noise network.
pub struct TransformerForDiffusion {
    input_emb: Linear,
    pos_emb: Tensor,
    cond_obs_emb: Linear,
    cond_pos_emb: Tensor,
    encoder: CondEncoder,
    decoder: Vec<DecoderLayer>,
    ln_f: LayerNorm,
    head: Linear,
    masks: Masks,
    n_emb: usize,
    n_obs_steps: usize,
    p_drop_emb: f64,
}

impl TransformerForDiffusion {
    /// `horizon` action tokens of `action_dim`, `n_obs_steps` condition tokens of `obs_dim`.
    pub fn new(
        c: &TransformerConfig,
        action_dim: usize,
        horizon: usize,
        n_obs_steps: usize,
        obs_dim: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let e = c.n_emb;
        let zeros = Init::Randn {
            mean: 0.0,
            stdev: 0.02,
        };
        let encoder = if c.n_cond_layers > 0 {
            CondEncoder::Layers(
                (0..c.n_cond_layers)
                    .map(|i| EncoderLayer::new(c, vb.pp(format!("encoder.layers.{i}"))))
                    .collect::<Result<_>>()?,
            )
        } else {
            CondEncoder::Mlp(
                candle_nn::linear(e, 4 * e, vb.pp("encoder.0"))?,
                candle_nn::linear(4 * e, e, vb.pp("encoder.2"))?,
            )
        };
        Ok(Self {
            input_emb: candle_nn::linear(action_dim, e, vb.pp("input_emb"))?,
            pos_emb: vb.get_with_hints((1, horizon, e), "pos_emb", zeros)?,
            cond_obs_emb: candle_nn::linear(obs_dim, e, vb.pp("cond_obs_emb"))?,
            cond_pos_emb: vb.get_with_hints((1, 1 + n_obs_steps, e), "cond_pos_emb", zeros)?,
            encoder,
            decoder: (0..c.n_layer)
                .map(|i| DecoderLayer::new(c, vb.pp(format!("decoder.layers.{i}"))))
                .collect::<Result<_>>()?,
            ln_f: layer_norm(e, vb.pp("ln_f"))?,
            head: candle_nn::linear(e, action_dim, vb.pp("head"))?,
            masks: Masks::new(c.causal_attn, horizon, 1 + n_obs_steps, vb.device())?,
            n_emb: e,
            n_obs_steps,
            p_drop_emb: c.p_drop_emb,
        })
    }

    /// Diffusion Policy's `SinusoidalPosEmb`: `[sin(t f), cos(t f)]`, `f_i = exp(-i ln(10000)
    /// / (half - 1))`, `(B, 1, n_emb)`.
    fn time_embedding(&self, timesteps: &[usize], dev: &Device) -> Result<Tensor> {
        let half = self.n_emb / 2;
        let scale = (10000f64).ln() / (half as f64 - 1.0).max(1.0);
        let mut v = Vec::with_capacity(timesteps.len() * self.n_emb);
        for &t in timesteps {
            let f = |i: usize| (t as f64 * (-(i as f64) * scale).exp()) as f32;
            v.extend((0..half).map(|i| f(i).sin()));
            v.extend((0..half).map(|i| f(i).cos()));
        }
        Tensor::from_vec(v, (timesteps.len(), 1, self.n_emb), dev)
    }

    /// Predict from the noisy chunk `x (B, T, A)` at `timesteps` with the observation features
    /// `global_cond (B, n_obs_steps * F)` (the U-Net's global conditioning, one token per
    /// observation step here); `dropout` in training; products as `p` says
    /// ([`Products::PerSample`] at evaluation: batch-invariant).
    pub fn forward(
        &self,
        x: &Tensor,
        timesteps: &[usize],
        global_cond: &Tensor,
        dropout: Option<&Dropout<'_>>,
        p: Products,
    ) -> Result<Tensor> {
        let (b, g) = global_cond.dims2()?;
        let obs = global_cond.reshape((b, self.n_obs_steps, g / self.n_obs_steps))?;
        let time = self
            .time_embedding(timesteps, x.device())?
            .to_dtype(x.dtype())?;
        let cond = Tensor::cat(&[&time, &linear3(&self.cond_obs_emb, &obs, p)?], 1)?;
        let emb_drop = dropout.filter(|_| self.p_drop_emb > 0.0);
        let mut memory = drop(&cond.broadcast_add(&self.cond_pos_emb)?, emb_drop)?;
        memory = match &self.encoder {
            CondEncoder::Mlp(l0, l2) => {
                linear3(l2, &candle_nn::ops::mish(&linear3(l0, &memory, p)?)?, p)?
            }
            CondEncoder::Layers(layers) => {
                for l in layers {
                    memory = l.forward(&memory, dropout, p)?;
                }
                memory
            }
        };
        let tokens = linear3(&self.input_emb, x, p)?;
        let mut h = drop(&tokens.broadcast_add(&self.pos_emb)?, emb_drop)?;
        for layer in &self.decoder {
            h = layer.forward(&h, &memory, &self.masks, dropout, p)?;
        }
        linear3(&self.head, &self.ln_f.forward(&h)?, p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn causal_masks_follow_diffusion_policys_rule() {
        let m = Masks::new(true, 3, 3, &Device::Cpu).expect("masks");
        let tgt: Vec<Vec<f32>> = m.tgt.expect("tgt").to_vec2().expect("v");
        assert_eq!(tgt[0], vec![0.0, MASKED, MASKED]);
        assert_eq!(tgt[2], vec![0.0, 0.0, 0.0]);
        // Action t sees condition s iff t >= s - 1: t = 0 sees the time token and the first
        // observation, not the second.
        let mem: Vec<Vec<f32>> = m.memory.expect("memory").to_vec2().expect("v");
        assert_eq!(mem[0], vec![0.0, 0.0, MASKED]);
        assert_eq!(mem[1], vec![0.0, 0.0, 0.0]);
    }

    /// Every parameter of the Diffusion Transformer receives a gradient in training (no op
    /// without a backward pass on the way: candle-nn's fused LayerNorm and softmax had cut
    /// all of them but the head's), and so do its inputs (PGD attacks through them).
    #[test]
    fn every_parameter_and_the_condition_get_gradients() {
        let varmap = candle_nn::VarMap::new();
        let vb = crate::init::seeded_var_builder(&varmap, 0, candle_core::DType::F32, &Device::Cpu);
        let c = TransformerConfig {
            n_layer: 2,
            n_emb: 16,
            n_head: 2,
            n_cond_layers: 1,
            ..TransformerConfig::cpu()
        };
        let net = TransformerForDiffusion::new(&c, 2, 4, 2, 3, vb).expect("net");
        let x = Tensor::randn(0f32, 1.0, (2, 4, 2), &Device::Cpu).expect("x");
        let cond = candle_core::Var::from_tensor(
            &Tensor::randn(0f32, 1.0, (2, 6), &Device::Cpu).expect("cond"),
        )
        .expect("var");
        let cell = std::cell::RefCell::new(
            <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0),
        );
        let d = Dropout::new(0.0, &cell);
        let y = net
            .forward(&x, &[3, 7], cond.as_tensor(), Some(&d), Products::Fused)
            .expect("forward");
        let grads = y
            .sqr()
            .and_then(|v| v.sum_all())
            .and_then(|l| l.backward())
            .expect("backward");
        let missing: Vec<String> = varmap
            .data()
            .lock()
            .expect("lock")
            .iter()
            .filter(|(_, v)| grads.get(v.as_tensor()).is_none())
            .map(|(n, _)| n.clone())
            .collect();
        assert!(missing.is_empty(), "no gradient for {missing:?}");
        let g = grads.get(cond.as_tensor()).expect("condition gradient");
        let norm = g
            .sqr()
            .and_then(|v| v.sum_all())
            .and_then(|v| v.to_scalar::<f32>())
            .expect("norm");
        assert!(norm > 0.0, "the condition's gradient is zero");
    }
}
