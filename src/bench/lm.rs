//! `motionscale bench train`: the prefix-LM training step (forward, backward, clipped AdamW)
//! and generation with and without the key/value cache, on the layout of
//! `../shared/bench/pytorch_prefix_lm.py` (batch 32, 16 text positions of 384-d embeddings,
//! 64 motion positions, 1024 codes + 3 specials); `--reference` runs that script in the same
//! session and prints the ratios.

use super::lm_step::{
    bench_batch, bench_train_step, parse_size, shape_flags, BenchTrainArgs, CODES, TEXT_DIM,
};
use super::time;
use anyhow::Result;
use candle_core::Device;
use lm::accounting::SequenceShape;
use lm::generate::Sampling;
use lm::prefix_lm::{init_model, PrefixLmConfig};
use serde_json::{json, Value};
use std::process::ExitCode;
use std::time::Instant;

fn bench_generate(args: &BenchTrainArgs) -> Result<Value> {
    let config = PrefixLmConfig::new(256, 4, 4, CODES, TEXT_DIM);
    let (model, _) = init_model(&config, 0, &Device::Cpu)?;
    let mut out = serde_json::Map::new();
    for batch in [1usize, 32] {
        let b = bench_batch(&config, batch, 2)?;
        let texts: Vec<&[f32]> = b.text.chunks(16 * TEXT_DIM).collect();
        for cached in [true, false] {
            let s = Sampling {
                temperature: 0.0,
                max_tokens: SequenceShape::BENCH.motion,
                allow_eos: false,
                kv_cache: cached,
                ..Sampling::default()
            };
            let st = time(1, 3, args.min_time / 2.0, || {
                lm::generate::generate(&model, &texts, &s)?;
                Ok(())
            })?;
            let tps = (batch * s.max_tokens) as f64 / st["median_s"].as_f64().expect("median");
            let key = format!(
                "batch{batch}_{}",
                if cached { "cached" } else { "uncached" }
            );
            out.insert(key, json!({"tokens_per_s": tps, "time": st}));
        }
    }
    Ok(Value::Object(out))
}

fn run_reference(args: &BenchTrainArgs, mode: &str, d: usize, layers: usize) -> Result<Value> {
    let mut flags = shape_flags(d, layers, args.batch);
    flags.extend([
        "--mode".into(),
        mode.into(),
        "--threads".into(),
        args.threads.to_string(),
    ]);
    flags.extend(["--min-time".into(), args.min_time.to_string()]);
    let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
    super::run_reference(&args.reference_script, &flags)
}

/// candle's sgemm on 2048² now, the best of five after a warm-up (context for the MFU
/// figures on a shared machine; not through [`time`], so a profile leaves it out).
fn sgemm_now() -> Result<f64> {
    let a = candle_core::Tensor::ones(
        (2048, 2048),
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    )?;
    let mut best = f64::INFINITY;
    for call in 0..6 {
        let started = Instant::now();
        a.matmul(&a)?;
        if call > 0 {
            best = best.min(started.elapsed().as_secs_f64());
        }
    }
    Ok(2.0 * 2048f64.powi(3) / best / 1e9)
}

/// Run the PyTorch reference of a d×layers training step, print and record the ratio, and the
/// ceiling: the ratio an executor running every FLOP at `peak` would reach.
fn compare_train(
    args: &BenchTrainArgs,
    (d, layers): (usize, usize),
    peak: f64,
    ours: &mut Value,
) -> Result<()> {
    let reference = run_reference(args, "train", d, layers)?;
    let ratio = ours["motion_tokens_per_s"].as_f64().unwrap_or(0.0)
        / reference["motion_tokens_per_s"]
            .as_f64()
            .unwrap_or(f64::NAN);
    let same_flops =
        reference["flops_per_step_exact"].as_f64() == ours["flops_per_step_exact"].as_f64();
    let reference_gflops = reference["achieved_gflops_exact"]
        .as_f64()
        .unwrap_or(f64::NAN);
    // Both sides run the same exact FLOPs, so the rates' ratio is the speed ratio.
    let ceiling = peak / reference_gflops;
    println!(
        "  PyTorch: {:.0} motion tok/s, {reference_gflops:.1} GFLOP/s → ratio {ratio:.2}× (same exact FLOPs per step: {same_flops}; foreign load {:.2}); every FLOP at the peak would be {ceiling:.2}×",
        reference["motion_tokens_per_s"].as_f64().unwrap_or(0.0),
        reference["step_time"]["foreign_cpu_fraction"]
            .as_f64()
            .unwrap_or(f64::NAN),
    );
    ours["reference"] = json!({"motion_tokens_per_s": reference["motion_tokens_per_s"],
        "achieved_gflops_exact": reference["achieved_gflops_exact"],
        "flops_per_step_exact": reference["flops_per_step_exact"], "ratio": ratio,
        "ceiling_ratio_at_peak": ceiling});
    Ok(())
}

/// `motionscale bench train`.
pub fn train(args: BenchTrainArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    if !device.is_cpu() {
        return super::lm_gpu::train(&args, &device);
    }
    let compute = args.compute.compute();
    let (peak, peak_source) = super::machine::mfu_peak(args.peak_gflops);
    let mut report = json!({"peak_gflops": peak, "peak_source": peak_source,
                            "threads": rayon::current_num_threads()});
    let sgemm = sgemm_now()?;
    report["candle_sgemm_2048_gflops"] = json!(sgemm);
    println!(
        "fp32 peak for MFU {peak:.0} GFLOP/s ({peak_source}); candle sgemm 2048³ now {sgemm:.0} GFLOP/s ({:.0}% of it); {} threads",
        100.0 * sgemm / peak,
        rayon::current_num_threads()
    );
    let mut sizes = Vec::new();
    let cpu_sizes = ["256x4".to_string(), "512x8".to_string()];
    let sizes_asked = if args.no_train {
        &[][..]
    } else if args.sizes.is_empty() {
        &cpu_sizes[..]
    } else {
        &args.sizes[..]
    };
    for size in sizes_asked {
        let (d, layers) = parse_size(size)?;
        let shape = (d, layers, args.batch);
        let mut ours = bench_train_step(&args, shape, &device, compute, peak)?;
        let phases = &ours["phase_median_s"];
        println!(
            "train d{d}/{layers}L B{}: {:.0} motion tok/s, {:.1} GFLOP/s exact, MFU {:.1}% ({:.0} ms/step: forward + backward {:.0}, AdamW {:.0}; foreign load {:.2})",
            args.batch,
            ours["motion_tokens_per_s"].as_f64().unwrap_or(0.0),
            ours["achieved_gflops_exact"].as_f64().unwrap_or(0.0),
            100.0 * ours["mfu"].as_f64().unwrap_or(0.0),
            1e3 * ours["step_time"]["median_s"].as_f64().unwrap_or(0.0),
            1e3 * phases["fwd_bwd"].as_f64().unwrap_or(0.0),
            1e3 * phases["opt"].as_f64().unwrap_or(0.0),
            ours["step_time"]["foreign_cpu_fraction"]
                .as_f64()
                .unwrap_or(f64::NAN),
        );
        let cpu = &ours["cpu_time_equivalent"];
        println!(
            "  own CPU time per step / threads: {:.0} ms → {:.0} motion tok/s, {:.1} GFLOP/s if the threads never waited for a busy core",
            1e3 * cpu["step_s"].as_f64().unwrap_or(0.0),
            cpu["motion_tokens_per_s"].as_f64().unwrap_or(0.0),
            cpu["gflops_exact"].as_f64().unwrap_or(0.0),
        );
        if args.reference {
            compare_train(&args, (d, layers), peak, &mut ours)?;
        }
        sizes.push(ours);
    }
    report["train"] = json!(sizes);
    if !args.no_generate {
        let mut gen = bench_generate(&args)?;
        for (key, v) in gen.as_object().expect("object") {
            println!(
                "generate d256/4L {key}: {:.0} tokens/s",
                v["tokens_per_s"].as_f64().unwrap_or(0.0)
            );
        }
        if args.reference {
            let reference = run_reference(&args, "generate", 256, 4)?;
            for batch in ["1", "32"] {
                let r = reference["by_batch"][batch]["tokens_per_s"]
                    .as_f64()
                    .unwrap_or(f64::NAN);
                let ours = gen[format!("batch{batch}_cached")]["tokens_per_s"]
                    .as_f64()
                    .unwrap_or(0.0);
                println!(
                    "  PyTorch cached batch {batch}: {r:.0} tokens/s → ratio {:.2}×",
                    ours / r
                );
                gen[format!("reference_batch{batch}_cached")] = json!(r);
            }
        }
        report["generate"] = gen;
    }
    super::write_json(args.json.as_ref(), &report)?;
    Ok(ExitCode::SUCCESS)
}
