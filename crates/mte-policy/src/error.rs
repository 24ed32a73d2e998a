//! Typed errors of the policy crate.

use std::path::PathBuf;

/// What can go wrong building, loading or running a policy.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    /// A configuration field outside its valid range.
    #[error("config field `{field}` = {value}: expected {expected}")]
    Config {
        /// Field name (LeRobot's `config.json` key).
        field: &'static str,
        /// Offending value, printed.
        value: String,
        /// What was expected.
        expected: String,
    },
    /// A checkpoint tensor that is missing or has the wrong shape.
    #[error("checkpoint {path}: {reason}")]
    Checkpoint {
        /// The checkpoint file or directory.
        path: PathBuf,
        /// Which key is missing or misshapen, and what was expected.
        reason: String,
    },
    /// An observation or chunk with the wrong size or non-finite values.
    #[error("input `{name}`: {reason}")]
    Input {
        /// Which input.
        name: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A compute device that cannot be opened or cannot run this policy.
    #[error("device {device}: {reason}")]
    Device {
        /// The device, as named (`cuda:0`).
        device: String,
        /// Why not.
        reason: String,
    },
    /// A scheduler error.
    #[error("scheduler: {0}")]
    Scheduler(#[from] crate::scheduler::SchedulerError),
    /// An error from candle.
    #[error("tensor: {0}")]
    Candle(#[from] candle_core::Error),
    /// File I/O.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// JSON (de)serialisation.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: serde_json::Error,
    },
}

/// A [`PolicyError::Config`] for `field` holding `value` (printed with `Debug`), where
/// `expected` was wanted.
pub fn config_err(
    field: &'static str,
    value: impl std::fmt::Debug,
    expected: impl Into<String>,
) -> PolicyError {
    PolicyError::Config {
        field,
        value: format!("{value:?}"),
        expected: expected.into(),
    }
}
