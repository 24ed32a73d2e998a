//! Diffusion Policy (Chi et al., as LeRobot 0.4.4 implements it), one folder as
//! candle-transformers and LeRobot keep one per model: the config schema and presets
//! (`config`), the conditional U-Net 1D (`unet`) or the Diffusion Transformer's noise network
//! (`transformer`), DDPM/DDIM schedulers (`scheduler`), the
//! model with its observation encoding, sampling, loss and observation gradients (`model`),
//! LeRobot-compatible checkpoints (`checkpoint`), training (`train`), the encoder's
//! keypoint-regression warm start (`pretrain`), PGD on its loss (`attack`), and the physical
//! patch, encoder fine-tuning and gradient probe (`patch`), and the count of frames that
//! give PGD a pixel gradient at all (`activity`). The crate root re-exports each
//! module under its old path (`mte_policy::config`, ...).

pub mod activity;
pub mod attack;
pub mod checkpoint;
pub mod config;
pub mod model;
pub mod patch;
pub mod pretrain;
pub mod scheduler;
pub mod train;
pub mod transformer;
pub mod unet;
