//! AdamW with saveable state, gradient-norm clipping and a warm-up + cosine schedule, shared
//! by every training loop of the workspace (tokenizers here, transformers downstream).
//!
//! candle-nn's `AdamW` keeps its moments private, so a run could not resume from a checkpoint
//! with its optimiser state; this one keeps f32 moments where the parameter lives, updates
//! them with PyTorch's `torch.optim.AdamW` arithmetic (bias corrections included) and saves
//! them as safetensors (`m.<name>`, `v.<name>`, `step`). For f32 parameters on the CPU the
//! moments are plain vectors updated in one fused pass per parameter; elsewhere (a GPU) they
//! are f32 tensors on the parameter's device, updated with tensor ops there (no copy through
//! host memory).

use crate::cpu_f32::{contiguous_f32, F32Values};
use crate::error::NnError;
use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, DType, Device, InplaceOp2, Layout, Tensor, Var};
use motionscale_core::FileError;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;

/// AdamW hyper-parameters (the learning rate comes from the schedule at every step).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AdamWConfig {
    /// First-moment decay.
    pub beta1: f64,
    /// Second-moment decay.
    pub beta2: f64,
    /// Denominator epsilon.
    pub eps: f64,
    /// Decoupled weight decay.
    pub weight_decay: f64,
}

impl Default for AdamWConfig {
    /// PyTorch's defaults.
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 0.01,
        }
    }
}

/// Linear warm-up to `peak`, then cosine decay to `peak · final_ratio` at `total` steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LrSchedule {
    /// Peak learning rate.
    pub peak: f64,
    /// Warm-up steps.
    pub warmup: u64,
    /// Total steps (the decay ends here and stays flat after).
    pub total: u64,
    /// Final learning rate as a fraction of the peak.
    pub final_ratio: f64,
}

impl LrSchedule {
    /// Learning rate of optimiser step `step` (0-based).
    pub fn at(&self, step: u64) -> f64 {
        if step < self.warmup {
            return self.peak * (step + 1) as f64 / self.warmup as f64;
        }
        let span = self.total.saturating_sub(self.warmup).max(1) as f64;
        let progress = ((step - self.warmup) as f64 / span).min(1.0);
        let cosine = 0.5 * (1.0 + (std::f64::consts::PI * progress).cos());
        self.peak * (self.final_ratio + (1.0 - self.final_ratio) * cosine)
    }
}

/// Elements per parallel task of the update.
const CHUNK: usize = 16 * 1024;

/// The numbers of one AdamW step, shared by every parameter.
#[derive(Debug, Clone, Copy)]
struct StepValues {
    /// Gradient scale from norm clipping.
    scale: f32,
    beta: (f32, f32),
    eps: f32,
    /// Learning rate over the first moment's bias correction.
    step_size: f32,
    bias2_sqrt: f32,
    /// `1 − lr · weight_decay`.
    decay: f32,
}

impl StepValues {
    /// Update parameters `p` and moments `m`, `v` from gradient `g` (PyTorch's arithmetic).
    fn apply(&self, p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &[f32]) {
        p.par_chunks_mut(CHUNK)
            .zip(m.par_chunks_mut(CHUNK))
            .zip(v.par_chunks_mut(CHUNK))
            .zip(g.par_chunks(CHUNK))
            .for_each(|(((p, m), v), g)| step_chunk(self, p, m, v, g));
    }

    /// The same update on the parameter's device, from moments `mv` (`(2, n)`; `None`:
    /// zero): the new moments; the parameter is set in place. On a GPU one fused kernel
    /// (`nn::fused_ops`), elsewhere tensor ops.
    fn apply_device(
        &self,
        var: &Var,
        mv: Option<Tensor>,
        grad: &Tensor,
    ) -> candle_core::Result<Tensor> {
        #[cfg(feature = "cuda")]
        if var.device().is_cuda() && var.dtype() == DType::F32 && var.is_contiguous() {
            let n = var.elem_count();
            let mv = match mv {
                Some(mv) => mv,
                None => Tensor::zeros((2, n), DType::F32, var.device())?,
            };
            let grad = grad.to_dtype(DType::F32)?.contiguous()?;
            var.as_tensor()
                .inplace_op3(&grad, &mv, &DeviceUpdate(*self))?;
            return Ok(mv);
        }
        let mv = mv
            .map(|mv| Ok::<_, candle_core::Error>((mv.get(0)?, mv.get(1)?)))
            .transpose()?;
        let (m, v) = self.apply_tensors(var, mv.as_ref(), grad)?;
        Tensor::stack(&[m, v], 0)
    }

    /// The update in tensor ops, from moments `mv` (`None`: zero): the new moments.
    fn apply_tensors(
        &self,
        var: &Var,
        mv: Option<&(Tensor, Tensor)>,
        grad: &Tensor,
    ) -> candle_core::Result<(Tensor, Tensor)> {
        let (b1, b2) = self.beta;
        let g = (grad.flatten_all()?.to_dtype(DType::F32)? * f64::from(self.scale))?;
        let (m, v) = (
            (&g * f64::from(1.0 - b1))?,
            (g.sqr()? * f64::from(1.0 - b2))?,
        );
        let (m, v) = match mv {
            Some((m0, v0)) => (((m0 * f64::from(b1))? + m)?, ((v0 * f64::from(b2))? + v)?),
            None => (m, v),
        };
        let denom = ((v.sqrt()? / f64::from(self.bias2_sqrt))? + f64::from(self.eps))?;
        let p = var.as_tensor().flatten_all()?.to_dtype(DType::F32)?;
        let p = ((p * f64::from(self.decay))? - (m.div(&denom)? * f64::from(self.step_size))?)?;
        var.set(&p.reshape(var.shape())?.to_dtype(var.dtype())?)?;
        Ok((m, v))
    }

    /// One chunk of the update; iterators rather than indices, so that it vectorises.
    #[inline(always)]
    fn chunk(&self, p: &mut [f32], m: &mut [f32], v: &mut [f32], g: &[f32]) {
        let (b1, b2) = self.beta;
        for (((p, m), v), &g) in p.iter_mut().zip(m).zip(v).zip(g) {
            let g = g * self.scale;
            *m = b1 * *m + (1.0 - b1) * g;
            *v = b2 * *v + (1.0 - b2) * g * g;
            let denom = v.sqrt() / self.bias2_sqrt + self.eps;
            *p = *p * self.decay - self.step_size * *m / denom;
        }
    }
}

crate::vectorised!(
    /// [`StepValues::chunk`] at the CPU's widest vectors: its square roots and divisions are
    /// most of the optimiser's time. Exactly rounded at every width (no FMA contraction), so
    /// the values do not depend on the path.
    fn step_chunk / step_chunk_at(
        values: &StepValues,
        p: &mut [f32],
        m: &mut [f32],
        v: &mut [f32],
        g: &[f32],
    ) = StepValues::chunk;
);

/// One parameter's update applied in place to its storage, reading the gradient where it
/// lies, instead of copying the parameter out and back and the gradient out. The moments sit
/// behind a lock only because candle hands the op `&self`.
struct Update<'a> {
    moments: Mutex<(&'a mut [f32], &'a mut [f32])>,
    step: StepValues,
}

impl InplaceOp2 for Update<'_> {
    fn name(&self) -> &'static str {
        "adamw-update"
    }

    fn cpu_fwd(
        &self,
        p: &mut CpuStorage,
        pl: &Layout,
        g: &CpuStorage,
        gl: &Layout,
    ) -> candle_core::Result<()> {
        let g = contiguous_f32(g, gl, "gradient")?;
        let (start, end) = pl
            .contiguous_offsets()
            .ok_or_else(|| candle_core::Error::Msg("adamw: parameter not contiguous".into()))?;
        let CpuStorage::F32(p) = p else {
            candle_core::bail!("adamw: parameter is not f32");
        };
        let mut moments = self.moments.lock().expect("adamw moments lock");
        let (m, v) = &mut *moments;
        self.step.apply(&mut p[start..end], m, v, g);
        Ok(())
    }
}

/// One parameter's update on a GPU: the kernel `adamw_step` over the parameter in place, its
/// gradient and its moments `(2, n)`.
#[cfg(feature = "cuda")]
struct DeviceUpdate(StepValues);

#[cfg(feature = "cuda")]
impl candle_core::InplaceOp3 for DeviceUpdate {
    fn name(&self) -> &'static str {
        "adamw-update-device"
    }

    fn cpu_fwd(
        &self,
        _: &mut CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<()> {
        candle_core::bail!("adamw: the device update runs on a GPU only")
    }

    fn cuda_fwd(
        &self,
        p: &mut candle_core::CudaStorage,
        lp: &Layout,
        g: &candle_core::CudaStorage,
        lg: &Layout,
        mv: &candle_core::CudaStorage,
        lmv: &Layout,
    ) -> candle_core::Result<()> {
        let s = &self.0;
        let values = [
            s.scale,
            s.beta.0,
            s.beta.1,
            s.eps,
            s.step_size,
            s.bias2_sqrt,
            s.decay,
        ];
        crate::fused_ops::gpu::adamw_step(p, lp, (g, lg), (mv, lmv), values)
    }
}

/// The first and second moments of one parameter.
enum Moments {
    /// f32 CPU parameters: updated by the fused pass.
    Host { m: Vec<f32>, v: Vec<f32> },
    /// Parameters elsewhere: one f32 tensor `(2, n)`, m then v, on the parameter's device
    /// (`None` while both are zero, before the first step).
    Device(Option<Tensor>),
}

impl Moments {
    /// Zero moments for `var`, where it lives.
    fn zeros(var: &Var) -> Self {
        let n = var.elem_count();
        if var.device().is_cpu() && var.dtype() == DType::F32 {
            Self::Host {
                m: vec![0.0; n],
                v: vec![0.0; n],
            }
        } else {
            Self::Device(None)
        }
    }

    /// `(m, v)` of `n` values as host vectors (for saving).
    fn to_host(&self, n: usize) -> Result<(Vec<f32>, Vec<f32>), NnError> {
        Ok(match self {
            Self::Host { m, v } => (m.clone(), v.clone()),
            Self::Device(Some(mv)) => (mv.get(0)?.to_vec1()?, mv.get(1)?.to_vec1()?),
            Self::Device(None) => (vec![0.0; n], vec![0.0; n]),
        })
    }

    /// Replace the moments of `var` by saved values of its length.
    fn restore(&mut self, var: &Var, m: Vec<f32>, v: Vec<f32>) -> Result<(), NnError> {
        match self {
            Self::Host { m: hm, v: hv } => (*hm, *hv) = (m, v),
            Self::Device(moments) => {
                let n = m.len();
                *moments = Some(Tensor::from_vec([m, v].concat(), (2, n), var.device())?);
            }
        }
        Ok(())
    }
}

/// One parameter with its moments.
struct Slot {
    name: String,
    var: Var,
    moments: Moments,
}

/// AdamW over named variables.
pub struct AdamW {
    config: AdamWConfig,
    slots: Vec<Slot>,
    step: u64,
}

impl AdamW {
    /// An optimiser for `vars` (name → variable, e.g. `VarMap::data()`), sorted by name;
    /// the moments live on each variable's device.
    pub fn new(vars: &HashMap<String, Var>, config: AdamWConfig) -> Self {
        let mut names: Vec<&String> = vars.keys().collect();
        names.sort();
        let slots = names
            .into_iter()
            .map(|name| Slot {
                name: name.clone(),
                var: vars[name].clone(),
                moments: Moments::zeros(&vars[name]),
            })
            .collect();
        Self {
            config,
            slots,
            step: 0,
        }
    }

    /// Optimiser steps taken so far.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// One AdamW step at learning rate `lr`, gradients first scaled so their global norm is
    /// at most `max_norm` (none when `None`). Variables without a gradient are left alone.
    /// Returns the global gradient norm before clipping.
    pub fn step(
        &mut self,
        grads: &GradStore,
        lr: f64,
        max_norm: Option<f64>,
    ) -> Result<f64, NnError> {
        let grads: Vec<Option<&Tensor>> = self
            .slots
            .iter()
            .map(|slot| grads.get(slot.var.as_tensor()))
            .collect();
        // Sums of squares per fixed chunk in parallel, added in order: deterministic.
        let mut squares = Vec::new();
        // Off the CPU, one sum per gradient, read back together: one wait for the device.
        let mut device_sums = Vec::new();
        for g in grads.iter().flatten() {
            if !g.device().is_cpu() {
                device_sums.push(crate::fused_ops::sum_of_squares(&g.to_dtype(DType::F32)?)?);
                continue;
            }
            let g = F32Values::of(g)?;
            squares.extend(
                g.par_chunks(CHUNK)
                    .map(|c| c.iter().map(|&v| (v as f64) * (v as f64)).sum::<f64>())
                    .collect::<Vec<_>>(),
            );
        }
        if !device_sums.is_empty() {
            let sums = Tensor::cat(&device_sums, 0)?.to_vec1::<f32>()?;
            squares.extend(sums.into_iter().map(f64::from));
        }
        let norm = squares.iter().sum::<f64>().sqrt();
        let scale = match max_norm {
            Some(max) if norm > max => (max / (norm + 1e-6)) as f32,
            _ => 1.0,
        };
        self.step += 1;
        let c = self.config;
        let t = self.step as i32;
        let (bias1, bias2) = (1.0 - c.beta1.powi(t), 1.0 - c.beta2.powi(t));
        let step = StepValues {
            scale,
            beta: (c.beta1 as f32, c.beta2 as f32),
            eps: c.eps as f32,
            step_size: (lr / bias1) as f32,
            bias2_sqrt: bias2.sqrt() as f32,
            decay: (1.0 - lr * c.weight_decay) as f32,
        };
        for (slot, grad) in self.slots.iter_mut().zip(grads) {
            let Some(grad) = grad else {
                continue;
            };
            match &mut slot.moments {
                Moments::Host { m, v } => {
                    let update = Update {
                        moments: Mutex::new((&mut m[..], &mut v[..])),
                        step,
                    };
                    slot.var
                        .as_tensor()
                        .inplace_op2(&grad.contiguous()?, &update)?;
                }
                Moments::Device(moments) => {
                    *moments = Some(step.apply_device(&slot.var, moments.take(), grad)?)
                }
            }
        }
        Ok(norm)
    }

    /// Save the moments and step count as safetensors.
    pub fn save(&self, path: &Path) -> Result<(), NnError> {
        let mut tensors = HashMap::new();
        for slot in &self.slots {
            let (m, v) = slot.moments.to_host(slot.var.elem_count())?;
            let n = m.len();
            tensors.insert(
                format!("m.{}", slot.name),
                Tensor::from_vec(m, n, &Device::Cpu)?,
            );
            tensors.insert(
                format!("v.{}", slot.name),
                Tensor::from_vec(v, n, &Device::Cpu)?,
            );
        }
        // The step as two u32 halves: safetensors in candle has no u64 tensors.
        let halves = [(self.step & 0xffff_ffff) as u32, (self.step >> 32) as u32];
        tensors.insert("step".into(), Tensor::from_slice(&halves, 2, &Device::Cpu)?);
        Ok(crate::checkpoint::save_safetensors(&tensors, path)?)
    }

    /// Restore the moments and step count saved by [`AdamW::save`] for the same variables.
    pub fn load(&mut self, path: &Path) -> Result<(), NnError> {
        let file_error = |message: String| NnError::File(FileError::invalid(path, message));
        let tensors = candle_core::safetensors::load(path, &Device::Cpu)
            .map_err(|e| file_error(e.to_string()))?;
        let get = |key: &str| {
            tensors
                .get(key)
                .ok_or_else(|| file_error(format!("no tensor {key}")))
        };
        for slot in &mut self.slots {
            let read = |kind: &str| -> Result<Vec<f32>, NnError> {
                let key = format!("{kind}.{}", slot.name);
                let values = get(&key)?.to_vec1::<f32>()?;
                if values.len() != slot.var.elem_count() {
                    return Err(file_error(format!(
                        "{key} has {} values, the variable {}",
                        values.len(),
                        slot.var.elem_count()
                    )));
                }
                Ok(values)
            };
            let (m, v) = (read("m")?, read("v")?);
            slot.moments.restore(&slot.var, m, v)?;
        }
        let halves = get("step")?.to_vec1::<u32>()?;
        self.step = u64::from(halves[0]) | (u64::from(halves[1]) << 32);
        Ok(())
    }
}

/// Three clipped steps with weight decay on `var`, each from the gradient of Σ var³ at a
/// rising learning rate: the comparison of the optimiser's update paths.
fn three_clipped_steps(var: &Var, opt: &mut AdamW) -> Result<(), NnError> {
    for step in 0..3 {
        let grads = var.as_tensor().powf(3.0)?.sum_all()?.backward()?;
        opt.step(&grads, 1e-2 * (step + 1) as f64, Some(5.0))?;
    }
    Ok(())
}

/// The seeded 20 × 15 parameter of [`three_clipped_steps`] on `device`, with its optimiser.
fn seeded_parameter(device: &Device) -> Result<(Var, AdamW), NnError> {
    let values: Vec<f32> = (0..300)
        .map(|i| ((i * 37 % 101) as f32 - 50.0) / 40.0)
        .collect();
    let var = Var::from_vec(values, (20, 15), device)?;
    let config = AdamWConfig {
        weight_decay: 0.1,
        ..AdamWConfig::default()
    };
    let opt = AdamW::new(&HashMap::from([("w".into(), var.clone())]), config);
    Ok((var, opt))
}

/// Three clipped AdamW steps on `device` (on a GPU, the fused kernel) against the fused host
/// pass on the CPU: the largest parameter difference over the largest parameter.
pub fn device_agreement(device: &Device) -> Result<f32, NnError> {
    let run = |on: &Device| -> Result<Vec<f32>, NnError> {
        let (var, mut opt) = seeded_parameter(on)?;
        three_clipped_steps(&var, &mut opt)?;
        Ok(var
            .as_tensor()
            .flatten_all()?
            .to_device(&Device::Cpu)?
            .to_vec1()?)
    };
    let (host, there) = (run(&Device::Cpu)?, run(device)?);
    let scale = host.iter().fold(f32::MIN_POSITIVE, |m, v| m.max(v.abs()));
    Ok(crate::gradcheck::max_abs_diff(&host, &there) / scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// AdamW's chunk update gives the same bits at every vector level.
    #[test]
    fn step_chunk_agrees_at_every_vector_level() {
        let values = StepValues {
            scale: 0.7,
            beta: (0.9, 0.95),
            eps: 1e-8,
            step_size: 3e-4,
            bias2_sqrt: 0.3,
            decay: 0.999,
        };
        let mut rng = motionscale_core::rng::SplitMix64(5);
        let mut draw =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect() };
        let (p, m, g) = (draw(1001), draw(1001), draw(1001));
        let v: Vec<f32> = draw(1001).iter().map(|x| x * x).collect();
        crate::simd::assert_levels_agree(|isa| {
            let (mut p, mut m, mut v) = (p.clone(), m.clone(), v.clone());
            step_chunk_at(isa, &values, &mut p, &mut m, &mut v, &g);
            crate::simd::bits(&[p, m, v].concat())
        });
    }

    #[test]
    fn schedule_warms_up_linearly_then_decays_by_cosine() {
        let s = LrSchedule {
            peak: 1.0,
            warmup: 4,
            total: 14,
            final_ratio: 0.1,
        };
        assert_eq!(s.at(0), 0.25);
        assert_eq!(s.at(3), 1.0);
        assert_eq!(s.at(4), 1.0);
        // Halfway through the decay the cosine factor is 1/2: 0.1 + 0.9 · 0.5.
        assert!((s.at(9) - 0.55).abs() < 1e-12);
        assert!((s.at(14) - 0.1).abs() < 1e-12);
        assert!((s.at(100) - 0.1).abs() < 1e-12);
    }

    #[test]
    fn two_steps_match_a_hand_computation() {
        // One scalar parameter p = 1, loss = 3p (gradient 3), lr 0.1, wd 0.5.
        let var = Var::new(&[1f32], &Device::Cpu).unwrap();
        let vars = HashMap::from([("p".to_string(), var.clone())]);
        let config = AdamWConfig {
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-8,
            weight_decay: 0.5,
        };
        let mut opt = AdamW::new(&vars, config);
        let mut expected = 1f64;
        let (mut m, mut v) = (0f64, 0f64);
        for t in 1..=2 {
            let grads = (var.as_tensor() * 3.0)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            opt.step(&grads, 0.1, None).unwrap();
            m = 0.9 * m + 0.1 * 3.0;
            v = 0.99 * v + 0.01 * 9.0;
            let m_hat = m / (1.0 - 0.9f64.powi(t));
            let v_hat = v / (1.0 - 0.99f64.powi(t));
            expected = expected * (1.0 - 0.1 * 0.5) - 0.1 * m_hat / (v_hat.sqrt() + 1e-8);
        }
        let got = var.as_tensor().to_vec1::<f32>().unwrap()[0] as f64;
        assert!((got - expected).abs() < 1e-6, "{got} vs {expected}");
    }

    #[test]
    fn clipping_scales_the_gradient_to_the_max_norm() {
        // Gradient (3, 4) has norm 5; clipped to 1 the first Adam step is unchanged in
        // direction (Adam normalises), so check the reported norm and the moments instead.
        let var = Var::new(&[0f32, 0.0], &Device::Cpu).unwrap();
        let vars = HashMap::from([("p".to_string(), var.clone())]);
        let w = Tensor::new(&[3f32, 4.0], &Device::Cpu).unwrap();
        let grads = (var.as_tensor() * &w)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let mut opt = AdamW::new(&vars, AdamWConfig::default());
        let norm = opt.step(&grads, 0.0, Some(1.0)).unwrap();
        assert!((norm - 5.0).abs() < 1e-6);
        let (m, _) = opt.slots[0].moments.to_host(2).unwrap();
        assert!((m[0] - 0.1 * 0.6).abs() < 1e-6 && (m[1] - 0.1 * 0.8).abs() < 1e-6);
    }

    #[test]
    fn save_and_load_restore_the_state() {
        let dir = tempfile::tempdir().unwrap();
        let var = Var::new(&[1f32, 2.0], &Device::Cpu).unwrap();
        let vars = HashMap::from([("w".to_string(), var.clone())]);
        let mut opt = AdamW::new(&vars, AdamWConfig::default());
        let grads = var
            .as_tensor()
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        opt.step(&grads, 0.01, None).unwrap();
        let path = dir.path().join("optimizer.safetensors");
        opt.save(&path).unwrap();
        let mut restored = AdamW::new(&vars, AdamWConfig::default());
        restored.load(&path).unwrap();
        assert_eq!(restored.steps(), 1);
        assert_eq!(
            restored.slots[0].moments.to_host(2).unwrap(),
            opt.slots[0].moments.to_host(2).unwrap()
        );
    }

    #[test]
    fn moments_kept_as_tensors_update_as_the_fused_pass_does() {
        // The path of parameters off the CPU, run here on CPU tensors, against the fused
        // host pass: same parameters and moments after a few clipped steps.
        let (host, mut opt_host) = seeded_parameter(&Device::Cpu).unwrap();
        let (tensors, mut opt_tensors) = seeded_parameter(&Device::Cpu).unwrap();
        opt_tensors.slots[0].moments = Moments::Device(None);
        three_clipped_steps(&host, &mut opt_host).unwrap();
        three_clipped_steps(&tensors, &mut opt_tensors).unwrap();
        let flat = |v: &Var| {
            v.as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        };
        let worst = crate::gradcheck::max_abs_diff(&flat(&host), &flat(&tensors));
        assert!(worst <= 1e-6, "parameters differ by {worst}");
        let (mh, vh) = opt_host.slots[0].moments.to_host(300).unwrap();
        let (mt, vt) = opt_tensors.slots[0].moments.to_host(300).unwrap();
        assert!(crate::gradcheck::max_abs_diff(&mh, &mt) <= 1e-6);
        assert!(crate::gradcheck::max_abs_diff(&vh, &vt) <= 1e-6);
    }
}
