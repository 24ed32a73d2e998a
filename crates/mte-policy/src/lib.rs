//! # mte-policy: chunked visuomotor policies on candle
//!
//! - [`policy`]: the seam, free of tensor types. [`ChunkPolicy`] (a history of `T_o`
//!   [`Observation`]s in, a `T_p x d` chunk out, randomness injected, [`ObsNeeds`] saying
//!   what it reads), [`AttackablePolicy`] (the gradient access PGD needs) and
//!   [`load_policy`], which dispatches on a checkpoint's `config.json` `type`
//!   ([`load_policy_on`] puts it on a [`ComputeDevice`]: the CPU or, built with `cuda`, a GPU).
//! - [`diffusion`]: Diffusion Policy as LeRobot 0.4.4 defines it (config, U-Net, schedulers,
//!   model, checkpoints in both LeRobot layouts, training, PGD, the physical patch and the
//!   encoder defence); its modules are re-exported here under their old paths.
//! - Shared pieces: [`vision`] (the ResNet-18-GN encoder), [`kernels`] (fused CPU kernels with
//!   backward passes), [`normalize`], [`init`] (seeded initialisation; candle's own CPU
//!   initialisers use a global RNG), `training` (the loop's model-independent pieces:
//!   per-step random streams, checkpoint schedule, gradient clipping, the warm-up + cosine
//!   learning rate, the weights' moving average, the loss trace),
//!   [`memory`] (an opt-in allocator setting for binaries).
//!
//! Conventions: observations and actions unnormalised in the environment's units (PushT:
//! pixels of the 512 x 512 workspace), images RGB u8 HWC; every random draw comes from an
//! injected seeded generator.
// One exception, in `memory`: two calls to glibc's `mallopt`.
#![deny(unsafe_code)]

pub mod act;
pub mod attention;
pub mod compute;
pub mod diffusion;
pub mod error;
pub mod init;
pub mod kernels;
pub mod memory;
pub mod normalize;
pub mod overrides;
pub mod policy;
mod training;
pub mod vision;

pub use diffusion::{
    activity, attack, checkpoint, config, model, patch, pretrain, scheduler, train, transformer,
    unet,
};

pub use attack::{PgdConfig, PgdOutcome};
pub use compute::ComputeDevice;
pub use config::{DiffusionConfig, ObsKind};
pub use error::PolicyError;
pub use model::{DiffusionPolicy, ObsBatch, ObsGradient, StatsMap};
pub use normalize::{NormMode, Normalizer, Stats};
pub use policy::{
    AttackablePolicy, AttackedQuery, ChunkPolicy, ObsNeeds, Observation, POLICY_TYPES, Query,
    attackable, load_policy, load_policy_on,
};
