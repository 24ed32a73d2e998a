//! Training Diffusion Policy on an `mte-demo-v1` dataset: AdamW, cosine learning rate with
//! linear warm-up, global gradient-norm clipping, an exponential moving average of the weights,
//! random crops for images, all randomness from one seeded ChaCha stream (windows, noise,
//! timesteps, crops), periodic checkpoints and resume.
//!
//! Resume restores the weights, the EMA, AdamW's moment estimates (`optimizer_state.safetensors`,
//! in the run directory only, not in `checkpoints/<step>/`) and the step, and re-seeds the data
//! stream from `(seed, step)`: a resumed run matches an uninterrupted one bit for bit on the
//! same machine. Runs saved before the moments were kept resume with fresh ones.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::checkpoint;
use crate::config::{DiffusionConfig, FeatureType};
use crate::error::{PolicyError, config_err};
use crate::model::{DiffusionPolicy, ObsBatch, StatsMap};
use crate::normalize::Stats;
pub use crate::training::learning_rate;
use crate::training::{
    AdamW, LossTrace, ParamsAdamW, checkpoint_due, clip_gradients, ema_decay, ema_update,
    restore_optimizers, save_optimizers, step_rng, weight_copies,
};

/// Training settings (the model's own settings, e.g. learning rate, are in the config).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainConfig {
    /// Optimiser steps in total.
    pub steps: usize,
    /// Windows per batch.
    pub batch_size: usize,
    /// Global gradient-norm clip (LeRobot PushT: 10).
    pub grad_clip: f64,
    /// EMA decay ceiling; the decay ramps as min(max, (1 + step) / (10 + step)). None: no EMA.
    pub ema_max_decay: Option<f64>,
    /// Seed of every random draw.
    pub seed: u64,
    /// Write a checkpoint every this many steps (0: only at the end).
    pub checkpoint_every: usize,
    /// Only train on windows of successful episodes.
    pub successful_only: bool,
    /// A safetensors file whose tensors replace the seeded initialisation of the variables
    /// they name (LeRobot keys, e.g. `diffusion.rgb_encoder.…` from
    /// [`crate::pretrain::pretrain_encoder`], or a whole `model.safetensors`). Every key must
    /// be a variable of the policy with the same shape. Ignored when resuming.
    #[serde(default)]
    pub init: Option<PathBuf>,
    /// The `n_obs_steps` the `init` weights were trained with, when it is fewer than this
    /// policy's (U-Net only): each conditioning layer's columns for the older observations the
    /// init never saw start at zero, and its own columns serve the newest observations, so
    /// the policy starts as the init's exactly (it ignores the older frames until trained).
    /// An mte extension, for testing longer observation histories from a warm start.
    #[serde(default)]
    pub init_n_obs_steps: Option<usize>,
    /// Keep the image encoder fixed: its variables are not optimised, and each frame's
    /// features are computed once (centre crop, as at evaluation) and reused, which makes a
    /// step cost about as much as a keypoint policy's. An mte extension for CPU training.
    #[serde(default)]
    pub freeze_encoder: bool,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            steps: 20_000,
            batch_size: 64,
            grad_clip: 10.0,
            ema_max_decay: Some(0.999),
            seed: 100_000,
            checkpoint_every: 2_000,
            successful_only: false,
            init: None,
            init_n_obs_steps: None,
            freeze_encoder: false,
        }
    }
}

impl TrainConfig {
    /// Check every field.
    pub fn validate(&self) -> Result<(), PolicyError> {
        if self.steps == 0 {
            return Err(config_err("steps", self.steps, ">= 1"));
        }
        if self.batch_size == 0 {
            return Err(config_err("batch_size", self.batch_size, ">= 1"));
        }
        if !(self.grad_clip.is_finite() && self.grad_clip > 0.0) {
            return Err(config_err(
                "grad_clip",
                self.grad_clip,
                "a finite number > 0",
            ));
        }
        if let Some(d) = self.ema_max_decay
            && !(0.0..1.0).contains(&d)
        {
            return Err(config_err("ema_max_decay", d, "in [0, 1)"));
        }
        Ok(())
    }
}

/// The arrays training reads, frames first (see `mte_data::Dataset`).
#[derive(Clone, Debug)]
pub struct TrainData {
    /// Agent state per frame (frames x state_dim).
    pub state: Vec<f32>,
    /// Environment state per frame, if the policy uses it.
    pub env_state: Option<Vec<f32>>,
    /// Images per frame, HWC u8, if the policy uses them.
    pub images: Option<Vec<u8>>,
    /// The wrist camera's images per frame, HWC u8 (the scene camera's size), if the policy
    /// reads the wrist camera.
    pub wrist_images: Option<Vec<u8>>,
    /// Actions per frame (frames x action_dim).
    pub action: Vec<f32>,
    /// Frames per episode, in storage order.
    pub episode_lengths: Vec<usize>,
    /// Whether each episode succeeded.
    pub episode_success: Vec<bool>,
    /// Normalisation statistics by feature name.
    pub stats: StatsMap,
}

/// Progress callback: (step, loss, learning rate).
pub type Progress<'a> = &'a (dyn Fn(usize, f32, f64) + Sync);

/// What a finished run reports.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct TrainReport {
    /// Steps run in this invocation.
    pub steps_run: usize,
    /// Final step.
    pub step: usize,
    /// Mean loss over the last 100 steps run by this invocation (`None` when it ran none:
    /// the run was already at its last step).
    pub final_loss: Option<f32>,
    /// Wall time of this invocation (s).
    pub seconds: f64,
}

fn windows(data: &TrainData, c: &DiffusionConfig, successful_only: bool) -> Windows {
    let pad_before = (c.n_obs_steps - 1) as isize;
    let pad_after = (c.n_action_steps - 1) as isize;
    let mut index = Vec::new();
    let mut start = 0;
    for (e, &len) in data.episode_lengths.iter().enumerate() {
        if !successful_only || data.episode_success.get(e).copied().unwrap_or(false) {
            let last = len as isize - c.horizon as isize + pad_after;
            for s in -pad_before..=last {
                index.push((start, len, s));
            }
        }
        start += len;
    }
    Windows { index }
}

/// Demonstration windows of `data` (LeRobot's padding: `n_obs_steps - 1` frames before an
/// episode's start, `n_action_steps - 1` after its end, repeated edge frames).
pub struct Windows {
    /// (episode start frame, episode length, window offset) per window.
    index: Vec<(usize, usize, isize)>,
}

impl Windows {
    /// Every window of `data` for `config` (optionally only successful episodes).
    pub fn new(data: &TrainData, config: &DiffusionConfig, successful_only: bool) -> Self {
        windows(data, config, successful_only)
    }

    /// Number of windows.
    pub fn len(&self) -> usize {
        self.index.len()
    }

    /// No windows.
    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }
}

/// A batch of `b` windows drawn uniformly from `win`: the observation batch (images in
/// [0, 1]: random crops when `crop` and the config crops randomly, else full frames) and the
/// normalised action chunks `x0 (b, horizon, action_dim)` as a flat vector. Every draw comes
/// from `rng`.
pub fn sample_batch(
    policy: &DiffusionPolicy,
    data: &TrainData,
    win: &Windows,
    b: usize,
    rng: &mut ChaCha8Rng,
    crop: bool,
) -> Result<(ObsBatch, Vec<f32>), PolicyError> {
    let mode = if crop { Images::Crop } else { Images::Full };
    let (obs, x0, _) = draw_batch(policy, data, win, b, rng, mode)?;
    Ok((obs, x0))
}

/// How [`draw_batch`] treats images.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Images {
    /// Random crops when the config crops randomly (training).
    Crop,
    /// Full frames.
    Full,
    /// No pixels (the caller has cached features for the returned frames).
    Skip,
}

/// The (top, left) corner of a `crop` window in an `[h, w]` frame: uniform from `rng` when
/// `random`, else centred (nothing drawn).
pub(crate) fn crop_origin(
    [h, w]: [usize; 2],
    [crop_h, crop_w]: [usize; 2],
    random: bool,
    rng: &mut ChaCha8Rng,
) -> (usize, usize) {
    if random {
        (
            rng.random_range(0..=h - crop_h),
            rng.random_range(0..=w - crop_w),
        )
    } else {
        ((h - crop_h) / 2, (w - crop_w) / 2)
    }
}

/// A window of a frame: top-left pixel and size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Crop {
    pub top: usize,
    pub left: usize,
    pub h: usize,
    pub w: usize,
}

/// Copy the `crop` window of HWC u8 frame `f` (of shape `[c, h, w]`) into `out` as CHW f32
/// in [0, 1].
pub(crate) fn push_crop(
    px: &[u8],
    f: usize,
    [c, h, w]: [usize; 3],
    crop: Crop,
    out: &mut Vec<f32>,
) {
    let Crop {
        top,
        left,
        h: crop_h,
        w: crop_w,
    } = crop;
    let base = f * h * w * c;
    for ch in 0..c {
        for y in top..top + crop_h {
            for x in left..left + crop_w {
                out.push(f32::from(px[base + (y * w + x) * c + ch]) / 255.0);
            }
        }
    }
}

/// [`sample_batch`], also returning the frame index of every observation step
/// (`b x n_obs_steps`, window-major).
fn draw_batch(
    policy: &DiffusionPolicy,
    data: &TrainData,
    win: &Windows,
    b: usize,
    rng: &mut ChaCha8Rng,
    mode: Images,
) -> Result<(ObsBatch, Vec<f32>, Vec<usize>), PolicyError> {
    if win.is_empty() {
        return Err(config_err(
            "dataset",
            0,
            "episodes long enough for one window",
        ));
    }
    let config = policy.config();
    let device = policy.device();
    let s_dim = config.vector_dim(FeatureType::State).unwrap_or(0);
    let e_dim = config.vector_dim(FeatureType::Env);
    let a_dim = config.action_dim()?;
    let image = config.image_shape().filter(|_| mode != Images::Skip);
    let t_o = config.n_obs_steps;
    let tp = config.horizon;
    let mut st = Vec::with_capacity(b * t_o * s_dim);
    let mut env = Vec::new();
    let mut act = Vec::with_capacity(b * tp * a_dim);
    let mut imgs: Vec<f32> = Vec::new();
    let mut frames = Vec::with_capacity(b * t_o);
    let crop = mode == Images::Crop;
    let (crop_h, crop_w) = match (image, config.crop_shape) {
        (Some(_), Some([h, w])) if crop => (h, w),
        (Some([_, h, w]), _) => (h, w),
        _ => (0, 0),
    };
    for _ in 0..b {
        let (start, len, off) = win.index[rng.random_range(0..win.index.len())];
        let frame = |k: isize| start + (off + k).clamp(0, len as isize - 1) as usize;
        for k in 0..t_o as isize {
            let f = frame(k);
            frames.push(f);
            st.extend_from_slice(&data.state[f * s_dim..(f + 1) * s_dim]);
            if let (Some(d), Some(e)) = (e_dim, &data.env_state) {
                env.extend_from_slice(&e[f * d..(f + 1) * d]);
            }
            if let Some(shape @ [_, h, w]) = image {
                // Each camera's frame of the step, each with its own crop.
                for px in camera_frames(data, policy.n_cameras())? {
                    let (top, left) =
                        crop_origin([h, w], [crop_h, crop_w], crop && config.crop_is_random, rng);
                    let window = Crop {
                        top,
                        left,
                        h: crop_h,
                        w: crop_w,
                    };
                    push_crop(px, f, shape, window, &mut imgs);
                }
            }
        }
        for k in 0..tp as isize {
            let f = frame(k);
            act.extend_from_slice(&data.action[f * a_dim..(f + 1) * a_dim]);
        }
    }
    // Normalise with the policy's own normalisers (the ones it will use at inference).
    let mut x0 = act;
    policy.action_normalizer().normalize(&mut x0);
    let obs = policy.normalized_obs_batch(st, (!env.is_empty()).then_some(env), b)?;
    let obs = ObsBatch {
        image: match image {
            Some([c, _, _]) => Some(Tensor::from_vec(
                imgs,
                (b * t_o * policy.n_cameras(), c, crop_h, crop_w),
                device,
            )?),
            None => None,
        },
        ..obs
    };
    Ok((obs, x0, frames))
}

/// The frames of each of the policy's `n` cameras in `data` (the scene camera's, then the
/// wrist camera's), or an error naming the one missing.
pub(crate) fn camera_frames(data: &TrainData, n: usize) -> Result<Vec<&[u8]>, PolicyError> {
    let scene = data
        .images
        .as_deref()
        .ok_or_else(|| config_err("dataset", "no images", "observation.image frames"))?;
    if n < 2 {
        return Ok(vec![scene]);
    }
    let wrist = data.wrist_images.as_deref().ok_or_else(|| {
        config_err(
            "dataset",
            "no wrist images",
            "observation.images.wrist frames (the policy reads the wrist camera)",
        )
    })?;
    if wrist.len() != scene.len() {
        return Err(config_err(
            "dataset",
            format!("{} wrist pixel values", wrist.len()),
            format!("{}, one wrist frame per scene frame", scene.len()),
        ));
    }
    Ok(vec![scene, wrist])
}

/// The evaluation-time image features (centre crop) of the frames `range` of `data`
/// (`range.len() x n_cameras feature_dim`, row-major, each frame's cameras in the policy's
/// order), computed in batches of 256 frames.
pub fn frame_features(
    policy: &DiffusionPolicy,
    data: &TrainData,
    range: std::ops::Range<usize>,
) -> Result<Vec<f32>, PolicyError> {
    let [c, h, w] = policy
        .config()
        .image_shape()
        .ok_or_else(|| config_err("input_features", "no observation.image", "an image policy"))?;
    let cameras = camera_frames(data, policy.n_cameras())?;
    let n = cameras[0].len() / (c * h * w);
    if range.end > n {
        return Err(config_err(
            "frames",
            range,
            format!("within the {n} frames"),
        ));
    }
    let mut out = Vec::new();
    let mut buf = Vec::new();
    for lo in range.clone().step_by(256) {
        let hi = (lo + 256).min(range.end);
        buf.clear();
        let full = Crop {
            top: 0,
            left: 0,
            h,
            w,
        };
        for f in lo..hi {
            for px in &cameras {
                push_crop(px, f, [c, h, w], full, &mut buf);
            }
        }
        let rows = (hi - lo) * cameras.len();
        let t = Tensor::from_slice(&buf, (rows, c, h, w), policy.device())?;
        let feats = policy.image_features(&t)?;
        out.extend(feats.flatten_all()?.to_vec1::<f32>()?);
    }
    Ok(out)
}

/// Train from scratch, or resume from `out` if it holds a training state. Checkpoints go to
/// `out/checkpoints/<step>/` and the final (EMA) policy to `out/`.
pub fn train(
    config: &DiffusionConfig,
    train: &TrainConfig,
    data: &TrainData,
    out: &Path,
    device: &Device,
    progress: Progress,
) -> Result<TrainReport, PolicyError> {
    validate(config, train)?;
    let widen = widening(config, train)?;
    let t0 = std::time::Instant::now();
    let varmap = VarMap::new();
    let vb = crate::init::seeded_var_builder(&varmap, train.seed, DType::F32, device);
    let policy = DiffusionPolicy::new(config.clone(), data.stats.clone(), vb)?;
    let (mut step, mut ema) = start_or_resume(&varmap, train, widen, out, device)?;
    // Every variable (EMA, checkpoints) and the optimised ones (all but a frozen encoder).
    let all_vars = sorted_vars(&varmap, |_| true)?;
    let vars: Vec<(String, Var)> = all_vars
        .iter()
        .filter(|(k, _)| !(train.freeze_encoder && k.starts_with(ENCODER_PREFIX)))
        .cloned()
        .collect();
    // With a frozen encoder, every frame's features once (the encoder's weights are final).
    let cached = if train.freeze_encoder {
        let frames = data.episode_lengths.iter().sum();
        Some(frame_features(&policy, data, 0..frames)?)
    } else {
        None
    };
    let win = windows(data, config, train.successful_only);
    if win.index.is_empty() {
        return Err(config_err(
            "dataset",
            data.episode_lengths.len(),
            "episodes long enough for one window",
        ));
    }
    let stepper = Stepper {
        policy: &policy,
        data,
        win: &win,
        cached: cached.as_deref(),
        vars: &vars,
        train,
    };
    let mut opt = adamw(config, &vars)?;
    if step > 0 {
        restore_optimizers(out, step, &mut [("main.", &mut opt)])?;
    }
    let (steps_at_start, mut trace) = (step, LossTrace::default());
    while step < train.steps {
        let (l, lr) = stepper.step(&mut opt, ema.as_mut(), step)?;
        trace.push(l);
        step += 1;
        progress(step, l, lr);
        if checkpoint_due(step, train.checkpoint_every, train.steps) {
            let saved = Saved {
                config,
                train,
                stats: &data.stats,
                all_vars: &all_vars,
                ema: ema.as_ref(),
            };
            save_optimizers(out, step, &[("main.", &opt)])?;
            saved.write(out, step)?;
        }
    }
    Ok(TrainReport {
        steps_run: step - steps_at_start,
        step,
        final_loss: trace.recent_mean(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Both configurations valid, and a frozen encoder only where the policy has one.
fn validate(config: &DiffusionConfig, train: &TrainConfig) -> Result<(), PolicyError> {
    config.validate()?;
    train.validate()?;
    if train.freeze_encoder && config.image_shape().is_none() {
        return Err(config_err(
            "freeze_encoder",
            true,
            "an image policy (a keypoint policy has no encoder)",
        ));
    }
    Ok(())
}

/// AdamW over `vars` with the config's learning rate, betas, epsilon and weight decay (the
/// learning rate is then set at every step by [`learning_rate`]).
fn adamw(config: &DiffusionConfig, vars: &[(String, Var)]) -> Result<AdamW, PolicyError> {
    let params = ParamsAdamW {
        lr: config.optimizer_lr,
        beta1: config.optimizer_betas[0],
        beta2: config.optimizer_betas[1],
        eps: config.optimizer_eps,
        weight_decay: config.optimizer_weight_decay,
    };
    AdamW::new(vars, params)
}

/// What one optimisation step reads and does not change.
struct Stepper<'a> {
    policy: &'a DiffusionPolicy,
    data: &'a TrainData,
    win: &'a Windows,
    /// Every frame's encoder features, when the encoder is frozen.
    cached: Option<&'a [f32]>,
    /// The optimised variables.
    vars: &'a [(String, Var)],
    train: &'a TrainConfig,
}

impl Stepper<'_> {
    /// Optimisation step `step` (0-based): a batch drawn from the step's own stream, the
    /// clipped gradient, AdamW at the scheduled learning rate, the EMA update. Returns the
    /// batch loss and the learning rate; a non-finite loss is an error.
    fn step(
        &self,
        opt: &mut AdamW,
        ema: Option<&mut HashMap<String, Tensor>>,
        step: usize,
    ) -> Result<(f32, f64), PolicyError> {
        let (config, train) = (self.policy.config(), self.train);
        let mut rng = step_rng(train.seed, step);
        let b = train.batch_size;
        let loss = batch_loss(self.policy, self.data, self.win, self.cached, b, &mut rng)?;
        let mut grads = loss.backward()?;
        clip_gradients(&mut grads, self.vars, train.grad_clip)?;
        let lr = learning_rate(
            config.optimizer_lr,
            config.scheduler_warmup_steps,
            train.steps,
            step,
        );
        opt.set_learning_rate(lr);
        opt.step(&grads)?;
        if let (Some(max), Some(e)) = (train.ema_max_decay, ema) {
            ema_update(e, self.vars, ema_decay(max, step))?;
        }
        let l = loss.to_scalar::<f32>()?;
        if !l.is_finite() {
            return Err(config_err(
                "loss",
                l,
                "finite (training diverged; lower optimizer_lr)",
            ));
        }
        Ok((l, lr))
    }
}

/// The denoising loss of one training batch of `b` windows drawn with `rng` (noise and
/// timesteps too); with `cached` frame features, the encoder is skipped.
fn batch_loss(
    policy: &DiffusionPolicy,
    data: &TrainData,
    win: &Windows,
    cached: Option<&[f32]>,
    b: usize,
    rng: &mut ChaCha8Rng,
) -> Result<Tensor, PolicyError> {
    let config = policy.config();
    let device = policy.device();
    let (tp, a_dim) = (config.horizon, config.action_dim()?);
    let mode = if cached.is_some() {
        Images::Skip
    } else {
        Images::Crop
    };
    let (obs, x0, frames) = draw_batch(policy, data, win, b, rng, mode)?;
    let eps: Vec<f32> = (0..b * tp * a_dim)
        .map(|_| StandardNormal.sample(&mut *rng))
        .collect();
    let ts: Vec<usize> = (0..b)
        .map(|_| rng.random_range(0..config.num_train_timesteps))
        .collect();
    let x0 = Tensor::from_vec(x0, (b, tp, a_dim), device)?;
    let eps = Tensor::from_vec(eps, (b, tp, a_dim), device)?;
    let cond = match cached {
        Some(feats) => {
            let d = policy.n_cameras() * 2 * config.spatial_softmax_num_keypoints;
            let rows: Vec<f32> = frames
                .iter()
                .flat_map(|&f| feats[f * d..(f + 1) * d].iter().copied())
                .collect();
            let rows = Tensor::from_vec(rows, (frames.len(), d), device)?;
            policy.global_cond_from_features(&obs, Some(&rows))?
        }
        None => policy.global_cond_cropped(&obs)?,
    };
    policy.loss(&cond, &x0, &eps, &ts, None)
}

/// Fresh weights (from `train.init` when given) at step 0, or the state of an interrupted
/// run in `out` (its raw weights); with the EMA weights when the run keeps an EMA (a copy of
/// the starting weights for a fresh run).
fn start_or_resume(
    varmap: &VarMap,
    train: &TrainConfig,
    widen: Option<HistoryWidening>,
    out: &Path,
    device: &Device,
) -> Result<(usize, Option<HashMap<String, Tensor>>), PolicyError> {
    let state_path = out.join("training_state.json");
    if !state_path.exists() {
        if let Some(init) = &train.init {
            load_init_widened(varmap, init, widen, device)?;
        }
        let ema = match train.ema_max_decay {
            Some(_) => Some(weight_copies(&sorted_vars(varmap, |_| true)?)?),
            None => None,
        };
        return Ok((0, ema));
    }
    let text = std::fs::read_to_string(&state_path).map_err(|source| PolicyError::Io {
        path: state_path.clone(),
        source,
    })?;
    let st: serde_json::Value =
        serde_json::from_str(&text).map_err(|source| PolicyError::Json {
            path: state_path.clone(),
            source,
        })?;
    let step = st["step"].as_u64().ok_or_else(|| PolicyError::Checkpoint {
        path: state_path.clone(),
        reason: "no integer `step`".into(),
    })? as usize;
    let raw = out.join("raw_model.safetensors");
    let tensors = candle_core::safetensors::load(&raw, device)?;
    checkpoint::set_variables(varmap, &raw, &tensors, |name| Some(name.to_string()))?;
    let ema = match train.ema_max_decay {
        Some(_) => Some(candle_core::safetensors::load(
            out.join(checkpoint::WEIGHTS),
            device,
        )?),
        None => None,
    };
    Ok((step, ema))
}

/// What a checkpoint of a training run holds.
struct Saved<'a> {
    config: &'a DiffusionConfig,
    train: &'a TrainConfig,
    stats: &'a StatsMap,
    all_vars: &'a [(String, Var)],
    ema: Option<&'a HashMap<String, Tensor>>,
}

impl Saved<'_> {
    /// Writes the policy (EMA weights when kept), the raw weights and the training state
    /// into `out`, and before the last step also into `out/checkpoints/<step>`.
    fn write(&self, out: &Path, step: usize) -> Result<(), PolicyError> {
        let raw: HashMap<String, Tensor> = self
            .all_vars
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect();
        let weights = self.ema.cloned().unwrap_or_else(|| raw.clone());
        let mut dirs = vec![out.to_path_buf()];
        if step != self.train.steps {
            dirs.push(out.join("checkpoints").join(format!("{step:06}")));
        }
        for d in dirs {
            checkpoint::save(&d, self.config, &weights, self.stats)?;
            candle_core::safetensors::save(&raw, d.join("raw_model.safetensors"))?;
            let st = serde_json::json!({
                "step": step,
                "train": self.train,
                "ema": self.train.ema_max_decay.is_some(),
                "note": "model.safetensors holds the EMA weights (the policy); raw_model.safetensors the optimised ones. AdamW's moments are in optimizer_state.safetensors (the run directory only).",
            });
            let p = d.join("training_state.json");
            std::fs::write(&p, serde_json::to_string_pretty(&st).unwrap_or_default()).map_err(
                |source| PolicyError::Io {
                    path: p.clone(),
                    source,
                },
            )?;
        }
        Ok(())
    }
}

/// The key prefix of the image encoder's variables.
pub const ENCODER_PREFIX: &str = "diffusion.rgb_encoder.";

/// The variables of `varmap` whose names pass `keep`, sorted by name (a stable order for the
/// optimiser and for checkpoints).
pub(crate) fn sorted_vars(
    varmap: &VarMap,
    keep: impl Fn(&str) -> bool,
) -> Result<Vec<(String, Var)>, PolicyError> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| config_err("varmap", "poisoned", "unlocked"))?;
    let mut v: Vec<(String, Var)> = data
        .iter()
        .filter(|(k, _)| keep(k))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(v)
}

/// Set the variables of `varmap` named in the safetensors file `path` to its tensors; a key
/// the model lacks or a shape that differs is an error naming it.
pub fn load_init(varmap: &VarMap, path: &Path, device: &Device) -> Result<usize, PolicyError> {
    load_init_widened(varmap, path, None, device)
}

/// An init trained on `from` observations loaded into a U-Net conditioned on `to` of them
/// ([`TrainConfig::init_n_obs_steps`]). The conditioning is `[step embedding (step_embed),
/// observation 1, ..., observation to]`, oldest first, `per_step` values each.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HistoryWidening {
    /// `diffusion_step_embed_dim`.
    pub step_embed: usize,
    /// The init's `n_obs_steps`.
    pub from: usize,
    /// The policy's `n_obs_steps`.
    pub to: usize,
}

impl HistoryWidening {
    /// The conditioning layer weight `(out, step_embed + from * per_step)` of the init as
    /// `(out, step_embed + to * per_step)`: zero columns for the `to - from` oldest
    /// observations, the init's columns for the newest `from`.
    pub fn widen(&self, w: &Tensor) -> Result<Tensor, PolicyError> {
        let (out, cols) = w.dims2()?;
        let fits = |c: &usize| self.from > 0 && self.to >= self.from && c.is_multiple_of(self.from);
        let Some(obs_cols) = cols.checked_sub(self.step_embed).filter(fits) else {
            return Err(config_err(
                "init_n_obs_steps",
                format!("{} for a conditioning weight of {cols} columns", self.from),
                "the n_obs_steps the init was trained with (step embedding + n_obs_steps x \
                 per-step features columns), at most the policy's",
            ));
        };
        let extra = (self.to - self.from) * (obs_cols / self.from);
        let zeros = Tensor::zeros((out, extra), w.dtype(), w.device())?;
        let parts = [
            &w.narrow(1, 0, self.step_embed)?,
            &zeros,
            &w.narrow(1, self.step_embed, obs_cols)?,
        ];
        Ok(Tensor::cat(&parts, 1)?)
    }
}

/// The widening `train` asks for, checked against `config`.
fn widening(
    config: &DiffusionConfig,
    train: &TrainConfig,
) -> Result<Option<HistoryWidening>, PolicyError> {
    let Some(from) = train.init_n_obs_steps else {
        return Ok(None);
    };
    if train.init.is_none() {
        return Err(config_err(
            "init_n_obs_steps",
            from,
            "only with an init file",
        ));
    }
    if config.transformer.is_some() {
        return Err(config_err(
            "init_n_obs_steps",
            from,
            "a U-Net policy (the transformer's condition tokens are not widened)",
        ));
    }
    if from == 0 || from > config.n_obs_steps {
        return Err(config_err(
            "init_n_obs_steps",
            from,
            format!("1..={} (the policy's n_obs_steps)", config.n_obs_steps),
        ));
    }
    Ok(Some(HistoryWidening {
        step_embed: config.diffusion_step_embed_dim,
        from,
        to: config.n_obs_steps,
    }))
}

/// [`load_init`], the U-Net's conditioning layers (`…cond_encoder.1.weight`) widened by
/// `widen` when given.
pub fn load_init_widened(
    varmap: &VarMap,
    path: &Path,
    widen: Option<HistoryWidening>,
    device: &Device,
) -> Result<usize, PolicyError> {
    let mut tensors = candle_core::safetensors::load(path, device)?;
    if let Some(w) = widen {
        for (name, t) in tensors.iter_mut() {
            if name.ends_with("cond_encoder.1.weight") {
                *t = w.widen(t)?;
            }
        }
    }
    let vars = varmap
        .data()
        .lock()
        .map_err(|_| config_err("varmap", "poisoned", "unlocked"))?;
    let mut names: Vec<&String> = tensors.keys().collect();
    names.sort();
    for name in names {
        let t = &tensors[name];
        let var = vars.get(name).ok_or_else(|| PolicyError::Checkpoint {
            path: path.to_path_buf(),
            reason: format!("`{name}` is not a variable of this policy"),
        })?;
        if var.shape() != t.shape() {
            return Err(PolicyError::Checkpoint {
                path: path.to_path_buf(),
                reason: format!(
                    "`{name}` has shape {:?}, the policy expects {:?}",
                    t.dims(),
                    var.dims()
                ),
            });
        }
        var.set(&t.to_dtype(var.dtype())?)?;
    }
    Ok(tensors.len())
}

/// Statistics as the policy wants them, from per-feature (min, max, mean, std) vectors.
pub fn stats_from(
    features: impl IntoIterator<Item = (String, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>)>,
) -> StatsMap {
    let f = |v: Vec<f64>| v.into_iter().map(|x| x as f32).collect();
    features
        .into_iter()
        .map(|(name, min, max, mean, std)| {
            (
                name,
                Stats {
                    min: f(min),
                    max: f(max),
                    mean: f(mean),
                    std: f(std),
                },
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ObsKind;

    #[test]
    fn successful_only_keeps_the_windows_of_successful_episodes() {
        let c = DiffusionConfig::cpu(ObsKind::Keypoints);
        let lengths = vec![20, 30, 25];
        let frames: usize = lengths.iter().sum();
        let data = TrainData {
            state: vec![0.0; frames * 2],
            env_state: Some(vec![0.0; frames * 16]),
            images: None,
            wrist_images: None,
            action: vec![0.0; frames * 2],
            episode_lengths: lengths.clone(),
            episode_success: vec![true, false, true],
            stats: StatsMap::new(),
        };
        // LeRobot's padding: T_o - 1 windows before each start, n_action_steps - 1 after.
        let per = |len: usize| len + c.n_obs_steps - 1 + c.n_action_steps - 1 - c.horizon + 1;
        let all = Windows::new(&data, &c, false);
        assert_eq!(all.len(), lengths.iter().map(|&l| per(l)).sum::<usize>());
        let kept = Windows::new(&data, &c, true);
        assert_eq!(kept.len(), per(20) + per(25));
        assert!(
            kept.index.iter().all(|&(start, _, _)| start != 20),
            "episode 1 dropped"
        );
    }
}
