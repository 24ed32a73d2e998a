//! The physical patch attack and the metric-type defence (protocol sections 4-5).
//!
//! - [`train_patch`]: a square texture pasted at a fixed place in the frame (callers map the
//!   patch's world position with `mte_sim::patch::origin_px`), optimised offline on
//!   demonstration windows to *maximise* the policy's own noise-prediction loss, by raw
//!   gradient ascent or sign ascent, for a number of epochs; pixels stay in [0, 1].
//! - [`finetune_encoder`]: the denoising head frozen, the image encoder fine-tuned (AdamW) on
//!   batches carrying the patch at random positions, minimising the policy loss plus a
//!   consistency term `λ · mean(‖f(x ⊕ patch) − f(x)‖²)` tying the perturbed embedding to the
//!   clean one (the clean embedding is detached); optionally the patch is regenerated against
//!   the current encoder every step (one ascent step).
//! - [`gradient_probe`]: how the fine-tuned encoder changes the attack surface: cosine between
//!   the loss's input gradients through the original and the fine-tuned policy at the same
//!   patched frames (over the whole frame and over the patch's own pixels; at the clean
//!   frames too, for comparison), the ratio of their norms (tuned / original), and the ratio
//!   of the latent displacements the patch induces (tuned / original).
//!
//! Images are full frames `(N, 3, H, W)` in [0, 1], cropped by the policy as at evaluation.
//! All randomness comes from the seeds in the configs.

use candle_core::{D, DType, Tensor, Var};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::error::{PolicyError, config_err};
use crate::model::{DiffusionPolicy, ObsBatch};
use crate::train::{TrainData, Windows, sample_batch};

/// How the patch climbs the loss.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Ascent {
    /// `P ← clip(P + step · g)`.
    Raw,
    /// `P ← clip(P + step · sign(g))` (sign-PGD without a ball: the patch is unconstrained).
    Sign,
}

impl std::fmt::Display for Ascent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Ascent::Raw => "raw",
            Ascent::Sign => "sign",
        })
    }
}

/// Where the texture sits in the frames of a training batch.
///
/// The paper's threat is a physical patch in the scene, away from the goal, that works
/// wherever it lands; a patch trained at one place over the goal acts mostly as an occluder
/// of the goal (BENCHMARKS.md, the grey-square control). mte's rule for `AwayFromGoal`:
/// every batch draws the top-left pixel uniformly among those whose whole texture lies in
/// the `region` (the frame's evaluation crop) and whose centre is at least
/// `min_goal_distance` frame px from `goal` (the goal's centre in frame px).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum Placement {
    /// Every batch at [`PatchConfig::origin`].
    Fixed,
    /// A position per batch, away from the goal (see the type's doc).
    AwayFromGoal {
        /// Allowed area `[x0, y0, x1, y1]` in frame px (end exclusive).
        region: [usize; 4],
        /// Goal centre `[x, y]` in frame px.
        goal: [f64; 2],
        /// Least distance of the texture's centre from `goal`, frame px.
        min_goal_distance: f64,
    },
}

impl Placement {
    /// The top-left pixels this rule allows for a `side` px texture, row-major.
    pub fn origins(&self, side: usize, fixed: [usize; 2]) -> Vec<[usize; 2]> {
        match self {
            Placement::Fixed => vec![fixed],
            Placement::AwayFromGoal {
                region: [x0, y0, x1, y1],
                goal,
                min_goal_distance,
            } => {
                let half = side as f64 / 2.0;
                let mut out = Vec::new();
                for y in *y0..y1.saturating_sub(side) + 1 {
                    for x in *x0..x1.saturating_sub(side) + 1 {
                        let (cx, cy) = (x as f64 + half, y as f64 + half);
                        if (cx - goal[0]).hypot(cy - goal[1]) >= *min_goal_distance {
                            out.push([x, y]);
                        }
                    }
                }
                out
            }
        }
    }
}

/// Patch training settings. Defaults: the protocol's 11 epochs and sign ascent at 1.5e-3 (the
/// middle of its step grid {1e-4, 5e-4, 1.5e-3, 5e-3}); a 16 px patch (1/36 of a 96 px frame)
/// at pixel (40, 40), i.e. centred on the table at world (256, 256), fixed; 16 batches of 16
/// windows per epoch, sized for 2 CPU cores (the protocol's epochs run over the whole dataset
/// on a GPU; set `batches_per_epoch` to `windows / batch_size` for that). `mte attack patch`
/// defaults to [`Placement::AwayFromGoal`] instead.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PatchConfig {
    /// Texture side (observation px).
    pub side: usize,
    /// Top-left pixel `[x, y]` of the texture in the policy's (uncropped) frame: where a
    /// [`Placement::Fixed`] patch trains, and where the patch file says it is evaluated.
    pub origin: [usize; 2],
    /// Where the texture sits in each training batch.
    pub placement: Placement,
    /// Epochs.
    pub epochs: usize,
    /// Batches per epoch.
    pub batches_per_epoch: usize,
    /// Windows per batch.
    pub batch_size: usize,
    /// Step size (pixel units in [0, 1]).
    pub step: f64,
    /// Ascent rule.
    pub ascent: Ascent,
    /// Seed of windows, noise and timesteps.
    pub seed: u64,
}

impl Default for PatchConfig {
    fn default() -> Self {
        PatchConfig {
            side: 16,
            origin: [40, 40],
            placement: Placement::Fixed,
            epochs: 11,
            batches_per_epoch: 16,
            batch_size: 16,
            step: 1.5e-3,
            ascent: Ascent::Sign,
            seed: 0,
        }
    }
}

impl PatchConfig {
    /// Check every field.
    pub fn validate(&self) -> Result<(), PolicyError> {
        if self.side == 0 {
            return Err(config_err("side", self.side, ">= 1 px"));
        }
        for (name, v) in [
            ("epochs", self.epochs),
            ("batches_per_epoch", self.batches_per_epoch),
            ("batch_size", self.batch_size),
        ] {
            if v == 0 {
                return Err(config_err(name, v, ">= 1"));
            }
        }
        if !(self.step.is_finite() && self.step > 0.0) {
            return Err(config_err("step", self.step, "a finite step > 0"));
        }
        Ok(())
    }
}

/// A trained patch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatchReport {
    /// Texture `(3, side, side)` in [0, 1], channel-major.
    pub texture: Vec<f32>,
    /// Side (px).
    pub side: usize,
    /// Top-left pixel `(x, y)` in the policy's frame.
    pub origin: (usize, usize),
    /// Mean policy loss with the initial (grey) patch, on the first epoch's batches.
    pub initial_loss: f64,
    /// Mean policy loss per epoch, while training.
    pub epoch_loss: Vec<f64>,
}

impl PatchReport {
    /// The texture as RGB u8, row-major (for `mte_sim::Patch` and PNG files).
    pub fn rgb_u8(&self) -> Vec<u8> {
        texture_to_rgb(&self.texture, self.side)
    }
}

/// `(3, s, s)` in [0, 1] → RGB u8 row-major.
pub fn texture_to_rgb(texture: &[f32], side: usize) -> Vec<u8> {
    let n = side * side;
    (0..n)
        .flat_map(|i| {
            (0..3).map(move |c| (texture[c * n + i].clamp(0.0, 1.0) * 255.0).round() as u8)
        })
        .collect()
}

/// RGB u8 row-major → `(3, s, s)` in [0, 1].
pub fn rgb_to_texture(rgb: &[u8], side: usize) -> Vec<f32> {
    let n = side * side;
    (0..3)
        .flat_map(|c| (0..n).map(move |i| f32::from(rgb[i * 3 + c]) / 255.0))
        .collect()
}

/// Paste `patch (3, s, s)` into every frame of `images (N, 3, H, W)` with its top-left
/// pixel at `(x, y)`; differentiable in both.
pub fn paste(images: &Tensor, patch: &Tensor, x: usize, y: usize) -> Result<Tensor, PolicyError> {
    let (_, c, h, w) = images.dims4()?;
    let (pc, s, s2) = patch.dims3()?;
    if pc != c || s != s2 || x + s > w || y + s > h {
        return Err(config_err(
            "patch",
            format!("({pc}, {s}, {s2}) at ({x}, {y})"),
            format!("a ({c}, s, s) texture inside the {w} x {h} frame"),
        ));
    }
    let place = |t: &Tensor| -> candle_core::Result<Tensor> {
        t.pad_with_zeros(1, y, h - y - s)?
            .pad_with_zeros(2, x, w - x - s)?
            .unsqueeze(0)
    };
    let mask = place(&patch.ones_like()?)?;
    let placed = place(patch)?;
    Ok((images.broadcast_mul(&(1.0 - &mask)?)?
        + placed.broadcast_as(images.shape())?.broadcast_mul(&mask)?)?)
}

/// One batch for patch work: full frames, normalised actions, noise and timesteps.
struct Batch {
    obs: ObsBatch,
    x0: Tensor,
    eps: Tensor,
    ts: Vec<usize>,
}

fn batch(
    policy: &DiffusionPolicy,
    data: &TrainData,
    win: &Windows,
    b: usize,
    rng: &mut ChaCha8Rng,
) -> Result<Batch, PolicyError> {
    let c = policy.config();
    let (tp, a) = (c.horizon, c.action_dim()?);
    let (obs, x0) = sample_batch(policy, data, win, b, rng, false)?;
    let eps: Vec<f32> = (0..b * tp * a)
        .map(|_| StandardNormal.sample(rng))
        .collect();
    let ts = (0..b)
        .map(|_| rng.random_range(0..c.num_train_timesteps))
        .collect();
    let dev = policy.device();
    Ok(Batch {
        obs,
        x0: Tensor::from_vec(x0, (b, tp, a), dev)?,
        eps: Tensor::from_vec(eps, (b, tp, a), dev)?,
        ts,
    })
}

fn images(b: &Batch) -> Result<&Tensor, PolicyError> {
    b.obs
        .image
        .as_ref()
        .ok_or_else(|| config_err("input_features", "no observation.image", "an image policy"))
}

/// The policy loss on `b` with its images replaced by `imgs`.
fn loss_with(policy: &DiffusionPolicy, b: &Batch, imgs: &Tensor) -> Result<Tensor, PolicyError> {
    let obs = ObsBatch {
        image: Some(imgs.clone()),
        ..b.obs.clone()
    };
    let cond = policy.global_cond(&obs)?;
    policy.loss(&cond, &b.x0, &b.eps, &b.ts, None)
}

/// The frozen head's denoising loss on batch `b` with the image features `f` in place of
/// the encoder's (the same noise and timesteps whatever the features).
fn head_loss(policy: &DiffusionPolicy, b: &Batch, f: &Tensor) -> Result<Tensor, PolicyError> {
    let cond = policy.global_cond_from_features(&b.obs, Some(f))?;
    policy.loss(&cond, &b.x0, &b.eps, &b.ts, None)
}

/// The scene camera's frame size; a policy that also reads the wrist camera is refused (the
/// patch lives in the scene camera's frames, and the defences here fine-tune on them alone).
fn frame_hw(policy: &DiffusionPolicy) -> Result<(usize, usize), PolicyError> {
    if policy.n_cameras() > 1 {
        return Err(config_err(
            "input_features",
            policy.config().cameras(),
            "one camera (the patch and the encoder defences act on the scene camera alone)",
        ));
    }
    match policy.config().image_shape() {
        Some([_, h, w]) => Ok((h, w)),
        None => Err(config_err(
            "input_features",
            "no observation.image",
            "an image policy (the patch is drawn into camera frames)",
        )),
    }
}

/// One ascent step on `patch` from gradient `g`.
fn ascend(patch: &Tensor, g: &Tensor, step: f64, rule: Ascent) -> Result<Tensor, PolicyError> {
    let dir = match rule {
        Ascent::Raw => g.clone(),
        Ascent::Sign => g.sign()?,
    };
    Ok((patch + (dir * step)?)?.clamp(0f32, 1f32)?.detach())
}

/// Train a patch on demonstration windows of `data` against `policy` (see the module doc).
/// `progress(epoch, mean loss)` is called after each epoch.
pub fn train_patch(
    policy: &DiffusionPolicy,
    data: &TrainData,
    cfg: &PatchConfig,
    progress: &dyn Fn(usize, f64),
) -> Result<PatchReport, PolicyError> {
    cfg.validate()?;
    let (h, w) = frame_hw(policy)?;
    let [x, y] = cfg.origin;
    if x + cfg.side > w || y + cfg.side > h {
        return Err(config_err(
            "origin",
            format!("{:?} with side {}", cfg.origin, cfg.side),
            format!("a texture inside the {w} x {h} frame"),
        ));
    }
    let origins = cfg.placement.origins(cfg.side, cfg.origin);
    if let Some(bad) = origins
        .iter()
        .find(|[x, y]| x + cfg.side > w || y + cfg.side > h)
    {
        return Err(config_err(
            "placement",
            format!("{:?} allows origin {bad:?}", cfg.placement),
            format!("textures inside the {w} x {h} frame"),
        ));
    }
    if origins.is_empty() {
        return Err(config_err(
            "placement",
            format!("{:?}", cfg.placement),
            format!(
                "a rule that allows at least one position of a {} px texture",
                cfg.side
            ),
        ));
    }
    let win = Windows::new(data, policy.config(), false);
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let dev = policy.device();
    // Start from mid-grey: no prior on what hurts the policy.
    let mut patch = Tensor::full(0.5f32, (3, cfg.side, cfg.side), dev)?;
    let mut initial_loss = None;
    let mut epoch_loss = Vec::with_capacity(cfg.epochs);
    for epoch in 0..cfg.epochs {
        let mut total = 0.0;
        for _ in 0..cfg.batches_per_epoch {
            let b = batch(policy, data, &win, cfg.batch_size, &mut rng)?;
            let [px, py] = match cfg.placement {
                Placement::Fixed => [x, y],
                _ => origins[rng.random_range(0..origins.len())],
            };
            let var = Var::from_tensor(&patch)?;
            let imgs = paste(images(&b)?, var.as_tensor(), px, py)?;
            let loss = loss_with(policy, &b, &imgs)?;
            let grads = loss.backward()?;
            let g = grads
                .get(var.as_tensor())
                .ok_or_else(|| config_err("patch", "no gradient", "a differentiable encoder"))?;
            total += scalar(&loss)?;
            patch = ascend(&patch, g, cfg.step, cfg.ascent)?;
        }
        let mean = total / cfg.batches_per_epoch as f64;
        if epoch == 0 {
            initial_loss = Some(mean);
        }
        epoch_loss.push(mean);
        progress(epoch, mean);
    }
    Ok(PatchReport {
        texture: patch.flatten_all()?.to_vec1::<f32>()?,
        side: cfg.side,
        origin: (x, y),
        initial_loss: initial_loss.unwrap_or(f64::NAN),
        epoch_loss,
    })
}

/// Which clean embedding the consistency term pulls the patched embedding towards.
///
/// The protocol says only "tying the perturbed embedding to the clean one". mte's default is
/// the encoder *before* fine-tuning: the denoising head is frozen and was trained on those
/// features, so the target never moves and the encoder cannot lower the term by flattening
/// its features. `Current` (the fine-tuned encoder's own clean embedding, detached) is the
/// other reading; on the shipped image policy it lost more than half the clean coverage at
/// h = 2 in 1,000 steps (BENCHMARKS.md).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Anchor {
    /// `f_θ0(x)`: a frozen copy of the encoder as it was when fine-tuning started.
    #[default]
    Original,
    /// `stop_grad(f_θ(x))`: the encoder being fine-tuned.
    Current,
}

impl std::fmt::Display for Anchor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Anchor::Original => "original",
            Anchor::Current => "current",
        })
    }
}

/// Encoder fine-tuning settings. Defaults: the protocol's 3000 steps at lr 1e-5; consistency
/// weight 1 towards the original encoder's clean embedding; no clean-feature term; batches
/// of 16 windows; the patch fixed (no regeneration).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FinetuneConfig {
    /// Optimiser steps.
    pub steps: usize,
    /// AdamW learning rate.
    pub lr: f64,
    /// Weight λ of the consistency term.
    pub consistency: f64,
    /// The clean embedding the consistency term ties the patched one to.
    pub anchor: Anchor,
    /// Weight μ of the clean-feature term `μ · mean ‖f_θ(x) − f_θ0(x)‖²`: the encoder being
    /// tuned, on the clean frames, against its frozen copy from before fine-tuning (the
    /// features the frozen denoising head was trained on). An mte extension, 0 (off) by
    /// default: the protocol trains on patched batches only, and nothing there keeps the
    /// clean embedding where the head expects it.
    pub clean_features: f64,
    /// Weight ν of the clean task term `ν · L(f_θ(x))`: the frozen head's denoising loss
    /// on the clean frames (the same windows, noise and timesteps as the patched task term).
    /// An mte extension, 0 (off) by default: where the clean-feature term holds the
    /// embedding near the original, this one holds the objective the head was trained for.
    pub clean_task: f64,
    /// Windows per batch.
    pub batch_size: usize,
    /// Regenerate the patch against the current encoder every step (one ascent step).
    pub regenerate: bool,
    /// Ascent step when regenerating.
    pub regenerate_step: f64,
    /// Seed of windows, positions, noise and timesteps.
    pub seed: u64,
}

impl Default for FinetuneConfig {
    fn default() -> Self {
        FinetuneConfig {
            steps: 3000,
            lr: 1e-5,
            consistency: 1.0,
            anchor: Anchor::Original,
            clean_features: 0.0,
            clean_task: 0.0,
            batch_size: 16,
            regenerate: false,
            regenerate_step: 1.5e-3,
            seed: 0,
        }
    }
}

impl FinetuneConfig {
    /// Check every field.
    pub fn validate(&self) -> Result<(), PolicyError> {
        if self.steps == 0 {
            return Err(config_err("steps", self.steps, ">= 1"));
        }
        if self.batch_size == 0 {
            return Err(config_err("batch_size", self.batch_size, ">= 1"));
        }
        for (name, v) in [("lr", self.lr), ("regenerate_step", self.regenerate_step)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(config_err(name, v, "a finite value > 0"));
            }
        }
        for (name, v) in [
            ("consistency", self.consistency),
            ("clean_features", self.clean_features),
            ("clean_task", self.clean_task),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(config_err(name, v, "a finite weight >= 0"));
            }
        }
        Ok(())
    }
}

/// What fine-tuning did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FinetuneReport {
    /// Steps run.
    pub steps: usize,
    /// Encoder parameters trained (tensors).
    pub encoder_tensors: usize,
    /// Mean total loss over the first and last up-to-100 steps.
    pub first_loss: f64,
    /// See `first_loss`.
    pub last_loss: f64,
    /// Mean consistency term over the first and last up-to-100 steps.
    pub first_consistency: f64,
    /// See `first_consistency`.
    pub last_consistency: f64,
    /// Mean clean-feature drift `mean ‖f_θ(x) − f_θ0(x)‖²` (unweighted) over the first and
    /// last up-to-100 steps; `None` when the term is off.
    pub first_clean_drift: Option<f64>,
    /// See `first_clean_drift`.
    pub last_clean_drift: Option<f64>,
    /// Mean policy loss under the patch at the regeneration's ascent steps (before each
    /// step's update of the patch) over the first and last up-to-100 steps; `None` when the
    /// patch is not regenerated.
    #[serde(default)]
    pub first_patch_loss: Option<f64>,
    /// See `first_patch_loss`.
    #[serde(default)]
    pub last_patch_loss: Option<f64>,
    /// The clean task term's mean over the first and the last up to 100 steps; `None` when
    /// the term is off.
    #[serde(default)]
    pub first_clean_task_loss: Option<f64>,
    /// See `first_clean_task_loss`.
    #[serde(default)]
    pub last_clean_task_loss: Option<f64>,
    /// The patch at the end (changed only when regenerating), `(3, side, side)`.
    pub texture: Vec<f32>,
}

/// A copy of `policy` whose weights are constants holding the values in `varmap` now.
fn frozen_copy(policy: &DiffusionPolicy, varmap: &VarMap) -> Result<DiffusionPolicy, PolicyError> {
    let weights = crate::train::sorted_vars(varmap, |_| true)?
        .into_iter()
        .map(|(k, v)| Ok((k, v.as_tensor().copy()?)))
        .collect::<Result<std::collections::HashMap<_, _>, candle_core::Error>>()?;
    let vb = candle_nn::VarBuilder::from_tensors(weights, DType::F32, policy.device());
    DiffusionPolicy::new(policy.config().clone(), policy.stats().clone(), vb)
}

/// Fine-tune the image encoder of `policy` (whose weights live in `varmap`, see
/// `checkpoint::load_trainable`) against `texture (3, side, side)`; only variables under
/// `diffusion.rgb_encoder.` change. `after_step(steps done, loss)` is called after every
/// step, with `varmap` holding the weights of that many steps (to save checkpoints along
/// the way); its error stops fine-tuning.
pub fn finetune_encoder(
    policy: &DiffusionPolicy,
    varmap: &VarMap,
    data: &TrainData,
    texture: &[f32],
    side: usize,
    cfg: &FinetuneConfig,
    after_step: &mut dyn FnMut(usize, f64) -> Result<(), PolicyError>,
) -> Result<FinetuneReport, PolicyError> {
    cfg.validate()?;
    let (h, w) = frame_hw(policy)?;
    if texture.len() != 3 * side * side || side > h.min(w) {
        return Err(config_err(
            "texture",
            texture.len(),
            format!("3 x side x side values with side <= {}", h.min(w)),
        ));
    }
    let vars: Vec<Var> =
        crate::train::sorted_vars(varmap, |k| k.starts_with(crate::train::ENCODER_PREFIX))?
            .into_iter()
            .map(|(_, v)| v)
            .collect();
    if vars.is_empty() {
        return Err(config_err(
            "varmap",
            "no diffusion.rgb_encoder.* variables",
            "the policy's trainable weights (checkpoint::load_trainable)",
        ));
    }
    let encoder_tensors = vars.len();
    let cfg_c = policy.config().clone();
    let mut opt = AdamW::new(
        vars,
        ParamsAdamW {
            lr: cfg.lr,
            beta1: cfg_c.optimizer_betas[0],
            beta2: cfg_c.optimizer_betas[1],
            eps: cfg_c.optimizer_eps,
            weight_decay: cfg_c.optimizer_weight_decay,
        },
    )?;
    let win = Windows::new(data, policy.config(), false);
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let dev = policy.device();
    // The original encoder is a constant copy of the whole policy as it is now (only its
    // encoder runs), needed by the `Original` anchor and by the clean-feature term.
    let original = (cfg.anchor == Anchor::Original || cfg.clean_features > 0.0)
        .then(|| frozen_copy(policy, varmap))
        .transpose()?;
    let mut patch = Tensor::from_vec(texture.to_vec(), (3, side, side), dev)?;
    let (mut losses, mut cons, mut drift, mut patch_losses, mut clean_losses) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for step in 0..cfg.steps {
        let b = batch(policy, data, &win, cfg.batch_size, &mut rng)?;
        let clean = images(&b)?;
        let (x, y) = (
            rng.random_range(0..=w - side),
            rng.random_range(0..=h - side),
        );
        if cfg.regenerate {
            let var = Var::from_tensor(&patch)?;
            let loss = loss_with(policy, &b, &paste(clean, var.as_tensor(), x, y)?)?;
            let grads = loss.backward()?;
            patch_losses.push(scalar(&loss)?);
            if let Some(g) = grads.get(var.as_tensor()) {
                patch = ascend(&patch, g, cfg.regenerate_step, Ascent::Sign)?;
            }
        }
        let attacked = paste(clean, &patch, x, y)?;
        // The encoder runs once on the attacked batch: its features feed both terms.
        let f_att = policy.image_features(&attacked)?;
        let task = head_loss(policy, &b, &f_att)?;
        let terms = clean_terms(policy, original.as_ref(), clean, cfg)?;
        let consistency = (f_att - terms.anchor)?.sqr()?.sum(D::Minus1)?.mean_all()?;
        let mut total = (task + (&consistency * cfg.consistency)?)?;
        if let Some(d) = terms.drift {
            total = (total + (&d * cfg.clean_features)?)?;
            drift.push(scalar(&d)?);
        }
        if let (true, Some(f)) = (cfg.clean_task > 0.0, terms.features) {
            let clean_task = head_loss(policy, &b, &f)?;
            total = (total + (&clean_task * cfg.clean_task)?)?;
            clean_losses.push(scalar(&clean_task)?);
        }
        let grads = total.backward()?;
        // Only the encoder's variables are in the optimiser: the denoising head is frozen.
        opt.step(&grads)?;
        let l = scalar(&total)?;
        losses.push(l);
        cons.push(scalar(&consistency)?);
        after_step(step + 1, l)?;
    }
    let ((first_loss, last_loss), (first_consistency, last_consistency)) =
        (first_last(&losses), first_last(&cons));
    let drift = (!drift.is_empty()).then(|| first_last(&drift));
    let patch_loss = (!patch_losses.is_empty()).then(|| first_last(&patch_losses));
    let clean_loss = (!clean_losses.is_empty()).then(|| first_last(&clean_losses));
    Ok(FinetuneReport {
        steps: cfg.steps,
        encoder_tensors,
        first_loss,
        last_loss,
        first_consistency,
        last_consistency,
        first_clean_drift: drift.map(|e| e.0),
        last_clean_drift: drift.map(|e| e.1),
        first_patch_loss: patch_loss.map(|e| e.0),
        last_patch_loss: patch_loss.map(|e| e.1),
        first_clean_task_loss: clean_loss.map(|e| e.0),
        last_clean_task_loss: clean_loss.map(|e| e.1),
        texture: patch.flatten_all()?.to_vec1::<f32>()?,
    })
}

/// What the clean frames give the loss: the clean embedding the consistency term ties the
/// patched one to (detached); the clean-feature drift `mean ‖f_θ(x) − f_θ0(x)‖²` when that
/// term is on; and the tuned encoder's clean features (with their gradient) when the
/// clean-feature or the clean task term needs them.
struct CleanTerms {
    anchor: Tensor,
    drift: Option<Tensor>,
    features: Option<Tensor>,
}

/// [`CleanTerms`]; `original` is the frozen copy from before fine-tuning, present when the
/// anchor or the clean-feature term needs it.
fn clean_terms(
    policy: &DiffusionPolicy,
    original: Option<&DiffusionPolicy>,
    clean: &Tensor,
    cfg: &FinetuneConfig,
) -> Result<CleanTerms, PolicyError> {
    let keep_clean = cfg.clean_features > 0.0;
    let f_orig = original
        .map(|o| o.image_features(clean).map(|f| f.detach()))
        .transpose()?;
    let f_now = (keep_clean || cfg.clean_task > 0.0 || cfg.anchor == Anchor::Current)
        .then(|| policy.image_features(clean))
        .transpose()?;
    let anchor = match cfg.anchor {
        Anchor::Original => f_orig.clone(),
        Anchor::Current => f_now.as_ref().map(Tensor::detach),
    }
    .ok_or_else(|| config_err("anchor", cfg.anchor, "a clean embedding"))?;
    let drift = match (keep_clean, &f_now, f_orig) {
        (true, Some(now), Some(orig)) => Some((now - orig)?.sqr()?.sum(D::Minus1)?.mean_all()?),
        _ => None,
    };
    Ok(CleanTerms {
        anchor,
        drift,
        features: f_now,
    })
}

/// A scalar tensor's value as f64.
fn scalar(t: &Tensor) -> Result<f64, PolicyError> {
    Ok(f64::from(t.to_dtype(DType::F32)?.to_scalar::<f32>()?))
}

/// Means over the first and the last up-to-100 values (0 for none).
fn first_last(v: &[f64]) -> (f64, f64) {
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let k = v.len().min(100);
    (mean(&v[..k]), mean(&v[v.len() - k..]))
}

/// The gradient probe's figures (means over the probed batches).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProbeReport {
    /// Batches probed.
    pub batches: usize,
    /// Cosine between d loss / d pixels through the original and the tuned policy, at the
    /// patched frames (the paper's probe: same observations, same patch).
    pub cosine: f64,
    /// ‖∇ tuned‖ / ‖∇ original‖ at the patched frames.
    pub grad_norm_ratio: f64,
    /// The cosine over the patch's own pixels only: the gradient the patch optimiser sees.
    pub patch_cosine: f64,
    /// ‖∇ tuned‖ / ‖∇ original‖ over the patch's own pixels.
    pub patch_grad_norm_ratio: f64,
    /// The full-frame cosine at the clean frames (the patch absent), for comparison.
    pub clean_cosine: f64,
    /// ‖∇ tuned‖ / ‖∇ original‖ at the clean frames.
    pub clean_grad_norm_ratio: f64,
    /// ‖f_tuned(x ⊕ patch) − f_tuned(x)‖ / ‖f_orig(x ⊕ patch) − f_orig(x)‖.
    pub latent_displacement_ratio: f64,
}

/// Running sums of a probe's cosine and norm ratio over batches.
#[derive(Default)]
struct Agreement {
    cosine: f64,
    ratio: f64,
}

impl Agreement {
    /// Adds the cosine and norm ratio of `tuned` against `original`.
    fn add(&mut self, original: &[f64], tuned: &[f64]) {
        let dot: f64 = original.iter().zip(tuned).map(|(a, b)| a * b).sum();
        let (no, nt) = (norm(original), norm(tuned));
        self.cosine += dot / (no * nt).max(f64::MIN_POSITIVE);
        self.ratio += nt / no.max(f64::MIN_POSITIVE);
    }
}

/// A trained patch at its place in the frame: `texture` is `3 x side x side` CHW in
/// `[0, 1]`, `origin` its top-left pixel `(x, y)` in the uncropped frame.
#[derive(Clone, Copy, Debug)]
pub struct PlacedPatch<'a> {
    /// The texture.
    pub texture: &'a [f32],
    /// Side (px).
    pub side: usize,
    /// Top-left pixel `(x, y)`.
    pub origin: (usize, usize),
}

/// How many windows the probe averages over, and its seed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProbeConfig {
    /// Batches.
    pub batches: usize,
    /// Windows per batch.
    pub batch_size: usize,
    /// Seed of the windows, noise and timesteps.
    pub seed: u64,
}

/// Probe `original` against `tuned` on `cfg.batches` batches of `cfg.batch_size` windows,
/// with the patch at its trained place.
pub fn gradient_probe(
    original: &DiffusionPolicy,
    tuned: &DiffusionPolicy,
    data: &TrainData,
    placed: PlacedPatch<'_>,
    cfg: ProbeConfig,
) -> Result<ProbeReport, PolicyError> {
    let PlacedPatch {
        texture,
        side,
        origin,
    } = placed;
    let ProbeConfig {
        batches,
        batch_size,
        seed,
    } = cfg;
    if batches == 0 || batch_size == 0 {
        return Err(config_err("batches", (batches, batch_size), ">= 1 each"));
    }
    frame_hw(original)?;
    frame_hw(tuned)?;
    let win = Windows::new(data, original.config(), false);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let patch = Tensor::from_vec(texture.to_vec(), (3, side, side), original.device())?;
    let (mut patched, mut on_patch, mut clean_only) = (
        Agreement::default(),
        Agreement::default(),
        Agreement::default(),
    );
    let mut disp = 0.0;
    let flat = |t: &Tensor| -> Result<Vec<f64>, PolicyError> {
        Ok(t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?)
    };
    let (x, y) = origin;
    for _ in 0..batches {
        let b = batch(original, data, &win, batch_size, &mut rng)?;
        let clean = images(&b)?;
        let attacked = paste(clean, &patch, x, y)?;
        let grad = |p: &DiffusionPolicy, imgs: &Tensor| -> Result<Tensor, PolicyError> {
            let obs = ObsBatch {
                image: Some(imgs.clone()),
                ..b.obs.clone()
            };
            let (_, g) = p.observation_gradient(&obs, &b.x0, &b.eps, &b.ts)?;
            g.image
                .ok_or_else(|| config_err("image", "none", "an image gradient"))
        };
        let (go, gt) = (grad(original, &attacked)?, grad(tuned, &attacked)?);
        patched.add(&flat(&go)?, &flat(&gt)?);
        let cut = |g: &Tensor| -> Result<Vec<f64>, PolicyError> {
            flat(&g.narrow(2, y, side)?.narrow(3, x, side)?)
        };
        on_patch.add(&cut(&go)?, &cut(&gt)?);
        clean_only.add(
            &flat(&grad(original, clean)?)?,
            &flat(&grad(tuned, clean)?)?,
        );
        let shift = |p: &DiffusionPolicy| -> Result<f64, PolicyError> {
            let d = (p.image_features(&attacked)? - p.image_features(clean)?)?;
            Ok(norm(&flat(&d)?))
        };
        disp += shift(tuned)? / shift(original)?.max(f64::MIN_POSITIVE);
    }
    let n = batches as f64;
    Ok(ProbeReport {
        batches,
        cosine: patched.cosine / n,
        grad_norm_ratio: patched.ratio / n,
        patch_cosine: on_patch.cosine / n,
        patch_grad_norm_ratio: on_patch.ratio / n,
        clean_cosine: clean_only.cosine / n,
        clean_grad_norm_ratio: clean_only.ratio / n,
        latent_displacement_ratio: disp / n,
    })
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}
