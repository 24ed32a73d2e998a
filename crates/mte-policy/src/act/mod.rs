//! ACT, the Action Chunking Transformer (Zhao et al., 2023), as LeRobot 0.4.4 defines it:
//! the config schema and presets (`config`), the network with its CVAE objective (`model`),
//! the policy behind the seam with LeRobot-compatible checkpoints (`policy`), training
//! (`train`, optionally with the camera backbone frozen and its feature maps cached) and a
//! warm start of the camera backbone from an image Diffusion Policy's encoder, its
//! GroupNorms turned into calibrated frozen BatchNorms (`warm_start`; an mte extension, as no
//! ImageNet weights can be had here). Observations: the state (PushT keypoints) and at most one camera through
//! torchvision's ResNet-18 with FrozenBatchNorm (`crate::vision`); a checkpoint with two or
//! more cameras is refused with a typed error.

pub mod config;
pub mod model;
pub mod policy;
pub mod train;
pub mod warm_start;

pub use config::ActConfig;
pub use model::ActNet;
pub use policy::ActPolicy;
