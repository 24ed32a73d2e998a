//! The runner's own cost: a 300-step PushT episode with a policy that costs nothing (a
//! fixed chunk), so what is timed is the simulator, observation bookkeeping, corruption and
//! the ensembler. Compare with `cargo bench -p mte-sim --bench step` (the simulator alone)
//! and with the policy's chunk time (`cargo bench -p mte-policy --bench unet`): the
//! difference per step is the runner's overhead. The per-stage counters of every recorded
//! episode report the same split (`mte report`, section "Runner overhead").
//!
//! `cargo bench -p mte-eval --bench runner`

use mte_eval::corruption::{CorruptionSpec, Schedule, SensorFault};
use mte_eval::pusht::{EpisodeSpec, ObsNeeds, run_episode};
use mte_policy::{ChunkPolicy, Observation, PolicyError};
use mte_sim::ResetStream;
use rand::RngCore;

fn main() {
    // As the `mte` binary does: freed tensor buffers stay in the heap.
    mte_policy::memory::keep_freed_memory();
    divan::main();
}

/// Heads for a fixed point far from the block: the episode never succeeds, so every run is
/// 300 steps.
struct Fixed;

impl ChunkPolicy for Fixed {
    fn horizon(&self) -> usize {
        16
    }
    fn needs(&self) -> ObsNeeds {
        ObsNeeds {
            env_state: true,
            image: None,
            wrist_image: false,
        }
    }
    fn n_obs_steps(&self) -> usize {
        2
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn predict_chunk(
        &self,
        _: &[Observation],
        _: &mut dyn RngCore,
    ) -> Result<Vec<f32>, PolicyError> {
        Ok(vec![20.0; 32])
    }
}

#[divan::bench(args = ["open-loop", "ewm:0.01", "median"], sample_count = 20)]
fn episode_300_steps(bencher: divan::Bencher, arm: &str) {
    let corruption = CorruptionSpec {
        fault: SensorFault::Blank.into(),
        schedule: Schedule::Burst {
            q: 2,
            phase: 0,
            period: None,
        },
    };
    let spec = EpisodeSpec {
        needs: ObsNeeds {
            env_state: true,
            image: None,
            wrist_image: false,
        },
        seed: 100_000,
        stream: ResetStream::Legacy,
        h: 2,
        max_steps: 300,
        execution: arm.parse().expect("arm"),
        corruption: &corruption,
        noise_seed: 0,
        sampling: Default::default(),
        monitors: &[],
        span: None,
    };
    bencher.bench_local(|| run_episode(&Fixed, &spec).expect("episode"));
}
