//! Chunked visuomotor policies on candle: LeRobot-compatible Diffusion Policy.
#![forbid(unsafe_code)]

pub mod diffusion;
pub mod error;
pub mod init;
pub mod kernels;
pub mod normalize;
pub mod policy;
pub mod vision;

pub use diffusion::{attack, checkpoint, config, model, patch, pretrain, scheduler, train, unet};

pub use attack::{PgdConfig, PgdOutcome};
pub use config::{DiffusionConfig, ObsKind};
pub use error::PolicyError;
pub use model::{DiffusionPolicy, ObsBatch, ObsGradient, StatsMap};
pub use normalize::{NormMode, Normalizer, Stats};
pub use policy::{
    AttackablePolicy, ChunkPolicy, ObsNeeds, Observation, POLICY_TYPES, attackable, load_policy,
};
