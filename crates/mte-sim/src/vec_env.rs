//! `VecEnv`: N independent PushT environments stepped in parallel.
//!
//! Every environment owns its physics world and is stepped by exactly one thread, so results
//! do not depend on the number of threads or on scheduling (a test checks 1 thread against
//! many). A step splits the environments into one contiguous block per thread (the thread
//! count is rayon's, so `RAYON_NUM_THREADS` and `ThreadPool::install` set it); the calling
//! thread takes the first block and scoped threads the others, for steps and resets alike.

/// The fewest environments stepped on several threads; fewer run on the calling thread. A
/// step is 10-20 us of physics, and starting a thread costs about as much
/// (`benches/step.rs`, `vec_env_tick` against `plain_loop_tick`).
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
        self.map_envs(seeds, |e, &s| e.reset(s, stream))
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
        self.map_envs(actions, |e, &a| e.step(a))
    }

    /// `f(env i, &inputs[i])` for every environment, in order: on the calling thread below
    /// [`PARALLEL_MIN_ENVS`], else one contiguous block per thread, the calling thread taking
    /// the first and scoped threads the others (a tick wakes `threads - 1` threads and
    /// nothing waits on a pool's sleeping workers).
    fn map_envs<A: Sync, R: Send>(
        &mut self,
        inputs: &[A],
        f: impl Fn(&mut PushT, &A) -> Result<R, SimError> + Sync,
    ) -> Result<Vec<R>, SimError> {
        if !self.parallel() {
            return self
                .envs
                .iter_mut()
                .zip(inputs)
                .map(|(e, a)| f(e, a))
                .collect();
        }
        let chunk = self.chunk();
        let f = &f;
        let mut out: Vec<Result<R, SimError>> = Vec::with_capacity(self.envs.len());
        std::thread::scope(|scope| {
            let mut blocks = self.envs.chunks_mut(chunk).zip(inputs.chunks(chunk));
            let first = blocks.next();
            let handles: Vec<_> = blocks
                .map(|(envs, ins)| {
                    scope.spawn(move || {
                        envs.iter_mut()
                            .zip(ins)
                            .map(|(e, a)| f(e, a))
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            if let Some((envs, ins)) = first {
                out.extend(envs.iter_mut().zip(ins).map(|(e, a)| f(e, a)));
            }
            for h in handles {
                // A worker only panics on a bug; its panic continues here.
                match h.join() {
                    Ok(v) => out.extend(v),
                    Err(p) => std::panic::resume_unwind(p),
                }
            }
        });
        out.into_iter().collect()
    }

    /// Whether a tick is worth more threads: not below [`PARALLEL_MIN_ENVS`] environments,
    /// nor with one thread.
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
