//! Training data of the prefix LM: a token set's clips joined with the frozen text
//! embeddings of their corpus captions, served as seeded batches.
//!
//! The training stream is every train clip once per epoch in a seeded order (a fresh
//! permutation per epoch), each occurrence with one of the clip's captions drawn by the same
//! seed; batch k is stream items `k·B .. (k+1)·B`. The stream is a pure function of the
//! seed, so a run resumes from its step count alone. Evaluation takes every clip of a split
//! in motion-id order with its first caption.

use crate::prefix_lm::{LmBatch, PrefixLmConfig};
use nn::ModelError;
use text::embed::{clip_captions, CaptionEmbeddings};

use ingest::corpus::split::SplitAssignment;
use ingest::corpus::{Corpus, Origin};
use motionscale_core::rng::SplitMix64;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use tokenizer::{TokenManifest, TokenSet, UnigramCounts};

/// One clip: caption indices into [`LmData::text`], its motion tokens, and whether they
/// reach the clip's end (an EOS target) or were cut at the length limit.
#[derive(Debug, Clone, PartialEq)]
pub struct Example {
    /// The clip's id.
    pub motion_id: String,
    /// Indices of the clip's captions (may be empty: no text prefix).
    pub captions: Vec<usize>,
    /// Motion tokens, at most the configured maximum.
    pub tokens: Vec<u32>,
    /// Whether the clip ends here (EOS is a target).
    pub ends: bool,
    /// Captured or synthetic motion (test losses are also reported per origin).
    pub origin: Origin,
}

impl Example {
    /// Loss positions: the tokens, plus EOS when the clip ends.
    pub fn targets(&self) -> u64 {
        self.tokens.len() as u64 + u64::from(self.ends)
    }
}

/// Length limits applied while loading.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Text tokens kept per caption (the first ones).
    pub text_tokens: usize,
    /// Motion tokens kept per clip (the first ones; longer clips lose their EOS).
    pub motion_tokens: usize,
}

/// A token set with its captions' text embeddings, in memory.
#[derive(Debug, Clone)]
pub struct LmData {
    /// The token set's manifest.
    pub tokens: TokenManifest,
    /// Unigram counts of the token set.
    pub unigram: UnigramCounts,
    /// Text encoder id of the embeddings.
    pub encoder: String,
    /// Width of the text embeddings.
    pub text_dim: usize,
    /// Distinct captions' token embeddings (rows of `text_dim`).
    pub text: Vec<Vec<f32>>,
    /// Clips by split, in motion-id order.
    pub splits: BTreeMap<String, Vec<Example>>,
}

/// The origin of every clip of the corpus in `corpus_dir`, by motion id.
fn clip_origins(corpus_dir: &Path) -> Result<HashMap<String, Origin>, ModelError> {
    let invalid = |e: ingest::IngestError| ModelError::invalid(corpus_dir, e);
    let corpus = Corpus::open(corpus_dir).map_err(invalid)?;
    Ok(corpus
        .clip_metadata()
        .map_err(invalid)?
        .into_iter()
        .map(|m| (m.motion_id, Origin::of(&m.source)))
        .collect())
}

/// A 64-bit value mixing `a` and `b` (for per-epoch and per-item generators).
fn mix(a: u64, b: u64) -> u64 {
    SplitMix64(a ^ b.wrapping_mul(0x9E37_79B9_7F4A_7C15)).next_u64()
}

impl LmData {
    /// Load the token set in `tokens_dir` and the embeddings of encoder `encoder` (or the
    /// corpus's only one) for the captions of its clips in `corpus_dir`, each clip in the
    /// split `splits` assigns it (clips in none are left out).
    pub fn load(
        tokens_dir: &Path,
        corpus_dir: &Path,
        encoder: Option<&str>,
        limits: Limits,
        splits: &SplitAssignment,
    ) -> Result<Self, ModelError> {
        let set = TokenSet::open(tokens_dir).map_err(|e| ModelError::invalid(tokens_dir, e))?;
        let encoder = text::resolve_encoder(corpus_dir, encoder)?;
        let embeddings = CaptionEmbeddings::open(corpus_dir, &encoder)?;
        let captions = clip_captions(corpus_dir)?;
        let origins = clip_origins(corpus_dir)?;
        let wanted = set
            .clips
            .iter()
            .filter_map(|clip| captions.get(&clip.motion_id))
            .flatten()
            .map(String::as_str);
        let mut stored = embeddings.get_many(wanted)?;
        let mut index: HashMap<String, usize> = HashMap::new();
        let mut text = Vec::new();
        let mut by_split: BTreeMap<String, Vec<Example>> = BTreeMap::new();
        for clip in &set.clips {
            let Some(split) = splits.split_of(&clip.motion_id, &clip.split) else {
                continue;
            };
            let clip_captions = captions.get(&clip.motion_id).ok_or_else(|| {
                ModelError::corpus(
                    corpus_dir,
                    format!(
                        "clip {} of the token set is not in the corpus",
                        clip.motion_id
                    ),
                )
            })?;
            let origin = *origins.get(&clip.motion_id).ok_or_else(|| {
                ModelError::corpus(
                    corpus_dir,
                    format!("clip {} has captions but no metadata row", clip.motion_id),
                )
            })?;
            let mut ids = Vec::with_capacity(clip_captions.len());
            for caption in clip_captions {
                if let Some(&i) = index.get(caption) {
                    ids.push(i);
                    continue;
                }
                let emb = stored.remove(caption).ok_or_else(|| {
                    ModelError::corpus(
                        corpus_dir,
                        format!("caption {caption:?} has no {encoder} embedding; rerun embed-text"),
                    )
                })?;
                let rows = emb.len().min(limits.text_tokens);
                text.push(emb.embeddings[..rows * emb.dim].to_vec());
                index.insert(caption.clone(), text.len() - 1);
                ids.push(text.len() - 1);
            }
            let keep = clip.tokens.len().min(limits.motion_tokens);
            by_split
                .entry(split.to_string())
                .or_default()
                .push(Example {
                    motion_id: clip.motion_id.clone(),
                    captions: ids,
                    tokens: clip.tokens[..keep].to_vec(),
                    ends: keep == clip.tokens.len(),
                    origin,
                });
        }
        Ok(Self {
            tokens: set.manifest,
            unigram: set.unigram,
            encoder,
            text_dim: embeddings.dim(),
            text,
            splits: by_split,
        })
    }

    /// Motion codes K of the token set.
    pub fn codebook_size(&self) -> usize {
        self.tokens.tokenizer.codebook_size
    }

    /// The clips of `split` (empty when absent).
    pub fn split(&self, split: &str) -> &[Example] {
        self.splits.get(split).map_or(&[], Vec::as_slice)
    }

    /// The order of the train clips in epoch `epoch` (a seeded Fisher–Yates permutation).
    fn epoch_order(&self, epoch: u64, seed: u64) -> Vec<usize> {
        let n = self.split("train").len();
        let mut order: Vec<usize> = (0..n).collect();
        let mut rng = SplitMix64(mix(seed, epoch));
        for i in 0..n.saturating_sub(1) {
            order.swap(i, i + rng.index(n - i));
        }
        order
    }

    /// The train clip at `offset` of epoch `epoch` with its caption for that occurrence.
    fn stream_item(
        &self,
        order: &[usize],
        epoch: u64,
        offset: usize,
        seed: u64,
    ) -> (&Example, Option<usize>) {
        let example = &self.split("train")[order[offset]];
        let caption = (!example.captions.is_empty()).then(|| {
            let mut rng = SplitMix64(mix(mix(seed, epoch), offset as u64));
            example.captions[rng.index(example.captions.len())]
        });
        (example, caption)
    }

    /// Examples of training step `step`: stream items `step·batch .. (step+1)·batch`.
    pub fn train_items(
        &self,
        step: u64,
        batch: usize,
        seed: u64,
    ) -> Vec<(&Example, Option<usize>)> {
        let n = self.split("train").len() as u64;
        let mut order: Option<(u64, Vec<usize>)> = None;
        (step * batch as u64..(step + 1) * batch as u64)
            .map(|item| {
                let epoch = item / n;
                if order.as_ref().is_none_or(|(e, _)| *e != epoch) {
                    order = Some((epoch, self.epoch_order(epoch, seed)));
                }
                let (_, o) = order.as_ref().expect("set above");
                self.stream_item(o, epoch, (item % n) as usize, seed)
            })
            .collect()
    }

    /// Training steps (whole batches of `batch`) needed to see at least `tokens` loss
    /// positions, or `None` when the train split has no loss position.
    pub fn steps_for_tokens(&self, tokens: u64, batch: usize, seed: u64) -> Option<u64> {
        let train = self.split("train");
        if batch == 0 || train.iter().all(|e| e.targets() == 0) {
            return None;
        }
        let (mut seen, mut items) = (0u64, 0u64);
        for epoch in 0.. {
            for &i in &self.epoch_order(epoch, seed) {
                if seen >= tokens && items % batch as u64 == 0 {
                    return Some(items / batch as u64);
                }
                seen += train[i].targets();
                items += 1;
            }
        }
        unreachable!("the epochs never end")
    }

    /// The caption embeddings of an item (empty without a caption).
    pub fn text_of(&self, item: &(&Example, Option<usize>)) -> &[f32] {
        item.1.map_or(&[][..], |c| self.text[c].as_slice())
    }

    /// A model batch of `items`.
    pub fn batch(&self, config: &PrefixLmConfig, items: &[(&Example, Option<usize>)]) -> LmBatch {
        let texts: Vec<&[f32]> = items.iter().map(|item| self.text_of(item)).collect();
        let motions: Vec<(&[u32], bool)> = items
            .iter()
            .map(|(e, _)| (e.tokens.as_slice(), e.ends))
            .collect();
        LmBatch::new(config, &texts, &motions)
    }

    /// Evaluation items of `split`: every clip in order with its first caption.
    pub fn eval_items(&self, split: &str) -> Vec<(&Example, Option<usize>)> {
        self.split(split)
            .iter()
            .map(|e| (e, e.captions.first().copied()))
            .collect()
    }
}
