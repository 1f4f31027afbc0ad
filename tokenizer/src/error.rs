//! The error type of every fallible operation of this crate.

use std::path::PathBuf;
use thiserror::Error;

/// What went wrong.
#[derive(Debug, Error)]
pub enum TokenizerError {
    /// A tensor operation failed (shape or dtype mismatch, device error…).
    #[error("tensor operation failed: {0}")]
    Candle(#[from] candle_core::Error),
    /// A caller passed an unusable argument or configuration.
    #[error("invalid argument: {0}")]
    Argument(String),
    /// A file could not be read or written, or its content is wrong.
    #[error("{}: {message}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// What went wrong with it.
        message: String,
    },
}

impl From<motionscale_core::FileError> for TokenizerError {
    fn from(e: motionscale_core::FileError) -> Self {
        let message = match &e {
            motionscale_core::FileError::Io { source, .. } => source.to_string(),
            motionscale_core::FileError::Invalid { message, .. } => message.clone(),
        };
        Self::File {
            path: e.path().to_path_buf(),
            message,
        }
    }
}

impl From<nn::NnError> for TokenizerError {
    fn from(e: nn::NnError) -> Self {
        match e {
            nn::NnError::Candle(e) => Self::Candle(e),
            nn::NnError::File(e) => e.into(),
            nn::NnError::Device(m) => Self::Argument(m),
        }
    }
}
