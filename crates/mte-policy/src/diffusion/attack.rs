//! Projected gradient descent (ascent) on the policy's own training loss: the paper's
//! observation attack (protocol section 4).
//!
//! At an attacked query the attacker first samples the chunk the policy predicts from the
//! *clean* observation and uses it as `x_0`; each iteration then draws diffusion timesteps
//! and noise, takes the gradient of the noise-prediction MSE with respect to the
//! observation, and steps `alpha * sign(grad)` uphill, projecting onto the L-infinity ball
//! of radius `eps` around the clean observation (and, for images, onto `[0, 1]`). The chunk
//! the runner executes is then sampled from the perturbed observation. Following the DP-
//! Attacker online attack, as the protocol chooses.
//!
//! What is perturbed: images in `[0, 1]` pixel units for image policies; for state policies
//! the *normalised* environment state (the block keypoints), in normalised units. The
//! agent's own position is proprioception and is left alone, as for the sensor faults.

use candle_core::{DType, Tensor};
use rand::{Rng, RngCore};
use rand_distr::{Distribution, StandardNormal};

use crate::error::PolicyError;
use crate::model::{DiffusionPolicy, ObsBatch, Observation};
use crate::policy::AttackedQuery;

/// PGD settings. Defaults: the paper's (eps 0.03, step 0.001875, 200 iterations).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PgdConfig {
    /// L-infinity radius (pixel units in [0, 1], or normalised state units).
    pub eps: f64,
    /// Step size per iteration.
    pub step: f64,
    /// Iterations (the attack budget).
    pub iterations: usize,
    /// Start from a uniform point in the ball instead of the clean observation.
    pub random_start: bool,
    /// Diffusion timesteps (with their noise) averaged per iteration.
    pub samples: usize,
}

impl Default for PgdConfig {
    fn default() -> Self {
        Self {
            eps: 0.03,
            step: 0.001_875,
            iterations: 200,
            random_start: false,
            samples: 4,
        }
    }
}

impl PgdConfig {
    /// Checks ranges.
    pub fn validate(&self) -> Result<(), PolicyError> {
        let bad = |name: &'static str, v: String, e: &str| PolicyError::Config {
            field: name,
            value: v,
            expected: e.to_string(),
        };
        if !(self.eps.is_finite() && self.eps >= 0.0) {
            return Err(bad("pgd.eps", self.eps.to_string(), "a finite value >= 0"));
        }
        if !(self.step.is_finite() && self.step > 0.0) {
            return Err(bad("pgd.step", self.step.to_string(), "a finite value > 0"));
        }
        if self.samples == 0 {
            return Err(bad("pgd.samples", "0".into(), "at least 1"));
        }
        Ok(())
    }
}

/// What one attack did.
#[derive(Clone, Debug, PartialEq)]
pub struct PgdOutcome {
    /// The chunk sampled from the perturbed observation (unnormalised, `horizon x d`).
    pub chunk: Vec<f32>,
    /// Loss at the clean observation (first iteration) and at the last iteration.
    pub loss_first: f32,
    /// Loss at the last iteration.
    pub loss_last: f32,
    /// Largest absolute perturbation applied (same units as `eps`).
    pub max_perturbation: f32,
}

impl DiffusionPolicy {
    /// The perturbed observation batch of [`DiffusionPolicy::pgd_attack`], before sampling,
    /// with the losses at the first and the last iteration. `attack_rng` draws the random
    /// start, timesteps and noise.
    pub fn pgd_perturb(
        &self,
        history: &[Observation],
        x0: &Tensor,
        cfg: &PgdConfig,
        attack_rng: &mut dyn RngCore,
    ) -> Result<(ObsBatch, f32, f32), PolicyError> {
        let (adv, losses) =
            self.pgd_perturb_batch(&self.obs_batch(&[history])?, x0, cfg, &mut [attack_rng])?;
        Ok((adv, losses[0].0, losses[0].1))
    }

    /// [`DiffusionPolicy::pgd_perturb`] for `B` queries at once from their clean batch and
    /// clean chunks `x0 (B, horizon, d)`, query `i` driven by `attack_rngs[i]` exactly as a
    /// batch of one is (its random start, then per iteration its timesteps and noise), its
    /// gradient its own ([`DiffusionPolicy::observation_gradient_per_query`]): each query is
    /// perturbed as it would be alone. Returns the perturbed batch and each query's first
    /// and last loss.
    pub fn pgd_perturb_batch(
        &self,
        clean: &ObsBatch,
        x0: &Tensor,
        cfg: &PgdConfig,
        attack_rngs: &mut [&mut (dyn RngCore + '_)],
    ) -> Result<(ObsBatch, Vec<(f32, f32)>), PolicyError> {
        cfg.validate()?;
        let (target, is_image) = pgd_target(clean)?;
        let b = attack_rngs.len();
        let eps = cfg.eps as f32;
        let dtype = target.dtype();
        let mut x: Vec<f32> = target.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        if b == 0 || !x.len().is_multiple_of(b) {
            return Err(PolicyError::Input {
                name: "attack_rngs",
                reason: format!("{b} streams for a batch of {} values", x.len()),
            });
        }
        // Each query's values are one contiguous run (images: its T_o frames).
        let per = x.len() / b;
        let base = x.clone();
        if cfg.random_start {
            for (part, rng) in x.chunks_mut(per).zip(attack_rngs.iter_mut()) {
                for v in part {
                    *v += rng.random_range(-eps..=eps);
                }
            }
        }
        let project = |x: &mut [f32]| {
            for (v, &b) in x.iter_mut().zip(&base) {
                *v = v.clamp(b - eps, b + eps);
                if is_image {
                    *v = v.clamp(0.0, 1.0);
                }
            }
        };
        project(&mut x);
        let shape = target.shape().clone();
        // The clean batch with the perturbed channel replaced by `x`.
        let with_perturbed = |x: Vec<f32>| -> Result<ObsBatch, PolicyError> {
            let xt = Tensor::from_vec(x, shape.clone(), self.device())?.to_dtype(dtype)?;
            let (env, image) = if is_image {
                (clean.env.clone(), Some(xt))
            } else {
                (Some(xt), None)
            };
            Ok(ObsBatch {
                state: clean.state.clone(),
                env,
                image,
            })
        };
        let mut losses = vec![(f32::NAN, f32::NAN); b];
        for it in 0..cfg.iterations {
            let batch = with_perturbed(x.clone())?;
            let (timesteps, noise) = self.pgd_draws(attack_rngs, cfg.samples, dtype)?;
            let (loss, g) = self.observation_gradient_per_query(&batch, x0, &noise, &timesteps)?;
            for (l, &v) in losses.iter_mut().zip(&loss) {
                if it == 0 {
                    l.0 = v;
                }
                l.1 = v;
            }
            let grad = if is_image { g.image } else { g.env };
            let grad: Vec<f32> = match grad {
                Some(t) => t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?,
                None => vec![0.0; x.len()],
            };
            sign_step(&mut x, &grad, cfg.step as f32);
            project(&mut x);
        }
        Ok((with_perturbed(x)?, losses))
    }

    /// One PGD iteration's draws for each query, from its own stream in query order: its
    /// `samples` diffusion timesteps, then its noise `(samples, horizon, d)`; the noise of
    /// all queries as one `(B samples, horizon, d)` tensor of `dtype`.
    fn pgd_draws(
        &self,
        attack_rngs: &mut [&mut (dyn RngCore + '_)],
        samples: usize,
        dtype: DType,
    ) -> Result<(Vec<usize>, Tensor), PolicyError> {
        let (tp, d) = (self.config().horizon, self.action_normalizer().dim());
        let (b, n_train) = (attack_rngs.len(), self.config().num_train_timesteps);
        let mut timesteps = Vec::with_capacity(b * samples);
        let mut noise = Vec::with_capacity(b * samples * tp * d);
        for rng in attack_rngs.iter_mut() {
            timesteps.extend((0..samples).map(|_| rng.random_range(0..n_train)));
            noise.extend(
                (0..samples * tp * d).map(|_| -> f32 { StandardNormal.sample(&mut **rng) }),
            );
        }
        let noise = Tensor::from_vec(noise, (b * samples, tp, d), self.device())?;
        Ok((timesteps, noise.to_dtype(dtype)?))
    }

    /// Attack one query: sample the clean chunk as `x_0` (with `sample_rng`), run PGD
    /// (`attack_rng`), and sample the executed chunk from the perturbed observation (with
    /// `sample_rng` again).
    pub fn pgd_attack(
        &self,
        history: &[Observation],
        cfg: &PgdConfig,
        attack_rng: &mut dyn RngCore,
        sample_rng: &mut dyn RngCore,
    ) -> Result<PgdOutcome, PolicyError> {
        let mut q = [AttackedQuery {
            history,
            attack_rng,
            sample_rng,
        }];
        let mut out = self.pgd_attack_batch(&mut q, cfg)?;
        Ok(out.remove(0))
    }

    /// [`DiffusionPolicy::pgd_attack`] for several queries at once, each exactly as it would
    /// be attacked alone (batch-invariant network, per-query streams and gradients).
    pub fn pgd_attack_batch<'a>(
        &self,
        queries: &mut [AttackedQuery<'a>],
        cfg: &PgdConfig,
    ) -> Result<Vec<PgdOutcome>, PolicyError> {
        let histories: Vec<&[Observation]> = queries.iter().map(|q| q.history).collect();
        let clean = self.obs_batch(&histories)?;
        let mut sample: Vec<&mut (dyn RngCore + 'a)> =
            queries.iter_mut().map(|q| &mut *q.sample_rng).collect();
        let x0 = self.sample_chunks_normalized(&clean, &mut sample)?;
        drop(sample);
        let mut attack: Vec<&mut (dyn RngCore + 'a)> =
            queries.iter_mut().map(|q| &mut *q.attack_rng).collect();
        let (adv, losses) = self.pgd_perturb_batch(&clean, &x0, cfg, &mut attack)?;
        drop(attack);
        let perturbation = max_perturbation(&adv, &clean, queries.len())?;
        let mut sample: Vec<&mut (dyn RngCore + 'a)> =
            queries.iter_mut().map(|q| &mut *q.sample_rng).collect();
        let chunks =
            self.unnormalized_chunks(&self.sample_chunks_normalized(&adv, &mut sample)?)?;
        Ok(chunks
            .into_iter()
            .zip(losses)
            .zip(perturbation)
            .map(
                |((chunk, (loss_first, loss_last)), max_perturbation)| PgdOutcome {
                    chunk,
                    loss_first,
                    loss_last,
                    max_perturbation,
                },
            )
            .collect())
    }
}

/// Each query's largest absolute change of the attacked channel (images, else the
/// environment state).
fn max_perturbation(adv: &ObsBatch, clean: &ObsBatch, b: usize) -> Result<Vec<f32>, PolicyError> {
    let (a, c) = match (&adv.image, &clean.image, &adv.env, &clean.env) {
        (Some(a), Some(c), _, _) | (None, None, Some(a), Some(c)) => (a, c),
        _ => return Ok(vec![0.0; b]),
    };
    let diff: Vec<f32> = (a - c)?
        .abs()?
        .to_dtype(DType::F32)?
        .flatten_all()?
        .to_vec1()?;
    Ok(diff
        .chunks(diff.len() / b.max(1))
        .map(|part| part.iter().copied().fold(0f32, f32::max))
        .collect())
}

/// What PGD perturbs in `clean`, and whether it is a camera frame (kept in [0, 1]): the
/// frames when the policy has a camera, else the environment state.
fn pgd_target(clean: &ObsBatch) -> Result<(Tensor, bool), PolicyError> {
    match (&clean.image, &clean.env) {
        (Some(img), _) => Ok((img.clone(), true)),
        (None, Some(env)) => Ok((env.clone(), false)),
        (None, None) => Err(PolicyError::Input {
            name: "observation",
            reason: "PGD needs an image or an environment state to perturb".into(),
        }),
    }
}

/// One signed step: each coordinate moves `step` along its gradient's sign (sign(0) = 0: a
/// coordinate without gradient does not move).
fn sign_step(x: &mut [f32], grad: &[f32], step: f32) {
    for (v, gv) in x.iter_mut().zip(grad) {
        if *gv > 0.0 {
            *v += step;
        } else if *gv < 0.0 {
            *v -= step;
        }
    }
}
