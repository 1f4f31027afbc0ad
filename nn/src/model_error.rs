//! The error of every model stage (text encoders, the LM, the evaluator): a missing or
//! unusable file, named, a failed tensor or optimiser operation, a failed motion tokenizer, a
//! text encoder's bad output, a bad
//! argument, or an unreadable corpus, each carrying what it concerns.

use motionscale_core::FileError;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Any error a corpus reader returns, kept as the source.
pub type SourceError = Box<dyn std::error::Error + Send + Sync>;

/// What went wrong, naming the file, encoder, argument or corpus involved.
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
    /// A tensor operation of a model failed.
    #[error("model run failed: {0}")]
    Candle(#[from] candle_core::Error),
    /// An optimiser step or a checkpoint of `nn` failed.
    #[error(transparent)]
    Nn(#[from] crate::NnError),
    /// The motion tokenizer failed (decoding tokens to motion).
    #[error("motion tokenizer: {0}")]
    MotionTokenizer(SourceError),
    /// A text encoder (or its tokenizer) failed or returned something unusable.
    #[error("text encoder {encoder}: {problem}")]
    Encoder {
        /// The encoder's id or name.
        encoder: String,
        /// What went wrong.
        problem: String,
    },
    /// A caller passed an unusable argument.
    #[error("invalid {argument}: {problem}")]
    Argument {
        /// Which argument (a flag, a setting, a model part).
        argument: &'static str,
        /// Why it is unusable.
        problem: String,
    },
    /// The corpus could not be read or updated, or lacks what the stage needs.
    #[error("corpus {}: {source}", dir.display())]
    Corpus {
        /// The corpus folder.
        dir: PathBuf,
        /// The reader's error, or what is missing.
        source: SourceError,
    },
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

    /// `argument` is unusable, for the reason `problem`.
    pub fn argument(argument: &'static str, problem: impl std::fmt::Display) -> Self {
        Self::Argument {
            argument,
            problem: problem.to_string(),
        }
    }

    /// The corpus at `dir` failed with `source` (a reader's error or a message).
    pub fn corpus(dir: &Path, source: impl Into<SourceError>) -> Self {
        Self::Corpus {
            dir: dir.to_path_buf(),
            source: source.into(),
        }
    }

    /// The text encoder `encoder` failed with `problem`.
    pub fn encoder(encoder: impl std::fmt::Display, problem: impl std::fmt::Display) -> Self {
        Self::Encoder {
            encoder: encoder.to_string(),
            problem: problem.to_string(),
        }
    }
}
