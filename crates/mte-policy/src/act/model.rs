//! The ACT network (Zhao et al., as LeRobot 0.4.4 implements it) on candle.
//!
//! Tokens of the transformer encoder: `[latent, robot state, environment state]`, each a
//! linear projection to `dim_model`, with a learned 1-D position embedding, then, per camera,
//! the `h x w` cells of the ResNet-18 feature map (frozen BatchNorm, layer4), each projected
//! by a 1x1 convolution, row by row, with LeRobot's fixed 2-D sinusoidal embedding; the decoder's
//! `chunk_size` queries start at zero with a learned position embedding (DETR's object
//! queries), cross-attend to the encoder, and a linear head maps them to actions. Training
//! adds the CVAE encoder over `[cls, robot state, actions]` (fixed sinusoidal positions,
//! padded actions masked) whose class token gives the latent's mean and `2 log sigma`; at
//! inference the latent is zero. Layers are post-norm unless `pre_norm`; the decoder ends in a
//! LayerNorm. Attention is PyTorch's `nn.MultiheadAttention` (packed `in_proj_weight`, the
//! query scaled by `head_dim^-1/2` before the product).
//!
//! Tensors are batch-first here, `(B, L, D)`; LeRobot's are sequence-first, which changes no
//! value. State-dict names are LeRobot's (`model.encoder.layers.0.self_attn.in_proj_weight`,
//! ...), so its checkpoints load as they are.

use candle_core::{D, DType, Device, Result, Tensor};
use candle_nn::{Init, Linear, Module, VarBuilder};

use super::config::ActConfig;
pub use crate::attention::Dropout;
use crate::attention::{Attention, FeedForward, LayerNorm, drop, linear3};
use crate::kernels::{Conv2d, Products};
use crate::vision::{BackboneNames, BackboneNorm, ResNet18};

/// How a pass computes its products: per sample (batch-invariant) at inference, fused in
/// training (recognised by its dropout).
fn products(d: Option<&Dropout<'_>>) -> Products {
    if d.is_some() {
        Products::Fused
    } else {
        Products::PerSample
    }
}

/// `layer` on every row of `x (B, in)`.
fn linear2(layer: &Linear, x: &Tensor, p: Products) -> Result<Tensor> {
    linear3(layer, &x.unsqueeze(1)?, p)?.squeeze(1)
}

fn layer_norm(d: usize, vb: VarBuilder) -> Result<LayerNorm> {
    LayerNorm::new(d, vb)
}

fn add_pos(x: &Tensor, pos: Option<&Tensor>) -> Result<Tensor> {
    match pos {
        Some(p) => x.broadcast_add(p),
        None => Ok(x.clone()),
    }
}

/// A layer's feed-forward block as the config sets it (ReLU, or GELU).
fn feed_forward(c: &ActConfig, vb: &VarBuilder) -> Result<FeedForward> {
    FeedForward::new(
        c.dim_model,
        c.dim_feedforward,
        c.feedforward_activation == "gelu",
        vb,
    )
}

struct EncoderLayer {
    attn: Attention,
    ff: FeedForward,
    norm1: LayerNorm,
    norm2: LayerNorm,
    pre_norm: bool,
}

impl EncoderLayer {
    fn new(c: &ActConfig, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            attn: Attention::new(c.dim_model, c.n_heads, vb.pp("self_attn"))?,
            ff: feed_forward(c, &vb)?,
            norm1: layer_norm(c.dim_model, vb.pp("norm1"))?,
            norm2: layer_norm(c.dim_model, vb.pp("norm2"))?,
            pre_norm: c.pre_norm,
        })
    }

    fn forward(
        &self,
        x: &Tensor,
        pos: Option<&Tensor>,
        pad: Option<&Tensor>,
        d: Option<&Dropout<'_>>,
    ) -> Result<Tensor> {
        let mut skip = x.clone();
        let mut x = if self.pre_norm {
            self.norm1.forward(x)?
        } else {
            x.clone()
        };
        let qk = add_pos(&x, pos)?;
        let a = self
            .attn
            .forward_masked(&qk, &qk, &x, None, pad, d, products(d))?;
        x = (skip + drop(&a, d)?)?;
        if self.pre_norm {
            skip = x.clone();
            x = self.norm2.forward(&x)?;
        } else {
            x = self.norm1.forward(&x)?;
            skip = x.clone();
        }
        x = (skip + drop(&self.ff.forward(&x, d, products(d))?, d)?)?;
        if self.pre_norm {
            Ok(x)
        } else {
            self.norm2.forward(&x)
        }
    }
}

struct Encoder {
    layers: Vec<EncoderLayer>,
    norm: Option<LayerNorm>,
}

impl Encoder {
    fn new(c: &ActConfig, n: usize, vb: VarBuilder) -> Result<Self> {
        let layers = (0..n)
            .map(|i| EncoderLayer::new(c, vb.pp(format!("layers.{i}"))))
            .collect::<Result<_>>()?;
        let norm = if c.pre_norm {
            Some(layer_norm(c.dim_model, vb.pp("norm"))?)
        } else {
            None
        };
        Ok(Self { layers, norm })
    }

    fn forward(
        &self,
        mut x: Tensor,
        pos: Option<&Tensor>,
        pad: Option<&Tensor>,
        d: Option<&Dropout<'_>>,
    ) -> Result<Tensor> {
        for layer in &self.layers {
            x = layer.forward(&x, pos, pad, d)?;
        }
        match &self.norm {
            Some(n) => n.forward(&x),
            None => Ok(x),
        }
    }
}

struct DecoderLayer {
    self_attn: Attention,
    cross_attn: Attention,
    ff: FeedForward,
    norms: [LayerNorm; 3],
    pre_norm: bool,
}

/// The decoder's inputs besides its tokens: the encoder output and both position embeddings.
struct Memory<'a> {
    out: &'a Tensor,
    pos: &'a Tensor,
    query_pos: &'a Tensor,
}

impl DecoderLayer {
    fn new(c: &ActConfig, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            self_attn: Attention::new(c.dim_model, c.n_heads, vb.pp("self_attn"))?,
            cross_attn: Attention::new(c.dim_model, c.n_heads, vb.pp("multihead_attn"))?,
            ff: feed_forward(c, &vb)?,
            norms: [
                layer_norm(c.dim_model, vb.pp("norm1"))?,
                layer_norm(c.dim_model, vb.pp("norm2"))?,
                layer_norm(c.dim_model, vb.pp("norm3"))?,
            ],
            pre_norm: c.pre_norm,
        })
    }

    /// One residual block around `f`, post- or pre-norm with norm `i`.
    fn block(
        &self,
        x: &Tensor,
        i: usize,
        d: Option<&Dropout<'_>>,
        f: impl FnOnce(&Tensor) -> Result<Tensor>,
    ) -> Result<Tensor> {
        if self.pre_norm {
            let y = f(&self.norms[i].forward(x)?)?;
            x + drop(&y, d)?
        } else {
            let y = f(x)?;
            self.norms[i].forward(&(x + drop(&y, d)?)?)
        }
    }

    fn forward(&self, x: &Tensor, m: &Memory<'_>, d: Option<&Dropout<'_>>) -> Result<Tensor> {
        let x = self.block(x, 0, d, |x| {
            let qk = x.broadcast_add(m.query_pos)?;
            self.self_attn
                .forward_masked(&qk, &qk, x, None, None, d, products(d))
        })?;
        let key = m.out.broadcast_add(m.pos)?;
        let x = self.block(&x, 1, d, |x| {
            let q = x.broadcast_add(m.query_pos)?;
            self.cross_attn
                .forward_masked(&q, &key, m.out, None, None, d, products(d))
        })?;
        self.block(&x, 2, d, |x| self.ff.forward(x, d, products(d)))
    }
}

/// The CVAE encoder of the training objective.
struct VaeEncoder {
    encoder: Encoder,
    cls: Tensor,
    state_proj: Option<Linear>,
    action_proj: Linear,
    latent_out: Linear,
    pos: Tensor,
}

/// 1-D sinusoidal position table `(n, dim)`: `sin` at even columns, `cos` at odd ones, of
/// `pos / 10000^(2 floor(j / 2) / dim)` (Attention Is All You Need; computed in f64).
pub fn sinusoidal_table(n: usize, dim: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(n * dim);
    for p in 0..n {
        for j in 0..dim {
            let angle = p as f64 / 10000f64.powf((2 * (j / 2)) as f64 / dim as f64);
            out.push(if j % 2 == 0 { angle.sin() } else { angle.cos() } as f32);
        }
    }
    out
}

/// LeRobot's `ACTSinusoidalPositionEmbedding2d` for an `h x w` feature map, as rows `(h w, dm)`
/// in token order (row-major over (y, x)). With `D = dm / 2` and positions `1..=h` scaled to
/// `y / (h + 1e-6) * 2 pi` (the same for x), channel `2p` of the first `D` is
/// `sin(y / 10000^(2p / D))` and channel `2p + 1` its cosine; the last `D` are the same of x.
/// The arithmetic follows PyTorch's f32 order; sines and cosines are taken in f64 and
/// rounded (PyTorch's are within an ulp of that).
pub fn sinusoidal_2d(h: usize, w: usize, dm: usize) -> Vec<f32> {
    let d = dm / 2;
    let two_pi = std::f64::consts::TAU as f32;
    let freq: Vec<f32> = (0..d)
        .map(|i| 10000f32.powf((2 * (i / 2)) as f32 / d as f32))
        .collect();
    let scaled = |p: usize, n: usize| (p + 1) as f32 / (n as f32 + 1e-6) * two_pi;
    let mut out = Vec::with_capacity(h * w * dm);
    for y in 0..h {
        for x in 0..w {
            for pos in [scaled(y, h), scaled(x, w)] {
                out.extend(freq.iter().enumerate().map(|(i, f)| {
                    let a = f64::from(pos / f);
                    (if i % 2 == 0 { a.sin() } else { a.cos() }) as f32
                }));
            }
        }
    }
    out
}

/// The camera path: backbone, projection to `dim_model`.
struct Vision {
    backbone: ResNet18,
    proj: Conv2d,
    /// The position embedding of the last feature-map size seen, `(h, w)` and `(1, h w,
    /// dm)`: computed once per size, not on every forward (PGD calls it per iteration).
    pos: std::sync::Mutex<Option<((usize, usize), Tensor)>>,
}

impl Vision {
    fn new(c: &ActConfig, vb: &VarBuilder) -> Result<Self> {
        let backbone = ResNet18::new(
            c.vision_backbone_width,
            BackboneNorm::FrozenBatch,
            BackboneNames::Torchvision,
            vb.pp("backbone"),
        )?;
        let proj = Conv2d::new(
            backbone.out_channels(),
            c.dim_model,
            1,
            1,
            0,
            true,
            vb.pp("encoder_img_feat_input_proj"),
        )?;
        Ok(Self {
            backbone,
            proj,
            pos: std::sync::Mutex::new(None),
        })
    }

    /// [`sinusoidal_2d`] for an `h x w` map as a `(1, h w, dm)` tensor on `dev`, from the
    /// cache when the size is the last one seen.
    fn position(&self, (h, w, dm): (usize, usize, usize), dev: &Device) -> Result<Tensor> {
        // A poisoned lock only means another thread panicked mid-update of a cache whose
        // every state is valid (empty or complete): take it.
        let mut slot = self.pos.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(((ch, cw), t)) = slot.as_ref()
            && (*ch, *cw) == (h, w)
            && t.device().same_device(dev)
        {
            return Ok(t.clone());
        }
        let t = Tensor::from_vec(sinusoidal_2d(h, w, dm), (1, h * w, dm), dev)?;
        *slot = Some(((h, w), t.clone()));
        Ok(t)
    }

    /// The tokens `(B, h w, dm)` and their position embedding `(1, h w, dm)` of one camera's
    /// normalised frames `(B, 3, H, W)`.
    fn tokens(&self, img: &Tensor, p: Products) -> Result<(Tensor, Tensor)> {
        self.tokens_of_features(&self.backbone.forward(img, p)?, p)
    }

    /// [`Self::tokens`] from the backbone's feature map `(B, C, h, w)`.
    fn tokens_of_features(&self, features: &Tensor, p: Products) -> Result<(Tensor, Tensor)> {
        let f = self.proj.forward(features, p)?;
        let (b, dm, h, w) = f.dims4()?;
        let tokens = f.reshape((b, dm, h * w))?.transpose(1, 2)?.contiguous()?;
        let pos = self.position((h, w, dm), features.device())?;
        Ok((tokens, pos))
    }
}

/// The normalised observations of a batch, as the config has them.
#[derive(Clone, Copy, Debug, Default)]
pub struct ActInputs<'a> {
    /// Robot state `(B, k s)`: the `k = n_obs_steps` observed steps' states side by side,
    /// oldest first.
    pub state: Option<&'a Tensor>,
    /// Environment state `(B, k e)`, as `state`.
    pub env: Option<&'a Tensor>,
    /// One `(B, 3, H, W)` batch of normalised frames per camera, in the config's order.
    pub images: &'a [Tensor],
    /// Instead of `images` (which must then be empty): each camera's backbone feature map
    /// `(B, C, h, w)`, as [`ActNet::backbone_features`] gives it (a frozen backbone's
    /// cached output, for training).
    pub features: &'a [Tensor],
}

/// The ACT network (weights under `model.` in LeRobot's checkpoints).
pub struct ActNet {
    vision: Option<Vision>,
    cameras: usize,
    config: ActConfig,
    vae: Option<VaeEncoder>,
    encoder: Encoder,
    decoder: Vec<DecoderLayer>,
    decoder_norm: LayerNorm,
    state_proj: Option<Linear>,
    env_proj: Option<Linear>,
    latent_proj: Linear,
    pos_1d: Tensor,
    query_pos: Tensor,
    head: Linear,
}

/// What the network returns: actions `(B, chunk, A)` and, with the CVAE, `(mu, 2 log sigma)`.
pub struct ActOutput {
    /// Normalised actions `(B, chunk_size, action_dim)`.
    pub actions: Tensor,
    /// The latent's mean and `2 log sigma`, `(B, latent_dim)` each, when the CVAE ran.
    pub latent: Option<(Tensor, Tensor)>,
}

/// The CVAE inputs of a training batch.
pub struct VaeInput<'a> {
    /// Normalised target actions `(B, chunk_size, A)`.
    pub actions: &'a Tensor,
    /// `(B, chunk_size)`: 1 where the action is padding beyond the episode's end.
    pub is_pad: &'a Tensor,
    /// Standard normal draws for the reparameterisation, `(B, latent_dim)`.
    pub eps: &'a Tensor,
}

impl ActNet {
    /// Build from `config` and a `VarBuilder` rooted at the model (`model.` in checkpoints).
    pub fn new(config: ActConfig, vb: VarBuilder) -> Result<Self> {
        let c = &config;
        let dm = c.dim_model;
        let a = c.action_dim().map_err(candle_core::Error::wrap)?;
        let lin = |inp: usize, name: &str| candle_nn::linear(inp, dm, vb.pp(name));
        let state_proj = c
            .state_input_dim()
            .map(|s| lin(s, "encoder_robot_state_input_proj"))
            .transpose()?;
        let env_proj = c
            .env_state_input_dim()
            .map(|e| lin(e, "encoder_env_state_input_proj"))
            .transpose()?;
        let n_1d = 1 + usize::from(state_proj.is_some()) + usize::from(env_proj.is_some());
        let vae = if c.use_vae {
            Some(Self::vae(c, &vb)?)
        } else {
            None
        };
        let decoder = (0..c.n_decoder_layers)
            .map(|i| DecoderLayer::new(c, vb.pp(format!("decoder.layers.{i}"))))
            .collect::<Result<_>>()?;
        let vision = if c.has_images() {
            Some(Vision::new(c, &vb)?)
        } else {
            None
        };
        Ok(Self {
            vision,
            cameras: c.image_features().map_err(candle_core::Error::wrap)?.len(),
            vae,
            encoder: Encoder::new(c, c.n_encoder_layers, vb.pp("encoder"))?,
            decoder,
            decoder_norm: layer_norm(dm, vb.pp("decoder.norm"))?,
            state_proj,
            env_proj,
            latent_proj: lin(c.latent_dim, "encoder_latent_input_proj")?,
            pos_1d: vb.get_with_hints(
                (n_1d, dm),
                "encoder_1d_feature_pos_embed.weight",
                Init::Randn {
                    mean: 0.0,
                    stdev: 1.0,
                },
            )?,
            query_pos: vb.get_with_hints(
                (c.chunk_size, dm),
                "decoder_pos_embed.weight",
                Init::Randn {
                    mean: 0.0,
                    stdev: 1.0,
                },
            )?,
            head: candle_nn::linear(dm, a, vb.pp("action_head"))?,
            config,
        })
    }

    fn vae(c: &ActConfig, vb: &VarBuilder) -> Result<VaeEncoder> {
        let dm = c.dim_model;
        let a = c.action_dim().map_err(candle_core::Error::wrap)?;
        let state_proj = c
            .state_input_dim()
            .map(|s| candle_nn::linear(s, dm, vb.pp("vae_encoder_robot_state_input_proj")))
            .transpose()?;
        let n = 1 + c.chunk_size + usize::from(state_proj.is_some());
        let pos = Tensor::from_vec(sinusoidal_table(n, dm), (1, n, dm), vb.device())?;
        Ok(VaeEncoder {
            encoder: Encoder::new(c, c.n_vae_encoder_layers, vb.pp("vae_encoder"))?,
            cls: vb.get_with_hints(
                (1, dm),
                "vae_encoder_cls_embed.weight",
                Init::Randn {
                    mean: 0.0,
                    stdev: 1.0,
                },
            )?,
            state_proj,
            action_proj: candle_nn::linear(a, dm, vb.pp("vae_encoder_action_input_proj"))?,
            latent_out: candle_nn::linear(
                dm,
                2 * c.latent_dim,
                vb.pp("vae_encoder_latent_output_proj"),
            )?,
            pos,
        })
    }

    /// The config.
    pub fn config(&self) -> &ActConfig {
        &self.config
    }

    /// The backbone's feature map `(B, C, h, w)` of one camera's normalised frames
    /// `(B, 3, H, W)`, each sample's products of a batch of one's shape (so a cache of it
    /// gives the bits an evaluation computes); `None` without cameras.
    pub fn backbone_features(&self, img: &Tensor) -> Result<Option<Tensor>> {
        self.vision
            .as_ref()
            .map(|v| v.backbone.forward(img, Products::PerSample))
            .transpose()
    }

    /// The CVAE encoder's fixed position table `(1, S, D)` (LeRobot's `vae_encoder_pos_enc`
    /// buffer, written into checkpoints so LeRobot loads them strictly).
    pub fn vae_pos_enc(&self) -> Option<&Tensor> {
        self.vae.as_ref().map(|v| &v.pos)
    }

    /// The latent's `(mu, 2 log sigma)` from the CVAE encoder.
    fn encode_latent(
        &self,
        vae: &VaeEncoder,
        state: Option<&Tensor>,
        input: &VaeInput<'_>,
        d: Option<&Dropout<'_>>,
    ) -> Result<(Tensor, Tensor)> {
        let b = input.actions.dim(0)?;
        let dm = self.config.dim_model;
        let mut tokens = vec![
            vae.cls
                .unsqueeze(0)?
                .broadcast_as((b, 1, dm))?
                .contiguous()?,
        ];
        let mut fixed = 1;
        if let (Some(p), Some(s)) = (&vae.state_proj, state) {
            tokens.push(p.forward(s)?.unsqueeze(1)?);
            fixed += 1;
        }
        tokens.push(vae.action_proj.forward(input.actions)?);
        let x = Tensor::cat(&tokens, 1)?;
        let keep = Tensor::zeros((b, fixed), DType::F32, x.device())?;
        let is_pad = Tensor::cat(&[keep, input.is_pad.to_dtype(DType::F32)?], 1)?;
        let mask = (is_pad * -1e9)?;
        let out = vae.encoder.forward(x, Some(&vae.pos), Some(&mask), d)?;
        let params = vae.latent_out.forward(&out.narrow(1, 0, 1)?.squeeze(1)?)?;
        let l = self.config.latent_dim;
        Ok((params.narrow(1, 0, l)?, params.narrow(1, l, l)?))
    }

    /// Normalised observations in, normalised actions out; `vae` (training) runs the CVAE
    /// encoder and samples the latent, else the latent is zero; `d` is training dropout.
    pub fn forward(
        &self,
        inputs: &ActInputs<'_>,
        vae: Option<&VaeInput<'_>>,
        d: Option<&Dropout<'_>>,
    ) -> Result<ActOutput> {
        let first = (inputs.state.or(inputs.env))
            .or(inputs.images.first())
            .or(inputs.features.first());
        let b = first.map(|t| t.dim(0)).transpose()?.unwrap_or(1);
        let dev = self.pos_1d.device();
        let (latent, z) = match (&self.vae, vae) {
            (Some(enc), Some(input)) => {
                let (mu, log_sigma_x2) = self.encode_latent(enc, inputs.state, input, d)?;
                let z = (&mu + (&log_sigma_x2 / 2.0)?.exp()?.mul(input.eps)?)?;
                (Some((mu, log_sigma_x2)), z)
            }
            _ => (
                None,
                Tensor::zeros((b, self.config.latent_dim), DType::F32, dev)?,
            ),
        };
        let (x, pos) = self.encoder_tokens(&z, inputs, products(d))?;
        let memory = self.encoder.forward(x, Some(&pos), None, d)?;
        let query_pos = self.query_pos.unsqueeze(0)?;
        let m = Memory {
            out: &memory,
            pos: &pos,
            query_pos: &query_pos,
        };
        let dm = self.config.dim_model;
        let mut y = Tensor::zeros((b, self.config.chunk_size, dm), DType::F32, dev)?;
        for layer in &self.decoder {
            y = layer.forward(&y, &m, d)?;
        }
        let y = self.decoder_norm.forward(&y)?;
        Ok(ActOutput {
            actions: linear3(&self.head, &y, products(d))?,
            latent,
        })
    }

    /// The encoder's tokens `(B, L, dm)` and their position embedding `(1, L, dm)`:
    /// latent, states, then each camera's feature-map cells.
    fn encoder_tokens(
        &self,
        z: &Tensor,
        inputs: &ActInputs<'_>,
        p: Products,
    ) -> Result<(Tensor, Tensor)> {
        let mut tokens = vec![linear2(&self.latent_proj, z, p)?.unsqueeze(1)?];
        for (proj, input) in [
            (&self.state_proj, inputs.state),
            (&self.env_proj, inputs.env),
        ] {
            if let Some(proj) = proj {
                let x = input.ok_or_else(|| {
                    candle_core::Error::Msg("a configured input is missing".into())
                })?;
                tokens.push(linear2(proj, x, p)?.unsqueeze(1)?);
            }
        }
        let mut pos = vec![self.pos_1d.unsqueeze(0)?];
        let (images, features) = (inputs.images, inputs.features);
        match &self.vision {
            Some(v) if images.len() == self.cameras && features.is_empty() => {
                for img in images {
                    let (t, q) = v.tokens(img, p)?;
                    tokens.push(t);
                    pos.push(q);
                }
            }
            Some(v) if features.len() == self.cameras && images.is_empty() => {
                for f in features {
                    let (t, q) = v.tokens_of_features(f, p)?;
                    tokens.push(t);
                    pos.push(q);
                }
            }
            None if images.is_empty() && features.is_empty() => {}
            _ => candle_core::bail!(
                "{} camera batches and {} feature maps given, the config has {} cameras",
                images.len(),
                features.len(),
                self.cameras
            ),
        }
        Ok((Tensor::cat(&tokens, 1)?, Tensor::cat(&pos, 1)?))
    }

    /// LeRobot's loss: the L1 error over non-padded actions (averaged over every element, as
    /// LeRobot's `.mean()` does) plus `kl_weight` times the KL divergence of the latent from
    /// the standard normal (summed over the latent, averaged over the batch).
    pub fn loss(
        &self,
        out: &ActOutput,
        target: &Tensor,
        is_pad: &Tensor,
    ) -> Result<(Tensor, f32, f32)> {
        let keep = (1.0 - is_pad.to_dtype(DType::F32)?)?.unsqueeze(D::Minus1)?;
        let l1 = (&out.actions - target)?
            .abs()?
            .broadcast_mul(&keep)?
            .mean_all()?;
        let Some((mu, ls)) = &out.latent else {
            let v = l1.to_scalar::<f32>()?;
            return Ok((l1, v, 0.0));
        };
        let kld = ((1.0 + ls)? - mu.sqr()? - ls.exp()?)?
            .affine(-0.5, 0.0)?
            .sum(1)?
            .mean_all()?;
        let total = (&l1 + (&kld * self.config.kl_weight)?)?;
        let (a, b) = (l1.to_scalar::<f32>()?, kld.to_scalar::<f32>()?);
        Ok((total, a, b))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sinusoid_table_matches_the_formula_at_known_points() {
        let t = sinusoidal_table(3, 4);
        // Position 0: sin 0, cos 0, sin 0, cos 0.
        assert_eq!(&t[..4], &[0.0, 1.0, 0.0, 1.0]);
        // Position 2, column 2: sin(2 / 10000^(2/4)) = sin(0.02).
        assert!((t[2 * 4 + 2] - 0.02f32.sin()).abs() < 1e-7);
        assert!((t[2 * 4 + 1] - 2f32.cos()).abs() < 1e-7);
    }

    /// The cached 2-D position table is the formula's for whichever map size comes, in any
    /// order (a size change replaces the cache, a repeat reads it).
    #[test]
    fn the_position_cache_follows_the_feature_map_size() {
        let c = ActConfig {
            vision_backbone_width: 4,
            dim_model: 8,
            ..ActConfig::cpu()
        };
        let vm = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let v = Vision::new(&c, &vb).expect("vision");
        for (h, w) in [(3, 3), (3, 3), (2, 5), (3, 3)] {
            let got = v.position((h, w, 8), &Device::Cpu).expect("position");
            assert_eq!(got.dims(), &[1, h * w, 8]);
            let got = got.flatten_all().and_then(|t| t.to_vec1::<f32>());
            assert_eq!(got.expect("values"), sinusoidal_2d(h, w, 8), "{h}x{w}");
        }
    }
}
