//! The environment seam: what the runner needs of a task it executes chunks in.
//!
//! [`Environment`] is shaped for an environment in this process ([`PushTEnv`], native) as
//! much as for one in another process behind a bridge (robosuite through a worker): every
//! call is one request with plain data in and out (an action slice, the observations a
//! policy asks for as [`ObsNeeds`]), nothing borrows the environment's internals, and every
//! failure is an [`EnvError`] the runner records as a failed episode.
//!
//! Conventions: `score` is the task's progress in `[0, 1]` (PushT: gym-pusht's coverage of
//! the goal); actions are in the task's units (PushT: the agent's target, pixels of the
//! 512 x 512 workspace).

use mte_policy::{ObsNeeds, Observation};
use mte_sim::render::Renderer;
use mte_sim::{PushT, ResetStream};

/// A failure of an environment.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EnvError {
    /// The simulator failed.
    #[error(transparent)]
    Sim(#[from] mte_sim::SimError),
    /// Rendering failed.
    #[error(transparent)]
    Render(#[from] mte_sim::render::RenderError),
    /// An action of the wrong length.
    #[error("action of {got} values: expected {expected} (the environment's action dimension)")]
    ActionShape {
        /// Values given.
        got: usize,
        /// Action dimension.
        expected: usize,
    },
    /// The environment was used before its first reset.
    #[error("the environment was stepped or observed before reset")]
    NotReset,
}

/// The outcome of one control step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Outcome {
    /// Task progress after the step, in `[0, 1]`.
    pub score: f64,
    /// Whether the task is solved (the episode ends).
    pub success: bool,
}

/// A task the runner executes chunks in, one control step at a time.
pub trait Environment {
    /// Action dimension `d`.
    fn action_dim(&self) -> usize;
    /// Starts an episode from reset seed `seed`; returns the initial score.
    fn reset(&mut self, seed: u64) -> Result<f64, EnvError>;
    /// The current observation, with only what `needs` asks for.
    fn observe(&mut self, needs: ObsNeeds) -> Result<Observation, EnvError>;
    /// Executes `action` (`d` values) for one control step.
    fn step(&mut self, action: &[f32]) -> Result<Outcome, EnvError>;
}

/// PushT (`mte_sim`) as an [`Environment`]: gym-pusht's task, reset from `stream`.
pub struct PushTEnv {
    env: PushT,
    stream: ResetStream,
    renderer: Option<Renderer>,
    reset: bool,
}

impl PushTEnv {
    /// PushT with the default configuration, reset seeds drawn from `stream`.
    pub fn new(stream: ResetStream) -> Self {
        Self {
            env: PushT::default(),
            stream,
            renderer: None,
            reset: false,
        }
    }

    /// The simulator, for callers that want more than the seam offers.
    pub fn sim(&self) -> &PushT {
        &self.env
    }
}

impl Environment for PushTEnv {
    fn action_dim(&self) -> usize {
        2
    }

    fn reset(&mut self, seed: u64) -> Result<f64, EnvError> {
        self.env.reset(seed, self.stream)?;
        // The renderer caches the goal and the walls: one per episode.
        self.renderer = None;
        self.reset = true;
        Ok(self.env.coverage())
    }

    fn observe(&mut self, needs: ObsNeeds) -> Result<Observation, EnvError> {
        if !self.reset {
            return Err(EnvError::NotReset);
        }
        let a = self.env.agent_pos();
        let image = match needs.image {
            Some((w, h)) => {
                let goal = self.env.goal();
                let r = self.renderer.get_or_insert_with(|| Renderer::new(goal));
                let mut px = vec![0u8; w * h * 3];
                r.observation_with_contacts_into(
                    &self.env.scene(),
                    self.env.contact_segments(),
                    w,
                    h,
                    &mut px,
                )?;
                Some(px)
            }
            None => None,
        };
        Ok(Observation {
            state: vec![a[0] as f32, a[1] as f32],
            env_state: needs
                .env_state
                .then(|| self.env.keypoints().iter().map(|&v| v as f32).collect()),
            image,
        })
    }

    fn step(&mut self, action: &[f32]) -> Result<Outcome, EnvError> {
        if !self.reset {
            return Err(EnvError::NotReset);
        }
        let &[x, y] = action else {
            return Err(EnvError::ActionShape {
                got: action.len(),
                expected: 2,
            });
        };
        let info = self.env.step([f64::from(x), f64::from(y)])?;
        Ok(Outcome {
            score: info.coverage,
            success: info.is_success,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pusht_through_the_seam_matches_the_simulator() {
        let mut env = PushTEnv::new(ResetStream::Legacy);
        let needs = ObsNeeds {
            env_state: true,
            image: Some((96, 96)),
        };
        assert!(matches!(env.observe(needs), Err(EnvError::NotReset)));
        let score = env.reset(100_000).expect("reset");
        let mut sim = PushT::default();
        sim.reset(100_000, ResetStream::Legacy).expect("reset");
        assert_eq!(score, sim.coverage());
        let o = env.observe(needs).expect("observe");
        assert_eq!(o.image.as_ref().map(Vec::len), Some(96 * 96 * 3));
        assert_eq!(o.env_state.as_ref().map(Vec::len), Some(16));
        for k in 0..20 {
            let a = [200.0 + 5.0 * k as f32, 300.0];
            let out = env.step(&a).expect("step");
            let info = sim.step([f64::from(a[0]), f64::from(a[1])]).expect("step");
            assert_eq!((out.score, out.success), (info.coverage, info.is_success));
        }
        assert_eq!(env.sim().agent_pos(), sim.agent_pos());
        let e = env.step(&[1.0, 2.0, 3.0]).expect_err("three values");
        assert!(e.to_string().contains("expected 2"), "{e}");
        let e = env.step(&[f32::NAN, 0.0]).expect_err("NaN");
        assert!(e.to_string().to_lowercase().contains("finite"), "{e}");
    }
}
