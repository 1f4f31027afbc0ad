//! ES-MoE (L²-EMG; `../shared/docs/continual.md`): one LoRA expert per scenario on the frozen
//! prefix LM, mixed per sequence by a gate, θ' = θ + Σ_j w_j·ΔW_j.
//!
//! The gate reads the caption (the text prefix X, `L × E` token embeddings), the only input a
//! sequence has before its first motion token, so generation can run it too:
//! - CGED (causal-guided emotion decoupling): self-sampling s_x = softmax(f(X)·K(X)ᵀ/√c)·V(X),
//!   cross-sampling s_m = softmax(g(X)·K(D)ᵀ/√c)·V(D) over a global dictionary D (seeded
//!   K-means centroids of the first step's training text features, frozen), and
//!   h = W·(FFN₁(s_x) ⊕ FFN₂(s_m)) + b, mean-pooled over the caption; an MLP emotion
//!   classifier on h adds λ·CE(emotion) to the loss. Without CGED, h is a linear projection
//!   of X, pooled, and there is no emotion loss.
//! - Query up(down(h)) against mutually orthogonal expert keys (Gram–Schmidt at
//!   initialisation), softmax over the experts; during training each older expert is masked
//!   with a probability that falls linearly from `mask_probability` to 0 over the step's
//!   schedule; of the rest the top k are kept and their softmax renormalised.
//!
//! At step i only expert i's A and B, key i, and the gate network (CGED, emotion head, query
//! projections) train. Weights differ per caption, so training runs one sequence at a time
//! through the fused LM: expert i's gradient is Σ_b w_bi·∂L_b/∂W', and the gate's comes from
//! candle autograd on the surrogate Σ_b Σ_j w_bj·⟨∂L_b/∂W', ΔW_j⟩ (+ λ·CE), whose gradient
//! with respect to every gate parameter is the loss's (∂L/∂w_bj = ⟨∂L_b/∂W', ΔW_j⟩).
//!
//! Without the mixture (the "single LoRA" ablation) one expert is fine-tuned through every
//! step with weight 1 and no gate: since h reaches the LM only through the gate, that is
//! sequential LoRA by construction.
//!
//! Files of a run folder besides `config.json`: `adapter.safetensors` (every expert, keyed as
//! [`crate::lora`]), `gate.safetensors` (`gate.cged.*`, `gate.emotion.*`, `gate.query.*`,
//! `gate.keys.<j>`, the dictionary `gate.cged.dictionary`) and `moe.json` ([`MoeManifest`]).

pub mod train;

use crate::lora::{add_deltas, base_weights, merged_lm, LoraAdapter, LoraConfig, ADAPTER_FILE};
use crate::prefix_lm::{Compute, PrefixLm, PrefixLmConfig};
use crate::MotionLm;
use candle_core::{DType, Device, Result, Tensor, Var, D};
use candle_nn::{Init, Linear, Module, VarBuilder, VarMap};
use motionscale_core::rng::SplitMix64;
use motionscale_core::{read_json, write_json};
use nn::checkpoint::var_tensors;
use nn::kmeans::kmeans;
use nn::ModelError;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;

/// The gate's weights in a run folder.
pub const GATE_FILE: &str = "gate.safetensors";
/// The experts and emotion classes of a run folder.
pub const MANIFEST_FILE: &str = "moe.json";
/// K-means rows drawn from the training text features (more add little to 32 centroids).
const KMEANS_ROWS: usize = 20_000;
/// Lloyd iterations of the dictionary's K-means.
const KMEANS_ITERATIONS: usize = 25;

/// Everything that shapes an ES-MoE model and its training.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EsMoeConfig {
    /// Rank and scale of every expert.
    pub lora: LoraConfig,
    /// Experts kept per sequence (renormalised); ≥ 2 lets the gate learn from the LM loss.
    pub top_k: usize,
    /// Initial probability of masking each older expert during a step's training.
    pub mask_probability: f64,
    /// Expert keys created (the most steps a run can have).
    pub max_experts: usize,
    /// Width of the keys and queries (≥ `max_experts`, so the keys can be orthogonal).
    pub key_dim: usize,
    /// Width of the query network's down projection.
    pub query_hidden: usize,
    /// Width c of the CGED features h.
    pub cged_dim: usize,
    /// Centroids of the global dictionary.
    pub dictionary_size: usize,
    /// Weight λ of the emotion loss.
    pub emotion_weight: f64,
    /// Whether the CGED block (and its emotion classifier) builds h.
    pub cged: bool,
    /// Whether experts are mixed by the gate (otherwise one shared expert).
    pub mixture: bool,
}

impl Default for EsMoeConfig {
    /// Rank 8 (α 16), top-2, masking from 0.5, 16 keys of 16, query bottleneck 16, c = 64,
    /// 32 centroids, λ = 0.1, CGED and mixture on.
    fn default() -> Self {
        Self {
            lora: LoraConfig {
                rank: 8,
                alpha: 16.0,
            },
            top_k: 2,
            mask_probability: 0.5,
            max_experts: 16,
            key_dim: 16,
            query_hidden: 16,
            cged_dim: 64,
            dictionary_size: 32,
            emotion_weight: 0.1,
            cged: true,
            mixture: true,
        }
    }
}

/// `moe.json`: the experts in the order learned and the emotion classes of the classifier.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MoeManifest {
    /// Expert names (their key prefixes in `adapter.safetensors`), oldest first.
    pub experts: Vec<String>,
    /// Emotion classes, in classifier output order.
    pub emotions: Vec<String>,
}

/// A linear layer with zero-initialised variables (set by [`seeded_init`]).
fn linear(vb: &VarBuilder, inp: usize, out: usize, name: &str) -> Result<Linear> {
    let vb = vb.pp(name);
    let w = vb.get_with_hints((out, inp), "weight", Init::Const(0.0))?;
    let b = vb.get_with_hints(out, "bias", Init::Const(0.0))?;
    Ok(Linear::new(w, Some(b)))
}

/// Two linear layers with a ReLU between them.
struct Mlp(Linear, Linear);

impl Mlp {
    fn new(vb: &VarBuilder, inp: usize, hidden: usize, out: usize, name: &str) -> Result<Self> {
        let vb = vb.pp(name);
        Ok(Self(
            linear(&vb, inp, hidden, "0")?,
            linear(&vb, hidden, out, "2")?,
        ))
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.1.forward(&self.0.forward(x)?.relu()?)
    }
}

/// Scaled dot-product attention of queries over keys and values.
fn attend(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    let scale = 1.0 / (q.dim(D::Minus1)? as f64).sqrt();
    candle_nn::ops::softmax(&(q.matmul(&k.t()?)? * scale)?, D::Minus1)?.matmul(v)
}

/// The causal-guided emotion decoupling block.
struct Cged {
    self_q: Linear,
    self_k: Linear,
    self_v: Linear,
    cross_q: Linear,
    cross_k: Linear,
    cross_v: Linear,
    ffn_self: Mlp,
    ffn_cross: Mlp,
    fuse: Linear,
    dictionary: Tensor,
}

impl Cged {
    fn new(vb: &VarBuilder, c: &EsMoeConfig, text_dim: usize) -> Result<Self> {
        let (e, d) = (text_dim, c.cged_dim);
        Ok(Self {
            self_q: linear(vb, e, d, "self_q")?,
            self_k: linear(vb, e, d, "self_k")?,
            self_v: linear(vb, e, d, "self_v")?,
            cross_q: linear(vb, e, d, "cross_q")?,
            cross_k: linear(vb, e, d, "cross_k")?,
            cross_v: linear(vb, e, d, "cross_v")?,
            ffn_self: Mlp::new(vb, d, d, d, "ffn_self")?,
            ffn_cross: Mlp::new(vb, d, d, d, "ffn_cross")?,
            fuse: linear(vb, 2 * d, d, "fuse")?,
            dictionary: vb.get_with_hints(
                (c.dictionary_size, e),
                "dictionary",
                Init::Const(0.0),
            )?,
        })
    }

    /// h of every token of `x` (`L × E`), `L × c`.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let s_x = attend(
            &self.self_q.forward(x)?,
            &self.self_k.forward(x)?,
            &self.self_v.forward(x)?,
        )?;
        let dict = &self.dictionary;
        let s_m = attend(
            &self.cross_q.forward(x)?,
            &self.cross_k.forward(dict)?,
            &self.cross_v.forward(dict)?,
        )?;
        let both = Tensor::cat(
            &[self.ffn_self.forward(&s_x)?, self.ffn_cross.forward(&s_m)?],
            1,
        )?;
        self.fuse.forward(&both)
    }
}

/// The gate: h from the caption, the emotion head, and query·key scores over the experts.
struct Gate {
    varmap: VarMap,
    cged: Option<Cged>,
    /// h without CGED: a projection of the caption's tokens.
    input: Option<Linear>,
    emotion: Option<Mlp>,
    down: Linear,
    up: Linear,
    keys: Vec<Tensor>,
    text_dim: usize,
    cged_dim: usize,
    /// Where the gate's weights live (the base model's device).
    device: Device,
}

/// Fill every `.weight` matrix of `varmap` with PyTorch's `nn.Linear` default,
/// U(±1/√fan_in), drawn from `seed` and the variable's place in name order.
fn seeded_init(varmap: &VarMap, seed: u64) -> Result<()> {
    let vars = varmap.data().lock().expect("varmap lock");
    let mut names: Vec<&String> = vars.keys().filter(|n| n.ends_with(".weight")).collect();
    names.sort();
    for (i, name) in names.into_iter().enumerate() {
        let var = &vars[name];
        let (out, inp) = var.dims2()?;
        let bound = 1.0 / (inp as f64).sqrt();
        let mut rng = SplitMix64::stream(seed, i as u64);
        let values: Vec<f32> = (0..out * inp)
            .map(|_| rng.range(-bound, bound) as f32)
            .collect();
        var.set(&Tensor::from_vec(values, (out, inp), var.device())?)?;
    }
    Ok(())
}

/// `n` mutually orthogonal unit vectors of width `dim` (Gram–Schmidt on seeded Gaussians).
pub fn orthogonal_keys(n: usize, dim: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut rng = SplitMix64::stream(seed, 0x6b657973);
    let mut keys: Vec<Vec<f64>> = Vec::with_capacity(n);
    while keys.len() < n {
        let mut v: Vec<f64> = (0..dim).map(|_| rng.normal()).collect();
        for k in &keys {
            let dot: f64 = v.iter().zip(k).map(|(a, b)| a * b).sum();
            v.iter_mut().zip(k).for_each(|(a, b)| *a -= dot * b);
        }
        let norm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
        if norm > 1e-6 {
            keys.push(v.iter().map(|a| a / norm).collect());
        }
    }
    keys.into_iter()
        .map(|k| k.into_iter().map(|a| a as f32).collect())
        .collect()
}

impl Gate {
    fn new(
        c: &EsMoeConfig,
        text_dim: usize,
        emotions: usize,
        seed: u64,
        device: &Device,
    ) -> Result<Self> {
        if c.key_dim < c.max_experts {
            candle_core::bail!(
                "{} orthogonal keys need a key width of at least that (got {})",
                c.max_experts,
                c.key_dim
            )
        }
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, device).pp("gate");
        let d = c.cged_dim;
        let (cged, input, emotion) = if c.cged {
            (
                Some(Cged::new(&vb.pp("cged"), c, text_dim)?),
                None,
                Some(Mlp::new(&vb, d, d, emotions.max(1), "emotion")?),
            )
        } else {
            (None, Some(linear(&vb, text_dim, d, "input")?), None)
        };
        let down = linear(&vb.pp("query"), d, c.query_hidden, "down")?;
        let up = linear(&vb.pp("query"), c.query_hidden, c.key_dim, "up")?;
        let keys = (0..c.max_experts)
            .map(|j| vb.get_with_hints(c.key_dim, &format!("keys.{j}"), Init::Const(0.0)))
            .collect::<Result<Vec<_>>>()?;
        seeded_init(&varmap, seed)?;
        let vars = varmap.data().lock().expect("varmap lock").clone();
        for (j, key) in orthogonal_keys(c.max_experts, c.key_dim, seed)
            .into_iter()
            .enumerate()
        {
            vars[&format!("gate.keys.{j}")].set(&Tensor::new(key, device)?)?;
        }
        Ok(Self {
            varmap,
            cged,
            input,
            emotion,
            down,
            up,
            keys,
            text_dim,
            cged_dim: d,
            device: device.clone(),
        })
    }

    /// h of each caption (`rows × E` token embeddings), `batch × c`.
    fn h(&self, texts: &[&[f32]]) -> Result<Tensor> {
        let rows = texts
            .iter()
            .map(|t| {
                let n = t.len() / self.text_dim;
                if n == 0 {
                    return Tensor::zeros(self.cged_dim, DType::F32, &self.device);
                }
                let x = Tensor::from_slice(t, (n, self.text_dim), &self.device)?;
                let tokens = match (&self.cged, &self.input) {
                    (Some(cged), _) => cged.forward(&x)?,
                    (None, Some(input)) => input.forward(&x)?,
                    (None, None) => unreachable!("the gate has CGED or an input projection"),
                };
                tokens.mean(0)
            })
            .collect::<Result<Vec<_>>>()?;
        Tensor::stack(&rows, 0)
    }

    /// Scores query(h)·K_j of the first `experts` experts, `batch × experts`.
    fn scores(&self, h: &Tensor, experts: usize) -> Result<Tensor> {
        let query = self.up.forward(&self.down.forward(h)?.relu()?)?;
        let keys = Tensor::stack(&self.keys[..experts], 0)?;
        query.matmul(&keys.t()?)
    }

    /// Every gate variable by name.
    fn vars(&self) -> HashMap<String, Var> {
        self.varmap.data().lock().expect("varmap lock").clone()
    }
}

/// The additive mask keeping, of `scores`, the `k` largest not `masked` (0 for kept, −∞ for
/// dropped): softmax(scores + mask) is the top-k renormalised gate.
pub fn top_k_mask(scores: &[f32], masked: &[bool], k: usize) -> Vec<f32> {
    let mut open: Vec<usize> = (0..scores.len()).filter(|&j| !masked[j]).collect();
    open.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let mut mask = vec![f32::NEG_INFINITY; scores.len()];
    for &j in open.iter().take(k.max(1)) {
        mask[j] = 0.0;
    }
    mask
}

/// An ES-MoE model: the frozen base, the experts so far and the gate.
pub struct EsMoe {
    /// Its configuration.
    pub config: EsMoeConfig,
    /// The experts and emotion classes.
    pub manifest: MoeManifest,
    model: PrefixLmConfig,
    base: HashMap<String, Tensor>,
    experts: Vec<LoraAdapter>,
    gate: Gate,
    /// How the merged models run.
    compute: Compute,
}

impl EsMoe {
    /// The model of a run folder (`adapter.safetensors`, `gate.safetensors`, `moe.json`) on
    /// the base weights in `base_file`, loaded onto `device`.
    pub fn load(
        dir: &Path,
        base_file: &Path,
        model: &PrefixLmConfig,
        config: EsMoeConfig,
        device: &Device,
    ) -> std::result::Result<Self, ModelError> {
        let manifest: MoeManifest = read_json(&dir.join(MANIFEST_FILE))?;
        let mut moe = Self::build(
            model,
            config,
            base_weights(base_file, device)?,
            manifest.emotions.clone(),
            0,
        )?;
        moe.load_parts(dir, &manifest.experts)?;
        moe.manifest = manifest;
        Ok(moe)
    }

    /// A model with no expert yet on the device of `base`; gate initialised from `seed`.
    fn build(
        model: &PrefixLmConfig,
        config: EsMoeConfig,
        base: HashMap<String, Tensor>,
        emotions: Vec<String>,
        seed: u64,
    ) -> std::result::Result<Self, ModelError> {
        let device = base
            .get("head.weight")
            .ok_or_else(|| ModelError::argument("ES-MoE base", "no head.weight"))?
            .device()
            .clone();
        let gate = Gate::new(&config, model.text_dim, emotions.len(), seed, &device)?;
        Ok(Self {
            config,
            manifest: MoeManifest {
                experts: Vec::new(),
                emotions,
            },
            model: model.clone(),
            base,
            experts: Vec::new(),
            gate,
            compute: Compute::default(),
        })
    }

    /// Load the experts `names` and the gate from a run folder.
    fn load_parts(&mut self, dir: &Path, names: &[String]) -> std::result::Result<(), ModelError> {
        let adapters = dir.join(ADAPTER_FILE);
        for name in names {
            let expert =
                LoraAdapter::new(&self.model, self.config.lora, name, 0, &self.gate.device)
                    .map_err(ModelError::Candle)?;
            expert.load(&adapters)?;
            self.experts.push(expert);
        }
        self.manifest.experts = names.to_vec();
        let gate = dir.join(GATE_FILE);
        self.gate
            .varmap
            .load(&gate)
            .map_err(|e| ModelError::invalid(&gate, e))
    }

    /// Save the experts, the gate and the manifest into `dir`.
    pub fn save(&self, dir: &Path) -> std::result::Result<(), ModelError> {
        let mut adapters = HashMap::new();
        for expert in &self.experts {
            adapters.extend(var_tensors(&expert.vars()));
        }
        let save = |t: &HashMap<String, Tensor>, path: &Path| {
            nn::checkpoint::save_safetensors(t, path).map_err(|e| ModelError::invalid(path, e))
        };
        save(&adapters, &dir.join(ADAPTER_FILE))?;
        save(&var_tensors(&self.gate.vars()), &dir.join(GATE_FILE))?;
        Ok(write_json(&dir.join(MANIFEST_FILE), &self.manifest)?)
    }

    /// The global dictionary: K-means centroids of (up to [`KMEANS_ROWS`] seeded rows of)
    /// the token embeddings of the training captions `texts`.
    fn fit_dictionary(&self, texts: &[&[f32]], seed: u64) -> Result<()> {
        if self.gate.cged.is_none() {
            return Ok(());
        }
        let e = self.model.text_dim;
        let mut rows: Vec<&[f32]> = texts.iter().flat_map(|t| t.chunks_exact(e)).collect();
        SplitMix64::stream(seed, 0x64696374).shuffle(&mut rows);
        rows.truncate(KMEANS_ROWS);
        let flat: Vec<f32> = rows.concat();
        let k = self.config.dictionary_size;
        let mut centroids = kmeans(&flat, e, k, KMEANS_ITERATIONS, seed);
        // Fewer distinct rows than centroids: repeat them (the attention is unchanged).
        while centroids.len() < k {
            let again = centroids
                .get(centroids.len() % centroids.len().max(1))
                .cloned()
                .unwrap_or_else(|| vec![0.0; e]);
            centroids.push(again);
        }
        let values: Vec<f32> = centroids.concat();
        let dict = Tensor::from_vec(values, (k, e), &self.gate.device)?;
        self.gate.vars()["gate.cged.dictionary"].set(&dict)
    }

    /// Experts in the mixture.
    pub fn experts(&self) -> usize {
        self.experts.len()
    }

    /// The gate's weight of every expert for each caption, `masked` experts excluded.
    fn gate_weights(&self, h: &Tensor, masked: &[Vec<bool>]) -> Result<Tensor> {
        let n = self.experts.len();
        let scores = self.gate.scores(h, n)?;
        let values = scores.to_vec2::<f32>()?;
        let mask: Vec<f32> = values
            .iter()
            .zip(masked)
            .flat_map(|(s, m)| top_k_mask(s, m, self.config.top_k))
            .collect();
        let mask = Tensor::from_vec(mask, (values.len(), n), &self.gate.device)?;
        candle_nn::ops::softmax(&(scores + mask)?, D::Minus1)
    }

    /// The expert weights of one caption (top-k of every expert, renormalised; 1 for the one
    /// shared expert without the mixture).
    pub fn weights(&self, text: &[f32]) -> Result<Vec<f32>> {
        if !self.config.mixture || self.experts.len() == 1 {
            return Ok(vec![1.0; self.experts.len()]);
        }
        let h = self.gate.h(&[text])?;
        let none = vec![vec![false; self.experts.len()]];
        self.gate_weights(&h, &none)?.squeeze(0)?.to_vec1()
    }

    /// Every expert's update ΔW_j by weight name.
    fn deltas(&self) -> Result<Vec<Vec<(String, Tensor)>>> {
        self.experts.iter().map(LoraAdapter::deltas).collect()
    }

    /// The base with the experts merged in at `weights`: the model and its weight tensors.
    fn merged(
        &self,
        deltas: &[Vec<(String, Tensor)>],
        weights: &[f32],
    ) -> Result<(PrefixLm, HashMap<String, Tensor>)> {
        let updates: Vec<(f32, Vec<(String, Tensor)>)> = weights
            .iter()
            .copied()
            .zip(deltas.iter().cloned())
            .collect();
        let merged = add_deltas(&self.base, &updates)?;
        Ok((merged_lm(&self.model, &merged, self.compute)?, merged))
    }

    /// Run the merged models with `compute`.
    pub fn set_compute(&mut self, compute: Compute) {
        self.compute = compute;
    }

    /// The device of the base, the experts and the gate.
    pub fn device(&self) -> &Device {
        &self.gate.device
    }
}

impl MotionLm for EsMoe {
    fn config(&self) -> &PrefixLmConfig {
        &self.model
    }

    fn per_caption(&self) -> bool {
        true
    }

    fn for_caption(&self, text: &[f32]) -> Result<Cow<'_, PrefixLm>> {
        let weights = self.weights(text)?;
        Ok(Cow::Owned(self.merged(&self.deltas()?, &weights)?.0))
    }
}
