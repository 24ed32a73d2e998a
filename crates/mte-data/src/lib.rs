//! Demonstration datasets for mte.
//!
//! On-disk format (`mte-demo-v1`), chosen over LeRobot's parquet layout because writing
//! parquet from Rust would add the arrow/parquet stack (a large build for a small need) and
//! LeRobot's layout changes between versions; the feature names are LeRobot's, so mapping
//! to a `LeRobotDataset` is a rename-free copy (see `docs/datasets.md`):
//!
//! ```text
//! DIR/info.json          format, fps, features (dtype, shape, file), episodes, generator
//! DIR/episodes.jsonl     one line per episode: index, seed, start frame, length, success, max coverage
//! DIR/stats.json         per feature: min, max, mean, std (LeRobot's meta/stats.json keys)
//! DIR/data/<feature>.npy one array per feature, frames first (numpy.load reads them)
//! ```
//!
//! Frame t of an episode holds the observation before action t, action t, and the reward,
//! done and success flags after it (LeRobot's `next.*` convention).
#![forbid(unsafe_code)]

pub mod dataset;
pub mod error;
pub mod generate;
pub mod npy;
pub mod sampler;
pub mod stats;

pub use dataset::{Dataset, EpisodeMeta, Feature, Info};
pub use error::DataError;
pub use generate::{GenerateConfig, ObsSet, generate, in_order, record_expert};
pub use sampler::{Window, WindowSampler};
pub use stats::FeatureStats;
