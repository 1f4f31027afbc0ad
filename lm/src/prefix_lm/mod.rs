//! Text-prefix autoregressive motion transformer (ScaMo, Lu et al. 2024, "ScaMo: Exploring the
//! Scaling Law in Autoregressive Motion Generation"): LLaMA-style pre-norm blocks
//! (RMSNorm, fused-QKV attention with rotary positions, SwiGLU FFN with fused W1|W3, no
//! biases), frozen text-encoder token embeddings projected to the model width as a prefix,
//! then `[BOS, motion tokens…, EOS]`. Attention is bidirectional within the prefix, causal
//! within the motion, and every motion position sees the whole prefix; the loss covers the
//! motion positions only.
//!
//! Weights use the PyTorch key names of `../shared/bench/pytorch_prefix_lm.py`'s `PrefixLM`,
//! so `safetensors.torch.load_file` + `load_state_dict` loads them there (for the same d,
//! layers, heads, vocabulary and a 384-d text encoder):
//!
//! ```text
//! tok_emb.weight (V, d)                  prefix_proj.weight (d, E)   prefix_proj.bias (d)
//! blocks.{i}.n1.weight (d)               blocks.{i}.attn.wqkv.weight (3d, d)   rows [q | k | v]
//! blocks.{i}.attn.wo.weight (d, d)       blocks.{i}.n2.weight (d)
//! blocks.{i}.ffn.w13.weight (2f, d)      rows [W1 (gate, silu) | W3]   blocks.{i}.ffn.w2.weight (d, f)
//! norm.weight (d)                        head.weight (V, d)   (untied from tok_emb)
//! ```
//!
//! Vocabulary: the motion codes `0..K`, then BOS = K, EOS = K + 1, PAD = K + 2 (V = K + 3).
//!
//! The model is defined once here (shape, weights by name, built from a `VarBuilder`) and run
//! by one of three executors, as the tokenizer's convolutions are by two:
//! - [`Executor::Cpu`] (`cpu.rs`): the fused CPU kernels of [`nn::lm_kernels`] with a forward
//!   trace and a hand-written backward ([`PrefixLm::loss_and_grads`] returns a `GradStore`
//!   as `loss.backward()` would). f32 weights on the CPU only.
//! - [`Executor::Graph`] (`graph.rs`): the same model in candle's differentiable ops and the
//!   fused ops of [`nn::fused_ops`], on any device and in f32 or bf16 ([`Precision`]);
//!   candle's autograd gives the gradients.
//! - [`Executor::Gpu`] (`gpu.rs`): the graph executor's model with a forward trace and the
//!   backward written out (no autograd graph), for training on a GPU; its inference is
//!   `Graph`'s.
//!
//! Each executor is a module of free functions of the same shape (`forward(model, batch)`,
//! `loss_and_grads(model, batch, …)`, …) reading the weights by name ([`Weights`]).
//! Training may drop values of each block's attention and FFN outputs ([`LmBatch::dropout`],
//! [`nn::dropout`]); every executor drops the same ones.
//!
//! The executor follows the weights: f32 on the CPU runs `Cpu`, anything else `Gpu`;
//! [`Compute::executor`] forces one (tests and comparisons). Tests check that they agree
//! on the loss, every gradient, the logits and KV-cached decoding.

mod cpu;
mod gpu;
mod graph;
mod grid;

pub use gpu::StageClock;
#[cfg(test)]
mod tests;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var};
use candle_nn::{Init, VarBuilder, VarMap};
use motionscale_core::rng::SplitMix64;
use nn::device::Precision;
use nn::dropout::Dropout;
use nn::lm_kernels::{self, Rope};
use nn::seq_layout::SeqLayout;
use nn::ModelError;
use serde::{Deserialize, Serialize};

/// Special tokens appended to the motion codebook: BOS, EOS, PAD.
pub const SPECIAL_TOKENS: usize = 3;
/// Standard deviation of the initial weight matrices (the reference's `normal_(std=0.02)`).
pub const INIT_STD: f64 = 0.02;

/// The SwiGLU width of the reference and LLaMA's rule without rounding: round(8d/3).
pub fn ffn_hidden_for(d_model: usize) -> usize {
    (8 * d_model + 1) / 3
}

/// Shape of a prefix LM.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PrefixLmConfig {
    /// Width d.
    pub d_model: usize,
    /// Blocks.
    pub n_layers: usize,
    /// Attention heads (d divisible by it, even head width).
    pub n_heads: usize,
    /// SwiGLU hidden width f.
    pub ffn_hidden: usize,
    /// Motion codes K (the vocabulary adds [`SPECIAL_TOKENS`]).
    pub codebook_size: usize,
    /// Width E of the frozen text embeddings.
    pub text_dim: usize,
    /// Rotary base.
    pub rope_base: f64,
    /// RMSNorm epsilon.
    pub norm_eps: f64,
    /// Longest sequence (prefix + motion positions) the rotary table covers.
    pub max_positions: usize,
}

impl PrefixLmConfig {
    /// A configuration with the reference's conventions: f = round(8d/3), rotary base 1e4,
    /// RMSNorm eps 1e-6, 1024 positions.
    pub fn new(
        d_model: usize,
        n_layers: usize,
        n_heads: usize,
        codebook_size: usize,
        text_dim: usize,
    ) -> Self {
        Self {
            d_model,
            n_layers,
            n_heads,
            ffn_hidden: ffn_hidden_for(d_model),
            codebook_size,
            text_dim,
            rope_base: 10_000.0,
            norm_eps: 1e-6,
            max_positions: 1024,
        }
    }

    /// The configuration of a named preset.
    pub fn preset(name: &str, codebook_size: usize, text_dim: usize) -> Option<Self> {
        let p = preset(name)?;
        Some(Self::new(
            p.d_model,
            p.n_layers,
            p.n_heads,
            codebook_size,
            text_dim,
        ))
    }

    /// Vocabulary V = K + 3.
    pub fn vocab_size(&self) -> usize {
        self.codebook_size + SPECIAL_TOKENS
    }

    /// Begin-of-motion token.
    pub fn bos(&self) -> u32 {
        self.codebook_size as u32
    }

    /// End-of-motion token.
    pub fn eos(&self) -> u32 {
        self.codebook_size as u32 + 1
    }

    /// Padding token (never a target).
    pub fn pad(&self) -> u32 {
        self.codebook_size as u32 + 2
    }

    /// Width of one head.
    pub fn head_dim(&self) -> usize {
        self.d_model / self.n_heads.max(1)
    }

    /// Check that the shape is buildable.
    pub fn validate(&self) -> std::result::Result<(), ModelError> {
        let bad = |m: String| Err(ModelError::argument("model shape", m));
        if self.d_model == 0 || self.n_layers == 0 || self.n_heads == 0 || self.ffn_hidden == 0 {
            return bad(format!("empty model shape {self:?}"));
        }
        if self.d_model % self.n_heads != 0 || self.head_dim() % 2 != 0 {
            return bad(format!(
                "width {} must split into {} heads of even width",
                self.d_model, self.n_heads
            ));
        }
        if self.codebook_size == 0 || self.text_dim == 0 || self.max_positions < 2 {
            return bad(format!(
                "codebook {}, text width {} and positions {} must be positive",
                self.codebook_size, self.text_dim, self.max_positions
            ));
        }
        Ok(())
    }
}

/// A named model shape.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Preset {
    /// Name (`44M`…`3B` for ScaMo's table, `cpu-…` for the CPU ladder).
    pub name: &'static str,
    /// Blocks.
    pub n_layers: usize,
    /// Heads.
    pub n_heads: usize,
    /// Width.
    pub d_model: usize,
    /// Parameters the source states, where it states them (ScaMo Table 1).
    pub nominal_params: Option<f64>,
}

const fn scamo(
    name: &'static str,
    n_layers: usize,
    n_heads: usize,
    d_model: usize,
    nominal: f64,
) -> Preset {
    Preset {
        name,
        n_layers,
        n_heads,
        d_model,
        nominal_params: Some(nominal),
    }
}

const fn cpu(name: &'static str, n_layers: usize, d_model: usize) -> Preset {
    Preset {
        name,
        n_layers,
        n_heads: d_model / 64,
        d_model,
        nominal_params: None,
    }
}

/// ScaMo Table 1 (layers / heads / width), then the CPU ladder built by the same rule (heads
/// of width 64, depth growing with width), named by their block parameters.
pub const PRESETS: [Preset; 15] = [
    scamo("44M", 8, 8, 512, 44e6),
    scamo("111M", 12, 12, 768, 111e6),
    scamo("343M", 24, 16, 1024, 343e6),
    scamo("775M", 36, 20, 1280, 775e6),
    scamo("1.4B", 48, 24, 1536, 1.4e9),
    scamo("3B", 24, 32, 3200, 3e9),
    cpu("cpu-50K", 1, 64),
    cpu("cpu-100K", 2, 64),
    cpu("cpu-400K", 2, 128),
    cpu("cpu-800K", 4, 128),
    cpu("cpu-1.8M", 4, 192),
    cpu("cpu-3M", 4, 256),
    cpu("cpu-7M", 6, 320),
    cpu("cpu-14M", 8, 384),
    cpu("cpu-20M", 8, 448),
];

/// The preset called `name`.
pub fn preset(name: &str) -> Option<&'static Preset> {
    PRESETS.iter().find(|p| p.name == name)
}

/// One model input: text embeddings and motion tokens laid out by a [`SeqLayout`], real
/// slots only (sequence-major).
#[derive(Debug, Clone)]
pub struct LmBatch {
    /// The layout.
    pub layout: SeqLayout,
    /// Text embeddings of the real text slots, `Σ prefix_lens × E` row-major.
    pub text: Vec<f32>,
    /// Motion inputs `[BOS, m0, …]` of the real motion slots, `Σ motion_lens`.
    pub inputs: Vec<u32>,
    /// Next-token targets `[m0, …(, EOS)]`, one per input; [`lm_kernels::IGNORE`] on the
    /// slot after the last token of a clip that does not end there.
    pub targets: Vec<u32>,
    /// Residual dropout of a training step (the loss-and-gradient calls apply it; inference
    /// never does); `None` by default.
    pub dropout: Option<Dropout>,
}

impl LmBatch {
    /// A batch from per-sequence text embeddings (rows of `text_dim` values) and motion
    /// tokens with whether the clip ends there. A sequence of n tokens has a target per
    /// token, plus EOS when it ends: inputs `[BOS, m0, …]`, targets `[m0, …, m(n−1) (, EOS)]`,
    /// n (+1) slots (at least one).
    pub fn new(config: &PrefixLmConfig, texts: &[&[f32]], motions: &[(&[u32], bool)]) -> Self {
        let e = config.text_dim;
        let prefix_lens: Vec<usize> = texts.iter().map(|t| t.len() / e).collect();
        let motion_lens: Vec<usize> = motions
            .iter()
            .map(|(m, ends)| (m.len() + usize::from(*ends)).max(1))
            .collect();
        let layout = SeqLayout::packed(prefix_lens, motion_lens);
        let text = texts.concat();
        let (mut inputs, mut targets) = (Vec::new(), Vec::new());
        for (&(tokens, ends), &n) in motions.iter().zip(&layout.motion_lens) {
            inputs.push(config.bos());
            inputs.extend_from_slice(&tokens[..n - 1]);
            targets.extend_from_slice(&tokens[..n.min(tokens.len())]);
            if ends {
                targets.push(config.eos());
            }
            // An empty clip that does not end has one slot and nothing to predict.
            targets.resize(inputs.len(), lm_kernels::IGNORE);
        }
        Self {
            layout,
            text,
            inputs,
            targets,
            dropout: None,
        }
    }
}

fn matrix(vb: &VarBuilder, rows: usize, cols: usize, name: &str) -> Result<Tensor> {
    vb.get_with_hints((rows, cols), name, Init::Const(0.0))
}

/// The model's weights by name (the keys of the table above), whatever holds each one: the
/// model's tensors, one call's cast copies, the CPU executor's values, their gradients.
#[derive(Debug, Clone)]
pub(crate) struct Weights<T> {
    pub(crate) tok_emb: T,
    pub(crate) proj_w: T,
    pub(crate) proj_b: T,
    pub(crate) blocks: Vec<BlockWeights<T>>,
    pub(crate) norm: T,
    pub(crate) head: T,
}

/// One pre-norm block's weights: `h += Wo·attn(Wqkv·RMSNorm(h; n1)); h += W2·swiglu(W13·RMSNorm(h; n2))`.
#[derive(Debug, Clone)]
pub(crate) struct BlockWeights<T> {
    pub(crate) n1: T,
    pub(crate) wqkv: T,
    pub(crate) wo: T,
    pub(crate) n2: T,
    pub(crate) w13: T,
    pub(crate) w2: T,
}

/// What a weight is to the executors: a matrix of a product (cast to the product dtype), the
/// embedding table (rows gathered or one-hot multiplied in f32), or a vector (norm scales, bias).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Role {
    Matrix,
    Embedding,
    Vector,
}

impl<T> BlockWeights<T> {
    fn try_map_any<'a, U, E>(
        &'a self,
        f: &mut impl FnMut(Role, &'a T) -> std::result::Result<U, E>,
    ) -> std::result::Result<BlockWeights<U>, E> {
        Ok(BlockWeights {
            n1: f(Role::Vector, &self.n1)?,
            wqkv: f(Role::Matrix, &self.wqkv)?,
            wo: f(Role::Matrix, &self.wo)?,
            n2: f(Role::Vector, &self.n2)?,
            w13: f(Role::Matrix, &self.w13)?,
            w2: f(Role::Matrix, &self.w2)?,
        })
    }

    fn into_array(self) -> [T; 6] {
        [self.n1, self.wqkv, self.wo, self.n2, self.w13, self.w2]
    }
}

impl<T> Weights<T> {
    fn try_map_any<'a, U, E>(
        &'a self,
        mut f: impl FnMut(Role, &'a T) -> std::result::Result<U, E>,
    ) -> std::result::Result<Weights<U>, E> {
        Ok(Weights {
            tok_emb: f(Role::Embedding, &self.tok_emb)?,
            proj_w: f(Role::Matrix, &self.proj_w)?,
            proj_b: f(Role::Vector, &self.proj_b)?,
            blocks: self
                .blocks
                .iter()
                .map(|b| b.try_map_any(&mut f))
                .collect::<std::result::Result<_, E>>()?,
            norm: f(Role::Vector, &self.norm)?,
            head: f(Role::Matrix, &self.head)?,
        })
    }

    /// The same names, each weight mapped by `f` (given its role).
    pub(crate) fn try_map<'a, U>(
        &'a self,
        f: impl FnMut(Role, &'a T) -> Result<U>,
    ) -> Result<Weights<U>> {
        self.try_map_any(f)
    }

    /// The same names, each weight mapped by `f`.
    pub(crate) fn map<'a, U>(&'a self, mut f: impl FnMut(&'a T) -> U) -> Weights<U> {
        let mapped: std::result::Result<_, std::convert::Infallible> =
            self.try_map_any(|_, t| Ok(f(t)));
        mapped.unwrap_or_else(|never| match never {})
    }

    /// Every weight, by reference, in [`Self::into_vec`]'s order.
    pub(crate) fn refs(&self) -> Vec<&T> {
        self.map(|t| t).into_vec()
    }

    /// Every weight in a fixed order (embedding, projection, blocks, norm, head).
    pub(crate) fn into_vec(self) -> Vec<T> {
        let mut all = vec![self.tok_emb, self.proj_w, self.proj_b];
        all.extend(self.blocks.into_iter().flat_map(BlockWeights::into_array));
        all.extend([self.norm, self.head]);
        all
    }
}

impl Weights<Tensor> {
    fn new(config: &PrefixLmConfig, vb: &VarBuilder) -> Result<Self> {
        let (d, f, v) = (config.d_model, config.ffn_hidden, config.vocab_size());
        let vector =
            |vb: VarBuilder, name: &str, init: f64| vb.get_with_hints(d, name, Init::Const(init));
        let block = |vb: VarBuilder| -> Result<BlockWeights<Tensor>> {
            Ok(BlockWeights {
                n1: vector(vb.pp("n1"), "weight", 1.0)?,
                wqkv: matrix(&vb.pp("attn.wqkv"), 3 * d, d, "weight")?,
                wo: matrix(&vb.pp("attn.wo"), d, d, "weight")?,
                n2: vector(vb.pp("n2"), "weight", 1.0)?,
                w13: matrix(&vb.pp("ffn.w13"), 2 * f, d, "weight")?,
                w2: matrix(&vb.pp("ffn.w2"), d, f, "weight")?,
            })
        };
        Ok(Self {
            tok_emb: matrix(&vb.pp("tok_emb"), v, d, "weight")?,
            proj_w: matrix(&vb.pp("prefix_proj"), d, config.text_dim, "weight")?,
            proj_b: vector(vb.pp("prefix_proj"), "bias", 0.0)?,
            blocks: (0..config.n_layers)
                .map(|i| block(vb.pp(format!("blocks.{i}"))))
                .collect::<Result<_>>()?,
            norm: vector(vb.pp("norm"), "weight", 1.0)?,
            head: matrix(&vb.pp("head"), v, d, "weight")?,
        })
    }

    /// A `GradStore` keyed by these tensors from their gradients (absent ones left out),
    /// each reshaped to its weight's shape.
    pub(crate) fn grad_store(&self, grads: Weights<Option<Tensor>>) -> Result<GradStore> {
        let mut store = GradStore::default();
        for (t, g) in self.refs().into_iter().zip(grads.into_vec()) {
            if let Some(g) = g {
                store.insert(t, g.reshape(t.shape())?);
            }
        }
        Ok(store)
    }
}

/// Which implementation runs the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Executor {
    /// Fused CPU kernels with a hand-written backward (f32 CPU weights only).
    Cpu,
    /// candle's differentiable ops with autograd, on any device and dtype.
    Graph,
    /// The GPU executor: the graph executor's model and fused ops with the backward written out
    /// (no autograd graph), for training off the CPU (it runs wherever candle's tensors do);
    /// inference runs the graph executor. Named `fused` before 2026-11-29.
    #[serde(alias = "fused")]
    #[value(alias = "fused")]
    Gpu,
}

/// How a model computes: the executor (by default the one its weights call for) and the
/// precision of the graph executor's products.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Compute {
    /// Forced executor, or `None` to follow the weights' device and dtype.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub executor: Option<Executor>,
    /// f32, or bf16 products from f32 master weights (graph executor only).
    #[serde(default)]
    pub precision: Precision,
}

/// An extra loss on the logits (`rows × V`): its value and its gradient with respect to the
/// logits, or `None` for no extra term.
pub type ExtraLoss<'a> = dyn Fn(&[f32]) -> Option<(f32, Vec<f32>)> + Sync + 'a;

/// The text-prefix autoregressive transformer.
#[derive(Debug, Clone)]
pub struct PrefixLm {
    config: PrefixLmConfig,
    weights: Weights<Tensor>,
    rope: Rope,
    compute: Compute,
}

impl PrefixLm {
    /// Build the model from `vb` (new variables start at zero/one: see [`init_weights`]); it
    /// runs on the executor its weights call for, in f32, until [`Self::with_compute`].
    pub fn new(config: &PrefixLmConfig, vb: VarBuilder) -> Result<Self> {
        config
            .validate()
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        Ok(Self {
            weights: Weights::new(config, &vb)?,
            rope: Rope::new(config.head_dim(), config.rope_base, config.max_positions),
            config: config.clone(),
            compute: Compute::default(),
        })
    }

    /// The model run with `compute`'s executor and precision.
    pub fn with_compute(mut self, compute: Compute) -> Self {
        self.compute = compute;
        self
    }

    /// The configuration.
    pub fn config(&self) -> &PrefixLmConfig {
        &self.config
    }

    /// The device of the weights.
    pub fn device(&self) -> &Device {
        self.weights.head.device()
    }

    /// The executor that runs the model: the forced one, else `Cpu` for f32 CPU weights in
    /// f32 and `Gpu` for anything else (whose inference is `Graph`'s). Forcing `Cpu` on
    /// other weights is an error.
    pub fn executor(&self) -> Result<Executor> {
        let cpu_ok = self.weights.head.device().is_cpu()
            && self.weights.head.dtype() == DType::F32
            && self.compute.precision == Precision::F32;
        match self.compute.executor {
            Some(Executor::Cpu) if !cpu_ok => candle_core::bail!(
                "the cpu executor runs f32 weights on the CPU in f32 (weights {:?} on {}, \
                 precision {}): use the graph executor",
                self.weights.head.dtype(),
                nn::device::device_name(self.weights.head.device()),
                self.compute.precision
            ),
            Some(e) => Ok(e),
            None if cpu_ok => Ok(Executor::Cpu),
            None => Ok(Executor::Gpu),
        }
    }

    fn check(&self, layout: &SeqLayout) -> Result<()> {
        if layout.max_position() >= self.rope.max_positions() {
            candle_core::bail!(
                "position {} beyond the {} of the rotary table",
                layout.max_position(),
                self.rope.max_positions()
            )
        }
        Ok(())
    }

    /// Logits of every real motion slot, `motion_rows × V` (sequence-major), f32 on the
    /// weights' device.
    pub fn forward(&self, batch: &LmBatch) -> Result<Tensor> {
        match self.executor()? {
            Executor::Cpu => cpu::forward(self, batch),
            Executor::Graph | Executor::Gpu => graph::forward(self, batch),
        }
    }

    /// `log p(target)` of every motion slot of `batch` (NaN where there is no target); the
    /// head runs only on the slots with a target.
    pub fn target_log_probs(&self, batch: &LmBatch) -> Result<Vec<f32>> {
        match self.executor()? {
            Executor::Cpu => cpu::target_log_probs(self, batch),
            Executor::Graph | Executor::Gpu => graph::target_log_probs(self, batch),
        }
    }

    /// Mean cross-entropy over the targets of `batch` and the gradient of every weight
    /// (keyed by the weight tensors, as `loss.backward()` would key them; f32, on the
    /// weights' device).
    pub fn loss_and_grads(&self, batch: &LmBatch) -> Result<(f32, GradStore)> {
        match self.executor()? {
            Executor::Cpu => cpu::loss_and_grads(self, batch),
            Executor::Graph => graph::loss_and_grads(self, batch, None),
            Executor::Gpu => gpu::loss_and_grads(self, batch, None),
        }
    }

    /// [`Self::loss_and_grads`], with `clock` told as each stage of the step ends: the GPU
    /// executor's stages (where a GPU step spends its time); the other executors' whole step
    /// is one stage, `step`.
    pub fn loss_and_grads_timed(
        &self,
        batch: &LmBatch,
        clock: &dyn StageClock,
    ) -> Result<(f32, GradStore)> {
        match self.executor()? {
            Executor::Gpu => gpu::loss_and_grads(self, batch, Some(clock)),
            Executor::Cpu | Executor::Graph => {
                let out = self.loss_and_grads(batch)?;
                clock.stage_done("step")?;
                Ok(out)
            }
        }
    }

    /// As [`Self::loss_and_grads`], plus an [`ExtraLoss`] term on the logits: `extra(logits)`
    /// returns its value and its gradient with respect to the logits (e.g. distillation).
    pub fn loss_and_grads_with(
        &self,
        batch: &LmBatch,
        extra: &ExtraLoss<'_>,
    ) -> Result<(f32, GradStore)> {
        match self.executor()? {
            Executor::Cpu => cpu::loss_and_grads_with(self, batch, extra),
            // The extra term's gradient enters at the logits: the graph executor's autograd.
            Executor::Graph | Executor::Gpu => graph::loss_and_grads(self, batch, Some(extra)),
        }
    }

    /// An empty decoding cache for sequences laid out by `layout`.
    pub fn new_cache(&self, layout: &SeqLayout) -> Result<DecodeCache> {
        Ok(DecodeCache(match self.executor()? {
            Executor::Cpu => CacheKind::Cpu(cpu::new_cache(self, layout)?),
            Executor::Graph | Executor::Gpu => {
                CacheKind::Graph(graph::GraphCache::new(self.config.n_layers))
            }
        }))
    }

    /// Run slots `from..to` of every sequence through the model against `cache` (filled
    /// below `from`) and return the logits of each sequence's last new slot (`batch × V`).
    /// `text` (`batch · prefix_slots × E`) is read for new text slots; `tokens` holds the
    /// inputs of the new motion slots, sequence-major.
    pub fn forward_cached(
        &self,
        cache: &mut DecodeCache,
        layout: &SeqLayout,
        text: &[f32],
        tokens: &[u32],
        (from, to): (usize, usize),
    ) -> Result<Tensor> {
        let p = layout.prefix_slots;
        self.check(layout)?;
        if to > layout.slots() || tokens.len() != layout.batch * (to - from.max(p)) {
            candle_core::bail!(
                "slots {from}..{to} and {} tokens do not fit the layout",
                tokens.len()
            )
        }
        match &mut cache.0 {
            CacheKind::Cpu(c) => cpu::forward_cached(self, c, layout, text, tokens, (from, to)),
            CacheKind::Graph(c) => graph::forward_cached(self, c, layout, text, tokens, (from, to)),
        }
    }
}

/// What cached decoding keeps between steps, for the executor that made it.
pub struct DecodeCache(CacheKind);

enum CacheKind {
    Cpu(cpu::CpuCache),
    Graph(graph::GraphCache),
}

/// Fill every weight matrix of `varmap` with N(0, [`INIT_STD`]²) values drawn from a
/// generator seeded by `seed` and the variable's name (norm scales and biases keep their
/// ones and zeros), so initial weights depend on nothing but the seed.
pub fn init_weights(varmap: &VarMap, seed: u64) -> Result<()> {
    let vars = varmap.data().lock().expect("varmap lock");
    let mut names: Vec<&String> = vars.keys().collect();
    names.sort();
    for name in names {
        let var: &Var = &vars[name];
        if var.rank() != 2 {
            continue;
        }
        let mut rng = SplitMix64(seed ^ fnv1a(name.as_bytes()));
        let n = var.elem_count();
        let mut values = Vec::with_capacity(n + 1);
        while values.len() < n {
            // Box–Muller: two normals per pair of uniforms.
            let (u1, u2) = (1.0 - rng.unit(), rng.unit());
            let r = (-2.0 * u1.ln()).sqrt() * INIT_STD;
            let t = std::f64::consts::TAU * u2;
            values.push((r * t.cos()) as f32);
            values.push((r * t.sin()) as f32);
        }
        values.truncate(n);
        var.set(&Tensor::from_vec(values, var.shape(), var.device())?)?;
    }
    Ok(())
}

/// FNV-1a hash (stable across versions, unlike `DefaultHasher`).
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// A freshly initialised model (f32 weights on `device`) and its variables.
pub fn init_model(
    config: &PrefixLmConfig,
    seed: u64,
    device: &Device,
) -> Result<(PrefixLm, VarMap)> {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
    let model = PrefixLm::new(config, vb)?;
    init_weights(&varmap, seed)?;
    Ok((model, varmap))
}
