//! BERT-family sentence encoders (the default: sentence-transformers' all-MiniLM-L6-v2).

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
    model: BertModel,
    tokenizer: Tokenizer,
    device: Device,
}

impl BertEncoder {
    /// Load the encoder in `dir` onto [`nn::default_device`]. Its id is the folder name
    /// plus a hash of the three files.
    pub fn load(dir: &Path) -> Result<Self, ModelError> {
        Self::load_on(dir, &nn::default_device())
    }

    /// Load the encoder in `dir` onto `device`.
    pub fn load_on(dir: &Path, device: &Device) -> Result<Self, ModelError> {
        let config: Config = transformer::read_config(dir)?;
        let tokenizer = transformer::read_tokenizer(dir, config.pad_token_id as u32)?;
        let (vb, weights) = transformer::read_weights(dir, device)?;
        let model = BertModel::load(vb, &config).map_err(|e| ModelError::invalid(&weights, e))?;
        let id = crate::encoder_id(
            &crate::dir_name(dir),
            &[&dir.join(CONFIG), &dir.join(TOKENIZER), &weights],
        )?;
        Ok(Self {
            id,
            dim: config.hidden_size,
            model,
            tokenizer,
            device: device.clone(),
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

    /// One forward pass for the whole batch, padded to its longest text and masked.
    fn encode(&self, texts: &[&str]) -> Result<Vec<TokenEmbeddings>, ModelError> {
        if texts.is_empty() {
            return Ok(Vec::new());
        }
        let encodings = transformer::tokenize(&self.tokenizer, texts)?;
        let refs: Vec<&Encoding> = encodings.iter().collect();
        let ids = transformer::stack(&refs, Encoding::get_ids, &self.device)?;
        let mask = transformer::stack(&refs, Encoding::get_attention_mask, &self.device)?;
        let type_ids = Tensor::zeros_like(&ids).map_err(ModelError::inference)?;
        let hidden = self
            .model
            .forward(&ids, &type_ids, Some(&mask))
            .map_err(ModelError::inference)?;
        transformer::real_tokens(&hidden, &refs)
    }
}
