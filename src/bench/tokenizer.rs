//! `motionscale bench tokenizer`: training steps/s of the T2M-GPT-shape tokenizer (width 512,
//! 64-frame windows of 263 features) for FSQ and VQ, and with `--reference` the same step of
//! `shared/bench/pytorch_vqvae.py` run by the same command, alternating, with the ratio.
//!
//! FLOPs follow the reference's rule: (conv + linear multiply-accumulates of one forward) × 2
//! × 3; the VQ distance matmul (no gradient) is not counted, as there.

use crate::device_args::DeviceArgs;
use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use nn::device::device_name;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::process::ExitCode;
use tokenizer::model::{MotionTokenizer, TokenizerConfig, FEATURES};
use tokenizer::train::{optimizer_for, optimizer_step, TrainConfig};
use tokenizer::{Bound, ConvConfig};

/// Arguments of `motionscale bench tokenizer`.
#[derive(clap::Args, Debug)]
pub struct BenchTokenizerArgs {
    /// Batch sizes to time (windows per step).
    #[arg(long, value_delimiter = ',', default_value = "256,64")]
    pub batches: Vec<usize>,
    /// Quantizers to time.
    #[arg(long, value_delimiter = ',', default_value = "fsq,vq")]
    pub quantizers: Vec<String>,
    /// Untimed steps first.
    #[arg(long, default_value_t = 2)]
    pub warmup: usize,
    /// Timed steps (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub reps: usize,
    /// Also run shared/bench/pytorch_vqvae.py (needs torch) and print the ratio; on a GPU,
    /// --gpu-reference-script on the same GPU.
    #[arg(long)]
    pub reference: bool,
    /// The PyTorch reference on a GPU (the same model, imported from --bench-dir).
    #[arg(long, default_value = "scripts/pytorch_vqvae_gpu.py")]
    pub gpu_reference_script: PathBuf,
    /// Folder of the PyTorch reference scripts.
    #[arg(long, default_value = "../shared/bench")]
    pub bench_dir: PathBuf,
    /// fp32 peak in GFLOP/s [default: this machine's FMA peak, measured at the start].
    #[arg(long)]
    pub peak_gflops: Option<f64>,
    /// Also write the figures as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Where the tokenizer trains.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// One timed configuration.
struct Timing {
    steps_per_s: f64,
    flops_per_step: f64,
}

/// The figures of one quantizer and batch of `bench tokenizer` (its `--json` lists them under
/// `figures`).
#[derive(Debug, Serialize, Deserialize)]
pub struct TokenizerFigure {
    /// What was timed: "tokenizer training step".
    pub what: String,
    /// `fsq` or `vq`.
    pub quantizer: String,
    /// Windows per step.
    pub batch: usize,
    /// Where the tokenizer trained.
    pub device: String,
    /// Threads of the pool.
    pub threads: usize,
    /// Our training steps per second.
    pub steps_per_s: f64,
    /// Our GFLOP/s at the reference's FLOP count.
    pub gflops: f64,
    /// The reference's FLOP count of one step.
    pub flops_per_step: f64,
    /// With `--reference`: PyTorch's rate.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reference: Option<TokenizerReferenceFigure>,
    /// With `--reference`: our steps/s over PyTorch's.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub ratio: Option<f64>,
}

/// PyTorch's rate at one quantizer and batch.
#[derive(Debug, Serialize, Deserialize)]
pub struct TokenizerReferenceFigure {
    /// Its training steps per second.
    pub steps_per_s: f64,
    /// Its GFLOP/s at its own FLOP count.
    pub gflops: f64,
}

/// The output of `pytorch_vqvae.py` (and `scripts/pytorch_vqvae_gpu.py`) this bench reads.
#[derive(Debug, Serialize, Deserialize)]
pub struct VqvaeReference {
    /// Training steps per second.
    pub steps_per_s: f64,
    /// Its FLOP count of one step (conv + linear multiply-accumulates × 6).
    pub model_flops_per_step: f64,
}

/// The reference's shapes: FSQ [8,5,5,5] (1000 codes), VQ 512 codes × 512.
fn reference_config(quantizer: &str) -> Result<TokenizerConfig> {
    let conv = ConvConfig::default();
    Ok(match quantizer {
        "fsq" => TokenizerConfig::new("fsq", 1024, Bound::Tanh, conv)?,
        "vq" => TokenizerConfig::new("vq", 512, Bound::Tanh, conv)?,
        other => bail!("unknown quantizer {other:?}"),
    })
}

fn time_ours(
    quantizer: &str,
    batch: usize,
    args: &BenchTokenizerArgs,
    device: &Device,
) -> Result<Timing> {
    let config = reference_config(quantizer)?;
    let conv = config.conv.clone();
    let mut model =
        MotionTokenizer::new(config, vec![0.0; FEATURES], vec![1.0; FEATURES], device, 0)?;
    let train = TrainConfig {
        lr: 2e-4,
        ..TrainConfig::default()
    };
    let mut optimizer = optimizer_for(&model, &train);
    let x = Tensor::randn(0f32, 1.0, (batch, train.window, FEATURES), device)?;
    let mut step = 0;
    let timing = super::time(args.warmup, args.reps, 0.0, || {
        optimizer_step(&mut model, &mut optimizer, &x, train.lr, &train, step == 0)?;
        step += 1;
        // A GPU queues the update: the step ends when it has run.
        Ok(device.synchronize()?)
    })?;
    let median = timing.median_s;
    // FSQ's two projections are the reference's "linear" MACs.
    let linear = if quantizer == "fsq" {
        2 * (batch * train.window / conv.downsample_factor()) as u64 * conv.code_dim as u64 * 4
    } else {
        0
    };
    let macs = batch as u64 * conv.forward_macs(train.window) + linear;
    Ok(Timing {
        steps_per_s: 1.0 / median,
        flops_per_step: macs as f64 * 6.0,
    })
}

fn time_reference(
    quantizer: &str,
    batch: usize,
    args: &BenchTokenizerArgs,
    device: &Device,
) -> Result<Timing> {
    let (batch, warmup, reps) = (
        batch.to_string(),
        args.warmup.to_string(),
        args.reps.to_string(),
    );
    let bench_dir = args
        .bench_dir
        .to_str()
        .context("--bench-dir is not UTF-8")?;
    let mut flags = vec![
        "--quant", quantizer, "--batch", &batch, "--warmup", &warmup, "--reps", &reps,
    ];
    let script = if device.is_cpu() {
        flags.extend(["--threads", "2"]);
        args.bench_dir.join("pytorch_vqvae.py")
    } else {
        flags.extend(["--bench-dir", bench_dir]);
        args.gpu_reference_script.clone()
    };
    let theirs: VqvaeReference = super::run_reference(&script, &flags)?;
    Ok(Timing {
        steps_per_s: theirs.steps_per_s,
        flops_per_step: theirs.model_flops_per_step,
    })
}

/// `motionscale bench tokenizer`.
pub fn bench_tokenizer(args: BenchTokenizerArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    // The CPU's peak: on a GPU the share of it would mean nothing.
    let peak = device
        .is_cpu()
        .then(|| super::machine::mfu_peak(args.peak_gflops));
    println!(
        "tokenizer training step, width 512, 64 × 263 windows, {}, {} threads{}",
        device_name(&device),
        rayon::current_num_threads(),
        peak.as_ref()
            .map(|(gflops, source)| format!(", fp32 peak {gflops:.0} GFLOP/s ({source})"))
            .unwrap_or_default(),
    );
    // Both sides count the reference's FLOPs (every conv's multiply-adds × 6); our Winograd
    // convolutions run fewer, so our rate can pass the peak.
    println!("GFLOP/s at the reference's FLOP count (nominal)");
    let mut figures = Vec::new();
    for quantizer in &args.quantizers {
        for &batch in &args.batches {
            let ours = time_ours(quantizer, batch, &args, &device)?;
            let gflops = ours.flops_per_step * ours.steps_per_s / 1e9;
            let mut line = format!(
                "{quantizer} batch {batch:>3}: {:.3} steps/s, {:.0} frames/s, {:.0} nominal GFLOP/s{}",
                ours.steps_per_s,
                ours.steps_per_s * (batch * 64) as f64,
                gflops,
                peak.as_ref()
                    .map(|(p, _)| format!(" ({:.0}% of peak)", 100.0 * gflops / p))
                    .unwrap_or_default(),
            );
            let mut figure = TokenizerFigure {
                what: "tokenizer training step".into(),
                quantizer: quantizer.clone(),
                batch,
                device: device_name(&device),
                threads: rayon::current_num_threads(),
                steps_per_s: ours.steps_per_s,
                gflops,
                flops_per_step: ours.flops_per_step,
                reference: None,
                ratio: None,
            };
            if args.reference {
                let theirs = time_reference(quantizer, batch, &args, &device)?;
                if (theirs.flops_per_step / ours.flops_per_step - 1.0).abs() > 1e-6 {
                    bail!(
                        "FLOP counts differ: ours {} vs PyTorch {} per step",
                        ours.flops_per_step,
                        theirs.flops_per_step
                    );
                }
                let ratio = ours.steps_per_s / theirs.steps_per_s;
                line.push_str(&format!(
                    "; PyTorch {:.3} steps/s → ratio {ratio:.2}×",
                    theirs.steps_per_s
                ));
                figure.reference = Some(TokenizerReferenceFigure {
                    steps_per_s: theirs.steps_per_s,
                    gflops: theirs.flops_per_step * theirs.steps_per_s / 1e9,
                });
                figure.ratio = Some(ratio);
            }
            println!("{line}");
            figures.push(figure);
        }
    }
    super::write_json(args.json.as_ref(), &figures)?;
    Ok(ExitCode::SUCCESS)
}
