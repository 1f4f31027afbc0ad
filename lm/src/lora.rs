//! Low-rank adapters (LoRA) on the prefix LM's attention and FFN projections, by
//! reparameterisation: the model runs with W' = W + (α/r)·B·A for every adapted projection W
//! (base frozen), so [`PrefixLm`]'s own forward and backward serve unchanged, and the
//! adapters' gradients follow from W's by the chain rule: ∂L/∂B = s·(∂L/∂W')·Aᵀ and
//! ∂L/∂A = s·Bᵀ·(∂L/∂W') (s = α/r).
//!
//! Shapes and names follow PEFT: `lora_A` is `r × in` (Kaiming-uniform, PyTorch's
//! `nn.Linear` bound 1/√in), `lora_B` is `out × r` (zeros, so a new adapter leaves the model
//! unchanged). Adapters of several experts share one safetensors file, keyed
//! `experts.<expert>.blocks.<i>.<projection>.lora_{A,B}.weight`.

use crate::prefix_lm::{Compute, PrefixLm, PrefixLmConfig};
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var};
use candle_nn::VarBuilder;
use motionscale_core::rng::SplitMix64;
use nn::ModelError;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;

/// The adapter file of a run folder (every expert of the run).
pub const ADAPTER_FILE: &str = "adapter.safetensors";

/// The adapted projections of every block (the attention's QKV and output, the FFN's
/// gate/up and down projections).
pub const TARGETS: [&str; 4] = ["attn.wqkv", "attn.wo", "ffn.w13", "ffn.w2"];

/// Rank and scale of an adapter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LoraConfig {
    /// Rank r.
    pub rank: usize,
    /// α: the update is scaled by α/r.
    pub alpha: f64,
}

impl LoraConfig {
    /// The scale α/r.
    pub fn scale(&self) -> f64 {
        self.alpha / self.rank as f64
    }
}

/// One adapter (one expert): an (A, B) pair for every adapted projection.
pub struct LoraAdapter {
    /// Rank and scale.
    pub config: LoraConfig,
    /// Expert name (its key prefix in the adapter file).
    pub expert: String,
    /// `(weight name, A, B)` per adapted projection, in block and [`TARGETS`] order.
    pairs: Vec<(String, Var, Var)>,
    /// Where A and B live.
    device: Device,
}

/// Name and `(out, in)` shape of every adapted weight of a model.
fn targets(model: &PrefixLmConfig) -> Vec<(String, (usize, usize))> {
    let (d, f) = (model.d_model, model.ffn_hidden);
    let shapes = [(3 * d, d), (d, d), (2 * f, d), (d, f)];
    (0..model.n_layers)
        .flat_map(|i| {
            TARGETS
                .iter()
                .zip(shapes)
                .map(move |(t, shape)| (format!("blocks.{i}.{t}.weight"), shape))
        })
        .collect()
}

impl LoraAdapter {
    /// A new adapter for `model` on `device`: A drawn from `seed`, B zero.
    pub fn new(
        model: &PrefixLmConfig,
        config: LoraConfig,
        expert: &str,
        seed: u64,
        device: &Device,
    ) -> Result<Self> {
        let pairs = targets(model)
            .into_iter()
            .enumerate()
            .map(|(k, (name, (out, inp)))| {
                let bound = 1.0 / (inp as f64).sqrt();
                let mut rng = SplitMix64::stream(seed, k as u64);
                let a: Vec<f32> = (0..config.rank * inp)
                    .map(|_| rng.range(-bound, bound) as f32)
                    .collect();
                let a = Var::from_tensor(&Tensor::from_vec(a, (config.rank, inp), device)?)?;
                let b = Var::zeros((out, config.rank), DType::F32, device)?;
                Ok((name, a, b))
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            config,
            expert: expert.to_string(),
            pairs,
            device: device.clone(),
        })
    }

    /// The trainable variables, named as in the adapter file.
    pub fn vars(&self) -> HashMap<String, Var> {
        self.pairs
            .iter()
            .flat_map(|(name, a, b)| {
                let stem = self.key(name);
                [
                    (format!("{stem}.lora_A.weight"), a.clone()),
                    (format!("{stem}.lora_B.weight"), b.clone()),
                ]
            })
            .collect()
    }

    /// `experts.<expert>.<projection>` for the weight `blocks.<i>.<projection>.weight`.
    fn key(&self, weight: &str) -> String {
        let stem = weight.strip_suffix(".weight").unwrap_or(weight);
        format!("experts.{}.{stem}", self.expert)
    }

    /// The update s·B·A of every adapted weight, by weight name.
    pub fn deltas(&self) -> Result<Vec<(String, Tensor)>> {
        let scale = self.config.scale();
        self.pairs
            .iter()
            .map(|(name, a, b)| {
                Ok((
                    name.clone(),
                    (b.as_tensor().matmul(a.as_tensor())? * scale)?,
                ))
            })
            .collect()
    }

    /// The base weights with every adapted projection replaced by W + s·B·A.
    pub fn merge(&self, base: &HashMap<String, Tensor>) -> Result<HashMap<String, Tensor>> {
        add_deltas(base, &[(1.0, self.deltas()?)])
    }

    /// The model with this adapter merged into `base`, run with `compute` (its weight
    /// tensors are the entries of the returned map, so gradients keyed by them can be read
    /// back).
    pub fn merged_model(
        &self,
        config: &PrefixLmConfig,
        base: &HashMap<String, Tensor>,
        compute: Compute,
    ) -> Result<(PrefixLm, HashMap<String, Tensor>)> {
        let merged = self.merge(base)?;
        let model = merged_lm(config, &merged, compute)?;
        Ok((model, merged))
    }

    /// The device of the adapter's matrices.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The adapter's gradients from the gradients of the merged weights (chain rule).
    pub fn grads(&self, merged: &HashMap<String, Tensor>, grads: &GradStore) -> Result<GradStore> {
        let by_name: HashMap<String, Tensor> = self
            .pairs
            .iter()
            .filter_map(|(name, _, _)| Some((name.clone(), grads.get(&merged[name])?.clone())))
            .collect();
        self.grads_by_name(&by_name)
    }

    /// The adapter's gradients from the gradients of the adapted weights, by weight name
    /// (∂L/∂B = s·G·Aᵀ, ∂L/∂A = s·Bᵀ·G; weights without a gradient give none).
    pub fn grads_by_name(&self, grads: &HashMap<String, Tensor>) -> Result<GradStore> {
        let scale = self.config.scale();
        let mut out = GradStore::default();
        for (name, a, b) in &self.pairs {
            let Some(g) = grads.get(name) else {
                continue;
            };
            let gb = (g.matmul(&a.as_tensor().t()?)? * scale)?;
            let ga = (b.as_tensor().t()?.matmul(g)? * scale)?;
            out.insert(a.as_tensor(), ga);
            out.insert(b.as_tensor(), gb);
        }
        Ok(out)
    }

    /// Load this expert's A and B from an adapter file.
    pub fn load(&self, path: &Path) -> std::result::Result<(), ModelError> {
        let tensors = base_weights(path, self.device())?;
        for (key, var) in self.vars() {
            let t = tensors
                .get(&key)
                .ok_or_else(|| ModelError::invalid(path, format!("no tensor {key}")))?;
            var.set(t).map_err(|e| ModelError::invalid(path, e))?;
        }
        Ok(())
    }
}

/// The model whose weights are `weights` (by name, as a model file holds them), run with
/// `compute`.
pub fn merged_lm(
    config: &PrefixLmConfig,
    weights: &HashMap<String, Tensor>,
    compute: Compute,
) -> Result<PrefixLm> {
    let device = weights
        .get("head.weight")
        .ok_or_else(|| candle_core::Error::Msg("the weights have no head.weight".into()))?
        .device()
        .clone();
    let vb = VarBuilder::from_tensors(weights.clone(), DType::F32, &device);
    Ok(PrefixLm::new(config, vb)?.with_compute(compute))
}

/// `base` with weighted updates added: W + Σ_j w_j·ΔW_j for every weight the updates name
/// (`(w_j, [(weight name, ΔW_j)])` per adapter; a zero weight adds nothing).
pub fn add_deltas(
    base: &HashMap<String, Tensor>,
    updates: &[(f32, Vec<(String, Tensor)>)],
) -> Result<HashMap<String, Tensor>> {
    let mut merged = base.clone();
    for (weight, deltas) in updates {
        if *weight == 0.0 {
            continue;
        }
        for (name, delta) in deltas {
            let w = merged
                .get(name)
                .ok_or_else(|| candle_core::Error::Msg(format!("base has no {name}")))?;
            let update = if *weight == 1.0 {
                delta.clone()
            } else {
                (delta * f64::from(*weight))?
            };
            merged.insert(name.clone(), (w + update)?);
        }
    }
    Ok(merged)
}

/// The `lora_A` matrices of every expert in an adapter file, by the weight they adapt
/// (`blocks.<i>.<projection>.weight`): the subspaces an O-LoRA adapter keeps orthogonal to.
pub fn adapter_a_matrices(
    path: &Path,
    device: &Device,
) -> std::result::Result<Vec<HashMap<String, Tensor>>, ModelError> {
    let tensors = base_weights(path, device)?;
    let mut by_expert: std::collections::BTreeMap<String, HashMap<String, Tensor>> =
        std::collections::BTreeMap::new();
    for (key, t) in tensors {
        let Some(rest) = key.strip_prefix("experts.") else {
            continue;
        };
        let Some(stem) = rest.strip_suffix(".lora_A.weight") else {
            continue;
        };
        let Some((expert, projection)) = stem.split_once('.') else {
            continue;
        };
        by_expert
            .entry(expert.to_string())
            .or_default()
            .insert(format!("{projection}.weight"), t);
    }
    Ok(by_expert.into_values().collect())
}

impl LoraAdapter {
    /// O-LoRA's orthogonality loss λ·Σ_p Σ_proj ‖A·A_pᵀ‖²_F against earlier adapters' A
    /// matrices; its gradient 2λ·Σ_p (A·A_pᵀ)·A_p is added to `grads`. Returns the loss.
    pub fn orthogonality(
        &self,
        previous: &[HashMap<String, Tensor>],
        weight: f64,
        grads: &mut GradStore,
    ) -> Result<f32> {
        let mut loss = 0f32;
        for (name, a, _) in &self.pairs {
            let a_t = a.as_tensor();
            let mut grad = match grads.get(a_t) {
                Some(g) => g.clone(),
                None => a_t.zeros_like()?,
            };
            for p in previous {
                let Some(ap) = p.get(name) else { continue };
                let overlap = a_t.matmul(&ap.t()?)?;
                loss += (overlap.sqr()?.sum_all()?.to_scalar::<f32>()?) * weight as f32;
                grad = (grad + (overlap.matmul(ap)? * (2.0 * weight))?)?;
            }
            grads.insert(a_t, grad);
        }
        Ok(loss)
    }
}

/// Every weight of a model file, by name, on `device`.
pub fn base_weights(
    path: &Path,
    device: &Device,
) -> std::result::Result<HashMap<String, Tensor>, ModelError> {
    candle_core::safetensors::load(path, device).map_err(|e| ModelError::invalid(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prefix_lm::{init_model, Executor, LmBatch};
    use nn::gradcheck::numeric_gradient;

    fn weights(varmap: &candle_nn::VarMap) -> HashMap<String, Tensor> {
        varmap
            .data()
            .lock()
            .unwrap()
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect()
    }

    fn batch(config: &PrefixLmConfig) -> LmBatch {
        let mut rng = SplitMix64(5);
        let text: Vec<f32> = (0..3 * config.text_dim)
            .map(|_| rng.range(-1.0, 1.0) as f32)
            .collect();
        let motion: Vec<u32> = vec![1, 4, 7, 2, 9];
        LmBatch::new(config, &[&text], &[(&motion, false)])
    }

    /// A seeded base model of `layers` blocks, its weights and a new rank-`rank` adapter.
    fn fixture(
        layers: usize,
        rank: usize,
    ) -> (
        PrefixLmConfig,
        PrefixLm,
        HashMap<String, Tensor>,
        LoraAdapter,
    ) {
        let config = PrefixLmConfig::new(32, layers, 4, 20, 6);
        let (base, varmap) = init_model(&config, 1, &Device::Cpu).unwrap();
        let lora = LoraConfig {
            rank,
            alpha: 2.0 * rank as f64,
        };
        let adapter = LoraAdapter::new(&config, lora, "e0", 2, &Device::Cpu).unwrap();
        (config, base, weights(&varmap), adapter)
    }

    /// Every B of `lora` drawn from U(−0.1, 0.1) with `seed` (a new adapter's are zero).
    fn random_b(lora: &LoraAdapter, seed: u64) {
        let mut rng = SplitMix64(seed);
        for (_, _, b) in &lora.pairs {
            let values: Vec<f32> = (0..b.elem_count())
                .map(|_| rng.range(-0.1, 0.1) as f32)
                .collect();
            b.set(&Tensor::from_vec(values, b.dims(), &Device::Cpu).unwrap())
                .unwrap();
        }
    }

    fn loss(model: &PrefixLm, b: &LmBatch) -> f64 {
        f64::from(model.loss_and_grads(b).unwrap().0)
    }

    #[test]
    fn a_new_adapter_leaves_the_model_unchanged() {
        let (config, base, w, lora) = fixture(2, 4);
        let (merged, _) = lora.merged_model(&config, &w, Compute::default()).unwrap();
        let b = batch(&config);
        let (x, y) = (base.forward(&b).unwrap(), merged.forward(&b).unwrap());
        let diff: f32 = (x - y)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar()
            .unwrap();
        assert_eq!(diff, 0.0);
        assert_eq!(lora.vars().len(), 2 * 4 * config.n_layers);
    }

    #[test]
    fn orthogonality_is_zero_for_orthogonal_subspaces_and_its_gradient_is_exact() {
        let (_, _, _, lora) = fixture(1, 2);
        let name = "blocks.0.attn.wo.weight".to_string();
        let a = lora.vars()["experts.e0.blocks.0.attn.wo.lora_A.weight"].clone();
        // A = rows e0, e1 of R^32; previous A = rows e2, e3: orthogonal, then overlapping.
        let basis = |rows: [usize; 2]| {
            let mut v = vec![0f32; 2 * 32];
            v[rows[0]] = 1.0;
            v[32 + rows[1]] = 1.0;
            Tensor::from_vec(v, (2, 32), &Device::Cpu).unwrap()
        };
        a.set(&basis([0, 1])).unwrap();
        let previous = vec![HashMap::from([(name.clone(), basis([2, 3]))])];
        let mut grads = GradStore::default();
        assert_eq!(lora.orthogonality(&previous, 0.5, &mut grads).unwrap(), 0.0);
        let overlapping = vec![HashMap::from([(name, basis([0, 3]))])];
        let mut grads = GradStore::default();
        // A·A_pᵀ = [[1, 0], [0, 0]]: loss 0.5·1; gradient 2·0.5·(A·A_pᵀ)·A_p = e0 in row 0.
        assert_eq!(
            lora.orthogonality(&overlapping, 0.5, &mut grads).unwrap(),
            0.5
        );
        let g: Vec<f32> = grads
            .get(a.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert_eq!(g[0], 1.0);
        assert_eq!(g.iter().sum::<f32>(), 1.0);
    }

    #[test]
    fn adapter_gradients_match_finite_differences() {
        let (config, _, w, lora) = fixture(1, 2);
        // Non-zero B, so both A and B have gradients.
        random_b(&lora, 9);
        let b = batch(&config);
        let (model, merged) = lora.merged_model(&config, &w, Compute::default()).unwrap();
        let (_, g) = model.loss_and_grads(&b).unwrap();
        let g = lora.grads(&merged, &g).unwrap();
        for (name, var) in lora.vars() {
            let analytic: Vec<f32> = g
                .get(var.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let values: Vec<f32> = var.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            for k in [0, values.len() / 2, values.len() - 1] {
                let numeric = numeric_gradient(&var, k, || {
                    loss(
                        &lora
                            .merged_model(&config, &w, Compute::default())
                            .unwrap()
                            .0,
                        &b,
                    )
                });
                let a = f64::from(analytic[k]);
                assert!(
                    (a - numeric).abs() <= 2e-3 + 2e-2 * numeric.abs(),
                    "{name}[{k}]: analytic {a}, numeric {numeric}"
                );
            }
        }
    }

    #[test]
    fn adapter_gradients_agree_on_both_executors() {
        let (config, _, w, lora) = fixture(2, 4);
        random_b(&lora, 10);
        let b = batch(&config);
        let run = |executor| {
            let compute = Compute {
                executor: Some(executor),
                ..Compute::default()
            };
            let (model, merged) = lora.merged_model(&config, &w, compute).unwrap();
            let (loss, g) = model.loss_and_grads(&b).unwrap();
            (loss, lora.grads(&merged, &g).unwrap())
        };
        let (l_cpu, g_cpu) = run(Executor::Cpu);
        for other in [Executor::Graph, Executor::Gpu] {
            let (l_graph, g_graph) = run(other);
            assert!(
                (l_cpu - l_graph).abs() <= 1e-5 * l_cpu.abs(),
                "{l_cpu} vs {l_graph}"
            );
            let mut worst = 0f32;
            for (name, var) in lora.vars() {
                let values = |g: &GradStore| -> Vec<f32> {
                    g.get(var.as_tensor())
                        .unwrap()
                        .flatten_all()
                        .unwrap()
                        .to_vec1()
                        .unwrap()
                };
                let (a, c) = (values(&g_graph), values(&g_cpu));
                let scale = c.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
                let d = nn::gradcheck::max_abs_diff(&a, &c) / scale;
                assert!(
                    d <= 1e-5,
                    "{name}: gradients differ by {d:.2e} of their scale"
                );
                worst = worst.max(d);
            }
            eprintln!("LoRA {other:?} vs cpu: loss {l_graph} vs {l_cpu}, gradients {worst:.2e} (relative)");
        }
    }
}
