//! The error type of every fallible operation of this crate.

use motionscale_core::FileError;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// What went wrong, naming the file involved.
#[derive(Debug, Error)]
pub enum EvaluatorError {
    /// A required file is absent.
    #[error("{}: missing ({what})", path.display())]
    Missing {
        /// The file looked for.
        path: PathBuf,
        /// What it should have held.
        what: &'static str,
    },
    /// A file could not be read or written, or holds something unusable.
    #[error(transparent)]
    File(#[from] FileError),
    /// Running the model failed.
    #[error("encoding failed: {0}")]
    Inference(String),
    /// A caller passed an unusable argument.
    #[error("invalid argument: {0}")]
    Argument(String),
    /// The corpus could not be read or updated.
    #[error("corpus: {0}")]
    Corpus(String),
    /// A text encoder or the caption embeddings failed.
    #[error(transparent)]
    Text(#[from] text::TextError),
    /// A motion LM failed (generating the motions to score).
    #[error(transparent)]
    Lm(#[from] lm::LmError),
}

impl EvaluatorError {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::File(FileError::io(path, source))
    }

    /// `path` holds something unusable.
    pub fn invalid(path: &Path, message: impl std::fmt::Display) -> Self {
        Self::File(FileError::invalid(path, message))
    }

    /// A model run failed.
    pub fn inference(e: impl std::fmt::Display) -> Self {
        Self::Inference(e.to_string())
    }
}
