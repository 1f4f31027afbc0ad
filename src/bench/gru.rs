//! `motionscale bench evaluator` and `bench ctvae`: training steps/s of the two GRU models
//! (the text–motion evaluator; BI-CTVAE at `cl2gen`'s shapes) and, with `--reference`, the
//! same step of their PyTorch references run by the same command, with the ratio.
//!
//! The evaluator's workload is `shared/bench/pytorch_evaluator.py`'s: B clips of 40–196
//! frames (multiples of 4) and captions of 8–32 tokens of 384-d embeddings, N(0, 1) values,
//! 6 emotion and 12 action labels; loss InfoNCE (τ 0.07) + both cross-entropies; AdamW at
//! 1e-3. With `--reference` the lengths are the reference's own (drawn by torch's generator
//! with its seed), so both time the same sequences. BI-CTVAE's is `scripts/pytorch_ctvae.py`'s.

use crate::device_args::DeviceArgs;
use anyhow::{Context, Result};
use candle_core::Device;
use evaluator::model::{init_evaluator, labelled_cross_entropy, EvaluatorConfig, Padded};
use experiments::ctvae::CtvaeConfig;
use experiments::ctvae_train::{CtvaeTrainer, LossWeights, Sample};
use motionscale_core::rng::SplitMix64;
use nn::device::device_name;
use nn::optim::{AdamW, AdamWConfig};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Arguments of `motionscale bench evaluator`.
#[derive(clap::Args, Debug)]
pub struct BenchEvaluatorArgs {
    /// Clips per step.
    #[arg(long, default_value_t = 64)]
    pub batch: usize,
    /// GRU and convolution width.
    #[arg(long, default_value_t = 256)]
    pub hidden: usize,
    /// Untimed steps first.
    #[arg(long, default_value_t = 3)]
    pub warmup: usize,
    /// Timed steps (the median is reported).
    #[arg(long, default_value_t = 15)]
    pub reps: usize,
    /// Also run shared/bench/pytorch_evaluator.py (needs torch) and print the ratio.
    #[arg(long)]
    pub reference: bool,
    /// Folder of the shared PyTorch reference scripts.
    #[arg(long, default_value = "../shared/bench")]
    pub bench_dir: PathBuf,
    /// Also write the figures as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Where the evaluator trains.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// Arguments of `motionscale bench ctvae`.
#[derive(clap::Args, Debug)]
pub struct BenchCtvaeArgs {
    /// Shapes to time (`cl2gen --shape`).
    #[arg(long, value_delimiter = ',', default_value = "cpu,paper")]
    pub shapes: Vec<String>,
    /// Sequences per step.
    #[arg(long, default_value_t = 64)]
    pub batch: usize,
    /// Action classes.
    #[arg(long, default_value_t = 10)]
    pub classes: usize,
    /// Untimed steps first.
    #[arg(long, default_value_t = 2)]
    pub warmup: usize,
    /// Timed steps (the median is reported).
    #[arg(long, default_value_t = 10)]
    pub reps: usize,
    /// Also run scripts/pytorch_ctvae.py (needs torch) and print the ratio.
    #[arg(long)]
    pub reference: bool,
    /// The BI-CTVAE PyTorch reference.
    #[arg(long, default_value = "scripts/pytorch_ctvae.py")]
    pub reference_script: PathBuf,
    /// Also write the figures as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Where BI-CTVAE trains.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// The figures of `bench evaluator` (its `--json`).
#[derive(Debug, Serialize, Deserialize)]
pub struct EvaluatorFigures {
    /// What was timed: "evaluator training step".
    pub what: String,
    /// Clips per step.
    pub batch: usize,
    /// GRU and convolution width.
    pub hidden: usize,
    /// Mean frames per clip.
    pub mean_frames: f64,
    /// Mean caption tokens per clip.
    pub mean_tokens: f64,
    /// Where the evaluator trained.
    pub device: String,
    /// Threads of the pool.
    pub threads: usize,
    /// Our median step, seconds.
    pub median_step_s: f64,
    /// With `--reference`: the PyTorch step beside ours.
    #[serde(flatten)]
    pub compared: Compared,
}

/// The figures of one shape of `bench ctvae` (its `--json` lists them under `figures`).
#[derive(Debug, Serialize, Deserialize)]
pub struct CtvaeFigure {
    /// What was timed: "BI-CTVAE training step".
    pub what: String,
    /// `cl2gen --shape`.
    pub shape: String,
    /// Sequences per step.
    pub batch: usize,
    /// Where BI-CTVAE trained.
    pub device: String,
    /// Threads of the pool.
    pub threads: usize,
    /// Our median step, seconds.
    pub median_step_s: f64,
    /// With `--reference`: the PyTorch step beside ours.
    #[serde(flatten)]
    pub compared: Compared,
}

/// A PyTorch reference's step beside ours: both absent without `--reference`.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct Compared {
    /// The reference script's output.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reference: Option<StepReference>,
    /// Its median step over ours.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub ratio: Option<f64>,
}

/// The output of a training-step reference (`pytorch_evaluator.py`, `pytorch_ctvae.py`).
#[derive(Debug, Serialize, Deserialize)]
pub struct StepReference {
    /// Its median step, seconds.
    pub median_step_s: f64,
    /// The rest of its output (torch version, shape, samples), kept as it wrote them.
    #[serde(flatten)]
    pub other: serde_json::Map<String, serde_json::Value>,
}

/// Frames and caption tokens of each clip as `pytorch_evaluator.py` draws them.
fn reference_lengths(batch: usize) -> Result<(Vec<usize>, Vec<usize>)> {
    let code = format!(
        "import json, torch\n\
         g = torch.Generator().manual_seed(1)\n\
         f = [int(v) // 4 * 4 for v in torch.randint(40, 197, ({batch},), generator=g)]\n\
         t = [int(v) for v in torch.randint(8, 33, ({batch},), generator=g)]\n\
         print(json.dumps([f, t]))"
    );
    let out = std::process::Command::new("python3")
        .args(["-c", &code])
        .output()
        .context("running python3 for the reference's lengths")?;
    anyhow::ensure!(
        out.status.success(),
        "python3 (torch) failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    Ok(serde_json::from_slice(&out.stdout)?)
}

/// The same ranges drawn by our generator (no torch needed).
fn own_lengths(batch: usize) -> (Vec<usize>, Vec<usize>) {
    let mut rng = SplitMix64::stream(1, 0);
    let frames = (0..batch).map(|_| (40 + rng.index(157)) / 4 * 4).collect();
    let tokens = (0..batch).map(|_| 8 + rng.index(25)).collect();
    (frames, tokens)
}

fn normal_rows(lengths: &[usize], width: usize, rng: &mut SplitMix64) -> Vec<Vec<f32>> {
    lengths
        .iter()
        .map(|&l| (0..l * width).map(|_| rng.normal() as f32).collect())
        .collect()
}

fn slices(rows: &[Vec<f32>]) -> Vec<&[f32]> {
    rows.iter().map(Vec::as_slice).collect()
}

/// Median seconds of our evaluator training step on `device`, on clips of `frames` and
/// captions of `tokens`.
fn time_evaluator(
    args: &BenchEvaluatorArgs,
    device: &Device,
    frames: &[usize],
    tokens: &[usize],
) -> Result<f64> {
    let config = EvaluatorConfig {
        feature_dim: ingest::hml263::FEATURE_DIM,
        text_dim: 384,
        hidden: args.hidden,
        embed_dim: 256,
        max_frames: 196,
        max_text_tokens: 32,
        temperature: 0.07,
        emotions: (0..6).map(|i| format!("e{i}")).collect(),
        actions: (0..12).map(|i| format!("a{i}")).collect(),
    };
    let (net, varmap) = init_evaluator(config.clone(), 0, device)?;
    let mut opt = AdamW::new(
        &varmap.data().lock().expect("varmap lock").clone(),
        AdamWConfig::default(),
    );
    let mut rng = SplitMix64::stream(2, 0);
    let motions = normal_rows(frames, config.feature_dim, &mut rng);
    let texts = normal_rows(tokens, config.text_dim, &mut rng);
    let emotion: Vec<Option<u32>> = (0..frames.len())
        .map(|_| Some(rng.index(6) as u32))
        .collect();
    let action: Vec<Option<u32>> = (0..frames.len())
        .map(|_| Some(rng.index(12) as u32))
        .collect();
    let distinct = vec![vec![false; frames.len()]; frames.len()];
    // The padded batch is built once, as the reference builds its tensors once.
    let motion_batch = Padded::new(&slices(&motions), config.feature_dim, device)?;
    let text_batch = Padded::new(&slices(&texts), config.text_dim, device)?;
    let timing = super::time(args.warmup, args.reps, 0.0, || {
        let motion = net.encode_motion(&motion_batch)?;
        let text = net.encode_text(&text_batch)?;
        let loss = (net.contrastive_loss(&text, &motion.embedding, &distinct)?
            + labelled_cross_entropy(&motion.emotion, &emotion)?
            + labelled_cross_entropy(&motion.action, &action)?)?;
        opt.step(&loss.backward()?, 1e-3, None)?;
        // A GPU queues the update: the step ends when it has run.
        device.synchronize()?;
        Ok(())
    })?;
    Ok(timing.median_s)
}

/// `motionscale bench evaluator`.
pub fn evaluator(args: BenchEvaluatorArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    let (frames, tokens) = if args.reference {
        reference_lengths(args.batch)?
    } else {
        own_lengths(args.batch)
    };
    let mean = |v: &[usize]| v.iter().sum::<usize>() as f64 / v.len() as f64;
    let ours = time_evaluator(&args, &device, &frames, &tokens)?;
    let mut line = format!(
        "evaluator training step, batch {}, hidden {}, {:.1} frames and {:.1} tokens per clip, {}, {} threads: {:.3} s ({:.2} steps/s)",
        args.batch,
        args.hidden,
        mean(&frames),
        mean(&tokens),
        device_name(&device),
        rayon::current_num_threads(),
        ours,
        1.0 / ours
    );
    let mut compared = Compared::default();
    if args.reference {
        let script = args.bench_dir.join("pytorch_evaluator.py");
        let (batch, hidden) = (args.batch.to_string(), args.hidden.to_string());
        let flags = ["--batch", &batch, "--hidden", &hidden];
        let repeats = (args.warmup, args.reps);
        compared = add_reference(&script, &flags, repeats, ours, &mut line)?;
    }
    let figures = EvaluatorFigures {
        what: "evaluator training step".into(),
        batch: args.batch,
        hidden: args.hidden,
        mean_frames: mean(&frames),
        mean_tokens: mean(&tokens),
        device: device_name(&device),
        threads: rayon::current_num_threads(),
        median_step_s: ours,
        compared,
    };
    println!("{line}");
    super::write_json(args.json.as_ref(), &figures)?;
    Ok(ExitCode::SUCCESS)
}

/// Lengths of the BI-CTVAE workload: 60 + (7·b mod 41) frames, as the reference script.
fn ctvae_lengths(batch: usize) -> Vec<usize> {
    (0..batch).map(|b| 60 + (7 * b) % 41).collect()
}

/// Median seconds of our BI-CTVAE training step at `shape` on `device`.
fn time_ctvae(args: &BenchCtvaeArgs, shape: &str, device: &Device) -> Result<f64> {
    let classes: Vec<String> = (0..args.classes).map(|i| format!("c{i}")).collect();
    let config = match shape {
        "paper" => CtvaeConfig::paper(classes),
        "cpu" => CtvaeConfig::cpu(classes),
        other => anyhow::bail!("unknown shape {other:?} (cpu or paper)"),
    };
    let dim = config.feature_dim;
    let weights = LossWeights {
        latent: 1e-5,
        aux: 0.0,
    };
    let mut trainer = CtvaeTrainer::new(config, weights, &vec![1.0; dim], 0, device)?;
    let mut rng = SplitMix64::stream(3, 0);
    let samples: Vec<Sample> = ctvae_lengths(args.batch)
        .iter()
        .enumerate()
        .map(|(b, &l)| Sample {
            class: (b % args.classes) as u32,
            poses: (0..l * dim).map(|_| rng.normal() as f32).collect(),
        })
        .collect();
    let batch: Vec<&Sample> = samples.iter().collect();
    let timing = super::time(args.warmup, args.reps, 0.0, || {
        trainer.step(&batch, 1e-3, None, &mut rng)?;
        Ok(())
    })?;
    Ok(timing.median_s)
}

/// `motionscale bench ctvae`.
pub fn ctvae(args: BenchCtvaeArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    let mut figures = Vec::new();
    for shape in &args.shapes {
        let ours = time_ctvae(&args, shape, &device)?;
        let mut line = format!(
            "BI-CTVAE training step, shape {shape}, batch {}, 60–100 frames, {}, {} threads: {ours:.3} s ({:.2} steps/s)",
            args.batch,
            device_name(&device),
            rayon::current_num_threads(),
            1.0 / ours
        );
        let mut compared = Compared::default();
        if args.reference {
            let (batch, classes) = (args.batch.to_string(), args.classes.to_string());
            let flags = ["--shape", shape, "--batch", &batch, "--classes", &classes];
            let repeats = (args.warmup, args.reps);
            compared = add_reference(&args.reference_script, &flags, repeats, ours, &mut line)?;
        }
        println!("{line}");
        figures.push(CtvaeFigure {
            what: "BI-CTVAE training step".into(),
            shape: shape.clone(),
            batch: args.batch,
            device: device_name(&device),
            threads: rayon::current_num_threads(),
            median_step_s: ours,
            compared,
        });
    }
    super::write_json(args.json.as_ref(), &figures)?;
    Ok(ExitCode::SUCCESS)
}

/// Run the reference `script` with `flags` on 2 threads (`(warm-up, timed)` steps), add its
/// median step and our ratio to it to `line`, and return both.
fn add_reference(
    script: &Path,
    flags: &[&str],
    (warmup, reps): (usize, usize),
    ours: f64,
    line: &mut String,
) -> Result<Compared> {
    let (warmup, reps) = (warmup.to_string(), reps.to_string());
    let mut all = flags.to_vec();
    all.extend(["--threads", "2", "--warmup", &warmup, "--reps", &reps]);
    let reference: StepReference = super::run_reference(script, &all)?;
    let theirs = reference.median_step_s;
    line.push_str(&format!(
        "; PyTorch {theirs:.3} s ({:.2} steps/s) → ratio {:.2}×",
        1.0 / theirs,
        theirs / ours
    ));
    Ok(Compared {
        reference: Some(reference),
        ratio: Some(theirs / ours),
    })
}
