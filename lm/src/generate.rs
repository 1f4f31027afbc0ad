//! Sampling motion tokens from a prefix LM: autoregressive decoding from BOS until EOS or a
//! length limit, with temperature, top-k and top-p (nucleus) sampling, seeded per sequence.
//! With the key/value cache each new token costs one position; without it every step
//! recomputes the whole sequence (the reference for the cache, and its benchmark).
//!
//! On the CPU executor a cached batch decodes in groups, one per thread, each group running
//! whole steps of every layer on its own sequences: the threads meet once per call instead of
//! at each of the step's twenty-odd small kernels. The grouping changes no value: the
//! decoding cache's products and the attention compute each row alone ([`nn::panels`]).

use crate::prefix_lm::{Executor, LmBatch, PrefixLm};
use candle_core::{Result, Tensor};
use motionscale_core::rng::SplitMix64;
use nn::seq_layout::SeqLayout;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How to sample.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sampling {
    /// Softmax temperature; 0 takes the most likely token.
    pub temperature: f64,
    /// Keep only the k most likely tokens.
    pub top_k: Option<usize>,
    /// Keep the smallest set of most likely tokens whose probability reaches p.
    pub top_p: Option<f64>,
    /// Seed (sequence b draws from a generator seeded by this and b).
    pub seed: u64,
    /// Most motion tokens per sequence.
    pub max_tokens: usize,
    /// Whether EOS may be sampled (otherwise every sequence runs to `max_tokens`).
    pub allow_eos: bool,
    /// Motion tokens every sequence has before EOS may be sampled.
    #[serde(default)]
    pub min_tokens: usize,
    /// Decode with the key/value cache.
    pub kv_cache: bool,
}

impl Default for Sampling {
    /// Temperature 1, top-k 50 (no top-p), seed 0, 64 tokens, EOS allowed, cached.
    fn default() -> Self {
        Self {
            temperature: 1.0,
            top_k: Some(50),
            top_p: None,
            seed: 0,
            max_tokens: 64,
            allow_eos: true,
            min_tokens: 0,
            kv_cache: true,
        }
    }
}

/// Draw one token from `logits` (one row) among `candidates` ids.
pub fn sample(logits: &[f32], candidates: usize, s: &Sampling, rng: &mut SplitMix64) -> usize {
    let mut ranked: Vec<(usize, f64)> =
        (0..candidates).map(|i| (i, f64::from(logits[i]))).collect();
    let order = |a: &(usize, f64), b: &(usize, f64)| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0));
    let keep = if s.temperature <= 0.0 {
        1
    } else {
        s.top_k.unwrap_or(candidates).clamp(1, candidates)
    };
    // Only the `keep` best need ordering.
    if keep < ranked.len() {
        ranked.select_nth_unstable_by(keep - 1, order);
        ranked.truncate(keep);
    }
    ranked.sort_by(order);
    if s.temperature <= 0.0 {
        return ranked[0].0;
    }
    let max = ranked[0].1;
    let mut probs: Vec<f64> = ranked
        .iter()
        .map(|(_, l)| ((l - max) / s.temperature).exp())
        .collect();
    let total: f64 = probs.iter().sum();
    probs.iter_mut().for_each(|p| *p /= total);
    if let Some(top_p) = s.top_p {
        let mut acc = 0.0;
        let keep = probs
            .iter()
            .position(|p| {
                acc += p;
                acc >= top_p
            })
            .map_or(probs.len(), |i| i + 1);
        probs.truncate(keep);
    }
    let mut u = rng.unit() * probs.iter().sum::<f64>();
    for (i, p) in probs.iter().enumerate() {
        if u < *p {
            return ranked[i].0;
        }
        u -= p;
    }
    ranked[probs.len() - 1].0
}

/// Sequences a decoding group holds at least: each group streams every weight at each step,
/// so smaller groups would trade the threads' meetings for memory traffic.
pub const MIN_GROUP: usize = 8;

/// Motion tokens (without BOS/EOS) for each text prefix (`text_dim`-wide rows).
pub fn generate(model: &PrefixLm, texts: &[&[f32]], s: &Sampling) -> Result<Vec<Vec<u32>>> {
    let groups = match model.executor()? {
        Executor::Cpu if s.kv_cache => {
            (texts.len() / MIN_GROUP).clamp(1, rayon::current_num_threads())
        }
        _ => 1,
    };
    let size = texts.len().div_ceil(groups).max(1);
    nn::lm_kernels::in_pool(|| {
        let parts = (texts.par_chunks(size).enumerate())
            .map(|(g, texts)| decode(model, texts, s, g * size))
            .collect::<Result<Vec<_>>>()?;
        Ok(parts.into_iter().flatten().collect())
    })
}

/// [`generate`] for sequences `first..` of the batch (`texts`).
fn decode(model: &PrefixLm, texts: &[&[f32]], s: &Sampling, first: usize) -> Result<Vec<Vec<u32>>> {
    let c = model.config();
    let (batch, eos) = (texts.len(), c.eos() as usize);
    // Candidates: the codes, then (BOS masked out) EOS once `min_tokens` are out.
    let candidates = |len: usize| {
        if s.allow_eos && len >= s.min_tokens {
            eos + 1
        } else {
            c.codebook_size
        }
    };
    let bos = c.bos() as usize;
    let mut rngs: Vec<SplitMix64> = (first as u64..(first + batch) as u64)
        .map(|b| SplitMix64(s.seed ^ b.wrapping_mul(0x9E37_79B9_7F4A_7C15)))
        .collect();
    let mut out = vec![Vec::new(); batch];
    let mut done = vec![false; batch];
    let layout = SeqLayout::new(
        texts.iter().map(|t| t.len() / c.text_dim).collect(),
        s.max_tokens + 1,
    );
    let p = layout.prefix_slots;
    let mut text = vec![0f32; batch * p * c.text_dim];
    for (b, t) in texts.iter().enumerate() {
        text[b * p * c.text_dim..][..t.len()].copy_from_slice(t);
    }
    let mut cache = s.kv_cache.then(|| model.new_cache(&layout)).transpose()?;
    let mut inputs = vec![c.bos(); batch];
    for t in 0..s.max_tokens {
        let logits = match cache.as_mut() {
            Some(cache) => {
                let slots = if t == 0 {
                    (0, p + 1)
                } else {
                    (p + t, p + t + 1)
                };
                model.forward_cached(cache, &layout, &text, &inputs, slots)?
            }
            None => {
                // `true`: a slot after the last token, whose logits predict the next one.
                let motions: Vec<(&[u32], bool)> =
                    out.iter().map(|o| (o.as_slice(), true)).collect();
                let full = LmBatch::new(c, texts, &motions);
                let (l, p) = (&full.layout, full.layout.prefix_slots);
                let rows: Vec<u32> = (0..batch)
                    .map(|b| l.row(b, p + out[b].len()).expect("a real slot") as u32)
                    .collect();
                let full = model.forward(&full)?;
                full.index_select(&Tensor::new(rows.as_slice(), full.device())?, 0)?
            }
        };
        let mut logits = logits.to_vec2::<f32>()?;
        // Rows draw from their own generators, so sampling them in parallel changes nothing.
        let drawn: Vec<Option<usize>> = logits
            .par_iter_mut()
            .zip(rngs.par_iter_mut())
            .enumerate()
            .map(|(b, (row, rng))| {
                (!done[b]).then(|| {
                    row[bos] = f32::NEG_INFINITY;
                    sample(row, candidates(out[b].len()), s, rng)
                })
            })
            .collect();
        for (b, token) in drawn.into_iter().enumerate() {
            match token {
                Some(t) if t == eos => done[b] = true,
                Some(t) => {
                    out[b].push(t as u32);
                    inputs[b] = t as u32;
                }
                None => {}
            }
        }
        if done.iter().all(|&d| d) {
            break;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_respects_greedy_top_k_and_top_p() {
        let logits = [0.0f32, 3.0, 1.0, 2.9];
        let mut rng = SplitMix64(1);
        let greedy = Sampling {
            temperature: 0.0,
            ..Sampling::default()
        };
        assert_eq!(sample(&logits, 4, &greedy, &mut rng), 1);
        assert_eq!(sample(&logits, 3, &greedy, &mut rng), 1);
        let top2 = Sampling {
            top_k: Some(2),
            ..Sampling::default()
        };
        for _ in 0..200 {
            assert!(matches!(sample(&logits, 4, &top2, &mut rng), 1 | 3));
        }
        // p(1) ≈ 0.46, p(3) ≈ 0.42: top-p 0.4 keeps token 1 only.
        let nucleus = Sampling {
            top_k: None,
            top_p: Some(0.4),
            ..Sampling::default()
        };
        for _ in 0..50 {
            assert_eq!(sample(&logits, 4, &nucleus, &mut rng), 1);
        }
    }

    /// A tiny seeded model (12 codes, 5-wide text) and random texts of `lens` text slots.
    fn tiny_model_and_texts(lens: &[usize], seed: u64) -> (PrefixLm, Vec<Vec<f32>>) {
        let config = crate::PrefixLmConfig::new(32, 2, 2, 12, 5);
        let (model, _) =
            crate::prefix_lm::init_model(&config, 4, &candle_core::Device::Cpu).unwrap();
        let mut rng = SplitMix64(seed);
        let texts = (lens.iter())
            .map(|&n| (0..n * 5).map(|_| rng.range(-1.0, 1.0) as f32).collect())
            .collect();
        (model, texts)
    }

    #[test]
    fn cached_and_recomputed_decoding_agree() {
        let (model, texts) = tiny_model_and_texts(&[3, 1], 9);
        let texts: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
        let s = Sampling {
            max_tokens: 10,
            seed: 3,
            ..Sampling::default()
        };
        let cached = generate(&model, &texts, &s).unwrap();
        let full = generate(
            &model,
            &texts,
            &Sampling {
                kv_cache: false,
                ..s
            },
        )
        .unwrap();
        assert_eq!(cached, full);
        assert!(cached.iter().all(|t| t.iter().all(|&v| v < 12)));
        let at_least_three = Sampling {
            min_tokens: 3,
            ..s.clone()
        };
        let long = generate(&model, &texts, &at_least_three).unwrap();
        assert!(long.iter().all(|t| t.len() >= 3), "{long:?}");
    }

    /// A batch decoded in groups (three threads) draws the tokens it draws as one group (one
    /// thread), sampling included.
    #[test]
    fn grouped_decoding_draws_the_tokens_of_one_group() {
        let lens: Vec<usize> = (0..2 * MIN_GROUP + 3).map(|b| 1 + b % 4).collect();
        let (model, texts) = tiny_model_and_texts(&lens, 2);
        let texts: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
        let s = Sampling {
            max_tokens: 12,
            seed: 5,
            top_k: None,
            ..Sampling::default()
        };
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| generate(&model, &texts, &s)).unwrap()
        };
        let (one, grouped) = (run(1), run(3));
        assert_eq!(one, grouped);
        assert_eq!(one.len(), texts.len());
        assert!(one.iter().any(|t| t.len() > 1), "{one:?}");
    }
}
