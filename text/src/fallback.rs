//! The dependency-free fallback encoder: a word-embedding table built from the corpus
//! captions and initialised at random. It is NOT a pretrained model: it exists so training
//! can run where no pretrained encoder is available, and must be learned downstream. Its id
//! starts with `fallback-untrained-` so every output that uses it says so.

use crate::{TextEncoder, TokenEmbeddings};
use motionscale_core::rng::SplitMix64;
use nn::ModelError;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use sha2::{Digest, Sha256};
use std::collections::{BTreeSet, HashMap};
use std::path::Path;

/// Prefix of every fallback encoder id.
pub const ID_PREFIX: &str = "fallback-untrained-";
/// The unknown-word token, row 0 of the table.
pub const UNK: &str = "<unk>";
/// Safetensors key of the table.
pub const EMBEDDINGS_KEY: &str = "embeddings";
/// Table file name.
pub const WEIGHTS_FILE: &str = "model.safetensors";
/// Vocabulary file name (a JSON array of words, row order).
pub const VOCAB_FILE: &str = "vocab.json";

/// Lowercased words of `text`, split on every non-alphanumeric character.
pub fn words(text: &str) -> Vec<String> {
    text.split(|c: char| !c.is_alphanumeric())
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
        .collect()
}

/// A word-level embedding table; see the module docs.
pub struct FallbackEncoder {
    id: String,
    dim: usize,
    vocab: Vec<String>,
    index: HashMap<String, usize>,
    table: Vec<f32>,
}

impl FallbackEncoder {
    /// Build the vocabulary from `captions` (`<unk>` first, then the distinct words sorted)
    /// and fill the table with N(0, 1/dim) draws from a generator seeded with `seed`.
    pub fn build<'a>(
        captions: impl IntoIterator<Item = &'a str>,
        dim: usize,
        seed: u64,
    ) -> Result<Self, ModelError> {
        if dim == 0 {
            return Err(ModelError::argument(
                "fallback encoder width",
                "must be positive",
            ));
        }
        let distinct: BTreeSet<String> = captions.into_iter().flat_map(words).collect();
        let vocab: Vec<String> = std::iter::once(UNK.to_string())
            .chain(distinct.into_iter().filter(|w| w != UNK))
            .collect();
        let mut rng = SplitMix64(seed);
        let std = (1.0 / dim as f64).sqrt();
        let table = (0..vocab.len() * dim)
            .map(|_| (rng.normal() * std) as f32)
            .collect();
        Self::from_parts(vocab, table, dim).map_err(|e| ModelError::argument("fallback encoder", e))
    }

    /// [`Self::build`] over the distinct captions of the corpus in `corpus_dir`.
    pub fn for_corpus(corpus_dir: &Path, dim: usize, seed: u64) -> Result<Self, ModelError> {
        let captions = crate::embed::corpus_captions(corpus_dir)?;
        Self::build(captions.iter().map(String::as_str), dim, seed)
    }

    /// Load `vocab.json` and `model.safetensors` (key `embeddings`, vocab × dim f32) from `dir`.
    pub fn load(dir: &Path) -> Result<Self, ModelError> {
        let vocab_path = crate::transformer::required(dir, VOCAB_FILE, "fallback vocabulary")?;
        let text =
            std::fs::read_to_string(&vocab_path).map_err(|e| ModelError::io(&vocab_path, e))?;
        let vocab: Vec<String> =
            serde_json::from_str(&text).map_err(|e| ModelError::invalid(&vocab_path, e))?;
        let path = crate::transformer::required(dir, WEIGHTS_FILE, "fallback embedding table")?;
        let bytes = std::fs::read(&path).map_err(|e| ModelError::io(&path, e))?;
        let tensors =
            SafeTensors::deserialize(&bytes).map_err(|e| ModelError::invalid(&path, e))?;
        let view = tensors
            .tensor(EMBEDDINGS_KEY)
            .map_err(|e| ModelError::invalid(&path, e))?;
        let shape = view.shape();
        if view.dtype() != Dtype::F32
            || shape.len() != 2
            || shape[0] != vocab.len()
            || shape[1] == 0
        {
            return Err(ModelError::invalid(
                &path,
                format!(
                    "{EMBEDDINGS_KEY} is {:?} {shape:?}, expected F32 [{}, dim] for the {} words of {VOCAB_FILE}",
                    view.dtype(),
                    vocab.len(),
                    vocab.len()
                ),
            ));
        }
        let table = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        Self::from_parts(vocab, table, shape[1]).map_err(|e| ModelError::invalid(&vocab_path, e))
    }

    /// Write `vocab.json` and `model.safetensors` into `dir` (atomically each).
    pub fn save(&self, dir: &Path) -> Result<(), ModelError> {
        let (vocab, weights) = serialize(&self.vocab, &self.table, self.dim)?;
        for (name, bytes) in [(VOCAB_FILE, vocab), (WEIGHTS_FILE, weights)] {
            let path = dir.join(name);
            motionscale_core::write_atomic(&path, &bytes).map_err(|e| ModelError::io(&path, e))?;
        }
        Ok(())
    }

    /// The vocabulary, in table row order.
    pub fn vocab(&self) -> &[String] {
        &self.vocab
    }

    /// The vocab × dim table, row-major (the initial values of a learned embedding).
    pub fn table(&self) -> &[f32] {
        &self.table
    }

    /// Table rows of the words of `text` (unknown words map to row 0, `<unk>`).
    pub fn token_ids(&self, text: &str) -> Vec<usize> {
        words(text)
            .iter()
            .map(|w| self.index.get(w).copied().unwrap_or(0))
            .collect()
    }

    fn from_parts(vocab: Vec<String>, table: Vec<f32>, dim: usize) -> Result<Self, String> {
        let (vocab_bytes, weights) = serialize(&vocab, &table, dim).map_err(|e| e.to_string())?;
        let mut hasher = Sha256::new();
        hasher.update(&vocab_bytes);
        hasher.update(&weights);
        let index: HashMap<String, usize> = vocab
            .iter()
            .enumerate()
            .map(|(i, w)| (w.clone(), i))
            .collect();
        if index.len() != vocab.len() || vocab.first().map(String::as_str) != Some(UNK) {
            return Err(format!(
                "vocabulary must start with {UNK} and hold distinct words"
            ));
        }
        Ok(Self {
            id: format!("{ID_PREFIX}{}", crate::short_hash(hasher)),
            dim,
            vocab,
            index,
            table,
        })
    }
}

/// The bytes of `vocab.json` and `model.safetensors`; the id hashes exactly these, so a built
/// encoder and its saved-then-loaded copy share an id.
fn serialize(
    vocab: &[String],
    table: &[f32],
    dim: usize,
) -> Result<(Vec<u8>, Vec<u8>), ModelError> {
    let failed = |e: &dyn std::fmt::Display| ModelError::encoder("fallback", e);
    let vocab_bytes = serde_json::to_vec(vocab).map_err(|e| failed(&e))?;
    let data: Vec<u8> = table.iter().flat_map(|v| v.to_le_bytes()).collect();
    let view =
        TensorView::new(Dtype::F32, vec![vocab.len(), dim], &data).map_err(|e| failed(&e))?;
    let weights = safetensors::serialize([(EMBEDDINGS_KEY, view)], None).map_err(|e| failed(&e))?;
    Ok((vocab_bytes, weights))
}

impl TextEncoder for FallbackEncoder {
    fn id(&self) -> &str {
        &self.id
    }

    fn dim(&self) -> usize {
        self.dim
    }

    /// Each word's table row; the token strings are vocabulary entries (`<unk>` for unknown words).
    fn encode(&self, texts: &[&str]) -> Result<Vec<TokenEmbeddings>, ModelError> {
        Ok(texts
            .iter()
            .map(|text| {
                let ids = self.token_ids(text);
                TokenEmbeddings {
                    tokens: ids.iter().map(|&i| self.vocab[i].clone()).collect(),
                    embeddings: ids
                        .iter()
                        .flat_map(|&i| &self.table[i * self.dim..(i + 1) * self.dim])
                        .copied()
                        .collect(),
                    dim: self.dim,
                }
            })
            .collect())
    }
}
