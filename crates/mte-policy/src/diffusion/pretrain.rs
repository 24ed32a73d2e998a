//! A supervised warm start for the image encoder: regress the simulator's block keypoints
//! (`observation.environment_state`, MIN_MAX-normalised to [-1, 1]) from single frames through
//! the policy's own encoder and a linear head that is thrown away afterwards.
//!
//! Why: no pretrained weights can be downloaded here, and on 2 CPU cores the diffusion loss
//! alone teaches a randomly initialised ResNet where the block is far too slowly (a 4,000-step
//! image policy reached 0.15 mean coverage). The simulator knows the keypoints, so the encoder
//! can learn to find the block from a direct regression signal first; the policy is then
//! trained on top of it ([`crate::train::TrainConfig::init`], optionally with
//! [`crate::train::TrainConfig::freeze_encoder`]). The architecture and the checkpoint stay
//! Diffusion Policy's; only the training recipe differs. An mte extension.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Module, Optimizer, ParamsAdamW, VarMap};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::config::DiffusionConfig;
use crate::error::{PolicyError, config_err};
use crate::model::DiffusionPolicy;
use crate::normalize::{NormMode, Normalizer};
use crate::train::{
    Crop, ENCODER_PREFIX, Progress, TrainData, crop_origin, frame_features, learning_rate,
    push_crop, sorted_vars,
};
use crate::training::{LossTrace, step_rng};

/// The name of the regression target in a dataset.
pub const TARGET: &str = "observation.environment_state";

/// Encoder pre-training settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EncoderPretrainConfig {
    /// Optimiser steps.
    pub steps: usize,
    /// Frames per batch.
    pub batch_size: usize,
    /// Peak AdamW learning rate (after 100 warm-up steps, cosine decay to 0). 1e-3: a
    /// regression with a fresh head tolerates a larger rate than the diffusion loss (3e-4).
    pub lr: f64,
    /// Fraction of episodes (the last ones) held out to measure the keypoint error.
    pub heldout_fraction: f64,
    /// Seed of the initialisation and of every draw.
    pub seed: u64,
}

impl Default for EncoderPretrainConfig {
    fn default() -> Self {
        EncoderPretrainConfig {
            steps: 2_000,
            batch_size: 64,
            lr: 1e-3,
            heldout_fraction: 0.05,
            seed: 0,
        }
    }
}

impl EncoderPretrainConfig {
    /// Check every field.
    pub fn validate(&self) -> Result<(), PolicyError> {
        if self.steps == 0 {
            return Err(config_err("steps", self.steps, ">= 1"));
        }
        if self.batch_size == 0 {
            return Err(config_err("batch_size", self.batch_size, ">= 1"));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(config_err("lr", self.lr, "a finite number > 0"));
        }
        if !(0.0..1.0).contains(&self.heldout_fraction) {
            return Err(config_err(
                "heldout_fraction",
                self.heldout_fraction,
                "in [0, 1)",
            ));
        }
        Ok(())
    }
}

/// What a pre-training run reports.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct PretrainReport {
    /// Steps run.
    pub steps: usize,
    /// Mean normalised MSE over the first 50 steps.
    pub first_loss: f32,
    /// Mean normalised MSE over the last 100 steps.
    pub final_loss: f32,
    /// Held-out episodes (the last ones of the dataset).
    pub heldout_episodes: usize,
    /// Mean absolute keypoint-coordinate error on the held-out frames, in the dataset's units
    /// (PushT: pixels of the 512 x 512 workspace), centre crop; None without held-out frames.
    pub heldout_mae: Option<f32>,
    /// The same error of a predictor that always outputs the training frames' mean target:
    /// the baseline `heldout_mae` has to beat.
    pub heldout_mae_of_mean: Option<f32>,
    /// Wall time (s).
    pub seconds: f64,
}

/// Writes a pre-trained encoder into `dir`: its weights as `encoder.safetensors` (policy
/// keys, for [`crate::train::TrainConfig::init`]) and `pretrain.json` (the settings and the
/// report). Returns the weights' path.
pub fn save_encoder(
    dir: &std::path::Path,
    weights: &HashMap<String, Tensor>,
    pc: &EncoderPretrainConfig,
    report: &PretrainReport,
) -> Result<std::path::PathBuf, PolicyError> {
    let io = |path: &std::path::Path| {
        let path = path.to_path_buf();
        move |source| PolicyError::Io { path, source }
    };
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let path = dir.join("encoder.safetensors");
    candle_core::safetensors::save(weights, &path)?;
    let json = serde_json::json!({ "config": pc, "report": report });
    let rp = dir.join("pretrain.json");
    let text = serde_json::to_string_pretty(&json).map_err(|source| PolicyError::Json {
        path: rp.clone(),
        source,
    })?;
    std::fs::write(&rp, text).map_err(io(&rp))?;
    Ok(path)
}

/// Pre-train the encoder of an image policy of `config` on `data` (which must carry
/// `env_state` and images). Returns the encoder's weights under their policy keys
/// (`diffusion.rgb_encoder.…`, ready for [`crate::train::TrainConfig::init`]) and a report.
pub fn pretrain_encoder(
    config: &DiffusionConfig,
    pc: &EncoderPretrainConfig,
    data: &TrainData,
    device: &Device,
    progress: Progress,
) -> Result<(HashMap<String, Tensor>, PretrainReport), PolicyError> {
    config.validate()?;
    pc.validate()?;
    if config.cameras().len() > 1 || config.use_separate_rgb_encoder_per_camera {
        // The warm start is one shared encoder's weights, learnt on the scene camera.
        return Err(config_err(
            "input_features",
            config.cameras(),
            "one camera and a shared encoder (the warm start regresses the scene camera)",
        ));
    }
    let t0 = std::time::Instant::now();
    let inputs = Inputs::of(config, data)?;
    let (frames, k) = (inputs.frames, inputs.k);
    let stats = data
        .stats
        .get(TARGET)
        .ok_or_else(|| config_err("stats", "no observation.environment_state", "its min/max"))?;
    let norm = Normalizer::new(TARGET, NormMode::MinMax, stats, k)?;
    let mut y = inputs.target.to_vec();
    norm.normalize(&mut y);

    // Held-out episodes: the last ones.
    let n_ep = data.episode_lengths.len();
    let held = ((n_ep as f64 * pc.heldout_fraction).round() as usize).min(n_ep - 1);
    let train_frames: usize = data.episode_lengths[..n_ep - held].iter().sum();

    let varmap = VarMap::new();
    let vb = crate::init::seeded_var_builder(&varmap, pc.seed, DType::F32, device);
    let policy = DiffusionPolicy::new(config.clone(), data.stats.clone(), vb.clone())?;
    let head = candle_nn::linear(
        2 * config.spatial_softmax_num_keypoints,
        k,
        vb.pp("pretrain_head"),
    )?;
    let vars = sorted_vars(&varmap, |n| {
        n.starts_with(ENCODER_PREFIX) || n.starts_with("pretrain_head")
    })?;
    let mut opt = AdamW::new(
        vars.iter().map(|(_, v)| v.clone()).collect(),
        ParamsAdamW {
            lr: pc.lr,
            weight_decay: 1e-6,
            ..ParamsAdamW::default()
        },
    )?;
    let mut batch = Batch::default();
    let mut trace = LossTrace::default();
    for step in 0..pc.steps {
        let mut rng = step_rng(pc.seed, step);
        inputs.draw(
            config,
            &y,
            train_frames,
            pc.batch_size,
            &mut rng,
            &mut batch,
        );
        let (x, t) = batch.tensors(device)?;
        let pred = head.forward(&policy.image_features_cropped(&x)?)?;
        let loss = (pred - t)?.sqr()?.mean_all()?;
        let lr = learning_rate(pc.lr, 100, pc.steps, step);
        opt.set_learning_rate(lr);
        opt.backward_step(&loss)?;
        let l = loss.to_scalar::<f32>()?;
        if !l.is_finite() {
            return Err(config_err("loss", l, "finite (lower lr)"));
        }
        trace.push(l);
        progress(step + 1, l, lr);
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len().max(1) as f32;

    let (heldout_mae, heldout_mae_of_mean) = if train_frames < frames {
        let (e, e0) = heldout_error(&policy, &head, data, &inputs, &norm, train_frames)?;
        (Some(e), Some(e0))
    } else {
        (None, None)
    };
    let weights = vars
        .iter()
        .filter(|(n, _)| n.starts_with(ENCODER_PREFIX))
        .map(|(n, v)| (n.clone(), v.as_tensor().detach()))
        .collect();
    Ok((
        weights,
        PretrainReport {
            steps: pc.steps,
            first_loss: mean(trace.first()),
            final_loss: mean(trace.recent()),
            heldout_episodes: held,
            heldout_mae,
            heldout_mae_of_mean,
            seconds: t0.elapsed().as_secs_f64(),
        },
    ))
}

/// The frames and keypoint targets of a pre-training dataset, checked against each other.
struct Inputs<'a> {
    px: &'a [u8],
    target: &'a [f32],
    frames: usize,
    shape: [usize; 3],
    /// Target values per frame.
    k: usize,
}

impl<'a> Inputs<'a> {
    fn of(config: &DiffusionConfig, data: &'a TrainData) -> Result<Self, PolicyError> {
        let shape = config.image_shape().ok_or_else(|| {
            config_err("input_features", "no observation.image", "an image policy")
        })?;
        let px = data
            .images
            .as_deref()
            .ok_or_else(|| config_err("dataset", "no images", "observation.image frames"))?;
        let target = data.env_state.as_deref().ok_or_else(|| {
            config_err(
                "dataset",
                "no observation.environment_state",
                "keypoint targets (generate with --obs keypoints,pixels)",
            )
        })?;
        let frames: usize = data.episode_lengths.iter().sum();
        let [c, h, w] = shape;
        if frames == 0 || px.len() != frames * c * h * w || target.len() % frames != 0 {
            return Err(config_err(
                "dataset",
                format!(
                    "{frames} frames, {} pixels, {} targets",
                    px.len(),
                    target.len()
                ),
                "one image and one target row per frame",
            ));
        }
        Ok(Self {
            px,
            target,
            frames,
            shape,
            k: target.len() / frames,
        })
    }
}

/// Reused buffers of one pre-training batch: crops (CHW f32) and normalised targets.
#[derive(Default)]
struct Batch {
    imgs: Vec<f32>,
    ys: Vec<f32>,
    /// `(b, c, crop_h, crop_w)` of `imgs`.
    shape: (usize, usize, usize, usize),
    /// Target values per frame.
    k: usize,
}

impl Batch {
    /// The images `(b, c, crop_h, crop_w)` and targets `(b, k)` on `device`.
    fn tensors(&self, device: &Device) -> Result<(Tensor, Tensor), PolicyError> {
        Ok((
            Tensor::from_slice(&self.imgs, self.shape, device)?,
            Tensor::from_slice(&self.ys, (self.shape.0, self.k), device)?,
        ))
    }
}

impl Inputs<'_> {
    /// Draws `b` frames of the first `train_frames` with `rng` (a crop each, at the config's
    /// crop shape, random or centred) and their rows of `y` into `batch`.
    fn draw(
        &self,
        config: &DiffusionConfig,
        y: &[f32],
        train_frames: usize,
        b: usize,
        rng: &mut ChaCha8Rng,
        batch: &mut Batch,
    ) {
        let ([c, h, w], k) = (self.shape, self.k);
        let (crop_h, crop_w) = config.crop_shape.map_or((h, w), |[a, b]| (a, b));
        batch.imgs.clear();
        batch.ys.clear();
        for _ in 0..b {
            let f = rng.random_range(0..train_frames);
            let (top, left) = crop_origin([h, w], [crop_h, crop_w], config.crop_is_random, rng);
            let crop = Crop {
                top,
                left,
                h: crop_h,
                w: crop_w,
            };
            push_crop(self.px, f, self.shape, crop, &mut batch.imgs);
            batch.ys.extend_from_slice(&y[f * k..(f + 1) * k]);
        }
        batch.shape = (b, c, crop_h, crop_w);
        batch.k = k;
    }
}

/// Held-out mean absolute error in dataset units (centre crop, as the policy sees frames at
/// evaluation) of the regression, and of predicting the training frames' mean.
fn heldout_error(
    policy: &DiffusionPolicy,
    head: &candle_nn::Linear,
    data: &TrainData,
    inputs: &Inputs<'_>,
    norm: &Normalizer,
    train_frames: usize,
) -> Result<(f32, f32), PolicyError> {
    let (target, frames, k) = (inputs.target, inputs.frames, inputs.k);
    let mut mean_y = vec![0f64; k];
    for f in 0..train_frames {
        for (j, m) in mean_y.iter_mut().enumerate() {
            *m += f64::from(target[f * k + j]) / train_frames as f64;
        }
    }
    let feats = frame_features(policy, data, train_frames..frames)?;
    let d = 2 * policy.config().spatial_softmax_num_keypoints;
    let feats = Tensor::from_vec(feats, (frames - train_frames, d), policy.device())?;
    let mut pred = head.forward(&feats)?.flatten_all()?.to_vec1::<f32>()?;
    norm.unnormalize(&mut pred);
    let (mut err, mut err_mean) = (0f64, 0f64);
    for (i, p) in pred.iter().enumerate() {
        let truth = f64::from(target[train_frames * k + i]);
        err += (f64::from(*p) - truth).abs();
        err_mean += (mean_y[i % k] - truth).abs();
    }
    let n = pred.len() as f64;
    Ok(((err / n) as f32, (err_mean / n) as f32))
}
