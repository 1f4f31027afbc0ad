//! Text-prefix autoregressive motion transformer (ScaMo): LLaMA-style pre-norm blocks
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
//! Weights live in candle tensors (built from a `VarBuilder`, optimised as `Var`s); the
//! forward and backward passes run on the CPU kernels of [`nn::lm_kernels`] directly
//! ([`PrefixLm::loss_and_grads`] returns a `GradStore` as `loss.backward()` would), which is
//! checked against candle's autograd of the same model written with composite ops.

use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, DType, Device, Layout, Result, Storage, Tensor, Var};
use candle_nn::{Init, VarBuilder, VarMap};
use motionscale_core::rng::SplitMix64;
use nn::head_loss;
use nn::lm_kernels::{self, LayerCache, Rope};
use nn::matmul::{transpose, Operand};
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
        let bad = |m: String| Err(ModelError::Argument(m));
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
        }
    }
}

fn matrix(vb: &VarBuilder, rows: usize, cols: usize, name: &str) -> Result<Tensor> {
    vb.get_with_hints((rows, cols), name, Init::Const(0.0))
}

/// One pre-norm block: `h += Wo·attn(Wqkv·RMSNorm(h; n1)); h += W2·swiglu(W13·RMSNorm(h; n2))`.
#[derive(Debug, Clone)]
struct Block {
    n1: Tensor,
    wqkv: Tensor,
    wo: Tensor,
    n2: Tensor,
    w13: Tensor,
    w2: Tensor,
}

/// The values of one block's weights.
struct BlockWeights<'a> {
    n1: &'a [f32],
    wqkv: &'a [f32],
    wo: &'a [f32],
    n2: &'a [f32],
    w13: &'a [f32],
    w2: &'a [f32],
}

impl BlockWeights<'_> {
    /// The four matrices as the forward products read them: each `W` (`out × in`) transposed.
    fn forward_mats(&self) -> [Operand<'_>; 4] {
        [self.wqkv, self.wo, self.w13, self.w2].map(|m| (m, true))
    }
}

/// What the backward pass needs from a block's forward pass.
struct BlockTrace {
    h: Vec<f32>,
    qkv: Vec<f32>,
    probs: Vec<f32>,
    a: Vec<f32>,
    h1: Vec<f32>,
    ab: Vec<f32>,
    sig: Vec<f32>,
}

/// Gradients of one block's weights, in [`Block`] field order.
type BlockGrads = [Vec<f32>; 6];

impl Block {
    fn new(c: &PrefixLmConfig, vb: VarBuilder) -> Result<Self> {
        let (d, f) = (c.d_model, c.ffn_hidden);
        Ok(Self {
            n1: vb.pp("n1").get_with_hints(d, "weight", Init::Const(1.0))?,
            wqkv: matrix(&vb.pp("attn.wqkv"), 3 * d, d, "weight")?,
            wo: matrix(&vb.pp("attn.wo"), d, d, "weight")?,
            n2: vb.pp("n2").get_with_hints(d, "weight", Init::Const(1.0))?,
            w13: matrix(&vb.pp("ffn.w13"), 2 * f, d, "weight")?,
            w2: matrix(&vb.pp("ffn.w2"), d, f, "weight")?,
        })
    }

    fn tensors(&self) -> [&Tensor; 6] {
        [
            &self.n1, &self.wqkv, &self.wo, &self.n2, &self.w13, &self.w2,
        ]
    }

    /// The block on rows `h` (`rows × d`) with its matrices read as `mats` (Wqkvᵀ, Woᵀ,
    /// W13ᵀ, W2ᵀ: [`BlockWeights::forward_mats`] or a decoding cache's copies); `attend` maps
    /// the packed QKV rows to the attention output and its softmax probabilities.
    fn forward(
        c: &PrefixLmConfig,
        w: &BlockWeights,
        [wqkv, wo, w13, w2]: [Operand; 4],
        h: Vec<f32>,
        attend: impl FnOnce(&[f32]) -> (Vec<f32>, Vec<f32>),
    ) -> (Vec<f32>, BlockTrace) {
        let (d, f, eps) = (c.d_model, c.ffn_hidden, c.norm_eps as f32);
        let rows = h.len() / d;
        let xn = lm_kernels::rms_norm(&h, w.n1, eps);
        let qkv = lm_kernels::matmul_new((&xn, false), wqkv, (rows, 3 * d, d));
        let (a, probs) = attend(&qkv);
        let mut h1 = h.clone();
        lm_kernels::gemm(&mut h1, (&a, false), wo, (rows, d, d), true);
        let xn = lm_kernels::rms_norm(&h1, w.n2, eps);
        let ab = lm_kernels::matmul_new((&xn, false), w13, (rows, 2 * f, d));
        let sig = lm_kernels::gate_sigmoid(&ab, f);
        let mut h2 = h1.clone();
        let act = lm_kernels::swiglu(&ab, &sig, f);
        lm_kernels::gemm(&mut h2, (&act, false), w2, (rows, d, f), true);
        let trace = BlockTrace {
            h,
            qkv,
            probs,
            a,
            h1,
            ab,
            sig,
        };
        (h2, trace)
    }

    /// Backward through the block: `gh` holds the gradient of its output on entry and of its
    /// input on return; returns the weights' gradients.
    fn backward(
        c: &PrefixLmConfig,
        w: &BlockWeights,
        t: &BlockTrace,
        attn: &lm_kernels::Attention,
        gh: &mut [f32],
    ) -> BlockGrads {
        let (d, f, eps) = (c.d_model, c.ffn_hidden, c.norm_eps as f32);
        let rows = gh.len() / d;
        // h2 = h1 + swiglu(ab)·W2ᵀ.
        let act = lm_kernels::swiglu(&t.ab, &t.sig, f);
        let g_w2 = lm_kernels::matmul_new((gh, true), (&act, false), (d, f, rows));
        let g_act = lm_kernels::matmul_new((gh, false), (w.w2, false), (rows, f, d));
        let g_ab = lm_kernels::swiglu_backward(&t.ab, &t.sig, &g_act, f);
        // ab = RMSNorm(h1)·W13ᵀ.
        let xn = lm_kernels::rms_norm(&t.h1, w.n2, eps);
        let g_w13 = lm_kernels::matmul_new((&g_ab, true), (&xn, false), (2 * f, d, rows));
        let g_xn = lm_kernels::matmul_new((&g_ab, false), (w.w13, false), (rows, d, 2 * f));
        let g_n2 = lm_kernels::rms_norm_backward(&t.h1, w.n2, &g_xn, eps, gh);
        // h1 = h + a·Woᵀ.
        let g_wo = lm_kernels::matmul_new((gh, true), (&t.a, false), (d, d, rows));
        let g_a = lm_kernels::matmul_new((gh, false), (w.wo, false), (rows, d, d));
        let g_qkv = attn.backward(&t.qkv, &t.probs, &g_a);
        // qkv = RMSNorm(h)·Wqkvᵀ.
        let xn = lm_kernels::rms_norm(&t.h, w.n1, eps);
        let g_wqkv = lm_kernels::matmul_new((&g_qkv, true), (&xn, false), (3 * d, d, rows));
        let g_xn = lm_kernels::matmul_new((&g_qkv, false), (w.wqkv, false), (rows, d, 3 * d));
        let g_n1 = lm_kernels::rms_norm_backward(&t.h, w.n1, &g_xn, eps, gh);
        [g_n1, g_wqkv, g_wo, g_n2, g_w13, g_w2]
    }
}

/// The values of every weight of a [`PrefixLm`].
struct Weights<'a> {
    tok_emb: &'a [f32],
    proj_w: &'a [f32],
    proj_b: &'a [f32],
    blocks: Vec<BlockWeights<'a>>,
    norm: &'a [f32],
    head: &'a [f32],
}

/// The f32 values of a contiguous CPU tensor's storage.
fn cpu_values<'a>(storage: &'a Storage, layout: &Layout) -> Result<&'a [f32]> {
    match (storage, layout.contiguous_offsets()) {
        (Storage::Cpu(CpuStorage::F32(v)), Some((start, end))) => Ok(&v[start..end]),
        _ => candle_core::bail!("the prefix LM runs on contiguous f32 CPU weights"),
    }
}

/// What the backward pass needs from the forward pass.
struct Trace {
    blocks: Vec<BlockTrace>,
    /// The last block's output.
    h: Vec<f32>,
}

/// An extra loss on the logits (`rows × V`): its value and its gradient with respect to the
/// logits, or `None` for no extra term.
pub type ExtraLoss<'a> = dyn Fn(&[f32]) -> Option<(f32, Vec<f32>)> + Sync + 'a;

/// The loss of the normalised motion rows `xn` and its gradients with respect to `xn` and
/// the head weight.
type HeadLoss<'a> = dyn Fn(&Weights<'_>, &[f32]) -> (f32, Vec<f32>, Vec<f32>) + Sync + 'a;

/// The text-prefix autoregressive transformer.
#[derive(Debug, Clone)]
pub struct PrefixLm {
    config: PrefixLmConfig,
    tok_emb: Tensor,
    proj_w: Tensor,
    proj_b: Tensor,
    blocks: Vec<Block>,
    norm: Tensor,
    head: Tensor,
    rope: Rope,
}

impl PrefixLm {
    /// Build the model from `vb` (new variables start at zero/one: see [`init_weights`]).
    pub fn new(config: &PrefixLmConfig, vb: VarBuilder) -> Result<Self> {
        config
            .validate()
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        let (d, v) = (config.d_model, config.vocab_size());
        let blocks = (0..config.n_layers)
            .map(|i| Block::new(config, vb.pp(format!("blocks.{i}"))))
            .collect::<Result<_>>()?;
        Ok(Self {
            tok_emb: matrix(&vb.pp("tok_emb"), v, d, "weight")?,
            proj_w: matrix(&vb.pp("prefix_proj"), d, config.text_dim, "weight")?,
            proj_b: vb
                .pp("prefix_proj")
                .get_with_hints(d, "bias", Init::Const(0.0))?,
            blocks,
            norm: vb
                .pp("norm")
                .get_with_hints(d, "weight", Init::Const(1.0))?,
            head: matrix(&vb.pp("head"), v, d, "weight")?,
            rope: Rope::new(config.head_dim(), config.rope_base, config.max_positions),
            config: config.clone(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &PrefixLmConfig {
        &self.config
    }

    /// Every weight, in a fixed order (embedding, projection, blocks, norm, head).
    fn tensors(&self) -> Vec<&Tensor> {
        let mut t = vec![&self.tok_emb, &self.proj_w, &self.proj_b];
        t.extend(self.blocks.iter().flat_map(Block::tensors));
        t.extend([&self.norm, &self.head]);
        t
    }

    /// Run `f` with read access to the values of every weight.
    fn with_weights<R>(&self, f: impl FnOnce(&Weights) -> Result<R>) -> Result<R> {
        let guards: Vec<_> = self
            .tensors()
            .into_iter()
            .map(|t| t.storage_and_layout())
            .collect();
        let v = guards
            .iter()
            .map(|(s, l)| cpu_values(s, l))
            .collect::<Result<Vec<_>>>()?;
        let blocks = v[3..v.len() - 2]
            .chunks(6)
            .map(|b| BlockWeights {
                n1: b[0],
                wqkv: b[1],
                wo: b[2],
                n2: b[3],
                w13: b[4],
                w2: b[5],
            })
            .collect();
        f(&Weights {
            tok_emb: v[0],
            proj_w: v[1],
            proj_b: v[2],
            blocks,
            norm: v[v.len() - 2],
            head: v[v.len() - 1],
        })
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

    /// `text · Wᵀ + b` of text rows (`rows × E`).
    fn project_text(&self, w: &Weights, text: &[f32]) -> Vec<f32> {
        let (d, e) = (self.config.d_model, self.config.text_dim);
        let rows = text.len() / e;
        let mut out = lm_kernels::matmul_new((text, false), (w.proj_w, true), (rows, d, e));
        out.chunks_mut(d)
            .for_each(|r| r.iter_mut().zip(w.proj_b).for_each(|(x, b)| *x += b));
        out
    }

    /// Rows of the input embedding for `tokens`.
    fn embed(&self, w: &Weights, tokens: &[u32]) -> Vec<f32> {
        let d = self.config.d_model;
        tokens
            .iter()
            .flat_map(|&t| &w.tok_emb[t as usize * d..][..d])
            .copied()
            .collect()
    }

    /// Forward pass through the blocks: the last block's output and, when `keep`, the
    /// blocks' traces.
    fn run(&self, w: &Weights, batch: &LmBatch, keep: bool) -> Result<Trace> {
        let (c, layout) = (&self.config, &batch.layout);
        self.check(layout)?;
        let attn = self.attention(layout);
        let mut h = self.embed(w, &batch.inputs);
        h.extend(self.project_text(w, &batch.text));
        let mut blocks = Vec::new();
        for bw in &w.blocks {
            let mats = bw.forward_mats();
            let (next, trace) = Block::forward(c, bw, mats, h, |qkv| attn.forward(qkv));
            if keep {
                blocks.push(trace);
            }
            h = next;
        }
        Ok(Trace { blocks, h })
    }

    /// `RMSNorm(h; norm)` of the motion slots' rows of the last block's output.
    fn final_norm(&self, w: &Weights, batch: &LmBatch, trace: &Trace) -> Vec<f32> {
        let rows = batch.inputs.len() * self.config.d_model;
        lm_kernels::rms_norm(&trace.h[..rows], w.norm, self.config.norm_eps as f32)
    }

    fn attention<'a>(&'a self, layout: &'a SeqLayout) -> lm_kernels::Attention<'a> {
        lm_kernels::Attention {
            layout,
            rope: &self.rope,
            heads: self.config.n_heads,
            d: self.config.d_model,
        }
    }

    /// `RMSNorm(h; norm) · headᵀ`, with `headᵀ` read as `head_t`.
    fn head(&self, w: &Weights, h: &[f32], head_t: Operand) -> Vec<f32> {
        let (d, v) = (self.config.d_model, self.config.vocab_size());
        let xn = lm_kernels::rms_norm(h, w.norm, self.config.norm_eps as f32);
        lm_kernels::matmul_new((&xn, false), head_t, (h.len() / d, v, d))
    }

    /// Logits of every real motion slot, `motion_rows × V` (sequence-major).
    pub fn forward(&self, batch: &LmBatch) -> Result<Tensor> {
        let logits = self.with_weights(|w| {
            let trace = self.run(w, batch, false)?;
            let h = &trace.h[..batch.inputs.len() * self.config.d_model];
            Ok(self.head(w, h, (w.head, true)))
        })?;
        let rows = batch.inputs.len();
        Tensor::from_vec(logits, (rows, self.config.vocab_size()), &Device::Cpu)
    }

    /// `log p(target)` of every motion slot of `batch` (NaN where there is no target); the
    /// head runs only on the slots with a target.
    pub fn target_log_probs(&self, batch: &LmBatch) -> Result<Vec<f32>> {
        self.with_weights(|w| {
            let trace = self.run(w, batch, false)?;
            let xn = self.final_norm(w, batch, &trace);
            let d = self.config.d_model;
            Ok(head_loss::linear_target_log_probs(
                &xn,
                w.head,
                d,
                &batch.targets,
            ))
        })
    }

    /// Mean cross-entropy over the targets of `batch` and the gradient of every weight
    /// (keyed by the weight tensors, as `loss.backward()` would key them). The head and
    /// the loss run fused, on the slots with a target only.
    pub fn loss_and_grads(&self, batch: &LmBatch) -> Result<(f32, GradStore)> {
        let d = self.config.d_model;
        self.loss_and_grads_by(batch, &|w, xn| {
            head_loss::linear_cross_entropy(xn, w.head, d, &batch.targets)
        })
    }

    /// As [`Self::loss_and_grads`], plus an [`ExtraLoss`] term on the logits: `extra(logits)`
    /// returns its value and its gradient with respect to the logits (e.g. distillation).
    pub fn loss_and_grads_with(
        &self,
        batch: &LmBatch,
        extra: &ExtraLoss<'_>,
    ) -> Result<(f32, GradStore)> {
        let (d, v) = (self.config.d_model, self.config.vocab_size());
        self.loss_and_grads_by(batch, &|w, xn| {
            let rows = xn.len() / d;
            let logits = lm_kernels::matmul_new((xn, false), (w.head, true), (rows, v, d));
            let (mut loss, mut g_logits) = lm_kernels::cross_entropy(&logits, v, &batch.targets);
            if let Some((term, g_term)) = extra(&logits) {
                loss += term;
                g_logits.iter_mut().zip(g_term).for_each(|(g, e)| *g += e);
            }
            let g_xn = lm_kernels::matmul_new((&g_logits, false), (w.head, false), (rows, d, v));
            let g_head = lm_kernels::matmul_new((&g_logits, true), (xn, false), (v, d, rows));
            (loss, g_xn, g_head)
        })
    }

    /// The loss and every weight's gradient, given `head_loss(weights, xn)`: the loss of the
    /// normalised motion rows `xn` and its gradients with respect to `xn` and the head.
    fn loss_and_grads_by(
        &self,
        batch: &LmBatch,
        head_loss: &HeadLoss<'_>,
    ) -> Result<(f32, GradStore)> {
        let (loss, grads) = lm_kernels::in_pool(|| {
            self.with_weights(|w| {
                let trace = self.run(w, batch, true)?;
                let xn = self.final_norm(w, batch, &trace);
                let (loss, g_xn, g_head) = head_loss(w, &xn);
                Ok((loss, self.backward(w, batch, &trace, &g_xn, g_head)))
            })
        })?;
        let mut store = GradStore::default();
        for (t, g) in self.tensors().into_iter().zip(grads) {
            store.insert(t, Tensor::from_vec(g, t.shape(), &Device::Cpu)?);
        }
        Ok((loss, store))
    }

    /// Backward pass from the gradients of the normalised motion rows and of the head: the
    /// gradient of every weight, in [`Self::tensors`] order.
    fn backward(
        &self,
        w: &Weights,
        batch: &LmBatch,
        trace: &Trace,
        g_xn: &[f32],
        g_head: Vec<f32>,
    ) -> Vec<Vec<f32>> {
        let c = &self.config;
        let (d, v, e, eps) = (c.d_model, c.vocab_size(), c.text_dim, c.norm_eps as f32);
        let motion = batch.inputs.len();
        let attn = self.attention(&batch.layout);
        let hm = &trace.h[..motion * d];
        let mut gh = vec![0f32; trace.h.len()];
        let g_norm = lm_kernels::rms_norm_backward(hm, w.norm, g_xn, eps, &mut gh[..motion * d]);
        let mut g_blocks: Vec<BlockGrads> = w
            .blocks
            .iter()
            .zip(&trace.blocks)
            .rev()
            .map(|(bw, bt)| Block::backward(c, bw, bt, &attn, &mut gh))
            .collect();
        g_blocks.reverse();
        // Inputs: embedding rows of the motion inputs, projection of the text rows.
        let mut g_emb = vec![0f32; v * d];
        for (&t, g) in batch.inputs.iter().zip(gh.chunks(d)) {
            let row = &mut g_emb[t as usize * d..][..d];
            row.iter_mut().zip(g).for_each(|(a, b)| *a += b);
        }
        let gt = &gh[motion * d..];
        let g_proj_w =
            lm_kernels::matmul_new((gt, true), (&batch.text, false), (d, e, gt.len() / d));
        let mut grads = vec![g_emb, g_proj_w, lm_kernels::column_sums(gt, d)];
        grads.extend(g_blocks.into_iter().flatten());
        grads.extend([g_norm, g_head]);
        grads
    }

    /// An empty decoding cache for sequences laid out by `layout`.
    pub fn new_cache(&self, layout: &SeqLayout) -> Result<DecodeCache> {
        let (c, d) = (&self.config, self.config.d_model);
        let (heads, hd, f) = (c.n_heads, c.head_dim(), c.ffn_hidden);
        // One row per step reads the weights fastest as they are (gemm's matrix-vector path).
        let transposed = (layout.batch > 1)
            .then(|| {
                self.with_weights(|w| {
                    let t = |b: &BlockWeights| {
                        [
                            transpose(b.wqkv, 3 * d, d),
                            transpose(b.wo, d, d),
                            transpose(b.w13, 2 * f, d),
                            transpose(b.w2, d, f),
                        ]
                    };
                    Ok(TransposedWeights {
                        blocks: w.blocks.iter().map(t).collect(),
                        head: transpose(w.head, c.vocab_size(), d),
                    })
                })
            })
            .transpose()?;
        Ok(DecodeCache {
            layers: (0..c.n_layers)
                .map(|_| LayerCache::new(layout, heads, hd))
                .collect(),
            transposed,
        })
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
        let (c, p, n_new) = (&self.config, layout.prefix_slots, to - from);
        let d = c.d_model;
        self.check(layout)?;
        if to > layout.slots() || tokens.len() != layout.batch * (to - from.max(p)) {
            candle_core::bail!(
                "slots {from}..{to} and {} tokens do not fit the layout",
                tokens.len()
            )
        }
        let logits = self.with_weights(|w| {
            let projected = if from < p {
                self.project_text(w, text)
            } else {
                Vec::new()
            };
            let motion = self.embed(w, tokens);
            let per_seq = to - from.max(p);
            let mut h = Vec::with_capacity(layout.batch * n_new * d);
            for b in 0..layout.batch {
                for s in from..to.min(p) {
                    h.extend_from_slice(&projected[(b * p + s) * d..][..d]);
                }
                h.extend_from_slice(&motion[b * per_seq * d..][..per_seq * d]);
            }
            let attn = self.attention(layout);
            let t = cache.transposed.as_ref();
            for (i, (bw, layer)) in w.blocks.iter().zip(&mut cache.layers).enumerate() {
                let attend = |qkv: &[f32]| (attn.cached(qkv, layer, (from, to)), Vec::new());
                let mats = t.map_or(bw.forward_mats(), |t| {
                    t.blocks[i].each_ref().map(|m| (m.as_slice(), false))
                });
                h = Block::forward(c, bw, mats, h, attend).0;
            }
            let last: Vec<f32> = h
                .chunks(n_new * d)
                .flat_map(|rows| &rows[(n_new - 1) * d..])
                .copied()
                .collect();
            let head_t = t.map_or((w.head, true), |t| (t.head.as_slice(), false));
            Ok(self.head(w, &last, head_t))
        })?;
        Tensor::from_vec(logits, (layout.batch, c.vocab_size()), &Device::Cpu)
    }
}

/// What cached decoding keeps between steps: each layer's keys and values and, for batches
/// of several sequences, the weights transposed.
pub struct DecodeCache {
    layers: Vec<LayerCache>,
    transposed: Option<TransposedWeights>,
}

/// Every matrix a decoding step multiplies by, transposed once (`in × out`), so that each
/// step's few-row products read it as it lies (see [`nn::matmul::transpose`]).
struct TransposedWeights {
    /// Per block: Wqkvᵀ, Woᵀ, W13ᵀ, W2ᵀ.
    blocks: Vec<[Vec<f32>; 4]>,
    head: Vec<f32>,
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

/// A freshly initialised model and its variables on the CPU.
pub fn init_model(config: &PrefixLmConfig, seed: u64) -> Result<(PrefixLm, VarMap)> {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let model = PrefixLm::new(config, vb)?;
    init_weights(&varmap, seed)?;
    Ok((model, varmap))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nn::gradcheck::max_abs_diff;
    use std::collections::HashMap;

    fn tiny() -> PrefixLmConfig {
        PrefixLmConfig::new(32, 2, 4, 20, 6)
    }

    fn text(n: usize, e: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64(seed);
        (0..n * e).map(|_| rng.range(-1.0, 1.0) as f32).collect()
    }

    fn logits(model: &PrefixLm, texts: &[&[f32]], motions: &[(&[u32], bool)]) -> Vec<Vec<f32>> {
        let batch = LmBatch::new(model.config(), texts, motions);
        model.forward(&batch).unwrap().to_vec2::<f32>().unwrap()
    }

    #[test]
    fn motion_is_causal_and_every_motion_slot_sees_the_whole_text() {
        let (model, _) = init_model(&tiny(), 1).unwrap();
        let t = text(5, 6, 2);
        let m = [3u32, 7, 1, 12, 5, 9];
        let base = logits(&model, &[&t], &[(&m, true)]);
        // Changing motion token k (input slot k + 1) leaves slots 0..=k alone and moves the rest.
        for k in 0..m.len() {
            let mut changed = m;
            changed[k] = (m[k] + 4) % 20;
            let other = logits(&model, &[&t], &[(&changed, true)]);
            for s in 0..=k {
                assert_eq!(
                    max_abs_diff(&base[s], &other[s]),
                    0.0,
                    "token {k} moved slot {s}"
                );
            }
            for s in k + 1..base.len() {
                assert!(
                    max_abs_diff(&base[s], &other[s]) > 1e-6,
                    "token {k} left slot {s}"
                );
            }
        }
        // Changing any text token moves the logits of every motion slot.
        for j in 0..5 {
            let mut changed = t.clone();
            changed[j * 6..(j + 1) * 6]
                .iter_mut()
                .for_each(|v| *v += 0.5);
            let other = logits(&model, &[&changed], &[(&m, true)]);
            for s in 0..base.len() {
                assert!(
                    max_abs_diff(&base[s], &other[s]) > 1e-6,
                    "text {j} left slot {s}"
                );
            }
        }
    }

    #[test]
    fn padding_changes_nothing() {
        let (model, _) = init_model(&tiny(), 3).unwrap();
        let (t0, t1) = (text(5, 6, 4), text(2, 6, 5));
        let (m0, m1) = ([1u32, 2, 3, 4], [9u32, 8]);
        // The shorter sequence first: its padding has no rows, so the longer one's start at 2.
        let both = logits(&model, &[&t1, &t0], &[(&m1, false), (&m0, true)]);
        let alone0 = logits(&model, &[&t0], &[(&m0, true)]);
        let alone1 = logits(&model, &[&t1], &[(&m1, false)]);
        assert_eq!((alone1.len(), alone0.len(), both.len()), (2, 5, 7));
        for s in 0..alone1.len() {
            assert!(max_abs_diff(&both[s], &alone1[s]) < 1e-5);
        }
        for s in 0..alone0.len() {
            assert!(max_abs_diff(&both[2 + s], &alone0[s]) < 1e-5);
        }
    }

    #[test]
    fn kv_cached_logits_equal_full_recomputation() {
        let (model, _) = init_model(&tiny(), 6).unwrap();
        let c = model.config().clone();
        let (t0, t1) = (text(4, 6, 7), text(2, 6, 8));
        let tokens = [[5u32, 11, 2, 19, 0, 7], [3, 3, 14, 1, 8, 6]];
        let full = logits(
            &model,
            &[&t0, &t1],
            &[(&tokens[0], true), (&tokens[1], true)],
        );
        let layout = SeqLayout::new(vec![4, 2], tokens[0].len() + 1);
        let mut text_rows = vec![0f32; 2 * 4 * 6];
        text_rows[..t0.len()].copy_from_slice(&t0);
        text_rows[24..24 + t1.len()].copy_from_slice(&t1);
        let mut cache = model.new_cache(&layout).unwrap();
        let p = layout.prefix_slots;
        let mut worst = 0f32;
        for t in 0..layout.motion_slots {
            let input: Vec<u32> = (0..2)
                .map(|b| if t == 0 { c.bos() } else { tokens[b][t - 1] })
                .collect();
            let (from, to) = if t == 0 {
                (0, p + 1)
            } else {
                (p + t, p + t + 1)
            };
            let step = model
                .forward_cached(&mut cache, &layout, &text_rows, &input, (from, to))
                .unwrap()
                .to_vec2::<f32>()
                .unwrap();
            for b in 0..2 {
                worst = worst.max(max_abs_diff(&step[b], &full[b * layout.motion_slots + t]));
            }
        }
        eprintln!("KV cache: largest logit difference from full recomputation {worst:.2e}");
        assert!(worst <= 1e-4, "cached vs full: {worst}");
    }

    /// The loss of `batch` with candle's composite ops (autograd-differentiable): the
    /// reference for [`PrefixLm::loss_and_grads`].
    fn reference_loss(c: &PrefixLmConfig, vars: &HashMap<String, Var>, batch: &LmBatch) -> Tensor {
        use candle_nn::ops::{rms_norm_slow, silu, softmax};
        let dev = &Device::Cpu;
        let w = |n: &str| vars[n].as_tensor().clone();
        let (l, d, f, hd) = (&batch.layout, c.d_model, c.ffn_hidden, c.head_dim());
        let eps = c.norm_eps as f32;
        let lin = |x: &Tensor, name: &str| x.matmul(&w(name).t().unwrap()).unwrap();
        let text_rows = batch.text.len() / c.text_dim;
        let text = Tensor::from_slice(&batch.text, (text_rows, c.text_dim), dev).unwrap();
        let text = lin(&text, "prefix_proj.weight")
            .broadcast_add(&w("prefix_proj.bias"))
            .unwrap();
        let inputs = Tensor::from_slice(&batch.inputs, batch.inputs.len(), dev).unwrap();
        let mut h = Tensor::cat(
            &[&w("tok_emb.weight").embedding(&inputs).unwrap(), &text],
            0,
        )
        .unwrap();
        // Rows in slot order, sequence by sequence (padding slots read an extra zero row),
        // and back.
        let all = l.batch * l.slots();
        let order: Vec<u32> = (0..l.batch)
            .flat_map(|b| (0..l.slots()).map(move |s| l.row(b, s).unwrap_or(l.rows()) as u32))
            .collect();
        let mut back = vec![0u32; l.rows()];
        order
            .iter()
            .enumerate()
            .filter(|(_, &r)| (r as usize) < l.rows())
            .for_each(|(i, &r)| back[r as usize] = i as u32);
        let (order, back) = (
            Tensor::new(order, dev).unwrap(),
            Tensor::new(back, dev).unwrap(),
        );
        let rope = Rope::new(hd, c.rope_base, 64);
        let table = |sin: bool| {
            let v: Vec<f32> = (0..l.batch)
                .flat_map(|b| (0..l.slots()).map(move |s| l.position(b, s)))
                .flat_map(|p| {
                    let (cos, s) = rope.at(p);
                    let t = if sin { s } else { cos };
                    t.iter().chain(t).copied().collect::<Vec<_>>()
                })
                .collect();
            Tensor::from_vec(v, (all, hd), dev).unwrap()
        };
        let (cos, sin) = (table(false), table(true));
        let rotate = |x: &Tensor| {
            let (x1, x2) = (
                x.narrow(1, 0, hd / 2).unwrap(),
                x.narrow(1, hd / 2, hd / 2).unwrap(),
            );
            let half = Tensor::cat(&[&x2.neg().unwrap(), &x1], 1).unwrap();
            ((x * &cos).unwrap() + (half * &sin).unwrap()).unwrap()
        };
        let mask: Vec<f32> = (0..l.batch * l.slots() * l.slots())
            .map(|ij| {
                let (b, i, j) = (
                    ij / l.slots() / l.slots(),
                    ij / l.slots() % l.slots(),
                    ij % l.slots(),
                );
                if l.allowed(b, i, j) {
                    0.0
                } else {
                    -1e9
                }
            })
            .collect();
        let mask = Tensor::from_vec(mask, (l.batch, l.slots(), l.slots()), dev).unwrap();
        for i in 0..c.n_layers {
            let p = |n: &str| format!("blocks.{i}.{n}");
            let xn = rms_norm_slow(&h, &w(&p("n1.weight")), eps).unwrap();
            let qkv = lin(&xn, &p("attn.wqkv.weight"));
            let zero = Tensor::zeros((1, 3 * d), DType::F32, dev).unwrap();
            let qkv = Tensor::cat(&[&qkv, &zero], 0)
                .unwrap()
                .index_select(&order, 0)
                .unwrap();
            let heads: Vec<Tensor> = (0..c.n_heads)
                .map(|k| {
                    let part = |o: usize| qkv.narrow(1, o * d + k * hd, hd).unwrap();
                    let seq = |x: Tensor| x.reshape((l.batch, l.slots(), hd)).unwrap();
                    let (q, kk, v) = (seq(rotate(&part(0))), seq(rotate(&part(1))), seq(part(2)));
                    let scores =
                        (q.matmul(&kk.t().unwrap()).unwrap() / (hd as f64).sqrt()).unwrap();
                    let probs = softmax(&(scores + &mask).unwrap(), 2).unwrap();
                    probs.matmul(&v).unwrap().reshape((all, hd)).unwrap()
                })
                .collect();
            let a = Tensor::cat(&heads, 1)
                .unwrap()
                .index_select(&back, 0)
                .unwrap();
            h = (&h + lin(&a, &p("attn.wo.weight"))).unwrap();
            let ab = lin(
                &rms_norm_slow(&h, &w(&p("n2.weight")), eps).unwrap(),
                &p("ffn.w13.weight"),
            );
            let act = (silu(&ab.narrow(1, 0, f).unwrap()).unwrap() * ab.narrow(1, f, f).unwrap())
                .unwrap();
            h = (&h + lin(&act, &p("ffn.w2.weight"))).unwrap();
        }
        let hm = h.narrow(0, 0, batch.inputs.len()).unwrap();
        let logits = lin(
            &rms_norm_slow(&hm, &w("norm.weight"), eps).unwrap(),
            "head.weight",
        );
        let (rows, targets): (Vec<u32>, Vec<u32>) = batch
            .targets
            .iter()
            .enumerate()
            .filter(|(_, &t)| t != lm_kernels::IGNORE)
            .map(|(r, &t)| (r as u32, t))
            .unzip();
        let picked = logits
            .index_select(&Tensor::new(rows, dev).unwrap(), 0)
            .unwrap();
        candle_nn::loss::cross_entropy(&picked, &Tensor::new(targets, dev).unwrap()).unwrap()
    }

    #[test]
    fn loss_and_gradients_match_candle_autograd_of_composite_ops() {
        let config = tiny();
        let (model, varmap) = init_model(&config, 11).unwrap();
        let (t0, t1) = (text(4, 6, 12), text(2, 6, 13));
        let (m0, m1) = ([4u32, 17, 2, 9, 0], [11u32, 3, 3]);
        let batch = LmBatch::new(&config, &[&t0, &t1], &[(&m0, true), (&m1, false)]);
        let (loss, grads) = model.loss_and_grads(&batch).unwrap();
        let vars = varmap.data().lock().unwrap().clone();
        let reference = reference_loss(&config, &vars, &batch);
        let expected = reference.to_scalar::<f32>().unwrap();
        assert!((loss - expected).abs() < 1e-5, "{loss} vs {expected}");
        let expected_grads = reference.backward().unwrap();
        let mut names: Vec<&String> = vars.keys().collect();
        names.sort();
        for name in names {
            let t = vars[name].as_tensor();
            let (ours, theirs) = (grads.get(t).unwrap(), expected_grads.get(t).unwrap());
            let scale = theirs
                .abs()
                .unwrap()
                .max_keepdim(0)
                .unwrap()
                .flatten_all()
                .unwrap()
                .max(0)
                .unwrap();
            let diff = (ours - theirs)
                .unwrap()
                .abs()
                .unwrap()
                .flatten_all()
                .unwrap()
                .max(0)
                .unwrap();
            let (diff, scale) = (
                diff.to_scalar::<f32>().unwrap(),
                scale.to_scalar::<f32>().unwrap(),
            );
            assert!(
                diff <= 1e-4 * scale.max(1e-3),
                "{name}: max |Δ| {diff} (max |g| {scale})"
            );
        }
    }
}
