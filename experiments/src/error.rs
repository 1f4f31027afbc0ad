//! The error type of every fallible operation of this crate.

use motionscale_core::FileError;
use std::path::Path;
use thiserror::Error;

/// What went wrong, naming the file or plan point involved.
#[derive(Debug, Error)]
pub enum SweepError {
    /// A file could not be read or written, or is unusable (bad TOML/JSON, a different plan…).
    #[error(transparent)]
    File(#[from] FileError),
    /// A caller passed an unusable argument.
    #[error("invalid argument: {0}")]
    Argument(String),
    /// A tokenizer stage failed.
    #[error("tokenizer: {0}")]
    Tokenizer(#[from] tokenizer::TokenizerError),
    /// A fit could not be read or used.
    #[error(transparent)]
    Fit(#[from] fits::FitError),
    /// A model stage (text encoder, LM, evaluator) failed.
    #[error("model: {0}")]
    Model(#[from] nn::ModelError),
    /// An external command (sbatch, squeue, a worker process) failed.
    #[error("{command}: {message}")]
    Command {
        /// The command line.
        command: String,
        /// Its output or exit status.
        message: String,
    },
}

impl SweepError {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::File(FileError::io(path, source))
    }

    /// `path` holds something unusable.
    pub fn invalid(path: &Path, message: impl std::fmt::Display) -> Self {
        Self::File(FileError::invalid(path, message))
    }
}
