//! The error of every model stage (text encoders, the LM, the evaluator): a missing or
//! unusable file, named, a failed model run, a bad argument, or an unreadable corpus.

use motionscale_core::FileError;
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
    /// A file could not be read or written, or holds something unusable.
    #[error(transparent)]
    File(#[from] FileError),
    /// Running a model failed.
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
