//! The Diffusion Policy model: observation encoding to the global conditioning, DDPM/DDIM
//! sampling with injected noise, the training loss, and the loss gradient with respect to the
//! observation.

use std::collections::BTreeMap;

use candle_core::{D, DType, Device, Tensor, Var};
use candle_nn::VarBuilder;
use rand::RngCore;
use rand_distr::{Distribution, StandardNormal};

use crate::config::{DiffusionConfig, FeatureType};
use crate::error::{PolicyError, config_err};
use crate::kernels::Products;
use crate::normalize::{ImageNorm, NormMode, Normalizer, Stats};
pub use crate::policy::Observation;
use crate::policy::{AttackablePolicy, AttackedQuery, ChunkPolicy, ObsNeeds, Query};
use crate::scheduler::Scheduler;
use crate::transformer::TransformerForDiffusion;
use crate::unet::ConditionalUnet1d;
use crate::vision::RgbEncoder;

/// Normalised observation tensors of a batch: `state (B, T_o, S)`, `env (B, T_o, E)`,
/// `image (B T_o N, 3, H, W)` in [0, 1] for `N` cameras, rows in (query, step, camera)
/// order as LeRobot's `(b s n)` (normalised inside, so gradients can be taken w.r.t. pixel
/// values).
#[derive(Clone, Debug)]
pub struct ObsBatch {
    /// Normalised state.
    pub state: Tensor,
    /// Normalised environment state.
    pub env: Option<Tensor>,
    /// Images in [0, 1], every camera's frame of a step together.
    pub image: Option<Tensor>,
}

/// The error of an image operation on a policy without a camera.
fn no_camera() -> PolicyError {
    config_err("input_features", "no observation.image", "an image policy")
}

/// The statistics a policy needs, by feature name (LeRobot's names).
pub type StatsMap = BTreeMap<String, Stats>;

/// The noise network: LeRobot's conditional U-Net 1D, or Diffusion Policy's transformer
/// (`DiffusionConfig::transformer`).
pub enum NoiseNet {
    /// The conditional U-Net 1D.
    Unet(ConditionalUnet1d),
    /// `TransformerForDiffusion`.
    Transformer(TransformerForDiffusion),
}

impl NoiseNet {
    /// The prediction for the noisy chunk `x (B, T, A)` at `timesteps` with the observation
    /// features `cond (B, n_obs_steps * F)`, the products computed as `products` says (no
    /// dropout: mte trains the transformer without it).
    pub fn forward_with(
        &self,
        x: &Tensor,
        timesteps: &[usize],
        cond: &Tensor,
        products: Products,
    ) -> candle_core::Result<Tensor> {
        match self {
            NoiseNet::Unet(u) => u.forward_with(x, timesteps, cond, products),
            NoiseNet::Transformer(t) => t.forward(x, timesteps, cond, None, products),
        }
    }
}

/// Diffusion Policy.
pub struct DiffusionPolicy {
    config: DiffusionConfig,
    device: Device,
    net: NoiseNet,
    /// The image encoder: one shared by every camera, or one per camera
    /// (`use_separate_rgb_encoder_per_camera`); empty without cameras.
    rgb: Vec<RgbEncoder>,
    /// The cameras, [`DiffusionConfig::cameras`]' order.
    n_cameras: usize,
    scheduler: Scheduler,
    state_norm: Normalizer,
    env_norm: Option<Normalizer>,
    /// Each camera's normalisation (from its own statistics, as LeRobot's).
    image_norms: Vec<Option<ImageNorm>>,
    action_norm: Normalizer,
    stats: StatsMap,
}

fn norm_for(
    config: &DiffusionConfig,
    stats: &StatsMap,
    name: &'static str,
    kind: &str,
    dim: usize,
) -> Result<Normalizer, PolicyError> {
    let mode = config
        .normalization_mapping
        .get(kind)
        .copied()
        .unwrap_or(NormMode::Identity);
    let empty = Stats::default();
    let s = stats.get(name).unwrap_or(&empty);
    Normalizer::new(name, mode, s, dim)
}

impl DiffusionPolicy {
    /// Build from a config, normalisation statistics and a `VarBuilder` rooted at the model
    /// (keys `diffusion.unet.…`, `diffusion.rgb_encoder.…`).
    pub fn new(
        config: DiffusionConfig,
        stats: StatsMap,
        vb: VarBuilder,
    ) -> Result<Self, PolicyError> {
        config.validate()?;
        let device = vb.device().clone();
        let s_dim = config.vector_dim(FeatureType::State).unwrap_or(0);
        let e_dim = config.vector_dim(FeatureType::Env);
        let a_dim = config.action_dim()?;
        let vb = vb.pp("diffusion");
        let cameras: Vec<String> = config.cameras().into_iter().map(String::from).collect();
        let encoder = |vb: VarBuilder| {
            RgbEncoder::with_width(
                config.vision_backbone_width,
                config.crop_shape,
                config.spatial_softmax_num_keypoints,
                vb,
            )
        };
        // LeRobot's keys: `rgb_encoder.…` shared, `rgb_encoder.<i>.…` one per camera.
        let rgb = match (cameras.len(), config.use_separate_rgb_encoder_per_camera) {
            (0, _) => Vec::new(),
            (_, false) => vec![encoder(vb.pp("rgb_encoder"))?],
            (n, true) => (0..n)
                .map(|i| encoder(vb.pp("rgb_encoder").pp(i)))
                .collect::<candle_core::Result<_>>()?,
        };
        let image_dim = rgb.first().map_or(0, RgbEncoder::feature_dim) * cameras.len();
        let per_step = s_dim + image_dim + e_dim.unwrap_or(0);
        let net = match &config.transformer {
            None => NoiseNet::Unet(ConditionalUnet1d::new(
                &config,
                per_step * config.n_obs_steps,
                vb.pp("unet"),
            )?),
            Some(t) => NoiseNet::Transformer(TransformerForDiffusion::new(
                t,
                a_dim,
                config.horizon,
                config.n_obs_steps,
                per_step,
                vb.pp("transformer"),
            )?),
        };
        let scheduler = Scheduler::new(config.scheduler_config()?)?;
        let state_norm = norm_for(&config, &stats, "observation.state", "STATE", s_dim)?;
        let env_norm = match e_dim {
            Some(d) => Some(norm_for(
                &config,
                &stats,
                "observation.environment_state",
                "ENV",
                d,
            )?),
            None => None,
        };
        // LeRobot: a kind absent from the mapping is not normalised.
        let visual = config
            .normalization_mapping
            .get("VISUAL")
            .copied()
            .unwrap_or(NormMode::Identity);
        let image_norms = cameras
            .iter()
            .map(|name| ImageNorm::for_mode(visual, name, stats.get(name)))
            .collect::<Result<Vec<_>, _>>()?;
        let action_norm = norm_for(&config, &stats, "action", "ACTION", a_dim)?;
        Ok(DiffusionPolicy {
            config,
            device,
            net,
            rgb,
            n_cameras: cameras.len(),
            scheduler,
            state_norm,
            env_norm,
            image_norms,
            action_norm,
            stats,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &DiffusionConfig {
        &self.config
    }

    /// The device the weights live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Normalisation statistics.
    pub fn stats(&self) -> &StatsMap {
        &self.stats
    }

    /// The noise scheduler.
    pub fn scheduler(&self) -> &Scheduler {
        &self.scheduler
    }

    /// The U-Net, when it is the noise network.
    pub fn unet(&self) -> Option<&ConditionalUnet1d> {
        match &self.net {
            NoiseNet::Unet(u) => Some(u),
            NoiseNet::Transformer(_) => None,
        }
    }

    /// The noise network.
    pub fn noise_net(&self) -> &NoiseNet {
        &self.net
    }

    /// The action normaliser.
    pub fn action_normalizer(&self) -> &Normalizer {
        &self.action_norm
    }

    /// Normalised observation tensors for a batch of histories (each `n_obs_steps` long,
    /// oldest first).
    pub fn obs_batch(&self, histories: &[&[Observation]]) -> Result<ObsBatch, PolicyError> {
        let t_o = self.config.n_obs_steps;
        let b = histories.len();
        let s_dim = self.state_norm.dim();
        let mut state = Vec::with_capacity(b * t_o * s_dim);
        let mut env = Vec::new();
        let mut image = Vec::new();
        let img_shape = self.config.image_shape();
        let wrist = self.config.has_wrist_camera();
        for h in histories {
            if h.len() != t_o {
                return Err(PolicyError::Input {
                    name: "history",
                    reason: format!("{} observations, expected n_obs_steps = {t_o}", h.len()),
                });
            }
            for o in h.iter() {
                if o.state.len() != s_dim || o.state.iter().any(|v| !v.is_finite()) {
                    return Err(PolicyError::Input {
                        name: "observation.state",
                        reason: format!("{:?}: expected {s_dim} finite values", o.state),
                    });
                }
                state.extend_from_slice(&o.state);
                if let Some(n) = &self.env_norm {
                    match &o.env_state {
                        Some(e) if e.len() == n.dim() && e.iter().all(|v| v.is_finite()) => {
                            env.extend_from_slice(e);
                        }
                        other => {
                            return Err(PolicyError::Input {
                                name: "observation.environment_state",
                                reason: format!("{other:?}: expected {} finite values", n.dim()),
                            });
                        }
                    }
                }
                if let Some([_, hh, ww]) = img_shape {
                    crate::vision::push_camera_frames(o, wrist, hh, ww, &mut image)?;
                }
            }
        }
        let batch = self.normalized_obs_batch(state, self.env_norm.is_some().then_some(env), b)?;
        Ok(ObsBatch {
            image: match img_shape {
                Some([c, hh, ww]) => Some(Tensor::from_vec(
                    image,
                    (b * t_o * self.n_cameras, c, hh, ww),
                    &self.device,
                )?),
                None => None,
            },
            ..batch
        })
    }

    /// The global conditioning `(B, n_obs_steps * per_step)`: per step [state, image
    /// features, environment state], as LeRobot's `_prepare_global_conditioning`. Images are
    /// full frames and get the evaluation centre crop.
    pub fn global_cond(&self, obs: &ObsBatch) -> Result<Tensor, PolicyError> {
        self.global_cond_impl(obs, false)
    }

    /// [`DiffusionPolicy::global_cond`] for images that are already cropped (training's
    /// random crops).
    pub fn global_cond_cropped(&self, obs: &ObsBatch) -> Result<Tensor, PolicyError> {
        self.global_cond_impl(obs, true)
    }

    /// A batch from raw (unnormalised) state and environment-state rows, `B x n_obs_steps`
    /// of each, normalised with this policy's statistics; no images.
    pub fn normalized_obs_batch(
        &self,
        mut state: Vec<f32>,
        env: Option<Vec<f32>>,
        b: usize,
    ) -> Result<ObsBatch, PolicyError> {
        let t_o = self.config.n_obs_steps;
        self.state_norm.normalize(&mut state);
        let env = match (env, &self.env_norm) {
            (Some(mut e), Some(n)) => {
                n.normalize(&mut e);
                Some(Tensor::from_vec(e, (b, t_o, n.dim()), &self.device)?)
            }
            _ => None,
        };
        Ok(ObsBatch {
            state: Tensor::from_vec(state, (b, t_o, self.state_norm.dim()), &self.device)?,
            env,
            image: None,
        })
    }

    fn global_cond_impl(&self, obs: &ObsBatch, cropped: bool) -> Result<Tensor, PolicyError> {
        let features = match (self.rgb.is_empty(), &obs.image) {
            (false, Some(img)) => Some(self.encode(img, cropped)?),
            _ => None,
        };
        self.global_cond_from_features(obs, features.as_ref())
    }

    /// The features `(R, F)` of frames `(R, 3, H, W)` in [0, 1] whose rows cycle through
    /// the cameras (R a multiple of their number): each camera normalised with its own
    /// statistics and encoded by its encoder (the shared one, or its own), rows kept.
    fn encode(&self, img: &Tensor, cropped: bool) -> Result<Tensor, PolicyError> {
        let run = |enc: &RgbEncoder, x: &Tensor| -> Result<Tensor, PolicyError> {
            Ok(if cropped {
                enc.forward_cropped(x)?
            } else {
                enc.forward(x)?
            })
        };
        let n = self.n_cameras;
        if n <= 1 {
            let enc = self.rgb.first().ok_or_else(no_camera)?;
            return run(enc, &self.normalize_camera(img, 0)?);
        }
        let normed = crate::vision::split_cameras(img, n)?
            .iter()
            .enumerate()
            .map(|(i, x)| self.normalize_camera(x, i))
            .collect::<Result<Vec<_>, _>>()?;
        let feats = if self.rgb.len() == n {
            (0..n)
                .map(|i| run(&self.rgb[i], &normed[i]))
                .collect::<Result<Vec<_>, _>>()?
        } else {
            // The shared encoder once over every frame, rows back in (b n) order.
            let x = Tensor::stack(&normed, 1)?.flatten_to(1)?;
            return run(&self.rgb[0], &x);
        };
        Ok(Tensor::stack(&feats, 1)?.flatten_to(1)?)
    }

    /// Camera `i`'s frames normalised.
    fn normalize_camera(&self, img: &Tensor, i: usize) -> Result<Tensor, PolicyError> {
        match self.image_norms.get(i) {
            Some(Some(n)) => Ok(n.apply(img)?),
            _ => Ok(img.clone()),
        }
    }

    /// The global conditioning of `obs` with its image features already computed
    /// (`(B n_obs_steps, 2K)`, e.g. by [`DiffusionPolicy::image_features`]); `obs.image` is
    /// not read. For callers that need the features themselves too (the fine-tuning
    /// consistency term), so the encoder runs once.
    pub fn global_cond_from_features(
        &self,
        obs: &ObsBatch,
        features: Option<&Tensor>,
    ) -> Result<Tensor, PolicyError> {
        let (b, t_o, _) = obs.state.dims3()?;
        let mut parts = vec![obs.state.clone()];
        if let (Some(enc), Some(f)) = (self.rgb.first(), features) {
            // (b s n, F) -> (b, s, n F): LeRobot's `(b s n) ... -> b s (n ...)`.
            parts.push(f.reshape((b, t_o, self.n_cameras * enc.feature_dim()))?);
        }
        if let Some(e) = &obs.env {
            parts.push(e.clone());
        }
        Ok(Tensor::cat(&parts, D::Minus1)?.flatten_from(1)?)
    }

    /// The image encoder's features `(R, 2K)` of full frames `(R, 3, H, W)` in [0, 1]
    /// (normalised and centre-cropped as at evaluation), for probes and defences. With
    /// several cameras the rows cycle through them ([`ObsBatch`]'s order).
    pub fn image_features(&self, img: &Tensor) -> Result<Tensor, PolicyError> {
        self.encode(img, false)
    }

    /// [`DiffusionPolicy::image_features`] for frames already cropped to the encoder's crop
    /// (training's random crops).
    pub fn image_features_cropped(&self, img: &Tensor) -> Result<Tensor, PolicyError> {
        self.encode(img, true)
    }

    /// The number of cameras the policy reads (0 for a state policy).
    pub fn n_cameras(&self) -> usize {
        self.n_cameras
    }

    /// Denoise from `noise` (normalised action space, `(B, horizon, action_dim)`) with
    /// the per-step variance noise drawn from `rng` (only on steps that add noise, in
    /// timestep order, as LeRobot draws it); returns normalised chunks.
    pub fn sample_normalized(
        &self,
        cond: &Tensor,
        noise: Tensor,
        rng: &mut dyn RngCore,
    ) -> Result<Tensor, PolicyError> {
        self.sample_normalized_with(cond, noise, &mut |_, buf: &mut [f32]| {
            for v in buf.iter_mut() {
                *v = StandardNormal.sample(rng);
            }
        })
    }

    /// [`DiffusionPolicy::sample_normalized`] with the variance noise supplied by `fill(t,
    /// buffer)`, called once per step that adds noise.
    pub fn sample_normalized_with(
        &self,
        cond: &Tensor,
        noise: Tensor,
        fill: &mut dyn FnMut(usize, &mut [f32]),
    ) -> Result<Tensor, PolicyError> {
        let n = self.config.inference_steps();
        let shape = noise.shape().clone();
        let b = shape.dims()[0];
        let mut x: Vec<f32> = noise.flatten_all()?.to_vec1()?;
        let mut step_noise = vec![0f32; x.len()];
        for t in self.scheduler.timesteps(n)? {
            let xt = Tensor::from_vec(x.clone(), shape.clone(), &self.device)?;
            let eps: Vec<f32> = self
                .net
                .forward_with(&xt, &vec![t; b], cond, Products::PerSample)?
                .flatten_all()?
                .to_vec1()?;
            if self.scheduler.step_adds_noise(t, n)? {
                fill(t, &mut step_noise);
                self.scheduler.step(&eps, t, n, &mut x, &step_noise)?;
            } else {
                self.scheduler.step(&eps, t, n, &mut x, &[])?;
            }
        }
        Ok(Tensor::from_vec(x, shape, &self.device)?)
    }

    /// Predict one chunk (`horizon x action_dim`, row-major, unnormalised, row `r` is the
    /// action for `t - (n_obs_steps - 1) + r`) from a history of `n_obs_steps` observations.
    pub fn predict(
        &self,
        history: &[Observation],
        rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        let x = self.sample_chunk_normalized(&self.obs_batch(&[history])?, rng)?;
        self.unnormalized_chunk(&x)
    }

    /// One normalised chunk `(1, horizon, d)` sampled from a one-history observation batch:
    /// the initial noise, then the per-step variance noise, both drawn from `rng`.
    pub fn sample_chunk_normalized(
        &self,
        obs: &ObsBatch,
        rng: &mut dyn RngCore,
    ) -> Result<Tensor, PolicyError> {
        self.sample_chunks_normalized(obs, &mut [rng])
    }

    /// Normalised chunks `(B, horizon, d)` for an observation batch of `B` histories, chunk
    /// `i` drawn from `rngs[i]` exactly as [`DiffusionPolicy::sample_chunk_normalized`]
    /// draws a batch of one (initial noise, then each noisy step's variance noise), and the
    /// network batch-invariant (`kernels::batch`): chunk `i` does not depend on the others.
    pub fn sample_chunks_normalized(
        &self,
        obs: &ObsBatch,
        rngs: &mut [&mut (dyn RngCore + '_)],
    ) -> Result<Tensor, PolicyError> {
        let cond = self.global_cond(obs)?;
        let b = cond.dim(0)?;
        if rngs.len() != b {
            return Err(config_err(
                "rngs",
                rngs.len(),
                format!("one per history ({b})"),
            ));
        }
        let (tp, d) = (self.config.horizon, self.config.action_dim()?);
        let mut init = Vec::with_capacity(b * tp * d);
        for rng in rngs.iter_mut() {
            init.extend((0..tp * d).map(|_| -> f32 { StandardNormal.sample(&mut **rng) }));
        }
        let noise = Tensor::from_vec(init, (b, tp, d), &self.device)?.to_dtype(cond.dtype())?;
        self.sample_normalized_with(&cond, noise, &mut |_, buf: &mut [f32]| {
            for (rng, part) in rngs.iter_mut().zip(buf.chunks_mut(tp * d)) {
                for v in part.iter_mut() {
                    *v = StandardNormal.sample(&mut **rng);
                }
            }
        })
    }

    /// Chunks for a batch of queries ([`ChunkPolicy::predict_chunks`]'s contract).
    pub fn predict_batch<'a>(
        &self,
        queries: &mut [Query<'a>],
    ) -> Result<Vec<Vec<f32>>, PolicyError> {
        let histories: Vec<&[Observation]> = queries.iter().map(|q| q.history).collect();
        let obs = self.obs_batch(&histories)?;
        let mut rngs: Vec<&mut (dyn RngCore + 'a)> =
            queries.iter_mut().map(|q| &mut *q.rng).collect();
        let x = self.sample_chunks_normalized(&obs, &mut rngs)?;
        self.unnormalized_chunks(&x)
    }

    /// [`DiffusionPolicy::unnormalized_chunk`] of each chunk of `x (B, horizon, d)`.
    pub fn unnormalized_chunks(&self, x: &Tensor) -> Result<Vec<Vec<f32>>, PolicyError> {
        (0..x.dim(0)?)
            .map(|i| self.unnormalized_chunk(&x.narrow(0, i, 1)?))
            .collect()
    }

    /// A sampled normalised chunk as unnormalised actions, row-major; a non-finite action is
    /// an error.
    pub fn unnormalized_chunk(&self, x: &Tensor) -> Result<Vec<f32>, PolicyError> {
        let mut chunk: Vec<f32> = x.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        self.action_norm.unnormalize(&mut chunk);
        if chunk.iter().any(|v| !v.is_finite()) {
            return Err(PolicyError::Input {
                name: "action",
                reason: "sampling produced a non-finite action".into(),
            });
        }
        Ok(chunk)
    }

    /// The training loss (noise-prediction MSE, mean over all elements, or over unpadded
    /// rows when `do_mask_loss_for_padding`) for normalised actions `x0 (B, horizon, d)`,
    /// given `eps` of the same shape and one timestep per row. A training loss: the batch's
    /// products are fused ([`Products::Fused`]), so a row's value may depend on the batch.
    pub fn loss(
        &self,
        cond: &Tensor,
        x0: &Tensor,
        eps: &Tensor,
        timesteps: &[usize],
        pad: Option<&Tensor>,
    ) -> Result<Tensor, PolicyError> {
        let se = self.squared_error(cond, x0, eps, timesteps, Products::Fused)?;
        let loss = match (self.config.do_mask_loss_for_padding, pad) {
            (true, Some(p)) => {
                // p: (B, horizon) with 1 where padded.
                let keep = (1.0 - p.to_dtype(x0.dtype())?)?.unsqueeze(D::Minus1)?;
                se.broadcast_mul(&keep)?.mean_all()?
            }
            _ => se.mean_all()?,
        };
        Ok(loss)
    }

    /// The per-element squared error of the noise (or sample) prediction, `(B, horizon, d)`.
    fn squared_error(
        &self,
        cond: &Tensor,
        x0: &Tensor,
        eps: &Tensor,
        timesteps: &[usize],
        products: Products,
    ) -> Result<Tensor, PolicyError> {
        let abar = self.scheduler.alphas_cumprod();
        let b = timesteps.len();
        let mut sa = Vec::with_capacity(b);
        let mut sb = Vec::with_capacity(b);
        for &t in timesteps {
            let a = *abar
                .get(t)
                .ok_or_else(|| config_err("timestep", t, format!("< {}", abar.len())))?;
            sa.push(a.sqrt() as f32);
            sb.push((1.0 - a).sqrt() as f32);
        }
        let sa = Tensor::from_vec(sa, (b, 1, 1), &self.device)?.to_dtype(x0.dtype())?;
        let sb = Tensor::from_vec(sb, (b, 1, 1), &self.device)?.to_dtype(x0.dtype())?;
        let noisy = (x0.broadcast_mul(&sa)? + eps.broadcast_mul(&sb)?)?;
        let pred = self.net.forward_with(&noisy, timesteps, cond, products)?;
        let target = match self.config.prediction_type.as_str() {
            "sample" => x0.clone(),
            _ => eps.clone(),
        };
        Ok((pred - target)?.sqr()?)
    }

    /// The policy's own training loss and its gradient with respect to the observation:
    /// the normalised state (and environment state) and, for image policies, the pixel values
    /// in [0, 1]. `x0` is the (normalised) action chunk used as the clean sample, `eps` and
    /// `timesteps` the noise and steps (one per sample); the loss is averaged over them.
    pub fn observation_gradient(
        &self,
        obs: &ObsBatch,
        x0: &Tensor,
        eps: &Tensor,
        timesteps: &[usize],
    ) -> Result<(f32, ObsGradient), PolicyError> {
        let (vars, batch) = ObsVars::new(obs)?;
        let cond = self.global_cond(&batch)?;
        let n = timesteps.len();
        let cond = if cond.dim(0)? == 1 && n > 1 {
            cond.repeat((n, 1))?
        } else {
            cond
        };
        let x0 = if x0.dim(0)? == 1 && n > 1 {
            x0.repeat((n, 1, 1))?
        } else {
            x0.clone()
        };
        let loss = self.loss(&cond, &x0, eps, timesteps, None)?;
        let grads = loss.backward()?;
        Ok((
            loss.to_dtype(DType::F32)?.to_scalar::<f32>()?,
            vars.gradient(&grads)?,
        ))
    }

    /// [`DiffusionPolicy::observation_gradient`] for a batch of `B` independent queries:
    /// `obs` and `x0 (B, horizon, d)` hold one query each, `eps` and `timesteps` `n` samples
    /// per query, query-major (`B n` rows). Query `i`'s loss is the mean over its own samples,
    /// and the gradient is that of the sum of the queries' losses, so each query's gradient
    /// is exactly its own (a batch of one is [`DiffusionPolicy::observation_gradient`]'s
    /// repeated-conditioning case, operation for operation). Returns each query's loss.
    pub fn observation_gradient_per_query(
        &self,
        obs: &ObsBatch,
        x0: &Tensor,
        eps: &Tensor,
        timesteps: &[usize],
    ) -> Result<(Vec<f32>, ObsGradient), PolicyError> {
        let (vars, batch) = ObsVars::new(obs)?;
        let cond = self.global_cond(&batch)?;
        let b = cond.dim(0)?;
        if b == 0 || !timesteps.len().is_multiple_of(b) || x0.dim(0)? != b {
            return Err(config_err(
                "timesteps",
                timesteps.len(),
                format!("the same number of samples for each of the {b} queries"),
            ));
        }
        let n = timesteps.len() / b;
        // Each query's row repeated n times, query-major.
        let per_query = |t: &Tensor| -> Result<Tensor, PolicyError> {
            let mut reps = vec![1; t.rank() + 1];
            reps[1] = n;
            let mut dims = t.dims().to_vec();
            dims[0] = b * n;
            Ok(t.unsqueeze(1)?.repeat(reps)?.reshape(dims)?)
        };
        let (cond, x0) = (per_query(&cond)?, per_query(x0)?);
        let se = self.squared_error(&cond, &x0, eps, timesteps, Products::PerSample)?;
        let losses = se.reshape((b, ()))?.mean(1)?;
        let grads = losses.sum_all()?.backward()?;
        Ok((
            losses.to_dtype(DType::F32)?.to_vec1::<f32>()?,
            vars.gradient(&grads)?,
        ))
    }
}

/// The observation tensors of a batch as variables, for their gradients.
struct ObsVars {
    state: Var,
    env: Option<Var>,
    image: Option<Var>,
}

impl ObsVars {
    /// The variables, and the batch that reads them.
    fn new(obs: &ObsBatch) -> Result<(Self, ObsBatch), PolicyError> {
        let var = |t: &Option<Tensor>| t.as_ref().map(Var::from_tensor).transpose();
        let vars = ObsVars {
            state: Var::from_tensor(&obs.state)?,
            env: var(&obs.env)?,
            image: var(&obs.image)?,
        };
        let batch = ObsBatch {
            state: vars.state.as_tensor().clone(),
            env: vars.env.as_ref().map(|v| v.as_tensor().clone()),
            image: vars.image.as_ref().map(|v| v.as_tensor().clone()),
        };
        Ok((vars, batch))
    }

    /// Each variable's gradient (zeros where the loss does not depend on it).
    fn gradient(
        &self,
        grads: &candle_core::backprop::GradStore,
    ) -> Result<ObsGradient, PolicyError> {
        let get = |v: &Var| -> Result<Tensor, PolicyError> {
            Ok(match grads.get(v.as_tensor()) {
                Some(g) => g.clone(),
                None => v.as_tensor().zeros_like()?,
            })
        };
        Ok(ObsGradient {
            state: get(&self.state)?,
            env: self.env.as_ref().map(get).transpose()?,
            image: self.image.as_ref().map(get).transpose()?,
        })
    }
}

/// Gradients of the loss with respect to the observation tensors of an [`ObsBatch`].
#[derive(Clone, Debug)]
pub struct ObsGradient {
    /// d loss / d normalised state.
    pub state: Tensor,
    /// d loss / d normalised environment state.
    pub env: Option<Tensor>,
    /// d loss / d pixel value in [0, 1].
    pub image: Option<Tensor>,
}

impl ChunkPolicy for DiffusionPolicy {
    fn horizon(&self) -> usize {
        self.config.horizon
    }
    fn n_obs_steps(&self) -> usize {
        self.config.n_obs_steps
    }
    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }
    fn needs(&self) -> ObsNeeds {
        ObsNeeds {
            env_state: self.config.vector_dim(FeatureType::Env).is_some(),
            image: self.config.image_shape().map(|[_, h, w]| (w, h)),
            wrist_image: self.config.has_wrist_camera(),
        }
    }
    fn predict_chunk(
        &self,
        history: &[Observation],
        rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        self.predict(history, rng)
    }
    fn attackable(&self) -> Option<&dyn AttackablePolicy> {
        Some(self)
    }
    fn predict_chunks(&self, queries: &mut [Query<'_>]) -> Result<Vec<Vec<f32>>, PolicyError> {
        self.predict_batch(queries)
    }
}

impl AttackablePolicy for DiffusionPolicy {
    fn predict_chunk_attacked(
        &self,
        history: &[Observation],
        pgd: &crate::attack::PgdConfig,
        attack_rng: &mut dyn RngCore,
        sample_rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        Ok(self.pgd_attack(history, pgd, attack_rng, sample_rng)?.chunk)
    }
    fn predict_chunks_attacked(
        &self,
        queries: &mut [AttackedQuery<'_>],
        pgd: &crate::attack::PgdConfig,
    ) -> Result<Vec<Vec<f32>>, PolicyError> {
        Ok(self
            .pgd_attack_batch(queries, pgd)?
            .into_iter()
            .map(|o| o.chunk)
            .collect())
    }
}
