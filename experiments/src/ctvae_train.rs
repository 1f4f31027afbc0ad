//! Training and sampling of BI-CTVAE ([`crate::ctvae`]) on windows of pose features
//! normalised with the evaluator's statistics (so its frozen action classifier reads the
//! reconstructions directly for the auxiliary loss).
//!
//! Loss = pose MSE (normalised features) + joint-position MSE (the root-relative joint
//! positions of the features, dims 4..67, in metres: **a stand-in for the paper's SMPL vertex
//! loss**, there being no body model) + λ_latent·KL to the class mode + λ_aux·CE of the frozen
//! action classifier on the reconstruction.

use crate::ctvae::{init_ctvae, Ctvae, CtvaeConfig};
use candle_core::{Device, Result, Tensor};
use evaluator::model::{Padded, TrainedEvaluator, UNIT};
use motionscale_core::rng::SplitMix64;
use nn::optim::{AdamW, AdamWConfig};
use serde::{Deserialize, Serialize};

/// The root-relative joint positions inside a 263-d feature row (21 joints × 3).
pub const JOINT_POSITIONS: std::ops::Range<usize> = 4..67;

/// Loss weights.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LossWeights {
    /// λ_latent (paper: 1e-5).
    pub latent: f64,
    /// λ_aux (paper: 1e-4); 0 leaves the classifier out.
    pub aux: f64,
}

/// One training sequence: its class and normalised poses (`frames × feature_dim`).
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Class index.
    pub class: u32,
    /// Normalised poses.
    pub poses: Vec<f32>,
}

/// The loss terms of one step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepLoss {
    /// Pose MSE.
    pub pose: f32,
    /// Joint-position MSE (m²).
    pub joints: f32,
    /// KL to the class modes, summed over the batch.
    pub latent: f32,
    /// Auxiliary classifier cross-entropy (0 without it).
    pub aux: f32,
}

/// A BI-CTVAE with its optimiser.
pub struct CtvaeTrainer {
    /// The model.
    pub model: Ctvae,
    /// Its variables (saved as the checkpoint).
    pub varmap: candle_nn::VarMap,
    opt: AdamW,
    weights: LossWeights,
    /// Per-feature scale of the joint positions (the evaluator's std).
    joint_std: Tensor,
}

impl CtvaeTrainer {
    /// A fresh model of `config` (seeded) on `device` with AdamW (β 0.9/0.999, weight decay
    /// 0.01).
    pub fn new(
        config: CtvaeConfig,
        weights: LossWeights,
        std: &[f32],
        seed: u64,
        device: &Device,
    ) -> Result<Self> {
        let (model, varmap) = init_ctvae(config, seed, device)?;
        let vars = varmap.data().lock().expect("varmap lock").clone();
        let opt = AdamW::new(&vars, AdamWConfig::default());
        let joint_std = Tensor::from_slice(&std[JOINT_POSITIONS], JOINT_POSITIONS.len(), device)?;
        Ok(Self {
            model,
            varmap,
            opt,
            weights,
            joint_std,
        })
    }

    /// One AdamW step at `lr` on `batch` (gradient norm clipped at 1). `aux` is the frozen
    /// evaluator with the evaluator's action index of each class; `rng` draws ε.
    pub fn step(
        &mut self,
        batch: &[&Sample],
        lr: f64,
        aux: Option<(&TrainedEvaluator, &[u32])>,
        rng: &mut SplitMix64,
    ) -> Result<StepLoss> {
        let (dim, device) = (self.model.config.feature_dim, self.model.device());
        let rows: Vec<&[f32]> = batch.iter().map(|s| s.poses.as_slice()).collect();
        let padded = Padded::new(&rows, dim, device)?;
        let (n, steps, _) = padded.values.dims3()?;
        let classes: Vec<u32> = batch.iter().map(|s| s.class).collect();
        let mask: Vec<f32> = padded
            .lengths
            .iter()
            .flat_map(|&l| (0..steps).map(move |t| if t < l { 1.0 } else { 0.0 }))
            .collect();
        let mask = Tensor::from_vec(mask, (n, steps, 1), device)?;
        let frames: usize = padded.lengths.iter().sum();
        let posterior = self
            .model
            .encode(&padded.values, &classes, &padded.lengths)?;
        let eps: Vec<f32> = (0..n * self.model.config.latent)
            .map(|_| rng.normal() as f32)
            .collect();
        let eps = Tensor::from_vec(eps, posterior.mu.dims(), device)?;
        let z = (&posterior.mu + (eps * (&posterior.logvar * 0.5)?.exp()?)?)?;
        let recon = self
            .model
            .decode(&z, &classes, steps)?
            .broadcast_mul(&mask)?;
        let err = (&recon - &padded.values)?;
        let pose = (err.sqr()?.sum_all()? / (frames * dim) as f64)?;
        let joint_err = err
            .narrow(2, JOINT_POSITIONS.start, JOINT_POSITIONS.len())?
            .broadcast_mul(&self.joint_std)?;
        // Squared distance per joint: 3 coordinates summed, averaged over joints and frames.
        let joints = (joint_err.sqr()?.sum_all()? / (frames * JOINT_POSITIONS.len() / 3) as f64)?;
        let latent = self.model.latent_loss(&posterior, &classes)?;
        let mut total = ((&pose + &joints)? + (&latent * self.weights.latent)?)?;
        let mut aux_loss = 0f32;
        if let (Some((evaluator, actions)), true) = (aux, self.weights.aux > 0.0) {
            let lengths: Vec<usize> = padded
                .lengths
                .iter()
                .map(|&l| (l / UNIT * UNIT).max(UNIT))
                .collect();
            let logits = evaluator
                .net
                .encode_motion(&Padded {
                    values: recon,
                    lengths,
                })?
                .action;
            let targets: Vec<u32> = classes.iter().map(|&c| actions[c as usize]).collect();
            let ce = candle_nn::loss::cross_entropy(&logits, &Tensor::new(targets, device)?)?;
            aux_loss = ce.to_scalar()?;
            total = (total + (ce * self.weights.aux)?)?;
        }
        let grads = total.backward()?;
        self.opt
            .step(&grads, lr, Some(1.0))
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        Ok(StepLoss {
            pose: pose.to_scalar()?,
            joints: joints.to_scalar()?,
            latent: latent.to_scalar()?,
            aux: aux_loss,
        })
    }

    /// Save the weights (safetensors, PyTorch names) and the optimiser moments into `dir`.
    pub fn save(
        &self,
        dir: &std::path::Path,
    ) -> std::result::Result<(), motionscale_core::FileError> {
        let weights = dir.join("model.safetensors");
        let tensors = nn::checkpoint::var_tensors(&self.varmap.data().lock().expect("varmap lock"));
        nn::checkpoint::save_safetensors(&tensors, &weights)
            .map_err(|e| motionscale_core::FileError::invalid(&weights, e))?;
        let moments = dir.join("optimizer.safetensors");
        self.opt
            .save(&moments)
            .map_err(|e| motionscale_core::FileError::invalid(&moments, e))
    }

    /// Restore what [`Self::save`] wrote.
    pub fn load(
        &mut self,
        dir: &std::path::Path,
    ) -> std::result::Result<(), motionscale_core::FileError> {
        let weights = dir.join("model.safetensors");
        self.varmap
            .load(&weights)
            .map_err(|e| motionscale_core::FileError::invalid(&weights, e))?;
        let moments = dir.join("optimizer.safetensors");
        self.opt
            .load(&moments)
            .map_err(|e| motionscale_core::FileError::invalid(&moments, e))
    }

    /// `n` normalised motions of class `class`, `frames` frames each, from its mode.
    pub fn generate(
        &self,
        class: u32,
        n: usize,
        frames: usize,
        rng: &mut SplitMix64,
    ) -> Result<Vec<Vec<f32>>> {
        if n == 0 {
            return Ok(Vec::new());
        }
        let z = self.model.sample_latents(class, n, rng)?;
        let poses = self.model.decode(&z, &vec![class; n], frames)?;
        (0..n)
            .map(|i| poses.get(i)?.flatten_all()?.to_vec1::<f32>())
            .collect()
    }
}
