//! BERT-family sentence encoders (the default: sentence-transformers' all-MiniLM-L6-v2).

use crate::bert_cpu::BertCpu;
use crate::transformer::{self, CONFIG, TOKENIZER};
use crate::{TextEncoder, TokenEmbeddings};
use candle_core::{Device, Tensor};
use candle_transformers::models::bert::{BertModel, Config};
use nn::ModelError;
use std::path::Path;
use tokenizers::{Encoding, Tokenizer};

/// A frozen BERT encoder: `config.json`, `tokenizer.json` and `model.safetensors` in one
/// folder (the Hugging Face layout). Its token embeddings are the last hidden states of
/// every real token, `[CLS]` and `[SEP]` included; padding never appears in the output.
pub struct BertEncoder {
    id: String,
    dim: usize,
    model: Backend,
    tokenizer: Tokenizer,
}

/// What runs the model: the hand-written forward on the CPU, candle's model elsewhere.
enum Backend {
    Cpu(BertCpu),
    Candle(BertModel),
}

impl BertEncoder {
    /// Load the encoder in `dir` onto `device`: on the CPU it runs [`BertCpu`], elsewhere
    /// candle's `BertModel`. Its id is the folder name plus a hash of the three files.
    pub fn load(dir: &Path, device: &Device) -> Result<Self, ModelError> {
        Self::load_backend(dir, device, device.is_cpu())
    }

    /// Load the encoder in `dir` onto `device`, with [`BertCpu`] when `cpu_forward`.
    fn load_backend(dir: &Path, device: &Device, cpu_forward: bool) -> Result<Self, ModelError> {
        let config: Config = transformer::read_config(dir)?;
        let tokenizer = transformer::read_tokenizer(dir, config.pad_token_id as u32)?;
        let (vb, weights) = transformer::read_weights(dir, device)?;
        let model = if cpu_forward {
            Backend::Cpu(BertCpu::load(vb, &config, dir)?)
        } else {
            let model =
                BertModel::load(vb, &config).map_err(|e| ModelError::invalid(&weights, e))?;
            Backend::Candle(model)
        };
        let id = crate::encoder_id(
            &crate::dir_name(dir),
            &[&dir.join(CONFIG), &dir.join(TOKENIZER), &weights],
        )?;
        Ok(Self {
            id,
            dim: config.hidden_size,
            model,
            tokenizer,
        })
    }
}

impl TextEncoder for BertEncoder {
    fn id(&self) -> &str {
        &self.id
    }

    fn dim(&self) -> usize {
        self.dim
    }

    /// One forward pass for the whole batch: packed on the CPU, else padded to its longest
    /// text and masked.
    fn encode(&self, texts: &[&str]) -> Result<Vec<TokenEmbeddings>, ModelError> {
        if texts.is_empty() {
            return Ok(Vec::new());
        }
        let encodings = transformer::tokenize(&self.tokenizer, texts)?;
        let refs: Vec<&Encoding> = encodings.iter().collect();
        match &self.model {
            Backend::Cpu(model) => encode_packed(model, &refs),
            Backend::Candle(model) => encode_padded(model, &refs),
        }
    }
}

/// The real tokens of each encoding (the tokenizer pads on the right, so they come first)
/// through [`BertCpu`], no padding computed.
fn encode_packed(
    model: &BertCpu,
    encodings: &[&Encoding],
) -> Result<Vec<TokenEmbeddings>, ModelError> {
    let lens: Vec<usize> = encodings
        .iter()
        .map(|e| e.get_attention_mask().iter().filter(|&&m| m == 1).count())
        .collect();
    let ids: Vec<&[u32]> = encodings
        .iter()
        .zip(&lens)
        .map(|(e, &n)| &e.get_ids()[..n])
        .collect();
    let hidden = model.forward(&ids)?;
    let dim = model.dim();
    let mut rows = hidden.chunks_exact(dim);
    Ok(encodings
        .iter()
        .zip(&lens)
        .map(|(e, &n)| TokenEmbeddings {
            tokens: e.get_tokens()[..n].to_vec(),
            embeddings: rows.by_ref().take(n).flatten().copied().collect(),
            dim,
        })
        .collect())
}

/// The padded batch through candle's model, masked, cut back to the real tokens.
fn encode_padded(
    model: &BertModel,
    encodings: &[&Encoding],
) -> Result<Vec<TokenEmbeddings>, ModelError> {
    let ids = transformer::stack(encodings, Encoding::get_ids, &model.device)?;
    let mask = transformer::stack(encodings, Encoding::get_attention_mask, &model.device)?;
    let type_ids = Tensor::zeros_like(&ids).map_err(ModelError::Candle)?;
    let hidden = model
        .forward(&ids, &type_ids, Some(&mask))
        .map_err(ModelError::Candle)?;
    transformer::real_tokens(&hidden, encodings)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nn::gradcheck::max_abs_diff;

    /// ~50 captions of 1 to ~40 words: templates, punctuation, digits, case, unknown words.
    fn captions() -> Vec<String> {
        let subjects = ["a person", "Someone", "the man", "A WOMAN", "figure"];
        let actions = [
            "walks forward",
            "waves the left hand twice",
            "jumps; then crouches down and stands up again",
            "turns around 180 degrees, slowly",
            "kicks with the right foot while holding a cup of coffee in the left hand",
        ];
        let mut out: Vec<String> = subjects
            .iter()
            .flat_map(|s| actions.iter().map(move |a| format!("{s} {a}.")))
            .collect();
        out.extend(
            [
                "",
                "walk",
                "zxqv-jumpz!!",
                "a person walks in a circle, stops, looks around, raises both arms above the \
                 head, waves them from side to side three times, lowers them, turns to the \
                 left and walks back to where they started, looking tired and a little sad",
            ]
            .map(String::from),
        );
        out.extend((0..21).map(|i| format!("step {i}: the person hops {} times", i * 7)));
        out
    }

    #[test]
    fn cpu_forward_matches_candle_on_minilm() {
        let dir = crate::test_common::minilm_dir();
        let Some(dir) = dir else {
            return;
        };
        let fused = BertEncoder::load(&dir, &Device::Cpu).unwrap();
        assert!(matches!(fused.model, Backend::Cpu(_)));
        let candle = BertEncoder::load_backend(&dir, &Device::Cpu, false).unwrap();
        let captions = captions();
        let texts: Vec<&str> = captions.iter().map(String::as_str).collect();
        let (ours, theirs) = (
            fused.encode(&texts).unwrap(),
            candle.encode(&texts).unwrap(),
        );
        assert_eq!(ours.len(), texts.len());
        let mut worst = 0f32;
        for ((a, b), text) in ours.iter().zip(&theirs).zip(&texts) {
            assert_eq!(a.tokens, b.tokens, "{text}");
            assert_eq!(a.dim, b.dim);
            worst = worst.max(max_abs_diff(&a.embeddings, &b.embeddings));
        }
        eprintln!("MiniLM: max |fused − candle| = {worst:e}");
        assert!(worst <= 1e-4, "max |Δ| {worst}");
    }
}
