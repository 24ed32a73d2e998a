//! Chunked visuomotor policies on candle: LeRobot-compatible Diffusion Policy.
#![forbid(unsafe_code)]

pub mod attack;
pub mod checkpoint;
pub mod config;
pub mod error;
pub mod init;
pub mod kernels;
pub mod model;
pub mod normalize;
pub mod patch;
pub mod policy;
pub mod pretrain;
pub mod scheduler;
pub mod train;
pub mod unet;
pub mod vision;

pub use attack::{PgdConfig, PgdOutcome};
pub use config::{DiffusionConfig, ObsKind};
pub use error::PolicyError;
pub use model::{DiffusionPolicy, ObsBatch, ObsGradient, StatsMap};
pub use normalize::{NormMode, Normalizer, Stats};
pub use policy::{
    AttackablePolicy, ChunkPolicy, ObsNeeds, Observation, POLICY_TYPES, attackable, load_policy,
};
