//! `motionscale generate --captions-from C`: one caption of every clip of a split animated
//! by a trained model, written as a HumanML3D-layout folder that `motionscale eval` (and
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
//! Ids are `<source clip>_g<sample>`. `--mm-texts` clips (drawn by the seed) get
//! `--mm-samples` samples each for multimodality; every other clip gets one.

use crate::lm::{run_tokenizer, GenerateArgs};
use anyhow::{Context, Result};
use ingest::corpus::reader::Corpus;
use ingest::export::hml3d::caption_line;
use ingest::npy::{write_atomic, write_f32};
use ingest::rng::SplitMix64;
use model::generate::Sampling;
use model::motion_eval::GeneratedEntry;
use model::train::RunConfig;
use model::{CaptionEmbeddings, PrefixLm, TextEncoder};
use std::process::ExitCode;

/// `motionscale generate --captions-from`.
pub fn generate_batch(
    args: &GenerateArgs,
    model: &PrefixLm,
    run: &RunConfig,
    encoder: &dyn TextEncoder,
    sampling: Sampling,
) -> Result<ExitCode> {
    let corpus_dir = args.captions_from.as_ref().expect("batch mode");
    let corpus = Corpus::open(corpus_dir).map_err(anyhow::Error::msg)?;
    let captions = model::embed::clip_captions(corpus_dir)?;
    let mut rng = SplitMix64::stream(sampling.seed, 0);
    let lists = args
        .splits
        .as_deref()
        .map(ingest::corpus::split::read_split_lists)
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let split_of = |id: &str, own: &str| match &lists {
        Some(l) => l.get(id).is_some_and(|s| *s == args.split),
        None => own == args.split,
    };
    let clips: Vec<(String, String)> = corpus
        .clips()
        .iter()
        .filter(|c| split_of(&c.motion_id, &c.split))
        .filter_map(|c| {
            let list = captions.get(&c.motion_id).filter(|l| !l.is_empty())?;
            Some((c.motion_id.clone(), list[rng.index(list.len())].clone()))
        })
        .collect();
    anyhow::ensure!(
        !clips.is_empty(),
        "{}: no captioned clips in split {:?}",
        corpus_dir.display(),
        args.split
    );
    let mut multi: Vec<usize> = (0..clips.len()).collect();
    for i in (1..multi.len()).rev() {
        multi.swap(i, rng.index(i + 1));
    }
    multi.truncate(args.mm_texts);
    let mut jobs = Vec::new();
    for (i, (motion_id, caption)) in clips.iter().enumerate() {
        let samples = if multi.contains(&i) {
            args.mm_samples.max(1)
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
    let stored = CaptionEmbeddings::open(corpus_dir, &run.text_encoder).ok();
    let tokenizer = run_tokenizer(run, args.tokenizer.as_deref())?;
    let out = &args.out;
    for sub in ["new_joint_vecs", "new_joints", "texts"] {
        std::fs::create_dir_all(out.join(sub))
            .with_context(|| format!("creating {}", out.join(sub).display()))?;
    }
    let bar = crate::commands::progress_bar("generate", "motions");
    bar.set_length(jobs.len() as u64);
    let started = std::time::Instant::now();
    let (mut written, mut rejects, mut tokens_total) = (Vec::new(), String::new(), 0usize);
    for (b, chunk) in jobs.chunks(args.batch.max(1)).enumerate() {
        let mut prefixes = Vec::with_capacity(chunk.len());
        for job in chunk {
            let caption = &job.caption;
            let text = match stored
                .as_ref()
                .map(|s| s.get(caption))
                .transpose()?
                .flatten()
            {
                Some(t) => t,
                None => encoder.encode(&[caption.as_str()])?.remove(0),
            };
            let rows = text.len().min(run.train.max_text_tokens);
            prefixes.push(text.embeddings[..rows * text.dim].to_vec());
        }
        let views: Vec<&[f32]> = prefixes.iter().map(Vec::as_slice).collect();
        let chunk_sampling = Sampling {
            seed: SplitMix64::stream(sampling.seed, 1 + b as u64).next_u64(),
            ..sampling.clone()
        };
        let sequences = model::generate::generate(model, &views, &chunk_sampling)?;
        for (e, tokens) in chunk.iter().zip(sequences) {
            if tokens.is_empty() {
                let reject = serde_json::json!({"id": e.id, "caption": e.caption,
                    "reason": "the model ended the sequence before any motion token"});
                rejects.push_str(&format!("{reject}\n"));
                continue;
            }
            tokens_total += tokens.len();
            let features = tokenizer.detokenize(&tokens)?;
            let frames = features.len() / ingest::hml263::FEATURE_DIM;
            let joints: Vec<f32> = ingest::hml263::recover_joints(&features)
                .iter()
                .flatten()
                .flatten()
                .map(|&v| v as f32)
                .collect();
            let path = |sub: &str, ext: &str| out.join(sub).join(format!("{}.{ext}", e.id));
            write_f32(&path("new_joint_vecs", "npy"), &[frames, 263], &features)?;
            write_f32(&path("new_joints", "npy"), &[frames, 22, 3], &joints)?;
            write_atomic(&path("texts", "txt"), caption_line(&e.caption).as_bytes())?;
            written.push(e.clone());
        }
        bar.inc(chunk.len() as u64);
    }
    bar.finish_and_clear();
    let ids: String = written.iter().map(|e| format!("{}\n", e.id)).collect();
    write_atomic(&out.join(format!("{}.txt", args.split)), ids.as_bytes())?;
    let lines: String = written
        .iter()
        .map(|e| serde_json::to_string(e).map(|l| l + "\n"))
        .collect::<Result<_, _>>()?;
    write_atomic(&out.join("generated.jsonl"), lines.as_bytes())?;
    write_atomic(&out.join("rejects.jsonl"), rejects.as_bytes())?;
    let summary = serde_json::json!({
        "model": args.model,
        "tokenizer": run.tokenizer,
        "text_encoder": run.text_encoder,
        "captions_from": corpus_dir,
        "split": args.split,
        "clips": clips.len(),
        "mm_texts": multi.len(),
        "mm_samples": args.mm_samples,
        "motions": written.len(),
        "rejected": jobs.len() - written.len(),
        "motion_tokens": tokens_total,
        "sampling": sampling,
    });
    write_atomic(
        &out.join("generate.json"),
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "{} motions from {} captions ({} rejected: no motion token) in {seconds:.1} s, {:.0} tokens/s → {}",
        written.len(),
        clips.len(),
        jobs.len() - written.len(),
        tokens_total as f64 / seconds,
        out.display()
    );
    Ok(if written.len() == jobs.len() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(2)
    })
}
