//! The ingest crate's one error: a named file that could not be read, written or understood,
//! or input that breaks a rule, with what is wrong.

use motionscale_core::FileError;
use std::fmt::Display;
use std::path::Path;

/// What went wrong while reading sources, building, reading or exporting a corpus.
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// A file that could not be read, written or understood (named in the message).
    #[error(transparent)]
    File(#[from] FileError),
    /// Input, an argument or data that breaks a rule: the message says which and why.
    #[error("{0}")]
    Invalid(String),
}

impl IngestError {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        FileError::io(path, source).into()
    }

    /// `path` holds something unusable, as `message` says.
    pub fn file(path: &Path, message: impl Display) -> Self {
        FileError::invalid(path, message).into()
    }

    /// For `map_err`: any error about `path` as [`IngestError::file`].
    pub fn at<E: Display>(path: &Path) -> impl Fn(E) -> Self + '_ {
        move |e| Self::file(path, e)
    }
}

impl From<String> for IngestError {
    fn from(message: String) -> Self {
        Self::Invalid(message)
    }
}

impl From<&str> for IngestError {
    fn from(message: &str) -> Self {
        Self::Invalid(message.to_string())
    }
}

/// A rejection reason (the rejects list holds text).
impl From<IngestError> for String {
    fn from(e: IngestError) -> Self {
        e.to_string()
    }
}
