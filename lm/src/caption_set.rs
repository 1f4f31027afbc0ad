//! Motions for the captions of a corpus split: one caption of every clip animated by a
//! trained prefix LM, written as a HumanML3D-layout folder that the evaluator's `score` (and
//! T2M-style tools) read:
//!
//! ```text
//! OUT/new_joint_vecs/<id>.npy   n × 263 de-normalised features
//! OUT/new_joints/<id>.npy       n × 22 × 3 joints recovered from them (metres, Y up)
//! OUT/texts/<id>.txt            the caption (caption#word/POS…#0.0#0.0)
//! OUT/<split>.txt               the ids
//! OUT/generated.jsonl           id, source_motion_id, caption, sample: how each was made
//! OUT/rejects.jsonl             captions whose generation produced no motion token
//! OUT/generate.json             model, tokenizer, sampling, counts
//! ```
//!
//! Ids are `<source clip>_g<sample>`. `mm_texts` clips (drawn by the seed) get `mm_samples`
//! samples each for multimodality; every other clip gets one.

use crate::generate::{generate, Sampling};
use crate::run_config::RunConfig;
use crate::MotionLm;
use ingest::corpus::reader::Corpus;
use ingest::corpus::split::SplitAssignment;
use ingest::export::hml3d::{caption_line, GeneratedEntry};
use ingest::npy::write_f32;
use motionscale_core::rng::SplitMix64;
use motionscale_core::write_atomic;
use nn::ModelError;
use serde::Serialize;
use std::path::{Path, PathBuf};
use text::{CaptionEmbeddings, TextEncoder};
use tokenizer::model::MotionTokenizer;

/// The split assignment of the `{train,val,test}.txt` lists in `dir` (the clips' own splits
/// without one).
pub fn split_assignment(dir: Option<&Path>) -> Result<SplitAssignment, ModelError> {
    SplitAssignment::from_dir(dir)
        .map_err(|e| ModelError::invalid(dir.unwrap_or(Path::new(".")), e))
}

/// Which captions to animate and how.
#[derive(Debug, Clone)]
pub struct CaptionSetOptions {
    /// Corpus whose captions (and caption embeddings) are used.
    pub corpus: PathBuf,
    /// Split whose clips are animated.
    pub split: String,
    /// Folder of `{train,val,test}.txt` lists deciding the split instead of the corpus's.
    pub splits: Option<PathBuf>,
    /// Clips that get `mm_samples` samples.
    pub mm_texts: usize,
    /// Samples for each of those.
    pub mm_samples: usize,
    /// Sequences generated together.
    pub batch: usize,
    /// Sampling settings (the seed also draws captions and multimodality clips).
    pub sampling: Sampling,
}

/// What [`generate_caption_set`] wrote (`OUT/generate.json`).
#[derive(Debug, Clone, Serialize)]
pub struct CaptionSetReport {
    /// Clips whose captions were animated.
    pub clips: usize,
    /// Clips with several samples.
    pub mm_texts: usize,
    /// Motions written.
    pub motions: usize,
    /// Sequences that ended before any motion token.
    pub rejected: usize,
    /// Motion tokens generated.
    pub motion_tokens: usize,
    /// Wall time.
    pub seconds: f64,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> ModelError + '_ {
    move |e| ModelError::io(path, e)
}

/// One caption (drawn by the seed) of every captioned clip of the split `options` selects,
/// and the motions to generate: one per clip, `mm_samples` for `mm_texts` clips (drawn too).
/// Returns the clip count, the multimodality clip count and the motions.
fn pick_jobs(
    corpus: &Corpus,
    options: &CaptionSetOptions,
) -> Result<(usize, usize, Vec<GeneratedEntry>), ModelError> {
    let corpus_dir = &options.corpus;
    let captions = text::embed::clip_captions(corpus_dir)?;
    let mut rng = SplitMix64::stream(options.sampling.seed, 0);
    let splits = split_assignment(options.splits.as_deref())?;
    let clips: Vec<(String, String)> = corpus
        .clips()
        .iter()
        .filter(|c| splits.split_of(&c.motion_id, &c.split) == Some(options.split.as_str()))
        .filter_map(|c| {
            let list = captions.get(&c.motion_id).filter(|l| !l.is_empty())?;
            Some((c.motion_id.clone(), list[rng.index(list.len())].clone()))
        })
        .collect();
    if clips.is_empty() {
        return Err(ModelError::corpus(
            corpus_dir,
            format!("no captioned clips in split {:?}", options.split),
        ));
    }
    let mut multi: Vec<usize> = (0..clips.len()).collect();
    rng.shuffle(&mut multi);
    multi.truncate(options.mm_texts);
    let mut jobs = Vec::new();
    for (i, (motion_id, caption)) in clips.iter().enumerate() {
        let samples = if multi.contains(&i) {
            options.mm_samples.max(1)
        } else {
            1
        };
        for sample in 0..samples {
            jobs.push(GeneratedEntry {
                id: format!("{motion_id}_g{sample}"),
                source_motion_id: motion_id.clone(),
                caption: caption.clone(),
                sample,
            });
        }
    }
    Ok((clips.len(), multi.len(), jobs))
}

/// Write one generated motion `id` into `out`: its features, the joints recovered from them
/// and its caption, in the HumanML3D layout.
fn write_generated(
    out: &Path,
    id: &str,
    caption: &str,
    features: &[f32],
) -> Result<(), ModelError> {
    let frames = features.len() / ingest::hml263::FEATURE_DIM;
    let joints = ingest::hml263::recover_joints_f32(features);
    let path = |sub: &str, ext: &str| out.join(sub).join(format!("{id}.{ext}"));
    let vecs = path("new_joint_vecs", "npy");
    write_f32(&vecs, &[frames, 263], features).map_err(io(&vecs))?;
    let joints_path = path("new_joints", "npy");
    write_f32(&joints_path, &[frames, 22, 3], &joints).map_err(io(&joints_path))?;
    let text_path = path("texts", "txt");
    write_atomic(&text_path, caption_line(caption).as_bytes()).map_err(io(&text_path))
}

/// Animate the captions `options` selects with `lm` (decoded by `tokenizer`) into `out`.
/// Caption embeddings come from the corpus, else from `encoder`. `progress(done, total)`.
/// An LM with a model per caption (ES-MoE) generates one sequence at a time.
pub fn generate_caption_set(
    lm: &dyn MotionLm,
    run: &RunConfig,
    tokenizer: &MotionTokenizer,
    encoder: Option<&dyn TextEncoder>,
    options: &CaptionSetOptions,
    out: &Path,
    mut progress: impl FnMut(usize, usize),
) -> Result<CaptionSetReport, ModelError> {
    let started = std::time::Instant::now();
    let corpus_dir = &options.corpus;
    let corpus = Corpus::open(corpus_dir).map_err(|e| ModelError::corpus(corpus_dir, e))?;
    let (clips, mm_texts, jobs) = pick_jobs(&corpus, options)?;
    let stored = CaptionEmbeddings::open(corpus_dir, &run.text_encoder).ok();
    for sub in ["new_joint_vecs", "new_joints", "texts"] {
        std::fs::create_dir_all(out.join(sub)).map_err(io(&out.join(sub)))?;
    }
    let (mut written, mut rejects, mut tokens_total) = (Vec::new(), String::new(), 0usize);
    let batch = if lm.per_caption() {
        1
    } else {
        options.batch.max(1)
    };
    for (b, chunk) in jobs.chunks(batch).enumerate() {
        let mut prefixes = Vec::with_capacity(chunk.len());
        for job in chunk {
            let caption = &job.caption;
            let stored_text = match &stored {
                Some(s) => s.get(caption)?,
                None => None,
            };
            let text = match (stored_text, encoder) {
                (Some(t), _) => t,
                (None, Some(e)) => e.encode(&[caption.as_str()])?.remove(0),
                (None, None) => {
                    return Err(ModelError::corpus(
                        corpus_dir,
                        format!(
                            "caption {caption:?} is not embedded and no text encoder was given"
                        ),
                    ))
                }
            };
            let rows = text.len().min(run.train.hyper.max_text_tokens);
            prefixes.push(text.embeddings[..rows * text.dim].to_vec());
        }
        let views: Vec<&[f32]> = prefixes.iter().map(Vec::as_slice).collect();
        let chunk_sampling = Sampling {
            seed: SplitMix64::stream(options.sampling.seed, 1 + b as u64).next_u64(),
            ..options.sampling.clone()
        };
        let sequences = lm
            .for_caption(views[0])
            .and_then(|model| generate(&model, &views, &chunk_sampling))
            .map_err(ModelError::Candle)?;
        for (e, tokens) in chunk.iter().zip(sequences) {
            if tokens.is_empty() {
                let reject = serde_json::json!({"id": e.id, "caption": e.caption,
                    "reason": "the model ended the sequence before any motion token"});
                rejects.push_str(&format!("{reject}\n"));
                continue;
            }
            tokens_total += tokens.len();
            let features = tokenizer
                .detokenize(&tokens)
                .map_err(|e| ModelError::MotionTokenizer(e.into()))?;
            write_generated(out, &e.id, &e.caption, &features)?;
            written.push(e.clone());
        }
        progress(((b + 1) * batch).min(jobs.len()), jobs.len());
    }
    let ids: String = written.iter().map(|e| format!("{}\n", e.id)).collect();
    let split_file = out.join(format!("{}.txt", options.split));
    write_atomic(&split_file, ids.as_bytes()).map_err(io(&split_file))?;
    let lines: String = written
        .iter()
        .map(|e| serde_json::to_string(e).map(|l| l + "\n"))
        .collect::<Result<_, _>>()
        .map_err(|e| ModelError::invalid(out, e))?;
    let sidecar = out.join("generated.jsonl");
    write_atomic(&sidecar, lines.as_bytes()).map_err(io(&sidecar))?;
    let rejects_path = out.join("rejects.jsonl");
    write_atomic(&rejects_path, rejects.as_bytes()).map_err(io(&rejects_path))?;
    let report = CaptionSetReport {
        clips,
        mm_texts,
        motions: written.len(),
        rejected: jobs.len() - written.len(),
        motion_tokens: tokens_total,
        seconds: started.elapsed().as_secs_f64(),
    };
    let summary = serde_json::json!({
        "tokenizer": run.tokenizer,
        "text_encoder": run.text_encoder,
        "captions_from": corpus_dir,
        "split": options.split,
        "splits": options.splits,
        "mm_samples": options.mm_samples,
        "sampling": options.sampling,
        "report": report,
    });
    let summary_path = out.join("generate.json");
    let text = serde_json::to_string_pretty(&summary).map_err(|e| ModelError::invalid(out, e))?;
    write_atomic(&summary_path, text.as_bytes()).map_err(io(&summary_path))?;
    Ok(report)
}
