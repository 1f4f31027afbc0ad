//! The motion tokenizer: T2M-GPT conv encoder → FSQ or VQ → conv decoder, with the corpus
//! mean/std it normalises by, saved as a checkpoint folder PyTorch loads.
//!
//! ```text
//! DIR/config.json         TokenizerConfig (conv sizes, quantizer, nominal codebook)
//! DIR/model.safetensors   every weight and buffer, keyed like pytorch_vqvae.py's MotionVQVAE
//!                         state_dict: encoder.net.*, decoder.net.*, and
//!                         FSQ: quant.proj_in.{weight,bias}, quant.proj_out.{weight,bias} +
//!                              buffers quant.{L,half_l,offset,shift,half_width,basis}
//!                         VQ:  quant.codebook (K×D), quant.code_sum (K×D), quant.code_count (K)
//! DIR/mean.npy, std.npy   the 263 normalisation statistics (HumanML3D's Mean.npy/Std.npy)
//! ```
//!
//! `model.load_state_dict(safetensors.torch.load_file("DIR/model.safetensors"))` restores the
//! reference PyTorch model exactly (strict), so both compute the same reconstruction.

use crate::conv::{ConvConfig, ConvDecoder, ConvEncoder};
use crate::error::TokenizerError;
use crate::fsq::{levels_for, Bound, FsqConfig, FsqQuantizer};
use crate::vq::{VqConfig, VqQuantizer};
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use motionscale_core::rng::SplitMix64;
use motionscale_core::{read_json, write_json};
use nn::checkpoint::save_safetensors;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::Path;

/// Config file of a checkpoint.
pub const CONFIG_FILE: &str = "config.json";
/// Weights file of a checkpoint.
pub const WEIGHTS_FILE: &str = "model.safetensors";
/// Features per frame.
pub const FEATURES: usize = 263;

/// The quantizer of a tokenizer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum QuantizerConfig {
    /// Finite scalar quantization over `levels` (codebook Π levels).
    Fsq {
        /// Levels per quantized channel.
        levels: Vec<usize>,
        /// Bounding function.
        bound: Bound,
    },
    /// EMA vector quantization.
    Vq(VqConfig),
}

/// Everything that defines a tokenizer's architecture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TokenizerConfig {
    /// Encoder/decoder sizes.
    pub conv: ConvConfig,
    /// The quantizer.
    pub quantizer: QuantizerConfig,
    /// Codebook size as requested (FSQ level sets are named by a nominal 2^k).
    pub nominal_codebook: usize,
}

impl TokenizerConfig {
    /// `quantizer` (`fsq` or `vq`) with a nominal codebook of `codebook` codes: FSQ takes
    /// Mentzer et al.'s level set for 2^8…2^16 (tanh bound unless `bound` says otherwise), VQ
    /// exactly `codebook` codes of width `conv.code_dim`.
    pub fn new(
        quantizer: &str,
        codebook: usize,
        bound: Bound,
        conv: ConvConfig,
    ) -> Result<Self, TokenizerError> {
        let quantizer = match quantizer {
            "fsq" => QuantizerConfig::Fsq {
                levels: levels_for(codebook)
                    .ok_or_else(|| {
                        TokenizerError::Argument(format!(
                            "FSQ has level sets for codebooks 256, 1024, 4096, 16384 and 65536, not {codebook}"
                        ))
                    })?
                    .to_vec(),
                bound,
            },
            "vq" => QuantizerConfig::Vq(VqConfig::new(codebook, conv.code_dim)),
            other => {
                return Err(TokenizerError::Argument(format!(
                    "quantizer must be fsq or vq, not {other:?}"
                )))
            }
        };
        Ok(Self {
            conv,
            quantizer,
            nominal_codebook: codebook,
        })
    }

    /// `fsq` or `vq`.
    pub fn quantizer_name(&self) -> &'static str {
        match self.quantizer {
            QuantizerConfig::Fsq { .. } => "fsq",
            QuantizerConfig::Vq(_) => "vq",
        }
    }

    /// Number of distinct token ids.
    pub fn codebook_size(&self) -> usize {
        match &self.quantizer {
            QuantizerConfig::Fsq { levels, .. } => levels.iter().product(),
            QuantizerConfig::Vq(vq) => vq.codebook_size,
        }
    }
}

/// The quantizer in use.
#[derive(Debug, Clone)]
enum Quantizer {
    Fsq(FsqQuantizer),
    Vq(VqQuantizer),
}

/// One pass through the tokenizer.
#[derive(Debug, Clone)]
pub struct Reconstruction {
    /// Decoded normalised features (batch, frames, 263).
    pub motion: Tensor,
    /// Token ids (batch, frames / 4), u32.
    pub indices: Tensor,
    /// β·commitment loss (VQ only).
    pub commitment: Option<Tensor>,
}

/// An encoder–quantizer–decoder with its normalisation statistics.
pub struct MotionTokenizer {
    config: TokenizerConfig,
    vars: VarMap,
    encoder: ConvEncoder,
    quantizer: Quantizer,
    decoder: ConvDecoder,
    mean: Vec<f32>,
    std: Vec<f32>,
    device: Device,
}

/// PyTorch's default initialisation for every weight of `vars`, drawn from a generator
/// seeded with `seed` in name order: U(-1/√fan_in, 1/√fan_in), a bias sharing its weight's
/// fan-in (candle's own initialisers draw from an unseeded generator).
fn seeded_init(vars: &VarMap, seed: u64) -> Result<(), TokenizerError> {
    let data = vars.data().lock().expect("var map lock");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut rng = SplitMix64(seed);
    for name in names {
        let var = &data[name];
        let weight = name
            .strip_suffix(".bias")
            .map(|stem| format!("{stem}.weight"));
        let dims = match weight.as_ref().and_then(|w| data.get(w)) {
            Some(w) => w.dims().to_vec(),
            None => var.dims().to_vec(),
        };
        let fan_in: usize = dims.iter().skip(1).product::<usize>().max(1);
        let bound = 1.0 / (fan_in as f64).sqrt();
        let values: Vec<f32> = (0..var.elem_count())
            .map(|_| rng.range(-bound, bound) as f32)
            .collect();
        var.set(&Tensor::from_vec(values, var.shape(), var.device())?)?;
    }
    Ok(())
}

impl MotionTokenizer {
    /// A freshly initialised tokenizer (weights from `seed`) normalising with `mean`/`std`.
    pub fn new(
        config: TokenizerConfig,
        mean: Vec<f32>,
        std: Vec<f32>,
        device: &Device,
        seed: u64,
    ) -> Result<Self, TokenizerError> {
        if mean.len() != config.conv.input_dim || std.len() != config.conv.input_dim {
            return Err(TokenizerError::Argument(format!(
                "mean/std have {}/{} values, the tokenizer reads {} features",
                mean.len(),
                std.len(),
                config.conv.input_dim
            )));
        }
        let vars = VarMap::new();
        let vb = VarBuilder::from_varmap(&vars, DType::F32, device);
        let encoder = ConvEncoder::new(&config.conv, vb.pp("encoder"))?;
        let decoder = ConvDecoder::new(&config.conv, vb.pp("decoder"))?;
        let quantizer = match &config.quantizer {
            QuantizerConfig::Fsq { levels, bound } => Quantizer::Fsq(FsqQuantizer::new(
                &FsqConfig {
                    dim: config.conv.code_dim,
                    levels: levels.clone(),
                    bound: *bound,
                },
                vb.pp("quant"),
            )?),
            QuantizerConfig::Vq(vq) => {
                if vq.dim != config.conv.code_dim {
                    return Err(TokenizerError::Argument(format!(
                        "VQ code width {} differs from the encoder's code_dim {}",
                        vq.dim, config.conv.code_dim
                    )));
                }
                Quantizer::Vq(VqQuantizer::new(vq, device, seed ^ 0x5eed)?)
            }
        };
        seeded_init(&vars, seed)?;
        Ok(Self {
            config,
            vars,
            encoder,
            quantizer,
            decoder,
            mean,
            std,
            device: device.clone(),
        })
    }

    /// The architecture.
    pub fn config(&self) -> &TokenizerConfig {
        &self.config
    }

    /// The trainable variables (the VQ codebook is not one: it follows its EMA).
    pub fn vars(&self) -> &VarMap {
        &self.vars
    }

    /// The device the weights live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Per-feature mean used for normalisation.
    pub fn mean(&self) -> &[f32] {
        &self.mean
    }

    /// Per-feature standard deviation used for normalisation.
    pub fn std(&self) -> &[f32] {
        &self.std
    }

    /// The VQ reset generator's state (`None` for FSQ), saved with training checkpoints.
    pub fn vq_rng_state(&self) -> Option<u64> {
        match &self.quantizer {
            Quantizer::Vq(vq) => Some(vq.rng_state()),
            Quantizer::Fsq(_) => None,
        }
    }

    /// Restore the VQ reset generator's state (no-op for FSQ).
    pub fn set_vq_rng_state(&mut self, state: u64) {
        if let Quantizer::Vq(vq) = &mut self.quantizer {
            vq.set_rng_state(state);
        }
    }

    /// Frames per token.
    pub fn downsample(&self) -> usize {
        self.config.conv.downsample_factor()
    }

    /// Encode, quantize and decode normalised motion `x` (batch, frames, 263), `frames` a
    /// multiple of 4. Updates nothing.
    pub fn forward(&self, x: &Tensor) -> Result<Reconstruction, TokenizerError> {
        let z = self.encoder.forward(x)?;
        let (quantized, indices, commitment) = match &self.quantizer {
            Quantizer::Fsq(fsq) => {
                let out = fsq.forward(&z)?;
                (out.quantized, out.indices, None)
            }
            Quantizer::Vq(vq) => {
                let out = vq.forward(&z)?;
                (out.quantized, out.indices, Some(out.commitment_loss))
            }
        };
        Ok(Reconstruction {
            motion: self.decoder.forward(&quantized)?,
            indices,
            commitment,
        })
    }

    /// [`Self::forward`] for a training step: a VQ codebook is first initialised from the
    /// batch's encodings (on the first step, as T2M-GPT does), and its EMA statistics are
    /// updated after quantizing. Returns the pass and the number of dead codes reset.
    pub fn forward_train(
        &mut self,
        x: &Tensor,
        first_step: bool,
    ) -> Result<(Reconstruction, usize), TokenizerError> {
        let z = self.encoder.forward(x)?;
        let (quantized, indices, commitment, reset) = self.quantize_train(&z, first_step)?;
        let pass = Reconstruction {
            motion: self.decoder.forward(&quantized)?,
            indices,
            commitment,
        };
        Ok((pass, reset))
    }

    /// The quantizer's part of [`Self::forward_train`] on latents `z`: quantized latents
    /// (straight-through), token ids, the commitment loss (VQ) and the dead codes reset.
    fn quantize_train(
        &mut self,
        z: &Tensor,
        first_step: bool,
    ) -> Result<(Tensor, Tensor, Option<Tensor>, usize), TokenizerError> {
        match &mut self.quantizer {
            Quantizer::Fsq(fsq) => {
                let out = fsq.forward(z)?;
                Ok((out.quantized, out.indices, None, 0))
            }
            Quantizer::Vq(vq) => {
                if first_step {
                    vq.init_from(z)?;
                }
                let (out, reset) = vq.forward_train(z)?;
                Ok((out.quantized, out.indices, Some(out.commitment_loss), reset))
            }
        }
    }

    /// One training pass on normalised windows `x`: the loss (`reconstruction` of the decoded
    /// motion and `x`, plus the VQ commitment), the dead codes reset and the gradient of every
    /// variable, keyed as `loss.backward()` keys them.
    ///
    /// On the CPU the encoder and decoder run their hand-written passes ([`ConvEncoder::forward_tape`]):
    /// candle's autograd allocates and zero-fills a gradient buffer for every activation and
    /// adds into it, about a tenth of a step at the T2M-GPT shape. Candle differentiates only
    /// the loss (for the motion's gradient) and the quantizer (for the latents').
    pub fn loss_and_grads(
        &mut self,
        x: &Tensor,
        first_step: bool,
        reconstruction: impl Fn(&Tensor, &Tensor) -> candle_core::Result<Tensor>,
    ) -> Result<(f64, usize, GradStore), TokenizerError> {
        if !self.device.is_cpu() {
            let (pass, reset) = self.forward_train(x, first_step)?;
            let mut loss = reconstruction(&pass.motion, x)?;
            if let Some(commitment) = &pass.commitment {
                loss = (loss + commitment)?;
            }
            let grads = loss.backward()?;
            return Ok((loss.to_scalar::<f32>()? as f64, reset, grads));
        }
        let (z, encoder_tape) = self.encoder.forward_tape(x)?;
        let (quantized, _, commitment, reset) = self.quantize_train(z.as_tensor(), first_step)?;
        let (motion, decoder_tape) = self.decoder.forward_tape(&quantized)?;
        let loss = reconstruction(motion.as_tensor(), x)?;
        let dmotion = loss
            .backward()?
            .remove(motion.as_tensor())
            .expect("the loss reads the motion");
        let (dquantized, decoder_grads) = self.decoder.backward(decoder_tape, &dmotion)?;
        // Σ quantized ⊙ dquantized has the decoder's gradient at the quantized latents: its
        // backward carries it through the quantizer, with the commitment's own.
        let mut through_quantizer = (&quantized * &dquantized)?.sum_all()?;
        let mut total = loss.to_scalar::<f32>()? as f64;
        if let Some(commitment) = &commitment {
            through_quantizer = (through_quantizer + commitment)?;
            total += commitment.to_scalar::<f32>()? as f64;
        }
        let mut grads = through_quantizer.backward()?;
        let dz = grads
            .remove(z.as_tensor())
            .expect("the quantizer reads the latents");
        let encoder_grads = self.encoder.backward(encoder_tape, &dz)?;
        for (param, grad) in decoder_grads.into_iter().chain(encoder_grads) {
            grads.insert(&param, grad);
        }
        Ok((total, reset, grads))
    }

    /// Token ids (batch, frames / 4) of normalised motion `x` (batch, frames, 263).
    pub fn encode(&self, x: &Tensor) -> Result<Tensor, TokenizerError> {
        let z = self.encoder.forward(x)?;
        match &self.quantizer {
            Quantizer::Fsq(fsq) => Ok(fsq.forward(&z)?.indices),
            Quantizer::Vq(vq) => vq.nearest(&z),
        }
    }

    /// Normalised motion (batch, tokens · 4, 263) of token ids (batch, tokens).
    pub fn decode_indices(&self, indices: &Tensor) -> Result<Tensor, TokenizerError> {
        let size = self.config.codebook_size() as u32;
        let max = indices.flatten_all()?.max(0)?.to_scalar::<u32>()?;
        if max >= size {
            return Err(TokenizerError::Argument(format!(
                "token {max} is outside the codebook of {size}"
            )));
        }
        let latents = match &self.quantizer {
            Quantizer::Fsq(fsq) => fsq.project_out(&fsq.indices_to_codes(indices)?)?,
            Quantizer::Vq(vq) => vq.lookup(indices)?,
        };
        self.decoder.forward(&latents)
    }

    /// Token ids of one clip's raw features (frames × 263, row-major): normalised, cropped to
    /// a whole number of tokens (`frames / 4` of them, T2M-GPT's cropping), encoded.
    pub fn tokenize(&self, features: &[f32]) -> Result<Vec<u32>, TokenizerError> {
        let dim = self.config.conv.input_dim;
        let usable = features.len() / dim / self.downsample() * self.downsample();
        if usable == 0 {
            return Ok(Vec::new());
        }
        let normalised: Vec<f32> = features[..usable * dim]
            .chunks_exact(dim)
            .flat_map(|row| {
                row.iter()
                    .enumerate()
                    .map(|(d, v)| (v - self.mean[d]) / self.std[d])
            })
            .collect();
        let x = Tensor::from_vec(normalised, (1, usable, dim), &self.device)?;
        Ok(self.encode(&x)?.flatten_all()?.to_vec1::<u32>()?)
    }

    /// De-normalised features (tokens · 4 × 263, row-major) decoded from token ids.
    pub fn detokenize(&self, tokens: &[u32]) -> Result<Vec<f32>, TokenizerError> {
        if tokens.is_empty() {
            return Ok(Vec::new());
        }
        let indices = Tensor::from_slice(tokens, (1, tokens.len()), &self.device)?;
        let motion = self
            .decode_indices(&indices)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let dim = self.config.conv.input_dim;
        Ok(motion
            .chunks_exact(dim)
            .flat_map(|row| {
                row.iter()
                    .enumerate()
                    .map(|(d, v)| v * self.std[d] + self.mean[d])
            })
            .collect())
    }

    /// Every weight and buffer under its PyTorch `state_dict` key (see the module docs).
    pub fn state_dict(&self) -> Result<HashMap<String, Tensor>, TokenizerError> {
        let mut tensors: HashMap<String, Tensor> = self
            .vars
            .data()
            .lock()
            .expect("var map lock")
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect();
        match &self.quantizer {
            Quantizer::Fsq(fsq) => {
                for (name, values) in fsq.buffers() {
                    let n = values.len();
                    tensors.insert(
                        format!("quant.{name}"),
                        Tensor::from_vec(values, n, &self.device)?,
                    );
                }
            }
            Quantizer::Vq(vq) => {
                tensors.insert("quant.codebook".into(), vq.codebook().clone());
                tensors.insert("quant.code_sum".into(), vq.code_sum().clone());
                tensors.insert("quant.code_count".into(), vq.code_count().clone());
            }
        }
        Ok(tensors)
    }

    /// Write `config.json`, `model.safetensors`, `mean.npy` and `std.npy` into `dir`
    /// (each atomically).
    pub fn save(&self, dir: &Path) -> Result<(), TokenizerError> {
        let file_error = |path: &Path, e: &dyn std::fmt::Display| TokenizerError::File {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        save_safetensors(&self.state_dict()?, &dir.join(WEIGHTS_FILE))?;
        for (name, values) in [("mean.npy", &self.mean), ("std.npy", &self.std)] {
            let path = dir.join(name);
            ingest::npy::write_f32(&path, &[values.len()], values)
                .map_err(|e| file_error(&path, &e))?;
        }
        Ok(write_json(&dir.join(CONFIG_FILE), &self.config)?)
    }

    /// Load a checkpoint folder written by [`Self::save`] onto `device`.
    pub fn load(dir: &Path, device: &Device) -> Result<Self, TokenizerError> {
        let config: TokenizerConfig = read_json(&dir.join(CONFIG_FILE))?;
        let read_stat = |name: &str| -> Result<Vec<f32>, TokenizerError> {
            let path = dir.join(name);
            let array = ingest::npy::read(&path).map_err(|message| TokenizerError::File {
                path: path.clone(),
                message: message.to_string(),
            })?;
            Ok(array.data.iter().map(|&v| v as f32).collect())
        };
        let mut tokenizer = Self::new(
            config,
            read_stat("mean.npy")?,
            read_stat("std.npy")?,
            device,
            0,
        )?;
        let path = dir.join(WEIGHTS_FILE);
        let file_error = |message: String| TokenizerError::File {
            path: path.clone(),
            message,
        };
        tokenizer
            .vars
            .load(&path)
            .map_err(|e| file_error(e.to_string()))?;
        if let Quantizer::Vq(vq) = &mut tokenizer.quantizer {
            let tensors = candle_core::safetensors::load(&path, device)
                .map_err(|e| file_error(e.to_string()))?;
            let get = |key: &str| {
                tensors
                    .get(key)
                    .cloned()
                    .ok_or_else(|| file_error(format!("no tensor {key}")))
            };
            vq.set_state(
                get("quant.codebook")?,
                get("quant.code_sum")?,
                get("quant.code_count")?,
            )?;
        }
        Ok(tokenizer)
    }

    /// Short content id of a checkpoint folder: the first 12 hex digits of the sha256 of its
    /// config and weights.
    pub fn content_id(dir: &Path) -> Result<String, TokenizerError> {
        let mut hasher = Sha256::new();
        for name in [CONFIG_FILE, WEIGHTS_FILE] {
            let path = dir.join(name);
            let bytes = std::fs::read(&path).map_err(|e| TokenizerError::File {
                path: path.clone(),
                message: e.to_string(),
            })?;
            hasher.update(&bytes);
        }
        Ok(hasher.finalize()[..6]
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::loss::reconstruction_losses;

    fn tokenizer(quantizer: &str) -> MotionTokenizer {
        let conv = ConvConfig {
            width: 16,
            code_dim: 8,
            ..ConvConfig::default()
        };
        let config = TokenizerConfig::new(quantizer, 256, Bound::Tanh, conv).unwrap();
        let (mean, std) = (vec![0.0; FEATURES], vec![1.0; FEATURES]);
        MotionTokenizer::new(config, mean, std, &Device::Cpu, 3).unwrap()
    }

    fn reconstruction(motion: &Tensor, x: &Tensor) -> candle_core::Result<Tensor> {
        let weights = Tensor::new(&[1f32, 0.5], x.device())?;
        (reconstruction_losses(motion, x)? * weights)?.sum_all()
    }

    /// The CPU path's hand-written encoder and decoder passes give the loss and every
    /// gradient that candle's autograd of the same pass gives.
    #[test]
    fn hand_written_gradients_match_candle_autograd() {
        let mut rng = SplitMix64(11);
        let values: Vec<f32> = (0..2 * 32 * FEATURES)
            .map(|_| rng.range(-1.5, 1.5) as f32)
            .collect();
        let x = Tensor::from_vec(values, (2, 32, FEATURES), &Device::Cpu).unwrap();
        for quantizer in ["fsq", "vq"] {
            let (mut hand, mut autograd) = (tokenizer(quantizer), tokenizer(quantizer));
            let (loss, _, grads) = hand.loss_and_grads(&x, true, reconstruction).unwrap();
            let (pass, _) = autograd.forward_train(&x, true).unwrap();
            let mut expected_loss = reconstruction(&pass.motion, &x).unwrap();
            if let Some(commitment) = &pass.commitment {
                expected_loss = (expected_loss + commitment).unwrap();
            }
            let expected = expected_loss.backward().unwrap();
            let expected_loss = expected_loss.to_scalar::<f32>().unwrap() as f64;
            assert!(
                (loss - expected_loss).abs() < 1e-6,
                "{quantizer}: loss {loss} vs {expected_loss}"
            );
            let ours = hand.vars().data().lock().unwrap();
            let theirs = autograd.vars().data().lock().unwrap();
            assert!(ours.len() > 40, "{quantizer}: {} variables", ours.len());
            let values = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            for (name, var) in ours.iter() {
                let ours = values(grads.get(var.as_tensor()).expect(name));
                let theirs = values(expected.get(theirs[name].as_tensor()).expect(name));
                let scale = theirs.iter().fold(0f32, |m, v| m.max(v.abs()));
                let diff = nn::gradcheck::max_abs_diff(&ours, &theirs);
                assert!(scale > 0.0, "{quantizer} {name}: no gradient");
                assert!(
                    diff <= 1e-5 * scale.max(1e-3),
                    "{quantizer} {name}: {diff} (scale {scale})"
                );
            }
        }
    }
}
