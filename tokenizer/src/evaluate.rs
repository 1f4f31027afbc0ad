//! Tokenizer metrics on whole clips of a corpus split (ScaMo Fig. 6): reconstruction L1 on
//! normalised features, MPJPE on joints recovered from de-normalised features, codebook
//! utilisation, entropy and perplexity of code usage.
//!
//! Every clip goes through the same path as `tokenize` → `tokenizer decode`: features cropped
//! to a whole number of tokens → token ids → decoded features, so the MPJPE reported here is
//! the MPJPE of a tokenize/decode round trip.

use crate::error::TokenizerError;
use crate::model::{MotionTokenizer, FEATURES};
use crate::tokens::{TokenClip, TokenManifest, TokenSet, TokenizerInfo};
use crate::usage::CodeUsage;
use candle_core::Device;
use ingest::corpus::Corpus;
use ingest::hml263::recover_joints;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The metrics of one tokenizer on one split.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Tokenizer folder.
    pub tokenizer: PathBuf,
    /// Its content id.
    pub tokenizer_id: String,
    /// `fsq` or `vq`.
    pub quantizer: String,
    /// Requested codebook size.
    pub nominal_codebook: usize,
    /// Real number of codes.
    pub codebook_size: usize,
    /// Corpus folder.
    pub corpus: PathBuf,
    /// Split evaluated.
    pub split: String,
    /// Clips evaluated.
    pub clips: usize,
    /// Clips shorter than one token, skipped.
    pub skipped_clips: usize,
    /// Frames evaluated (each clip cropped to a multiple of 4).
    pub frames: u64,
    /// Tokens produced.
    pub tokens: u64,
    /// Mean |reconstruction − input| over normalised features.
    pub recon_l1: f64,
    /// Mean per-joint position error in millimetres (22 joints, every frame).
    pub mpjpe_mm: f64,
    /// Fraction of codes used at least once.
    pub utilization: f64,
    /// Codes used at least once.
    pub used_codes: usize,
    /// Entropy of code usage in nats.
    pub entropy: f64,
    /// exp(entropy): the exponential entropy (perplexity) of code usage.
    pub perplexity: f64,
}

/// Token ids of every clip of `corpus` in `splits` (all splits when empty), in corpus order.
pub fn tokenize_corpus(
    tokenizer: &MotionTokenizer,
    corpus: &Corpus,
    splits: &[&str],
    mut on_clip: impl FnMut(usize, usize),
) -> Result<Vec<TokenClip>, TokenizerError> {
    let clips = corpus.clips();
    let keep = |i: usize| splits.is_empty() || splits.contains(&clips[i].split.as_str());
    let total = (0..clips.len()).filter(|&i| keep(i)).count();
    let features = corpus
        .features_where(keep)
        .map_err(|message| corpus_error(corpus, message))?;
    let mut out = Vec::with_capacity(total);
    for (done, (index, feats)) in features.into_iter().enumerate() {
        out.push(TokenClip {
            motion_id: clips[index].motion_id.clone(),
            split: clips[index].split.clone(),
            tokens: tokenizer.tokenize(&feats)?,
        });
        on_clip(done + 1, total);
    }
    Ok(out)
}

/// Tokenize every clip of `corpus` with the checkpoint in `tokenizer_dir` (on the CPU) and
/// write the token set to `out` (manifest last); `on_clip` sees (done, total).
pub fn write_token_set(
    tokenizer_dir: &Path,
    corpus: &Corpus,
    out: &Path,
    on_clip: impl FnMut(usize, usize),
) -> Result<TokenManifest, TokenizerError> {
    let tokenizer = MotionTokenizer::load(tokenizer_dir, &Device::Cpu)?;
    let clips = tokenize_corpus(&tokenizer, corpus, &[], on_clip)?;
    let config = tokenizer.config();
    let info = TokenizerInfo {
        dir: tokenizer_dir.to_path_buf(),
        id: MotionTokenizer::content_id(tokenizer_dir)?,
        quantizer: config.quantizer_name().into(),
        codebook_size: config.codebook_size(),
        nominal_codebook: config.nominal_codebook,
        downsample: tokenizer.downsample(),
    };
    TokenSet::write(out, info, corpus.dir(), clips)
}

fn corpus_error(corpus: &Corpus, message: String) -> TokenizerError {
    TokenizerError::File {
        path: corpus.dir().to_path_buf(),
        message,
    }
}

/// Mean per-joint position error (metres) between the joints recovered from two feature
/// sequences of equal length, and the number of frames compared.
pub fn mpjpe(reference: &[f32], reconstruction: &[f32]) -> (f64, usize) {
    let (a, b) = (recover_joints(reference), recover_joints(reconstruction));
    let frames = a.len().min(b.len());
    let mut total = 0f64;
    for (pa, pb) in a.iter().zip(&b) {
        for (ja, jb) in pa.iter().zip(pb) {
            total += ja
                .iter()
                .zip(jb)
                .map(|(x, y)| (x - y).powi(2))
                .sum::<f64>()
                .sqrt();
        }
    }
    let joints = a.first().map_or(0, |p| p.len());
    (total / (frames * joints).max(1) as f64, frames)
}

/// Evaluate `tokenizer` (loaded from `dir`) on every clip of `split`.
pub fn evaluate(
    tokenizer: &MotionTokenizer,
    dir: PathBuf,
    corpus: &Corpus,
    split: &str,
    mut on_clip: impl FnMut(usize, usize),
) -> Result<EvalReport, TokenizerError> {
    let tokenizer_id = MotionTokenizer::content_id(&dir)?;
    let config = tokenizer.config();
    let clips = corpus.clips();
    let keep = |i: usize| clips[i].split == split;
    let total = (0..clips.len()).filter(|&i| keep(i)).count();
    let features = corpus
        .features_where(keep)
        .map_err(|message| corpus_error(corpus, message))?;
    let mut usage = CodeUsage::new(config.codebook_size());
    let (mut l1_sum, mut values, mut mpjpe_sum, mut frames) = (0f64, 0u64, 0f64, 0u64);
    let mut skipped = 0;
    let std = tokenizer.std();
    for (done, (_, original)) in features.into_iter().enumerate() {
        on_clip(done + 1, total);
        let tokens = tokenizer.tokenize(&original)?;
        if tokens.is_empty() {
            skipped += 1;
            continue;
        }
        usage.add(tokens.iter().copied())?;
        let decoded = tokenizer.detokenize(&tokens)?;
        let original = &original[..decoded.len()];
        for (i, (a, b)) in original.iter().zip(&decoded).enumerate() {
            l1_sum += ((a - b) / std[i % FEATURES]).abs() as f64;
        }
        values += decoded.len() as u64;
        let (error, n) = mpjpe(original, &decoded);
        mpjpe_sum += error * n as f64;
        frames += n as u64;
    }
    if frames == 0 {
        return Err(corpus_error(
            corpus,
            format!("no clip of split {split:?} is long enough to tokenize"),
        ));
    }
    Ok(EvalReport {
        tokenizer: dir,
        tokenizer_id,
        quantizer: config.quantizer_name().into(),
        nominal_codebook: config.nominal_codebook,
        codebook_size: config.codebook_size(),
        corpus: corpus.dir().to_path_buf(),
        split: split.into(),
        clips: total - skipped,
        skipped_clips: skipped,
        frames,
        tokens: usage.total(),
        recon_l1: l1_sum / values as f64,
        mpjpe_mm: mpjpe_sum / frames as f64 * 1000.0,
        utilization: usage.utilisation(),
        used_codes: usage.counts().iter().filter(|&&c| c > 0).count(),
        entropy: usage.entropy(),
        perplexity: usage.perplexity(),
    })
}
