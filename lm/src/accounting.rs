//! Parameter and FLOP accounting of the prefix LM: the one place every later stage (sweep
//! planner, fits, reports) takes N_nv, N_v, FLOPs per token and budgets from.
//!
//! Conventions:
//! - **Vocabulary** V = motion codes + 3 specials (BOS, EOS, PAD), so V·d counts the special
//!   rows too (they are trained parameters like any other row).
//! - **N_v** = vocabulary parameters. Input embedding and output head are **untied**, so
//!   N_v = 2·V·d (both matrices; ScaMo's N_v = V·d counts one). [`ParamCount::tied`] says so.
//! - **N_nv** = every other trainable parameter: the blocks (attention, SwiGLU FFN, two RMSNorm
//!   weights each), the final RMSNorm and the text projection (weight and bias). The frozen
//!   text encoder is not counted.
//! - **6N FLOPs** per motion token = 6·(N_nv + N_v); budget C = 6·(N_nv + N_v)·D for D motion
//!   tokens (ScaMo Eq. 7).
//! - **Exact FLOPs** count every executed matmul at 2 FLOPs per multiply-add, training = 3 ×
//!   forward (forward + backward of both operands): per sequence of P prefix and M motion
//!   positions, the blocks' projections on all P + M positions, the text projection on P,
//!   the output head (2·V·d) on M, the input-embedding gather 0, and dense attention (QKᵀ and
//!   PV, 2·2·(P+M)²·d per layer, masked entries not skipped). This is
//!   `../shared/bench/pytorch_prefix_lm.py`'s `exact` convention.

use crate::prefix_lm::PrefixLmConfig;
use serde::{Deserialize, Serialize};

/// Trainable parameters of a [`PrefixLmConfig`], by part.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ParamCount {
    /// Non-vocabulary parameters: blocks + final norm + text projection.
    pub n_nv: u64,
    /// Vocabulary parameters: embedding + head (2·V·d, untied).
    pub n_v: u64,
    /// N_nv + N_v.
    pub total: u64,
    /// Whether input embedding and output head share one matrix (never, here).
    pub tied: bool,
    /// All blocks.
    pub blocks: u64,
    /// Text projection (weight + bias).
    pub text_projection: u64,
    /// Final RMSNorm.
    pub final_norm: u64,
    /// Input embedding (V·d).
    pub embedding: u64,
    /// Output head (V·d).
    pub head: u64,
}

/// Closed-form parameter count: per block 4d² (fused QKV + output) + 3·d·f (SwiGLU W1|W3, W2)
/// + 2d (norms); N_nv adds the final norm d and the text projection E·d + d.
pub fn param_count(config: &PrefixLmConfig) -> ParamCount {
    let d = config.d_model as u64;
    let f = config.ffn_hidden as u64;
    let v = config.vocab_size() as u64;
    let blocks = config.n_layers as u64 * (4 * d * d + 3 * d * f + 2 * d);
    let text_projection = config.text_dim as u64 * d + d;
    let final_norm = d;
    let n_nv = blocks + text_projection + final_norm;
    let (embedding, head) = (v * d, v * d);
    let n_v = embedding + head;
    ParamCount {
        n_nv,
        n_v,
        total: n_nv + n_v,
        tied: false,
        blocks,
        text_projection,
        final_norm,
        embedding,
        head,
    }
}

/// Positions of one executed sequence: text prefix and motion (BOS + tokens, padded).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SequenceShape {
    /// Prefix positions.
    pub prefix: usize,
    /// Motion positions (the head runs on these).
    pub motion: usize,
}

impl SequenceShape {
    /// The benchmark layout of `pytorch_prefix_lm.py`: 16 prefix + 64 motion positions.
    pub const BENCH: Self = Self {
        prefix: 16,
        motion: 64,
    };
}

/// Forward FLOPs of one sequence, by part (2 FLOPs per multiply-add).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ForwardFlops {
    /// Block projections (QKV, output, W1|W3, W2) on every position.
    pub blocks: f64,
    /// Dense attention matmuls (QKᵀ, PV).
    pub attention: f64,
    /// Text projection on the prefix positions.
    pub text_projection: f64,
    /// Output head on the motion positions.
    pub head: f64,
    /// Sum of the parts.
    pub total: f64,
}

/// Forward FLOPs of one sequence of shape `seq`.
pub fn forward_flops(config: &PrefixLmConfig, seq: SequenceShape) -> ForwardFlops {
    let d = config.d_model as f64;
    let f = config.ffn_hidden as f64;
    let layers = config.n_layers as f64;
    let positions = (seq.prefix + seq.motion) as f64;
    let blocks = 2.0 * positions * layers * (4.0 * d * d + 3.0 * d * f);
    let attention = layers * 2.0 * 2.0 * positions * positions * d;
    let text_projection = 2.0 * seq.prefix as f64 * config.text_dim as f64 * d;
    let head = 2.0 * seq.motion as f64 * config.vocab_size() as f64 * d;
    ForwardFlops {
        blocks,
        attention,
        text_projection,
        head,
        total: blocks + attention + text_projection + head,
    }
}

/// Exact training FLOPs (forward + backward = 3 × forward) of one sequence.
pub fn train_flops_exact(config: &PrefixLmConfig, seq: SequenceShape) -> f64 {
    3.0 * forward_flops(config, seq).total
}

/// Exact training FLOPs per motion token for sequences of shape `seq`.
pub fn flops_exact_per_token(config: &PrefixLmConfig, seq: SequenceShape) -> f64 {
    train_flops_exact(config, seq) / seq.motion.max(1) as f64
}

/// 6N training FLOPs per motion token: 6·(N_nv + N_v).
pub fn flops_6n_per_token(config: &PrefixLmConfig) -> f64 {
    6.0 * param_count(config).total as f64
}

/// Compute budget C = 6·(N_nv + N_v)·D of training on `tokens` motion tokens.
pub fn budget(config: &PrefixLmConfig, tokens: f64) -> f64 {
    flops_6n_per_token(config) * tokens
}

/// Motion tokens D = C / (6·(N_nv + N_v)) that spend the budget `flops`.
pub fn tokens_for_budget(config: &PrefixLmConfig, flops: f64) -> f64 {
    flops / flops_6n_per_token(config)
}

/// Everything [`param_count`] and the FLOP functions say about a configuration, for reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Accounting {
    /// Parameter counts.
    pub params: ParamCount,
    /// Vocabulary incl. the 3 specials.
    pub vocab_size: usize,
    /// Sequence shape of the exact count.
    pub sequence: SequenceShape,
    /// 6·(N_nv + N_v) per motion token.
    pub flops_6n_per_token: f64,
    /// Exact training FLOPs per motion token.
    pub flops_exact_per_token: f64,
    /// Exact forward FLOPs per sequence, by part.
    pub forward_per_sequence: ForwardFlops,
}

impl Accounting {
    /// The accounting of `config` with exact FLOPs for sequences of shape `seq`.
    pub fn of(config: &PrefixLmConfig, seq: SequenceShape) -> Self {
        Self {
            params: param_count(config),
            vocab_size: config.vocab_size(),
            sequence: seq,
            flops_6n_per_token: flops_6n_per_token(config),
            flops_exact_per_token: flops_exact_per_token(config, seq),
            forward_per_sequence: forward_flops(config, seq),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prefix_lm::{PrefixLm, PRESETS};
    use candle_core::{DType, Device, Shape, Tensor};
    use candle_nn::var_builder::SimpleBackend;
    use candle_nn::{Init, VarBuilder};
    use std::sync::{Arc, Mutex};

    /// A backend that records every requested parameter and hands out zero-stride views, so
    /// even the 3B preset builds without allocating its weights.
    #[derive(Default, Clone)]
    struct Shapes(Arc<Mutex<Vec<(String, Shape)>>>);

    impl SimpleBackend for Shapes {
        fn get(
            &self,
            s: Shape,
            name: &str,
            _: Init,
            dtype: DType,
            dev: &Device,
        ) -> candle_core::Result<Tensor> {
            self.0.lock().unwrap().push((name.to_string(), s.clone()));
            Tensor::zeros((), dtype, dev)?.broadcast_as(s)
        }

        fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
            candle_core::bail!("{name}: shape needed")
        }

        fn contains_tensor(&self, _: &str) -> bool {
            true
        }
    }

    /// Parameters the model asks its VarBuilder for: total count and names.
    fn built_params(config: &PrefixLmConfig) -> (u64, Vec<String>) {
        let shapes = Shapes::default();
        let vb = VarBuilder::from_backend(Box::new(shapes.clone()), DType::F32, Device::Cpu);
        PrefixLm::new(config, vb).unwrap();
        let recorded = shapes.0.lock().unwrap();
        let total = recorded.iter().map(|(_, s)| s.elem_count() as u64).sum();
        (total, recorded.iter().map(|(n, _)| n.clone()).collect())
    }

    #[test]
    fn every_preset_has_the_closed_form_parameter_count() {
        for preset in &PRESETS {
            for codebook in [1 << 10, 1 << 16] {
                let config = PrefixLmConfig::preset(preset.name, codebook, 384).unwrap();
                let (built, names) = built_params(&config);
                let counted = param_count(&config);
                assert_eq!(built, counted.total, "{}", preset.name);
                assert_eq!(
                    counted.n_v,
                    2 * (codebook as u64 + 3) * config.d_model as u64
                );
                assert_eq!(counted.n_nv + counted.n_v, counted.total);
                assert!(names.contains(&"blocks.0.attn.wqkv.weight".to_string()));
            }
        }
        // 44M at K = 1024: 8·(4·512² + 3·512·1365 + 2·512) + 512 + 384·512 + 512 blocks etc.
        let c = PrefixLmConfig::preset("44M", 1024, 384).unwrap();
        let p = param_count(&c);
        assert_eq!(p.blocks, 8 * (4 * 512 * 512 + 3 * 512 * 1365 + 2 * 512));
        assert_eq!(p.n_nv, p.blocks + 512 + 384 * 512 + 512);
        assert_eq!(p.n_v, 2 * 1027 * 512);
    }

    #[test]
    fn flops_match_the_reference_conventions() {
        // pytorch_prefix_lm.py, d 256, 4 layers, B 32: exact = 3·(2·linear MACs + attention).
        let c = PrefixLmConfig::new(256, 4, 4, 1024, 384);
        let seq = SequenceShape::BENCH;
        let linear_macs = 80 * 4 * (3 * 256 * 256 + 256 * 256 + 2 * 256 * 683 + 683 * 256)
            + 16 * 384 * 256
            + 64 * 256 * 1027;
        let attention = 4 * 2 * (2 * 80 * 80 * 256);
        let exact = 3.0 * (2.0 * linear_macs as f64 + attention as f64);
        assert_eq!(train_flops_exact(&c, seq), exact);
        assert_eq!(flops_exact_per_token(&c, seq), exact / 64.0);
        let n = param_count(&c).total as f64;
        assert_eq!(flops_6n_per_token(&c), 6.0 * n);
        assert_eq!(budget(&c, 1e6), 6.0 * n * 1e6);
        assert!((tokens_for_budget(&c, budget(&c, 1e6)) - 1e6).abs() < 1e-6);
    }
}
