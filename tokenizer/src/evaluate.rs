//! Tokenizer metrics on whole clips of a corpus split (ScaMo Fig. 6): reconstruction L1 on
//! normalised features, MPJPE on joints recovered from de-normalised features (root-aligned
//! as MoMask's `calculate_mpjpe` does it, and global), codebook utilisation beside the
//! coverage a uniform tokenizer would reach with as many tokens, entropy and perplexity of
//! code usage.
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
    /// Mean per-joint position error in millimetres on global joints (22 joints, every frame;
    /// the root trajectory integrated over the clip, so drift dominates on long clips).
    pub mpjpe_mm: f64,
    /// Mean per-joint position error in millimetres on root-aligned joints (the pelvis
    /// subtracted per frame from both), comparable with T2M-GPT / MoMask's reconstruction MPJPE.
    #[serde(default)]
    pub mpjpe_root_mm: f64,
    /// Fraction of codes used at least once.
    pub utilization: f64,
    /// Tokens per code, N/K.
    #[serde(default)]
    pub tokens_per_code: f64,
    /// Fraction of codes a perfectly uniform tokenizer would use with N tokens, 1 − e^(−N/K):
    /// the ceiling `utilization` is read against on a small split.
    #[serde(default)]
    pub uniform_coverage: f64,
    /// Codes used at least once.
    pub used_codes: usize,
    /// Entropy of code usage in nats.
    pub entropy: f64,
    /// exp(entropy): the exponential entropy (perplexity) of code usage.
    pub perplexity: f64,
    /// Device the tokenizer ran on (`cpu`, `cuda:N`); empty in older reports.
    #[serde(default)]
    pub device: String,
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

/// Tokenize every clip of `corpus` with the checkpoint in `tokenizer_dir` (loaded onto
/// `device`) and write the token set to `out` (manifest last); `on_clip` sees (done, total).
pub fn write_token_set(
    tokenizer_dir: &Path,
    corpus: &Corpus,
    out: &Path,
    device: &Device,
    on_clip: impl FnMut(usize, usize),
) -> Result<TokenManifest, TokenizerError> {
    let tokenizer = MotionTokenizer::load(tokenizer_dir, device)?;
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

fn corpus_error(corpus: &Corpus, message: impl std::fmt::Display) -> TokenizerError {
    TokenizerError::File {
        path: corpus.dir().to_path_buf(),
        message: message.to_string(),
    }
}

/// Per-joint position errors between two motions, in metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointError {
    /// Mean error on global joints.
    pub global: f64,
    /// Mean error after subtracting each motion's root (pelvis, joint 0) per frame.
    pub root_aligned: f64,
    /// Frames compared.
    pub frames: usize,
}

/// Mean per-joint position error between the joints recovered from two feature sequences of
/// equal length: on global joints, and root-aligned as MoMask's `calculate_mpjpe` computes
/// it (pelvis subtracted per frame from each motion, Euclidean norm per joint, mean over
/// joints and frames).
pub fn mpjpe(reference: &[f32], reconstruction: &[f32]) -> JointError {
    let (a, b) = (recover_joints(reference), recover_joints(reconstruction));
    let frames = a.len().min(b.len());
    let (mut global, mut aligned) = (0f64, 0f64);
    for (pa, pb) in a.iter().zip(&b) {
        let (ra, rb) = (pa[0], pb[0]);
        for (ja, jb) in pa.iter().zip(pb) {
            global += distance(ja, jb, [0.0; 3], [0.0; 3]);
            aligned += distance(ja, jb, ra, rb);
        }
    }
    let points = (frames * a.first().map_or(0, |p| p.len())).max(1) as f64;
    JointError {
        global: global / points,
        root_aligned: aligned / points,
        frames,
    }
}

/// |(a − ra) − (b − rb)|.
fn distance(a: &[f64; 3], b: &[f64; 3], ra: [f64; 3], rb: [f64; 3]) -> f64 {
    (0..3)
        .map(|k| ((a[k] - ra[k]) - (b[k] - rb[k])).powi(2))
        .sum::<f64>()
        .sqrt()
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
    let (mut l1_sum, mut values, mut frames) = (0f64, 0u64, 0u64);
    let (mut global_sum, mut aligned_sum) = (0f64, 0f64);
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
        let error = mpjpe(original, &decoded);
        global_sum += error.global * error.frames as f64;
        aligned_sum += error.root_aligned * error.frames as f64;
        frames += error.frames as u64;
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
        mpjpe_mm: global_sum / frames as f64 * 1000.0,
        mpjpe_root_mm: aligned_sum / frames as f64 * 1000.0,
        utilization: usage.utilisation(),
        tokens_per_code: usage.total() as f64 / config.codebook_size() as f64,
        uniform_coverage: 1.0 - (-(usage.total() as f64) / config.codebook_size() as f64).exp(),
        used_codes: usage.counts().iter().filter(|&&c| c > 0).count(),
        entropy: usage.entropy(),
        perplexity: usage.perplexity(),
        device: nn::device::device_name(tokenizer.device()),
    })
}
