//! The text–motion evaluator: a motion encoder (movement convolutions + bidirectional GRU
//! over normalised 263-d features) and a text encoder (bidirectional GRU over frozen
//! per-token caption embeddings) that map into one space, trained contrastively, plus
//! emotion and action classifiers on the motion encoder's pooled features.
//!
//! The layout follows the T2M evaluator (`MovementConvEncoder` + `MotionEncoderBiGRUCo`,
//! `TextEncoderBiGRUCo`); parameter names are PyTorch's (`nn.Conv1d`, `nn.GRU` with
//! `bidirectional=True`, `nn.Linear`), so `model.safetensors` loads into the same modules.

use candle_core::{DType, Device, Module, Result, Tensor, D};
use candle_nn::{Conv1d, Conv1dConfig, Linear, VarBuilder};
use motionscale_core::rng::SplitMix64;
use nn::conv_op::{ConvGeometry, ConvOutput};
use nn::gru::{per_step, BiGru};
use nn::ModelError;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

/// Frames per motion-encoder step: two stride-2 convolutions.
pub const UNIT: usize = 4;

/// The evaluator's shape and label sets.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluatorConfig {
    /// Motion feature width (263).
    pub feature_dim: usize,
    /// Caption token-embedding width (384 for MiniLM).
    pub text_dim: usize,
    /// GRU and convolution width.
    pub hidden: usize,
    /// Width of the shared text–motion space.
    pub embed_dim: usize,
    /// Longest motion window seen, in frames (a multiple of [`UNIT`]).
    pub max_frames: usize,
    /// Longest caption, in tokens.
    pub max_text_tokens: usize,
    /// Softmax temperature of the contrastive loss.
    pub temperature: f64,
    /// Emotion classes, in logit order.
    pub emotions: Vec<String>,
    /// Action classes, in logit order.
    pub actions: Vec<String>,
}

/// A padded batch of variable-length sequences: `(batch, steps, width)` values and each
/// sequence's real length (≥ 1).
pub struct Padded {
    /// The values, zero past each length.
    pub values: Tensor,
    /// Real lengths.
    pub lengths: Vec<usize>,
}

impl Padded {
    /// Stack `rows` (each `len × width`, row-major) into one zero-padded batch.
    pub fn new(rows: &[&[f32]], width: usize, device: &Device) -> Result<Self> {
        let lengths: Vec<usize> = rows.iter().map(|r| (r.len() / width).max(1)).collect();
        let steps = lengths.iter().copied().max().unwrap_or(1);
        let mut values = vec![0f32; rows.len() * steps * width];
        for (b, row) in rows.iter().enumerate() {
            values[b * steps * width..][..row.len()].copy_from_slice(row);
        }
        Ok(Self {
            values: Tensor::from_vec(values, (rows.len(), steps, width), device)?,
            lengths,
        })
    }
}

/// `Linear → LeakyReLU(0.2) → Linear`, the output head of both encoders.
struct Head {
    first: Linear,
    second: Linear,
}

impl Head {
    fn new(input: usize, hidden: usize, output: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            first: candle_nn::linear(input, hidden, vb.pp("0"))?,
            second: candle_nn::linear(hidden, output, vb.pp("2"))?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = candle_nn::ops::leaky_relu(&self.first.forward(x)?, LEAKY_SLOPE.into())?;
        self.second.forward(&h)
    }
}

/// Negative slope of the evaluator's leaky ReLUs (T2M's).
const LEAKY_SLOPE: f32 = 0.2;

/// `LeakyReLU(conv(x))` for channels-last `x` `(batch, frames, in)` → `(batch, out_frames,
/// out)`, computed at each sequence's first `valid[b]` output frames and zero after them, as
/// the evaluator of one unpadded clip sees it.
///
/// Why not `Conv1d::forward`: candle 0.11.1's `conv1d` backward gives wrong weight gradients
/// for batches larger than one (see [`nn::conv_op::conv1d_reference`]).
fn movement_conv(x: &Tensor, conv: &Conv1d, valid: &[usize]) -> Result<Tensor> {
    let bias = conv
        .bias()
        .ok_or_else(|| candle_core::Error::Msg("movement conv without a bias".into()))?;
    let config = conv.config();
    let geometry = ConvGeometry::plain(
        conv.weight().dim(2)?,
        config.stride,
        config.dilation,
        config.padding,
    );
    let output = ConvOutput {
        valid: Some(valid.to_vec()),
        leaky_slope: Some(LEAKY_SLOPE),
    };
    nn::conv_op::conv1d_fused(x, conv.weight(), bias, geometry, &output)
}

/// Rows scaled to unit length.
fn unit_rows(x: &Tensor) -> Result<Tensor> {
    let norm = (x.sqr()?.sum_keepdim(D::Minus1)? + 1e-12)?.sqrt()?;
    x.broadcast_div(&norm)
}

/// What the motion side computes for a batch.
pub struct MotionOutputs {
    /// Unit-length embeddings in the shared space, `(batch, embed_dim)`.
    pub embedding: Tensor,
    /// Emotion logits, `(batch, emotions)`.
    pub emotion: Tensor,
    /// Action logits, `(batch, actions)`.
    pub action: Tensor,
}

/// The evaluator networks.
pub struct Evaluator {
    /// Its configuration.
    pub config: EvaluatorConfig,
    conv1: Conv1d,
    conv2: Conv1d,
    motion_gru: BiGru,
    motion_head: Head,
    emotion: Linear,
    action: Linear,
    text_in: Linear,
    text_gru: BiGru,
    text_head: Head,
}

impl Evaluator {
    /// Build from `vb` (fresh or loaded weights).
    pub fn new(config: EvaluatorConfig, vb: VarBuilder) -> Result<Self> {
        let h = config.hidden;
        let conv = Conv1dConfig {
            padding: 1,
            stride: 2,
            ..Default::default()
        };
        let motion = vb.pp("motion");
        let text = vb.pp("text");
        Ok(Self {
            conv1: candle_nn::conv1d(config.feature_dim, h, 4, conv, motion.pp("conv.0"))?,
            conv2: candle_nn::conv1d(h, h, 4, conv, motion.pp("conv.2"))?,
            motion_gru: BiGru::new(h, h, &motion.pp("gru"))?,
            motion_head: Head::new(2 * h, h, config.embed_dim, motion.pp("head"))?,
            emotion: candle_nn::linear(2 * h, config.emotions.len().max(1), vb.pp("emotion"))?,
            action: candle_nn::linear(2 * h, config.actions.len().max(1), vb.pp("action"))?,
            text_in: candle_nn::linear(config.text_dim, h, text.pp("input"))?,
            text_gru: BiGru::new(h, h, &text.pp("gru"))?,
            text_head: Head::new(2 * h, h, config.embed_dim, text.pp("head"))?,
            config,
        })
    }

    /// The device its weights live on.
    pub fn device(&self) -> &Device {
        self.conv1.weight().device()
    }

    /// Encode normalised motions (`lengths` multiples of [`UNIT`]).
    pub fn encode_motion(&self, motion: &Padded) -> Result<MotionOutputs> {
        // Each stage is zero past each clip's length, as in a batch of one: the second
        // convolution's window reaches one step beyond the end; the GRU reads no further.
        let within = |per_step: usize| -> Vec<usize> {
            motion
                .lengths
                .iter()
                .map(|&l| (l / per_step).max(1))
                .collect()
        };
        let x = movement_conv(&motion.values, &self.conv1, &within(UNIT / 2))?;
        let x = movement_conv(&x, &self.conv2, &within(UNIT))?;
        let steps = x.dim(1)?;
        let lengths: Vec<usize> = within(UNIT).iter().map(|&l| l.min(steps)).collect();
        let pooled = self.motion_gru.summary(&x, &lengths)?;
        Ok(MotionOutputs {
            embedding: unit_rows(&self.motion_head.forward(&pooled)?)?,
            emotion: self.emotion.forward(&pooled)?,
            action: self.action.forward(&pooled)?,
        })
    }

    /// Encode captions given as per-token embeddings; unit-length rows `(batch, embed_dim)`.
    pub fn encode_text(&self, text: &Padded) -> Result<Tensor> {
        let x = per_step(&self.text_in, &text.values, &text.lengths)?;
        let pooled = self.text_gru.summary(&x, &text.lengths)?;
        unit_rows(&self.text_head.forward(&pooled)?)
    }

    /// Symmetric InfoNCE over in-batch negatives. `same_caption[i][j]` marks pairs whose
    /// captions are identical: they are not negatives of each other (template captions
    /// repeat across clips, and pushing them apart would teach the model noise).
    pub fn contrastive_loss(
        &self,
        text: &Tensor,
        motion: &Tensor,
        same_caption: &[Vec<bool>],
    ) -> Result<Tensor> {
        let n = same_caption.len();
        let mask: Vec<f32> = (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                if i != j && same_caption[i][j] {
                    -1e9
                } else {
                    0.0
                }
            })
            .collect();
        let mask = Tensor::from_vec(mask, (n, n), text.device())?;
        let logits = ((text.matmul(&motion.t()?)? / self.config.temperature)? + mask)?;
        let targets = Tensor::arange(0u32, n as u32, text.device())?;
        let t2m = candle_nn::loss::cross_entropy(&logits, &targets)?;
        let m2t = candle_nn::loss::cross_entropy(&logits.t()?.contiguous()?, &targets)?;
        (t2m + m2t)? / 2.0
    }
}

/// Cross-entropy over the rows whose label is known (`None` rows are left out); zero when
/// no row has a label.
pub fn labelled_cross_entropy(logits: &Tensor, labels: &[Option<u32>]) -> Result<Tensor> {
    let (rows, targets): (Vec<u32>, Vec<u32>) = labels
        .iter()
        .enumerate()
        .filter_map(|(i, l)| l.map(|l| (i as u32, l)))
        .unzip();
    if rows.is_empty() {
        return Tensor::zeros((), DType::F32, logits.device());
    }
    let device = logits.device();
    let picked = logits.index_select(&Tensor::new(rows, device)?, 0)?;
    candle_nn::loss::cross_entropy(&picked, &Tensor::new(targets, device)?)
}

/// Overwrite every parameter with PyTorch's default initialisation, drawn from `seed`:
/// U(±1/√fan_in) for linear and convolution weights and their biases, U(±1/√hidden) for
/// the GRUs (candle's own initialisation is not seeded).
pub fn init_weights(varmap: &candle_nn::VarMap, seed: u64) -> Result<()> {
    let vars = varmap.data().lock().expect("varmap lock");
    let mut names: Vec<&String> = vars.keys().collect();
    names.sort();
    let fan_in = |weight: &str| -> usize {
        vars.get(weight)
            .map_or(1, |v| v.dims().iter().skip(1).product::<usize>().max(1))
    };
    for (i, name) in names.into_iter().enumerate() {
        let var = &vars[name];
        let bound = if name.contains("_ih_l") || name.contains("_hh_l") {
            1.0 / ((var.dims()[0] / 3) as f64).sqrt()
        } else if let Some(stem) = name.strip_suffix(".bias") {
            1.0 / (fan_in(&format!("{stem}.weight")) as f64).sqrt()
        } else {
            1.0 / (fan_in(name) as f64).sqrt()
        };
        let mut rng = SplitMix64::stream(seed, i as u64);
        let values: Vec<f32> = (0..var.elem_count())
            .map(|_| rng.range(-bound, bound) as f32)
            .collect();
        var.set(&Tensor::from_vec(values, var.dims(), var.device())?)?;
    }
    Ok(())
}

/// A fresh evaluator of `config` on `device` and its variables, initialised from `seed` as
/// [`init_weights`] does.
pub fn init_evaluator(
    config: EvaluatorConfig,
    seed: u64,
    device: &Device,
) -> Result<(Evaluator, candle_nn::VarMap)> {
    let varmap = candle_nn::VarMap::new();
    let net = Evaluator::new(config, VarBuilder::from_varmap(&varmap, DType::F32, device))?;
    init_weights(&varmap, seed)?;
    Ok((net, varmap))
}

/// `config.json` of an evaluator folder: the networks' shape, how they were trained and on
/// what.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluatorFile {
    /// Format tag ([`FORMAT`]).
    pub format: String,
    /// Network shape and label sets.
    pub config: EvaluatorConfig,
    /// Corpus folder it was trained on.
    pub corpus: PathBuf,
    /// Short sha256 of that corpus's manifest (which lists every shard's sha256).
    pub corpus_id: String,
    /// Text encoder whose caption embeddings it reads.
    pub text_encoder: String,
    /// Training settings (steps, batch, learning rate, seed…).
    pub train: serde_json::Value,
    /// Device training last ran on (`cpu`, `cuda:N`: a resume may change it); empty in older
    /// files.
    #[serde(default)]
    pub device: String,
}

/// Format tag of an evaluator's `config.json`.
pub const FORMAT: &str = "motionscale-evaluator-v1";
/// Files of an evaluator folder whose bytes make its content id.
pub const CONTENT_FILES: [&str; 4] = ["config.json", "model.safetensors", "mean.npy", "std.npy"];

/// Short sha256 of a corpus manifest: names the exact corpus (shard hashes included).
pub fn corpus_id(corpus_dir: &Path) -> std::result::Result<String, ModelError> {
    let path = corpus_dir.join("manifest.json");
    let bytes = std::fs::read(&path).map_err(|e| ModelError::io(&path, e))?;
    Ok(motionscale_core::hex(&Sha256::digest(&bytes)[..6]))
}

/// A trained evaluator loaded from its folder, with its own feature mean/std.
pub struct TrainedEvaluator {
    /// The networks.
    pub net: Evaluator,
    /// Its `config.json`.
    pub file: EvaluatorFile,
    /// Short sha256 of [`CONTENT_FILES`]: cited by every metric computed with it.
    pub id: String,
    mean: Vec<f32>,
    std: Vec<f32>,
}

fn read_stats(path: &Path, dim: usize) -> std::result::Result<Vec<f32>, ModelError> {
    let array = ingest::npy::read(path).map_err(|e| ModelError::invalid(path, e))?;
    if array.data.len() != dim {
        return Err(ModelError::invalid(
            path,
            format!("{} values, expected {dim}", array.data.len()),
        ));
    }
    Ok(array.data.iter().map(|&v| v as f32).collect())
}

impl TrainedEvaluator {
    /// Load the evaluator in `dir` onto `device`.
    pub fn load(dir: &Path, device: &Device) -> std::result::Result<Self, ModelError> {
        let file: EvaluatorFile = motionscale_core::read_json(&dir.join("config.json"))?;
        if file.format != FORMAT {
            return Err(ModelError::invalid(
                &dir.join("config.json"),
                format!("format {:?}, expected {FORMAT:?}", file.format),
            ));
        }
        let mut hasher = Sha256::new();
        for name in CONTENT_FILES {
            let path = dir.join(name);
            hasher.update(std::fs::read(&path).map_err(|e| ModelError::io(&path, e))?);
        }
        let weights = dir.join("model.safetensors");
        // SAFETY: the checkpoint is only read; it must not change while the model lives.
        let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[&weights], DType::F32, device) }
            .map_err(|e| ModelError::invalid(&weights, e))?;
        let net = Evaluator::new(file.config.clone(), vb)
            .map_err(|e| ModelError::invalid(&weights, e))?;
        let dim = file.config.feature_dim;
        Ok(Self {
            mean: read_stats(&dir.join("mean.npy"), dim)?,
            std: read_stats(&dir.join("std.npy"), dim)?,
            id: motionscale_core::hex(&hasher.finalize()[..6]),
            net,
            file,
        })
    }

    /// Build around freshly trained networks (used by training to validate).
    pub fn from_parts(net: Evaluator, file: EvaluatorFile, mean: Vec<f32>, std: Vec<f32>) -> Self {
        Self {
            net,
            file,
            id: String::new(),
            mean,
            std,
        }
    }

    /// Per-feature mean it normalises with.
    pub fn mean(&self) -> &[f32] {
        &self.mean
    }

    /// Per-feature standard deviation it normalises with.
    pub fn std(&self) -> &[f32] {
        &self.std
    }

    /// `features` (frames × feature_dim, de-normalised) normalised with the evaluator's own
    /// statistics and cut to its window: the first `max_frames` frames, rounded down to a
    /// multiple of [`UNIT`] (at least one unit).
    pub fn window(&self, features: &[f32], start: usize, frames: usize) -> Vec<f32> {
        let dim = self.file.config.feature_dim;
        let total = features.len() / dim;
        let start = start.min(total.saturating_sub(1));
        let len = frames.min(total - start).min(self.file.config.max_frames);
        let len = (len / UNIT * UNIT).max(UNIT.min(total - start));
        features[start * dim..(start + len) * dim]
            .chunks_exact(dim)
            .flat_map(|row| {
                row.iter()
                    .zip(&self.mean)
                    .zip(&self.std)
                    .map(|((v, m), s)| (v - m) / s)
            })
            .collect()
    }

    /// Embeddings and classifier predictions of whole motions (de-normalised features),
    /// `batch` at a time.
    pub fn embed_motions(
        &self,
        motions: &[&[f32]],
        batch: usize,
    ) -> std::result::Result<MotionPredictions, ModelError> {
        let mut out = MotionPredictions::default();
        let device = self.net.device();
        for chunk in motions.chunks(batch.max(1)) {
            let windows: Vec<Vec<f32>> = chunk
                .iter()
                .map(|m| self.window(m, 0, usize::MAX))
                .collect();
            let rows: Vec<&[f32]> = windows.iter().map(Vec::as_slice).collect();
            let mut run = || -> Result<()> {
                let padded = Padded::new(&rows, self.file.config.feature_dim, device)?;
                let o = self.net.encode_motion(&padded)?;
                let classes = |t: &Tensor| -> Result<Vec<usize>> {
                    let v: Vec<u32> = t.argmax(D::Minus1)?.to_vec1()?;
                    Ok(v.into_iter().map(|c| c as usize).collect())
                };
                out.embeddings.extend(o.embedding.to_vec2::<f32>()?);
                out.emotion.extend(classes(&o.emotion)?);
                out.action.extend(classes(&o.action)?);
                Ok(())
            };
            run().map_err(ModelError::Candle)?;
        }
        Ok(out)
    }

    /// Embeddings of captions given as per-token embeddings (`tokens × text_dim` each, cut
    /// to `max_text_tokens`), `batch` at a time.
    pub fn embed_texts(
        &self,
        texts: &[&[f32]],
        batch: usize,
    ) -> std::result::Result<Vec<Vec<f32>>, ModelError> {
        let c = &self.file.config;
        let device = self.net.device();
        let mut out = Vec::with_capacity(texts.len());
        for chunk in texts.chunks(batch.max(1)) {
            let rows: Vec<&[f32]> = chunk
                .iter()
                .map(|t| &t[..t.len().min(c.max_text_tokens * c.text_dim)])
                .collect();
            let run = || -> Result<Vec<Vec<f32>>> {
                let padded = Padded::new(&rows, c.text_dim, device)?;
                self.net.encode_text(&padded)?.to_vec2()
            };
            out.extend(run().map_err(ModelError::Candle)?);
        }
        Ok(out)
    }
}

/// What [`TrainedEvaluator::embed_motions`] returns, one entry per motion.
#[derive(Debug, Clone, Default)]
pub struct MotionPredictions {
    /// Unit-length embeddings.
    pub embeddings: Vec<Vec<f32>>,
    /// Predicted emotion class.
    pub emotion: Vec<usize>,
    /// Predicted action class.
    pub action: Vec<usize>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::VarMap;

    fn tiny() -> (Evaluator, VarMap) {
        let config = EvaluatorConfig {
            feature_dim: 6,
            text_dim: 5,
            hidden: 8,
            embed_dim: 4,
            max_frames: 16,
            max_text_tokens: 8,
            temperature: 0.1,
            emotions: vec!["happy".into(), "sad".into()],
            actions: vec!["walk".into()],
        };
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        (Evaluator::new(config, vb).unwrap(), varmap)
    }

    fn ramp(len: usize, width: usize, offset: f32) -> Vec<f32> {
        (0..len * width)
            .map(|i| (i as f32 * 0.37 + offset).sin())
            .collect()
    }

    fn rows(t: &Tensor) -> Vec<Vec<f32>> {
        t.to_vec2().unwrap()
    }

    /// The movement convolutions' weight gradients at a batch of three of different lengths
    /// agree with central differences (candle's own `conv1d` backward got them wrong for
    /// batches above one). The loss is piecewise linear in each weight (convolution, then
    /// leaky ReLU): where a step crosses a kink the one-sided differences disagree, and that
    /// weight is left out; most are not.
    #[test]
    fn movement_conv_gradients_match_central_differences() {
        let (eval, varmap) = tiny();
        init_weights(&varmap, 3).unwrap();
        let vars = varmap.data().lock().unwrap().clone();
        for (conv, name, width) in [
            (&eval.conv1, "motion.conv.0.weight", 6),
            (&eval.conv2, "motion.conv.2.weight", 8),
        ] {
            let clips: Vec<Vec<f32>> = (0..3).map(|b| ramp(16, width, b as f32)).collect();
            let refs: Vec<&[f32]> = clips.iter().map(Vec::as_slice).collect();
            let x = Padded::new(&refs, width, &Device::Cpu).unwrap().values;
            let probe = Tensor::arange(0f32, (3 * 8 * 8) as f32, &Device::Cpu)
                .unwrap()
                .sin()
                .unwrap()
                .reshape((3, 8, 8))
                .unwrap();
            let loss = || {
                (movement_conv(&x, conv, &[8, 5, 1]).unwrap() * &probe)
                    .unwrap()
                    .sum_all()
                    .unwrap()
            };
            let var = &vars[name];
            let grads = loss().backward().unwrap();
            let analytic: Vec<f32> = grads
                .get(var)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let values: Vec<f32> = var.flatten_all().unwrap().to_vec1().unwrap();
            let (mut checked, mut tried) = (0, 0);
            for i in (0..values.len()).step_by(5) {
                let at = |delta: f32| {
                    let mut v = values.clone();
                    v[i] += delta;
                    var.set(&Tensor::from_vec(v, var.dims(), &Device::Cpu).unwrap())
                        .unwrap();
                    loss().to_scalar::<f32>().unwrap()
                };
                let (up, mid, down) = (at(1e-2), at(0.0), at(-1e-2));
                let (ahead, behind) = ((up - mid) / 1e-2, (mid - down) / 1e-2);
                tried += 1;
                if (ahead - behind).abs() > 1e-2 * ahead.abs().max(1.0) {
                    continue;
                }
                checked += 1;
                let numeric = (up - down) / 2e-2;
                assert!(
                    (analytic[i] - numeric).abs() < 1e-2 * numeric.abs().max(1.0),
                    "{name}[{i}]: {} vs {numeric}",
                    analytic[i]
                );
            }
            assert!(
                2 * checked > tried,
                "{name}: {checked} of {tried} weights away from a kink"
            );
            var.set(&Tensor::from_vec(values, var.dims(), &Device::Cpu).unwrap())
                .unwrap();
        }
    }

    #[test]
    fn padding_does_not_change_an_embedding() {
        let (eval, _) = tiny();
        let (short, long) = (ramp(8, 6, 0.0), ramp(16, 6, 1.0));
        let alone = Padded::new(&[&short], 6, &Device::Cpu).unwrap();
        let padded = Padded::new(&[&short, &long], 6, &Device::Cpu).unwrap();
        let a = rows(&eval.encode_motion(&alone).unwrap().embedding);
        let b = rows(&eval.encode_motion(&padded).unwrap().embedding);
        let diff: f32 = a[0].iter().zip(&b[0]).map(|(x, y)| (x - y).abs()).sum();
        assert!(diff < 1e-5, "motion embeddings must ignore padding: {diff}");
        let (t_short, t_long) = (ramp(3, 5, 2.0), ramp(7, 5, 3.0));
        let alone = Padded::new(&[&t_short], 5, &Device::Cpu).unwrap();
        let padded = Padded::new(&[&t_short, &t_long], 5, &Device::Cpu).unwrap();
        let a = rows(&eval.encode_text(&alone).unwrap());
        let b = rows(&eval.encode_text(&padded).unwrap());
        let diff: f32 = a[0].iter().zip(&b[0]).map(|(x, y)| (x - y).abs()).sum();
        assert!(
            diff < 1e-5,
            "text embeddings must ignore padding exactly: {diff}"
        );
        let norm: f32 = b[1].iter().map(|v| v * v).sum();
        assert!((norm - 1.0).abs() < 1e-5);
    }

    #[test]
    fn contrastive_loss_matches_hand_computation_and_skips_duplicate_captions() {
        let (eval, _) = tiny();
        let text = Tensor::new(&[[1f32, 0.0], [0.0, 1.0]], &Device::Cpu).unwrap();
        let motion = Tensor::new(&[[1f32, 0.0], [0.6, 0.8]], &Device::Cpu).unwrap();
        let distinct = vec![vec![false; 2]; 2];
        let loss: f32 = eval
            .contrastive_loss(&text, &motion, &distinct)
            .unwrap()
            .to_scalar()
            .unwrap();
        // logits/τ = [[10, 6], [0, 8]]: text rows and motion columns.
        let lse = |a: f64, b: f64| (a.exp() + b.exp()).ln();
        let t2m = (lse(10.0, 6.0) - 10.0 + lse(0.0, 8.0) - 8.0) / 2.0;
        let m2t = (lse(10.0, 0.0) - 10.0 + lse(6.0, 8.0) - 8.0) / 2.0;
        assert!((f64::from(loss) - (t2m + m2t) / 2.0).abs() < 1e-5);
        let same = vec![vec![true; 2]; 2];
        let masked: f32 = eval
            .contrastive_loss(&text, &motion, &same)
            .unwrap()
            .to_scalar()
            .unwrap();
        assert!(
            masked.abs() < 1e-6,
            "only positives left: loss 0, got {masked}"
        );
    }

    #[test]
    fn unlabelled_rows_add_no_classifier_loss() {
        let logits = Tensor::new(&[[2f32, 0.0], [0.0, 2.0], [5.0, -5.0]], &Device::Cpu).unwrap();
        let all: f32 = labelled_cross_entropy(&logits, &[Some(0), Some(1), None])
            .unwrap()
            .to_scalar()
            .unwrap();
        let expected = (1.0 + (-2f64).exp()).ln();
        assert!((f64::from(all) - expected).abs() < 1e-6);
        let none: f32 = labelled_cross_entropy(&logits, &[None, None, None])
            .unwrap()
            .to_scalar()
            .unwrap();
        assert_eq!(none, 0.0);
    }
}
