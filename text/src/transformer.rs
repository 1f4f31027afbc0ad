//! File loading, tokenisation and output slicing shared by the transformer encoders.

use crate::TokenEmbeddings;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use nn::ModelError;
use serde::de::DeserializeOwned;
use std::path::{Path, PathBuf};
use tokenizers::{Encoding, PaddingDirection, PaddingParams, PaddingStrategy, Tokenizer};

/// Config file name.
pub const CONFIG: &str = "config.json";
/// Tokenizer file name.
pub const TOKENIZER: &str = "tokenizer.json";
/// Weights file name.
pub const WEIGHTS: &str = "model.safetensors";

/// `dir/name`, or [`ModelError::Missing`] when it is not a file.
pub fn required(dir: &Path, name: &str, what: &'static str) -> Result<PathBuf, ModelError> {
    let path = dir.join(name);
    if path.is_file() {
        Ok(path)
    } else {
        Err(ModelError::Missing { path, what })
    }
}

/// Parse `dir/config.json`.
pub fn read_config<T: DeserializeOwned>(dir: &Path) -> Result<T, ModelError> {
    let path = required(dir, CONFIG, "model config")?;
    let text = std::fs::read_to_string(&path).map_err(|e| ModelError::io(&path, e))?;
    serde_json::from_str(&text).map_err(|e| ModelError::invalid(&path, e))
}

/// Load `dir/tokenizer.json`, right-padding to the longest text of a batch with `pad_id`
/// (padding configured in the file, e.g. MiniLM's fixed 128, is replaced: a single text
/// is never padded).
pub fn read_tokenizer(dir: &Path, pad_id: u32) -> Result<Tokenizer, ModelError> {
    let path = required(dir, TOKENIZER, "tokenizer")?;
    let mut tokenizer = Tokenizer::from_file(&path).map_err(|e| ModelError::invalid(&path, e))?;
    let pad_token = tokenizer.id_to_token(pad_id).ok_or_else(|| {
        ModelError::invalid(&path, format!("no token for the padding id {pad_id}"))
    })?;
    tokenizer.with_padding(Some(PaddingParams {
        strategy: PaddingStrategy::BatchLongest,
        direction: PaddingDirection::Right,
        pad_to_multiple_of: None,
        pad_id,
        pad_type_id: 0,
        pad_token,
    }));
    Ok(tokenizer)
}

/// Memory-map `dir/model.safetensors` as f32 weights on `device`.
pub fn read_weights(
    dir: &Path,
    device: &Device,
) -> Result<(VarBuilder<'static>, PathBuf), ModelError> {
    let path = required(dir, WEIGHTS, "model weights")?;
    // SAFETY: the weights file is only read; it must not be modified while the model lives.
    let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[&path], DType::F32, device) }
        .map_err(|e| ModelError::invalid(&path, e))?;
    Ok((vb, path))
}

/// Tokenise a batch (with special tokens).
pub fn tokenize(tokenizer: &Tokenizer, texts: &[&str]) -> Result<Vec<Encoding>, ModelError> {
    tokenizer
        .encode_batch(texts.to_vec(), true)
        .map_err(|e| ModelError::encoder("tokenizer", e))
}

/// A (batch × length) u32 tensor of one field of equally long encodings.
pub fn stack(
    encodings: &[&Encoding],
    field: fn(&Encoding) -> &[u32],
    device: &Device,
) -> Result<Tensor, ModelError> {
    let len = encodings.first().map_or(0, |e| field(e).len());
    let flat: Vec<u32> = encodings
        .iter()
        .flat_map(|e| field(e).iter().copied())
        .collect();
    Tensor::from_vec(flat, (encodings.len(), len), device).map_err(ModelError::Candle)
}

/// Cut a (batch × length × dim) hidden-state tensor into each text's real (unmasked) tokens.
pub fn real_tokens(
    hidden: &Tensor,
    encodings: &[&Encoding],
) -> Result<Vec<TokenEmbeddings>, ModelError> {
    // `to_vec3` copies from any device.
    let hidden = hidden.to_vec3::<f32>().map_err(ModelError::Candle)?;
    let dim = hidden
        .first()
        .and_then(|rows| rows.first())
        .map_or(0, Vec::len);
    Ok(hidden
        .into_iter()
        .zip(encodings)
        .map(|(rows, enc)| {
            let mut out = TokenEmbeddings {
                tokens: Vec::new(),
                embeddings: Vec::new(),
                dim,
            };
            for ((row, token), &mask) in rows
                .iter()
                .zip(enc.get_tokens())
                .zip(enc.get_attention_mask())
            {
                if mask == 1 {
                    out.tokens.push(token.clone());
                    out.embeddings.extend_from_slice(row);
                }
            }
            out
        })
        .collect())
}
