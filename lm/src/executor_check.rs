//! The prefix LM's executors side by side on one seeded model and batch: the cpu executor on
//! the CPU against the graph and the GPU executors on any device (a GPU, or the CPU).
//! `motionscale model executors` prints it; `scripts/gpu-check.sh` runs it on a GPU.

use crate::prefix_lm::{init_model, Compute, Executor, LmBatch, PrefixLm, PrefixLmConfig};
use candle_core::{Device, Result, Tensor};
use motionscale_core::rng::SplitMix64;
use nn::device::{device_name, Precision};
use nn::seq_layout::SeqLayout;
use serde::Serialize;

/// How far the graph executor on a device is from the cpu executor on the CPU.
#[derive(Debug, Clone, Serialize)]
pub struct Agreement {
    /// The graph executor's device.
    pub device: String,
    /// The cpu executor's mean cross-entropy.
    pub loss: f32,
    /// |Δloss| / loss.
    pub loss_relative: f32,
    /// The largest, over the weights, of max |Δg| / max |g_cpu|.
    pub gradient_relative: f32,
    /// The weight where that is largest.
    pub worst_weight: String,
    /// The GPU executor's training step on the device: |Δloss| / loss, the largest
    /// relative gradient difference and its weight, as above.
    pub gpu_step: (f32, f32, String),
    /// max |Δlogit| / max |logit| over every motion slot.
    pub logits_relative: f32,
    /// The largest |Δlogit| of KV-cached decoding, step by step, against the cpu executor's.
    pub cached_logits_max_abs: f32,
    /// Each fused op's outputs and the AdamW update on the device against the CPU
    /// (`nn::device_check::self_check`): largest relative difference per output.
    pub fused_ops: Vec<(String, f32)>,
}

/// A seeded batch of `batch` sequences: random text of 2–16 tokens and 4–40 motion codes.
fn batch_of(config: &PrefixLmConfig, batch: usize, seed: u64) -> LmBatch {
    let mut rng = SplitMix64(seed);
    let texts: Vec<Vec<f32>> = (0..batch)
        .map(|_| {
            let n = 2 + rng.index(15);
            (0..n * config.text_dim)
                .map(|_| rng.range(-1.0, 1.0) as f32)
                .collect()
        })
        .collect();
    let motions: Vec<Vec<u32>> = (0..batch)
        .map(|_| {
            let n = 4 + rng.index(37);
            (0..n)
                .map(|_| rng.index(config.codebook_size) as u32)
                .collect()
        })
        .collect();
    let texts: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
    let motions: Vec<(&[u32], bool)> = motions
        .iter()
        .enumerate()
        .map(|(i, m)| (m.as_slice(), i % 2 == 0))
        .collect();
    LmBatch::new(config, &texts, &motions)
}

/// max |a − b| / max(|b|, 1e-3) of two tensors (on any devices).
fn relative(a: &Tensor, b: &Tensor) -> Result<f32> {
    let a = a.flatten_all()?.to_vec1::<f32>()?;
    let b = b.flatten_all()?.to_vec1::<f32>()?;
    let scale = b.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
    Ok(nn::gradcheck::max_abs_diff(&a, &b) / scale)
}

/// Logits of cached decoding, one step per motion slot, of a three-sequence batch.
fn cached_logits(model: &PrefixLm, seed: u64) -> Result<Vec<Vec<f32>>> {
    let c = model.config();
    let mut rng = SplitMix64(seed);
    let prefix_lens = [5usize, 2, 9];
    let layout = SeqLayout::new(prefix_lens.to_vec(), 12);
    let p = layout.prefix_slots;
    let text: Vec<f32> = (0..3 * p * c.text_dim)
        .map(|_| rng.range(-1.0, 1.0) as f32)
        .collect();
    let mut cache = model.new_cache(&layout)?;
    let mut out = Vec::new();
    for t in 0..layout.motion_slots {
        let inputs: Vec<u32> = (0..3)
            .map(|_| match t {
                0 => c.bos(),
                _ => rng.index(c.codebook_size) as u32,
            })
            .collect();
        let slots = if t == 0 {
            (0, p + 1)
        } else {
            (p + t, p + t + 1)
        };
        let logits = model.forward_cached(&mut cache, &layout, &text, &inputs, slots)?;
        out.extend(logits.to_vec2::<f32>()?);
    }
    Ok(out)
}

/// Compare the executors on a seeded `config` model and a batch of `batch` sequences.
pub fn compare(
    config: &PrefixLmConfig,
    batch: usize,
    seed: u64,
    device: &Device,
) -> Result<Agreement> {
    let forced = |e| Compute {
        executor: Some(e),
        precision: Precision::F32,
    };
    let (cpu, cpu_vars) = init_model(config, seed, &Device::Cpu)?;
    let (graph, graph_vars) = init_model(config, seed, device)?;
    let gpu = graph.clone().with_compute(forced(Executor::Gpu));
    let (cpu, graph) = (
        cpu.with_compute(forced(Executor::Cpu)),
        graph.with_compute(forced(Executor::Graph)),
    );
    let data = batch_of(config, batch, seed ^ 0x5eed);
    let (l_cpu, g_cpu) = cpu.loss_and_grads(&data)?;
    let (cpu_vars, graph_vars) = (
        cpu_vars.data().lock().expect("vars"),
        graph_vars.data().lock().expect("vars"),
    );
    let step_agreement = |model: &PrefixLm| -> Result<(f32, f32, String)> {
        let (loss, grads) = model.loss_and_grads(&data)?;
        let mut names: Vec<&String> = cpu_vars.keys().collect();
        names.sort();
        let (mut worst, mut worst_weight) = (0f32, String::new());
        for name in names {
            let missing = || candle_core::Error::Msg(format!("no gradient of {name}"));
            let a = grads.get(&graph_vars[name]).ok_or_else(missing)?;
            let b = g_cpu.get(&cpu_vars[name]).ok_or_else(missing)?;
            let d = relative(a, b)?;
            if d >= worst {
                (worst, worst_weight) = (d, name.clone());
            }
        }
        Ok(((loss - l_cpu).abs() / l_cpu.abs(), worst, worst_weight))
    };
    let (loss_relative, worst, worst_weight) = step_agreement(&graph)?;
    let gpu_step = step_agreement(&gpu)?;
    let logits = relative(&graph.forward(&data)?, &cpu.forward(&data)?)?;
    let (cached_graph, cached_cpu) = (cached_logits(&graph, seed)?, cached_logits(&cpu, seed)?);
    let cached = cached_graph
        .iter()
        .zip(&cached_cpu)
        .map(|(a, b)| nn::gradcheck::max_abs_diff(a, b))
        .fold(0f32, f32::max);
    Ok(Agreement {
        device: device_name(device),
        loss: l_cpu,
        loss_relative,
        gradient_relative: worst,
        worst_weight,
        gpu_step,
        logits_relative: logits,
        cached_logits_max_abs: cached,
        fused_ops: nn::device_check::self_check(device)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_executors_agree_on_the_cpu() {
        let config = PrefixLmConfig::new(64, 2, 2, 30, 8);
        let a = compare(&config, 4, 3, &Device::Cpu).unwrap();
        eprintln!("{a:?}");
        assert!(a.loss_relative <= 1e-5, "{a:?}");
        assert!(a.gradient_relative <= 1e-5, "{a:?}");
        assert!(a.logits_relative <= 1e-5, "{a:?}");
        assert!(a.cached_logits_max_abs <= 1e-4, "{a:?}");
    }
}
