//! `motionscale evaluator train` and `motionscale eval`: the text–motion evaluator trained on
//! the user's corpus, and generation metrics computed with it.

use crate::commands::progress_bar;
use crate::device_args::DeviceArgs;
use anyhow::{Context, Result};
use evaluator::model::TrainedEvaluator;
use evaluator::score::{
    corpus_split, embed_set, evaluate_motions, hml3d_folder, EvalOptions, EvalReport, MotionSet,
};
use evaluator::train::{corpus_clips, train_evaluator, EvaluatorEvent, EvaluatorTrainConfig};
use std::path::PathBuf;
use std::process::ExitCode;
use text::{BertEncoder, TextEncoder};

/// Arguments of `motionscale evaluator train`.
#[derive(clap::Args, Debug)]
pub struct EvaluatorTrainArgs {
    /// Corpus folder (with caption embeddings: `motionscale embed-text`).
    #[arg(long)]
    pub corpus: PathBuf,
    /// Text encoder id of the caption embeddings (default: the corpus's only one).
    #[arg(long = "text-emb")]
    pub text_emb: Option<String>,
    /// Output folder; re-running the same command resumes.
    #[arg(long)]
    pub out: PathBuf,
    /// GRU and convolution width.
    #[arg(long, default_value_t = 256)]
    pub hidden: usize,
    /// Width of the shared text–motion space.
    #[arg(long, default_value_t = 256)]
    pub embed_dim: usize,
    /// Longest training window in frames (HumanML3D's 196).
    #[arg(long, default_value_t = 196)]
    pub max_frames: usize,
    /// Longest caption in tokens.
    #[arg(long, default_value_t = 32)]
    pub max_text_tokens: usize,
    /// Contrastive softmax temperature.
    #[arg(long, default_value_t = 0.07)]
    pub temperature: f64,
    /// Weight of the emotion and action classifier losses.
    #[arg(long, default_value_t = 1.0)]
    pub classifier_weight: f64,
    /// Clips per batch (in-batch negatives).
    #[arg(long, default_value_t = 64)]
    pub batch: usize,
    /// Optimiser steps.
    #[arg(long, default_value_t = 3000)]
    pub steps: u64,
    /// Peak learning rate (AdamW, 5% warm-up, cosine to 10%).
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Steps between validations (val split) and checkpoints.
    #[arg(long, default_value_t = 250)]
    pub eval_every: u64,
    /// Seed of initialisation, batches, captions and windows.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Stop (with a checkpoint) after this many steps; the same command without it continues.
    #[arg(long)]
    pub stop_after: Option<u64>,
    /// Where the evaluator trains (recorded in its config.json; a resume may change it).
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// `motionscale evaluator train`.
pub fn evaluator_train(args: EvaluatorTrainArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    let config = EvaluatorTrainConfig {
        corpus: args.corpus,
        text_encoder: args.text_emb,
        out: args.out,
        hidden: args.hidden,
        embed_dim: args.embed_dim,
        max_frames: args.max_frames,
        max_text_tokens: args.max_text_tokens,
        temperature: args.temperature,
        classifier_weight: args.classifier_weight,
        batch: args.batch,
        steps: args.steps,
        lr: args.lr,
        eval_every: args.eval_every,
        seed: args.seed,
        stop_after: args.stop_after,
    };
    let started = std::time::Instant::now();
    let bar = progress_bar("evaluator", "steps");
    let last = train_evaluator(&config, &device, &mut |event| match event {
        EvaluatorEvent::Step(step, total, loss) => {
            bar.set_length(total);
            bar.set_position(step);
            bar.set_message(format!("loss {loss:.3}"));
        }
        EvaluatorEvent::Validated(v) => {
            let line = format!(
                "step {}: train loss {:.3}, val R-precision@1 {:.3}, emotion acc {:.3}, action acc {:.3}",
                v.step, v.train_loss, v.r_precision_top1, v.emotion_accuracy, v.action_accuracy
            );
            if bar.is_hidden() {
                eprintln!("{line}");
            } else {
                bar.println(line);
            }
        }
    })?;
    bar.finish_and_clear();
    let evaluator = TrainedEvaluator::load(&config.out, &device)?;
    println!(
        "evaluator {} → {} in {:.0} s: val R-precision@1 {:.3}, emotion acc {:.3}, action acc {:.3}",
        evaluator.id,
        config.out.display(),
        started.elapsed().as_secs_f64(),
        last.r_precision_top1,
        last.emotion_accuracy,
        last.action_accuracy
    );
    Ok(ExitCode::SUCCESS)
}

/// What both `eval` and `evaluator embed` read: the evaluator, the motions and the corpus.
#[derive(clap::Args, Debug)]
pub struct MotionSetArgs {
    /// Evaluator folder (`motionscale evaluator train --out`).
    #[arg(long)]
    pub evaluator: PathBuf,
    /// Motions: a corpus folder (its ground truth) or a HumanML3D-layout folder
    /// (`new_joint_vecs/`, `texts/`, optional `<split>.txt` and `generated.jsonl`).
    #[arg(long)]
    pub motions: PathBuf,
    /// Reference corpus: ground truth, caption embeddings and labels (default: the one the
    /// evaluator was trained on).
    #[arg(long)]
    pub corpus: Option<PathBuf>,
    /// Split of the reference and of the motions.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Only clips of this source kind (e.g. `synth`, `bvh`).
    #[arg(long)]
    pub source: Option<String>,
    /// Take `--split`'s clips from `DIR/<split>.txt` (e.g. a scenario dataset from
    /// `motionscale scenarios`) in both the motions and the reference.
    #[arg(long)]
    pub splits: Option<PathBuf>,
    /// BERT-family encoder folder for captions the corpus has not embedded.
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Where the evaluator and the encoder run.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// The loaded inputs of [`MotionSetArgs`].
struct Loaded {
    evaluator: TrainedEvaluator,
    corpus: PathBuf,
    set: MotionSet,
    encoder: Option<BertEncoder>,
}

impl MotionSetArgs {
    /// Load the evaluator and the optional encoder onto `--device`, and the motion set (with
    /// `options`).
    fn load(&self, options: &EvalOptions) -> Result<Loaded> {
        let device = self.device.open()?;
        let evaluator = TrainedEvaluator::load(&self.evaluator, &device)
            .with_context(|| format!("loading the evaluator in {}", self.evaluator.display()))?;
        let corpus = self
            .corpus
            .clone()
            .unwrap_or_else(|| evaluator.file.corpus.clone());
        let set = if self.motions.join("manifest.json").is_file() {
            corpus_split(&self.motions, options)?
        } else {
            // Labels of a HumanML3D folder come from the corpus clips with the same ids.
            let labels = corpus_clips(&corpus, |_| true)?
                .into_iter()
                .map(|c| (c.motion_id.clone(), c))
                .collect();
            hml3d_folder(&self.motions, options, &labels)?
        };
        let encoder = self
            .encoder
            .as_deref()
            .map(|dir| BertEncoder::load(dir, &device))
            .transpose()?;
        Ok(Loaded {
            evaluator,
            corpus,
            set,
            encoder,
        })
    }
}

impl Loaded {
    fn encoder(&self) -> Option<&dyn TextEncoder> {
        self.encoder.as_ref().map(|e| e as &dyn TextEncoder)
    }
}

/// Arguments of `motionscale eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Evaluator, motions and reference corpus.
    #[command(flatten)]
    pub set: MotionSetArgs,
    /// Repeats (captions, samples, pools and pairs redrawn each time).
    #[arg(long, default_value_t = 20)]
    pub repeats: usize,
    /// Seed of every draw (recorded in the output).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Compare two disjoint random halves of the motions with each other (FID floor).
    #[arg(long)]
    pub halves: bool,
    /// Sanity check: give each motion another motion's caption (R-precision → chance).
    #[arg(long)]
    pub shuffle_captions: bool,
    /// Sanity check: add Gaussian noise of this many standard deviations to every feature.
    #[arg(long, default_value_t = 0.0)]
    pub noise: f64,
    /// Output JSON file.
    #[arg(long)]
    pub out: PathBuf,
}

/// `motionscale eval`.
pub fn eval(args: EvalArgs) -> Result<ExitCode> {
    let options = EvalOptions {
        split: args.set.split.clone(),
        repeats: args.repeats.max(1),
        seed: args.seed,
        source: args.set.source.clone(),
        splits: args.set.splits.clone(),
        halves: args.halves,
        shuffle_captions: args.shuffle_captions,
        noise: args.noise,
        ..EvalOptions::default()
    };
    let started = std::time::Instant::now();
    let loaded = args.set.load(&options)?;
    let reference = corpus_split(&loaded.corpus, &options)?;
    let report = evaluate_motions(
        &loaded.evaluator,
        &args.set.evaluator,
        &reference,
        &loaded.set,
        &options,
        loaded.encoder(),
    )?;
    let text = serde_json::to_string_pretty(&report)?;
    motionscale_core::write_atomic(&args.out, text.as_bytes())
        .with_context(|| format!("writing {}", args.out.display()))?;
    print_report(&report);
    println!(
        "{} motions ({} texts) vs {} reference clips, {} repeats in {:.1} s → {}",
        report.motion_count,
        report.group_count,
        report.reference_count,
        options.repeats,
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale evaluator embed`.
#[derive(clap::Args, Debug)]
pub struct EmbedArgs {
    /// Evaluator, motions and corpus.
    #[command(flatten)]
    pub set: MotionSetArgs,
    /// Output folder: motion_embeddings.npy, text_embeddings.npy (N × embed_dim, set order)
    /// and motions.jsonl (id, group, first caption, predicted emotion and action).
    #[arg(long)]
    pub out: PathBuf,
}

/// `motionscale evaluator embed`.
pub fn embed(args: EmbedArgs) -> Result<ExitCode> {
    let options = EvalOptions {
        split: args.set.split.clone(),
        source: args.set.source.clone(),
        splits: args.set.splits.clone(),
        ..EvalOptions::default()
    };
    let loaded = args.set.load(&options)?;
    let (evaluator, set) = (&loaded.evaluator, &loaded.set);
    let e = embed_set(evaluator, &loaded.corpus, set, loaded.encoder())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let dim = evaluator.net.config.embed_dim;
    for (name, rows) in [
        ("motion_embeddings.npy", &e.motions.embeddings),
        ("text_embeddings.npy", &e.texts),
    ] {
        let flat: Vec<f32> = rows.iter().flatten().copied().collect();
        let path = args.out.join(name);
        ingest::npy::write_f32(&path, &[rows.len(), dim], &flat)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    let config = &evaluator.net.config;
    let mut lines = String::new();
    for (i, m) in set.motions.iter().enumerate() {
        let line = serde_json::json!({
            "id": m.clip.motion_id,
            "group": m.group,
            "caption": m.clip.captions[0],
            "emotion": config.emotions.get(e.motions.emotion[i]),
            "action": config.actions.get(e.motions.action[i]),
        });
        lines.push_str(&format!("{line}\n"));
    }
    motionscale_core::write_atomic(&args.out.join("motions.jsonl"), lines.as_bytes())?;
    println!(
        "{} motions embedded by evaluator {} → {}",
        set.motions.len(),
        evaluator.id,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn print_report(r: &EvalReport) {
    let line = |name: &str, i: Option<&evaluator::metrics::Interval>| match i {
        Some(i) => println!("{name:<22} {:>9.4} ± {:.4}", i.mean, i.high - i.mean),
        None => println!("{name:<22} {:>9}", "n/a"),
    };
    line("FID", Some(&r.fid));
    for (k, i) in r.r_precision.iter().enumerate() {
        line(&format!("R-precision top-{}", k + 1), Some(i));
    }
    line("matching score", Some(&r.matching_score));
    line("diversity", r.diversity.as_ref());
    line("multimodality", r.multimodality.as_ref());
    line("emotion weighted F1", r.emotion_weighted_f1.as_ref());
    line("action accuracy", r.action_accuracy.as_ref());
}
