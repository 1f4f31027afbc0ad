//! `motionscale bench train --device cuda`: the prefix-LM training step on a GPU at ScaMo's
//! shapes (44M: d512, 8 layers, batch 256; 343M: d1024, 24 layers, batch 128; `--sizes
//! WIDTHxLAYERS@BATCH,…` for others), and with `--reference` the PyTorch reference
//! `../shared/bench/gpu/pytorch_prefix_lm_gpu.py` on the same GPU in the same run, eager bf16
//! and `torch.compile`, with both ratios.

use super::lm_step::{bench_train_step, parse_size, shape_flags, BenchTrainArgs};
use anyhow::{bail, Context, Result};
use candle_core::Device;
use nn::device::Precision;
use serde_json::{json, Value};
use std::path::Path;
use std::process::ExitCode;

/// ScaMo's 44M and 343M shapes at the batches of `../shared/bench/gpu/README.md`.
const SCAMO_SHAPES: [(usize, usize, usize); 2] = [(512, 8, 256), (1024, 24, 128)];

/// H100/H200 dense bf16 tensor-core peak in GFLOP/s (the reference's MFU denominator).
const BF16_PEAK_GFLOPS: f64 = 989e3;

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
) -> Result<Value> {
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
    let value: Value = serde_json::from_str(line)?;
    if let Some(e) = value.get("error") {
        bail!("{}: {e}", script.display());
    }
    Ok(value)
}

/// `motionscale bench train` on a GPU.
pub fn train(args: &BenchTrainArgs, device: &Device) -> Result<ExitCode> {
    let compute = args.compute.compute_or(Precision::Bf16);
    let mut rows = Vec::new();
    for shape @ (d, layers, batch) in shapes(args)? {
        let mut ours = bench_train_step(args, shape, device, compute, BF16_PEAK_GFLOPS)?;
        let ours_tps = ours["motion_tokens_per_s"].as_f64().unwrap_or(0.0);
        let phases = &ours["phase_median_s"];
        println!(
            "train d{d}/{layers}L B{batch} on {} ({}, {} executor): {ours_tps:.0} motion tok/s, MFU {:.1}% ({:.1} ms/step: forward + backward {:.1} (forward alone {:.1}), AdamW {:.1}); peak memory allocated {:.2} GiB",
            ours["device"].as_str().unwrap_or("?"),
            compute.precision,
            ours["executor"].as_str().unwrap_or("?"),
            100.0 * ours["mfu"].as_f64().unwrap_or(0.0),
            1e3 * ours["step_time"]["median_s"].as_f64().unwrap_or(0.0),
            1e3 * phases["fwd_bwd"].as_f64().unwrap_or(0.0),
            1e3 * phases["fwd"].as_f64().unwrap_or(f64::NAN),
            1e3 * phases["opt"].as_f64().unwrap_or(0.0),
            ours["peak_gpu_memory_allocated_gib"].as_f64().unwrap_or(f64::NAN),
        );
        if let Some(stages) = ours["fused_stage_ms"].as_object() {
            let parts: Vec<String> = stages
                .iter()
                .map(|(k, ms)| format!("{k} {:.1}", ms.as_f64().unwrap_or(f64::NAN)))
                .collect();
            println!(
                "  stages, ms per step (each synchronised): {}",
                parts.join("; ")
            );
        }
        if args.reference {
            let mut refs = serde_json::Map::new();
            for (name, compile) in [("eager", false), ("compiled", true)] {
                let r = reference(&args.gpu_reference_script, shape, compile)?;
                let tps = r["motion_tokens_per_s"].as_f64().unwrap_or(f64::NAN);
                let mem = r["peak_mem_allocated_gib"].as_f64().unwrap_or(f64::NAN);
                println!(
                    "  PyTorch {} bf16 {name}: {tps:.0} motion tok/s, MFU {:.1}%, peak memory {mem:.2} GiB → ours {:.2}×",
                    r["torch_version"].as_str().unwrap_or("?"),
                    100.0 * r["mfu_exact"].as_f64().unwrap_or(f64::NAN),
                    ours_tps / tps
                );
                refs.insert(name.into(), json!({"result": r, "ratio": ours_tps / tps}));
            }
            ours["reference"] = Value::Object(refs);
        }
        rows.push(ours);
    }
    super::write_json(args.json.as_ref(), &json!({"train": rows}))?;
    Ok(ExitCode::SUCCESS)
}
