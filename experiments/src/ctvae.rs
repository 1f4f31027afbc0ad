//! BI-CTVAE (`../shared/docs/continual.md`; the CL2Gen paper): an action-conditioned temporal
//! VAE over normalised 263-d pose features with one trainable Gaussian mode per class.
//!
//! - Encoder: a stacked GRU over `[pose_t, one-hot(a), t / max_frames]`; its top state after
//!   the last real frame gives μ and log σ² of z.
//! - Decoder: a stacked GRU over `[z, one-hot(a), t / max_frames]` at every frame, then a
//!   linear map to the pose.
//! - Modes: μ_a and log σ_a² per class (`modes.mu`, `modes.logvar`, `classes × latent`); the
//!   latent loss is KL(N(μ, σ²) ‖ N(μ_a, σ_a²)) instead of the N(0, I) prior, and replay
//!   samples class a from its mode.
//!
//! Parameter names follow PyTorch (`encoder.gru.weight_ih_l0`, `decoder.out.weight`…:
//! `nn.GRU(num_layers=n, batch_first=True)` and `nn.Linear`).

use candle_core::{DType, Device, Module, Result, Tensor};
use candle_nn::{Init, Linear, VarBuilder};
use motionscale_core::rng::SplitMix64;
use nn::gru::{GruOutput, StackedGru};
use serde::{Deserialize, Serialize};

/// The shape of a BI-CTVAE.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CtvaeConfig {
    /// Pose feature width (263).
    pub feature_dim: usize,
    /// Action classes, in one-hot and mode order.
    pub classes: Vec<String>,
    /// GRU layers of the encoder and of the decoder.
    pub layers: usize,
    /// GRU width.
    pub hidden: usize,
    /// Width of z.
    pub latent: usize,
    /// Frames that map to time index 1 (the longest training window).
    pub max_frames: usize,
}

impl CtvaeConfig {
    /// The paper's shape: 8-layer GRUs of 256, z of 256, windows up to 100 frames.
    pub fn paper(classes: Vec<String>) -> Self {
        Self {
            feature_dim: ingest::hml263::FEATURE_DIM,
            classes,
            layers: 8,
            hidden: 256,
            latent: 256,
            max_frames: 100,
        }
    }

    /// A CPU-sized shape: 2-layer GRUs of 128, z of 64.
    pub fn cpu(classes: Vec<String>) -> Self {
        Self {
            layers: 2,
            hidden: 128,
            latent: 64,
            ..Self::paper(classes)
        }
    }

    /// Width of an encoder step (pose, one-hot class, time).
    fn encoder_input(&self) -> usize {
        self.feature_dim + self.classes.len() + 1
    }

    /// Width of a decoder step (z, one-hot class, time).
    fn decoder_input(&self) -> usize {
        self.latent + self.classes.len() + 1
    }
}

/// The BI-CTVAE networks and class modes.
pub struct Ctvae {
    /// Its shape.
    pub config: CtvaeConfig,
    encoder: StackedGru,
    to_mu: Linear,
    to_logvar: Linear,
    decoder: StackedGru,
    out: Linear,
    mode_mu: Tensor,
    mode_logvar: Tensor,
}

/// μ and log σ² of a batch's posteriors, `(batch, latent)` each.
pub struct Posterior {
    /// Means.
    pub mu: Tensor,
    /// Log variances.
    pub logvar: Tensor,
}

impl Ctvae {
    /// Build from `vb` (fresh variables: see [`evaluator::model::init_weights`] for the
    /// networks; modes start at μ = 0, log σ² = 0 until [`Ctvae::init_modes`]).
    pub fn new(config: CtvaeConfig, vb: VarBuilder) -> Result<Self> {
        let (h, z) = (config.hidden, config.latent);
        let enc = vb.pp("encoder");
        let dec = vb.pp("decoder");
        let classes = config.classes.len();
        Ok(Self {
            encoder: StackedGru::new(config.encoder_input(), h, config.layers, &enc.pp("gru"))?,
            to_mu: candle_nn::linear(h, z, enc.pp("mu"))?,
            to_logvar: candle_nn::linear(h, z, enc.pp("logvar"))?,
            decoder: StackedGru::new(config.decoder_input(), h, config.layers, &dec.pp("gru"))?,
            out: candle_nn::linear(h, config.feature_dim, dec.pp("out"))?,
            mode_mu: vb
                .pp("modes")
                .get_with_hints((classes, z), "mu", Init::Const(0.0))?,
            mode_logvar: vb
                .pp("modes")
                .get_with_hints((classes, z), "logvar", Init::Const(0.0))?,
            config,
        })
    }

    /// `(batch, steps, classes + 1)`: each sequence's one-hot class and the time index.
    fn conditions(&self, classes: &[u32], steps: usize, device: &Device) -> Result<Tensor> {
        let n = self.config.classes.len();
        let scale = self.config.max_frames.max(1) as f32;
        let values: Vec<f32> = classes
            .iter()
            .flat_map(|&a| {
                (0..steps).flat_map(move |t| {
                    (0..n)
                        .map(move |c| if c == a as usize { 1.0 } else { 0.0 })
                        .chain(std::iter::once(t as f32 / scale))
                })
            })
            .collect();
        Tensor::from_vec(values, (classes.len(), steps, n + 1), device)
    }

    /// The posterior of normalised poses `x` (`(batch, steps, feature_dim)`, zero past each
    /// sequence's `lengths`) of classes `classes`.
    pub fn encode(&self, x: &Tensor, classes: &[u32], lengths: &[usize]) -> Result<Posterior> {
        let steps = x.dim(1)?;
        let input = Tensor::cat(&[x, &self.conditions(classes, steps, x.device())?], 2)?;
        let last = self.encoder.run(&input, lengths, GruOutput::Final)?;
        Ok(Posterior {
            mu: self.to_mu.forward(&last)?,
            logvar: self.to_logvar.forward(&last)?,
        })
    }

    /// Poses decoded from `z` (`(batch, latent)`) for classes `classes`, `steps` frames each.
    pub fn decode(&self, z: &Tensor, classes: &[u32], steps: usize) -> Result<Tensor> {
        let (batch, latent) = z.dims2()?;
        let repeated = z.unsqueeze(1)?.broadcast_as((batch, steps, latent))?;
        let input = Tensor::cat(
            &[
                &repeated.contiguous()?,
                &self.conditions(classes, steps, z.device())?,
            ],
            2,
        )?;
        self.out.forward(
            &self
                .decoder
                .run(&input, &vec![steps; batch], GruOutput::States)?,
        )
    }

    /// The device its weights live on.
    pub fn device(&self) -> &Device {
        self.mode_mu.device()
    }

    /// The class modes' means and log variances, `(classes, latent)` each.
    pub fn modes(&self) -> (&Tensor, &Tensor) {
        (&self.mode_mu, &self.mode_logvar)
    }

    /// KL(N(μ, σ²) ‖ N(μ_a, σ_a²)) summed over the latent dims and over the batch:
    /// Σ_b ½ Σ_j [log σ_a² − log σ² − 1 + (σ² + (μ − μ_a)²) / σ_a²]. Summed over the batch as
    /// in ACTOR's code, which the paper's λ_latent = 1e-5 (ACTOR's λ_kl) is meant for, while the
    /// reconstruction losses are means. Only the modes of `classes` enter, so only they
    /// receive gradients.
    pub fn latent_loss(&self, posterior: &Posterior, classes: &[u32]) -> Result<Tensor> {
        let idx = Tensor::new(classes, posterior.mu.device())?;
        let mode_mu = self.mode_mu.index_select(&idx, 0)?;
        let mode_logvar = self.mode_logvar.index_select(&idx, 0)?;
        let var = posterior.logvar.exp()?;
        let diff2 = (&posterior.mu - &mode_mu)?.sqr()?;
        let ratio = ((var + diff2)? / mode_logvar.exp()?)?;
        let terms = (((&mode_logvar - &posterior.logvar)? - 1.0)? + ratio)?;
        terms.sum_all()? * 0.5
    }

    /// `n` latents of class `class` drawn from its mode (z = μ_a + σ_a·ε, ε from `rng`).
    pub fn sample_latents(&self, class: u32, n: usize, rng: &mut SplitMix64) -> Result<Tensor> {
        let z = self.config.latent;
        let mu = self.mode_mu.get(class as usize)?;
        let sd = (self.mode_logvar.get(class as usize)? * 0.5)?.exp()?;
        let eps: Vec<f32> = (0..n * z).map(|_| rng.normal() as f32).collect();
        let eps = Tensor::from_vec(eps, (n, z), self.device())?;
        eps.broadcast_mul(&sd)?.broadcast_add(&mu)
    }

    /// Set the class modes' means to seeded N(0, 1) draws (variances stay 1), so classes
    /// start apart in latent space.
    pub fn init_modes(varmap: &candle_nn::VarMap, seed: u64) -> Result<()> {
        let vars = varmap.data().lock().expect("varmap lock");
        let Some(mu) = vars.get("modes.mu") else {
            return Ok(());
        };
        let mut rng = SplitMix64::stream(seed, 0x6d6f6465);
        let values: Vec<f32> = (0..mu.elem_count()).map(|_| rng.normal() as f32).collect();
        mu.set(&Tensor::from_vec(values, mu.dims(), mu.device())?)?;
        vars["modes.logvar"].set(&vars["modes.logvar"].zeros_like()?)
    }
}

/// A fresh seeded BI-CTVAE and its variables on `device`: PyTorch's default initialisation
/// for the networks, N(0, 1) mode means.
pub fn init_ctvae(
    config: CtvaeConfig,
    seed: u64,
    device: &Device,
) -> Result<(Ctvae, candle_nn::VarMap)> {
    let varmap = candle_nn::VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
    let model = Ctvae::new(config, vb)?;
    evaluator::model::init_weights(&varmap, seed)?;
    Ctvae::init_modes(&varmap, seed)?;
    Ok((model, varmap))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> (Ctvae, candle_nn::VarMap) {
        let config = CtvaeConfig {
            feature_dim: 5,
            classes: vec!["a".into(), "b".into(), "c".into()],
            layers: 2,
            hidden: 6,
            latent: 2,
            max_frames: 10,
        };
        init_ctvae(config, 3, &Device::Cpu).unwrap()
    }

    fn set(varmap: &candle_nn::VarMap, name: &str, values: Vec<f32>, shape: (usize, usize)) {
        let vars = varmap.data().lock().unwrap();
        vars[name]
            .set(&Tensor::from_vec(values, shape, &Device::Cpu).unwrap())
            .unwrap();
    }

    #[test]
    fn latent_loss_is_the_kl_to_the_class_mode_by_hand() {
        let (model, varmap) = tiny();
        // Class 1's mode: μ_a = (1, −1), σ_a² = (e, 1).
        set(
            &varmap,
            "modes.mu",
            vec![0.0, 0.0, 1.0, -1.0, 0.0, 0.0],
            (3, 2),
        );
        set(
            &varmap,
            "modes.logvar",
            vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            (3, 2),
        );
        // Posterior μ = (0, 0), σ² = (1, e⁻¹).
        let posterior = Posterior {
            mu: Tensor::new(&[[0f32, 0.0]], &Device::Cpu).unwrap(),
            logvar: Tensor::new(&[[0f32, -1.0]], &Device::Cpu).unwrap(),
        };
        // Dim 1: ½[1 − 0 − 1 + (1 + 1)/e] = 1/e; dim 2: ½[0 + 1 − 1 + (e⁻¹ + 1)/1] = ½(1 + e⁻¹).
        let e = std::f64::consts::E;
        let want = 1.0 / e + 0.5 * (1.0 + 1.0 / e);
        let got: f32 = model
            .latent_loss(&posterior, &[1])
            .unwrap()
            .to_scalar()
            .unwrap();
        assert!((f64::from(got) - want).abs() < 1e-6, "{got} vs {want}");
        // At the mode itself the loss is zero.
        let at_mode = Posterior {
            mu: Tensor::new(&[[1f32, -1.0]], &Device::Cpu).unwrap(),
            logvar: Tensor::new(&[[1f32, 0.0]], &Device::Cpu).unwrap(),
        };
        let zero: f32 = model
            .latent_loss(&at_mode, &[1])
            .unwrap()
            .to_scalar()
            .unwrap();
        assert!(zero.abs() < 1e-6);
        // Summed over the batch (ACTOR's reduction): the posterior and the mode itself give
        // the single posterior's KL once.
        let batch = Posterior {
            mu: Tensor::new(&[[0f32, 0.0], [1.0, -1.0]], &Device::Cpu).unwrap(),
            logvar: Tensor::new(&[[0f32, -1.0], [1.0, 0.0]], &Device::Cpu).unwrap(),
        };
        let summed: f32 = model
            .latent_loss(&batch, &[1, 1])
            .unwrap()
            .to_scalar()
            .unwrap();
        assert!(
            (f64::from(summed) - want).abs() < 1e-6,
            "{summed} vs {want}"
        );
    }

    #[test]
    fn modes_of_classes_not_in_the_batch_get_no_gradient() {
        let (model, varmap) = tiny();
        let x = Tensor::ones((2, 4, 5), DType::F32, &Device::Cpu).unwrap();
        let classes = [0u32, 2];
        let posterior = model.encode(&x, &classes, &[4, 3]).unwrap();
        let recon = model.decode(&posterior.mu, &classes, 4).unwrap();
        let loss = ((recon - &x).unwrap().sqr().unwrap().mean_all().unwrap()
            + model.latent_loss(&posterior, &classes).unwrap())
        .unwrap();
        let grads = loss.backward().unwrap();
        let vars = varmap.data().lock().unwrap();
        for name in ["modes.mu", "modes.logvar"] {
            let g: Vec<Vec<f32>> = grads
                .get(vars[name].as_tensor())
                .unwrap()
                .to_vec2()
                .unwrap();
            assert!(
                g[1].iter().all(|&v| v == 0.0),
                "{name}: class 1 is not in the batch"
            );
            assert!(
                g[0].iter().chain(&g[2]).any(|&v| v != 0.0),
                "{name}: classes 0, 2 are"
            );
        }
        let decoder = grads.get(vars["decoder.gru.weight_ih_l1"].as_tensor());
        assert!(decoder.is_some(), "the whole stack trains");
    }

    #[test]
    fn replay_latents_come_from_their_class_mode() {
        let (model, varmap) = tiny();
        set(
            &varmap,
            "modes.mu",
            vec![0.0, 0.0, 5.0, -3.0, -8.0, 8.0],
            (3, 2),
        );
        let ln4 = 4f32.ln();
        set(
            &varmap,
            "modes.logvar",
            vec![0.0, 0.0, ln4, 0.0, 0.0, 0.0],
            (3, 2),
        );
        let mut rng = SplitMix64(11);
        let z: Vec<Vec<f32>> = model
            .sample_latents(1, 4000, &mut rng)
            .unwrap()
            .to_vec2()
            .unwrap();
        let n = z.len() as f32;
        let mean = |j: usize| z.iter().map(|r| r[j]).sum::<f32>() / n;
        let var = |j: usize| z.iter().map(|r| (r[j] - mean(j)).powi(2)).sum::<f32>() / n;
        assert!((mean(0) - 5.0).abs() < 0.1 && (mean(1) + 3.0).abs() < 0.05);
        assert!((var(0) - 4.0).abs() < 0.3 && (var(1) - 1.0).abs() < 0.08);
        let poses = model
            .decode(
                &model.sample_latents(2, 3, &mut rng).unwrap(),
                &[2, 2, 2],
                60,
            )
            .unwrap();
        assert_eq!(poses.dims(), &[3, 60, 5]);
    }
}
