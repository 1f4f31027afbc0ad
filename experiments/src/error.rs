//! The error type of every fallible operation of this crate.

use std::path::{Path, PathBuf};
use thiserror::Error;

/// What went wrong, naming the file or plan point involved.
#[derive(Debug, Error)]
pub enum SweepError {
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A file is present but unusable (bad TOML/JSON, a different plan…).
    #[error("{}: {message}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// A caller passed an unusable argument.
    #[error("invalid argument: {0}")]
    Argument(String),
    /// A tokenizer stage failed.
    #[error("tokenizer: {0}")]
    Tokenizer(#[from] tokenizer::TokenizerError),
    /// Training or evaluating a model failed.
    #[error("model: {0}")]
    Model(#[from] lm::LmError),
    /// The evaluator failed.
    #[error("evaluator: {0}")]
    Evaluator(#[from] evaluator::EvaluatorError),
    /// A text encoder or the caption embeddings failed.
    #[error("text: {0}")]
    Text(#[from] text::TextError),
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
}

impl From<motionscale_core::FileError> for SweepError {
    fn from(e: motionscale_core::FileError) -> Self {
        match e {
            motionscale_core::FileError::Io { path, source } => Self::Io { path, source },
            motionscale_core::FileError::Invalid { path, message } => {
                Self::Invalid { path, message }
            }
        }
    }
}
