//! DDPM and DDIM noise schedulers for Diffusion Policy, matching Hugging Face `diffusers`
//! 0.35.2 (`DDPMScheduler`, `DDIMScheduler`) as LeRobot configures them.
//!
//! This module works on plain `f32` slices (any length, any layout: the schedulers act
//! element-wise), so it does not depend on a tensor library.
//!
//! # Conventions
//!
//! * Timesteps are **training-timestep indices** `t` in `0..num_train_timesteps` (`N`);
//!   `t = 0` is the least noisy level. `alphas_cumprod[t]` is `ᾱ_t = Π_{i<=t} (1 - β_i)`.
//! * Inference uses diffusers' `"leading"` spacing with `steps_offset = 0`: with `n`
//!   inference steps, `step_ratio = N / n` (integer division) and the sampler visits
//!   `(n-1)·step_ratio, …, step_ratio, 0`. One reverse step goes from `t` to
//!   `t_prev = t - step_ratio`; when `t_prev < 0` the previous `ᾱ` is `1` (DDPM, and DDIM with
//!   `set_alpha_to_one`) or `ᾱ_0` (DDIM without it).
//! * DDPM uses `variance_type = "fixed_small"` (posterior variance
//!   `β̃_t = (1-ᾱ_prev)/(1-ᾱ_t)·(1-ᾱ_t/ᾱ_prev)`, clamped below at `1e-20`); no thresholding,
//!   no zero-SNR rescaling.
//!
//! # Precision
//!
//! diffusers keeps its tables in `float32` torch tensors and does every step in `float32`.
//! We do the same, so the results agree to float32 rounding:
//!
//! * `squaredcos_cap_v2` betas are evaluated in `f64` with the same formula and operation
//!   order as diffusers' Python code and then rounded to `f32` (diffusers builds the list in
//!   Python floats and converts it with `torch.tensor(..., dtype=float32)`).
//!   `linear` / `scaled_linear` betas are the `f64` linspace rounded to `f32`; torch's `f32`
//!   `linspace` kernel rounds some entries differently (its result even depends on the CPU's
//!   vector width), so those two schedules agree with diffusers to ~2 `f32` ulps.
//! * `alphas = 1 - betas` in `f32`; `alphas_cumprod` is a running product accumulated in
//!   `f64` and rounded to `f32` at every entry, which is exactly what torch's CPU `cumprod`
//!   does for `float32`. With the cosine schedule both tables are therefore bit-identical to
//!   diffusers'.
//! * [`Scheduler::step`] and [`Scheduler::add_noise`] evaluate diffusers' expressions in
//!   `f32` in the same order (IEEE `+ - * /` are correctly rounded, and Rust never contracts
//!   them into FMAs). They are not bit-identical: torch's CPU `float32` `sqrt` is not
//!   correctly rounded (off by one ulp for ~20% of inputs on the machine that generated the
//!   reference), while `f32::sqrt` is. Measured against diffusers 0.35.2: outputs differ by at
//!   most ~1 ulp of the vector's largest element (normwise 2.3e-7), except where diffusers'
//!   own formula cancels (DDIM with `eta > 0` right after the capped `β = 0.999` step:
//!   2.6e-6).
//!
//! The public tables ([`Scheduler::betas`], [`Scheduler::alphas_cumprod`]) are returned as
//! `f64` for convenience; every entry is exactly an `f32` value.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Largest accepted `num_train_timesteps` (keeps the precomputed tables bounded).
pub const MAX_TRAIN_TIMESTEPS: usize = 1_000_000;

/// Cap on squaredcos betas, diffusers' `max_beta` default.
const MAX_BETA: f64 = 0.999;

/// Lower clamp of the DDPM posterior variance, diffusers' `torch.clamp(variance, min=1e-20)`.
const MIN_VARIANCE: f32 = 1e-20;

/// Noise-level (beta) schedule, named as in diffusers' `beta_schedule`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BetaSchedule {
    /// Improved-DDPM cosine schedule ("Glide cosine"): `β_i = min(1 - ᾱ((i+1)/N)/ᾱ(i/N), 0.999)`
    /// with `ᾱ(s) = cos((s + 0.008)/1.008 · π/2)²`. Ignores `beta_start` / `beta_end`.
    SquaredcosCapV2,
    /// `β_i` evenly spaced from `beta_start` to `beta_end` (inclusive).
    Linear,
    /// `sqrt(β_i)` evenly spaced from `sqrt(beta_start)` to `sqrt(beta_end)` (latent diffusion).
    ScaledLinear,
}

/// What the denoising network predicts, diffusers' `prediction_type`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PredictionType {
    /// The network predicts the added noise `ε` (LeRobot's PushT setting).
    Epsilon,
    /// The network predicts the clean sample `x_0` directly.
    Sample,
}

/// Which reverse-process update [`Scheduler::step`] applies.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SchedulerKind {
    /// Ancestral DDPM sampling (diffusers `DDPMScheduler`, `fixed_small` variance).
    Ddpm,
    /// DDIM sampling (diffusers `DDIMScheduler`); deterministic when `eta = 0`.
    Ddim,
}

/// Scheduler hyper-parameters, mirroring the diffusers constructor arguments LeRobot passes
/// (`num_train_timesteps`, `beta_start`, `beta_end`, `beta_schedule`, `clip_sample`,
/// `clip_sample_range`, `prediction_type`) plus DDIM's `set_alpha_to_one` and `eta`.
///
/// Serialised with snake_case enum names (`"ddpm"`, `"squaredcos_cap_v2"`, `"epsilon"`, …);
/// `set_alpha_to_one` defaults to `true` and `eta` to `0.0` when absent.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SchedulerConfig {
    /// DDPM or DDIM update rule.
    pub kind: SchedulerKind,
    /// Number of training diffusion steps `N` (table length), `1..=MAX_TRAIN_TIMESTEPS`.
    pub num_train_timesteps: usize,
    /// First beta of the `linear` / `scaled_linear` schedules (dimensionless, in `(0, 1)`).
    pub beta_start: f64,
    /// Last beta of the `linear` / `scaled_linear` schedules (dimensionless, in `[beta_start, 1)`).
    pub beta_end: f64,
    /// Shape of the beta schedule.
    pub beta_schedule: BetaSchedule,
    /// Meaning of the network output passed to [`Scheduler::step`].
    pub prediction_type: PredictionType,
    /// Clamp the predicted `x_0` to `[-clip_sample_range, clip_sample_range]` in every step.
    pub clip_sample: bool,
    /// Half-width of the `x_0` clamp (same units as the samples); must be `> 0` when clipping.
    pub clip_sample_range: f64,
    /// DDIM only: use `ᾱ = 1` (instead of `ᾱ_0`) as the "previous" level of the final step.
    #[serde(default = "default_true")]
    pub set_alpha_to_one: bool,
    /// DDIM only: stochasticity `η` in `[0, 1]` (`0` = deterministic DDIM, `1` = DDPM-like
    /// variance). diffusers' `step(eta=...)` argument; LeRobot never passes it, so `0`.
    #[serde(default)]
    pub eta: f64,
}

fn default_true() -> bool {
    true
}

impl SchedulerConfig {
    /// LeRobot's `diffusion_pusht` noise scheduler: DDPM, `N = 100`, `squaredcos_cap_v2`,
    /// epsilon prediction, `clip_sample = true` with range `1.0` (`beta_start = 1e-4` and
    /// `beta_end = 0.02` are carried along but ignored by the cosine schedule). The DDIM
    /// fields hold diffusers' defaults (`set_alpha_to_one = true`, `eta = 0`), so setting
    /// `kind = SchedulerKind::Ddim` gives LeRobot's `noise_scheduler_type = "DDIM"`.
    pub fn lerobot_pusht() -> Self {
        Self {
            kind: SchedulerKind::Ddpm,
            num_train_timesteps: 100,
            beta_start: 1e-4,
            beta_end: 0.02,
            beta_schedule: BetaSchedule::SquaredcosCapV2,
            prediction_type: PredictionType::Epsilon,
            clip_sample: true,
            clip_sample_range: 1.0,
            set_alpha_to_one: true,
            eta: 0.0,
        }
    }

    /// Checks the hyper-parameters without building tables: `N` in `1..=MAX_TRAIN_TIMESTEPS`;
    /// `beta_start`, `beta_end`, `clip_sample_range`, `eta` finite; for `linear` /
    /// `scaled_linear`, `0 < beta_start <= beta_end < 1`; `clip_sample_range > 0` when
    /// `clip_sample`; `0 <= eta <= 1`. [`Scheduler::new`] additionally rejects schedules whose
    /// `f32` tables degenerate (some `ᾱ_t` rounds to `0` or `1`).
    pub fn validate(&self) -> Result<(), SchedulerError> {
        if self.num_train_timesteps == 0 || self.num_train_timesteps > MAX_TRAIN_TIMESTEPS {
            return Err(SchedulerError::InvalidTrainTimesteps {
                num_train_timesteps: self.num_train_timesteps,
                max: MAX_TRAIN_TIMESTEPS,
            });
        }
        for (name, value) in [
            ("beta_start", self.beta_start),
            ("beta_end", self.beta_end),
            ("clip_sample_range", self.clip_sample_range),
            ("eta", self.eta),
        ] {
            if !value.is_finite() {
                return Err(SchedulerError::NonFinite { name, value });
            }
        }
        if self.beta_schedule != BetaSchedule::SquaredcosCapV2
            && !(self.beta_start > 0.0 && self.beta_start <= self.beta_end && self.beta_end < 1.0)
        {
            return Err(SchedulerError::InvalidBetaRange {
                beta_start: self.beta_start,
                beta_end: self.beta_end,
            });
        }
        if self.clip_sample && self.clip_sample_range <= 0.0 {
            return Err(SchedulerError::InvalidClipRange {
                clip_sample_range: self.clip_sample_range,
            });
        }
        if !(0.0..=1.0).contains(&self.eta) {
            return Err(SchedulerError::InvalidEta { eta: self.eta });
        }
        Ok(())
    }
}

/// Everything that can go wrong building or using a [`Scheduler`]; each variant names the
/// offending values.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum SchedulerError {
    /// `num_train_timesteps` is zero or above [`MAX_TRAIN_TIMESTEPS`].
    #[error("num_train_timesteps = {num_train_timesteps}: expected 1..={max}")]
    InvalidTrainTimesteps {
        /// The rejected value.
        num_train_timesteps: usize,
        /// [`MAX_TRAIN_TIMESTEPS`].
        max: usize,
    },
    /// A floating-point hyper-parameter is NaN or infinite.
    #[error("{name} = {value}: expected a finite number")]
    NonFinite {
        /// Field name.
        name: &'static str,
        /// The rejected value.
        value: f64,
    },
    /// `linear` / `scaled_linear` need `0 < beta_start <= beta_end < 1`.
    #[error(
        "beta_start = {beta_start}, beta_end = {beta_end}: linear schedules need \
         0 < beta_start <= beta_end < 1"
    )]
    InvalidBetaRange {
        /// The configured `beta_start`.
        beta_start: f64,
        /// The configured `beta_end`.
        beta_end: f64,
    },
    /// Clipping is on but the range is not positive.
    #[error("clip_sample_range = {clip_sample_range}: expected > 0 when clip_sample is true")]
    InvalidClipRange {
        /// The rejected value.
        clip_sample_range: f64,
    },
    /// `eta` outside `[0, 1]`.
    #[error("eta = {eta}: expected 0 <= eta <= 1")]
    InvalidEta {
        /// The rejected value.
        eta: f64,
    },
    /// The `f32` table has `ᾱ_t` equal to `0` or `1` at `t`, which would divide by zero in
    /// a step (too many timesteps or too small / too large betas for `f32`).
    #[error(
        "degenerate schedule: alphas_cumprod[{t}] = {alpha_cumprod} in f32, expected \
         0 < alphas_cumprod < 1 (beta[{t}] = {beta})"
    )]
    DegenerateSchedule {
        /// First offending timestep.
        t: usize,
        /// `ᾱ_t` there (an `f32` value).
        alpha_cumprod: f64,
        /// `β_t` there (an `f32` value).
        beta: f64,
    },
    /// `num_inference_steps = 0`.
    #[error("num_inference_steps = 0: expected at least 1")]
    ZeroInferenceSteps,
    /// More inference steps than training steps (diffusers rejects this too).
    #[error(
        "num_inference_steps = {num_inference_steps} exceeds num_train_timesteps = \
         {num_train_timesteps}"
    )]
    TooManyInferenceSteps {
        /// The requested inference step count.
        num_inference_steps: usize,
        /// `N`.
        num_train_timesteps: usize,
    },
    /// `t >= num_train_timesteps`.
    #[error(
        "timestep t = {t} out of range: expected t < num_train_timesteps = {num_train_timesteps}"
    )]
    TimestepOutOfRange {
        /// The rejected timestep.
        t: usize,
        /// `N`.
        num_train_timesteps: usize,
    },
    /// DDPM only: `t` is not one of the `num_inference_steps` timesteps (diffusers looks `t`
    /// up in its timestep list and fails otherwise).
    #[error(
        "timestep t = {t} is not a DDPM inference timestep for num_inference_steps = \
         {num_inference_steps} (multiples of step_ratio = {step_ratio} up to {last})"
    )]
    TimestepNotInSchedule {
        /// The rejected timestep.
        t: usize,
        /// The inference step count.
        num_inference_steps: usize,
        /// `N / num_inference_steps`.
        step_ratio: usize,
        /// The largest valid timestep, `(num_inference_steps - 1) * step_ratio`.
        last: usize,
    },
    /// A slice argument has the wrong length.
    #[error("{name} has {actual} elements, expected {expected}")]
    LengthMismatch {
        /// Argument name (`model_output`, `noise`, `out`, …).
        name: &'static str,
        /// Required length (the length of `sample` / `x0`).
        expected: usize,
        /// Given length.
        actual: usize,
    },
}

/// A DDPM or DDIM scheduler with precomputed `f32` tables (see the module docs for the
/// precision contract). Cheap to clone; immutable after construction, so one instance can
/// serve any number of concurrent samplers and any inference step count.
#[derive(Clone, Debug)]
pub struct Scheduler {
    config: SchedulerConfig,
    /// `β_t`, `f32` values widened to `f64`.
    betas: Vec<f64>,
    /// `ᾱ_t`, `f32` values widened to `f64`.
    alphas_cumprod: Vec<f64>,
    /// `ᾱ_t` in `f32`, used by the step arithmetic.
    abar: Vec<f32>,
}

/// Per-step scalars shared by every element.
#[derive(Clone, Copy, Debug)]
struct StepCoefficients {
    /// `sqrt(1 - ᾱ_t)`.
    sqrt_beta_prod_t: f32,
    /// `sqrt(ᾱ_t)`.
    sqrt_alpha_prod_t: f32,
    /// DDPM: coefficient of `x̂_0`; DDIM: `sqrt(ᾱ_prev)`.
    c_x0: f32,
    /// DDPM: coefficient of `x_t`; DDIM: coefficient of `ε̂` (`sqrt(1 - ᾱ_prev - σ²)`).
    c_other: f32,
    /// Standard deviation multiplying `noise`, or `None` when the step adds no noise.
    noise_std: Option<f32>,
}

impl Scheduler {
    /// Validates `config` and precomputes the `f32` tables.
    ///
    /// # Errors
    /// Any [`SchedulerConfig::validate`] error, or [`SchedulerError::DegenerateSchedule`]
    /// when some `ᾱ_t` rounds to `0` or `1` in `f32`.
    pub fn new(config: SchedulerConfig) -> Result<Self, SchedulerError> {
        config.validate()?;
        let n = config.num_train_timesteps;
        let betas32: Vec<f32> = match config.beta_schedule {
            BetaSchedule::SquaredcosCapV2 => (0..n).map(|i| cosine_beta(i, n) as f32).collect(),
            BetaSchedule::Linear => linspace(config.beta_start, config.beta_end, n)
                .map(|b| b as f32)
                .collect(),
            BetaSchedule::ScaledLinear => {
                linspace(config.beta_start.sqrt(), config.beta_end.sqrt(), n)
                    .map(|s| (s * s) as f32)
                    .collect()
            }
        };
        // torch.cumprod on CPU accumulates float32 inputs in a double and rounds each output.
        let mut acc = 1.0_f64;
        let mut abar = Vec::with_capacity(n);
        for (t, &beta) in betas32.iter().enumerate() {
            let alpha = 1.0_f32 - beta;
            acc *= f64::from(alpha);
            let a = acc as f32;
            if !(a > 0.0 && a < 1.0) {
                return Err(SchedulerError::DegenerateSchedule {
                    t,
                    alpha_cumprod: f64::from(a),
                    beta: f64::from(beta),
                });
            }
            abar.push(a);
        }
        Ok(Self {
            betas: betas32.iter().map(|&b| f64::from(b)).collect(),
            alphas_cumprod: abar.iter().map(|&a| f64::from(a)).collect(),
            abar,
            config,
        })
    }

    /// The configuration this scheduler was built from.
    pub fn config(&self) -> &SchedulerConfig {
        &self.config
    }

    /// Number of training timesteps `N` (length of the tables).
    pub fn num_train_timesteps(&self) -> usize {
        self.config.num_train_timesteps
    }

    /// `β_t` for `t in 0..N` (dimensionless; exact `f32` values as `f64`).
    pub fn betas(&self) -> &[f64] {
        &self.betas
    }

    /// `ᾱ_t = Π_{i<=t}(1 - β_i)` for `t in 0..N`, strictly inside `(0, 1)` and non-increasing
    /// (exact `f32` values as `f64`).
    pub fn alphas_cumprod(&self) -> &[f64] {
        &self.alphas_cumprod
    }

    /// The inference timesteps for `num_inference_steps` (diffusers `set_timesteps` with
    /// `"leading"` spacing, `steps_offset = 0`): `step_ratio = N / num_inference_steps`
    /// (integer division) and the result is `(0..num_inference_steps).rev()` times
    /// `step_ratio`, i.e. descending and ending at `0`. When `N` is not a multiple of
    /// `num_inference_steps` the first timestep is below `N - 1` (e.g. `N = 100`, `n = 30`
    /// starts at 87), as in diffusers.
    ///
    /// # Errors
    /// [`SchedulerError::ZeroInferenceSteps`], [`SchedulerError::TooManyInferenceSteps`].
    pub fn timesteps(&self, num_inference_steps: usize) -> Result<Vec<usize>, SchedulerError> {
        let ratio = self.step_ratio(num_inference_steps)?;
        Ok((0..num_inference_steps).rev().map(|k| k * ratio).collect())
    }

    /// The timestep a reverse step from `t` lands on: `Some(t - N / num_inference_steps)`, or
    /// `None` when that is negative (the step produces the final, clean sample). Validates
    /// `t` like [`Scheduler::step`] does.
    ///
    /// # Errors
    /// As [`Scheduler::step`] for bad step counts and timesteps.
    pub fn previous_timestep(
        &self,
        t: usize,
        num_inference_steps: usize,
    ) -> Result<Option<usize>, SchedulerError> {
        let ratio = self.check_timestep(t, num_inference_steps)?;
        Ok(t.checked_sub(ratio))
    }

    /// Whether [`Scheduler::step`] at `t` consumes its `noise` argument: DDPM for `t > 0`,
    /// DDIM whenever `eta > 0`. When `false`, `step` accepts an empty `noise` slice, so a
    /// sampler can skip drawing it.
    ///
    /// # Errors
    /// As [`Scheduler::step`] for bad step counts and timesteps.
    pub fn step_adds_noise(
        &self,
        t: usize,
        num_inference_steps: usize,
    ) -> Result<bool, SchedulerError> {
        self.check_timestep(t, num_inference_steps)?;
        Ok(self.adds_noise(t))
    }

    /// One reverse step in place: `sample` holds `x_t` on entry and `x_{t_prev}` on return,
    /// where `t_prev = t - N / num_inference_steps` (see [`Scheduler::previous_timestep`]).
    ///
    /// `model_output` is the network output for `(x_t, t)` (`ε̂` or `x̂_0` according to
    /// `prediction_type`) and must have `sample`'s length. `noise` holds standard-normal
    /// draws of the same length; it is used when the step adds noise (DDPM with `t > 0`,
    /// scaled by the `fixed_small` standard deviation; DDIM with `eta > 0`, scaled by
    /// `eta · σ_t`) and may then not be empty; otherwise it is ignored and may be empty (a
    /// non-empty `noise` must always have `sample`'s length). See
    /// [`Scheduler::step_adds_noise`].
    ///
    /// Matches diffusers `DDPMScheduler.step` / `DDIMScheduler.step(eta=config.eta,
    /// use_clipped_model_output=False, variance_noise=noise)` after `set_timesteps(n)`,
    /// including the clamp of `x̂_0` when `clip_sample`. DDPM requires `t` to be one of
    /// [`Scheduler::timesteps`]`(n)` (diffusers fails otherwise); DDIM accepts any `t < N`,
    /// like diffusers. The only deliberate difference: DDIM's `sqrt(1 - ᾱ_prev - σ²)` is
    /// taken of `max(·, 0)` where rounding could make it negative (diffusers would return
    /// NaN there). Non-finite inputs propagate (no error).
    ///
    /// # Errors
    /// [`SchedulerError::ZeroInferenceSteps`], [`SchedulerError::TooManyInferenceSteps`],
    /// [`SchedulerError::TimestepOutOfRange`], [`SchedulerError::TimestepNotInSchedule`]
    /// (DDPM), [`SchedulerError::LengthMismatch`]. On error `sample` is untouched.
    pub fn step(
        &self,
        model_output: &[f32],
        t: usize,
        num_inference_steps: usize,
        sample: &mut [f32],
        noise: &[f32],
    ) -> Result<(), SchedulerError> {
        let ratio = self.check_timestep(t, num_inference_steps)?;
        let len = sample.len();
        check_len("model_output", len, model_output.len())?;
        let uses_noise = self.adds_noise(t);
        if uses_noise || !noise.is_empty() {
            check_len("noise", len, noise.len())?;
        }
        let prev = t.checked_sub(ratio);
        let c = match self.config.kind {
            SchedulerKind::Ddpm => self.ddpm_coefficients(t, prev),
            SchedulerKind::Ddim => self.ddim_coefficients(t, prev),
        };
        let clip = self
            .config
            .clip_sample
            .then_some(self.config.clip_sample_range as f32);
        let kind = self.config.kind;
        let prediction = self.config.prediction_type;
        for (i, (x, &out)) in sample.iter_mut().zip(model_output).enumerate() {
            let xt = *x;
            // x̂_0 and (DDIM) ε̂, in diffusers' operation order.
            let (x0, eps) = match prediction {
                PredictionType::Epsilon => {
                    ((xt - c.sqrt_beta_prod_t * out) / c.sqrt_alpha_prod_t, out)
                }
                PredictionType::Sample => {
                    (out, (xt - c.sqrt_alpha_prod_t * out) / c.sqrt_beta_prod_t)
                }
            };
            let x0 = match clip {
                Some(r) => clamp_f32(x0, -r, r),
                None => x0,
            };
            let mut next = match kind {
                SchedulerKind::Ddpm => c.c_x0 * x0 + c.c_other * xt,
                SchedulerKind::Ddim => c.c_x0 * x0 + c.c_other * eps,
            };
            if let (Some(std), Some(&z)) = (c.noise_std, noise.get(i)) {
                next += std * z;
            }
            *x = next;
        }
        Ok(())
    }

    /// Forward (noising) process for training: `out = sqrt(ᾱ_t)·x0 + sqrt(1 - ᾱ_t)·noise`
    /// element-wise, in `f32` exactly as diffusers' `add_noise`. `x0`, `noise` and `out`
    /// must have equal lengths; `t < N`.
    ///
    /// # Errors
    /// [`SchedulerError::TimestepOutOfRange`], [`SchedulerError::LengthMismatch`] (then `out`
    /// is untouched).
    pub fn add_noise(
        &self,
        x0: &[f32],
        noise: &[f32],
        t: usize,
        out: &mut [f32],
    ) -> Result<(), SchedulerError> {
        let a = self.abar_at(t)?;
        check_len("noise", x0.len(), noise.len())?;
        check_len("out", x0.len(), out.len())?;
        let sqrt_a = a.sqrt();
        let sqrt_one_minus_a = (1.0_f32 - a).sqrt();
        for ((o, &x), &z) in out.iter_mut().zip(x0).zip(noise) {
            *o = sqrt_a * x + sqrt_one_minus_a * z;
        }
        Ok(())
    }

    fn step_ratio(&self, num_inference_steps: usize) -> Result<usize, SchedulerError> {
        let n = self.config.num_train_timesteps;
        if num_inference_steps == 0 {
            return Err(SchedulerError::ZeroInferenceSteps);
        }
        if num_inference_steps > n {
            return Err(SchedulerError::TooManyInferenceSteps {
                num_inference_steps,
                num_train_timesteps: n,
            });
        }
        Ok(n / num_inference_steps)
    }

    /// Validates `(t, num_inference_steps)` and returns the step ratio.
    fn check_timestep(
        &self,
        t: usize,
        num_inference_steps: usize,
    ) -> Result<usize, SchedulerError> {
        let ratio = self.step_ratio(num_inference_steps)?;
        let n = self.config.num_train_timesteps;
        if t >= n {
            return Err(SchedulerError::TimestepOutOfRange {
                t,
                num_train_timesteps: n,
            });
        }
        if self.config.kind == SchedulerKind::Ddpm {
            let last = (num_inference_steps - 1) * ratio;
            if !t.is_multiple_of(ratio) || t > last {
                return Err(SchedulerError::TimestepNotInSchedule {
                    t,
                    num_inference_steps,
                    step_ratio: ratio,
                    last,
                });
            }
        }
        Ok(ratio)
    }

    fn adds_noise(&self, t: usize) -> bool {
        match self.config.kind {
            SchedulerKind::Ddpm => t > 0,
            SchedulerKind::Ddim => self.config.eta > 0.0,
        }
    }

    fn abar_at(&self, t: usize) -> Result<f32, SchedulerError> {
        self.abar
            .get(t)
            .copied()
            .ok_or(SchedulerError::TimestepOutOfRange {
                t,
                num_train_timesteps: self.config.num_train_timesteps,
            })
    }

    /// `ᾱ_t` and the previous level (`prev = None`: `1`, or `ᾱ_0` for DDIM without
    /// `set_alpha_to_one`). `t` and `prev` are already validated, so the lookups succeed;
    /// the fallbacks only keep this total.
    fn alpha_pair(&self, t: usize, prev: Option<usize>, final_alpha: f32) -> (f32, f32) {
        let a_t = self.abar.get(t).copied().unwrap_or(1.0);
        let a_prev = match prev {
            Some(p) => self.abar.get(p).copied().unwrap_or(1.0),
            None => final_alpha,
        };
        (a_t, a_prev)
    }

    /// diffusers `DDPMScheduler.step` scalars (`fixed_small` variance).
    fn ddpm_coefficients(&self, t: usize, prev: Option<usize>) -> StepCoefficients {
        let (alpha_prod_t, alpha_prod_t_prev) = self.alpha_pair(t, prev, 1.0);
        let beta_prod_t = 1.0_f32 - alpha_prod_t;
        let beta_prod_t_prev = 1.0_f32 - alpha_prod_t_prev;
        let current_alpha_t = alpha_prod_t / alpha_prod_t_prev;
        let current_beta_t = 1.0_f32 - current_alpha_t;
        let noise_std = (t > 0).then(|| {
            let variance =
                (1.0_f32 - alpha_prod_t_prev) / (1.0_f32 - alpha_prod_t) * current_beta_t;
            max_f32(variance, MIN_VARIANCE).sqrt()
        });
        StepCoefficients {
            sqrt_beta_prod_t: beta_prod_t.sqrt(),
            sqrt_alpha_prod_t: alpha_prod_t.sqrt(),
            c_x0: (alpha_prod_t_prev.sqrt() * current_beta_t) / beta_prod_t,
            c_other: current_alpha_t.sqrt() * beta_prod_t_prev / beta_prod_t,
            noise_std,
        }
    }

    /// diffusers `DDIMScheduler.step` scalars.
    fn ddim_coefficients(&self, t: usize, prev: Option<usize>) -> StepCoefficients {
        let final_alpha = if self.config.set_alpha_to_one {
            1.0
        } else {
            self.abar.first().copied().unwrap_or(1.0)
        };
        let (alpha_prod_t, alpha_prod_t_prev) = self.alpha_pair(t, prev, final_alpha);
        let beta_prod_t = 1.0_f32 - alpha_prod_t;
        let beta_prod_t_prev = 1.0_f32 - alpha_prod_t_prev;
        let variance =
            (beta_prod_t_prev / beta_prod_t) * (1.0_f32 - alpha_prod_t / alpha_prod_t_prev);
        let eta = self.config.eta as f32;
        let std_dev_t = eta * variance.sqrt();
        let direction_sq = 1.0_f32 - alpha_prod_t_prev - std_dev_t * std_dev_t;
        StepCoefficients {
            sqrt_beta_prod_t: beta_prod_t.sqrt(),
            sqrt_alpha_prod_t: alpha_prod_t.sqrt(),
            c_x0: alpha_prod_t_prev.sqrt(),
            c_other: max_f32(direction_sq, 0.0).sqrt(),
            noise_std: (self.config.eta > 0.0).then_some(std_dev_t),
        }
    }
}

/// diffusers' `betas_for_alpha_bar(N)` (cosine), term `i`, in `f64` with Python's operation
/// order: `min(1 - ᾱ((i+1)/N) / ᾱ(i/N), 0.999)`.
fn cosine_beta(i: usize, n: usize) -> f64 {
    fn alpha_bar(s: f64) -> f64 {
        let c = ((s + 0.008) / 1.008 * std::f64::consts::PI / 2.0).cos();
        c * c
    }
    let t1 = i as f64 / n as f64;
    let t2 = (i + 1) as f64 / n as f64;
    (1.0 - alpha_bar(t2) / alpha_bar(t1)).min(MAX_BETA)
}

/// `n` evenly spaced `f64` values from `start` to `end` inclusive (`[start]` when `n == 1`).
fn linspace(start: f64, end: f64, n: usize) -> impl Iterator<Item = f64> {
    let step = if n > 1 {
        (end - start) / (n - 1) as f64
    } else {
        0.0
    };
    (0..n).map(move |i| {
        if i + 1 == n && n > 1 {
            end
        } else {
            start + step * i as f64
        }
    })
}

/// `torch.clamp` semantics for ordered, finite bounds: NaN stays NaN.
fn clamp_f32(x: f32, lo: f32, hi: f32) -> f32 {
    if x < lo {
        lo
    } else if x > hi {
        hi
    } else {
        x
    }
}

/// `torch.clamp(x, min=lo)`: NaN stays NaN.
fn max_f32(x: f32, lo: f32) -> f32 {
    if x < lo { lo } else { x }
}

fn check_len(name: &'static str, expected: usize, actual: usize) -> Result<(), SchedulerError> {
    if expected == actual {
        Ok(())
    } else {
        Err(SchedulerError::LengthMismatch {
            name,
            expected,
            actual,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use serde::Deserialize;

    const FIXTURE: &str = include_str!("../../tests/fixtures/diffusers_schedulers.json");

    #[derive(Deserialize)]
    struct Fixture {
        versions: std::collections::BTreeMap<String, String>,
        shape: Vec<usize>,
        vectors: Vectors,
        cases: Vec<Case>,
    }

    #[derive(Deserialize)]
    struct Vectors {
        model_output: Vec<f32>,
        sample: Vec<f32>,
        noise: Vec<f32>,
        x0: Vec<f32>,
    }

    #[derive(Deserialize)]
    struct Case {
        name: String,
        config: SchedulerConfig,
        betas: Option<Vec<f64>>,
        alphas_cumprod: Option<Vec<f64>>,
        timesteps: Vec<TimestepsEntry>,
        steps: Vec<StepEntry>,
        add_noise: Vec<AddNoiseEntry>,
    }

    #[derive(Deserialize)]
    struct TimestepsEntry {
        num_inference_steps: usize,
        timesteps: Vec<usize>,
    }

    #[derive(Deserialize)]
    struct StepEntry {
        num_inference_steps: usize,
        t: usize,
        prev_sample: Vec<f32>,
    }

    #[derive(Deserialize)]
    struct AddNoiseEntry {
        t: usize,
        out: Vec<f32>,
    }

    fn fixture() -> Fixture {
        serde_json::from_str(FIXTURE).expect("fixture parses")
    }

    /// Largest |a - e| and |a - e| / |e| (relative part only where |e| > 0).
    fn errors(actual: &[f64], expected: &[f64]) -> (f64, f64) {
        assert_eq!(actual.len(), expected.len());
        actual
            .iter()
            .zip(expected)
            .fold((0.0, 0.0), |(abs, rel), (&a, &e)| {
                let d = (a - e).abs();
                let r = if e != 0.0 { d / e.abs() } else { 0.0 };
                (f64::max(abs, d), f64::max(rel, r))
            })
    }

    fn widen(v: &[f32]) -> Vec<f64> {
        v.iter().map(|&x| f64::from(x)).collect()
    }

    fn find<'a>(fx: &'a Fixture, name: &str) -> &'a Case {
        fx.cases
            .iter()
            .find(|c| c.name == name)
            .expect("case present")
    }

    /// Key identifying a schedule's tables (the fixture stores each distinct table once).
    fn table_key(c: &SchedulerConfig) -> String {
        format!(
            "{:?}/{}/{}/{}",
            c.beta_schedule, c.num_train_timesteps, c.beta_start, c.beta_end
        )
    }

    /// The reference tables of `case`, looked up from the first case with the same schedule.
    fn reference_tables<'a>(fx: &'a Fixture, case: &Case) -> (&'a [f64], &'a [f64]) {
        let key = table_key(&case.config);
        let owner = fx
            .cases
            .iter()
            .find(|c| table_key(&c.config) == key && c.betas.is_some())
            .expect("tables stored once per schedule");
        (
            owner.betas.as_deref().expect("betas"),
            owner.alphas_cumprod.as_deref().expect("alphas_cumprod"),
        )
    }

    /// Normwise error of a vector: max |a - e| / max(max |e|, 1e-30).
    fn normwise(actual: &[f32], expected: &[f32]) -> f64 {
        let (abs, _) = errors(&widen(actual), &widen(expected));
        let scale = expected
            .iter()
            .fold(0.0_f64, |m, &e| m.max(f64::from(e).abs()));
        abs / scale.max(1e-30)
    }

    /// Tolerance for one diffusers `step` / `add_noise` vector, normwise (relative to the
    /// vector's largest element): 1e-6, about 8 f32 ulps.
    ///
    /// Why not bit-exact: we evaluate diffusers' expressions in f32 in the same order, but
    /// torch's CPU `sqrt` for float32 is not correctly rounded (on the AVX-512 machine that
    /// generated the fixture ~20% of results are 1 ulp off; max error 0.75 ulp; it depends on
    /// the CPU kernel / MKL build), while Rust's `f32::sqrt` is. A step uses up to four
    /// square roots plus ~8 roundings, and linear-schedule tables differ from torch's
    /// `linspace` by a few ulps (see `linear_tables_match_diffusers_within_ulps`). Measured:
    /// max normwise error 2.3e-7 over all steps except the one below; a wrong coefficient,
    /// timestep or table entry gives errors > 1e-3.
    ///
    /// DDIM with eta > 0 evaluates `sqrt(1 - abar_prev - sigma^2)` where the two terms
    /// nearly cancel when abar_t << abar_prev (e.g. t = 99 -> 98 on the cosine schedule, where
    /// beta_99 = 0.999): a 1-ulp difference in `sigma` is amplified by
    /// kappa = (1 - abar_prev) / (1 - abar_prev - sigma^2) (about 1000 there; measured
    /// normwise error 2.6e-6). The tolerance is multiplied by kappa (1 when nothing cancels).
    const STEP_TOL: f64 = 1e-6;

    fn kappa(s: &Scheduler, t: usize, n: usize) -> f64 {
        let c = s.config();
        if c.kind == SchedulerKind::Ddpm || c.eta == 0.0 {
            return 1.0;
        }
        let abar = s.alphas_cumprod();
        let prev = s.previous_timestep(t, n).expect("valid t");
        let a_t = abar[t];
        let a_prev = match prev {
            Some(p) => abar[p],
            None if c.set_alpha_to_one => 1.0,
            None => abar[0],
        };
        let sigma2 = c.eta * c.eta * (1.0 - a_prev) / (1.0 - a_t) * (1.0 - a_t / a_prev);
        let rest = 1.0 - a_prev - sigma2;
        if rest <= 0.0 {
            1.0
        } else {
            ((1.0 - a_prev) / rest).max(1.0)
        }
    }

    #[test]
    fn fixture_is_from_the_pinned_versions() {
        let fx = fixture();
        assert_eq!(fx.versions["diffusers"], "0.35.2");
        assert_eq!(fx.versions["torch"], "2.10.0");
        assert_eq!(fx.versions["numpy"], "2.2.6");
        let len: usize = fx.shape.iter().product();
        for v in [
            &fx.vectors.model_output,
            &fx.vectors.sample,
            &fx.vectors.noise,
            &fx.vectors.x0,
        ] {
            assert_eq!(v.len(), len);
        }
        assert_eq!(fx.cases.len(), 10);
    }

    #[test]
    fn lerobot_configs_match_the_fixture() {
        let fx = fixture();
        assert_eq!(
            find(&fx, "pusht_ddpm").config,
            SchedulerConfig::lerobot_pusht()
        );
        let ddim = SchedulerConfig {
            kind: SchedulerKind::Ddim,
            ..SchedulerConfig::lerobot_pusht()
        };
        assert_eq!(find(&fx, "pusht_ddim_eta0").config, ddim);
        for case in &fx.cases {
            case.config.validate().expect("fixture configs are valid");
        }
    }

    /// Cosine tables are bit-identical: diffusers evaluates the same f64 formula (Python
    /// floats, glibc `cos`), rounds to f32, subtracts from 1 in f32 and takes torch's
    /// cumprod, which accumulates float32 in a double and rounds each entry; we do exactly
    /// that. Measured: 0 differing entries.
    #[test]
    fn cosine_tables_are_bit_identical_to_diffusers() {
        let fx = fixture();
        let mut checked = 0;
        for case in &fx.cases {
            if case.config.beta_schedule != BetaSchedule::SquaredcosCapV2 {
                continue;
            }
            let s = Scheduler::new(case.config.clone()).expect("valid");
            let (betas, abar) = reference_tables(&fx, case);
            assert_eq!(s.betas(), betas, "{}", case.name);
            assert_eq!(s.alphas_cumprod(), abar, "{}", case.name);
            checked += 1;
        }
        assert_eq!(checked, 7);
        // peer-facts 3.4: beta_0 = 6.3128e-4, beta_99 = 0.999 (capped), abar_99 = 2.43e-7.
        let s = Scheduler::new(SchedulerConfig::lerobot_pusht()).expect("valid");
        assert!((s.betas()[0] - 6.3128e-4).abs() < 1e-8);
        assert_eq!(s.betas()[99], f64::from(0.999_f32));
        assert!((s.alphas_cumprod()[99] - 2.43e-7).abs() < 1e-9);
    }

    /// Linear / scaled-linear betas: ours are the correctly rounded f32 of the exact
    /// linspace; torch's float32 `linspace` kernel rounds some entries differently (its
    /// vectorised path depends on the CPU), measured up to 2.3e-7 relative (2 ulps), so we
    /// allow 4e-7 (~3.4 ulps). `alphas_cumprod` inherits those differences: the relative
    /// error of abar_t is bounded by about 2 ulp x (1 + sum_{i<=t} beta_i) (each alpha_i
    /// differs by <= 2 ulp(beta_i)), i.e. ~1.3e-6 for the scaled-linear N = 1000 schedule
    /// (sum beta = 4.6); measured max 4.4e-7, allowed 2e-6.
    #[test]
    fn linear_tables_match_diffusers_within_ulps() {
        let fx = fixture();
        let mut checked = 0;
        for case in &fx.cases {
            if case.config.beta_schedule == BetaSchedule::SquaredcosCapV2 {
                continue;
            }
            let s = Scheduler::new(case.config.clone()).expect("valid");
            let (betas, abar) = reference_tables(&fx, case);
            let (_, rel_b) = errors(s.betas(), betas);
            let (_, rel_a) = errors(s.alphas_cumprod(), abar);
            assert!(rel_b <= 4e-7, "{}: betas rel {rel_b:e}", case.name);
            assert!(rel_a <= 2e-6, "{}: alphas_cumprod rel {rel_a:e}", case.name);
            if case.config.beta_schedule == BetaSchedule::Linear {
                // Endpoints are exact (torch's linspace hits start and end exactly too).
                assert_eq!(s.betas()[0], betas[0]);
                assert_eq!(s.betas().last(), betas.last());
            }
            checked += 1;
        }
        assert_eq!(checked, 3);
    }

    #[test]
    fn timesteps_match_diffusers() {
        let fx = fixture();
        let mut checked = 0;
        for case in &fx.cases {
            let s = Scheduler::new(case.config.clone()).expect("valid");
            for entry in &case.timesteps {
                let ours = s.timesteps(entry.num_inference_steps).expect("valid n");
                assert_eq!(
                    ours, entry.timesteps,
                    "{} n={}",
                    case.name, entry.num_inference_steps
                );
                checked += 1;
            }
        }
        assert!(checked >= 40, "{checked}");
        // Spot checks: N = 100, n = 10 -> 90..0; n = 30 -> step 3 starting at 87.
        let s = Scheduler::new(SchedulerConfig::lerobot_pusht()).expect("valid");
        assert_eq!(
            s.timesteps(10).expect("n"),
            vec![90, 80, 70, 60, 50, 40, 30, 20, 10, 0]
        );
        assert_eq!(s.timesteps(30).expect("n")[0], 87);
        assert_eq!(
            s.timesteps(100).expect("n"),
            (0..100).rev().collect::<Vec<_>>()
        );
    }

    #[test]
    fn steps_match_diffusers() {
        let fx = fixture();
        let v = &fx.vectors;
        let mut checked = 0;
        for case in &fx.cases {
            let s = Scheduler::new(case.config.clone()).expect("valid");
            for st in &case.steps {
                let mut x = v.sample.clone();
                s.step(
                    &v.model_output,
                    st.t,
                    st.num_inference_steps,
                    &mut x,
                    &v.noise,
                )
                .expect("step");
                let err = normwise(&x, &st.prev_sample);
                let tol = STEP_TOL * kappa(&s, st.t, st.num_inference_steps);
                assert!(
                    err <= tol,
                    "{} n={} t={}: normwise error {err:e} > {tol:e}",
                    case.name,
                    st.num_inference_steps,
                    st.t
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 52);
    }

    #[test]
    fn add_noise_matches_diffusers() {
        let fx = fixture();
        let v = &fx.vectors;
        let mut checked = 0;
        for case in &fx.cases {
            let s = Scheduler::new(case.config.clone()).expect("valid");
            for an in &case.add_noise {
                let mut out = vec![f32::NAN; v.x0.len()];
                s.add_noise(&v.x0, &v.noise, an.t, &mut out)
                    .expect("add_noise");
                let err = normwise(&out, &an.out);
                assert!(err <= STEP_TOL, "{} t={}: {err:e}", case.name, an.t);
                checked += 1;
            }
        }
        assert_eq!(checked, 10);
    }

    /// Whole sampling loops (model_output = 0.5 x + 0.1 m, noise rolled by the step index),
    /// so the timestep sequence and the hand-off between steps are covered. Per-step
    /// differences of ~1 ulp do not grow: the reverse process is contracting (coefficients of
    /// x_t are < 1). Tolerance 1e-5 normwise; measured <= 4.8e-7 on the cosine schedule and
    /// 1.0e-6 for 100 linear-schedule DDPM steps (whose tables differ by ~2 ulps).
    #[test]
    fn sampling_loops_match_diffusers() {
        let fx: serde_json::Value = serde_json::from_str(FIXTURE).expect("json");
        let typed = fixture();
        let v = &typed.vectors;
        let chains = fx["chains"].as_array().expect("chains");
        assert_eq!(chains.len(), 5);
        for chain in chains {
            let name = chain["case"].as_str().expect("case");
            let n = chain["num_inference_steps"].as_u64().expect("n") as usize;
            let expected: Vec<f32> =
                serde_json::from_value(chain["final_sample"].clone()).expect("final");
            let s = Scheduler::new(find(&typed, name).config.clone()).expect("valid");
            let mut x = v.sample.clone();
            let mut eps = vec![0.0_f32; x.len()];
            let mut noise = v.noise.clone();
            for (k, t) in s.timesteps(n).expect("n").into_iter().enumerate() {
                for ((e, &xi), &m) in eps.iter_mut().zip(&x).zip(&v.model_output) {
                    *e = 0.5 * xi + 0.1 * m;
                }
                noise.clone_from(&v.noise);
                let shift = k % noise.len();
                noise.rotate_right(shift);
                s.step(&eps, t, n, &mut x, &noise).expect("step");
            }
            let err = normwise(&x, &expected);
            assert!(err <= 1e-5, "{name} n={n}: {err:e}");
        }
    }

    fn config(
        kind: SchedulerKind,
        schedule: BetaSchedule,
        n: usize,
        prediction_type: PredictionType,
    ) -> SchedulerConfig {
        SchedulerConfig {
            kind,
            num_train_timesteps: n,
            beta_schedule: schedule,
            prediction_type,
            ..SchedulerConfig::lerobot_pusht()
        }
    }

    fn random_vec(rng: &mut ChaCha8Rng, len: usize, scale: f32) -> Vec<f32> {
        (0..len)
            .map(|_| rng.random_range(-1.0_f32..1.0) * scale)
            .collect()
    }

    const SCHEDULES: [BetaSchedule; 3] = [
        BetaSchedule::SquaredcosCapV2,
        BetaSchedule::Linear,
        BetaSchedule::ScaledLinear,
    ];

    #[test]
    fn alphas_cumprod_decrease_inside_unit_interval() {
        for schedule in SCHEDULES {
            for n in [1, 2, 3, 10, 100, 1000, 4000] {
                let s = Scheduler::new(config(
                    SchedulerKind::Ddpm,
                    schedule,
                    n,
                    PredictionType::Epsilon,
                ))
                .expect("valid");
                assert_eq!(s.betas().len(), n);
                assert_eq!(s.alphas_cumprod().len(), n);
                for &b in s.betas() {
                    assert!(
                        b > 0.0 && b <= f64::from(0.999_f32),
                        "{schedule:?} N={n}: beta {b}"
                    );
                }
                let abar = s.alphas_cumprod();
                for (t, &a) in abar.iter().enumerate() {
                    assert!(a > 0.0 && a < 1.0, "{schedule:?} N={n} t={t}: {a}");
                    assert_eq!(a, f64::from(a as f32), "stored values are f32");
                }
                for w in abar.windows(2) {
                    assert!(w[1] <= w[0], "{schedule:?} N={n}: not non-increasing");
                }
                // abar_0 = 1 - beta_0 (one f32 rounding at most).
                assert!((abar[0] - (1.0 - s.betas()[0])).abs() <= 1e-7);
            }
        }
    }

    /// With n = N, DDPM's last step (t = 0 -> "t = -1", abar_prev = 1) has coefficients
    /// exactly 1 (for x0_hat) and 0 (for x_t) and adds no noise: the result is the clipped
    /// x0 prediction. Same for DDIM with set_alpha_to_one (sigma = 0 there). So the final
    /// sample always lies in [-range, range] when clipping, whatever the inputs.
    #[test]
    fn clipping_keeps_the_final_sample_in_range() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for kind in [SchedulerKind::Ddpm, SchedulerKind::Ddim] {
            for prediction in [PredictionType::Epsilon, PredictionType::Sample] {
                for range in [0.25, 1.0, 3.0] {
                    for n in [100, 10, 1] {
                        let mut c = config(kind, BetaSchedule::SquaredcosCapV2, 100, prediction);
                        c.clip_sample_range = range;
                        c.eta = if kind == SchedulerKind::Ddim {
                            1.0
                        } else {
                            0.0
                        };
                        let s = Scheduler::new(c).expect("valid");
                        let len = 64;
                        let out = random_vec(&mut rng, len, 1e6);
                        let noise = random_vec(&mut rng, len, 3.0);
                        let mut x = random_vec(&mut rng, len, 1e4);
                        s.step(&out, 0, n, &mut x, &noise).expect("step");
                        let r = range as f32;
                        assert!(
                            x.iter().all(|v| (-r..=r).contains(v)),
                            "{kind:?} {prediction:?} range {range}: {x:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn ddpm_final_step_adds_no_noise() {
        let s = Scheduler::new(SchedulerConfig::lerobot_pusht()).expect("valid");
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let out = random_vec(&mut rng, 32, 1.0);
        let x = random_vec(&mut rng, 32, 1.0);
        for n in [100, 10, 1] {
            assert!(!s.step_adds_noise(0, n).expect("valid"));
            assert_eq!(s.previous_timestep(0, n).expect("valid"), None);
            let mut a = x.clone();
            let mut b = x.clone();
            let mut c = x.clone();
            s.step(&out, 0, n, &mut a, &random_vec(&mut rng, 32, 5.0))
                .expect("step");
            s.step(&out, 0, n, &mut b, &random_vec(&mut rng, 32, 5.0))
                .expect("step");
            s.step(&out, 0, n, &mut c, &[])
                .expect("empty noise allowed");
            assert_eq!(a, b);
            assert_eq!(a, c);
        }
        // t > 0 does use the noise, and needs it.
        assert!(s.step_adds_noise(1, 100).expect("valid"));
        let mut a = x.clone();
        assert!(matches!(
            s.step(&out, 1, 100, &mut a, &[]),
            Err(SchedulerError::LengthMismatch { name: "noise", .. })
        ));
        assert_eq!(a, x, "sample untouched on error");
    }

    /// DDPM noise enters as std * noise with std^2 = (1 - abar_prev)/(1 - abar_t) * beta_t'
    /// (fixed_small posterior variance); checked in f64 to 1e-6 relative.
    #[test]
    fn ddpm_noise_has_the_fixed_small_std() {
        let s = Scheduler::new(SchedulerConfig::lerobot_pusht()).expect("valid");
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let out = random_vec(&mut rng, 16, 1.0);
        let x = random_vec(&mut rng, 16, 1.0);
        let noise = vec![1.0_f32; 16];
        let abar = s.alphas_cumprod();
        for (n, t) in [(100, 99), (100, 50), (100, 1), (10, 90), (10, 10)] {
            let prev = s
                .previous_timestep(t, n)
                .expect("valid")
                .map_or(1.0, |p| abar[p]);
            let var = (1.0 - prev) / (1.0 - abar[t]) * (1.0 - abar[t] / prev);
            let mut with = x.clone();
            let mut without = x.clone();
            s.step(&out, t, n, &mut with, &noise).expect("step");
            s.step(&out, t, n, &mut without, &[0.0; 16]).expect("step");
            for (a, b) in with.iter().zip(&without) {
                let std = f64::from(a - b);
                assert!(
                    (std - var.sqrt()).abs() <= 1e-6 * (1.0 + var.sqrt()),
                    "t={t}: {std} vs {}",
                    var.sqrt()
                );
            }
        }
    }

    /// With the true noise as model output and zero added noise, a DDPM step returns the
    /// posterior mean, which for x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps simplifies to
    /// sqrt(abar_prev) x0 + sqrt(alpha_t) (1 - abar_prev) / sqrt(1 - abar_t) eps, with
    /// alpha_t = abar_t / abar_prev. The f64 reference uses the same (f32-valued) tables, so
    /// only the f32 arithmetic differs; diffusers' formula forms 1 - abar_t / abar_prev and
    /// 1 - abar_t in f32, whose relative rounding errors (<= ~2 eps) are amplified by the
    /// cancellation, 1 / min(beta_t', 1 - abar_t) (~3000 at t = 1 of the linear schedule,
    /// where the measured error is 5e-5); the tolerance is
    /// 1e-6 + 4 eps (|x0| + |x_t|) / min(beta_t', 1 - abar_t).
    #[test]
    fn ddpm_step_with_true_noise_is_the_posterior_mean() {
        for schedule in SCHEDULES {
            let s = Scheduler::new(config(
                SchedulerKind::Ddpm,
                schedule,
                100,
                PredictionType::Epsilon,
            ))
            .expect("valid");
            let mut rng = ChaCha8Rng::seed_from_u64(3);
            let x0 = random_vec(&mut rng, 32, 0.9);
            let eps = random_vec(&mut rng, 32, 2.0);
            let abar = s.alphas_cumprod();
            for (n, t) in [
                (100, 90),
                (100, 50),
                (100, 1),
                (100, 0),
                (10, 90),
                (10, 30),
                (10, 0),
            ] {
                let mut x = vec![0.0; 32];
                s.add_noise(&x0, &eps, t, &mut x).expect("add_noise");
                let xt = x.clone();
                s.step(&eps, t, n, &mut x, &[0.0; 32]).expect("step");
                let a_prev = s
                    .previous_timestep(t, n)
                    .expect("valid")
                    .map_or(1.0, |p| abar[p]);
                let alpha_t = abar[t] / a_prev;
                let c_eps = alpha_t.sqrt() * (1.0 - a_prev) / (1.0 - abar[t]).sqrt();
                let cancel = (1.0 - alpha_t).min(1.0 - abar[t]);
                for i in 0..32 {
                    let want = a_prev.sqrt() * f64::from(x0[i]) + c_eps * f64::from(eps[i]);
                    let scale = f64::from(x0[i].abs() + xt[i].abs());
                    let tol = 1e-6 + 4.0 * f64::from(f32::EPSILON) * scale / cancel;
                    let err = (f64::from(x[i]) - want).abs();
                    assert!(err <= tol, "{schedule:?} n={n} t={t}: {err:e} > {tol:e}");
                }
            }
        }
    }

    /// Deterministic DDIM with a perfect noise oracle follows the forward process: from
    /// x_t = add_noise(x0, eps, t) it lands on add_noise(x0, eps, t_prev) (or x0 at the end).
    #[test]
    fn ddim_with_true_noise_follows_the_forward_process() {
        for schedule in SCHEDULES {
            let mut c = config(SchedulerKind::Ddim, schedule, 100, PredictionType::Epsilon);
            c.eta = 0.0;
            let s = Scheduler::new(c).expect("valid");
            let mut rng = ChaCha8Rng::seed_from_u64(4);
            let x0 = random_vec(&mut rng, 32, 0.9);
            let eps = random_vec(&mut rng, 32, 2.0);
            for n in [10, 25, 100] {
                for t in s.timesteps(n).expect("n").into_iter().filter(|&t| t <= 90) {
                    let mut x = vec![0.0; 32];
                    s.add_noise(&x0, &eps, t, &mut x).expect("add_noise");
                    assert!(!s.step_adds_noise(t, n).expect("valid"));
                    s.step(&eps, t, n, &mut x, &[]).expect("step");
                    let mut want = x0.clone();
                    if let Some(p) = s.previous_timestep(t, n).expect("valid") {
                        s.add_noise(&x0, &eps, p, &mut want).expect("add_noise");
                    }
                    for (a, b) in x.iter().zip(&want) {
                        assert!(
                            (a - b).abs() <= 1e-5,
                            "{schedule:?} n={n} t={t}: {a} vs {b}"
                        );
                    }
                }
            }
        }
    }

    /// Sample prediction: a model that outputs the true x0 makes both kinds land exactly
    /// where the epsilon-prediction oracle does (DDPM posterior mean / DDIM forward process).
    #[test]
    fn sample_prediction_with_true_x0_agrees_with_epsilon_prediction() {
        for kind in [SchedulerKind::Ddpm, SchedulerKind::Ddim] {
            let eps_s = Scheduler::new(config(
                kind,
                BetaSchedule::SquaredcosCapV2,
                100,
                PredictionType::Epsilon,
            ))
            .expect("valid");
            let x0_s = Scheduler::new(config(
                kind,
                BetaSchedule::SquaredcosCapV2,
                100,
                PredictionType::Sample,
            ))
            .expect("valid");
            let mut rng = ChaCha8Rng::seed_from_u64(5);
            let x0 = random_vec(&mut rng, 32, 0.9);
            let eps = random_vec(&mut rng, 32, 2.0);
            for (n, t) in [(100, 80), (100, 10), (10, 50), (10, 0)] {
                let mut xt = vec![0.0; 32];
                eps_s.add_noise(&x0, &eps, t, &mut xt).expect("add_noise");
                let mut a = xt.clone();
                let mut b = xt.clone();
                eps_s.step(&eps, t, n, &mut a, &[0.0; 32]).expect("step");
                x0_s.step(&x0, t, n, &mut b, &[0.0; 32]).expect("step");
                for (p, q) in a.iter().zip(&b) {
                    assert!((p - q).abs() <= 1e-5, "{kind:?} n={n} t={t}: {p} vs {q}");
                }
            }
        }
    }

    #[test]
    fn add_noise_is_the_forward_process() {
        let s = Scheduler::new(SchedulerConfig::lerobot_pusht()).expect("valid");
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let x0 = random_vec(&mut rng, 40, 1.0);
        let eps = random_vec(&mut rng, 40, 3.0);
        for t in [0, 1, 37, 98, 99] {
            let a = s.alphas_cumprod()[t];
            let mut out = vec![0.0; 40];
            s.add_noise(&x0, &eps, t, &mut out).expect("add_noise");
            for i in 0..40 {
                let want = a.sqrt() * f64::from(x0[i]) + (1.0 - a).sqrt() * f64::from(eps[i]);
                assert!((f64::from(out[i]) - want).abs() <= 1e-6, "t={t}");
            }
        }
        // Empty slices are fine.
        s.add_noise(&[], &[], 5, &mut []).expect("empty");
    }

    #[test]
    fn timesteps_are_leading_spaced() {
        for n_train in [1, 7, 100, 1000] {
            let s = Scheduler::new(config(
                SchedulerKind::Ddim,
                BetaSchedule::Linear,
                n_train,
                PredictionType::Epsilon,
            ))
            .expect("valid");
            for n in 1..=n_train.min(120) {
                let ts = s.timesteps(n).expect("n");
                let ratio = n_train / n;
                assert_eq!(ts.len(), n);
                assert_eq!(ts.last(), Some(&0));
                assert!(ts[0] < n_train);
                for w in ts.windows(2) {
                    assert_eq!(w[0] - w[1], ratio);
                }
                for &t in &ts {
                    assert_eq!(
                        s.previous_timestep(t, n).expect("valid"),
                        t.checked_sub(ratio)
                    );
                }
            }
        }
    }

    #[test]
    fn step_and_timestep_errors() {
        let ddpm = Scheduler::new(SchedulerConfig::lerobot_pusht()).expect("valid");
        let ddim = Scheduler::new(SchedulerConfig {
            kind: SchedulerKind::Ddim,
            eta: 0.5,
            ..SchedulerConfig::lerobot_pusht()
        })
        .expect("valid");
        let out = [0.5_f32; 4];
        let noise = [0.1_f32; 4];
        let orig = [0.25_f32; 4];
        let mut x = orig;
        assert_eq!(ddpm.timesteps(0), Err(SchedulerError::ZeroInferenceSteps));
        assert_eq!(
            ddpm.timesteps(101),
            Err(SchedulerError::TooManyInferenceSteps {
                num_inference_steps: 101,
                num_train_timesteps: 100
            })
        );
        for s in [&ddpm, &ddim] {
            assert_eq!(
                s.step(&out, 0, 0, &mut x, &noise),
                Err(SchedulerError::ZeroInferenceSteps)
            );
            assert!(matches!(
                s.step(&out, 0, 1000, &mut x, &noise),
                Err(SchedulerError::TooManyInferenceSteps { .. })
            ));
            assert_eq!(
                s.step(&out, 100, 100, &mut x, &noise),
                Err(SchedulerError::TimestepOutOfRange {
                    t: 100,
                    num_train_timesteps: 100
                })
            );
            assert_eq!(
                s.step(&out[..3], 50, 100, &mut x, &noise),
                Err(SchedulerError::LengthMismatch {
                    name: "model_output",
                    expected: 4,
                    actual: 3
                })
            );
            assert_eq!(
                s.step(&out, 50, 100, &mut x, &noise[..2]),
                Err(SchedulerError::LengthMismatch {
                    name: "noise",
                    expected: 4,
                    actual: 2
                })
            );
            assert!(s.previous_timestep(usize::MAX, 10).is_err());
            assert!(s.step_adds_noise(100, 10).is_err());
        }
        // DDPM needs t on the inference grid (diffusers looks it up); DDIM does not.
        assert_eq!(
            ddpm.step(&out, 95, 10, &mut x, &noise),
            Err(SchedulerError::TimestepNotInSchedule {
                t: 95,
                num_inference_steps: 10,
                step_ratio: 10,
                last: 90
            })
        );
        assert!(
            ddpm.step(&out, 99, 30, &mut x, &noise).is_err(),
            "99 > 87 = last for n=30"
        );
        assert_eq!(x, orig, "sample untouched on every error");
        ddim.step(&out, 95, 10, &mut x, &noise)
            .expect("DDIM accepts off-grid t");
        assert_eq!(ddim.previous_timestep(95, 10), Ok(Some(85)));
        // add_noise
        let mut o = [0.0_f32; 4];
        assert_eq!(
            ddpm.add_noise(&out, &noise, 100, &mut o),
            Err(SchedulerError::TimestepOutOfRange {
                t: 100,
                num_train_timesteps: 100
            })
        );
        assert!(matches!(
            ddpm.add_noise(&out, &noise[..3], 1, &mut o),
            Err(SchedulerError::LengthMismatch { name: "noise", .. })
        ));
        assert!(matches!(
            ddpm.add_noise(&out, &noise, 1, &mut o[..2]),
            Err(SchedulerError::LengthMismatch { name: "out", .. })
        ));
        assert_eq!(o, [0.0; 4]);
        // Messages name the values.
        let msg = ddpm
            .step(&out, 95, 10, &mut x, &noise)
            .expect_err("off grid")
            .to_string();
        assert!(msg.contains("95") && msg.contains("10"), "{msg}");
    }

    #[test]
    fn config_validation_errors() {
        let ok = SchedulerConfig::lerobot_pusht();
        assert_eq!(ok.validate(), Ok(()));
        let with = |f: &dyn Fn(&mut SchedulerConfig)| {
            let mut c = ok.clone();
            f(&mut c);
            Scheduler::new(c).map(|_| ())
        };
        assert!(matches!(
            with(&|c| c.num_train_timesteps = 0),
            Err(SchedulerError::InvalidTrainTimesteps {
                num_train_timesteps: 0,
                ..
            })
        ));
        assert!(matches!(
            with(&|c| c.num_train_timesteps = MAX_TRAIN_TIMESTEPS + 1),
            Err(SchedulerError::InvalidTrainTimesteps { .. })
        ));
        assert!(matches!(
            with(&|c| c.beta_end = f64::NAN),
            Err(SchedulerError::NonFinite {
                name: "beta_end",
                ..
            })
        ));
        assert!(matches!(
            with(&|c| c.eta = f64::INFINITY),
            Err(SchedulerError::NonFinite { name: "eta", .. })
        ));
        // The cosine schedule ignores beta_start / beta_end (LeRobot passes the linear ones).
        assert_eq!(with(&|c| c.beta_start = 0.5), Ok(()));
        for (start, end) in [(0.0, 0.02), (-1e-4, 0.02), (0.03, 0.02), (1e-4, 1.0)] {
            for schedule in [BetaSchedule::Linear, BetaSchedule::ScaledLinear] {
                assert_eq!(
                    with(&|c| {
                        c.beta_schedule = schedule;
                        c.beta_start = start;
                        c.beta_end = end;
                    }),
                    Err(SchedulerError::InvalidBetaRange {
                        beta_start: start,
                        beta_end: end
                    })
                );
            }
        }
        assert_eq!(
            with(&|c| c.clip_sample_range = 0.0),
            Err(SchedulerError::InvalidClipRange {
                clip_sample_range: 0.0
            })
        );
        assert_eq!(
            with(&|c| {
                c.clip_sample = false;
                c.clip_sample_range = 0.0;
            }),
            Ok(())
        );
        assert_eq!(
            with(&|c| c.eta = -0.1),
            Err(SchedulerError::InvalidEta { eta: -0.1 })
        );
        assert_eq!(
            with(&|c| c.eta = 1.5),
            Err(SchedulerError::InvalidEta { eta: 1.5 })
        );
        // f32 degeneracy: 1 - 1e-9 rounds to 1, so abar_0 = 1 (division by 1 - abar = 0).
        assert!(matches!(
            with(&|c| {
                c.beta_schedule = BetaSchedule::Linear;
                c.beta_start = 1e-9;
            }),
            Err(SchedulerError::DegenerateSchedule { t: 0, .. })
        ));
        // ... and abar underflows to 0 for a long linear schedule.
        let err = with(&|c| {
            c.beta_schedule = BetaSchedule::Linear;
            c.num_train_timesteps = 100_000;
        })
        .expect_err("underflow");
        assert!(
            matches!(err, SchedulerError::DegenerateSchedule { t, alpha_cumprod, .. } if t > 1000 && alpha_cumprod == 0.0),
            "{err}"
        );
        let msg = with(&|c| c.eta = 1.5).expect_err("eta").to_string();
        assert!(msg.contains("1.5"), "{msg}");
    }

    #[test]
    fn config_serde_uses_snake_case_and_defaults() {
        let c = SchedulerConfig::lerobot_pusht();
        let json = serde_json::to_string(&c).expect("serialise");
        assert!(json.contains("\"kind\":\"ddpm\""), "{json}");
        assert!(
            json.contains("\"beta_schedule\":\"squaredcos_cap_v2\""),
            "{json}"
        );
        assert!(json.contains("\"prediction_type\":\"epsilon\""), "{json}");
        let back: SchedulerConfig = serde_json::from_str(&json).expect("parse");
        assert_eq!(back, c);
        let minimal = r#"{"kind":"ddim","num_train_timesteps":100,"beta_start":0.0001,
            "beta_end":0.02,"beta_schedule":"scaled_linear","prediction_type":"sample",
            "clip_sample":false,"clip_sample_range":1.0}"#;
        let m: SchedulerConfig = serde_json::from_str(minimal).expect("parse");
        assert!(m.set_alpha_to_one);
        assert_eq!(m.eta, 0.0);
        assert_eq!(m.kind, SchedulerKind::Ddim);
        assert_eq!(m.beta_schedule, BetaSchedule::ScaledLinear);
        assert_eq!(m.prediction_type, PredictionType::Sample);
        assert!(serde_json::from_str::<BetaSchedule>("\"linear\"").is_ok());
        assert!(serde_json::from_str::<BetaSchedule>("\"sigmoid\"").is_err());
    }

    /// Random (often invalid) configs and calls: everything returns, nothing panics.
    #[test]
    fn random_inputs_never_panic() {
        let mut rng = ChaCha8Rng::seed_from_u64(99);
        let floats = [
            0.0,
            -1.0,
            1e-4,
            0.02,
            0.5,
            0.999,
            1.0,
            2.0,
            f64::NAN,
            f64::INFINITY,
            -f64::INFINITY,
            1e-300,
        ];
        let specials = [
            0.0_f32,
            -0.0,
            1e30,
            -1e30,
            f32::NAN,
            f32::INFINITY,
            f32::MIN_POSITIVE,
        ];
        let mut built = 0;
        for _ in 0..400 {
            let pick = |rng: &mut ChaCha8Rng| floats[rng.random_range(0..floats.len())];
            let c = SchedulerConfig {
                kind: if rng.random() {
                    SchedulerKind::Ddpm
                } else {
                    SchedulerKind::Ddim
                },
                num_train_timesteps: rng.random_range(0..60),
                beta_start: pick(&mut rng),
                beta_end: pick(&mut rng),
                beta_schedule: SCHEDULES[rng.random_range(0..3)],
                prediction_type: if rng.random() {
                    PredictionType::Epsilon
                } else {
                    PredictionType::Sample
                },
                clip_sample: rng.random(),
                clip_sample_range: pick(&mut rng),
                set_alpha_to_one: rng.random(),
                eta: pick(&mut rng),
            };
            let Ok(s) = Scheduler::new(c) else { continue };
            built += 1;
            for _ in 0..20 {
                let n = rng.random_range(0..70);
                let t = rng.random_range(0..70);
                let len = rng.random_range(0..5);
                let vec_of = |rng: &mut ChaCha8Rng, l: usize| -> Vec<f32> {
                    (0..l)
                        .map(|_| {
                            if rng.random_range(0..4) == 0 {
                                specials[rng.random_range(0..specials.len())]
                            } else {
                                rng.random_range(-3.0..3.0)
                            }
                        })
                        .collect()
                };
                let out_len = if rng.random_range(0..5) == 0 {
                    len + 1
                } else {
                    len
                };
                let noise_len = if rng.random_range(0..5) == 0 { 0 } else { len };
                let out = vec_of(&mut rng, out_len);
                let noise = vec_of(&mut rng, noise_len);
                let mut x = vec_of(&mut rng, len);
                let _ = s.timesteps(n);
                let _ = s.previous_timestep(t, n);
                let _ = s.step_adds_noise(t, n);
                let _ = s.step(&out, t, n, &mut x, &noise);
                let mut o = vec![0.0; len];
                let _ = s.add_noise(&x, &noise, t, &mut o);
            }
        }
        assert!(built > 20, "{built}");
    }
}
