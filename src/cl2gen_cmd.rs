//! `motionscale cl2gen`: continual learning to generate with BI-CTVAE.

use crate::device_args::DeviceArgs;
use anyhow::{bail, Context, Result};
use evaluator::metrics::Interval;
use experiments::cl2gen::{compare_table, run_cl2gen, Cl2GenConfig, MetricIntervals, ReplaySource};
use experiments::ctvae::CtvaeConfig;
use experiments::ctvae_train::LossWeights;
use std::path::PathBuf;
use std::process::ExitCode;

/// Arguments of `motionscale cl2gen`.
#[derive(clap::Args, Debug)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct Cl2GenArgs {
    /// `compare RUNS…` instead of a run.
    #[command(subcommand)]
    pub compare: Option<Cl2GenCompare>,
    /// Corpus folder (clips with action labels).
    #[arg(long, required = true)]
    pub corpus: Option<PathBuf>,
    /// Evaluator folder (`motionscale evaluator train`): normalisation, the frozen action
    /// classifier of `--aux`, and the metrics.
    #[arg(long, required = true)]
    pub evaluator: Option<PathBuf>,
    /// Only clips of this source kind (bvh, synth…).
    #[arg(long)]
    pub source: Option<String>,
    /// Action classes need at least this many train clips.
    #[arg(long, default_value_t = 100)]
    pub min_clips: usize,
    /// Classes per task.
    #[arg(long, default_value_t = 2)]
    pub classes_per_task: usize,
    /// Train on every class at once (the offline reference).
    #[arg(long)]
    pub offline: bool,
    /// Replay motions per earlier class as a share of the new task's clips: 0, 1/16, 1/5…
    #[arg(long, default_value = "0")]
    pub replay: String,
    /// Replay generated motions (gen) or real clips (real).
    #[arg(long, default_value = "gen", value_parser = ["gen", "real"])]
    pub replay_source: String,
    /// Add the frozen action classifier's cross-entropy on reconstructions (λ_aux).
    #[arg(long)]
    pub aux: bool,
    /// λ_aux of `--aux`.
    #[arg(long, default_value_t = 1e-4)]
    pub aux_weight: f64,
    /// λ_latent.
    #[arg(long, default_value_t = 1e-5)]
    pub latent_weight: f64,
    /// Network shape: cpu (2-layer GRUs of 128, z 64) or paper (8 × 256, z 256).
    #[arg(long, default_value = "cpu", value_parser = ["cpu", "paper"])]
    pub shape: String,
    /// GRU layers (overrides the shape's).
    #[arg(long)]
    pub layers: Option<usize>,
    /// GRU width (overrides the shape's).
    #[arg(long)]
    pub hidden: Option<usize>,
    /// Width of z (overrides the shape's).
    #[arg(long)]
    pub latent: Option<usize>,
    /// Optimiser steps per task.
    #[arg(long, default_value_t = 400)]
    pub steps_per_task: usize,
    /// Sequences per step.
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    /// AdamW learning rate (the paper's 1e-4 is for 5,000 epochs per task).
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Shortest training window in frames (replay and evaluation length).
    #[arg(long, default_value_t = 60)]
    pub min_frames: usize,
    /// Longest training window in frames.
    #[arg(long, default_value_t = 100)]
    pub max_frames: usize,
    /// Generated motions per class at each evaluation.
    #[arg(long, default_value_t = 50)]
    pub samples_per_class: usize,
    /// Seed of everything random (repeat a run with --seed 1, 2… and `compare` gives the
    /// interval over seeds).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Evaluations of the final model, fresh samples each, behind the reported 95% intervals
    /// (the paper's ±); a finished run re-run with another count only re-evaluates.
    #[arg(long, default_value_t = 20)]
    pub repeats: usize,
    /// Output folder; re-running resumes after the last finished task.
    #[arg(long, required = true)]
    pub out: Option<PathBuf>,
    /// Where BI-CTVAE and the evaluator run (recorded in summary.json).
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// `motionscale cl2gen compare`.
#[derive(clap::Subcommand, Debug)]
pub enum Cl2GenCompare {
    /// Print one row per experiment (the final model's metrics) as a Markdown table; runs
    /// that differ only in --seed share a row: mean ± 95% interval over seeds.
    Compare {
        /// CL2Gen run folders.
        #[arg(required = true)]
        runs: Vec<PathBuf>,
        /// Put runs scored by different evaluators in one table (refused by default).
        #[arg(long)]
        mixed_evaluators: bool,
    },
}

/// A replay ratio written as a fraction (`1/16`) or a number (`0.2`).
fn ratio(text: &str) -> Result<f64> {
    let value = match text.split_once('/') {
        Some((a, b)) => a.trim().parse::<f64>()? / b.trim().parse::<f64>()?,
        None => text.trim().parse()?,
    };
    if !(0.0..=100.0).contains(&value) {
        bail!("--replay {text}: a share of the task's clips, e.g. 1/16");
    }
    Ok(value)
}

/// `motionscale cl2gen`.
pub fn cl2gen(args: Cl2GenArgs) -> Result<ExitCode> {
    if let Some(Cl2GenCompare::Compare {
        runs,
        mixed_evaluators,
    }) = &args.compare
    {
        print!("{}", compare_table(runs, *mixed_evaluators)?);
        return Ok(ExitCode::SUCCESS);
    }
    let (Some(corpus), Some(evaluator), Some(out)) = (args.corpus, args.evaluator, args.out) else {
        bail!("--corpus, --evaluator and --out are required");
    };
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    let replay = ratio(&args.replay).with_context(|| format!("--replay {:?}", args.replay))?;
    if args.min_frames < 4 || args.max_frames < args.min_frames {
        bail!("--min-frames must be at least 4 and at most --max-frames");
    }
    let mut model = match args.shape.as_str() {
        "paper" => CtvaeConfig::paper(Vec::new()),
        _ => CtvaeConfig::cpu(Vec::new()),
    };
    model.max_frames = args.max_frames;
    model.layers = args.layers.unwrap_or(model.layers);
    model.hidden = args.hidden.unwrap_or(model.hidden);
    model.latent = args.latent.unwrap_or(model.latent);
    let config = Cl2GenConfig {
        corpus,
        evaluator,
        source: args.source,
        min_clips: args.min_clips,
        classes_per_task: args.classes_per_task,
        offline: args.offline,
        replay,
        replay_source: if args.replay_source == "real" {
            ReplaySource::Real
        } else {
            ReplaySource::Gen
        },
        model,
        weights: LossWeights {
            latent: args.latent_weight,
            aux: if args.aux { args.aux_weight } else { 0.0 },
        },
        steps_per_task: args.steps_per_task,
        batch: args.batch,
        lr: args.lr,
        window: (args.min_frames, args.max_frames),
        samples_per_class: args.samples_per_class,
        seed: args.seed,
        repeats: args.repeats,
        out,
    };
    let started = std::time::Instant::now();
    let report = run_cl2gen(&config, &device, |line| eprintln!("{line}"))?;
    let last = report.evals.last().context("no task")?;
    let opt = |v: Option<f64>| v.map_or_else(|| "–".into(), |v| format!("{v:.3}"));
    println!(
        "{} tasks, {:.0} s: accuracy {:.3} (ground truth {:.3}), FID {:.4}, diversity {}, multimodality {} → {}",
        report.evals.len(),
        started.elapsed().as_secs_f64(),
        last.accuracy,
        report.ground_truth.accuracy,
        last.fid,
        opt(last.diversity),
        opt(last.multimodality),
        config.out.display()
    );
    let interval = |i: &Interval| format!("{:.3} ± {:.3}", i.mean, i.high - i.mean);
    let intervals = |m: &MetricIntervals| {
        let opt = |i: &Option<Interval>| i.as_ref().map_or_else(|| "–".into(), interval);
        format!(
            "accuracy {}, FID {}, diversity {}, multimodality {}",
            interval(&m.accuracy),
            interval(&m.fid),
            opt(&m.diversity),
            opt(&m.multimodality)
        )
    };
    if let (Some(model), Some(real)) = (&report.final_intervals, &report.ground_truth_intervals) {
        println!("over {} repeats: {}", report.repeats, intervals(model));
        println!("real test windows: {}", intervals(real));
    }
    Ok(ExitCode::SUCCESS)
}
