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
    /// An environment in a worker process failed (it crashed, hung, refused a request).
    #[error(transparent)]
    Bridge(#[from] crate::bridge::BridgeError),
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
    /// The policy reads an observation this environment does not have.
    #[error("{environment} has no {observation}: the policy reads it")]
    Unsupported {
        /// The environment.
        environment: String,
        /// The observation asked for.
        observation: &'static str,
    },
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

/// Where a run's episodes happen: native PushT, or a [`crate::bridge::Target`] in a worker
/// process. Text form (CLI `--env`, sweep specs' `env`): `pusht`, `gym:<module>/<EnvId>`,
/// `robomimic:<task>`, `toy:`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
pub enum EnvTarget {
    /// [`PushTEnv`], in this process.
    #[default]
    PushT,
    /// An environment behind the bridge.
    Bridge(crate::bridge::Target),
}

impl EnvTarget {
    /// Whether this is native PushT (sweep specs leave it out).
    pub fn is_pusht(&self) -> bool {
        *self == EnvTarget::PushT
    }

    /// A fresh environment: native PushT reset from `stream`, or a worker started for a
    /// policy that reads `needs`.
    pub fn open(
        &self,
        stream: ResetStream,
        needs: ObsNeeds,
        options: &crate::bridge::BridgeOptions,
    ) -> Result<Box<dyn Environment + Send>, EnvError> {
        Ok(match self {
            EnvTarget::PushT => Box::new(PushTEnv::new(stream)),
            EnvTarget::Bridge(t) => Box::new(crate::bridge::BridgeEnv::spawn(t, needs, options)?),
        })
    }
}

impl std::str::FromStr for EnvTarget {
    type Err = crate::bridge::TargetError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "pusht" => Ok(EnvTarget::PushT),
            _ => s.parse().map(EnvTarget::Bridge),
        }
    }
}

impl std::fmt::Display for EnvTarget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            EnvTarget::PushT => f.write_str("pusht"),
            EnvTarget::Bridge(t) => t.fmt(f),
        }
    }
}

impl serde::Serialize for EnvTarget {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for EnvTarget {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
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

    /// The simulator as the last step left it.
    pub fn into_sim(self) -> PushT {
        self.env
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
        if needs.wrist_image {
            return Err(EnvError::Unsupported {
                environment: "PushT".into(),
                observation: "wrist camera",
            });
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
            wrist_image: None,
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
    fn env_targets_round_trip_as_text() {
        for s in [
            "pusht",
            "gym:gym_pusht/PushT-v0",
            "robomimic:square",
            "toy:",
        ] {
            let t: EnvTarget = s.parse().expect(s);
            assert_eq!(t.to_string(), s);
            let json = serde_json::to_string(&t).expect("json");
            assert_eq!(serde_json::from_str::<EnvTarget>(&json).expect("back"), t);
        }
        assert!(EnvTarget::default().is_pusht());
        let e = serde_json::from_str::<EnvTarget>("\"mujoco:x\"").expect_err("unknown");
        assert!(e.to_string().contains("mujoco:x"), "{e}");
    }

    #[test]
    fn pusht_through_the_seam_matches_the_simulator() {
        let mut env = PushTEnv::new(ResetStream::Legacy);
        let needs = ObsNeeds {
            env_state: true,
            image: Some((96, 96)),
            wrist_image: false,
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
        let wrist = ObsNeeds {
            wrist_image: true,
            ..needs
        };
        let e = env.observe(wrist).expect_err("no wrist camera");
        assert!(matches!(e, EnvError::Unsupported { .. }), "{e}");
        assert!(e.to_string().contains("wrist camera"), "{e}");
        let e = env.step(&[1.0, 2.0, 3.0]).expect_err("three values");
        assert!(e.to_string().contains("expected 2"), "{e}");
        let e = env.step(&[f32::NAN, 0.0]).expect_err("NaN");
        assert!(e.to_string().to_lowercase().contains("finite"), "{e}");
    }
}
