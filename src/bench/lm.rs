//! `motionscale bench train`: the prefix-LM training step (forward, backward, clipped AdamW)
//! and generation with and without the key/value cache, on the layout of
//! `../shared/bench/pytorch_prefix_lm.py` (batch 32, 16 text positions of 384-d embeddings,
//! 64 motion positions, 1024 codes + 3 specials); `--reference` runs that script within the same
//! command and prints the ratios.

use super::lm_step::{
    bench_batch, bench_train_step, parse_size, shape_flags, BenchTrainArgs, TrainStep, CODES,
    TEXT_DIM,
};
use super::{time, Timing};
use anyhow::{Context, Result};
use candle_core::Device;
use lm::accounting::SequenceShape;
use lm::generate::Sampling;
use lm::prefix_lm::{init_model, PrefixLmConfig};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::process::ExitCode;
use std::time::Instant;

/// The figures of `bench train` on the CPU (its `--json`).
#[derive(Debug, Serialize, Deserialize)]
pub struct TrainReport {
    /// The fp32 peak MFU is measured against, GFLOP/s.
    pub peak_gflops: f64,
    /// Where that peak comes from.
    pub peak_source: String,
    /// Threads of the pool.
    pub threads: usize,
    /// candle's sgemm on 2048² now, GFLOP/s.
    pub candle_sgemm_2048_gflops: f64,
    /// Each size's training step (none with `--no-train`).
    pub train: Vec<TrainStep<CpuComparison>>,
    /// Generation (absent with `--no-generate`).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub generate: Option<GenerateFigures>,
}

/// The PyTorch training step beside ours on the CPU.
#[derive(Debug, Serialize, Deserialize)]
pub struct CpuComparison {
    /// Its motion tokens per second.
    pub motion_tokens_per_s: f64,
    /// Its GFLOP/s at the exact count.
    pub achieved_gflops_exact: f64,
    /// Its exact FLOPs of one step.
    pub flops_per_step_exact: f64,
    /// Our motion tokens/s over its.
    pub ratio: f64,
    /// The ratio an executor running every FLOP at the peak would reach.
    pub ceiling_ratio_at_peak: f64,
}

/// Generation of 64 motion tokens by the d256/4L model, greedy, with and without the
/// key/value cache, at batches 1 and 32.
#[derive(Debug, Serialize, Deserialize)]
pub struct GenerateFigures {
    /// Batch 1 with the cache.
    pub batch1_cached: Generation,
    /// Batch 1 without the cache.
    pub batch1_uncached: Generation,
    /// Batch 32 with the cache.
    pub batch32_cached: Generation,
    /// Batch 32 without the cache.
    pub batch32_uncached: Generation,
    /// With `--reference`: PyTorch's tokens/s at batch 1 with its cache.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reference_batch1_cached: Option<f64>,
    /// With `--reference`: PyTorch's tokens/s at batch 32 with its cache.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reference_batch32_cached: Option<f64>,
}

impl GenerateFigures {
    /// Each run with its key, in the order of the JSON.
    fn runs(&self) -> [(&'static str, &Generation); 4] {
        [
            ("batch1_cached", &self.batch1_cached),
            ("batch1_uncached", &self.batch1_uncached),
            ("batch32_cached", &self.batch32_cached),
            ("batch32_uncached", &self.batch32_uncached),
        ]
    }
}

/// One generation run.
#[derive(Debug, Serialize, Deserialize)]
pub struct Generation {
    /// Generated tokens per second (all sequences of the batch).
    pub tokens_per_s: f64,
    /// Wall time of one generation of the batch.
    pub time: Timing,
}

/// What `bench train` reads of `pytorch_prefix_lm.py --mode train`'s output.
#[derive(Debug, Deserialize)]
struct ReferenceTrain {
    motion_tokens_per_s: f64,
    flops_per_step_exact: f64,
    achieved_gflops_exact: f64,
    step_time: ReferenceStepTime,
}

/// The reference's step time (`common.timeit`): its foreign load.
#[derive(Debug, Deserialize)]
struct ReferenceStepTime {
    foreign_cpu_fraction: Option<f64>,
}

/// What `bench train` reads of `pytorch_prefix_lm.py --mode generate`'s output: each batch's
/// tokens/s, keyed by the batch.
#[derive(Debug, Deserialize)]
struct ReferenceGenerate {
    by_batch: BTreeMap<String, ReferenceGenerateBatch>,
}

#[derive(Debug, Deserialize)]
struct ReferenceGenerateBatch {
    tokens_per_s: f64,
}

/// Generation of `batch` sequences by `model`, with or without the cache, timed.
fn bench_generation(
    args: &BenchTrainArgs,
    model: &lm::prefix_lm::PrefixLm,
    texts: &[&[f32]],
    cached: bool,
) -> Result<Generation> {
    let s = Sampling {
        temperature: 0.0,
        max_tokens: SequenceShape::BENCH.motion,
        allow_eos: false,
        kv_cache: cached,
        ..Sampling::default()
    };
    let st = time(1, 3, args.min_time / 2.0, || {
        lm::generate::generate(model, texts, &s)?;
        Ok(())
    })?;
    Ok(Generation {
        tokens_per_s: (texts.len() * s.max_tokens) as f64 / st.median_s,
        time: st,
    })
}

fn bench_generate(args: &BenchTrainArgs) -> Result<GenerateFigures> {
    let config = PrefixLmConfig::new(256, 4, 4, CODES, TEXT_DIM);
    let (model, _) = init_model(&config, 0, &Device::Cpu)?;
    let mut runs = Vec::new();
    for batch in [1usize, 32] {
        let b = bench_batch(&config, batch, 2)?;
        let texts: Vec<&[f32]> = b.text.chunks(16 * TEXT_DIM).collect();
        for cached in [true, false] {
            runs.push(bench_generation(args, &model, &texts, cached)?);
        }
    }
    let [batch1_cached, batch1_uncached, batch32_cached, batch32_uncached] =
        <[Generation; 4]>::try_from(runs).expect("four runs");
    Ok(GenerateFigures {
        batch1_cached,
        batch1_uncached,
        batch32_cached,
        batch32_uncached,
        reference_batch1_cached: None,
        reference_batch32_cached: None,
    })
}

fn run_reference<T: DeserializeOwned>(
    args: &BenchTrainArgs,
    mode: &str,
    d: usize,
    layers: usize,
) -> Result<T> {
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
    ours: &mut TrainStep<CpuComparison>,
) -> Result<()> {
    let reference: ReferenceTrain = run_reference(args, "train", d, layers)?;
    let ratio = ours.motion_tokens_per_s / reference.motion_tokens_per_s;
    let same_flops = reference.flops_per_step_exact == ours.flops_per_step_exact;
    let reference_gflops = reference.achieved_gflops_exact;
    // Both sides run the same exact FLOPs, so the rates' ratio is the speed ratio.
    let ceiling = peak / reference_gflops;
    println!(
        "  PyTorch: {:.0} motion tok/s, {reference_gflops:.1} GFLOP/s → ratio {ratio:.2}× (same exact FLOPs per step: {same_flops}; foreign load {:.2}); every FLOP at the peak would be {ceiling:.2}×",
        reference.motion_tokens_per_s,
        reference.step_time.foreign_cpu_fraction.unwrap_or(f64::NAN),
    );
    ours.reference = Some(CpuComparison {
        motion_tokens_per_s: reference.motion_tokens_per_s,
        achieved_gflops_exact: reference.achieved_gflops_exact,
        flops_per_step_exact: reference.flops_per_step_exact,
        ratio,
        ceiling_ratio_at_peak: ceiling,
    });
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
    let sgemm = sgemm_now()?;
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
        ours.peak_gflops = super::machine::peak_around(peak, args.peak_gflops.is_some());
        ours.mfu = super::machine::mfu(ours.achieved_gflops_exact, ours.peak_gflops);
        let phases = &ours.phase_median_s;
        println!(
            "train d{d}/{layers}L B{}: {:.0} motion tok/s, {:.1} GFLOP/s exact, MFU {} against {:.0} GFLOP/s ({:.0} ms/step: forward + backward {:.0}, AdamW {:.0}; foreign load {:.2})",
            args.batch,
            ours.motion_tokens_per_s,
            ours.achieved_gflops_exact,
            super::machine::mfu_text(ours.mfu),
            ours.peak_gflops,
            1e3 * ours.step_time.median_s,
            1e3 * phases.fwd_bwd,
            1e3 * phases.opt,
            ours.step_time.foreign_cpu_fraction.unwrap_or(f64::NAN),
        );
        let cpu = &ours.cpu_time_equivalent;
        println!(
            "  own CPU time per step / threads: {:.0} ms → {:.0} motion tok/s, {:.1} GFLOP/s if the threads never waited for a busy core",
            1e3 * cpu.step_s,
            cpu.motion_tokens_per_s,
            cpu.gflops_exact,
        );
        if args.reference {
            compare_train(&args, (d, layers), peak, &mut ours)?;
        }
        sizes.push(ours);
    }
    let mut generate = None;
    if !args.no_generate {
        let mut gen = bench_generate(&args)?;
        for (key, v) in gen.runs() {
            println!("generate d256/4L {key}: {:.0} tokens/s", v.tokens_per_s);
        }
        if args.reference {
            let reference: ReferenceGenerate = run_reference(&args, "generate", 256, 4)?;
            for batch in ["1", "32"] {
                let r = reference
                    .by_batch
                    .get(batch)
                    .with_context(|| {
                        format!(
                            "reading the output of {}: no by_batch {batch:?}",
                            args.reference_script.display()
                        )
                    })?
                    .tokens_per_s;
                let (ours, slot) = match batch {
                    "1" => (&gen.batch1_cached, &mut gen.reference_batch1_cached),
                    _ => (&gen.batch32_cached, &mut gen.reference_batch32_cached),
                };
                println!(
                    "  PyTorch cached batch {batch}: {r:.0} tokens/s → ratio {:.2}×",
                    ours.tokens_per_s / r
                );
                *slot = Some(r);
            }
        }
        generate = Some(gen);
    }
    let report = TrainReport {
        peak_gflops: peak,
        peak_source,
        threads: rayon::current_num_threads(),
        candle_sgemm_2048_gflops: sgemm,
        train: sizes,
        generate,
    };
    super::write_json(args.json.as_ref(), &report)?;
    Ok(ExitCode::SUCCESS)
}
