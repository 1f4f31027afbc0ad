//! Tokenizer training: random 64-frame windows of normalised features from the corpus,
//! AdamW with warm-up + cosine decay, loss = smooth-L1 reconstruction + 0.5 · velocity
//! (+ commitment for VQ), periodic validation, resumable checkpoints.
//!
//! The output folder is a loadable tokenizer checkpoint at every moment (see [`crate::model`])
//! plus the training state:
//!
//! ```text
//! DIR/train.json             TrainConfig + corpus (what `--resume` must match), device
//! DIR/state.json             step, VQ generator state, last losses (the commit record)
//! DIR/resume/<step>/         that step's tokenizer files and optimizer.safetensors (AdamW)
//! DIR/log.jsonl              one line per validation: step, lr, train and val losses
//! ```
//!
//! Batch `s` is drawn with seed `hash(seed, s)`, so a run killed at any moment and started
//! again reproduces the uninterrupted run exactly.

use crate::error::TokenizerError;
use crate::loss::reconstruction_losses;
use crate::model::{MotionTokenizer, TokenizerConfig, FEATURES};
use candle_core::{Device, Tensor};
use ingest::corpus::Corpus;
use motionscale_core::files::{check_same_run, read_json, write_json};
use motionscale_core::rng::SplitMix64;
use nn::checkpoint::ResumeFiles;
use nn::optim::{AdamW, AdamWConfig, LrSchedule};
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The optimiser state inside a resume folder.
const OPTIMIZER_FILE: &str = "optimizer.safetensors";

/// Training hyper-parameters (T2M-GPT's defaults where it has one).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Optimiser steps.
    pub steps: u64,
    /// Windows per batch.
    pub batch: usize,
    /// Frames per window.
    pub window: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Linear warm-up steps.
    pub warmup: u64,
    /// Final learning rate as a fraction of the peak (cosine decay).
    pub final_lr_ratio: f64,
    /// AdamW decoupled weight decay.
    pub weight_decay: f64,
    /// AdamW β1.
    pub beta1: f64,
    /// AdamW β2.
    pub beta2: f64,
    /// Weight of the velocity term.
    pub velocity_weight: f64,
    /// Global gradient-norm clip (none when absent).
    pub grad_clip: Option<f64>,
    /// Validate (and log) every this many steps.
    pub eval_every: u64,
    /// Validation batches (fixed windows of the val split).
    pub eval_batches: usize,
    /// Write a checkpoint every this many steps (and at the end).
    pub checkpoint_every: u64,
    /// Seed of initialisation and batch draws.
    pub seed: u64,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            steps: 20_000,
            batch: 256,
            window: 64,
            lr: 2e-4,
            warmup: 1_000,
            final_lr_ratio: 0.05,
            weight_decay: 0.0,
            beta1: 0.9,
            beta2: 0.99,
            velocity_weight: 0.5,
            grad_clip: None,
            eval_every: 500,
            eval_batches: 4,
            checkpoint_every: 500,
            seed: 0,
        }
    }
}

/// `DIR/train.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainSpec {
    /// Corpus folder.
    pub corpus: PathBuf,
    /// Tokenizer architecture.
    pub tokenizer: TokenizerConfig,
    /// Hyper-parameters.
    pub train: TrainConfig,
    /// Device training last ran on (`cpu`, `cuda:N`: a resume may change it); empty in older
    /// files.
    #[serde(default)]
    pub device: String,
}

/// `DIR/state.json`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Optimiser steps done.
    pub step: u64,
    /// VQ reset generator state (0 for FSQ).
    pub vq_rng: u64,
    /// Last training loss (total).
    pub train_loss: Option<f64>,
    /// Last validation losses.
    pub val: Option<ValLosses>,
    /// Wall-clock seconds spent training, summed over resumed runs.
    pub wall_s: f64,
}

/// Losses on the fixed validation windows.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ValLosses {
    /// Smooth-L1 reconstruction.
    pub recon: f64,
    /// Smooth-L1 velocity.
    pub velocity: f64,
    /// Mean absolute error of normalised features.
    pub l1: f64,
}

/// What a training step reports to the caller (for progress bars).
#[derive(Debug, Clone, Copy)]
pub struct StepReport {
    /// Steps done.
    pub step: u64,
    /// Total steps.
    pub steps: u64,
    /// Loss of this step.
    pub loss: f64,
    /// Dead codes reset (VQ).
    pub reset: usize,
    /// Validation losses when this step validated.
    pub val: Option<ValLosses>,
}

/// The step-`step` batch seed: steps draw independent batches that a resumed run reproduces.
fn batch_seed(seed: u64, step: u64) -> u64 {
    SplitMix64(seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15)).next_u64()
}

fn corpus_error(path: &Path, message: impl std::fmt::Display) -> TokenizerError {
    TokenizerError::File {
        path: path.to_path_buf(),
        message: message.to_string(),
    }
}

/// Train a tokenizer on `corpus` into `out`, resuming when `out` holds a checkpoint of the
/// same spec. `on_step` sees every step (progress bars).
pub fn train(
    corpus_dir: &Path,
    out: &Path,
    tokenizer: TokenizerConfig,
    config: TrainConfig,
    device: &Device,
    mut on_step: impl FnMut(StepReport),
) -> Result<TrainState, TokenizerError> {
    let spec = TrainSpec {
        corpus: corpus_dir.to_path_buf(),
        tokenizer,
        train: config.clone(),
        device: nn::device::device_name(device),
    };
    let corpus = Corpus::open(corpus_dir).map_err(|e| corpus_error(corpus_dir, e))?;
    let resume = ResumeFiles::new(out);
    let (mut model, mut state) = resume_or_start(&spec, &corpus, out, &resume, device)?;
    if state.step >= config.steps {
        return Ok(state);
    }
    let mut optimizer = optimizer_for(&model, &config);
    if state.step > 0 {
        optimizer.load(&resume.files(state.step).join(OPTIMIZER_FILE))?;
    }
    let schedule = LrSchedule {
        peak: config.lr,
        warmup: config.warmup,
        total: config.steps,
        final_ratio: config.final_lr_ratio,
    };
    let load = |split: &str| {
        corpus
            .window_sampler(split, config.window, config.seed)
            .preload()
            .map_err(|e| corpus_error(corpus_dir, e))
    };
    let mut sampler = load("train")?;
    if sampler.eligible_clips() == 0 {
        return Err(corpus_error(
            corpus_dir,
            format!("no train clip has {} frames", config.window),
        ));
    }
    let validation = validation_batches(load("val")?, &config, device)?;
    let started = std::time::Instant::now();
    let wall_before = state.wall_s;
    while state.step < config.steps {
        let step = state.step;
        sampler.reseed(batch_seed(config.seed, step));
        let (windows, _) = sampler
            .sample(config.batch)
            .map_err(|e| corpus_error(corpus_dir, e))?;
        let x = Tensor::from_vec(windows, (config.batch, config.window, FEATURES), device)?;
        let (loss, reset) = optimizer_step(
            &mut model,
            &mut optimizer,
            &x,
            schedule.at(step),
            &config,
            step == 0,
        )?;
        state.step += 1;
        state.train_loss = Some(loss);
        let mut report = StepReport {
            step: state.step,
            steps: config.steps,
            loss: state.train_loss.unwrap_or_default(),
            reset,
            val: None,
        };
        let done = state.step == config.steps;
        if state.step % config.eval_every == 0 || done {
            let val = validate(&model, &validation)?;
            state.val = val;
            report.val = val;
            log_line(out, &state, schedule.at(step))?;
        }
        if state.step % config.checkpoint_every == 0 || done {
            state.vq_rng = model.vq_rng_state().unwrap_or(0);
            state.wall_s = wall_before + started.elapsed().as_secs_f64();
            model.save(out)?;
            let stage = resume.stage()?;
            model.save(&stage)?;
            optimizer.save(&stage.join(OPTIMIZER_FILE))?;
            resume.commit(state.step, &state)?;
        }
        on_step(report);
    }
    Ok(state)
}

/// The AdamW optimiser of `model`'s variables with `config`'s settings.
pub fn optimizer_for(model: &MotionTokenizer, config: &TrainConfig) -> AdamW {
    let adam = AdamWConfig {
        beta1: config.beta1,
        beta2: config.beta2,
        eps: 1e-8,
        weight_decay: config.weight_decay,
    };
    AdamW::new(&model.vars().data().lock().expect("var map lock"), adam)
}

/// One training step on normalised windows `x` (batch, frames, 263): forward (EMA update for
/// VQ, codebook initialised from `x` on the first step), loss, backward, AdamW at `lr`.
/// Returns the loss and the number of dead VQ codes reset.
pub fn optimizer_step(
    model: &mut MotionTokenizer,
    optimizer: &mut AdamW,
    x: &Tensor,
    lr: f64,
    config: &TrainConfig,
    first_step: bool,
) -> Result<(f64, usize), TokenizerError> {
    let weights = Tensor::new(&[1f32, config.velocity_weight as f32], x.device())?;
    let reconstruction =
        |motion: &Tensor, x: &Tensor| (reconstruction_losses(motion, x)? * &weights)?.sum_all();
    let (loss, reset, grads) = model.loss_and_grads(x, first_step, reconstruction)?;
    optimizer.step(&grads, lr, config.grad_clip)?;
    Ok((loss, reset))
}

/// Start from scratch, or restore weights, optimiser position and state from `out` when it
/// holds a run of the same spec (anything else there is an error, not silently overwritten).
fn resume_or_start(
    spec: &TrainSpec,
    corpus: &Corpus,
    out: &Path,
    resume: &ResumeFiles,
    device: &Device,
) -> Result<(MotionTokenizer, TrainState), TokenizerError> {
    let spec_path = out.join("train.json");
    let state_path = resume.state_path();
    // The same run may go on on another device.
    check_same_run(&spec_path, "a tokenizer run", |saved: TrainSpec| {
        TrainSpec {
            device: spec.device.clone(),
            ..saved
        } == *spec
    })?;
    if spec_path.exists() && state_path.exists() {
        let state: TrainState = read_json(state_path)?;
        if state.step < spec.train.steps {
            // Training goes on, maybe on another device: the spec names this run's.
            write_json(&spec_path, spec)?;
        }
        truncate_log(out, state.step)?;
        let mut model = MotionTokenizer::load(&resume.files(state.step), device)?;
        model.set_vq_rng_state(state.vq_rng);
        return Ok((model, state));
    }
    std::fs::create_dir_all(out).map_err(|e| corpus_error(out, e.to_string()))?;
    write_json(&spec_path, spec)?;
    let model = MotionTokenizer::new(
        spec.tokenizer.clone(),
        corpus.mean().to_vec(),
        corpus.std().to_vec(),
        device,
        spec.train.seed,
    )?;
    Ok((model, TrainState::default()))
}

/// Fixed validation windows (seeded once), or none when no val clip is long enough.
fn validation_batches(
    mut sampler: ingest::corpus::reader::WindowSampler<'_>,
    config: &TrainConfig,
    device: &Device,
) -> Result<Vec<Tensor>, TokenizerError> {
    if sampler.eligible_clips() == 0 {
        return Ok(Vec::new());
    }
    sampler.reseed(config.seed ^ 0x7a1);
    (0..config.eval_batches)
        .map(|_| {
            let (w, _) = sampler
                .sample(config.batch)
                .map_err(|e| TokenizerError::Argument(e.to_string()))?;
            Ok(Tensor::from_vec(
                w,
                (config.batch, config.window, FEATURES),
                device,
            )?)
        })
        .collect()
}

fn validate(
    model: &MotionTokenizer,
    batches: &[Tensor],
) -> Result<Option<ValLosses>, TokenizerError> {
    if batches.is_empty() {
        return Ok(None);
    }
    let (mut recon, mut velocity, mut l1) = (0f64, 0f64, 0f64);
    for x in batches {
        let motion = model.forward(x)?.motion;
        let l = reconstruction_losses(&motion, x)?.to_vec1::<f32>()?;
        recon += l[0] as f64;
        velocity += l[1] as f64;
        l1 += (&motion - x)?.abs()?.mean_all()?.to_scalar::<f32>()? as f64;
    }
    let n = batches.len() as f64;
    Ok(Some(ValLosses {
        recon: recon / n,
        velocity: velocity / n,
        l1: l1 / n,
    }))
}

/// Drop log lines past `step` (written by a run killed before its next checkpoint).
fn truncate_log(out: &Path, step: u64) -> Result<(), TokenizerError> {
    let path = out.join("log.jsonl");
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok(());
    };
    let kept: String = text
        .lines()
        .filter(|line| {
            serde_json::from_str::<serde_json::Value>(line)
                .ok()
                .and_then(|v| v["step"].as_u64())
                .is_some_and(|s| s <= step)
        })
        .map(|line| format!("{line}\n"))
        .collect();
    motionscale_core::write_atomic(&path, kept.as_bytes())
        .map_err(|e| corpus_error(&path, e.to_string()))
}

fn log_line(out: &Path, state: &TrainState, lr: f64) -> Result<(), TokenizerError> {
    let path = out.join("log.jsonl");
    let line = serde_json::json!({
        "step": state.step,
        "lr": lr,
        "train_loss": state.train_loss,
        "val": state.val,
    });
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .map_err(|e| corpus_error(&path, e.to_string()))?;
    writeln!(file, "{line}").map_err(|e| corpus_error(&path, e.to_string()))
}
