//! `VecEnv`: N independent PushT environments stepped in parallel with rayon.
//!
//! Every environment owns its physics world and is stepped by exactly one task, so results do
//! not depend on the number of threads or on scheduling (a test checks 1 thread against many).

use rayon::prelude::*;

/// The fewest environments stepped on the thread pool; fewer run on the calling thread. A
/// step is about 20 us of physics, and waking the pool's workers costs several times that.
pub const PARALLEL_MIN_ENVS: usize = 8;

use crate::env::{PhysicsConfig, PushT, State, StepInfo};
use crate::error::SimError;
use crate::rng::ResetStream;

/// A batch of PushT environments.
pub struct VecEnv {
    envs: Vec<PushT>,
}

impl VecEnv {
    /// `n` environments with the same physics configuration.
    pub fn new(n: usize, config: PhysicsConfig) -> Self {
        VecEnv {
            envs: (0..n).map(|_| PushT::new(config)).collect(),
        }
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.envs.len()
    }

    /// True when the batch is empty.
    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// The environments, for reading observations.
    pub fn envs(&self) -> &[PushT] {
        &self.envs
    }

    /// Mutable access to the environments.
    pub fn envs_mut(&mut self) -> &mut [PushT] {
        &mut self.envs
    }

    /// Reset environment `i` with seed `seeds[i]`.
    pub fn reset(&mut self, seeds: &[u64], stream: ResetStream) -> Result<Vec<State>, SimError> {
        if seeds.len() != self.envs.len() {
            return Err(SimError::BatchSize {
                actions: seeds.len(),
                envs: self.envs.len(),
            });
        }
        if !self.parallel() {
            return self
                .envs
                .iter_mut()
                .zip(seeds)
                .map(|(e, &s)| e.reset(s, stream))
                .collect();
        }
        let chunk = self.chunk();
        self.envs
            .par_iter_mut()
            .zip(seeds.par_iter())
            .with_min_len(chunk)
            .map(|(e, &s)| e.reset(s, stream))
            .collect()
    }

    /// Step environment `i` towards `actions[i]`. On error no environment is stepped.
    pub fn step(&mut self, actions: &[[f64; 2]]) -> Result<Vec<StepInfo>, SimError> {
        if actions.len() != self.envs.len() {
            return Err(SimError::BatchSize {
                actions: actions.len(),
                envs: self.envs.len(),
            });
        }
        if let Some(a) = actions.iter().find(|a| !a.iter().all(|v| v.is_finite())) {
            return Err(SimError::NonFiniteAction { action: *a });
        }
        if !self.parallel() {
            return self
                .envs
                .iter_mut()
                .zip(actions)
                .map(|(e, &a)| e.step(a))
                .collect();
        }
        let chunk = self.chunk();
        self.envs
            .par_iter_mut()
            .zip(actions.par_iter())
            .with_min_len(chunk)
            .map(|(e, &a)| e.step(a))
            .collect()
    }

    /// Whether a tick is worth the pool: below [`PARALLEL_MIN_ENVS`] environments, or with
    /// one thread, waking workers costs more than the physics (`benches/step.rs`,
    /// `vec_env`).
    fn parallel(&self) -> bool {
        self.envs.len() >= PARALLEL_MIN_ENVS && rayon::current_num_threads() > 1
    }

    /// Environments per task: one contiguous block per thread.
    fn chunk(&self) -> usize {
        self.envs
            .len()
            .div_ceil(rayon::current_num_threads())
            .max(1)
    }
}
