//! A hand-written CPU forward pass of BERT encoders (all-MiniLM-L6-v2 and its kin).
//!
//! candle's `BertModel` pads the batch, runs attention as 4-D tensor ops (a transpose and a
//! copy per head layout, a mask add, softmax) and allocates every intermediate; here the
//! batch's real tokens are packed into one matrix (no padding rows), each layer runs one QKV
//! product over all of them, attention runs per sequence, and bias, residual, LayerNorm and
//! GELU are fused row-wise passes. The row kernels work on fixed blocks of rows and attention
//! on whole sequences, so the result does not depend on the thread count.

use crate::transformer::{CONFIG, WEIGHTS};
use candle_core::Tensor;
use candle_nn::VarBuilder;
use candle_transformers::models::bert::{Config, HiddenAct, PositionEmbeddingType};
use nn::cpu_f32::tensor_f32;
use nn::fast_exp;
use nn::kernels::{dot, gemm, ROW_BLOCK};
use nn::ModelError;
use rayon::prelude::*;
use std::path::Path;

/// A LayerNorm's scale, shift and epsilon.
struct LayerNorm {
    weight: Vec<f32>,
    bias: Vec<f32>,
    eps: f32,
}

impl LayerNorm {
    fn load(vb: VarBuilder, d: usize, eps: f64) -> candle_core::Result<Self> {
        Ok(Self {
            weight: vb.get(d, "weight")?.to_vec1()?,
            bias: vb.get(d, "bias")?.to_vec1()?,
            eps: eps as f32,
        })
    }

    /// Normalise one row in place (mean, then the variance about it: two passes, which
    /// loses nothing to cancellation).
    fn apply(&self, x: &mut [f32]) {
        let n = x.len() as f32;
        let mean = lane_sum(x) / n;
        x.iter_mut().for_each(|v| *v -= mean);
        let r = 1.0 / (dot(x, x) / n + self.eps).sqrt();
        for ((v, w), b) in x.iter_mut().zip(&self.weight).zip(&self.bias) {
            *v = *v * r * w + b;
        }
    }
}

/// Sum of `x` with eight partial sums (vectorises; fixed order).
fn lane_sum(x: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let chunks = x.chunks_exact(8);
    let tail: f32 = chunks.remainder().iter().sum();
    for c in chunks {
        for i in 0..8 {
            acc[i] += c[i];
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// A dense layer `x·W + b`, W stored input-major (in × out) so the gemm reads it row by row.
struct Linear {
    w: Vec<f32>,
    b: Vec<f32>,
}

impl Linear {
    /// The layers under `vbs` (PyTorch's out × in weights), stacked along their outputs.
    fn load(vbs: &[VarBuilder], (inp, out): (usize, usize)) -> candle_core::Result<Self> {
        let ws = vbs
            .iter()
            .map(|vb| vb.get((out, inp), "weight"))
            .collect::<candle_core::Result<Vec<_>>>()?;
        let bs = vbs
            .iter()
            .map(|vb| vb.get(out, "bias"))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self {
            w: tensor_f32(&Tensor::cat(&ws, 0)?.t()?)?,
            b: Tensor::cat(&bs, 0)?.to_vec1()?,
        })
    }

    /// `dst (+)= x·W`.
    fn product(&self, x: &[f32], dst: &mut [f32], accumulate: bool) {
        let (n, k) = (self.b.len(), self.w.len() / self.b.len());
        let mnk = (x.len() / k, n, k);
        gemm(dst, (x, false), (&self.w, false), mnk, accumulate);
    }

    /// `dst = x·W + b`.
    fn forward(&self, x: &[f32], dst: &mut [f32]) {
        let n = self.b.len();
        dst.par_chunks_mut(n * ROW_BLOCK)
            .for_each(|block| block.chunks_mut(n).for_each(|r| r.copy_from_slice(&self.b)));
        self.product(x, dst, true);
    }
}

/// `x ← LayerNorm((y + b) + x)` row by row: a sublayer's bias, its residual and its norm.
fn add_norm(x: &mut [f32], y: &[f32], b: &[f32], norm: &LayerNorm) {
    let d = b.len();
    x.par_chunks_mut(d * ROW_BLOCK)
        .zip(y.par_chunks(d * ROW_BLOCK))
        .for_each(|(xb, yb)| {
            for (xr, yr) in xb.chunks_mut(d).zip(yb.chunks(d)) {
                for ((x, y), b) in xr.iter_mut().zip(yr).zip(b) {
                    *x += y + b;
                }
                norm.apply(xr);
            }
        });
}

/// `h ← GELU(h + b)` row by row, GELU the exact (erf) one.
fn bias_gelu(h: &mut [f32], b: &[f32]) {
    h.par_chunks_mut(b.len() * ROW_BLOCK)
        .for_each(|block| bias_gelu_block(block, b));
}

nn::vectorised!(
    /// [`bias_gelu`] of one block of rows at the CPU's widest vectors.
    fn bias_gelu_block / bias_gelu_block_at(h: &mut [f32], b: &[f32]) = bias_gelu_body;
);

#[inline(always)]
fn bias_gelu_body(h: &mut [f32], b: &[f32]) {
    for row in h.chunks_mut(b.len()) {
        for (v, b) in row.iter_mut().zip(b) {
            let x = *v + b;
            *v = (erf(x * std::f32::consts::FRAC_1_SQRT_2) + 1.0) * 0.5 * x;
        }
    }
}

/// erf by Eigen's rational approximation on [−4, 4] (within 5e-7; erf is ±1 in f32
/// beyond): plain arithmetic, so the GELU loop vectorises where libm's `erff` is a call per
/// value.
#[inline(always)]
fn erf(x: f32) -> f32 {
    let x = x.clamp(-4.0, 4.0);
    let x2 = x * x;
    let mut p = -2.726_142_3e-10;
    for c in [
        2.770_681_4e-8,
        -2.101_024e-6,
        -5.692_506_4e-5,
        -7.349_906_3e-4,
        -2.954_600_2e-3,
        -1.609_603_3e-2,
    ] {
        p = p * x2 + c;
    }
    let mut q = -1.456_607_2e-5;
    for c in [-2.133_740_6e-4, -1.682_827e-3, -7.373_329e-3, -1.426_474e-2] {
        q = q * x2 + c;
    }
    x * p / q
}

/// Softmax of `p` in place (each loop on its own, so each vectorises).
#[inline(always)]
fn softmax(p: &mut [f32]) {
    let max = p.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    p.iter_mut().for_each(|v| *v = fast_exp::exp(*v - max));
    let inv = 1.0 / lane_sum(p);
    p.iter_mut().for_each(|v| *v *= inv);
}

nn::vectorised!(
    /// Multi-head self-attention of one sequence over its own tokens: `qkv` holds its rows
    /// `[q | k | v]` (each `3d` wide, heads contiguous), `ctx` gets the heads' outputs side
    /// by side (`d` wide).
    fn attend / attend_at(qkv: &[f32], ctx: &mut [f32], dims: (usize, usize), p: &mut Vec<f32>)
        = attend_body;
);

/// [`attend`]: each score a dot product of two contiguous head rows (independent, so they
/// overlap), each output row a sum of value rows.
#[inline(always)]
fn attend_body(qkv: &[f32], ctx: &mut [f32], (d, heads): (usize, usize), p: &mut Vec<f32>) {
    let (n, hd) = (ctx.len() / d, d / heads);
    let scale = 1.0 / (hd as f32).sqrt();
    p.resize(n, 0.0);
    let at = |row: usize, part: usize, h: usize| &qkv[row * 3 * d + part * d + h * hd..][..hd];
    for h in 0..heads {
        for i in 0..n {
            let q = at(i, 0, h);
            for (j, s) in p.iter_mut().enumerate() {
                *s = dot(q, at(j, 1, h)) * scale;
            }
            softmax(p);
            let o = &mut ctx[i * d + h * hd..][..hd];
            o.fill(0.0);
            for (j, &w) in p.iter().enumerate() {
                o.iter_mut().zip(at(j, 2, h)).for_each(|(o, v)| *o += w * v);
            }
        }
    }
}

/// [`attend`] for every sequence of the packed rows (`lens` tokens each), in parallel.
fn attention(qkv: &[f32], ctx: &mut [f32], lens: &[usize], (d, heads): (usize, usize)) {
    let mut items = Vec::with_capacity(lens.len());
    let (mut qkv, mut ctx) = (qkv, ctx);
    for &n in lens {
        let (q, q_rest) = qkv.split_at(n * 3 * d);
        let (c, c_rest) = std::mem::take(&mut ctx).split_at_mut(n * d);
        items.push((q, c));
        (qkv, ctx) = (q_rest, c_rest);
    }
    items
        .into_par_iter()
        .for_each_init(Vec::new, |p, (q, c)| attend(q, c, (d, heads), p));
}

/// Token, position and token-type (always type 0) embeddings and their LayerNorm.
struct Embeddings {
    word: Vec<f32>,
    position: Vec<f32>,
    token_type: Vec<f32>,
    norm: LayerNorm,
}

impl Embeddings {
    fn load(vb: VarBuilder, c: &Config) -> candle_core::Result<Self> {
        let d = c.hidden_size;
        let table = |rows, name| vb.pp(name).get((rows, d), "weight");
        Ok(Self {
            word: tensor_f32(&table(c.vocab_size, "word_embeddings")?)?,
            position: tensor_f32(&table(c.max_position_embeddings, "position_embeddings")?)?,
            token_type: table(c.type_vocab_size, "token_type_embeddings")?
                .get(0)?
                .to_vec1()?,
            norm: LayerNorm::load(vb.pp("LayerNorm"), d, c.layer_norm_eps)?,
        })
    }

    /// The normalised embeddings of the packed tokens, `(id, position)` each.
    fn forward(&self, tokens: &[(usize, usize)]) -> Vec<f32> {
        let d = self.token_type.len();
        let mut x = vec![0f32; tokens.len() * d];
        x.par_chunks_mut(d * ROW_BLOCK)
            .zip(tokens.par_chunks(ROW_BLOCK))
            .for_each(|(xb, tb)| {
                for (xr, &(id, pos)) in xb.chunks_mut(d).zip(tb) {
                    let (word, position) = (&self.word[id * d..][..d], &self.position[pos * d..]);
                    for (((x, w), t), p) in
                        xr.iter_mut().zip(word).zip(&self.token_type).zip(position)
                    {
                        *x = (w + t) + p;
                    }
                    self.norm.apply(xr);
                }
            });
        x
    }
}

/// One encoder layer.
struct Layer {
    qkv: Linear,
    attn_out: Linear,
    attn_norm: LayerNorm,
    up: Linear,
    down: Linear,
    out_norm: LayerNorm,
}

impl Layer {
    fn load(vb: VarBuilder, c: &Config) -> candle_core::Result<Self> {
        let (d, f, eps) = (c.hidden_size, c.intermediate_size, c.layer_norm_eps);
        let (attn, own) = (vb.pp("attention"), vb.pp("attention.self"));
        let qkv = ["query", "key", "value"].map(|name| own.pp(name));
        Ok(Self {
            qkv: Linear::load(&qkv, (d, d))?,
            attn_out: Linear::load(&[attn.pp("output.dense")], (d, d))?,
            attn_norm: LayerNorm::load(attn.pp("output.LayerNorm"), d, eps)?,
            up: Linear::load(&[vb.pp("intermediate.dense")], (d, f))?,
            down: Linear::load(&[vb.pp("output.dense")], (f, d))?,
            out_norm: LayerNorm::load(vb.pp("output.LayerNorm"), d, eps)?,
        })
    }

    /// Update the packed hidden states `x` (sequences of `lens` tokens) in place.
    fn forward(&self, x: &mut [f32], lens: &[usize], heads: usize, s: &mut Scratch) {
        let d = self.attn_out.b.len();
        self.qkv.forward(x, &mut s.qkv);
        attention(&s.qkv, &mut s.ctx, lens, (d, heads));
        self.attn_out.product(&s.ctx, &mut s.proj, false);
        add_norm(x, &s.proj, &self.attn_out.b, &self.attn_norm);
        self.up.product(x, &mut s.up, false);
        bias_gelu(&mut s.up, &self.up.b);
        self.down.product(&s.up, &mut s.proj, false);
        add_norm(x, &s.proj, &self.down.b, &self.out_norm);
    }
}

/// The intermediate activations of a layer, allocated once per batch.
struct Scratch {
    qkv: Vec<f32>,
    ctx: Vec<f32>,
    proj: Vec<f32>,
    up: Vec<f32>,
}

/// A BERT encoder on the CPU: the last hidden state of every token of a batch of sequences.
pub struct BertCpu {
    embeddings: Embeddings,
    layers: Vec<Layer>,
    heads: usize,
    intermediate: usize,
}

impl BertCpu {
    /// The encoder of `config` with the weights under `vb` (at its root or under
    /// `config.model_type`, as candle's `BertModel` looks), read from the folder `dir`,
    /// which errors name. Only exact (erf) GELU is computed; other activations are refused.
    pub fn load(vb: VarBuilder, config: &Config, dir: &Path) -> Result<Self, ModelError> {
        let unsupported = |what: String| ModelError::invalid(&dir.join(CONFIG), what);
        if config.hidden_act != HiddenAct::Gelu {
            return Err(unsupported(format!(
                "hidden_act {:?}: the CPU forward computes exact (erf) GELU only",
                config.hidden_act
            )));
        }
        // candle's config knows absolute positions only (others fail to parse), which is
        // what `Embeddings` adds.
        let PositionEmbeddingType::Absolute = config.position_embedding_type;
        let vb = match &config.model_type {
            Some(prefix) if !vb.contains_tensor("embeddings.word_embeddings.weight") => {
                vb.pp(prefix)
            }
            _ => vb,
        };
        let heads = config.num_attention_heads;
        let load = || -> candle_core::Result<Self> {
            Ok(Self {
                embeddings: Embeddings::load(vb.pp("embeddings"), config)?,
                layers: (0..config.num_hidden_layers)
                    .map(|i| Layer::load(vb.pp(format!("encoder.layer.{i}")), config))
                    .collect::<candle_core::Result<_>>()?,
                heads,
                intermediate: config.intermediate_size,
            })
        };
        let model = load().map_err(|e| ModelError::invalid(&dir.join(WEIGHTS), e))?;
        if heads == 0 || config.hidden_size % heads != 0 {
            return Err(unsupported(format!(
                "hidden_size {} is not a multiple of num_attention_heads {heads}",
                config.hidden_size
            )));
        }
        Ok(model)
    }

    /// Hidden width.
    pub fn dim(&self) -> usize {
        self.embeddings.token_type.len()
    }

    /// The last hidden states of `sequences` (token ids, each attending to itself only),
    /// packed: `Σ len × dim` values, the first sequence's rows first.
    pub fn forward(&self, sequences: &[&[u32]]) -> Result<Vec<f32>, ModelError> {
        let tokens = self.pack(sequences)?;
        let lens: Vec<usize> = sequences.iter().map(|s| s.len()).collect();
        let (rows, d) = (tokens.len(), self.dim());
        let mut x = self.embeddings.forward(&tokens);
        let mut scratch = Scratch {
            qkv: vec![0.0; rows * 3 * d],
            ctx: vec![0.0; rows * d],
            proj: vec![0.0; rows * d],
            up: vec![0.0; rows * self.intermediate],
        };
        for layer in &self.layers {
            layer.forward(&mut x, &lens, self.heads, &mut scratch);
        }
        Ok(x)
    }

    /// The `(id, position)` of every token of `sequences`, checked against the tables.
    fn pack(&self, sequences: &[&[u32]]) -> Result<Vec<(usize, usize)>, ModelError> {
        let d = self.dim();
        let (vocab, positions) = (
            self.embeddings.word.len() / d,
            self.embeddings.position.len() / d,
        );
        let mut tokens = Vec::with_capacity(sequences.iter().map(|s| s.len()).sum());
        for seq in sequences {
            if seq.len() > positions {
                return Err(ModelError::encoder(
                    "BERT (cpu)",
                    format!(
                        "{} tokens, more than the model's {positions} positions",
                        seq.len()
                    ),
                ));
            }
            for (pos, &id) in seq.iter().enumerate() {
                if id as usize >= vocab {
                    return Err(ModelError::encoder(
                        "BERT (cpu)",
                        format!("token id {id} outside the vocabulary of {vocab}"),
                    ));
                }
                tokens.push((id as usize, pos));
            }
        }
        Ok(tokens)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarMap;
    use candle_transformers::models::bert::BertModel;
    use motionscale_core::rng::SplitMix64;
    use nn::gradcheck::max_abs_diff;

    /// The GELU block and the attention give the same bits at every vector level.
    #[test]
    fn row_kernels_agree_at_every_vector_level() {
        let (d, heads, n) = (32, 4, 11);
        let mut rng = SplitMix64(4);
        let mut draw =
            |len: usize| -> Vec<f32> { (0..len).map(|_| rng.range(-3.0, 3.0) as f32).collect() };
        let (h, b, qkv) = (draw(n * 2 * d), draw(2 * d), draw(n * 3 * d));
        nn::simd::assert_levels_agree(|isa| {
            let mut gelu = h.clone();
            bias_gelu_block_at(isa, &mut gelu, &b);
            let (mut ctx, mut scratch) = (vec![0f32; n * d], Vec::new());
            attend_at(isa, &qkv, &mut ctx, (d, heads), &mut scratch);
            nn::simd::bits(&[gelu, ctx].concat())
        });
    }

    fn tiny_config() -> Config {
        Config {
            vocab_size: 100,
            hidden_size: 32,
            num_hidden_layers: 2,
            num_attention_heads: 4,
            intermediate_size: 64,
            max_position_embeddings: 40,
            ..Config::default()
        }
    }

    /// candle's model with seeded random weights (every tensor, norms included) and the
    /// same weights in the map it was built from.
    fn tiny_bert(config: &Config) -> (BertModel, VarMap) {
        let map = VarMap::new();
        let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
        let model = BertModel::load(vb, config).unwrap();
        let mut vars: Vec<_> = map.data().lock().unwrap().clone().into_iter().collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        let mut rng = SplitMix64(3);
        for (name, var) in vars {
            let (lo, hi) = if name.ends_with("LayerNorm.weight") {
                (0.5, 1.5)
            } else {
                (-0.5, 0.5)
            };
            let values: Vec<f32> = (0..var.elem_count())
                .map(|_| rng.range(lo, hi) as f32)
                .collect();
            var.set(&Tensor::from_vec(values, var.shape(), &Device::Cpu).unwrap())
                .unwrap();
        }
        (model, map)
    }

    /// candle's output on the padded batch, cut to the real rows and packed.
    fn candle_packed(model: &BertModel, sequences: &[Vec<u32>]) -> Vec<f32> {
        let longest = sequences.iter().map(Vec::len).max().unwrap();
        let pad = |s: &Vec<u32>, v: fn(&u32) -> u32| {
            let mut row: Vec<u32> = s.iter().map(v).collect();
            row.resize(longest, 0);
            row
        };
        let stack = |v: fn(&u32) -> u32| {
            let flat: Vec<u32> = sequences.iter().flat_map(|s| pad(s, v)).collect();
            Tensor::from_vec(flat, (sequences.len(), longest), &Device::Cpu).unwrap()
        };
        let (ids, mask) = (stack(|&id| id), stack(|_| 1));
        let hidden = model
            .forward(&ids, &ids.zeros_like().unwrap(), Some(&mask))
            .unwrap();
        let hidden: Vec<Vec<Vec<f32>>> = hidden.to_vec3().unwrap();
        sequences
            .iter()
            .zip(hidden)
            .flat_map(|(s, rows)| rows.into_iter().take(s.len()).flatten())
            .collect()
    }

    #[test]
    fn matches_candle_on_a_tiny_random_bert_at_any_thread_count() {
        let config = tiny_config();
        let (reference, map) = tiny_bert(&config);
        let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
        let model = BertCpu::load(vb, &config, Path::new("tiny-bert")).unwrap();
        let mut rng = SplitMix64(11);
        let sequences: Vec<Vec<u32>> = [5, 1, 9, 9, 3, 17, 40]
            .iter()
            .map(|&n| (0..n).map(|_| rng.below(100) as u32).collect())
            .collect();
        let refs: Vec<&[u32]> = sequences.iter().map(Vec::as_slice).collect();
        let on = |threads| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| model.forward(&refs).unwrap())
        };
        let ours = on(2);
        assert_eq!(ours, on(1));
        let diff = max_abs_diff(&ours, &candle_packed(&reference, &sequences));
        eprintln!("tiny BERT: max |fused − candle| = {diff:e}");
        assert!(diff <= 1e-5, "max |Δ| {diff}");
    }

    #[test]
    fn refuses_what_it_does_not_compute() {
        let config = Config {
            hidden_act: HiddenAct::GeluApproximate,
            ..tiny_config()
        };
        let (_, map) = tiny_bert(&config);
        let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
        let err = BertCpu::load(vb, &config, Path::new("tiny-bert"))
            .err()
            .expect("tanh GELU is refused");
        assert!(err.to_string().contains("hidden_act"), "{err}");
        let (_, map) = tiny_bert(&tiny_config());
        let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
        let model = BertCpu::load(vb, &tiny_config(), Path::new("tiny-bert")).unwrap();
        let err = model
            .forward(&[&[3, 100]])
            .expect_err("an id outside the vocabulary");
        assert!(err.to_string().contains("vocabulary"), "{err}");
    }

    #[test]
    fn erf_is_within_5e7() {
        // Its Taylor series in f64 (exact to ~1e-11 for |x| ≤ 4), and ±1 beyond.
        let reference = |x: f64| -> f64 {
            if x.abs() > 4.0 {
                return x.signum();
            }
            let (mut term, mut sum) = (x, x);
            for n in 1..120 {
                term *= -x * x / n as f64;
                sum += term / (2 * n + 1) as f64;
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        };
        let worst = (-6000..=6000)
            .map(|i| {
                let x = i as f32 * 1e-3;
                (f64::from(erf(x)) - reference(f64::from(x))).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < 5e-7, "max |Δ| {worst}");
    }
}
