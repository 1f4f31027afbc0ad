//! What `motionscale bench train` times on any device: its arguments, the reference's batch
//! and one timed training step of the prefix LM ([`bench_train_step`]), and the PyTorch
//! references' shape flags. [`super::lm`] times it on the CPU, [`super::lm_gpu`] on a GPU.

use super::stage_timer::stage_ms;
use super::time;
use anyhow::{Context, Result};
use candle_core::Device;
use lm::accounting::{self, SequenceShape};
use lm::prefix_lm::{init_model, Compute, Executor, LmBatch, PrefixLmConfig};
use nn::optim::{AdamW, AdamWConfig};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

/// Motion codes of the benchmark model (the reference's N_CODES).
pub(super) const CODES: usize = 1024;
/// Text embedding width (the reference's PREFIX_DIM).
pub(super) const TEXT_DIM: usize = 384;

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

/// The figures of one timed training step of the prefix LM ([`bench_train_step`]), with the
/// reference beside it (`R`: the CPU's [`super::lm::CpuComparison`], a GPU's
/// [`super::lm_gpu::GpuComparisons`]).
#[derive(Debug, Serialize, Deserialize)]
pub struct TrainStep<R> {
    /// Model width.
    pub d_model: usize,
    /// Transformer layers.
    pub n_layers: usize,
    /// Attention heads (of width 64).
    pub n_heads: usize,
    /// SwiGLU hidden width.
    pub ffn_hidden: usize,
    /// Vocabulary (codes and specials).
    pub vocab: usize,
    /// Sequences per step.
    pub batch: usize,
    /// Non-vocabulary parameters.
    pub n_nv: u64,
    /// Vocabulary parameters.
    pub n_v: u64,
    /// Where it trained.
    pub device: String,
    /// Compute precision.
    pub precision: String,
    /// The executor that ran it, lower case.
    pub executor: String,
    /// Wall time of whole steps.
    pub step_time: super::Timing,
    /// Median seconds of each phase.
    pub phase_median_s: Phases,
    /// On a GPU with the GPU executor: ms per step of each of its stages (each synchronised).
    #[serde(alias = "fused_stage_ms")]
    pub gpu_stage_ms: Option<BTreeMap<String, f64>>,
    /// Motion tokens per second at the median step.
    pub motion_tokens_per_s: f64,
    /// On a GPU: the peak memory allocated, GiB.
    pub peak_gpu_memory_allocated_gib: Option<f64>,
    /// FLOPs of one step, counted exactly.
    pub flops_per_step_exact: f64,
    /// 6·N·tokens of one step.
    #[serde(rename = "flops_per_step_6N")]
    pub flops_per_step_6n: f64,
    /// GFLOP/s at the exact count.
    pub achieved_gflops_exact: f64,
    /// The fp32 (CPU) or bf16 (GPU) peak MFU is measured against, GFLOP/s: on the CPU the
    /// larger of the FMA peak measured before and after the step's timing.
    #[serde(default)]
    pub peak_gflops: f64,
    /// Achieved over that peak (absent where it would pass 100%: the peak was measured in a
    /// disturbed moment).
    pub mfu: Option<f64>,
    /// The step if this process's CPU time were spread over all threads without waiting.
    pub cpu_time_equivalent: CpuTimeEquivalent,
    /// With `--reference`: the PyTorch step beside ours (absent, or read back as none, without).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference: Option<R>,
}

/// Median seconds of a training step's phases.
#[derive(Debug, Serialize, Deserialize)]
pub struct Phases {
    /// Forward and backward.
    pub fwd_bwd: f64,
    /// The clipped AdamW update.
    pub opt: f64,
    /// On a GPU: the forward pass alone.
    pub fwd: Option<f64>,
}

/// A step's figures at this process's CPU time per step over the threads (a lower bound of a
/// quiet machine's step; 0 s when unmeasured).
#[derive(Debug, Serialize, Deserialize)]
pub struct CpuTimeEquivalent {
    /// Seconds per step.
    pub step_s: f64,
    /// Motion tokens per second.
    pub motion_tokens_per_s: f64,
    /// GFLOP/s at the exact count.
    pub gflops_exact: f64,
}

/// A `WIDTHxLAYERS` size: (width, layers).
pub(super) fn parse_size(s: &str) -> Result<(usize, usize)> {
    let (d, l) = s.split_once('x').context("sizes look like 512x8")?;
    Ok((d.trim().parse()?, l.trim().parse()?))
}

/// The reference's batch: random text embeddings and 64 random codes per sequence.
pub(super) fn bench_batch(config: &PrefixLmConfig, batch: usize, seed: u64) -> Result<LmBatch> {
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

/// One AdamW training step of a d×layers model at `batch` on `device`, timed; its figures
/// (the MFU against `peak_gflops`), no reference yet.
pub(super) fn bench_train_step<R>(
    args: &BenchTrainArgs,
    (d, layers, batch): (usize, usize, usize),
    device: &Device,
    compute: Compute,
    peak_gflops: f64,
) -> Result<TrainStep<R>> {
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
    // The GPU executor's stages, each ended by a synchronisation (so apart from the timing
    // above): where a GPU step spends its time.
    let stages = match device.is_cuda() && model.executor()? == Executor::Gpu {
        true => Some(stage_ms(&model, &lm_batch, args.reps.max(3))?),
        false => None,
    };
    let step_s = st.median_s;
    let flops = batch as f64 * accounting::train_flops_exact(&config, SequenceShape::BENCH);
    let six_n =
        batch as f64 * SequenceShape::BENCH.motion as f64 * accounting::flops_6n_per_token(&config);
    let tokens = (batch * SequenceShape::BENCH.motion) as f64;
    let gflops = flops / step_s / 1e9;
    let params = accounting::param_count(&config);
    // On a busy machine: the step time if this process's CPU time were spread over all
    // threads without waiting (a lower bound of a quiet run's time; 0 when unmeasured).
    let cpu_bound_s = st.own_cpu_s_per_call.unwrap_or(0.0) / rayon::current_num_threads() as f64;
    Ok(TrainStep {
        d_model: d,
        n_layers: layers,
        n_heads: d / 64,
        ffn_hidden: config.ffn_hidden,
        vocab: config.vocab_size(),
        batch,
        n_nv: params.n_nv,
        n_v: params.n_v,
        device: nn::device::device_name(device),
        precision: compute.precision.to_string(),
        executor: format!("{:?}", model.executor()?).to_lowercase(),
        step_time: st,
        phase_median_s: Phases {
            fwd_bwd,
            opt: optim,
            fwd: forward,
        },
        gpu_stage_ms: stages,
        motion_tokens_per_s: tokens / step_s,
        peak_gpu_memory_allocated_gib: peak_gib,
        flops_per_step_exact: flops,
        flops_per_step_6n: six_n,
        achieved_gflops_exact: gflops,
        peak_gflops,
        mfu: super::machine::mfu(gflops, peak_gflops),
        cpu_time_equivalent: CpuTimeEquivalent {
            step_s: cpu_bound_s,
            motion_tokens_per_s: tokens / cpu_bound_s,
            gflops_exact: flops / cpu_bound_s / 1e9,
        },
        reference: None,
    })
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
