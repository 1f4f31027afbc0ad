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

use crate::fused::{self, LayerCache, Rope};
use crate::ModelError;
use candle_core::{DType, Device, Result, Tensor, Var};
use candle_nn::{Init, VarBuilder, VarMap};
use ingest::rng::SplitMix64;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

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

/// How a batch of sequences is stored: every sequence has `prefix_slots` text slots (the
/// first `prefix_lens[b]` real, the rest padding that no position attends to) and
/// `motion_slots` motion slots. Rows hold all motion slots first (sample-major), then all
/// prefix slots, so the motion rows the head reads are one contiguous block.
///
/// Slot `s` of a sequence is a text slot for `s < prefix_slots`, else motion slot
/// `s − prefix_slots`. Positions are contiguous over the real tokens: text slot j sits at j,
/// motion slot t at `prefix_lens[b] + t`, so padding never shifts a rotary position.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SeqLayout {
    /// Sequences.
    pub batch: usize,
    /// Text slots per sequence.
    pub prefix_slots: usize,
    /// Motion slots per sequence.
    pub motion_slots: usize,
    /// Real text tokens of each sequence.
    pub prefix_lens: Vec<usize>,
}

impl SeqLayout {
    /// A layout padded to the longest prefix of `prefix_lens`.
    pub fn new(prefix_lens: Vec<usize>, motion_slots: usize) -> Self {
        Self {
            batch: prefix_lens.len(),
            prefix_slots: prefix_lens.iter().copied().max().unwrap_or(0),
            motion_slots,
            prefix_lens,
        }
    }

    /// Slots per sequence.
    pub fn slots(&self) -> usize {
        self.prefix_slots + self.motion_slots
    }

    /// Rows of the whole batch.
    pub fn rows(&self) -> usize {
        self.batch * self.slots()
    }

    /// Row of slot `s` of sequence `b`.
    pub fn row(&self, b: usize, s: usize) -> usize {
        if s < self.prefix_slots {
            self.batch * self.motion_slots + b * self.prefix_slots + s
        } else {
            b * self.motion_slots + s - self.prefix_slots
        }
    }

    /// Rotary position of slot `s` of sequence `b`.
    pub fn position(&self, b: usize, s: usize) -> usize {
        if s < self.prefix_slots {
            s
        } else {
            self.prefix_lens[b] + s - self.prefix_slots
        }
    }

    /// Highest position in the batch.
    pub fn max_position(&self) -> usize {
        (0..self.batch)
            .map(|b| self.position(b, self.slots().saturating_sub(1)))
            .max()
            .unwrap_or(0)
    }

    /// Whether slot `i` of sequence `b` attends to slot `j`: real text slots are seen by
    /// every slot; motion slots only by motion slots at or after them.
    pub fn allowed(&self, b: usize, i: usize, j: usize) -> bool {
        if j < self.prefix_slots {
            j < self.prefix_lens[b]
        } else {
            i >= self.prefix_slots && j <= i
        }
    }
}

/// One model input: text embeddings and motion tokens laid out by a [`SeqLayout`].
#[derive(Debug, Clone)]
pub struct LmBatch {
    /// The layout.
    pub layout: Arc<SeqLayout>,
    /// Text embeddings, `batch · prefix_slots × E` (padding rows zero).
    pub text: Tensor,
    /// Motion inputs `[BOS, m0, …]`, `batch · motion_slots` u32 (PAD after the end).
    pub inputs: Tensor,
    /// Next-token targets `[m0, …, EOS]`, [`fused::IGNORE`] on padding.
    pub targets: Arc<Vec<u32>>,
}

impl LmBatch {
    /// A batch from per-sequence text embeddings (rows of `text_dim` values) and motion
    /// tokens with whether the clip ends there. A sequence of n tokens has a target per
    /// token, plus EOS when it ends: inputs `[BOS, m0, …]`, targets `[m0, …, m(n−1) (, EOS)]`,
    /// n (+1) slots; all sequences are padded to the longest.
    pub fn new(
        config: &PrefixLmConfig,
        texts: &[&[f32]],
        motions: &[(&[u32], bool)],
        device: &Device,
    ) -> Result<Self> {
        let e = config.text_dim;
        let prefix_lens: Vec<usize> = texts.iter().map(|t| t.len() / e).collect();
        let slots = |(m, ends): &(&[u32], bool)| (m.len() + usize::from(*ends)).max(1);
        let motion_slots = motions.iter().map(slots).max().unwrap_or(1);
        let layout = SeqLayout::new(prefix_lens, motion_slots);
        let mut text = vec![0f32; layout.batch * layout.prefix_slots * e];
        for (b, t) in texts.iter().enumerate() {
            text[b * layout.prefix_slots * e..][..t.len()].copy_from_slice(t);
        }
        let mut inputs = vec![config.pad(); layout.batch * motion_slots];
        let mut targets = vec![fused::IGNORE; layout.batch * motion_slots];
        for (b, motion) in motions.iter().enumerate() {
            let (tokens, ends) = *motion;
            let n = slots(motion);
            let inp = &mut inputs[b * motion_slots..][..n];
            inp[0] = config.bos();
            inp[1..].copy_from_slice(&tokens[..n - 1]);
            let tgt = &mut targets[b * motion_slots..][..n];
            tgt[..tokens.len()].copy_from_slice(tokens);
            if ends {
                tgt[tokens.len()] = config.eos();
            }
        }
        let rows = layout.batch * layout.prefix_slots;
        Ok(Self {
            text: Tensor::from_vec(text, (rows, e), device)?,
            inputs: Tensor::from_vec(inputs, layout.batch * motion_slots, device)?,
            targets: Arc::new(targets),
            layout: Arc::new(layout),
        })
    }
}

fn matrix(vb: &VarBuilder, rows: usize, cols: usize, name: &str) -> Result<Tensor> {
    vb.get_with_hints((rows, cols), name, Init::Const(0.0))
}

/// The learned scale of an RMSNorm, applied fused with the projection after it.
#[derive(Debug, Clone)]
struct RmsNorm {
    weight: Tensor,
    eps: f32,
}

impl RmsNorm {
    fn new(d: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get_with_hints(d, "weight", Init::Const(1.0))?,
            eps: eps as f32,
        })
    }

    /// `RMSNorm(x) · wᵀ`.
    fn linear(&self, x: &Tensor, w: &Tensor) -> Result<Tensor> {
        fused::norm_linear(x, &self.weight, w, self.eps)
    }
}

/// Multi-head self-attention with a fused QKV projection.
#[derive(Debug, Clone)]
struct Attention {
    wqkv: Tensor,
    wo: Tensor,
    heads: usize,
}

impl Attention {
    fn new(c: &PrefixLmConfig, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            wqkv: matrix(&vb.pp("wqkv"), 3 * c.d_model, c.d_model, "weight")?,
            wo: matrix(&vb.pp("wo"), c.d_model, c.d_model, "weight")?,
            heads: c.n_heads,
        })
    }
}

/// SwiGLU feed-forward with a fused W1|W3 projection.
#[derive(Debug, Clone)]
struct Ffn {
    w13: Tensor,
    w2: Tensor,
}

impl Ffn {
    fn new(c: &PrefixLmConfig, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            w13: matrix(&vb.pp("w13"), 2 * c.ffn_hidden, c.d_model, "weight")?,
            w2: matrix(&vb.pp("w2"), c.d_model, c.ffn_hidden, "weight")?,
        })
    }
}

/// One pre-norm block: `h += Wo·attn(Wqkv·n1(h)); h += W2·swiglu(W13·n2(h))`.
#[derive(Debug, Clone)]
struct Block {
    n1: RmsNorm,
    attn: Attention,
    n2: RmsNorm,
    ffn: Ffn,
}

impl Block {
    fn new(c: &PrefixLmConfig, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            n1: RmsNorm::new(c.d_model, c.norm_eps, vb.pp("n1"))?,
            attn: Attention::new(c, vb.pp("attn"))?,
            n2: RmsNorm::new(c.d_model, c.norm_eps, vb.pp("n2"))?,
            ffn: Ffn::new(c, vb.pp("ffn"))?,
        })
    }

    /// The block with attention `attend` (full or cached) from the packed QKV rows.
    fn forward(
        &self,
        h: &Tensor,
        attend: impl FnOnce(&Tensor) -> Result<Tensor>,
    ) -> Result<Tensor> {
        let a = attend(&self.n1.linear(h, &self.attn.wqkv)?)?;
        let h = fused::linear_residual(&a, &self.attn.wo, h)?;
        fused::swiglu_linear_residual(&self.n2.linear(&h, &self.ffn.w13)?, &self.ffn.w2, &h)
    }
}

/// The text-prefix autoregressive transformer.
#[derive(Debug, Clone)]
pub struct PrefixLm {
    config: PrefixLmConfig,
    tok_emb: Tensor,
    proj_w: Tensor,
    proj_b: Tensor,
    blocks: Vec<Block>,
    norm: RmsNorm,
    head: Tensor,
    rope: Arc<Rope>,
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
            norm: RmsNorm::new(d, config.norm_eps, vb.pp("norm"))?,
            head: matrix(&vb.pp("head"), v, d, "weight")?,
            rope: Arc::new(Rope::new(
                config.head_dim(),
                config.rope_base,
                config.max_positions,
            )),
            config: config.clone(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &PrefixLmConfig {
        &self.config
    }

    /// Text embeddings projected to the model width.
    fn project_text(&self, text: &Tensor) -> Result<Tensor> {
        text.matmul(&self.proj_w.t()?)?.broadcast_add(&self.proj_b)
    }

    /// Logits of every motion slot, `batch · motion_slots × V` (sample-major).
    pub fn forward(&self, batch: &LmBatch) -> Result<Tensor> {
        let motion = self.tok_emb.embedding(&batch.inputs)?;
        let mut h = if batch.layout.prefix_slots == 0 {
            motion
        } else {
            Tensor::cat(&[&motion, &self.project_text(&batch.text)?], 0)?
        };
        for block in &self.blocks {
            h = block.forward(&h, |qkv| {
                fused::prefix_attention(qkv, &batch.layout, &self.rope, block.attn.heads)
            })?;
        }
        let motion_rows = batch.layout.batch * batch.layout.motion_slots;
        self.norm.linear(&h.narrow(0, 0, motion_rows)?, &self.head)
    }

    /// Mean cross-entropy over the targets of `batch`.
    pub fn loss(&self, batch: &LmBatch) -> Result<Tensor> {
        fused::cross_entropy(&self.forward(batch)?, &batch.targets)
    }

    /// An empty key/value cache for sequences laid out by `layout`.
    pub fn new_cache(&self, layout: &SeqLayout) -> Vec<LayerCache> {
        let (heads, hd) = (self.config.n_heads, self.config.head_dim());
        (0..self.config.n_layers)
            .map(|_| LayerCache::new(layout, heads, hd))
            .collect()
    }

    /// Run slots `from..to` of every sequence through the model against `cache` (filled
    /// below `from`) and return the logits of each sequence's last new slot (`batch × V`).
    /// `text` (`batch · prefix_slots × E`) is needed while `from < prefix_slots`;
    /// `tokens` holds the motion inputs of the new motion slots, sample-major.
    pub fn forward_cached(
        &self,
        cache: &mut [LayerCache],
        layout: &SeqLayout,
        text: Option<&Tensor>,
        tokens: &Tensor,
        (from, to): (usize, usize),
    ) -> Result<Tensor> {
        let (b, p, d) = (layout.batch, layout.prefix_slots, self.config.d_model);
        if to > layout.slots() || layout.max_position() >= self.rope.max_positions() {
            candle_core::bail!("slots {from}..{to} do not fit the layout or the rotary table")
        }
        let new_text = p.saturating_sub(from).min(to - from);
        let motion = self.tok_emb.embedding(tokens)?.reshape((b, (), d))?;
        let mut h = if new_text > 0 {
            let Some(text) = text else {
                candle_core::bail!("prefix slots need the text embeddings")
            };
            let text = self
                .project_text(text)?
                .reshape((b, p, d))?
                .narrow(1, from, new_text)?;
            Tensor::cat(&[&text, &motion], 1)?
        } else {
            motion
        };
        h = h.reshape((b * (to - from), d))?;
        for (block, layer) in self.blocks.iter().zip(cache.iter_mut()) {
            h = block.forward(&h, |qkv| {
                let values = qkv.flatten_all()?.to_vec1::<f32>()?;
                let heads = block.attn.heads;
                let out = fused::cached_attention(
                    &values,
                    layer,
                    layout,
                    &self.rope,
                    heads,
                    d,
                    (from, to),
                );
                Tensor::from_vec(out, (qkv.dim(0)?, d), qkv.device())
            })?;
        }
        let last = h.reshape((b, to - from, d))?.narrow(1, to - from - 1, 1)?;
        self.norm.linear(&last.reshape((b, d))?, &self.head)
    }
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

    fn tiny() -> PrefixLmConfig {
        PrefixLmConfig::new(32, 2, 4, 20, 6)
    }

    fn text(n: usize, e: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64(seed);
        (0..n * e).map(|_| rng.range(-1.0, 1.0) as f32).collect()
    }

    fn logits(model: &PrefixLm, texts: &[&[f32]], motions: &[(&[u32], bool)]) -> Vec<Vec<f32>> {
        let batch = LmBatch::new(model.config(), texts, motions, &Device::Cpu).unwrap();
        model.forward(&batch).unwrap().to_vec2::<f32>().unwrap()
    }

    fn row_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
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
                    row_diff(&base[s], &other[s]),
                    0.0,
                    "token {k} moved slot {s}"
                );
            }
            for s in k + 1..base.len() {
                assert!(
                    row_diff(&base[s], &other[s]) > 1e-6,
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
                    row_diff(&base[s], &other[s]) > 1e-6,
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
        let both = logits(&model, &[&t0, &t1], &[(&m0, true), (&m1, false)]);
        let alone0 = logits(&model, &[&t0], &[(&m0, true)]);
        let alone1 = logits(&model, &[&t1], &[(&m1, false)]);
        let slots = 5;
        for s in 0..alone0.len() {
            assert!(row_diff(&both[s], &alone0[s]) < 1e-5);
        }
        for s in 0..alone1.len() {
            assert!(row_diff(&both[slots + s], &alone1[s]) < 1e-5);
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
        let text_rows = Tensor::from_vec(text_rows, (8, 6), &Device::Cpu).unwrap();
        let mut cache = model.new_cache(&layout);
        let p = layout.prefix_slots;
        let mut worst = 0f32;
        for t in 0..layout.motion_slots {
            let input: Vec<u32> = (0..2)
                .map(|b| if t == 0 { c.bos() } else { tokens[b][t - 1] })
                .collect();
            let input = Tensor::new(input.as_slice(), &Device::Cpu).unwrap();
            let (from, to) = if t == 0 {
                (0, p + 1)
            } else {
                (p + t, p + t + 1)
            };
            let step = model
                .forward_cached(&mut cache, &layout, Some(&text_rows), &input, (from, to))
                .unwrap()
                .to_vec2::<f32>()
                .unwrap();
            for b in 0..2 {
                worst = worst.max(row_diff(&step[b], &full[b * layout.motion_slots + t]));
            }
        }
        assert!(worst <= 1e-4, "cached vs full: {worst}");
    }
}
