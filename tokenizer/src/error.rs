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
