//! The error type of the shared numerics.

use thiserror::Error;

/// What went wrong: a tensor operation, a checkpoint file (named), or a device.
#[derive(Debug, Error)]
pub enum NnError {
    /// A tensor operation failed (shape or dtype mismatch, device error…).
    #[error("tensor operation failed: {0}")]
    Candle(#[from] candle_core::Error),
    /// A checkpoint file could not be read or written, or its content is wrong.
    #[error(transparent)]
    File(#[from] motionscale_core::FileError),
    /// A device named on the command line cannot be opened (this build or this machine).
    #[error("{0}")]
    Device(String),
}
