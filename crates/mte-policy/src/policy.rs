//! The policy seam, free of any tensor type: what an evaluation runner, a controller or a
//! bridge needs of a chunked policy, whatever network (Diffusion Policy, ACT, a script)
//! is behind it.
//!
//! - [`Observation`]: one observation step as the environment reports it.
//! - [`ObsNeeds`]: which observations the policy reads, so an environment renders only those.
//! - [`ChunkPolicy`]: a history of `T_o` observations in, one `T_p x d` chunk out, randomness
//!   injected; [`ChunkPolicy::predict_chunks`] answers a batch of such queries at once, each
//!   exactly as it would be answered alone (batch invariance).
//! - [`AttackablePolicy`]: the gradient access that PGD needs, offered separately
//!   ([`ChunkPolicy::attackable`]); policies without an observation gradient refuse attacks
//!   with a typed error instead of implementing a stub.
//! - [`load_policy`]: a checkpoint directory to a policy, dispatching on `config.json`'s
//!   `type` ([`POLICY_TYPES`] lists the known ones).
//!
//! Conventions: actions and observations unnormalised, in the environment's units (PushT:
//! pixels of the 512 x 512 workspace); row `r` of the chunk from the query at control time
//! `t` is the action for `t - (T_o - 1) + r`.

use std::path::Path;

use rand::RngCore;

use crate::attack::PgdConfig;
use crate::error::{PolicyError, config_err};

/// One observation step, unnormalised, as the environment reports it.
#[derive(Clone, Debug, PartialEq)]
pub struct Observation {
    /// Robot state (PushT: agent position, px).
    pub state: Vec<f32>,
    /// Environment state (PushT: 16 keypoint coordinates, px), if the policy uses it.
    pub env_state: Option<Vec<f32>>,
    /// Camera frame, RGB u8 HWC, if the policy uses images (PushT: the top view; robomimic:
    /// `agentview_image`, flipped upright as robomimic does).
    pub image: Option<Vec<u8>>,
    /// The wrist camera's frame, RGB u8 HWC at `image`'s size, if the policy uses it
    /// (robomimic: `robot0_eye_in_hand_image`, flipped upright; PushT has no wrist camera).
    pub wrist_image: Option<Vec<u8>>,
}

/// Which observations a policy reads (the robot state always).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ObsNeeds {
    /// The environment state vector (PushT: the 16 keypoints).
    pub env_state: bool,
    /// Rendered frames of this (width, height), px.
    pub image: Option<(usize, usize)>,
    /// The wrist camera's frames too, at `image`'s size (so it needs `image`).
    pub wrist_image: bool,
}

/// A chunked policy as a runner sees it: a history of `n_obs_steps` observations in, one
/// chunk of `horizon x action_dim` actions out; randomness injected.
pub trait ChunkPolicy {
    /// Rows per chunk (T_p).
    fn horizon(&self) -> usize;
    /// Observations per query (T_o).
    fn n_obs_steps(&self) -> usize;
    /// Action dimension.
    fn action_dim(&self) -> usize;
    /// The observations the policy reads.
    fn needs(&self) -> ObsNeeds;
    /// Predict a chunk (row-major, unnormalised; row `r` is for time `t - (T_o - 1) + r`).
    fn predict_chunk(
        &self,
        history: &[Observation],
        rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError>;
    /// The policy's gradient access for attacks, if it has one.
    fn attackable(&self) -> Option<&dyn AttackablePolicy> {
        None
    }
    /// Answer several queries at once (one network evaluation per denoising step for all of
    /// them, where the policy can batch). Contract: chunk `i` is bit for bit what
    /// [`ChunkPolicy::predict_chunk`] returns for query `i` alone, and each query's stream
    /// advances exactly as it would alone, so a result never depends on which other queries
    /// shared its batch. The default answers them one by one.
    ///
    /// # Errors
    /// As [`ChunkPolicy::predict_chunk`]; a batch fails as a whole (a caller that needs to
    /// know which query failed asks them one by one with fresh streams).
    fn predict_chunks(&self, queries: &mut [Query<'_>]) -> Result<Vec<Vec<f32>>, PolicyError> {
        queries
            .iter_mut()
            .map(|q| self.predict_chunk(q.history, &mut *q.rng))
            .collect()
    }
}

/// One query of a batch: the history it sees and its own sampling stream.
pub struct Query<'a> {
    /// `n_obs_steps` observations, oldest first.
    pub history: &'a [Observation],
    /// The query's sampling stream (the same one a single query would get).
    pub rng: &'a mut dyn RngCore,
}

/// One attacked query of a batch: its history and its two streams.
pub struct AttackedQuery<'a> {
    /// `n_obs_steps` clean observations, oldest first.
    pub history: &'a [Observation],
    /// Drives the attack (random start, timesteps, noise).
    pub attack_rng: &'a mut dyn RngCore,
    /// Drives the sampling of the clean and the executed chunk.
    pub sample_rng: &'a mut dyn RngCore,
}

/// A policy whose observation can be attacked through its own loss's gradient.
pub trait AttackablePolicy {
    /// The chunk predicted from the observation after a PGD attack on the policy's own
    /// loss ([`crate::attack`]): `attack_rng` drives the attack, `sample_rng` the sampling.
    fn predict_chunk_attacked(
        &self,
        history: &[Observation],
        pgd: &PgdConfig,
        attack_rng: &mut dyn RngCore,
        sample_rng: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError>;

    /// Attack several queries at once, under the batch-invariance contract of
    /// [`ChunkPolicy::predict_chunks`]: chunk `i` is what
    /// [`AttackablePolicy::predict_chunk_attacked`] returns for query `i` alone. The default
    /// attacks them one by one.
    fn predict_chunks_attacked(
        &self,
        queries: &mut [AttackedQuery<'_>],
        pgd: &PgdConfig,
    ) -> Result<Vec<Vec<f32>>, PolicyError> {
        queries
            .iter_mut()
            .map(|q| {
                self.predict_chunk_attacked(q.history, pgd, &mut *q.attack_rng, &mut *q.sample_rng)
            })
            .collect()
    }
}

/// `policy`'s attack access, or the typed refusal for a policy without a gradient.
pub fn attackable(policy: &dyn ChunkPolicy) -> Result<&dyn AttackablePolicy, PolicyError> {
    policy.attackable().ok_or_else(|| PolicyError::Input {
        name: "policy",
        reason: "this policy offers no observation gradient, so PGD cannot attack it".into(),
    })
}

/// The policy types [`load_policy`] knows, as `config.json` spells them.
pub const POLICY_TYPES: &[&str] = &["diffusion", "act"];

/// Loads the policy in checkpoint directory `dir` (LeRobot's layout: `config.json` with its
/// `type`, weights, processor files) on the CPU.
///
/// # Errors
/// [`PolicyError::Io`] or [`PolicyError::Checkpoint`] for a missing or malformed
/// `config.json`, [`PolicyError::Config`] naming the known types for an unknown `type`, and
/// the policy's own load errors.
pub fn load_policy(dir: &Path) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError> {
    load_policy_on(dir, &candle_core::Device::Cpu)
}

/// [`load_policy`] with the weights on `device` (see [`crate::ComputeDevice`]).
///
/// # Errors
/// As [`load_policy`], and [`PolicyError::Device`] for an ACT checkpoint on a non-CPU device
/// (ACT is CPU-only for now).
pub fn load_policy_on(
    dir: &Path,
    device: &candle_core::Device,
) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError> {
    let path = dir.join("config.json");
    let text = std::fs::read_to_string(&path).map_err(|source| PolicyError::Io {
        path: path.clone(),
        source,
    })?;
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| PolicyError::Checkpoint {
            path: path.clone(),
            reason: format!("not JSON: {e}"),
        })?;
    let kind = value.get("type").and_then(|t| t.as_str()).unwrap_or("");
    match kind {
        "diffusion" => Ok(Box::new(crate::checkpoint::load(dir, device)?)),
        "act" if !device.is_cpu() => Err(PolicyError::Device {
            // Named as `--device` spells it.
            device: crate::ComputeDevice::from_location(device.location())
                .map_or_else(|| format!("{:?}", device.location()), |d| d.to_string()),
            reason: "ACT runs on the CPU only; load it with --device cpu".into(),
        }),
        "act" => Ok(Box::new(crate::act::ActPolicy::load(dir)?)),
        other => Err(config_err(
            "type",
            other,
            format!("one of the known policy types: {}", POLICY_TYPES.join(", ")),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_and_missing_types_name_the_known_ones() {
        let dir = tempfile::tempdir().expect("tmp");
        std::fs::write(dir.path().join("config.json"), r#"{"type": "vla"}"#).expect("write");
        let e = load_policy(dir.path())
            .err()
            .expect("unknown type")
            .to_string();
        assert!(
            e.contains("`type` = \"vla\"") && e.contains("diffusion, act"),
            "{e}"
        );
        std::fs::write(dir.path().join("config.json"), "{}").expect("write");
        let e = load_policy(dir.path()).err().expect("no type").to_string();
        assert!(e.contains("known policy types"), "{e}");
        std::fs::write(dir.path().join("config.json"), "{").expect("write");
        let e = load_policy(dir.path()).err().expect("not json").to_string();
        assert!(e.contains("not JSON"), "{e}");
        let e = load_policy(&dir.path().join("missing"))
            .err()
            .expect("no dir")
            .to_string();
        assert!(e.contains("config.json"), "{e}");
    }
}
