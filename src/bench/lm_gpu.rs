//! `motionscale bench train --device cuda`: the prefix-LM training step on a GPU at ScaMo's
//! shapes (44M: d512, 8 layers, batch 256; 343M: d1024, 24 layers, batch 128; `--sizes
//! WIDTHxLAYERS@BATCH,…` for others), and with `--reference` the PyTorch reference
//! `../shared/bench/gpu/pytorch_prefix_lm_gpu.py` on the same GPU in the same run, eager bf16
//! and `torch.compile`, with both ratios.

use super::lm_step::{bench_train_step, parse_size, shape_flags, BenchTrainArgs, TrainStep};
use anyhow::{bail, Context, Result};
use candle_core::Device;
use nn::device::Precision;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::path::Path;
use std::process::ExitCode;

/// ScaMo's 44M and 343M shapes at the batches of `../shared/bench/gpu/README.md`.
const SCAMO_SHAPES: [(usize, usize, usize); 2] = [(512, 8, 256), (1024, 24, 128)];

/// H100/H200 dense bf16 tensor-core peak in GFLOP/s (the reference's MFU denominator).
const BF16_PEAK_GFLOPS: f64 = 989e3;

/// The figures of `bench train` on a GPU (its `--json`).
#[derive(Debug, Serialize, Deserialize)]
pub struct GpuTrainReport {
    /// Each shape's training step.
    pub train: Vec<TrainStep<GpuComparisons>>,
}

/// The PyTorch reference beside our step on the same GPU: eager bf16 and `torch.compile`.
#[derive(Debug, Serialize, Deserialize)]
pub struct GpuComparisons {
    /// Eager bf16.
    pub eager: GpuComparison,
    /// `torch.compile`.
    pub compiled: GpuComparison,
}

/// One run of the GPU reference and our ratio to it.
#[derive(Debug, Serialize, Deserialize)]
pub struct GpuComparison {
    /// The reference's JSON line.
    pub result: GpuReference,
    /// Our motion tokens/s over its.
    pub ratio: f64,
}

/// The JSON line of `pytorch_prefix_lm_gpu.py` (a training run): what this bench reads typed,
/// the rest kept as it wrote it.
#[derive(Debug, Serialize, Deserialize)]
pub struct GpuReference {
    /// Motion tokens per second.
    pub motion_tokens_per_s: f64,
    /// MFU at the exact FLOP count against the GPU's bf16 peak.
    pub mfu_exact: f64,
    /// torch's version.
    pub torch_version: String,
    /// Peak memory allocated, GiB (written on CUDA only).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub peak_mem_allocated_gib: Option<f64>,
    /// The rest of its output.
    #[serde(flatten)]
    pub other: serde_json::Map<String, Value>,
}

/// The shapes to time: `--sizes` with `@BATCH` suffixes when given, else ScaMo's two.
fn shapes(args: &BenchTrainArgs) -> Result<Vec<(usize, usize, usize)>> {
    if args.sizes.is_empty() {
        return Ok(SCAMO_SHAPES.to_vec());
    }
    args.sizes
        .iter()
        .map(|s| {
            let (shape, batch) = s.split_once('@').unwrap_or((s, ""));
            let (d, layers) = parse_size(shape)?;
            let batch = match batch {
                "" => args.batch,
                b => b.parse().with_context(|| format!("batch of {s:?}"))?,
            };
            Ok((d, layers, batch))
        })
        .collect()
}

/// The reference's JSON line (its last line of output) for one shape.
fn reference(
    script: &Path,
    (d, layers, batch): (usize, usize, usize),
    compile: bool,
) -> Result<GpuReference> {
    let mut command = std::process::Command::new("python3");
    command
        .arg(script)
        .args(shape_flags(d, layers, batch))
        .args([
            "--device",
            "cuda",
            "--dtype",
            "bf16",
            "--vocab-codes",
            "1024",
            "--phases",
        ]);
    if compile {
        command.arg("--compile");
    }
    let out = command
        .output()
        .with_context(|| format!("running python3 {}", script.display()))?;
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .rev()
        .find(|l| l.trim_start().starts_with('{'))
        .with_context(|| format!("{} printed no JSON ({})", script.display(), out.status))?;
    let value: Value = serde_json::from_str(line)
        .with_context(|| format!("reading the output of {}", script.display()))?;
    if let Some(e) = value.get("error") {
        bail!("{}: {e}", script.display());
    }
    super::reference_output(script, line.as_bytes())
}

/// `motionscale bench train` on a GPU.
pub fn train(args: &BenchTrainArgs, device: &Device) -> Result<ExitCode> {
    let compute = args.compute.compute_or(Precision::Bf16);
    let mut rows = Vec::new();
    for shape @ (d, layers, batch) in shapes(args)? {
        let mut ours: TrainStep<GpuComparisons> =
            bench_train_step(args, shape, device, compute, BF16_PEAK_GFLOPS)?;
        let ours_tps = ours.motion_tokens_per_s;
        let phases = &ours.phase_median_s;
        println!(
            "train d{d}/{layers}L B{batch} on {} ({}, {} executor): {ours_tps:.0} motion tok/s, MFU {} ({:.1} ms/step: forward + backward {:.1} (forward alone {:.1}), AdamW {:.1}); peak memory allocated {:.2} GiB",
            ours.device,
            compute.precision,
            ours.executor,
            super::machine::mfu_text(ours.mfu),
            1e3 * ours.step_time.median_s,
            1e3 * phases.fwd_bwd,
            1e3 * phases.fwd.unwrap_or(f64::NAN),
            1e3 * phases.opt,
            ours.peak_gpu_memory_allocated_gib.unwrap_or(f64::NAN),
        );
        if let Some(stages) = &ours.gpu_stage_ms {
            let parts: Vec<String> = stages
                .iter()
                .map(|(k, ms)| format!("{k} {ms:.1}"))
                .collect();
            println!(
                "  stages, ms per step (each synchronised): {}",
                parts.join("; ")
            );
        }
        if args.reference {
            let compare = |name: &str, compile: bool| -> Result<GpuComparison> {
                let r = reference(&args.gpu_reference_script, shape, compile)?;
                let tps = r.motion_tokens_per_s;
                let mem = r.peak_mem_allocated_gib.unwrap_or(f64::NAN);
                println!(
                    "  PyTorch {} bf16 {name}: {tps:.0} motion tok/s, MFU {:.1}%, peak memory {mem:.2} GiB → ours {:.2}×",
                    r.torch_version,
                    100.0 * r.mfu_exact,
                    ours_tps / tps
                );
                Ok(GpuComparison {
                    result: r,
                    ratio: ours_tps / tps,
                })
            };
            let eager = compare("eager", false)?;
            let compiled = compare("compiled", true)?;
            ours.reference = Some(GpuComparisons { eager, compiled });
        }
        rows.push(ours);
    }
    super::write_json(args.json.as_ref(), &GpuTrainReport { train: rows })?;
    Ok(ExitCode::SUCCESS)
}
