//! `motionscale bench train`: the prefix-LM training step (forward, backward, clipped AdamW)
//! and generation with and without the key/value cache, on the layout of
//! `../shared/bench/pytorch_prefix_lm.py` (batch 32, 16 text positions of 384-d embeddings,
//! 64 motion positions, 1024 codes + 3 specials); `--reference` runs that script in the same
//! session and prints the ratios.

use super::time;
use anyhow::{Context, Result};
use candle_core::Device;
use lm::accounting::{self, SequenceShape};
use lm::generate::Sampling;
use lm::prefix_lm::{
    init_model, record_stage_times, stage_times, Compute, Executor, LmBatch, PrefixLmConfig,
};
use nn::optim::{AdamW, AdamWConfig};
use serde_json::{json, Value};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

/// Motion codes of the benchmark model (the reference's N_CODES).
const CODES: usize = 1024;
/// Text embedding width (the reference's PREFIX_DIM).
const TEXT_DIM: usize = 384;

/// Arguments of `motionscale bench train`.
#[derive(clap::Args, Debug)]
pub struct BenchTrainArgs {
    /// Model sizes as WIDTHxLAYERS (heads of width 64), on a GPU WIDTHxLAYERS@BATCH (default:
    /// 256x4,512x8 on the CPU; ScaMo's 512x8@256,1024x24@128 on a GPU).
    #[arg(long, value_delimiter = ',')]
    pub sizes: Vec<String>,
    /// Sequences per training step.
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    /// Untimed warm-up steps.
    #[arg(long, default_value_t = 2)]
    pub warmup: usize,
    /// Timed steps (at least; more until --min-time seconds).
    #[arg(long, default_value_t = 5)]
    pub reps: usize,
    /// Seconds of timed work per measurement.
    #[arg(long, default_value_t = 3.0)]
    pub min_time: f64,
    /// fp32 peak for MFU in GFLOP/s [default: this machine's FMA peak, measured at the start].
    #[arg(long)]
    pub peak_gflops: Option<f64>,
    /// Also run the PyTorch reference and print the ratios.
    #[arg(long)]
    pub reference: bool,
    /// The PyTorch reference script.
    #[arg(long, default_value = "../shared/bench/pytorch_prefix_lm.py")]
    pub reference_script: PathBuf,
    /// Threads the reference uses (ours: all cores, or RAYON_NUM_THREADS).
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Skip the generation benchmark.
    #[arg(long)]
    pub no_generate: bool,
    /// Skip the training steps (generation only).
    #[arg(long, conflicts_with = "no_generate")]
    pub no_train: bool,
    /// Write all figures as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Where the model trains (on a GPU: the ScaMo shapes beside
    /// `--gpu-reference-script`, see `bench::lm_gpu`).
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Executor and precision (on a GPU the default precision is bf16, as the reference's).
    #[command(flatten)]
    pub compute: crate::lm_cmd::ComputeArgs,
    /// The PyTorch reference on a GPU (eager bf16 and `torch.compile`).
    #[arg(long, default_value = "../shared/bench/gpu/pytorch_prefix_lm_gpu.py")]
    pub gpu_reference_script: PathBuf,
}

pub(super) fn parse_size(s: &str) -> Result<(usize, usize)> {
    let (d, l) = s.split_once('x').context("sizes look like 512x8")?;
    Ok((d.trim().parse()?, l.trim().parse()?))
}

/// The reference's batch: random text embeddings and 64 random codes per sequence.
fn bench_batch(config: &PrefixLmConfig, batch: usize, seed: u64) -> Result<LmBatch> {
    let mut rng = motionscale_core::rng::SplitMix64(seed);
    let seq = SequenceShape::BENCH;
    let texts: Vec<Vec<f32>> = (0..batch)
        .map(|_| {
            (0..seq.prefix * TEXT_DIM)
                .map(|_| rng.range(-1.7, 1.7) as f32)
                .collect()
        })
        .collect();
    let motions: Vec<Vec<u32>> = (0..batch)
        .map(|_| (0..seq.motion).map(|_| rng.index(CODES) as u32).collect())
        .collect();
    let texts: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
    let motions: Vec<(&[u32], bool)> = motions.iter().map(|m| (m.as_slice(), false)).collect();
    Ok(LmBatch::new(config, &texts, &motions))
}

/// One AdamW training step of a d×layers model at `batch` on `device`, timed; the figures
/// as JSON (the MFU against `peak_gflops`).
pub(super) fn bench_train_step(
    args: &BenchTrainArgs,
    (d, layers, batch): (usize, usize, usize),
    device: &Device,
    compute: Compute,
    peak_gflops: f64,
) -> Result<Value> {
    let config = PrefixLmConfig::new(d, layers, d / 64, CODES, TEXT_DIM);
    let (model, varmap) = init_model(&config, 0, device)?;
    let model = model.with_compute(compute);
    let vars = varmap.data().lock().expect("varmap lock").clone();
    let mut opt = AdamW::new(
        &vars,
        AdamWConfig {
            beta1: 0.9,
            beta2: 0.95,
            eps: 1e-8,
            weight_decay: 0.1,
        },
    );
    let lm_batch = bench_batch(&config, batch, 1)?;
    nn::device::gpu_peak_allocated(device)?;
    let mut phases = [Vec::new(), Vec::new()];
    let st = time(args.warmup, args.reps, args.min_time, || {
        let t0 = Instant::now();
        let (_, grads) = model.loss_and_grads(&lm_batch)?;
        device.synchronize()?;
        let t1 = Instant::now();
        opt.step(&grads, 3e-4, Some(1.0))?;
        device.synchronize()?;
        let t2 = Instant::now();
        for (p, (a, b)) in phases.iter_mut().zip([(t0, t1), (t1, t2)]) {
            p.push((b - a).as_secs_f64());
        }
        Ok(())
    })?;
    let median = |v: &mut Vec<f64>| {
        let v = &mut v[args.warmup..];
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let [fwd_bwd, optim] = phases.each_mut().map(median);
    let peak_gib = nn::device::gpu_peak_allocated(device)?.map(|b| b as f64 / (1u64 << 30) as f64);
    // On a GPU, the forward pass alone (motion logits), for the forward/backward split.
    let forward = match device.is_cuda() {
        true => {
            let mut times = Vec::new();
            for _ in 0..args.warmup + args.reps.max(3) {
                let t0 = Instant::now();
                model.forward(&lm_batch)?;
                device.synchronize()?;
                times.push(t0.elapsed().as_secs_f64());
            }
            Some(median(&mut times))
        }
        false => None,
    };
    // The fused executor's stages, each ended by a synchronisation (so apart from the timing
    // above): where a GPU step spends its time.
    let stages = match device.is_cuda() && model.executor()? == Executor::Fused {
        true => {
            record_stage_times(true);
            for _ in 0..args.reps.max(3) {
                model.loss_and_grads(&lm_batch)?;
            }
            let stages: serde_json::Map<String, Value> = stage_times()
                .into_iter()
                .map(|(k, ms)| (k, json!(ms)))
                .collect();
            record_stage_times(false);
            Some(stages)
        }
        false => None,
    };
    let step_s = st["median_s"].as_f64().expect("median");
    let flops = batch as f64 * accounting::train_flops_exact(&config, SequenceShape::BENCH);
    let six_n =
        batch as f64 * SequenceShape::BENCH.motion as f64 * accounting::flops_6n_per_token(&config);
    let tokens = (batch * SequenceShape::BENCH.motion) as f64;
    let gflops = flops / step_s / 1e9;
    let params = accounting::param_count(&config);
    // On a busy machine: the step time if this process's CPU time were spread over all
    // threads without waiting (a lower bound of a quiet run's time; 0 when unmeasured).
    let cpu_bound_s =
        st["own_cpu_s_per_call"].as_f64().unwrap_or(0.0) / rayon::current_num_threads() as f64;
    Ok(json!({
        "d_model": d, "n_layers": layers, "n_heads": d / 64, "ffn_hidden": config.ffn_hidden,
        "vocab": config.vocab_size(), "batch": batch, "n_nv": params.n_nv, "n_v": params.n_v,
        "device": nn::device::device_name(device), "precision": compute.precision.to_string(),
        "executor": format!("{:?}", model.executor()?).to_lowercase(),
        "step_time": st, "phase_median_s": {"fwd_bwd": fwd_bwd, "opt": optim, "fwd": forward},
        "fused_stage_ms": stages,
        "motion_tokens_per_s": tokens / step_s, "peak_gpu_memory_allocated_gib": peak_gib,
        "flops_per_step_exact": flops, "flops_per_step_6N": six_n,
        "achieved_gflops_exact": gflops, "mfu": gflops / peak_gflops,
        "cpu_time_equivalent": {"step_s": cpu_bound_s, "motion_tokens_per_s": tokens / cpu_bound_s,
                                "gflops_exact": flops / cpu_bound_s / 1e9},
    }))
}

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

/// The PyTorch references' flags of a d×layers model (heads of width 64) at `batch`.
pub(super) fn shape_flags(d: usize, layers: usize, batch: usize) -> Vec<String> {
    [
        ("--d", d),
        ("--layers", layers),
        ("--heads", d / 64),
        ("--batch", batch),
    ]
    .iter()
    .flat_map(|(flag, v)| [flag.to_string(), v.to_string()])
    .collect()
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
