//! The error type of every fallible operation of this crate.

use std::path::{Path, PathBuf};
use thiserror::Error;

/// What went wrong, naming the file involved.
#[derive(Debug, Error)]
pub enum ModelError {
    /// A required file is absent.
    #[error("{}: missing ({what})", path.display())]
    Missing {
        /// The file looked for.
        path: PathBuf,
        /// What it should have held.
        what: &'static str,
    },
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A file is present but unusable (bad JSON, wrong tensor shapes, corrupt Parquet…).
    #[error("{}: {message}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// Running the model failed.
    #[error("encoding failed: {0}")]
    Inference(String),
    /// A caller passed an unusable argument.
    #[error("invalid argument: {0}")]
    Argument(String),
    /// The corpus could not be read or updated.
    #[error("corpus: {0}")]
    Corpus(String),
}

impl ModelError {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// `path` holds something unusable.
    pub fn invalid(path: &Path, message: impl std::fmt::Display) -> Self {
        Self::Invalid {
            path: path.to_path_buf(),
            message: message.to_string(),
        }
    }

    /// A model run failed.
    pub fn inference(e: impl std::fmt::Display) -> Self {
        Self::Inference(e.to_string())
    }
}
