//! `motionscale tokenizer train|eval|sweep|decode` and `motionscale tokenize`: motion
//! tokenizers (FSQ / VQ VAEs) trained on a corpus, their metrics, and token sets.

use crate::commands::progress_bar;
use crate::device_args::DeviceArgs;
use anyhow::{bail, Context, Result};
use candle_core::Device;
use ingest::corpus::Corpus;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tokenizer::evaluate::{evaluate, mpjpe, write_token_set, EvalReport};
use tokenizer::model::{MotionTokenizer, TokenizerConfig};
use tokenizer::train::{train, StepReport, TrainConfig};
use tokenizer::{Bound, ConvConfig, TokenSet};

/// Architecture and optimisation flags shared by `train` and `sweep`.
#[derive(clap::Args, Debug, Clone)]
pub struct TrainFlags {
    /// Channels of the encoder/decoder convolutions (T2M-GPT: 512).
    #[arg(long, default_value_t = 512)]
    pub width: usize,
    /// Channels of the latent (default: the width).
    #[arg(long)]
    pub code_dim: Option<usize>,
    /// Residual units per dilated stack.
    #[arg(long, default_value_t = 3)]
    pub depth: usize,
    /// FSQ bound: tanh (Mentzer et al.) or sigmoid (ScaMo).
    #[arg(long, default_value = "tanh", value_parser = ["tanh", "sigmoid"])]
    pub bound: String,
    /// Windows per batch.
    #[arg(long, default_value_t = 256)]
    pub batch: usize,
    /// Optimiser steps.
    #[arg(long, default_value_t = 20_000)]
    pub steps: u64,
    /// Frames per training window.
    #[arg(long, default_value_t = 64)]
    pub window: usize,
    /// Peak learning rate.
    #[arg(long, default_value_t = 2e-4)]
    pub lr: f64,
    /// Warm-up steps (default: 5% of the steps).
    #[arg(long)]
    pub warmup: Option<u64>,
    /// Clip the global gradient norm to this value.
    #[arg(long)]
    pub grad_clip: Option<f64>,
    /// Validate every N steps (default: 20 times per run).
    #[arg(long)]
    pub eval_every: Option<u64>,
    /// Checkpoint every N steps (default: as often as validation).
    #[arg(long)]
    pub checkpoint_every: Option<u64>,
    /// Seed of initialisation and batch draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl TrainFlags {
    fn conv(&self) -> ConvConfig {
        ConvConfig {
            width: self.width,
            code_dim: self.code_dim.unwrap_or(self.width),
            depth: self.depth,
            ..ConvConfig::default()
        }
    }

    fn bound(&self) -> Bound {
        if self.bound == "sigmoid" {
            Bound::Sigmoid
        } else {
            Bound::Tanh
        }
    }

    /// The tokenizer architecture these flags describe for `quantizer` at a nominal `codebook`.
    pub(crate) fn tokenizer_config(
        &self,
        quantizer: &str,
        codebook: usize,
    ) -> Result<TokenizerConfig> {
        Ok(TokenizerConfig::new(
            quantizer,
            codebook,
            self.bound(),
            self.conv(),
        )?)
    }

    /// The training settings these flags describe.
    pub(crate) fn train_config(&self) -> TrainConfig {
        let eval_every = self.eval_every.unwrap_or((self.steps / 20).max(1));
        TrainConfig {
            steps: self.steps,
            batch: self.batch,
            window: self.window,
            lr: self.lr,
            warmup: self.warmup.unwrap_or(self.steps / 20),
            grad_clip: self.grad_clip,
            eval_every,
            checkpoint_every: self.checkpoint_every.unwrap_or(eval_every),
            seed: self.seed,
            ..TrainConfig::default()
        }
    }
}

/// Arguments of `motionscale tokenizer train`.
#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Corpus folder.
    #[arg(long)]
    pub corpus: PathBuf,
    /// fsq or vq.
    #[arg(long, value_parser = ["fsq", "vq"])]
    pub quantizer: String,
    /// Codebook size (FSQ: 256, 1024, 4096, 16384 or 65536, named by Mentzer et al.'s level sets).
    #[arg(long, default_value_t = 1024)]
    pub codebook: usize,
    /// Training settings.
    #[command(flatten)]
    pub flags: TrainFlags,
    /// Output folder: the checkpoint; re-running the same command resumes it.
    #[arg(long)]
    pub out: PathBuf,
    /// Where the tokenizer trains (recorded in train.json; a resume may change it).
    #[command(flatten)]
    pub device: DeviceArgs,
}

fn step_bar(label: &str, steps: u64) -> impl FnMut(StepReport) {
    let label = label.to_string();
    let bar = progress_bar(&label, "steps");
    bar.set_length(steps);
    move |r: StepReport| {
        bar.set_position(r.step);
        let mut message = format!("loss {:.4}", r.loss);
        if r.reset > 0 {
            message.push_str(&format!(" reset {}", r.reset));
        }
        bar.set_message(message);
        if let Some(val) = r.val {
            let line = format!(
                "{label} step {}/{}: train loss {:.4}, val recon {:.4} vel {:.4} L1 {:.4}",
                r.step, r.steps, r.loss, val.recon, val.velocity, val.l1
            );
            if bar.is_hidden() {
                eprintln!("{line}");
            } else {
                bar.println(line);
            }
        }
        if r.step == r.steps {
            bar.finish_and_clear();
        }
    }
}

/// `motionscale tokenizer train`.
pub fn train_cmd(args: TrainArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    let config = args
        .flags
        .tokenizer_config(&args.quantizer, args.codebook)?;
    let train_config = args.flags.train_config();
    let started = std::time::Instant::now();
    let label = format!("{} {}", args.quantizer, args.codebook);
    let state = train(
        &args.corpus,
        &args.out,
        config,
        train_config,
        &device,
        step_bar(&label, args.flags.steps),
    )?;
    println!(
        "trained {label} for {} steps in {:.1} s ({:.1} s in all runs): final train loss {:.4}{} → {}",
        state.step,
        started.elapsed().as_secs_f64(),
        state.wall_s,
        state.train_loss.unwrap_or(f64::NAN),
        state
            .val
            .map(|v| format!(", val L1 {:.4}", v.l1))
            .unwrap_or_default(),
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale tokenizer eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Tokenizer checkpoint folder.
    #[arg(long)]
    pub tokenizer: PathBuf,
    /// Corpus folder.
    #[arg(long)]
    pub corpus: PathBuf,
    /// Split to evaluate.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Also write the JSON report here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Where the tokenizer runs.
    #[command(flatten)]
    pub device: DeviceArgs,
}

fn open_corpus(dir: &Path) -> Result<Corpus> {
    Ok(Corpus::open(dir)?)
}

fn eval_report(
    tokenizer_dir: &Path,
    corpus: &Corpus,
    split: &str,
    device: &Device,
) -> Result<EvalReport> {
    let tokenizer = MotionTokenizer::load(tokenizer_dir, device)?;
    let bar = progress_bar(&format!("eval {split}"), "clips");
    let report = evaluate(
        &tokenizer,
        tokenizer_dir.to_path_buf(),
        corpus,
        split,
        |done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        },
    )?;
    bar.finish_and_clear();
    Ok(report)
}

/// `motionscale tokenizer eval`: metrics as JSON on stdout.
pub fn eval_cmd(args: EvalArgs) -> Result<ExitCode> {
    let device = args.device.open()?;
    let corpus = open_corpus(&args.corpus)?;
    let report = eval_report(&args.tokenizer, &corpus, &args.split, &device)?;
    let json = serde_json::to_string_pretty(&report)?;
    if let Some(out) = &args.out {
        motionscale_core::write_atomic(out, json.as_bytes())
            .with_context(|| format!("writing {}", out.display()))?;
    }
    println!("{json}");
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale tokenize`.
#[derive(clap::Args, Debug)]
pub struct TokenizeArgs {
    /// Tokenizer checkpoint folder.
    #[arg(long)]
    pub tokenizer: PathBuf,
    /// Corpus folder.
    #[arg(long)]
    pub corpus: PathBuf,
    /// Output token-set folder (tokens.parquet, unigram.json, manifest.json).
    #[arg(long)]
    pub out: PathBuf,
    /// Where the tokenizer runs.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// `motionscale tokenize`: every clip of a corpus → token ids.
pub fn tokenize_cmd(args: TokenizeArgs) -> Result<ExitCode> {
    let device = args.device.open()?;
    let corpus = open_corpus(&args.corpus)?;
    let bar = progress_bar("tokenize", "clips");
    let progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let manifest = write_token_set(&args.tokenizer, &corpus, &args.out, &device, progress)?;
    bar.finish_and_clear();
    for (split, count) in &manifest.splits {
        println!("{split}: {} clips, {} tokens", count.clips, count.tokens);
    }
    println!("wrote {}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale tokenizer decode`.
#[derive(clap::Args, Debug)]
pub struct DecodeArgs {
    /// Tokenizer checkpoint folder.
    #[arg(long)]
    pub tokenizer: PathBuf,
    /// Token-set folder (from `motionscale tokenize`).
    #[arg(long, conflicts_with = "ids")]
    pub tokens: Option<PathBuf>,
    /// One clip of the token set (writes OUT as a file).
    #[arg(long, requires = "tokens", conflicts_with = "split")]
    pub motion_id: Option<String>,
    /// Every clip of this split of the token set (writes OUT/<motion_id>.npy).
    #[arg(long, requires = "tokens")]
    pub split: Option<String>,
    /// Token ids given directly, comma-separated.
    #[arg(long, value_delimiter = ',')]
    pub ids: Option<Vec<u32>>,
    /// Compare with this corpus's clips: prints the round-trip MPJPE.
    #[arg(long)]
    pub corpus: Option<PathBuf>,
    /// Output: .npy (n × 263 features, or n × 22 × 3 joints with --joints) or .bvh; a folder with --split.
    #[arg(long)]
    pub out: PathBuf,
    /// Write joint positions instead of features to .npy files.
    #[arg(long)]
    pub joints: bool,
    /// Where the tokenizer runs.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// `motionscale tokenizer decode`: token ids → features, joints or BVH.
pub fn decode_cmd(args: DecodeArgs) -> Result<ExitCode> {
    let device = args.device.open()?;
    let tokenizer = MotionTokenizer::load(&args.tokenizer, &device)?;
    let corpus = args.corpus.as_deref().map(open_corpus).transpose()?;
    let clips: Vec<(String, Vec<u32>)> = match (&args.tokens, &args.ids) {
        (Some(dir), None) => {
            let set = TokenSet::open(dir)?;
            let wanted = |c: &&tokenizer::TokenClip| match (&args.motion_id, &args.split) {
                (Some(id), _) => &c.motion_id == id,
                (None, Some(split)) => &c.split == split,
                (None, None) => false,
            };
            let picked: Vec<_> = set
                .clips
                .iter()
                .filter(wanted)
                .map(|c| (c.motion_id.clone(), c.tokens.clone()))
                .collect();
            if picked.is_empty() {
                bail!("{}: no clip matches --motion-id/--split", dir.display());
            }
            picked
        }
        (None, Some(ids)) => vec![("tokens".into(), ids.clone())],
        _ => bail!("give --tokens DIR with --motion-id or --split, or --ids"),
    };
    let many = args.split.is_some();
    if many {
        std::fs::create_dir_all(&args.out)
            .with_context(|| format!("creating {}", args.out.display()))?;
    }
    let (mut global_sum, mut aligned_sum, mut frames) = (0f64, 0f64, 0usize);
    for (id, tokens) in &clips {
        let features = tokenizer.detokenize(tokens)?;
        let out = if many {
            args.out.join(format!("{id}.npy"))
        } else {
            args.out.clone()
        };
        ingest::export::motion::write_motion(&out, &features, args.joints)
            .with_context(|| format!("writing {}", out.display()))?;
        if let Some(corpus) = &corpus {
            let index = corpus
                .find(id)
                .with_context(|| format!("{id} is not in the corpus"))?;
            let original = corpus.features(index)?;
            let error = mpjpe(&original[..features.len()], &features);
            global_sum += error.global * error.frames as f64;
            aligned_sum += error.root_aligned * error.frames as f64;
            frames += error.frames;
        }
    }
    println!("decoded {} clip(s) → {}", clips.len(), args.out.display());
    if frames > 0 {
        println!(
            "round-trip MPJPE over {frames} frames: {:.3} mm root-aligned, {:.3} mm global",
            aligned_sum / frames as f64 * 1000.0,
            global_sum / frames as f64 * 1000.0
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale tokenizer sweep`.
#[derive(clap::Args, Debug)]
pub struct SweepArgs {
    /// Corpus folder.
    #[arg(long)]
    pub corpus: PathBuf,
    /// Quantizers, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "fsq,vq")]
    pub quantizers: Vec<String>,
    /// Nominal codebook sizes, comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "256,1024,4096,16384,65536"
    )]
    pub codebooks: Vec<usize>,
    /// Split reconstruction (and a second utilisation, beside the uniform tokenizer's
    /// coverage) is measured on; the headline utilisation is always the train split's.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Training settings shared by every run.
    #[command(flatten)]
    pub flags: TrainFlags,
    /// Output folder (one sub-folder per run, sweep.csv, sweep.parquet); re-running resumes.
    #[arg(long)]
    pub out: PathBuf,
    /// Where the tokenizers train and run.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// `motionscale tokenizer sweep`: train and evaluate every (quantizer, codebook) pair.
pub fn sweep_cmd(args: SweepArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    use experiments::codebook_sweep::{sweep, SweepEvent, SweepPlan};
    if let Some(q) = args
        .quantizers
        .iter()
        .find(|q| !["fsq", "vq"].contains(&q.as_str()))
    {
        bail!("unknown quantizer {q:?} (fsq or vq)");
    }
    let plan = SweepPlan {
        quantizers: args.quantizers.clone(),
        codebooks: args.codebooks.clone(),
        conv: args.flags.conv(),
        bound: args.flags.bound(),
        train: args.flags.train_config(),
        split: args.split.clone(),
    };
    let started = std::time::Instant::now();
    let bar = progress_bar("sweep", "steps");
    let rows = sweep(
        &args.corpus,
        &args.out,
        &plan,
        &device,
        |event| match event {
            SweepEvent::Step(name, r) => {
                bar.set_length(r.steps);
                bar.set_position(r.step);
                bar.set_message(format!("{name} loss {:.4}", r.loss));
            }
            SweepEvent::Eval(name, done, total) => {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
                bar.set_message(format!("{name} eval"));
            }
            SweepEvent::Done(name, row) => eprintln!(
                "{name}: train utilization {:.1}%, perplexity {:.1}; {}: recon L1 {:.4}, \
                 MPJPE {:.1} mm root-aligned, {:.1} mm global",
                100.0 * row.utilization,
                row.perplexity,
                row.split,
                row.recon_l1,
                row.mpjpe_root_mm,
                row.mpjpe_mm
            ),
        },
    )?;
    bar.finish_and_clear();
    print_sweep_table(&rows, &args.split);
    println!(
        "{} runs in {:.1} s → {}",
        rows.len(),
        started.elapsed().as_secs_f64(),
        args.out.join("sweep.csv").display()
    );
    Ok(ExitCode::SUCCESS)
}

/// The sweep's rows as a text table: the training figures, then those on the `split`.
fn print_sweep_table(rows: &[experiments::codebook_sweep::SweepRow], split: &str) {
    println!(
        "{:<6} {:>8} {:>8} {:>10} {:>10} {:>8} | {} split: {:>8} {:>6} {:>9} {:>9} {:>8} {:>8}",
        "quant",
        "codebook",
        "codes",
        "train util%",
        "perplexity",
        "entropy",
        split,
        "N/K",
        "util%",
        "uniform%",
        "recon_l1",
        "root_mm",
        "mpjpe_mm"
    );
    for r in rows {
        println!(
            "{:<6} {:>8} {:>8} {:>11.1} {:>10.1} {:>8.3} | {:>w$} {:>8.1} {:>6.1} {:>9.1} {:>9.4} {:>8.1} {:>8.1}",
            r.quantizer,
            r.codebook,
            r.codebook_size,
            100.0 * r.utilization,
            r.perplexity,
            r.entropy,
            "",
            r.split_tokens as f64 / r.codebook_size as f64,
            100.0 * r.split_utilization,
            100.0 * r.split_uniform_coverage,
            r.recon_l1,
            r.mpjpe_root_mm,
            r.mpjpe_mm,
            w = split.len() + 7
        );
    }
}
