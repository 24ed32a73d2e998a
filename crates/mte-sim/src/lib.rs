//! Native PushT for mte: gym-pusht's environment on rapier2d physics, exact seeded resets,
//! exact coverage, observations (state, keypoints, pixels), a batch of environments, and a
//! scripted expert that makes demonstrations.
//!
//! Conventions: world units are pixels of the 512 x 512 canvas, y points down, angles are
//! radians, the control rate is 10 Hz (see [`geometry`]).
#![forbid(unsafe_code)]

pub mod coverage;
pub mod env;
pub mod error;
pub mod expert;
pub mod geometry;
pub mod patch;
pub mod render;
pub mod rng;
pub mod rollout;
pub mod vec_env;

pub use env::{PhysicsConfig, PushT, Snapshot, State, StepInfo};
pub use error::SimError;
pub use expert::{Expert, ExpertConfig};
pub use geometry::{GOAL, Pose};
pub use patch::{Patch, PatchError};
pub use rng::ResetStream;
pub use vec_env::VecEnv;
