//! ACT behind the policy seam, and its checkpoints (LeRobot's layout: `config.json` with
//! `"type": "act"`, the weights under `model.` in `model.safetensors`, statistics in the
//! processor files).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use rand::RngCore;

use super::config::ActConfig;
use super::model::ActNet;
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
    action_norm: Normalizer,
    stats: StatsMap,
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

    /// Normalised `(state, env)` tensors `(B, ·)` of a batch of single observations.
    pub fn obs_tensors(
        &self,
        obs: &[&Observation],
    ) -> Result<(Option<Tensor>, Option<Tensor>), PolicyError> {
        let dev = Device::Cpu;
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
            Ok::<_, PolicyError>(Tensor::from_vec(flat, (obs.len(), norm.dim()), &dev)?)
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
        Ok((state, env))
    }

    /// Normalises one action row in place.
    pub fn normalize_action(&self, row: &mut [f32]) {
        self.action_norm.normalize(row);
    }

    /// The unnormalised chunk `(chunk_size x A)` for one observation (latent zero).
    pub fn predict(&self, obs: &Observation) -> Result<Vec<f32>, PolicyError> {
        Ok(self.predict_many(&[obs])?.remove(0))
    }

    /// The chunks of several observations in one pass; each is bit for bit what
    /// [`ActPolicy::predict`] gives alone (the products run per sample at inference).
    pub fn predict_many(&self, obs: &[&Observation]) -> Result<Vec<Vec<f32>>, PolicyError> {
        let (state, env) = self.obs_tensors(obs)?;
        let out = self.net.forward(state.as_ref(), env.as_ref(), None, None)?;
        let n = self.config().chunk_size * self.action_norm.dim();
        let flat = out.actions.flatten_all()?.to_vec1::<f32>()?;
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
        write_config(dir, self.config())?;
        let mut weights: HashMap<String, Tensor> = varmap
            .data()
            .lock()
            .map_err(|_| ck(dir, "variable map poisoned"))?
            .iter()
            .map(|(k, v)| (format!("model.{k}"), v.as_tensor().clone()))
            .collect();
        if let Some(pos) = self.net.vae_pos_enc() {
            weights.insert("model.vae_encoder_pos_enc".into(), pos.clone());
        }
        candle_core::safetensors::save(&weights, dir.join(WEIGHTS))?;
        save_stats(dir, &self.stats)
    }
}

impl ChunkPolicy for ActPolicy {
    fn horizon(&self) -> usize {
        self.config().chunk_size
    }
    fn n_obs_steps(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }
    fn needs(&self) -> ObsNeeds {
        ObsNeeds {
            env_state: self.env_norm.is_some(),
            image: None,
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
        let obs = queries
            .iter()
            .map(|q| {
                q.history
                    .last()
                    .ok_or_else(|| crate::error::config_err("history", 0, "1 observation"))
            })
            .collect::<Result<Vec<_>, _>>()?;
        self.predict_many(&obs)
    }
    /// ACT is deterministic at inference (latent zero): `rng` is not drawn from.
    fn predict_chunk(
        &self,
        history: &[Observation],
        _rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        let obs = history
            .last()
            .ok_or_else(|| crate::error::config_err("history", 0, "1 observation"))?;
        self.predict(obs)
    }
}

/// PGD on ACT (the paper's observation attack, transferred): the *normalised* environment
/// state (PushT: the block keypoints) is perturbed inside the L-infinity ball of radius
/// `eps`, climbing ACT's own training loss, the L1 distance of the predicted chunk from the
/// chunk predicted at the clean observation, by `step * sign(gradient)` per iteration. That
/// loss is flat at the clean observation (its minimum), so the attack always starts from a
/// uniform point in the ball (drawn from `attack_rng`), whatever `random_start` says;
/// `samples` is unused (ACT is deterministic). The agent's own position is left alone.
impl AttackablePolicy for ActPolicy {
    fn predict_chunk_attacked(
        &self,
        history: &[Observation],
        pgd: &PgdConfig,
        attack_rng: &mut dyn RngCore,
        _sample_rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        use rand::Rng;
        pgd.validate()?;
        let obs = history
            .last()
            .ok_or_else(|| crate::error::config_err("history", 0, "1 observation"))?;
        let (state, env) = self.obs_tensors(&[obs])?;
        let env0 = env.ok_or_else(|| PolicyError::Input {
            name: "policy",
            reason: "PGD perturbs the environment state, and this ACT reads none".into(),
        })?;
        let clean = self
            .net
            .forward(state.as_ref(), Some(&env0), None, None)?
            .actions
            .detach();
        let n = env0.elem_count();
        let eps = pgd.eps as f32;
        let start: Vec<f32> = (0..n)
            .map(|_| attack_rng.random_range(-eps..=eps))
            .collect();
        let mut delta = Tensor::from_vec(start, env0.shape(), env0.device())?;
        for _ in 0..pgd.iterations {
            let x = candle_core::Var::from_tensor(&(&env0 + &delta)?)?;
            let out = self
                .net
                .forward(state.as_ref(), Some(x.as_tensor()), None, None)?;
            let loss = (&out.actions - &clean)?.abs()?.mean_all()?;
            let grads = loss.backward()?;
            let Some(g) = grads.get(x.as_tensor()) else {
                break;
            };
            delta = (&delta + (g.sign()? * pgd.step)?)?
                .clamp(-eps, eps)?
                .detach();
        }
        let out = self
            .net
            .forward(state.as_ref(), Some(&(&env0 + &delta)?), None, None)?;
        let mut chunk = out.actions.squeeze(0)?.flatten_all()?.to_vec1::<f32>()?;
        for row in chunk.chunks_mut(self.action_norm.dim()) {
            self.action_norm.unnormalize(row);
        }
        Ok(chunk)
    }
}
