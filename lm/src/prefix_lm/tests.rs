//! Tests of the prefix LM: its masking, padding and decoding, and the agreement of its
//! executors.

use super::*;
use nn::gradcheck::max_abs_diff;
use nn::optim::{AdamW, AdamWConfig};
use std::collections::HashMap;

fn tiny() -> PrefixLmConfig {
    PrefixLmConfig::new(32, 2, 4, 20, 6)
}

fn text(n: usize, e: usize, seed: u64) -> Vec<f32> {
    let mut rng = SplitMix64(seed);
    (0..n * e).map(|_| rng.range(-1.0, 1.0) as f32).collect()
}

fn logits(model: &PrefixLm, texts: &[&[f32]], motions: &[(&[u32], bool)]) -> Vec<Vec<f32>> {
    let batch = LmBatch::new(model.config(), texts, motions);
    model.forward(&batch).unwrap().to_vec2::<f32>().unwrap()
}

#[test]
fn motion_is_causal_and_every_motion_slot_sees_the_whole_text() {
    let (model, _) = init_model(&tiny(), 1, &Device::Cpu).unwrap();
    let t = text(5, 6, 2);
    let m = [3u32, 7, 1, 12, 5, 9];
    let base = logits(&model, &[&t], &[(&m, true)]);
    // Changing motion token k (input slot k + 1) leaves slots 0..=k alone and moves the rest.
    for k in 0..m.len() {
        let mut changed = m;
        changed[k] = (m[k] + 4) % 20;
        let other = logits(&model, &[&t], &[(&changed, true)]);
        for s in 0..=k {
            assert_eq!(
                max_abs_diff(&base[s], &other[s]),
                0.0,
                "token {k} moved slot {s}"
            );
        }
        for s in k + 1..base.len() {
            assert!(
                max_abs_diff(&base[s], &other[s]) > 1e-6,
                "token {k} left slot {s}"
            );
        }
    }
    // Changing any text token moves the logits of every motion slot.
    for j in 0..5 {
        let mut changed = t.clone();
        changed[j * 6..(j + 1) * 6]
            .iter_mut()
            .for_each(|v| *v += 0.5);
        let other = logits(&model, &[&changed], &[(&m, true)]);
        for s in 0..base.len() {
            assert!(
                max_abs_diff(&base[s], &other[s]) > 1e-6,
                "text {j} left slot {s}"
            );
        }
    }
}

#[test]
fn padding_changes_nothing() {
    let (model, _) = init_model(&tiny(), 3, &Device::Cpu).unwrap();
    let (t0, t1) = (text(5, 6, 4), text(2, 6, 5));
    let (m0, m1) = ([1u32, 2, 3, 4], [9u32, 8]);
    // The shorter sequence first: its padding has no rows, so the longer one's start at 2.
    let both = logits(&model, &[&t1, &t0], &[(&m1, false), (&m0, true)]);
    let alone0 = logits(&model, &[&t0], &[(&m0, true)]);
    let alone1 = logits(&model, &[&t1], &[(&m1, false)]);
    assert_eq!((alone1.len(), alone0.len(), both.len()), (2, 5, 7));
    for s in 0..alone1.len() {
        assert!(max_abs_diff(&both[s], &alone1[s]) < 1e-5);
    }
    for s in 0..alone0.len() {
        assert!(max_abs_diff(&both[2 + s], &alone0[s]) < 1e-5);
    }
}

/// The model forced onto `executor` (f32).
fn on(model: &PrefixLm, executor: Executor) -> PrefixLm {
    model.clone().with_compute(Compute {
        executor: Some(executor),
        precision: Precision::F32,
    })
}

/// Two sequences of unequal text and motion lengths, one ending, one not.
fn two_clips(config: &PrefixLmConfig) -> LmBatch {
    let (t0, t1) = (text(4, 6, 12), text(2, 6, 13));
    let (m0, m1) = ([4u32, 17, 2, 9, 0], [11u32, 3, 3]);
    LmBatch::new(config, &[&t0, &t1], &[(&m0, true), (&m1, false)])
}

/// Largest |a − b| over the largest |b| (at least 1e-3) of two equal-shaped tensors.
fn relative_diff(a: &Tensor, b: &Tensor) -> f32 {
    let a = a.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let b = b.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let scale = b.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
    max_abs_diff(&a, &b) / scale
}

/// log-softmax of one row of logits (f64 sums).
fn log_softmax(row: &[f32]) -> Vec<f32> {
    let max = row.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    let sum: f64 = row.iter().map(|&v| f64::from(v - max).exp()).sum();
    row.iter()
        .map(|&v| (f64::from(v - max) - sum.ln()) as f32)
        .collect()
}

#[test]
fn kv_cached_log_probabilities_equal_full_recomputation_on_both_executors() {
    let (model, _) = init_model(&tiny(), 6, &Device::Cpu).unwrap();
    let c = model.config().clone();
    let (t0, t1) = (text(4, 6, 7), text(2, 6, 8));
    let tokens = [[5u32, 11, 2, 19, 0, 7], [3, 3, 14, 1, 8, 6]];
    let full = logits(
        &model,
        &[&t0, &t1],
        &[(&tokens[0], true), (&tokens[1], true)],
    );
    let layout = SeqLayout::new(vec![4, 2], tokens[0].len() + 1);
    let mut text_rows = vec![0f32; 2 * 4 * 6];
    text_rows[..t0.len()].copy_from_slice(&t0);
    text_rows[24..24 + t1.len()].copy_from_slice(&t1);
    let p = layout.prefix_slots;
    for executor in [Executor::Cpu, Executor::Graph] {
        let model = on(&model, executor);
        let mut cache = model.new_cache(&layout).unwrap();
        let mut worst = 0f32;
        for t in 0..layout.motion_slots {
            let input: Vec<u32> = (0..2)
                .map(|b| if t == 0 { c.bos() } else { tokens[b][t - 1] })
                .collect();
            let (from, to) = if t == 0 {
                (0, p + 1)
            } else {
                (p + t, p + t + 1)
            };
            let step = model
                .forward_cached(&mut cache, &layout, &text_rows, &input, (from, to))
                .unwrap()
                .to_vec2::<f32>()
                .unwrap();
            for b in 0..2 {
                let full = &full[b * layout.motion_slots + t];
                worst = worst.max(max_abs_diff(&log_softmax(&step[b]), &log_softmax(full)));
            }
        }
        eprintln!("{executor:?} KV cache: largest log-probability difference from the cpu executor's full recomputation {worst:.2e}");
        assert!(worst <= 1e-5, "{executor:?} cached vs full: {worst}");
    }
}

/// The logits of every cached decoding step of `texts` (tokens `tokens[b][t]` fed back) on
/// the CPU executor, per step and sequence.
fn cached_steps(model: &PrefixLm, texts: &[&[f32]], tokens: &[[u32; 5]]) -> Vec<Vec<Vec<f32>>> {
    let e = model.config().text_dim;
    let layout = SeqLayout::new(texts.iter().map(|t| t.len() / e).collect(), 6);
    let p = layout.prefix_slots;
    let mut text_rows = vec![0f32; texts.len() * p * e];
    for (b, t) in texts.iter().enumerate() {
        text_rows[b * p * e..][..t.len()].copy_from_slice(t);
    }
    let mut cache = model.new_cache(&layout).unwrap();
    (0..layout.motion_slots)
        .map(|t| {
            let input: Vec<u32> = (0..texts.len())
                .map(|b| {
                    if t == 0 {
                        model.config().bos()
                    } else {
                        tokens[b][t - 1]
                    }
                })
                .collect();
            let slots = if t == 0 {
                (0, p + 1)
            } else {
                (p + t, p + t + 1)
            };
            (model.forward_cached(&mut cache, &layout, &text_rows, &input, slots))
                .unwrap()
                .to_vec2::<f32>()
                .unwrap()
        })
        .collect()
}

/// Cached decoding on the CPU computes each sequence alone: one sequence and two give the
/// same bits by themselves as beside a third with a longer text (so more text slots), on one
/// thread or three. `generate` relies on it to decode a batch in groups.
#[test]
fn cached_cpu_decoding_gives_each_sequence_the_same_bits_whatever_its_batch() {
    let (model, _) = init_model(&tiny(), 3, &Device::Cpu).unwrap();
    let texts = [text(2, 6, 1), text(3, 6, 2), text(5, 6, 3)];
    let texts: Vec<&[f32]> = texts.iter().map(Vec::as_slice).collect();
    let tokens = [[4u32, 9, 1, 17, 2], [0, 13, 13, 6, 19], [8, 8, 3, 11, 5]];
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    let three = pool.install(|| cached_steps(&model, &texts, &tokens));
    let bits = |rows: &[Vec<f32>], n: usize| -> Vec<u32> {
        rows[..n].concat().iter().map(|v| v.to_bits()).collect()
    };
    for n in [1, 2] {
        let fewer = cached_steps(&model, &texts[..n], &tokens);
        for (t, (a, b)) in fewer.iter().zip(&three).enumerate() {
            assert_eq!(bits(a, n), bits(b, n), "{n} sequences, step {t}");
        }
    }
}

#[test]
fn executors_agree_on_logits_and_target_log_probs() {
    let config = tiny();
    let (model, _) = init_model(&config, 11, &Device::Cpu).unwrap();
    let batch = two_clips(&config);
    let (cpu, graph) = (on(&model, Executor::Cpu), on(&model, Executor::Graph));
    let logits = relative_diff(
        &graph.forward(&batch).unwrap(),
        &cpu.forward(&batch).unwrap(),
    );
    let (a, b) = (
        graph.target_log_probs(&batch).unwrap(),
        cpu.target_log_probs(&batch).unwrap(),
    );
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.is_nan(), y.is_nan());
        if !x.is_nan() {
            assert!((x - y).abs() <= 1e-5 * y.abs().max(1.0), "{x} vs {y}");
        }
    }
    eprintln!("logits: graph vs cpu, relative difference {logits:.2e}");
    assert!(logits <= 1e-5, "logits differ by {logits}");
}

/// Loss and every gradient of `model` on the cpu executor and on `other`: the loss's relative
/// difference and the largest per-weight relative gradient difference.
fn loss_and_grad_agreement(
    model: &PrefixLm,
    vars: &HashMap<String, Var>,
    batch: &LmBatch,
    (other, extra): (Executor, Option<&ExtraLoss<'_>>),
) -> (f32, f32) {
    let run = |e| {
        let m = on(model, e);
        match extra {
            Some(x) => m.loss_and_grads_with(batch, x).unwrap(),
            None => m.loss_and_grads(batch).unwrap(),
        }
    };
    let ((l_cpu, g_cpu), (l_graph, g_graph)) = (run(Executor::Cpu), run(other));
    let mut worst = 0f32;
    for (name, var) in vars {
        let (a, b) = (g_graph.get(var).unwrap(), g_cpu.get(var).unwrap());
        let d = relative_diff(a, b);
        assert!(
            d <= 1e-5,
            "{name}: gradients differ by {d:.2e} of their scale"
        );
        worst = worst.max(d);
    }
    ((l_graph - l_cpu).abs() / l_cpu.abs(), worst)
}

#[test]
fn executors_agree_on_the_loss_and_every_gradient() {
    let config = tiny();
    let (model, varmap) = init_model(&config, 11, &Device::Cpu).unwrap();
    let vars = varmap.data().lock().unwrap().clone();
    let batch = two_clips(&config);
    for other in [Executor::Graph, Executor::Gpu] {
        let (loss, grads) = loss_and_grad_agreement(&model, &vars, &batch, (other, None));
        eprintln!("{other:?} vs cpu: loss {loss:.2e}, gradients {grads:.2e} (relative)");
        assert!(loss <= 1e-5, "{other:?}: losses differ by {loss:.2e}");
    }
    // An extra term on the logits (here: pull every logit towards 0.1) reaches the weights
    // alike on both.
    let pull = |logits: &[f32]| {
        let g: Vec<f32> = logits.iter().map(|v| 1e-3 * (v - 0.1)).collect();
        let term = logits.iter().map(|v| 5e-4 * (v - 0.1).powi(2)).sum();
        Some((term, g))
    };
    let extra = (Executor::Graph, Some(&pull as &ExtraLoss));
    let (loss, grads) = loss_and_grad_agreement(&model, &vars, &batch, extra);
    eprintln!("with an extra loss: loss {loss:.2e}, gradients {grads:.2e} (relative)");
    assert!(loss <= 1e-5, "losses differ by {loss:.2e}");
}

#[test]
fn executors_drop_the_same_values_and_agree_under_dropout() {
    let config = tiny();
    let (model, varmap) = init_model(&config, 11, &Device::Cpu).unwrap();
    let vars = varmap.data().lock().unwrap().clone();
    let plain = two_clips(&config);
    let mut batch = plain.clone();
    batch.dropout = Some(Dropout { p: 0.25, seed: 17 });
    for other in [Executor::Graph, Executor::Gpu] {
        let (loss, grads) = loss_and_grad_agreement(&model, &vars, &batch, (other, None));
        eprintln!("dropout, {other:?} vs cpu: loss {loss:.2e}, gradients {grads:.2e} (relative)");
        assert!(loss <= 1e-5, "{other:?}: losses differ by {loss:.2e}");
    }
    let cpu = on(&model, Executor::Cpu);
    let (dropped, _) = cpu.loss_and_grads(&batch).unwrap();
    let (kept, _) = cpu.loss_and_grads(&plain).unwrap();
    assert!(
        (dropped - kept).abs() > 1e-4,
        "dropout changed nothing: {dropped} vs {kept}"
    );
    // Inference never drops.
    for e in [Executor::Cpu, Executor::Graph] {
        let m = on(&model, e);
        let diff = relative_diff(&m.forward(&batch).unwrap(), &m.forward(&plain).unwrap());
        assert_eq!(diff, 0.0, "{e:?}: forward dropped values");
    }
}

/// The losses of `steps` AdamW steps of a fresh model on `executor`, over a fixed cycle of
/// batches.
fn training_losses(executor: Executor, precision: Precision, steps: usize) -> Vec<f32> {
    let config = tiny();
    let (model, varmap) = init_model(&config, 21, &Device::Cpu).unwrap();
    let model = model.with_compute(Compute {
        executor: Some(executor),
        precision,
    });
    let vars = varmap.data().lock().unwrap().clone();
    let mut opt = AdamW::new(&vars, AdamWConfig::default());
    let batches: Vec<LmBatch> = (0..4u64)
        .map(|k| {
            let (t0, t1) = (text(3, 6, 30 + k), text(5, 6, 40 + k));
            let m0: Vec<u32> = (0..6).map(|i| ((i * 7 + k as usize) % 20) as u32).collect();
            let m1: Vec<u32> = (0..4)
                .map(|i| ((i * 3 + 2 * k as usize) % 20) as u32)
                .collect();
            LmBatch::new(&config, &[&t0, &t1], &[(&m0, true), (&m1, k % 2 == 0)])
        })
        .collect();
    (0..steps)
        .map(|s| {
            let (loss, grads) = model.loss_and_grads(&batches[s % batches.len()]).unwrap();
            opt.step(&grads, 3e-3, Some(1.0)).unwrap();
            loss
        })
        .collect()
}

#[test]
fn executors_agree_after_40_training_steps() {
    let cpu = training_losses(Executor::Cpu, Precision::F32, 40);
    assert!(
        cpu[39] < cpu[0] - 0.5,
        "training did not reduce the loss: {cpu:?}"
    );
    for other in [Executor::Graph, Executor::Gpu] {
        let losses = training_losses(other, Precision::F32, 40);
        let worst = cpu
            .iter()
            .zip(&losses)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        eprintln!(
            "40 steps: loss {:.5} -> {:.5} (cpu), {:.5} ({other:?}); largest difference {worst:.2e}",
            cpu[0], cpu[39], losses[39]
        );
        assert!(worst <= 1e-4, "{other:?}: losses differ by {worst}");
    }
}

#[test]
fn bf16_training_follows_f32_within_bf16_rounding() {
    let f32 = training_losses(Executor::Graph, Precision::F32, 40);
    for executor in [Executor::Graph, Executor::Gpu] {
        let bf16 = training_losses(executor, Precision::Bf16, 40);
        let worst = f32
            .iter()
            .zip(&bf16)
            .map(|(a, b)| (a - b).abs() / a)
            .fold(0f32, f32::max);
        eprintln!(
            "40 steps bf16 ({executor:?}) vs f32: final {:.4} vs {:.4}, largest relative difference {worst:.2e}",
            bf16[39], f32[39]
        );
        // bf16 keeps 8 mantissa bits (relative rounding 2^-9 ≈ 2e-3 per product).
        assert!(
            worst <= 3e-2,
            "{executor:?}: bf16 strays {worst:.2e} from f32"
        );
        assert!(
            worst > 0.0,
            "{executor:?}: bf16 computed exactly the f32 losses: the cast did not happen"
        );
    }
}

#[test]
fn the_cpu_executor_refuses_what_it_cannot_run() {
    let (model, _) = init_model(&tiny(), 1, &Device::Cpu).unwrap();
    assert_eq!(model.executor().unwrap(), Executor::Cpu);
    let bf16 = model.with_compute(Compute {
        executor: Some(Executor::Cpu),
        precision: Precision::Bf16,
    });
    let err = bf16.executor().unwrap_err().to_string();
    assert!(err.contains("graph executor"), "{err}");
    let graph = bf16.with_compute(Compute {
        executor: None,
        precision: Precision::Bf16,
    });
    assert_eq!(graph.executor().unwrap(), Executor::Gpu);
}

/// A clock that lists the stages it is told of.
struct StageNames(std::cell::RefCell<Vec<&'static str>>);

impl StageClock for StageNames {
    fn stage_done(&self, stage: &'static str) -> Result<()> {
        self.0.borrow_mut().push(stage);
        Ok(())
    }
}

#[test]
fn the_gpu_executor_tells_a_clock_its_stages() {
    let config = tiny();
    let (model, _) = init_model(&config, 5, &Device::Cpu).unwrap();
    let gpu = on(&model, Executor::Gpu);
    let batch = two_clips(&config);
    let (plain, _) = gpu.loss_and_grads(&batch).unwrap();
    let clock = StageNames(Default::default());
    let (timed, _) = gpu.loss_and_grads_timed(&batch, &clock).unwrap();
    assert_eq!(plain, timed);
    let first = clock.0.borrow().clone();
    gpu.loss_and_grads_timed(&batch, &clock).unwrap();
    assert_eq!(
        clock.0.borrow()[first.len()..],
        first[..],
        "a step's stages differ"
    );
    let names: std::collections::BTreeSet<_> = first.iter().collect();
    assert_eq!(names.len(), 11, "{names:?}");
    assert!(names.contains(&"backward: output product, attention"));
    assert_eq!(first.last(), Some(&"loss"));
    let cpu = StageNames(Default::default());
    model.loss_and_grads_timed(&batch, &cpu).unwrap();
    assert_eq!(cpu.0.into_inner(), ["step"]);
}

#[test]
fn the_gpu_executor_keeps_its_old_name_as_an_alias() {
    use clap::ValueEnum;
    assert_eq!(Executor::from_str("fused", false), Ok(Executor::Gpu));
    let old: Compute = serde_json::from_str(r#"{"executor": "fused"}"#).unwrap();
    assert_eq!(old.executor, Some(Executor::Gpu));
    assert_eq!(serde_json::to_string(&Executor::Gpu).unwrap(), "\"gpu\"");
}
