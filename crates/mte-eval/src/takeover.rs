//! Corrective demonstrations on PushT (DAgger's data, with the scripted expert as teacher):
//! a trained policy drives an episode under one arm (an aggregator at stride `h`, or open
//! loop) up to a switch step, then the scripted expert takes over from the state the policy
//! reached and only the expert's frames are recorded, as a demonstration that starts there.
//!
//! A policy trained on its teacher's states alone meets, under the deployed mean, states the
//! teacher never visited (covariate shift); these episodes show the teacher's way back from
//! exactly those states. Episode `i` resets with `seed + i`; its switch step is drawn
//! uniformly from `switch` by a ChaCha8 stream of `(seed, i)`, the policy's sampling noise
//! from `noise_seed` as in every evaluation, the expert's action noise as in
//! [`mte_data::generate`]. Episodes run in parallel batches and are written in index order,
//! so the dataset does not depend on the number of threads.

use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use mte_data::dataset::Frame;
use mte_data::{DataError, GenerateConfig, Info, in_order, record_expert};
use mte_policy::ChunkPolicy;
use mte_sim::expert::Expert;

use crate::corruption::CorruptionSpec;
use crate::environment::PushTEnv;
use crate::episode::NoObserver;
use crate::pusht::{EpisodeSpec, Execution, RolloutError, Sampling, run_episode_in};

/// What to run and record.
#[derive(Clone, Debug, PartialEq)]
pub struct TakeoverConfig {
    /// Episodes, seeds, reset stream, recorded observations, step limit and the expert's
    /// settings (as for demonstrations).
    pub record: GenerateConfig,
    /// The policy's arm before the switch.
    pub execution: Execution,
    /// The policy's query stride `h` (control steps).
    pub h: usize,
    /// Smallest and largest switch step (control steps, both included).
    pub switch: (usize, usize),
    /// Seed of the policy's per-query sampling noise.
    pub noise_seed: u64,
}

/// What one episode did.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TakeoverEpisode {
    /// Episode index `i`.
    pub index: usize,
    /// Reset seed.
    pub seed: u64,
    /// Control step at which the expert took over.
    pub switch: usize,
    /// Coverage of the state the policy handed over (fraction of the goal).
    pub coverage_at_switch: f64,
    /// The policy succeeded before the switch: nothing was recorded.
    pub policy_success: bool,
    /// Frames the expert recorded.
    pub frames: usize,
    /// The expert reached success.
    pub expert_success: bool,
    /// Maximum coverage from the switch on.
    pub max_coverage: f64,
}

/// Why corrective demonstrations could not be made.
#[derive(Debug, thiserror::Error)]
pub enum TakeoverError {
    /// A setting outside its range.
    #[error("`{field}` = {value}: expected {expected}")]
    Config {
        /// Field.
        field: &'static str,
        /// Value.
        value: String,
        /// Expectation.
        expected: String,
    },
    /// The policy's part of an episode failed.
    #[error("episode {index} (seed {seed}), the policy's part: {source}")]
    Rollout {
        /// Episode index.
        index: usize,
        /// Reset seed.
        seed: u64,
        /// The runner's error.
        source: RolloutError,
    },
    /// Recording or writing failed.
    #[error(transparent)]
    Data(#[from] DataError),
}

impl TakeoverConfig {
    /// Check every field.
    pub fn validate(&self) -> Result<(), TakeoverError> {
        self.record.validate()?;
        let (lo, hi) = self.switch;
        let max = self.record.max_steps;
        if lo == 0 || lo > hi || hi >= max {
            return Err(TakeoverError::Config {
                field: "switch",
                value: format!("{lo}..={hi}"),
                expected: format!("1 <= first <= last < the step limit {max}"),
            });
        }
        if self.h == 0 {
            return Err(TakeoverError::Config {
                field: "h",
                value: "0".into(),
                expected: "at least 1".into(),
            });
        }
        Ok(())
    }

    /// The switch step of episode `i`.
    pub fn switch_of(&self, i: usize) -> usize {
        let key = self.record.seed.rotate_left(17) ^ (i as u64) ^ (0x7A4E_0FF5_u64 << 32);
        let mut rng = ChaCha8Rng::seed_from_u64(key);
        rng.random_range(self.switch.0..=self.switch.1)
    }
}

/// One episode: the policy's part, then the expert's frames.
fn run_one(
    policy: &(dyn ChunkPolicy + Sync),
    config: &TakeoverConfig,
    i: usize,
) -> Result<(TakeoverEpisode, Vec<Frame>), TakeoverError> {
    let r = &config.record;
    let seed = r.seed + i as u64;
    let switch = config.switch_of(i);
    let spec = EpisodeSpec {
        needs: policy.needs(),
        seed,
        stream: r.stream,
        h: config.h,
        max_steps: switch,
        execution: config.execution,
        corruption: &CorruptionSpec::CLEAN,
        noise_seed: config.noise_seed,
        sampling: Sampling::Independent,
        monitors: &[],
        span: None,
    };
    let mut env = PushTEnv::new(r.stream);
    let record = run_episode_in(&mut env, policy, &spec, &mut NoObserver).map_err(|source| {
        TakeoverError::Rollout {
            index: i,
            seed,
            source,
        }
    })?;
    let mut sim = env.into_sim();
    let coverage_at_switch = sim.coverage();
    let (frames, max_coverage) = if record.success {
        (Vec::new(), coverage_at_switch)
    } else {
        let mut expert = Expert::new(r.expert.clone()).map_err(DataError::from)?;
        let mut rng = ChaCha8Rng::seed_from_u64(r.seed ^ (i as u64).rotate_left(32));
        record_expert(&mut sim, &mut expert, &mut rng, r, record.steps)?
    };
    Ok((
        TakeoverEpisode {
            index: i,
            seed,
            switch: record.steps,
            coverage_at_switch,
            policy_success: record.success,
            frames: frames.len(),
            expert_success: frames.iter().any(|f| f.success),
            max_coverage,
        },
        frames,
    ))
}

/// Run `config.record.episodes` takeover episodes of `policy` and write the expert's frames
/// into `out` (a new directory; an episode the policy finished before its switch writes
/// nothing), calling `on_episode` for every episode in index order after its frames are
/// on disk. `policy_name` goes into `info.json` beside the configuration and every
/// episode's [`TakeoverEpisode`]. Uses the current rayon pool.
pub fn generate_takeover(
    policy: &(dyn ChunkPolicy + Sync),
    policy_name: &str,
    config: &TakeoverConfig,
    out: &Path,
    on_episode: &(dyn Fn(&TakeoverEpisode) + Sync),
) -> Result<Info, TakeoverError> {
    config.validate()?;
    let r = &config.record;
    let mut writer = r.writer(out)?;
    let mut episodes = Vec::with_capacity(r.episodes);
    in_order(
        r.episodes,
        |i| run_one(policy, config, i),
        |(episode, frames)| {
            if !frames.is_empty() {
                writer.push_episode(episode.seed, episode.max_coverage, &frames)?;
            }
            on_episode(&episode);
            episodes.push(episode);
            Ok::<_, TakeoverError>(())
        },
    )?;
    let generator = serde_json::json!({
        "takeover": {
            "record": r,
            "execution": config.execution.to_string(),
            "h": config.h,
            "switch": config.switch,
            "noise_seed": config.noise_seed,
        },
        "policy": policy_name,
        "episodes": episodes,
    });
    Ok(writer.finish(generator)?)
}
