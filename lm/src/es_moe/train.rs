//! ES-MoE's training step: the model at one continual step with its new expert last, the
//! loss of a batch of clips, and the gradients of the expert, its key and the gate network.

use super::{EsMoe, EsMoeConfig};
use crate::lora::{base_weights, LoraAdapter};
use crate::prefix_lm::{LmBatch, PrefixLmConfig};
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var};
use motionscale_core::rng::SplitMix64;
use nn::ModelError;
use std::collections::HashMap;
use std::path::Path;

/// One training clip as ES-MoE sees it.
#[derive(Debug, Clone, Copy)]
pub struct MoeExample<'a> {
    /// The clip's id (its emotion label).
    pub motion_id: &'a str,
    /// Caption token embeddings (rows of the text width).
    pub text: &'a [f32],
    /// Motion tokens.
    pub tokens: &'a [u32],
    /// Whether EOS is a target.
    pub ends: bool,
}

impl MoeExample<'_> {
    /// Loss positions.
    fn targets(&self) -> usize {
        self.tokens.len() + usize::from(self.ends)
    }
}

/// What one ES-MoE training step computed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MoeStepLoss {
    /// LM cross-entropy (mean over the batch's targets).
    pub lm: f32,
    /// Emotion cross-entropy of the labelled captions (0 without the emotion loss).
    pub emotion: f32,
    /// Mean gate weight of the expert being trained.
    pub current_weight: f32,
}

impl MoeStepLoss {
    /// The training objective LM + λ·emotion.
    pub fn total(&self, emotion_weight: f64) -> f32 {
        self.lm + emotion_weight as f32 * self.emotion
    }
}

/// ES-MoE at one continual step: the model with the new expert last, and the emotion class of
/// each training clip.
pub struct EsMoeTrainer {
    /// The model (its last expert is the one trained).
    pub moe: EsMoe,
    emotion_of: HashMap<String, usize>,
}

impl EsMoeTrainer {
    /// The step that adds (or, when `previous` has it, continues) expert `expert`: the
    /// earlier experts, gate and dictionary come from `previous` (a run folder), else a new
    /// gate is drawn from `seed` and the dictionary is fitted on the training captions
    /// `train_texts`. `emotions` labels clips by motion id (classes in sorted order).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        model: &PrefixLmConfig,
        config: EsMoeConfig,
        base_file: &Path,
        previous: Option<&Path>,
        expert: &str,
        emotions: &HashMap<String, String>,
        train_texts: &[&[f32]],
        seed: u64,
        device: &Device,
    ) -> std::result::Result<Self, ModelError> {
        let mut moe = match previous {
            Some(dir) => EsMoe::load(dir, base_file, model, config, device)?,
            None => {
                let mut classes: Vec<String> = emotions.values().cloned().collect();
                classes.sort();
                classes.dedup();
                let base = base_weights(base_file, device)?;
                let moe = EsMoe::build(model, config, base, classes, seed)?;
                if config.cged {
                    moe.fit_dictionary(train_texts, seed)
                        .map_err(ModelError::Candle)?;
                }
                moe
            }
        };
        match moe.manifest.experts.iter().position(|e| e == expert) {
            // Continuing an expert (the shared one without the mixture): it moves last.
            Some(i) => {
                let e = moe.experts.remove(i);
                let name = moe.manifest.experts.remove(i);
                moe.experts.push(e);
                moe.manifest.experts.push(name);
            }
            None => {
                if config.mixture && moe.experts.len() >= config.max_experts {
                    return Err(ModelError::argument(
                        "max_experts",
                        format!(
                            "ES-MoE has keys for {} experts; raise max_experts",
                            config.max_experts
                        ),
                    ));
                }
                let index = moe.experts.len() as u64;
                let adapter =
                    LoraAdapter::new(model, config.lora, expert, seed ^ (index << 32), device)
                        .map_err(ModelError::Candle)?;
                moe.experts.push(adapter);
                moe.manifest.experts.push(expert.to_string());
            }
        }
        let classes: HashMap<&String, usize> = moe
            .manifest
            .emotions
            .iter()
            .enumerate()
            .map(|(i, e)| (e, i))
            .collect();
        let emotion_of = emotions
            .iter()
            .filter_map(|(id, e)| Some((id.clone(), *classes.get(e)?)))
            .collect();
        Ok(Self { moe, emotion_of })
    }

    /// The trained variables: the current expert's A and B, and (with the mixture) the gate
    /// network and the current expert's key; not the older keys or the dictionary.
    pub fn vars(&self) -> HashMap<String, Var> {
        let moe = &self.moe;
        let current = moe.experts.len() - 1;
        let mut vars = moe.experts[current].vars();
        if moe.config.mixture {
            let own_key = format!("gate.keys.{current}");
            vars.extend(moe.gate.vars().into_iter().filter(|(name, _)| {
                let key = name.starts_with("gate.keys.");
                (!key || *name == own_key) && name != "gate.cged.dictionary"
            }));
        }
        vars
    }

    /// Loss of the clips `items` and the gradients of [`Self::vars`]; `mask` (a generator
    /// and a probability) masks older experts, as in training.
    pub fn loss_and_grads(
        &self,
        items: &[MoeExample<'_>],
        mask: Option<(&mut SplitMix64, f64)>,
    ) -> Result<(MoeStepLoss, GradStore)> {
        let moe = &self.moe;
        let (n, current) = (moe.experts.len(), moe.experts.len() - 1);
        let texts: Vec<&[f32]> = items.iter().map(|item| item.text).collect();
        let gated = moe.config.mixture && n > 1;
        let h = if moe.config.mixture {
            Some(moe.gate.h(&texts)?)
        } else {
            None
        };
        let weights = match (&h, gated) {
            (Some(h), true) => {
                let masked: Vec<Vec<bool>> = match mask {
                    Some((rng, p)) => items
                        .iter()
                        .map(|_| (0..n).map(|j| j < current && rng.unit() < p).collect())
                        .collect(),
                    None => vec![vec![false; n]; items.len()],
                };
                Some(moe.gate_weights(h, &masked)?)
            }
            _ => None,
        };
        let w: Vec<Vec<f32>> = match &weights {
            Some(w) => w.to_vec2()?,
            None => vec![vec![1.0; n]; items.len()],
        };
        let deltas = moe.deltas()?;
        let total: usize = items.iter().map(MoeExample::targets).sum();
        let mut acc: HashMap<String, Tensor> = HashMap::new();
        let mut contributions = vec![0f32; items.len() * n];
        let mut lm = 0f32;
        for (b, item) in items.iter().enumerate() {
            let share = item.targets() as f32 / total.max(1) as f32;
            if share == 0.0 {
                continue;
            }
            let batch = LmBatch::new(&moe.model, &[item.text], &[(item.tokens, item.ends)]);
            let (model, merged) = moe.merged(&deltas, &w[b])?;
            let (loss, grads) = model.loss_and_grads(&batch)?;
            lm += share * loss;
            // Every expert's updates list the same weights in the same order.
            for (k, (name, _)) in deltas[current].iter().enumerate() {
                let Some(g) = grads.get(&merged[name]) else {
                    continue;
                };
                let g = (g * f64::from(share))?;
                if w[b][current] > 0.0 {
                    let part = (&g * f64::from(w[b][current]))?;
                    let sum = match acc.remove(name) {
                        Some(a) => (a + part)?,
                        None => part,
                    };
                    acc.insert(name.clone(), sum);
                }
                if gated {
                    for (j, expert) in deltas.iter().enumerate() {
                        if w[b][j] > 0.0 {
                            contributions[b * n + j] +=
                                (&g * &expert[k].1)?.sum_all()?.to_scalar::<f32>()?;
                        }
                    }
                }
            }
        }
        let mut grads = moe.experts[current].grads_by_name(&acc)?;
        let mut emotion = 0f32;
        if let Some(h) = &h {
            let mut objective = match &weights {
                Some(w) => {
                    let c = Tensor::from_vec(contributions, (items.len(), n), moe.device())?;
                    (w * c)?.sum_all()?
                }
                None => Tensor::zeros((), DType::F32, moe.device())?,
            };
            if let (Some(head), true) = (&moe.gate.emotion, moe.config.emotion_weight > 0.0) {
                let (rows, labels): (Vec<u32>, Vec<u32>) = items
                    .iter()
                    .enumerate()
                    .filter_map(|(b, e)| {
                        Some((b as u32, *self.emotion_of.get(e.motion_id)? as u32))
                    })
                    .unzip();
                if !rows.is_empty() {
                    let idx = Tensor::new(rows, moe.device())?;
                    let logits = head.forward(&h.index_select(&idx, 0)?)?;
                    let ce = candle_nn::loss::cross_entropy(
                        &logits,
                        &Tensor::new(labels, moe.device())?,
                    )?;
                    emotion = ce.to_scalar()?;
                    objective = (objective + (ce * moe.config.emotion_weight)?)?;
                }
            }
            let gate_grads = objective.backward()?;
            for var in self.vars().values() {
                if let Some(g) = gate_grads.get(var.as_tensor()) {
                    grads.insert(var.as_tensor(), g.clone());
                }
            }
        }
        let current_weight = w.iter().map(|row| row[current]).sum::<f32>() / w.len().max(1) as f32;
        Ok((
            MoeStepLoss {
                lm,
                emotion,
                current_weight,
            },
            grads,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::es_moe::{orthogonal_keys, top_k_mask};
    use crate::lora::LoraConfig;
    use crate::prefix_lm::{init_model, Compute, Executor, PrefixLm};
    use crate::MotionLm;
    use candle_nn::VarBuilder;
    use nn::checkpoint::var_tensors;
    use nn::optim::{AdamW, AdamWConfig};
    use std::path::PathBuf;

    struct Fixture {
        config: PrefixLmConfig,
        base: tempfile::TempDir,
        texts: Vec<Vec<f32>>,
        tokens: Vec<Vec<u32>>,
        emotions: HashMap<String, String>,
    }

    /// A seeded 1-block base model saved to a folder, four captions with motions, and
    /// emotion labels for three of them.
    fn fixture() -> Fixture {
        let config = PrefixLmConfig::new(16, 1, 2, 12, 6);
        let (_, varmap) = init_model(&config, 1, &Device::Cpu).unwrap();
        let base = tempfile::tempdir().unwrap();
        varmap.save(base.path().join("model.safetensors")).unwrap();
        let mut rng = SplitMix64(3);
        let texts = (0..4)
            .map(|i| {
                (0..(2 + i) * 6)
                    .map(|_| rng.range(-1.0, 1.0) as f32)
                    .collect()
            })
            .collect();
        let tokens = vec![vec![1, 4, 7], vec![2, 9], vec![3, 3, 5, 0], vec![11, 6]];
        let emotions = [("c0", "happy"), ("c1", "sad"), ("c2", "happy")]
            .into_iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect();
        Fixture {
            config,
            base,
            texts,
            tokens,
            emotions,
        }
    }

    impl Fixture {
        fn examples(&self) -> Vec<MoeExample<'_>> {
            const IDS: [&str; 4] = ["c0", "c1", "c2", "c3"];
            (0..4)
                .map(|i| MoeExample {
                    motion_id: IDS[i],
                    text: &self.texts[i],
                    tokens: &self.tokens[i],
                    ends: i % 2 == 0,
                })
                .collect()
        }

        fn trainer(&self, previous: Option<&Path>, expert: &str, c: EsMoeConfig) -> EsMoeTrainer {
            let texts: Vec<&[f32]> = self.texts.iter().map(Vec::as_slice).collect();
            EsMoeTrainer::new(
                &self.config,
                c,
                &self.base.path().join("model.safetensors"),
                previous,
                expert,
                &self.emotions,
                &texts,
                7,
                &Device::Cpu,
            )
            .unwrap()
        }
    }

    fn small() -> EsMoeConfig {
        EsMoeConfig {
            lora: LoraConfig {
                rank: 2,
                alpha: 4.0,
            },
            max_experts: 4,
            key_dim: 4,
            query_hidden: 4,
            cged_dim: 8,
            dictionary_size: 3,
            emotion_weight: 0.5,
            ..EsMoeConfig::default()
        }
    }

    /// The B matrices of `expert` drawn from U(−0.3, 0.3) with `seed` (in name order).
    fn random_b(expert: &LoraAdapter, seed: u64) {
        let mut rng = SplitMix64(seed);
        let vars = expert.vars();
        let mut names: Vec<&String> = vars
            .keys()
            .filter(|n| n.ends_with("lora_B.weight"))
            .collect();
        names.sort();
        for name in names {
            let var = &vars[name];
            let v: Vec<f32> = (0..var.elem_count())
                .map(|_| rng.range(-0.3, 0.3) as f32)
                .collect();
            var.set(&Tensor::from_vec(v, var.dims(), &Device::Cpu).unwrap())
                .unwrap();
        }
    }

    fn values(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    /// One AdamW step of the trainer's variables on the fixture's clips.
    fn train_step(t: &EsMoeTrainer, f: &Fixture) {
        let vars = t.vars();
        let mut opt = AdamW::new(&vars, AdamWConfig::default());
        let mut rng = SplitMix64(1);
        let (_, grads) = t
            .loss_and_grads(&f.examples(), Some((&mut rng, 0.5)))
            .unwrap();
        opt.step(&grads, 1e-2, Some(1.0)).unwrap();
    }

    /// Step 2 (expert e1) after one training step of expert e0 saved in `dir`.
    fn second_step(f: &Fixture, dir: &Path) -> EsMoeTrainer {
        let first = f.trainer(None, "e0", small());
        train_step(&first, f);
        first.moe.save(dir).unwrap();
        f.trainer(Some(dir), "e1", small())
    }

    #[test]
    fn keys_are_orthonormal_at_initialisation() {
        let keys = orthogonal_keys(16, 16, 5);
        for (i, a) in keys.iter().enumerate() {
            for (j, b) in keys.iter().enumerate() {
                let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((dot - want).abs() < 1e-5, "K{i}·K{j} = {dot}");
            }
        }
        let f = fixture();
        let t = f.trainer(None, "e0", small());
        let gate = t.moe.gate.vars();
        for (j, key) in orthogonal_keys(4, 4, 7).iter().enumerate() {
            assert_eq!(&values(gate[&format!("gate.keys.{j}")].as_tensor()), key);
        }
    }

    #[test]
    fn top_k_weights_are_renormalised_over_the_unmasked_experts() {
        let scores = [0.3f32, 2.0, -1.0, 1.5];
        let mask = top_k_mask(&scores, &[false, true, false, false], 2);
        assert_eq!(mask[1], f32::NEG_INFINITY, "masked");
        assert_eq!(mask[2], f32::NEG_INFINITY, "not in the top 2 of the rest");
        let w: Vec<f32> = scores
            .iter()
            .zip(&mask)
            .map(|(s, m)| (s + m).exp())
            .collect();
        let sum: f32 = w.iter().sum();
        assert!(((w[0] + w[3]) / sum - 1.0).abs() < 1e-6);
        // Through the gate: three experts, top-2 weights sum to one with one zero.
        let f = fixture();
        let dir = tempfile::tempdir().unwrap();
        let mut previous: Option<PathBuf> = None;
        for e in ["e0", "e1", "e2"] {
            let t = f.trainer(previous.as_deref(), e, small());
            let step = dir.path().join(e);
            std::fs::create_dir_all(&step).unwrap();
            t.moe.save(&step).unwrap();
            previous = Some(step);
        }
        let t = f.trainer(previous.as_deref(), "e2", small());
        assert_eq!(t.moe.experts(), 3);
        for text in &f.texts {
            let w = t.moe.weights(text).unwrap();
            assert_eq!(w.len(), 3);
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6, "{w:?}");
            assert_eq!(w.iter().filter(|&&v| v == 0.0).count(), 1, "{w:?}");
        }
    }

    #[test]
    fn a_new_expert_leaves_the_base_model_unchanged() {
        let f = fixture();
        let t = f.trainer(None, "e0", small());
        let weights = base_weights(&f.base.path().join("model.safetensors"), &Device::Cpu).unwrap();
        let vb = VarBuilder::from_tensors(weights, DType::F32, &Device::Cpu);
        let base = PrefixLm::new(&f.config, vb).unwrap();
        let batch = LmBatch::new(&f.config, &[&f.texts[0]], &[(&f.tokens[0], true)]);
        let want = values(&base.forward(&batch).unwrap());
        let got = values(
            &t.moe
                .for_caption(&f.texts[0])
                .unwrap()
                .forward(&batch)
                .unwrap(),
        );
        assert_eq!(got, want);
    }

    #[test]
    fn only_the_current_expert_its_key_and_the_gate_network_train() {
        let f = fixture();
        let dir = tempfile::tempdir().unwrap();
        let second = second_step(&f, dir.path());
        let all = |t: &EsMoeTrainer| -> HashMap<String, Vec<f32>> {
            let mut v = var_tensors(&t.moe.gate.vars());
            for e in &t.moe.experts {
                v.extend(var_tensors(&e.vars()));
            }
            v.into_iter().map(|(k, t)| (k, values(&t))).collect()
        };
        let before = all(&second);
        assert!(
            before["experts.e0.blocks.0.attn.wo.lora_B.weight"]
                .iter()
                .any(|&v| v != 0.0),
            "expert 0 was trained"
        );
        train_step(&second, &f);
        let after = all(&second);
        let trained = second.vars();
        for (name, value) in &after {
            let changed = *value != before[name];
            let current = name.starts_with("experts.e1.") || name == "gate.keys.1";
            if name.starts_with("experts.e0.")
                || name == "gate.keys.0"
                || name == "gate.cged.dictionary"
            {
                assert!(!changed, "{name} is frozen at step 2");
                assert!(!trained.contains_key(name));
            }
            if (current && name.ends_with("lora_B.weight")) || name == "gate.keys.1" {
                assert!(changed, "{name} trains");
            }
        }
        assert!(after["gate.query.up.weight"] != before["gate.query.up.weight"]);
    }

    #[test]
    fn gate_gradients_match_finite_differences() {
        let f = fixture();
        let dir = tempfile::tempdir().unwrap();
        let t = second_step(&f, dir.path());
        // Non-zero B for the new expert too, so both experts' weights matter.
        random_b(&t.moe.experts[1], 9);
        let examples = f.examples();
        let lambda = small().emotion_weight;
        let loss = |t: &EsMoeTrainer| {
            f64::from(t.loss_and_grads(&examples, None).unwrap().0.total(lambda))
        };
        let (_, grads) = t.loss_and_grads(&examples, None).unwrap();
        let vars = t.vars();
        for name in [
            "gate.query.up.weight",
            "gate.keys.1",
            "gate.cged.fuse.weight",
            "gate.cged.cross_q.bias",
            "gate.emotion.2.weight",
        ] {
            let var = &vars[name];
            let analytic = values(
                grads
                    .get(var.as_tensor())
                    .unwrap_or_else(|| panic!("no gradient for {name}")),
            );
            let n = var.elem_count();
            for k in [0, n / 2, n - 1] {
                let numeric = nn::gradcheck::numeric_gradient(var, k, || loss(&t));
                let a = f64::from(analytic[k]);
                assert!(
                    (a - numeric).abs() <= 1e-3 + 2e-2 * numeric.abs(),
                    "{name}[{k}]: analytic {a}, numeric {numeric}"
                );
            }
        }
    }

    #[test]
    fn expert_and_gate_gradients_agree_on_both_executors() {
        let f = fixture();
        let dir = tempfile::tempdir().unwrap();
        let mut t = second_step(&f, dir.path());
        random_b(&t.moe.experts[1], 11);
        let examples = f.examples();
        let lambda = small().emotion_weight;
        let mut run = |executor| {
            t.moe.set_compute(Compute {
                executor: Some(executor),
                ..Compute::default()
            });
            let (loss, grads) = t.loss_and_grads(&examples, None).unwrap();
            let grads: HashMap<String, Vec<f32>> = t
                .vars()
                .into_iter()
                .filter_map(|(n, v)| Some((n, values(grads.get(v.as_tensor())?))))
                .collect();
            (loss.total(lambda), grads)
        };
        let (l_cpu, g_cpu) = run(Executor::Cpu);
        for other in [Executor::Graph, Executor::Gpu] {
            let (l_graph, g_graph) = run(other);
            assert!(
                (l_cpu - l_graph).abs() <= 1e-5 * l_cpu.abs(),
                "{l_cpu} vs {l_graph}"
            );
            assert_eq!(g_cpu.len(), g_graph.len());
            let mut worst = 0f32;
            for (name, c) in &g_cpu {
                let scale = c.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
                let d = nn::gradcheck::max_abs_diff(&g_graph[name], c) / scale;
                assert!(
                    d <= 1e-5,
                    "{name}: gradients differ by {d:.2e} of their scale"
                );
                worst = worst.max(d);
            }
            eprintln!(
                "ES-MoE {other:?} vs cpu: loss {l_graph} vs {l_cpu}, {} gradients within {worst:.2e} (relative)",
                g_cpu.len()
            );
        }
    }
}
