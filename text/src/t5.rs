//! T5 encoders (the text side of T5 / Flan-T5 checkpoints).

use crate::transformer::{self, CONFIG, TOKENIZER};
use crate::{TextEncoder, TokenEmbeddings};
use candle_core::Device;
use candle_transformers::models::t5::{Config, T5EncoderModel};
use nn::ModelError;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Mutex;
use tokenizers::{Encoding, Tokenizer};

/// A frozen T5 encoder stack: `config.json`, `tokenizer.json` and `model.safetensors` (a
/// full T5 checkpoint or an encoder-only one). Token embeddings are the final-layer-norm
/// outputs of every real token, the closing `</s>` included.
pub struct T5Encoder {
    id: String,
    dim: usize,
    // candle's T5 encoder takes `&mut self` (for a cache only its decoder uses).
    model: Mutex<T5EncoderModel>,
    tokenizer: Tokenizer,
    device: Device,
}

impl T5Encoder {
    /// Load the encoder in `dir` onto `device`. Its id is the folder name plus a hash of the
    /// three files.
    pub fn load(dir: &Path, device: &Device) -> Result<Self, ModelError> {
        let config: Config = transformer::read_config(dir)?;
        let tokenizer = transformer::read_tokenizer(dir, config.pad_token_id as u32)?;
        let (vb, weights) = transformer::read_weights(dir, device)?;
        let model =
            T5EncoderModel::load(vb, &config).map_err(|e| ModelError::invalid(&weights, e))?;
        let id = crate::encoder_id(
            &crate::dir_name(dir),
            &[&dir.join(CONFIG), &dir.join(TOKENIZER), &weights],
        )?;
        Ok(Self {
            id,
            dim: config.d_model,
            model: Mutex::new(model),
            tokenizer,
            device: device.clone(),
        })
    }
}

impl TextEncoder for T5Encoder {
    fn id(&self) -> &str {
        &self.id
    }

    fn dim(&self) -> usize {
        self.dim
    }

    /// candle's T5 encoder takes no attention mask, so padding would leak into the
    /// attention: texts are grouped by token count and each group runs unpadded.
    fn encode(&self, texts: &[&str]) -> Result<Vec<TokenEmbeddings>, ModelError> {
        let encodings: Vec<Encoding> = texts
            .iter()
            .map(|t| transformer::tokenize(&self.tokenizer, &[t]).map(|mut e| e.remove(0)))
            .collect::<Result<_, _>>()?;
        let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for (i, e) in encodings.iter().enumerate() {
            groups.entry(e.len()).or_default().push(i);
        }
        let mut model = self
            .model
            .lock()
            .map_err(|_| ModelError::encoder("T5", "model lock poisoned"))?;
        let mut out: Vec<Option<TokenEmbeddings>> = vec![None; texts.len()];
        for members in groups.values() {
            let refs: Vec<&Encoding> = members.iter().map(|&i| &encodings[i]).collect();
            let ids = transformer::stack(&refs, Encoding::get_ids, &self.device)?;
            let hidden = model.forward(&ids).map_err(ModelError::Candle)?;
            for (&i, emb) in members
                .iter()
                .zip(transformer::real_tokens(&hidden, &refs)?)
            {
                out[i] = Some(emb);
            }
        }
        Ok(out.into_iter().flatten().collect())
    }
}
