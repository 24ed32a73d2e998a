//! Typed errors of dataset reading, writing and sampling.

use std::path::{Path, PathBuf};

/// What can go wrong with a dataset.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// An I/O failure on a named file.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A file whose contents are not what the format says.
    #[error("{path}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A configuration value outside its valid range.
    #[error("`{field}` = {value}: expected {expected}")]
    Config {
        /// Field name.
        field: &'static str,
        /// Offending value, printed.
        value: String,
        /// What was expected.
        expected: &'static str,
    },
    /// The simulator or expert failed.
    #[error("simulation: {0}")]
    Sim(#[from] mte_sim::SimError),
    /// The expert's configuration is invalid.
    #[error("expert: {0}")]
    Expert(#[from] mte_sim::expert::ExpertConfigError),
    /// Rendering failed.
    #[error("render: {0}")]
    Render(#[from] mte_sim::render::RenderError),
}

impl DataError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        DataError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}
