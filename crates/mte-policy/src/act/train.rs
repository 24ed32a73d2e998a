//! Training ACT on an `mte-demo-v1` dataset: AdamW at the config's learning rate and weight
//! decay, gradient norm clipped at 10 (LeRobot's default), batches of single frames with the
//! next `chunk_size` actions (actions past an episode's end repeat its last action and are
//! marked as padding, so the L1 term ignores them and the CVAE encoder masks them), the
//! CVAE's noise and dropout masks drawn from a stream keyed by `(seed, step)`. A run
//! checkpoints every `checkpoint_every` steps and resumes from its output directory exactly:
//! the weights, the average and AdamW's moments (`optimizer_state.safetensors`) are restored
//! and every draw is keyed by the step, so a resumed run matches an uninterrupted one bit for
//! bit on the same machine (runs saved before the moments were kept resume with fresh ones).
//!
//! Two parts of Diffusion Policy's recipe are options (LeRobot's ACT uses neither): a
//! warm-up + cosine learning rate ([`LrSchedule::Cosine`]) and an exponential moving average
//! of the weights (`ema_max_decay`). With the average, `model.safetensors` holds it (what an
//! evaluation loads) and `raw_model.safetensors` the optimised weights (what a resume loads).

use std::cell::RefCell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use super::config::ActConfig;
use super::model::{Dropout, VaeInput};
use super::policy::{ActPolicy, ObsTensors};
use crate::error::{PolicyError, config_err};
use crate::train::{TrainData, sorted_vars};
use crate::training::{
    AdamW, LossTrace, ParamsAdamW, checkpoint_due, clip_gradients, ema_decay, ema_update,
    learning_rate, restore_optimizers, save_optimizers, step_rng, weight_copies,
};

/// ACT training settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActTrainConfig {
    /// Optimiser steps in total (a resumed run continues to this count).
    pub steps: usize,
    /// Frames per batch.
    pub batch_size: usize,
    /// Seed of batches, CVAE noise and dropout.
    pub seed: u64,
    /// Checkpoint period (steps).
    pub checkpoint_every: usize,
    /// An ACT checkpoint's `model.safetensors` (same configuration) whose weights replace
    /// the seeded initialisation: training goes on from a bundled policy whose run directory
    /// is gone. Every variable must be in it (`model.<name>`, same shape). AdamW's moments
    /// start afresh. Ignored when resuming.
    #[serde(default)]
    pub init: Option<PathBuf>,
    /// A Diffusion Policy image checkpoint's `model.safetensors` whose encoder backbone
    /// (same width) becomes this policy's camera backbone before training, its frozen
    /// norms calibrated on training frames ([`super::warm_start`]). Ignored when resuming
    /// (the run's checkpoint holds the converted backbone) and after `init`.
    #[serde(default)]
    pub backbone_from: Option<PathBuf>,
    /// Keep the camera backbone fixed and compute each frame's feature map once, before
    /// the first step: a step then costs about what a keypoint policy's does. Exact, since
    /// ACT trains without image augmentation; the cache takes `C h w` floats per frame.
    #[serde(default)]
    pub freeze_backbone: bool,
    /// The learning rates over the run (both parameter groups scale alike).
    #[serde(default)]
    pub lr_schedule: LrSchedule,
    /// Keep an exponential moving average of the weights with this decay ceiling (the decay
    /// ramps as `min(max, (1 + step) / (10 + step))`, as Diffusion Policy's); `None`: none
    /// (LeRobot's ACT).
    #[serde(default)]
    pub ema_max_decay: Option<f64>,
}

/// ACT's learning rate over a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LrSchedule {
    /// The config's learning rates at every step (LeRobot's ACT).
    #[default]
    Constant,
    /// Linear warm-up over `warmup_steps`, then cosine decay to 0 at the run's last step
    /// (Diffusion Policy's schedule).
    Cosine {
        /// Steps of the linear warm-up.
        warmup_steps: usize,
    },
}

impl LrSchedule {
    /// The factor on the config's learning rates at step `step` (0-based) of `total`.
    pub fn factor(self, step: usize, total: usize) -> f64 {
        match self {
            Self::Constant => 1.0,
            Self::Cosine { warmup_steps } => learning_rate(1.0, warmup_steps, total, step),
        }
    }
}

/// `mte train act`'s defaults: 20,000 steps of 64 frames, seed 0, a checkpoint every 2,000
/// steps, from the seeded initialisation with a trained backbone. (LeRobot's ACT recipe is
/// 100,000 steps at batch 8; mte's `cpu` presets train on fewer, larger batches.)
impl Default for ActTrainConfig {
    fn default() -> Self {
        Self {
            steps: 20_000,
            batch_size: 64,
            seed: 0,
            checkpoint_every: 2_000,
            init: None,
            backbone_from: None,
            freeze_backbone: false,
            lr_schedule: LrSchedule::Constant,
            ema_max_decay: None,
        }
    }
}

impl ActTrainConfig {
    /// Check every field.
    pub fn validate(&self) -> Result<(), PolicyError> {
        for (name, v) in [("steps", self.steps), ("batch_size", self.batch_size)] {
            if v == 0 {
                return Err(config_err(name, v, ">= 1"));
            }
        }
        if let LrSchedule::Cosine { warmup_steps } = self.lr_schedule
            && warmup_steps >= self.steps
        {
            let expected = format!("fewer than the run's {} steps", self.steps);
            return Err(config_err("warmup_steps", warmup_steps, expected));
        }
        if let Some(d) = self.ema_max_decay
            && !(0.0..1.0).contains(&d)
        {
            return Err(config_err("ema_max_decay", d, "in [0, 1)"));
        }
        Ok(())
    }
}

/// What a run did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ActTrainReport {
    /// Steps run by this call.
    pub steps_run: usize,
    /// The step reached.
    pub step: usize,
    /// Mean L1 term over the last 100 steps run by this call (`None` when it ran none: the
    /// run was already at its last step).
    pub final_l1: Option<f32>,
    /// Mean KL term over the same steps.
    pub final_kld: Option<f32>,
    /// Wall time of this call (s).
    pub seconds: f64,
    /// With `backbone_from` on a fresh run: the converted backbone's relative error against
    /// the Diffusion Policy encoder's on held-out training frames.
    pub backbone_relative_error: Option<f64>,
}

const STATE_FILE: &str = "training_state.json";

#[derive(Serialize, Deserialize)]
struct TrainingState {
    step: usize,
    train: ActTrainConfig,
}

/// One batch: inputs, targets and padding.
struct Batch {
    obs: ObsTensors,
    /// The frames' cached feature maps (frozen backbone).
    features: Option<Tensor>,
    actions: Tensor,
    is_pad: Tensor,
    eps: Tensor,
}

/// Frames `idx` of `data` as the policy's observation tensors, their frames left out
/// unless `images`.
fn observations(
    policy: &ActPolicy,
    data: &TrainData,
    idx: &[usize],
    images: bool,
) -> Result<ObsTensors, PolicyError> {
    let frames = (data.action.len() / policy.config().action_dim()?).max(1);
    let sd = data.state.len() / frames;
    let ed = data.env_state.as_ref().map(|e| e.len() / frames);
    let px = data.images.as_ref().map(|i| i.len() / frames);
    // The wrist camera's frames, checked against the scene camera's as for a Diffusion Policy.
    let wrist = if images && policy.n_cameras() > 1 {
        crate::train::camera_frames(data, policy.n_cameras())?
            .get(1)
            .copied()
    } else {
        None
    };
    let obs: Vec<crate::policy::Observation> = idx
        .iter()
        .map(|&f| crate::policy::Observation {
            state: data.state[f * sd..(f + 1) * sd].to_vec(),
            env_state: data
                .env_state
                .as_ref()
                .zip(ed)
                .map(|(e, d)| e[f * d..(f + 1) * d].to_vec()),
            image: (data.images.as_ref().zip(px))
                .filter(|_| images)
                .map(|(i, n)| i[f * n..(f + 1) * n].to_vec()),
            wrist_image: wrist
                .zip(px)
                .and_then(|(i, n)| i.get(f * n..(f + 1) * n))
                .map(<[u8]>::to_vec),
        })
        .collect();
    let refs: Vec<&crate::policy::Observation> = obs.iter().collect();
    if images {
        policy.obs_tensors(&refs)
    } else {
        policy.obs_tensors_without_image(&refs)
    }
}

/// A frozen backbone's feature maps of every frame, `N C h w` floats each (its `N`
/// cameras' maps together).
struct FeatureCache {
    values: Vec<f32>,
    /// `(C, h, w)`.
    shape: (usize, usize, usize),
    /// Cameras per frame.
    cameras: usize,
}

impl FeatureCache {
    /// Every frame of `data` through `policy`'s backbone, in chunks of 128 frames.
    fn build(policy: &ActPolicy, data: &TrainData, frames: usize) -> Result<Self, PolicyError> {
        let mut values = Vec::new();
        let mut shape = (0, 0, 0);
        for lo in (0..frames).step_by(128) {
            let idx: Vec<usize> = (lo..(lo + 128).min(frames)).collect();
            let obs = observations(policy, data, &idx, true)?;
            let f = policy
                .backbone_features(&obs)?
                .ok_or_else(|| config_err("freeze_backbone", true, "a policy with a camera"))?;
            let (_, c, h, w) = f.dims4()?;
            shape = (c, h, w);
            values.extend(f.flatten_all()?.to_vec1::<f32>()?);
        }
        let cameras = policy.n_cameras();
        Ok(Self {
            values,
            shape,
            cameras,
        })
    }

    /// The feature maps of frames `idx`, `(B N, C, h, w)` (rows `(b n)`).
    fn gather(&self, idx: &[usize]) -> Result<Tensor, PolicyError> {
        let (c, h, w) = self.shape;
        let n = self.cameras * c * h * w;
        let mut out = Vec::with_capacity(idx.len() * n);
        for &f in idx {
            out.extend_from_slice(&self.values[f * n..(f + 1) * n]);
        }
        let rows = idx.len() * self.cameras;
        Ok(Tensor::from_vec(out, (rows, c, h, w), &Device::Cpu)?)
    }
}

/// Each sample frame's `k` observed frames, oldest first; steps before its episode's first
/// frame repeat that frame (Diffusion Policy's padding of the observation history).
fn history_frames(starts: &[usize], idx: &[usize], k: usize) -> Vec<usize> {
    idx.iter()
        .flat_map(|&f| {
            let first = starts[starts.partition_point(|&st| st <= f) - 1];
            (0..k).map(move |j| (f + j + 1).saturating_sub(k).max(first))
        })
        .collect()
}

/// Frames `idx` of `data` as a normalised batch: each sample's `n_obs_steps` observed frames
/// ending at its frame, and as targets the `chunk_size` actions from the oldest of them on
/// (steps outside the episode repeat its first or last action and are marked padding); with
/// a `cache`, the frames' feature maps from it instead of the frames.
fn batch(
    policy: &ActPolicy,
    data: &TrainData,
    starts: &[usize],
    idx: &[usize],
    cache: Option<&FeatureCache>,
    rng: &mut ChaCha8Rng,
) -> Result<Batch, PolicyError> {
    let c = policy.config();
    let (s, a, k) = (c.chunk_size, c.action_dim()?, c.n_obs_steps);
    let observed = history_frames(starts, idx, k);
    let obs = observations(policy, data, &observed, cache.is_none())?;
    let mut actions = Vec::with_capacity(idx.len() * s * a);
    let mut pad = Vec::with_capacity(idx.len() * s);
    for &f in idx {
        let ep = starts.partition_point(|&st| st <= f) - 1;
        let (first, end) = (starts[ep], starts[ep + 1]);
        for r in 0..s {
            // Frame f - (k - 1) + r, kept inside the episode.
            let t = (f + r + 1).checked_sub(k).filter(|&t| t >= first);
            let g = t.unwrap_or(first).min(end - 1);
            let mut row = data.action[g * a..(g + 1) * a].to_vec();
            policy.normalize_action(&mut row);
            actions.extend(row);
            let inside = t.is_some_and(|t| t < end);
            pad.push(if inside { 0f32 } else { 1.0 });
        }
    }
    let b = idx.len();
    let eps: Vec<f32> = (0..b * c.latent_dim)
        .map(|_| StandardNormal.sample(rng))
        .collect();
    let dev = Device::Cpu;
    Ok(Batch {
        obs,
        features: cache.map(|c| c.gather(idx)).transpose()?,
        actions: Tensor::from_vec(actions, (b, s, a), &dev)?,
        is_pad: Tensor::from_vec(pad, (b, s), &dev)?,
        eps: Tensor::from_vec(eps, (b, c.latent_dim), &dev)?,
    })
}

/// Trains (or resumes) an ACT policy of `config` on `data` into `out`; `progress(step, l1,
/// kld)` after every step.
pub fn train(
    data: &TrainData,
    config: ActConfig,
    train: &ActTrainConfig,
    out: &Path,
    progress: &mut dyn FnMut(usize, f32, f32),
) -> Result<ActTrainReport, PolicyError> {
    train.validate()?;
    config.validate()?;
    let t0 = std::time::Instant::now();
    let varmap = VarMap::new();
    let vb = crate::init::seeded_var_builder(&varmap, train.seed, DType::F32, &Device::Cpu);
    let policy = ActPolicy::new(config.clone(), data.stats.clone(), vb.clone())?;
    let starts = episode_starts(&data.episode_lengths);
    let frames = starts[starts.len() - 1];
    if frames == 0 {
        return Err(config_err("dataset", 0, "at least one frame"));
    }
    let (mut step, resumed_ema) = resume(&varmap, out, train.ema_max_decay.is_some())?;
    let mut backbone_relative_error = None;
    if step == 0 {
        if let Some(init) = &train.init {
            load_weights(&varmap, init)?;
        } else if let Some(dp) = &train.backbone_from {
            let e = warm_start_backbone(&policy, &varmap, data, dp, train.seed, frames)?;
            backbone_relative_error = Some(e);
        }
    }
    // A frozen norm reads its statistics when it is built: rebuild on the loaded variables
    // (the same variables; only the norms' derived scale and shift are new).
    let policy = ActPolicy::new(config, data.stats.clone(), vb)?;
    let (vars, mut backbone) = trainable(&varmap)?;
    let cache = if train.freeze_backbone {
        backbone.clear();
        Some(FeatureCache::build(&policy, data, frames)?)
    } else {
        None
    };
    // The average starts at the weights training starts from (or the resumed average).
    let mut ema = match (train.ema_max_decay, resumed_ema) {
        (Some(_), Some(e)) => Some(e),
        (Some(_), None) => Some(weight_copies(&sorted_vars(&varmap, |_| true)?)?),
        (None, _) => None,
    };
    let mut opt = Optimisers::new(policy.config(), vars, backbone)?;
    if step > 0 {
        opt.restore(out, step)?;
    }
    let stepper = Stepper {
        policy: &policy,
        data,
        starts: &starts,
        cache: cache.as_ref(),
        train,
    };
    let (start_step, mut l1s, mut klds) = (step, LossTrace::default(), LossTrace::default());
    while step < train.steps {
        if train.lr_schedule != LrSchedule::Constant {
            opt.scale_learning_rates(train.lr_schedule.factor(step, train.steps));
        }
        let (l1, kld) = stepper.step(&mut opt, step)?;
        if let (Some(max), Some(e)) = (train.ema_max_decay, ema.as_mut()) {
            ema_update(e, &opt.all, ema_decay(max, step))?;
        }
        step += 1;
        l1s.push(l1);
        klds.push(kld);
        progress(step, l1, kld);
        if checkpoint_due(step, train.checkpoint_every, train.steps) {
            opt.save(out, step)?;
            save(&policy, &varmap, ema.as_ref(), out, step, train)?;
        }
    }
    Ok(ActTrainReport {
        steps_run: step - start_step,
        step,
        final_l1: l1s.recent_mean(),
        final_kld: klds.recent_mean(),
        seconds: t0.elapsed().as_secs_f64(),
        backbone_relative_error,
    })
}

/// The first frame of each episode, then the total frame count.
fn episode_starts(lengths: &[usize]) -> Vec<usize> {
    let mut starts = vec![0usize];
    for l in lengths {
        starts.push(starts[starts.len() - 1] + l);
    }
    starts
}

/// ACT's two AdamW optimisers (LeRobot's parameter groups): the backbone at its own learning
/// rate, everything else at the main one, both with the config's weight decay.
struct Optimisers {
    main: AdamW,
    backbone: AdamW,
    /// The config's learning rates (main, backbone).
    lrs: (f64, f64),
    /// Every optimised variable by name, for the global gradient clip and the average.
    all: Vec<(String, Var)>,
}

impl Optimisers {
    fn new(
        config: &ActConfig,
        vars: Vec<(String, Var)>,
        backbone: Vec<(String, Var)>,
    ) -> Result<Self, PolicyError> {
        let adamw = |vars: &[(String, Var)], lr: f64| {
            let params = ParamsAdamW {
                lr,
                weight_decay: config.optimizer_weight_decay,
                ..ParamsAdamW::default()
            };
            AdamW::new(vars, params)
        };
        let all: Vec<(String, Var)> = vars.iter().chain(&backbone).cloned().collect();
        let lrs = (config.optimizer_lr, config.optimizer_lr_backbone);
        Ok(Self {
            main: adamw(&vars, lrs.0)?,
            backbone: adamw(&backbone, lrs.1)?,
            lrs,
            all,
        })
    }

    /// Writes both groups' moments beside the weights of step `step` ([`save_optimizers`]).
    fn save(&self, out: &Path, step: usize) -> Result<(), PolicyError> {
        save_optimizers(
            out,
            step,
            &[("main.", &self.main), ("backbone.", &self.backbone)],
        )
    }

    /// Restores both groups' moments saved at step `step`, if the run saved them.
    fn restore(&mut self, out: &Path, step: usize) -> Result<(), PolicyError> {
        let groups = &mut [("main.", &mut self.main), ("backbone.", &mut self.backbone)];
        restore_optimizers(out, step, groups)
    }

    /// Sets both groups' learning rates to `factor` times the config's.
    fn scale_learning_rates(&mut self, factor: f64) {
        self.main.set_learning_rate(self.lrs.0 * factor);
        self.backbone.set_learning_rate(self.lrs.1 * factor);
    }

    /// Clips the gradient's global norm at 10 (LeRobot's default) and steps both groups.
    fn step(&mut self, grads: &mut GradStore) -> Result<(), PolicyError> {
        clip_gradients(grads, &self.all, 10.0)?;
        self.main.step(grads)?;
        self.backbone.step(grads)?;
        Ok(())
    }
}

/// What one optimisation step reads and does not change.
struct Stepper<'a> {
    policy: &'a ActPolicy,
    data: &'a TrainData,
    /// [`episode_starts`] of the data.
    starts: &'a [usize],
    /// Every frame's backbone features, when the backbone is frozen.
    cache: Option<&'a FeatureCache>,
    train: &'a ActTrainConfig,
}

impl Stepper<'_> {
    /// Optimisation step `step` (0-based): frames, CVAE noise and dropout masks drawn from
    /// the step's own stream, the L1 + KL loss, the optimisers' step. Returns the L1 and KL
    /// terms; a non-finite loss is an error.
    fn step(&self, opt: &mut Optimisers, step: usize) -> Result<(f32, f32), PolicyError> {
        let (policy, config) = (self.policy, self.policy.config());
        let mut rng = step_rng(self.train.seed, step);
        let frames = self.starts[self.starts.len() - 1];
        let idx: Vec<usize> = (0..self.train.batch_size)
            .map(|_| rng.random_range(0..frames))
            .collect();
        let b = batch(policy, self.data, self.starts, &idx, self.cache, &mut rng)?;
        let drop_rng = RefCell::new(ChaCha8Rng::seed_from_u64(rng.random()));
        let dropout = Dropout::new(config.dropout, &drop_rng);
        let vae = VaeInput {
            actions: &b.actions,
            is_pad: &b.is_pad,
            eps: &b.eps,
        };
        let mut images = Vec::new();
        let mut inputs = policy.inputs_of(&b.obs, &mut images)?;
        let features = match &b.features {
            Some(f) => policy.split_cameras(f)?,
            None => Vec::new(),
        };
        inputs.features = &features;
        let o = policy.net().forward(&inputs, Some(&vae), Some(&dropout))?;
        let (loss, l1, kld) = policy.net().loss(&o, &b.actions, &b.is_pad)?;
        if !l1.is_finite() || !kld.is_finite() {
            return Err(config_err(
                "loss",
                l1 + kld,
                "finite (training diverged; lower optimizer_lr)",
            ));
        }
        opt.step(&mut loss.backward()?)?;
        Ok((l1, kld))
    }
}

/// Replaces the backbone variables in `varmap` with the Diffusion Policy encoder at `path`,
/// calibrated on 256 training frames and checked on 64 others drawn from `seed`; returns
/// the relative error ([`super::warm_start::BackboneWarmStart::relative_error`]).
fn warm_start_backbone(
    policy: &ActPolicy,
    varmap: &VarMap,
    data: &TrainData,
    path: &Path,
    seed: u64,
    frames: usize,
) -> Result<f64, PolicyError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5741_524D_5354_4152);
    let mut images = |n: usize| -> Result<Tensor, PolicyError> {
        let idx: Vec<usize> = (0..n).map(|_| rng.random_range(0..frames)).collect();
        policy
            .normalized_image(&observations(policy, data, &idx, true)?)?
            .ok_or_else(|| config_err("backbone_from", path.display(), "a policy with a camera"))
    };
    let (calibration, held_out) = (images(256)?, images(64)?);
    let width = policy.config().vision_backbone_width;
    let ws = super::warm_start::backbone_from_diffusion(path, width, &calibration, &held_out)?;
    let set = crate::checkpoint::set_variables(varmap, path, &ws.tensors, |name| {
        name.strip_prefix("backbone.").map(str::to_string)
    })?;
    if set != ws.tensors.len() {
        return Err(config_err(
            "backbone_from",
            set,
            format!("{} tensors", ws.tensors.len()),
        ));
    }
    Ok(ws.relative_error)
}

/// The variables an optimiser moves by name, split into (the rest, the backbone's): LeRobot's
/// two parameter groups. The backbone's frozen BatchNorm tensors are buffers and in neither.
#[allow(clippy::type_complexity)]
fn trainable(varmap: &VarMap) -> Result<(Vec<(String, Var)>, Vec<(String, Var)>), PolicyError> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| config_err("variables", "poisoned", "a usable variable map"))?;
    let (mut rest, mut backbone) = (Vec::new(), Vec::new());
    for (name, var) in data.iter() {
        let named = (name.clone(), var.clone());
        match name.strip_prefix("backbone.") {
            None => rest.push(named),
            Some(n) if !is_frozen_norm(n) => backbone.push(named),
            Some(_) => {}
        }
    }
    Ok((rest, backbone))
}

/// Whether a backbone tensor (name below `backbone.`) belongs to a FrozenBatchNorm2d: the
/// stem's `bn1`, the blocks' `bn1` and `bn2`, the shortcuts' `downsample.1`.
fn is_frozen_norm(name: &str) -> bool {
    let parts: Vec<&str> = name.split('.').collect();
    match parts.as_slice() {
        [.., "downsample", "1", _] => true,
        [.., norm, _] => norm.starts_with("bn"),
        _ => false,
    }
}

/// The optimised weights beside the average, when a run keeps one.
const RAW_WEIGHTS: &str = "raw_model.safetensors";

/// Writes the policy into `out` (the average's weights when `ema` is kept, with the optimised
/// ones in [`RAW_WEIGHTS`]) and the training state.
fn save(
    policy: &ActPolicy,
    varmap: &VarMap,
    ema: Option<&HashMap<String, Tensor>>,
    out: &Path,
    step: usize,
    train: &ActTrainConfig,
) -> Result<(), PolicyError> {
    match ema {
        Some(e) => {
            policy.save_tensors(out, e)?;
            let raw = sorted_vars(varmap, |_| true)?
                .into_iter()
                .map(|(k, v)| (k, v.as_tensor().clone()))
                .collect();
            policy.write_weights(&out.join(RAW_WEIGHTS), &raw)?;
        }
        None => {
            policy.save(out, varmap)?;
            // A run resumed without the average it kept: the policy file now holds the raw
            // weights, and a stale copy beside it would be what the next resume loads.
            let raw = out.join(RAW_WEIGHTS);
            if raw.exists() {
                std::fs::remove_file(&raw)
                    .map_err(|source| PolicyError::Io { path: raw, source })?;
            }
        }
    }
    let state = TrainingState {
        step,
        train: train.clone(),
    };
    let path = out.join(STATE_FILE);
    let text = serde_json::to_string_pretty(&state).map_err(|source| PolicyError::Json {
        path: path.clone(),
        source,
    })?;
    std::fs::write(&path, text).map_err(|source| PolicyError::Io { path, source })
}

/// Loads the optimised weights of a previous run in `out` into `varmap` (its
/// [`RAW_WEIGHTS`] when it kept an average); the step it reached (0 when there is none) and,
/// when `with_ema` and the run kept an average, that average. A run that kept none starts
/// one at its resumed weights.
#[allow(clippy::type_complexity)]
fn resume(
    varmap: &VarMap,
    out: &Path,
    with_ema: bool,
) -> Result<(usize, Option<HashMap<String, Tensor>>), PolicyError> {
    let path = out.join(STATE_FILE);
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok((0, None));
    };
    let state: TrainingState =
        serde_json::from_str(&text).map_err(|source| PolicyError::Json { path, source })?;
    let (weights, raw) = (out.join(crate::checkpoint::WEIGHTS), out.join(RAW_WEIGHTS));
    if !raw.exists() {
        load_weights(varmap, &weights)?;
        return Ok((state.step, None));
    }
    load_weights(varmap, &raw)?;
    if !with_ema {
        return Ok((state.step, None));
    }
    let mut saved = candle_core::safetensors::load(&weights, &Device::Cpu)?;
    let ema = sorted_vars(varmap, |_| true)?
        .into_iter()
        .map(|(k, _)| {
            let t = saved.remove(&format!("model.{k}")).ok_or_else(|| {
                crate::checkpoint::ck(&weights, format!("no `model.{k}` in the average"))
            })?;
            Ok((k, t))
        })
        .collect::<Result<HashMap<_, _>, PolicyError>>()?;
    Ok((state.step, Some(ema)))
}

/// Sets every variable of `varmap` from `model.<name>` in the checkpoint weights at `path`;
/// a missing key or a different shape is an error naming it. Other keys (buffers such as
/// `model.vae_encoder_pos_enc`) are ignored. Returns how many variables were set.
pub fn load_weights(varmap: &VarMap, path: &Path) -> Result<usize, PolicyError> {
    let weights = candle_core::safetensors::load(path, &Device::Cpu)?;
    crate::checkpoint::set_variables(varmap, path, &weights, |name| Some(format!("model.{name}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 2-token-wide ACT on 12 frames whose actions follow the state.
    fn tiny() -> (ActPolicy, VarMap, TrainData) {
        tiny_kl(ActConfig::cpu().kl_weight)
    }

    /// [`tiny`] with the KL term at `kl_weight`.
    fn tiny_kl(kl_weight: f64) -> (ActPolicy, VarMap, TrainData) {
        let c = ActConfig {
            kl_weight,
            ..ActConfig::tiny()
        };
        let n = 12usize;
        let (mut state, mut env, mut action) = (Vec::new(), Vec::new(), Vec::new());
        for f in 0..n {
            let x = f as f32 * 30.0;
            state.extend([x, 400.0 - x]);
            env.extend((0..16).map(|k| x + k as f32));
            action.extend([x + 5.0, 390.0 - x]);
        }
        let stat = |d: usize| crate::normalize::Stats {
            min: vec![0.0; d],
            max: vec![512.0; d],
            mean: vec![200.0; d],
            std: vec![100.0; d],
        };
        let data = TrainData {
            state,
            env_state: Some(env),
            images: None,
            wrist_images: None,
            action,
            episode_lengths: vec![n],
            episode_success: vec![true],
            stats: [
                ("observation.state".to_string(), stat(2)),
                ("observation.environment_state".to_string(), stat(16)),
                ("action".to_string(), stat(2)),
            ]
            .into_iter()
            .collect(),
        };
        let varmap = VarMap::new();
        let vb = crate::init::seeded_var_builder(&varmap, 1, DType::F32, &Device::Cpu);
        let policy = ActPolicy::new(c, data.stats.clone(), vb).expect("policy");
        (policy, varmap, data)
    }

    /// A 32 x 32 camera (layer4: 1 x 1) through a width-4 ResNet-18, with the robot state.
    fn tiny_image() -> (ActConfig, TrainData) {
        let (policy, _, mut data) = tiny();
        let c = ActConfig {
            vision_backbone_width: 4,
            ..policy.config().clone()
        }
        .with_camera("observation.image", [3, 32, 32]);
        c.validate().expect("valid");
        let frames = data.episode_lengths.iter().sum::<usize>();
        data.images = Some(
            (0..frames * 32 * 32 * 3)
                .map(|i| ((i * 7 + i / 97) % 256) as u8)
                .collect(),
        );
        data.env_state = None;
        let img = crate::normalize::Stats {
            mean: vec![0.5; 3],
            std: vec![0.25; 3],
            ..Default::default()
        };
        data.stats.insert("observation.image".into(), img);
        (c, data)
    }

    #[test]
    fn history_frames_repeat_each_episodes_first_frame() {
        let starts = [0, 3, 7];
        assert_eq!(history_frames(&starts, &[0, 1, 3, 5], 1), vec![0, 1, 3, 5]);
        assert_eq!(
            history_frames(&starts, &[0, 1, 3, 5], 2),
            vec![0, 0, 0, 1, 3, 3, 4, 5]
        );
        assert_eq!(history_frames(&starts, &[4], 3), vec![3, 3, 4]);
    }

    /// With two observed steps a sample's state row is both frames' normalised states side
    /// by side, and its targets start at the older frame; steps outside the episode repeat
    /// its edge actions and are padding.
    #[test]
    fn two_observed_steps_align_targets_with_the_older_step() {
        let (one, _, mut data) = tiny();
        data.episode_lengths = vec![5, 7];
        let c = ActConfig {
            n_obs_steps: 2,
            ..one.config().clone()
        };
        let vb = crate::init::seeded_var_builder(&VarMap::new(), 1, DType::F32, &Device::Cpu);
        let policy = ActPolicy::new(c, data.stats.clone(), vb).expect("policy");
        let starts = episode_starts(&data.episode_lengths);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let b = batch(&policy, &data, &starts, &[5, 6, 11], None, &mut rng).expect("batch");
        let state = b.obs.state.as_ref().expect("state");
        assert_eq!(state.dims(), &[3, 4]);
        let rows = state.to_vec2::<f32>().expect("rows");
        let norm = |f: usize| {
            data.state[2 * f..2 * f + 2]
                .iter()
                .map(|x| (x - 200.0) / 100.0)
        };
        let expect = |a: usize, b: usize| norm(a).chain(norm(b)).collect::<Vec<f32>>();
        let want = [expect(5, 5), expect(5, 6), expect(10, 11)];
        for (got, want) in rows.iter().zip(&want) {
            let close = got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-6);
            assert!(close && got.len() == want.len(), "{got:?} against {want:?}");
        }
        assert_eq!(b.obs.env.as_ref().expect("env").dims(), &[3, 32]);
        let action = |f: usize| {
            let mut row = data.action[2 * f..2 * f + 2].to_vec();
            policy.normalize_action(&mut row);
            row
        };
        let targets = b.actions.to_vec3::<f32>().expect("targets");
        let pad = b.is_pad.to_vec2::<f32>().expect("pad");
        // Sample 0 is frame 5, its episode's first: row 0 (frame 4) lies before it.
        assert_eq!(targets[0][0], action(5));
        assert_eq!(targets[0][1], action(5));
        assert_eq!(targets[0][2], action(6));
        assert_eq!(pad[0], vec![1.0, 0.0, 0.0, 0.0]);
        assert_eq!(targets[1][0], action(5));
        assert_eq!(pad[1], vec![0.0; 4]);
        // Sample 2 is the data's last frame: rows 2 and 3 lie past the episode.
        assert_eq!(targets[2][0], action(10));
        assert_eq!(targets[2][3], action(11));
        assert_eq!(pad[2], vec![0.0, 0.0, 1.0, 1.0]);
        let mut images = Vec::new();
        let inputs = policy.inputs_of(&b.obs, &mut images).expect("inputs");
        let vae = VaeInput {
            actions: &b.actions,
            is_pad: &b.is_pad,
            eps: &b.eps,
        };
        let o = policy
            .net()
            .forward(&inputs, Some(&vae), None)
            .expect("forward");
        let (_, l1, kld) = policy.net().loss(&o, &b.actions, &b.is_pad).expect("loss");
        assert!(l1.is_finite() && l1 > 0.0 && kld.is_finite(), "{l1} {kld}");
    }

    /// A width-16 image ACT (Diffusion Policy's GroupNorm needs multiples of 16) and a
    /// random Diffusion Policy backbone of that width saved in `dir`.
    fn width16(dir: &Path) -> (ActConfig, TrainData, PathBuf) {
        let (c, data) = tiny_image();
        let c = ActConfig {
            vision_backbone_width: 16,
            ..c
        };
        let vm = VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 9, DType::F32, &Device::Cpu);
        crate::vision::ResNet18::new(
            16,
            crate::vision::BackboneNorm::Group,
            crate::vision::BackboneNames::Sequential,
            vb.pp(super::super::warm_start::DIFFUSION_BACKBONE),
        )
        .expect("dp backbone");
        let path = dir.join("dp.safetensors");
        vm.save(&path).expect("save");
        (c, data, path)
    }

    /// The cached feature maps give the network exactly the output the frames give it.
    #[test]
    fn cached_features_give_the_bits_the_frames_give() {
        let dir = tempfile::tempdir().expect("tmp");
        let (c, data, _) = width16(dir.path());
        let vm = VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 2, DType::F32, &Device::Cpu);
        let policy = ActPolicy::new(c, data.stats.clone(), vb).expect("policy");
        let cache = FeatureCache::build(&policy, &data, 12).expect("cache");
        let idx = [0, 3, 5, 9];
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let from_frames = batch(&policy, &data, &[0, 12], &idx, None, &mut rng).expect("b");
        let from_cache = batch(&policy, &data, &[0, 12], &idx, Some(&cache), &mut rng).expect("c");
        assert!(from_cache.obs.image.is_none() && from_frames.features.is_none());
        let mut images = Vec::new();
        let a = policy
            .inputs_of(&from_frames.obs, &mut images)
            .expect("inputs");
        let mut none = Vec::new();
        let mut b = policy
            .inputs_of(&from_cache.obs, &mut none)
            .expect("inputs");
        let f = from_cache.features.expect("features");
        b.features = std::slice::from_ref(&f);
        let out = |i| {
            let t = policy
                .net()
                .forward(&i, None, None)
                .expect("forward")
                .actions;
            t.flatten_all()
                .and_then(|t| t.to_vec1::<f32>())
                .expect("values")
        };
        assert_eq!(out(a), out(b));
    }

    /// A warm start from a Diffusion Policy backbone with the backbone frozen: the
    /// checkpoint's convolutions are the Diffusion Policy's, its norms carry calibrated
    /// statistics, the rest trained, and the run reports the conversion's error.
    #[test]
    fn a_frozen_backbone_from_diffusion_policy_stays_as_converted() {
        let dir = tempfile::tempdir().expect("tmp");
        let (c, data, dp) = width16(dir.path());
        let tc = ActTrainConfig {
            steps: 3,
            batch_size: 4,
            seed: 5,
            checkpoint_every: 0,
            backbone_from: Some(dp.clone()),
            freeze_backbone: true,
            ..Default::default()
        };
        let out = dir.path().join("run");
        let r = train(&data, c.clone(), &tc, &out, &mut |_, _, _| {}).expect("train");
        let e = r.backbone_relative_error.expect("error reported");
        assert!(e.is_finite() && e >= 0.0, "{e}");
        let saved =
            candle_core::safetensors::load(out.join(crate::checkpoint::WEIGHTS), &Device::Cpu)
                .expect("weights");
        let src = candle_core::safetensors::load(&dp, &Device::Cpu).expect("dp");
        let values = |t: &Tensor| t.flatten_all().and_then(|t| t.to_vec1::<f32>()).expect("v");
        assert_eq!(
            values(&saved["model.backbone.layer2.0.conv1.weight"]),
            values(&src["diffusion.rgb_encoder.backbone.5.0.conv1.weight"])
        );
        assert_eq!(
            values(&saved["model.backbone.layer1.1.bn2.weight"]),
            values(&src["diffusion.rgb_encoder.backbone.4.1.bn2.weight"])
        );
        let var = values(&saved["model.backbone.layer3.1.bn1.running_var"]);
        assert!(var.iter().any(|&v| v != 1.0), "statistics calibrated");
        // A resumed run goes on from the checkpoint's backbone; the warm start is not redone.
        let more = ActTrainConfig { steps: 4, ..tc };
        let r2 = train(&data, c, &more, &out, &mut |_, _, _| {}).expect("resume");
        assert_eq!((r2.steps_run, r2.backbone_relative_error), (1, None));
        let again =
            candle_core::safetensors::load(out.join(crate::checkpoint::WEIGHTS), &Device::Cpu)
                .expect("weights");
        for k in [
            "model.backbone.layer3.1.bn1.running_var",
            "model.backbone.conv1.weight",
        ] {
            assert_eq!(values(&again[k]), values(&saved[k]), "{k}");
        }
    }

    #[test]
    fn backbone_norm_tensors_are_recognised_by_name() {
        for frozen in [
            "bn1.weight",
            "layer1.0.bn2.running_var",
            "layer3.0.downsample.1.bias",
        ] {
            assert!(is_frozen_norm(frozen), "{frozen}");
        }
        for trained in [
            "conv1.weight",
            "layer2.1.conv2.weight",
            "layer3.0.downsample.0.weight",
        ] {
            assert!(!is_frozen_norm(trained), "{trained}");
        }
    }

    /// Training an image ACT moves the backbone's convolutions and leaves its FrozenBatchNorm
    /// tensors at their identity statistics; the checkpoint has LeRobot's backbone names and
    /// reloads to the same predictions.
    #[test]
    fn an_image_act_trains_its_backbone_and_keeps_its_batchnorm_frozen() {
        let (c, data) = tiny_image();
        let dir = tempfile::tempdir().expect("tmp");
        let tc = ActTrainConfig {
            steps: 3,
            batch_size: 4,
            seed: 5,
            checkpoint_every: 0,
            ..Default::default()
        };
        train(&data, c.clone(), &tc, dir.path(), &mut |_, _, _| {}).expect("train");
        let saved = candle_core::safetensors::load(
            dir.path().join(crate::checkpoint::WEIGHTS),
            &Device::Cpu,
        )
        .expect("weights");
        let fresh = VarMap::new();
        let vb = crate::init::seeded_var_builder(&fresh, tc.seed, DType::F32, &Device::Cpu);
        let _p = ActPolicy::new(c, data.stats.clone(), vb).expect("fresh");
        let init = fresh.data().lock().expect("lock");
        let values = |t: &Tensor| t.flatten_all().and_then(|t| t.to_vec1::<f32>()).expect("v");
        let conv = "backbone.layer1.0.conv1.weight";
        assert_ne!(
            values(&saved[&format!("model.{conv}")]),
            values(init[conv].as_tensor()),
            "the backbone's convolution trained"
        );
        for (name, want) in [
            ("bn1.weight", 1.0),
            ("bn1.running_var", 1.0),
            ("layer2.0.downsample.1.bias", 0.0),
            ("layer4.1.bn2.running_mean", 0.0),
        ] {
            let v = values(&saved[&format!("model.backbone.{name}")]);
            assert!(v.iter().all(|&x| x == want), "{name}: {v:?}");
        }
        let policy = ActPolicy::load(dir.path()).expect("load");
        let obs = crate::policy::Observation {
            state: vec![30.0, 370.0],
            env_state: None,
            image: Some(data.images.as_ref().expect("frames")[..32 * 32 * 3].to_vec()),
            wrist_image: None,
        };
        let a = policy.predict(&obs).expect("predict");
        assert_eq!(a.len(), 4 * 2);
        assert!(a.iter().all(|v| v.is_finite()));
        // PGD perturbs the frame (this policy reads no environment state) and moves the chunk.
        use crate::policy::AttackablePolicy as _;
        let pgd = crate::attack::PgdConfig {
            eps: 0.1,
            step: 0.05,
            iterations: 2,
            ..Default::default()
        };
        let (mut r, mut s) = (ChaCha8Rng::seed_from_u64(3), ChaCha8Rng::seed_from_u64(4));
        let hit = policy
            .predict_chunk_attacked(std::slice::from_ref(&obs), &pgd, &mut r, &mut s)
            .expect("attack");
        assert_eq!(hit.len(), a.len());
        assert_ne!(hit, a, "the attacked frame changed nothing");
        let small = crate::policy::Observation {
            image: Some(vec![0; 16 * 16 * 3]),
            ..obs
        };
        let e = policy
            .predict(&small)
            .expect_err("a 16 x 16 frame")
            .to_string();
        assert!(
            e.contains("observation.image") && e.contains("32x32x3"),
            "{e}"
        );
    }

    /// A warm start sets every variable to the checkpoint's value; a checkpoint of another
    /// width is a typed error naming the first variable whose shape differs.
    #[test]
    fn a_warm_start_loads_every_variable_and_refuses_other_shapes() {
        let (policy, varmap, _) = tiny();
        let dir = tempfile::tempdir().expect("tmp");
        policy.save(dir.path(), &varmap).expect("save");
        let path = dir.path().join(crate::checkpoint::WEIGHTS);
        let other = VarMap::new();
        let vb = crate::init::seeded_var_builder(&other, 2, DType::F32, &Device::Cpu);
        let c = policy.config().clone();
        let _p = ActPolicy::new(c.clone(), policy.stats().clone(), vb).expect("policy");
        let values = |m: &VarMap| -> Vec<(String, Vec<f32>)> {
            let vars = m.data().lock().expect("lock");
            let mut v: Vec<_> = vars
                .iter()
                .map(|(k, t)| {
                    let x = t.as_tensor().flatten_all().and_then(|t| t.to_vec1());
                    (k.clone(), x.expect("values"))
                })
                .collect();
            v.sort_by(|a, b| a.0.cmp(&b.0));
            v
        };
        assert_ne!(
            values(&other),
            values(&varmap),
            "different seeds, different weights"
        );
        let n = load_weights(&other, &path).expect("load");
        assert_eq!(n, values(&varmap).len());
        assert_eq!(values(&other), values(&varmap));
        let wide = VarMap::new();
        let vb = crate::init::seeded_var_builder(&wide, 2, DType::F32, &Device::Cpu);
        let c = ActConfig { dim_model: 24, ..c };
        let _p = ActPolicy::new(c, policy.stats().clone(), vb).expect("policy");
        let e = load_weights(&wide, &path).expect_err("other width");
        let msg = e.to_string();
        assert!(
            msg.contains("the policy's `") && msg.contains("expects"),
            "{msg}"
        );
    }

    /// Every parameter gets the gradient that finite differences of the training loss give
    /// (central differences, h = 1e-3 in f32: agreement within 5% or 1e-3). Guards against
    /// ops without a backward pass, which cut gradients silently: candle-nn's fused LayerNorm
    /// and softmax left all but the action head and the latent projection untrained.
    #[test]
    fn every_parameter_gets_its_finite_difference_gradient() {
        let (bad, _) = finite_difference_check(tiny());
        assert!(bad.is_empty(), "{bad:#?}");
    }

    /// With the KL term off, the L1 term alone reaches every variable of the CVAE encoder
    /// (through the latent the decoder reads), with the gradients finite differences give. So
    /// the collapsed latent of every keypoint ACT trained here (KL 0.000) is a training
    /// outcome, not a cut path.
    #[test]
    fn the_l1_term_alone_reaches_the_cvae_encoder() {
        let (bad, norms) = finite_difference_check(tiny_kl(0.0));
        assert!(bad.is_empty(), "{bad:#?}");
        let vae: Vec<_> = norms
            .iter()
            .filter(|(n, _)| n.contains("vae_encoder"))
            .collect();
        assert!(vae.len() >= 8, "CVAE variables: {vae:?}");
        for (name, norm) in vae {
            assert!(*norm > 0.0, "zero gradient for {name}");
        }
    }

    /// Each parameter's backward gradient of the training loss at its middle entry against
    /// central finite differences (h = 1e-3 in f32, agreement within 5% or 1e-3): the
    /// mismatches (or missing gradients), and each parameter's gradient sum of squares.
    fn finite_difference_check(
        (policy, varmap, data): (ActPolicy, VarMap, TrainData),
    ) -> (Vec<String>, Vec<(String, f32)>) {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let b = batch(&policy, &data, &[0, 12], &[0, 3, 5, 9], None, &mut rng).expect("batch");
        let loss_of = || {
            let cell = RefCell::new(ChaCha8Rng::seed_from_u64(1));
            let d = Dropout::new(0.0, &cell);
            let vae = VaeInput {
                actions: &b.actions,
                is_pad: &b.is_pad,
                eps: &b.eps,
            };
            let net = policy.net();
            let mut images = Vec::new();
            let inputs = policy.inputs_of(&b.obs, &mut images).expect("inputs");
            let o = net.forward(&inputs, Some(&vae), Some(&d)).expect("forward");
            net.loss(&o, &b.actions, &b.is_pad).expect("loss").0
        };
        let grads = loss_of().backward().expect("backward");
        let vars = varmap.data().lock().expect("lock");
        let (mut bad, mut norms) = (Vec::new(), Vec::new());
        for (name, var) in vars.iter() {
            let Some(g) = grads.get(var.as_tensor()) else {
                bad.push(format!("{name}: no gradient"));
                continue;
            };
            let g = g
                .flatten_all()
                .and_then(|g| g.to_vec1::<f32>())
                .expect("grad");
            norms.push((name.clone(), g.iter().map(|v| v * v).sum()));
            let w = var
                .as_tensor()
                .flatten_all()
                .and_then(|w| w.to_vec1::<f32>())
                .expect("w");
            let i = w.len() / 2;
            let at = |v: f32| {
                let mut x = w.clone();
                x[i] = v;
                var.set(&Tensor::from_vec(x, var.as_tensor().shape(), &Device::Cpu).expect("t"))
                    .expect("set");
                f64::from(loss_of().to_scalar::<f32>().expect("scalar"))
            };
            let h = 1e-3f32;
            let fd = (at(w[i] + h) - at(w[i] - h)) / (2.0 * f64::from(h));
            at(w[i]);
            let an = f64::from(g[i]);
            if (fd - an).abs() > 0.05 * fd.abs().max(an.abs()) + 1e-3 {
                bad.push(format!(
                    "{name}[{i}]: finite differences {fd:+.5}, backward {an:+.5}"
                ));
            }
        }
        (bad, norms)
    }
}
