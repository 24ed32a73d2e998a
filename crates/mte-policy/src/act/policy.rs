//! ACT behind the policy seam, and its checkpoints (LeRobot's layout: `config.json` with
//! `"type": "act"`, the weights under `model.` in `model.safetensors`, statistics in the
//! processor files).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use rand::RngCore;

use super::config::ActConfig;
use super::model::{ActInputs, ActNet};
use crate::attack::PgdConfig;
use crate::checkpoint::{
    CONFIG, WEIGHTS, ck, read_processor_stats, read_tensors, save_stats, write_config,
};
use crate::error::PolicyError;
use crate::model::StatsMap;
use crate::normalize::{Normalizer, Stats};
use crate::policy::{AttackablePolicy, ChunkPolicy, ObsNeeds, Observation};

/// An ACT policy: the network, its normalisers and statistics.
pub struct ActPolicy {
    net: ActNet,
    state_norm: Option<Normalizer>,
    env_norm: Option<Normalizer>,
    /// The cameras in the config's order (the scene camera, then the wrist camera).
    cameras: Vec<Camera>,
    action_norm: Normalizer,
    stats: StatsMap,
}

/// A camera the policy reads: its frame size and per-channel normalisation.
struct Camera {
    h: usize,
    w: usize,
    /// MEAN_STD's per-channel statistics (IDENTITY: none).
    norm: Option<crate::normalize::ImageNorm>,
}

impl Camera {
    /// The config's cameras, each with its own statistics (`validate()` allows one, or the
    /// scene camera and the wrist camera of one size).
    fn all(c: &ActConfig, stats: &StatsMap) -> Result<Vec<Self>, PolicyError> {
        c.image_features()?
            .into_iter()
            .map(|(name, [_, h, w])| {
                let mode = c.norm_mode("VISUAL");
                let norm = crate::normalize::ImageNorm::for_mode(mode, &name, stats.get(&name))?;
                Ok(Self { h, w, norm })
            })
            .collect()
    }

    /// Frames `(B, 3, H, W)` in [0, 1] normalised as the network reads them.
    fn normalize(&self, img: &Tensor) -> candle_core::Result<Tensor> {
        match &self.norm {
            Some(n) => n.apply(img),
            None => Ok(img.clone()),
        }
    }
}

/// A batch of observations as tensors: normalised states, raw frames in [0, 1].
pub struct ObsTensors {
    /// Normalised robot state `(B, s)`.
    pub state: Option<Tensor>,
    /// Normalised environment state `(B, e)`.
    pub env: Option<Tensor>,
    /// Frames `(B N, 3, H, W)` in [0, 1] for `N` cameras, each observation's cameras
    /// together (rows `(b n)`), before normalisation (PGD's space).
    pub image: Option<Tensor>,
}

fn normalizer(
    c: &ActConfig,
    stats: &StatsMap,
    name: &'static str,
    kind: &str,
    dim: usize,
) -> Result<Normalizer, PolicyError> {
    let empty = Stats::default();
    Normalizer::new(
        name,
        c.norm_mode(kind),
        stats.get(name).unwrap_or(&empty),
        dim,
    )
}

impl ActPolicy {
    /// Build from a config, statistics and a `VarBuilder` rooted at the network (`model.`).
    pub fn new(config: ActConfig, stats: StatsMap, vb: VarBuilder) -> Result<Self, PolicyError> {
        config.validate()?;
        let state_norm = config
            .state_dim()
            .map(|d| normalizer(&config, &stats, "observation.state", "STATE", d))
            .transpose()?;
        let env_norm = config
            .env_state_dim()
            .map(|d| normalizer(&config, &stats, "observation.environment_state", "ENV", d))
            .transpose()?;
        let action_norm = normalizer(&config, &stats, "action", "ACTION", config.action_dim()?)?;
        Ok(Self {
            cameras: Camera::all(&config, &stats)?,
            net: ActNet::new(config, vb)?,
            state_norm,
            env_norm,
            action_norm,
            stats,
        })
    }

    /// The network.
    pub fn net(&self) -> &ActNet {
        &self.net
    }

    /// The config.
    pub fn config(&self) -> &ActConfig {
        self.net.config()
    }

    /// The normalisation statistics.
    pub fn stats(&self) -> &StatsMap {
        &self.stats
    }

    /// A batch of observations as tensors (states normalised, frames in [0, 1]): `obs` holds
    /// `k = n_obs_steps` consecutive observations per sample, oldest first (one per sample
    /// for LeRobot's ACT), and each sample's `k` state vectors become one row.
    ///
    /// # Errors
    /// An absent or misshapen input, named; a length that is not a multiple of `k`.
    pub fn obs_tensors(&self, obs: &[&Observation]) -> Result<ObsTensors, PolicyError> {
        let mut t = self.obs_tensors_without_image(obs)?;
        let Some(cam) = self.cameras.first() else {
            return Ok(t);
        };
        let n = self.cameras.len();
        let mut flat = Vec::with_capacity(obs.len() * n * 3 * cam.h * cam.w);
        for o in obs {
            crate::vision::push_camera_frames(o, n > 1, cam.h, cam.w, &mut flat)?;
        }
        let shape = (obs.len() * n, 3, cam.h, cam.w);
        t.image = Some(Tensor::from_vec(flat, shape, &Device::Cpu)?);
        Ok(t)
    }

    /// [`Self::obs_tensors`] without the frames (`image` is `None`, and the observations'
    /// frames are not read): for training on a frozen backbone's cached feature maps.
    ///
    /// # Errors
    /// An absent or misshapen state, named.
    pub fn obs_tensors_without_image(
        &self,
        obs: &[&Observation],
    ) -> Result<ObsTensors, PolicyError> {
        let dev = Device::Cpu;
        let k = self.config().n_obs_steps;
        if obs.is_empty() || !obs.len().is_multiple_of(k) {
            return Err(crate::error::config_err(
                "observations",
                obs.len(),
                format!("a positive multiple of n_obs_steps = {k} (that many per sample)"),
            ));
        }
        let rows = |norm: &Normalizer,
                    get: &dyn Fn(&Observation) -> Option<Vec<f32>>,
                    name: &'static str| {
            let mut flat = Vec::with_capacity(obs.len() * norm.dim());
            for o in obs {
                let mut v = get(o).ok_or_else(|| {
                    crate::error::config_err(name, "absent", "present in every observation")
                })?;
                if v.len() != norm.dim() {
                    return Err(crate::error::config_err(
                        name,
                        v.len(),
                        format!("{} values", norm.dim()),
                    ));
                }
                norm.normalize(&mut v);
                flat.extend(v);
            }
            let shape = (obs.len() / k, k * norm.dim());
            Ok::<_, PolicyError>(Tensor::from_vec(flat, shape, &dev)?)
        };
        let state = self
            .state_norm
            .as_ref()
            .map(|n| rows(n, &|o| Some(o.state.clone()), "observation.state"))
            .transpose()?;
        let env = self
            .env_norm
            .as_ref()
            .map(|n| rows(n, &|o| o.env_state.clone(), "observation.environment_state"))
            .transpose()?;
        Ok(ObsTensors {
            state,
            env,
            image: None,
        })
    }

    /// The network's output for `obs` with its frame replaced by `image` (`(B, 3, H, W)` in
    /// [0, 1]; gradients flow through its normalisation), the latent zero.
    fn forward_with_image(
        &self,
        obs: &ObsTensors,
        env: Option<&Tensor>,
        image: Option<&Tensor>,
    ) -> Result<Tensor, PolicyError> {
        let images = match image {
            Some(img) => self.per_camera(img)?,
            None => Vec::new(),
        };
        let inputs = ActInputs {
            state: obs.state.as_ref(),
            env,
            images: &images,
            features: &[],
        };
        Ok(self.net.forward(&inputs, None, None)?.actions)
    }

    /// The normalised network inputs of `obs` (for training).
    pub fn inputs_of<'a>(
        &self,
        obs: &'a ObsTensors,
        images: &'a mut Vec<Tensor>,
    ) -> Result<ActInputs<'a>, PolicyError> {
        images.clear();
        if let Some(img) = &obs.image {
            images.extend(self.per_camera(img)?);
        }
        Ok(ActInputs {
            state: obs.state.as_ref(),
            env: obs.env.as_ref(),
            images,
            features: &[],
        })
    }

    /// The backbone's feature maps `(B N, C, h, w)` of `obs`'s frames (rows as
    /// [`ObsTensors::image`]'s; normalised as the network reads them; each sample's products
    /// of a batch of one's shape, so the bits an evaluation computes); `None` without a
    /// camera.
    pub fn backbone_features(&self, obs: &ObsTensors) -> Result<Option<Tensor>, PolicyError> {
        match self.normalized_image(obs)? {
            Some(x) => Ok(self.net.backbone_features(&x)?),
            None => Ok(None),
        }
    }

    /// `obs`'s frames normalised as the network reads them, each camera with its own
    /// statistics (rows as [`ObsTensors::image`]'s); `None` without a camera.
    pub fn normalized_image(&self, obs: &ObsTensors) -> Result<Option<Tensor>, PolicyError> {
        let Some(img) = &obs.image else {
            return Ok(None);
        };
        let per = self.per_camera(img)?;
        Ok(Some(match per.as_slice() {
            [one] => one.clone(),
            more => Tensor::stack(more, 1)?.flatten_to(1)?,
        }))
    }

    /// The number of cameras the policy reads.
    pub fn n_cameras(&self) -> usize {
        self.cameras.len()
    }

    /// Rows `(B N, …)` in `(b n)` order as one `(B, …)` tensor per camera.
    pub fn split_cameras(&self, rows: &Tensor) -> Result<Vec<Tensor>, PolicyError> {
        crate::vision::split_cameras(rows, self.cameras.len())
    }

    /// Frames `(B N, 3, H, W)` as each camera's normalised `(B, 3, H, W)` batch.
    fn per_camera(&self, img: &Tensor) -> Result<Vec<Tensor>, PolicyError> {
        self.split_cameras(img)?
            .iter()
            .zip(&self.cameras)
            .map(|(x, cam)| Ok(cam.normalize(x)?))
            .collect()
    }

    /// Normalises one action row in place.
    pub fn normalize_action(&self, row: &mut [f32]) {
        self.action_norm.normalize(row);
    }

    /// The unnormalised chunk `(chunk_size x A)` for one observation (latent zero; a policy
    /// of `n_obs_steps` > 1 needs [`ActPolicy::predict_history`]).
    pub fn predict(&self, obs: &Observation) -> Result<Vec<f32>, PolicyError> {
        Ok(self.predict_many(&[obs])?.remove(0))
    }

    /// The chunk for the last `n_obs_steps` observations of `history` (oldest first).
    ///
    /// # Errors
    /// A history shorter than `n_obs_steps`, and what [`ActPolicy::predict_many`] refuses.
    pub fn predict_history(&self, history: &[Observation]) -> Result<Vec<f32>, PolicyError> {
        let refs: Vec<&Observation> = self.last_steps(history)?.iter().collect();
        Ok(self.predict_many(&refs)?.remove(0))
    }

    /// The last `n_obs_steps` observations of `history`.
    fn last_steps<'h>(&self, history: &'h [Observation]) -> Result<&'h [Observation], PolicyError> {
        let k = self.config().n_obs_steps;
        history
            .len()
            .checked_sub(k)
            .map(|from| &history[from..])
            .ok_or_else(|| {
                crate::error::config_err("history", history.len(), format!(">= {k} observations"))
            })
    }

    /// The chunks of several samples in one pass (`obs` as [`ActPolicy::obs_tensors`] takes
    /// them); each is bit for bit what the sample gives alone (the products run per sample
    /// at inference).
    pub fn predict_many(&self, obs: &[&Observation]) -> Result<Vec<Vec<f32>>, PolicyError> {
        let t = self.obs_tensors(obs)?;
        let actions = self.forward_with_image(&t, t.env.as_ref(), t.image.as_ref())?;
        let n = self.config().chunk_size * self.action_norm.dim();
        let flat = actions.flatten_all()?.to_vec1::<f32>()?;
        Ok(flat
            .chunks(n)
            .map(|c| {
                let mut chunk = c.to_vec();
                for row in chunk.chunks_mut(self.action_norm.dim()) {
                    self.action_norm.unnormalize(row);
                }
                chunk
            })
            .collect())
    }

    /// Loads a checkpoint directory (config, weights, processor statistics) on the CPU.
    ///
    /// # Errors
    /// A missing or malformed file, a config that does not validate, a missing or misshapen
    /// weight (named).
    pub fn load(dir: &Path) -> Result<Self, PolicyError> {
        let config = ActConfig::from_file(&dir.join(CONFIG))?;
        let dev = Device::Cpu;
        let wpath = dir.join(WEIGHTS);
        let weights = read_tensors(&wpath, &dev)?;
        let mut stats = StatsMap::new();
        read_processor_stats(dir, &dev, &mut stats)?;
        let vb = VarBuilder::from_tensors(weights, DType::F32, &dev).pp("model");
        Self::new(config, stats, vb).map_err(|e| match e {
            PolicyError::Candle(err) => ck(&wpath, err.to_string()),
            other => other,
        })
    }

    /// Saves `varmap` (the network's variables, names relative to `model.`) with the config
    /// and statistics as a LeRobot-layout checkpoint directory.
    pub fn save(&self, dir: &Path, varmap: &VarMap) -> Result<(), PolicyError> {
        let weights = varmap
            .data()
            .lock()
            .map_err(|_| ck(dir, "variable map poisoned"))?
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect();
        self.save_tensors(dir, &weights)
    }

    /// [`Self::save`] with the weights `tensors` (names relative to `model.`) in place of
    /// the variables': a checkpoint of other weights of this network (an average of them).
    pub fn save_tensors(
        &self,
        dir: &Path,
        tensors: &HashMap<String, Tensor>,
    ) -> Result<(), PolicyError> {
        write_config(dir, self.config())?;
        self.write_weights(&dir.join(WEIGHTS), tensors)?;
        save_stats(dir, &self.stats)
    }

    /// Writes `tensors` (names relative to `model.`) as a `model.safetensors` file at `path`,
    /// with the CVAE encoder's fixed position table when the network has one.
    pub fn write_weights(
        &self,
        path: &Path,
        tensors: &HashMap<String, Tensor>,
    ) -> Result<(), PolicyError> {
        let mut weights: HashMap<String, Tensor> = tensors
            .iter()
            .map(|(k, v)| (format!("model.{k}"), v.clone()))
            .collect();
        if let Some(pos) = self.net.vae_pos_enc() {
            weights.insert("model.vae_encoder_pos_enc".into(), pos.clone());
        }
        Ok(candle_core::safetensors::save(&weights, path)?)
    }
}

impl ChunkPolicy for ActPolicy {
    fn horizon(&self) -> usize {
        self.config().chunk_size
    }
    fn n_obs_steps(&self) -> usize {
        self.config().n_obs_steps
    }
    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }
    fn needs(&self) -> ObsNeeds {
        ObsNeeds {
            env_state: self.env_norm.is_some(),
            image: self.cameras.first().map(|c| (c.w, c.h)),
            wrist_image: self.cameras.len() > 1,
        }
    }
    fn attackable(&self) -> Option<&dyn AttackablePolicy> {
        Some(self)
    }
    /// All queries in one pass (ACT draws nothing from their streams).
    fn predict_chunks(
        &self,
        queries: &mut [crate::policy::Query<'_>],
    ) -> Result<Vec<Vec<f32>>, PolicyError> {
        let mut obs = Vec::new();
        for q in queries.iter() {
            obs.extend(self.last_steps(q.history)?);
        }
        self.predict_many(&obs)
    }
    /// ACT is deterministic at inference (latent zero): `rng` is not drawn from.
    fn predict_chunk(
        &self,
        history: &[Observation],
        _rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        self.predict_history(history)
    }
}

/// PGD on ACT (the paper's observation attack, transferred), climbing ACT's own training
/// loss, the L1 distance of the predicted chunk (latent zero) from the chunk predicted at the
/// clean observation, by `step * sign(gradient)` per iteration inside the L-infinity ball of
/// radius `eps`. What is perturbed: the camera frame in [0, 1] (clipped to [0, 1]), as the
/// protocol attacks pixels, when the policy has a camera; otherwise the *normalised*
/// environment state (PushT: the block keypoints) of every observed step. The agent's own
/// position is left alone.
/// That loss is flat at the clean observation (its minimum), so the attack always starts from
/// a uniform point in the ball (drawn from `attack_rng`), whatever `random_start` says;
/// `samples` is unused (ACT is deterministic).
impl AttackablePolicy for ActPolicy {
    fn predict_chunk_attacked(
        &self,
        history: &[Observation],
        pgd: &PgdConfig,
        attack_rng: &mut dyn RngCore,
        _sample_rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        pgd.validate()?;
        let obs: Vec<&Observation> = self.last_steps(history)?.iter().collect();
        let t = self.obs_tensors(&obs)?;
        let pixels = t.image.is_some();
        let x0 = match (&t.image, &t.env) {
            (Some(img), _) => img.clone(),
            (None, Some(env)) => env.clone(),
            (None, None) => {
                return Err(PolicyError::Input {
                    name: "policy",
                    reason: "PGD perturbs a camera frame or the environment state, and this ACT reads neither".into(),
                });
            }
        };
        let run = |x: &Tensor| -> Result<Tensor, PolicyError> {
            if pixels {
                self.forward_with_image(&t, t.env.as_ref(), Some(x))
            } else {
                self.forward_with_image(&t, Some(x), None)
            }
        };
        let clean = run(&x0)?.detach();
        // Pixels stay in [0, 1]: the perturbation is cut where it would leave.
        let project = |delta: Tensor| -> candle_core::Result<Tensor> {
            if pixels {
                (&x0 + delta)?.clamp(0f32, 1f32)? - &x0
            } else {
                Ok(delta)
            }
        };
        let delta = pgd_ascent(&x0, pgd, attack_rng, &project, &|x| {
            Ok((run(x)? - &clean)?.abs()?.mean_all()?)
        })?;
        let mut chunk = run(&(&x0 + delta)?)?
            .squeeze(0)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        for row in chunk.chunks_mut(self.action_norm.dim()) {
            self.action_norm.unnormalize(row);
        }
        Ok(chunk)
    }
}

/// Sign-gradient ascent of `loss` from a uniform random start in the L-infinity ball of
/// radius `pgd.eps` around `x0`, `pgd.iterations` steps of `pgd.step`; each perturbation is
/// clipped to the ball, then by `project` (to keep `x0 + delta` valid). Returns the final
/// perturbation.
fn pgd_ascent(
    x0: &Tensor,
    pgd: &PgdConfig,
    attack_rng: &mut dyn RngCore,
    project: &dyn Fn(Tensor) -> candle_core::Result<Tensor>,
    loss: &dyn Fn(&Tensor) -> Result<Tensor, PolicyError>,
) -> Result<Tensor, PolicyError> {
    use rand::Rng;
    let eps = pgd.eps as f32;
    let start: Vec<f32> = (0..x0.elem_count())
        .map(|_| attack_rng.random_range(-eps..=eps))
        .collect();
    let mut delta = project(Tensor::from_vec(start, x0.shape(), x0.device())?)?;
    for _ in 0..pgd.iterations {
        let x = candle_core::Var::from_tensor(&(x0 + &delta)?)?;
        let grads = loss(x.as_tensor())?.backward()?;
        let Some(g) = grads.get(x.as_tensor()) else {
            break;
        };
        delta = project((&delta + (g.sign()? * pgd.step)?)?.clamp(-eps, eps)?)?.detach();
    }
    Ok(delta)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// Ascent on `sum(x)` drives every coordinate to the top of the ball, cut at 1 where the
    /// pixel box ends first; no perturbation leaves the ball.
    #[test]
    fn pixel_ascent_stays_in_the_ball_and_the_unit_box() {
        let x0 = Tensor::from_vec(vec![0.0f32, 0.5, 0.97, 1.0], 4, &Device::Cpu).expect("x0");
        let pgd = PgdConfig {
            eps: 0.1,
            step: 0.03,
            iterations: 12,
            random_start: true,
            samples: 1,
        };
        let project = |d: Tensor| (&x0 + d)?.clamp(0f32, 1f32)? - &x0;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let delta =
            pgd_ascent(&x0, &pgd, &mut rng, &project, &|x| Ok(x.sum_all()?)).expect("ascent");
        let d = delta.to_vec1::<f32>().expect("values");
        let want = [0.1f32, 0.1, 0.03, 0.0];
        for (got, want) in d.iter().zip(want) {
            assert!((got - want).abs() < 1e-6, "{d:?} against {want:?}");
        }
        // Without the box (the keypoint path), the same ascent ends at +eps everywhere.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let free = pgd_ascent(&x0, &pgd, &mut rng, &Ok, &|x| Ok(x.sum_all()?)).expect("ascent");
        let f = free.to_vec1::<f32>().expect("values");
        assert!(f.iter().all(|v| (v - 0.1).abs() < 1e-6), "{f:?}");
    }

    /// A two-step keypoint ACT with random weights and unit statistics.
    fn two_step() -> ActPolicy {
        let c = ActConfig {
            n_obs_steps: 2,
            chunk_size: 5,
            ..ActConfig::tiny()
        };
        let stat = |d: usize| crate::normalize::Stats {
            min: vec![0.0; d],
            max: vec![512.0; d],
            mean: vec![200.0; d],
            std: vec![100.0; d],
        };
        let stats = [
            ("observation.state", stat(2)),
            ("observation.environment_state", stat(16)),
            ("action", stat(2)),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let vb = crate::init::seeded_var_builder(&VarMap::new(), 3, DType::F32, &Device::Cpu);
        ActPolicy::new(c, stats, vb).expect("policy")
    }

    fn obs(x: f32) -> Observation {
        Observation {
            state: vec![x, 300.0 - x],
            env_state: Some((0..16).map(|k| x + 3.0 * k as f32).collect()),
            image: None,
            wrist_image: None,
        }
    }

    /// A two-step ACT reads both steps of its history (the older one changes the chunk),
    /// ignores anything older, answers a batch as it answers each query, and refuses a
    /// history of one.
    #[test]
    fn a_two_step_act_reads_the_last_two_observations() {
        let p = two_step();
        assert_eq!(ChunkPolicy::n_obs_steps(&p), 2);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let h = [obs(10.0), obs(50.0), obs(60.0)];
        let chunk = p.predict_chunk(&h, &mut rng).expect("chunk");
        assert_eq!(chunk.len(), 5 * 2);
        assert!(chunk.iter().all(|v| v.is_finite()));
        assert_eq!(p.predict_chunk(&h[1..], &mut rng).expect("last two"), chunk);
        let other_old = [obs(90.0), obs(60.0)];
        assert_ne!(p.predict_chunk(&other_old, &mut rng).expect("chunk"), chunk);
        let e = p.predict_chunk(&h[2..], &mut rng).expect_err("one step");
        assert!(e.to_string().contains("history"), "{e}");
        let e = p.predict(&h[2]).expect_err("one observation for two steps");
        assert!(e.to_string().contains("n_obs_steps"), "{e}");
        let (mut r1, mut r2) = (
            rand_chacha::ChaCha8Rng::seed_from_u64(1),
            rand_chacha::ChaCha8Rng::seed_from_u64(2),
        );
        let mut queries = [
            crate::policy::Query {
                history: &h,
                rng: &mut r1,
            },
            crate::policy::Query {
                history: &other_old,
                rng: &mut r2,
            },
        ];
        let both = p.predict_chunks(&mut queries).expect("batch");
        assert_eq!(both[0], chunk);
        assert_eq!(both[1], p.predict_history(&other_old).expect("alone"));
        // The keypoint attack perturbs both steps' keypoints and moves the chunk.
        let pgd = PgdConfig {
            eps: 0.5,
            step: 0.1,
            iterations: 3,
            random_start: true,
            samples: 1,
        };
        let attacked = p
            .predict_chunk_attacked(&h, &pgd, &mut r1, &mut r2)
            .expect("attacked");
        assert_eq!(attacked.len(), chunk.len());
        assert!(attacked.iter().all(|v| v.is_finite()));
        assert_ne!(attacked, chunk);
    }
}
