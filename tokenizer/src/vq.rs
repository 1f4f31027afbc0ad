//! Vector quantization with an EMA codebook and dead-code reset (T2M-GPT's
//! `QuantizeEMAReset`): nearest code by L2, straight-through gradient, commitment loss.
//!
//! The codebook is not a gradient parameter: it is updated by exponential moving averages
//! outside autograd, so it and its EMA statistics are plain tensors held here (not in a
//! `VarMap`, where an optimiser would also decay them) and replaced on every update.

use crate::error::TokenizerError;
use crate::ste::straight_through;
use candle_core::{DType, Device, Tensor, D};
use motionscale_core::rng::SplitMix64;
use serde::{Deserialize, Serialize};

/// Configuration of a [`VqQuantizer`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VqConfig {
    /// Number of codes K.
    pub codebook_size: usize,
    /// Code width D (the encoder's output channels).
    pub dim: usize,
    /// Commitment weight β.
    #[serde(default = "default_beta")]
    pub beta: f64,
    /// EMA decay of code sums and counts.
    #[serde(default = "default_decay")]
    pub decay: f64,
    /// A code whose EMA count falls below this is dead and reset.
    #[serde(default = "default_reset_below")]
    pub reset_below: f64,
}

fn default_beta() -> f64 {
    0.02
}

fn default_decay() -> f64 {
    0.99
}

fn default_reset_below() -> f64 {
    1.0
}

impl VqConfig {
    /// K codes of width D with the T2M-GPT defaults (β = 0.02, decay 0.99, reset below 1).
    pub fn new(codebook_size: usize, dim: usize) -> Self {
        Self {
            codebook_size,
            dim,
            beta: default_beta(),
            decay: default_decay(),
            reset_below: default_reset_below(),
        }
    }
}

/// Rows × codes of one distance-matrix chunk in [`VqQuantizer::nearest`].
const DISTANCE_CHUNK: usize = 1 << 24;

/// Laplace smoothing of the EMA cluster sizes, so no code divides by zero.
const LAPLACE_EPS: f64 = 1e-5;

/// What [`VqQuantizer::forward`] returns.
#[derive(Debug, Clone)]
pub struct VqOutput {
    /// The nearest codes (`..., D`) with the gradient of the input (straight-through).
    pub quantized: Tensor,
    /// Index of the nearest code per position (`...`, u32).
    pub indices: Tensor,
    /// `β · mean((z - sg(q))²)`, a scalar.
    pub commitment_loss: Tensor,
}

/// A K×D codebook with its EMA statistics and the seeded generator that picks reset rows.
#[derive(Debug, Clone)]
pub struct VqQuantizer {
    config: VqConfig,
    codebook: Tensor,
    code_sum: Tensor,
    code_count: Tensor,
    rng: SplitMix64,
}

impl VqQuantizer {
    /// A codebook of N(0, 1) draws from a generator seeded with `seed` (which then also
    /// drives dead-code resets), on `device`, in f32.
    pub fn new(config: &VqConfig, device: &Device, seed: u64) -> Result<Self, TokenizerError> {
        let mut rng = SplitMix64(seed);
        let values: Vec<f32> = (0..config.codebook_size * config.dim)
            .map(|_| rng.normal() as f32)
            .collect();
        let codebook = Tensor::from_vec(values, (config.codebook_size, config.dim), device)?;
        Self::from_codebook(config, codebook, rng.next_u64())
    }

    /// Start from a given `codebook` (K×D, f32). As in T2M-GPT, the EMA code sums start at
    /// the codebook and the EMA counts at one.
    pub fn from_codebook(
        config: &VqConfig,
        codebook: Tensor,
        seed: u64,
    ) -> Result<Self, TokenizerError> {
        if config.codebook_size == 0 || config.dim == 0 {
            return Err(TokenizerError::Argument(
                "VQ codebook size and dim must be positive".into(),
            ));
        }
        if !(0.0..1.0).contains(&config.decay) {
            return Err(TokenizerError::Argument(format!(
                "VQ EMA decay must lie in [0, 1), got {}",
                config.decay
            )));
        }
        let expected = [config.codebook_size, config.dim];
        if codebook.dims() != expected {
            return Err(TokenizerError::Argument(format!(
                "VQ codebook has shape {:?}, expected {expected:?}",
                codebook.dims()
            )));
        }
        let codebook = codebook.detach().to_dtype(DType::F32)?;
        let code_count = Tensor::ones(config.codebook_size, DType::F32, codebook.device())?;
        Ok(Self {
            config: config.clone(),
            code_sum: codebook.clone(),
            codebook,
            code_count,
            rng: SplitMix64(seed),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &VqConfig {
        &self.config
    }

    /// The current codebook (K×D).
    pub fn codebook(&self) -> &Tensor {
        &self.codebook
    }

    /// EMA of the per-code counts (K).
    pub fn code_count(&self) -> &Tensor {
        &self.code_count
    }

    /// EMA of the per-code sums of assigned encoder outputs (K×D).
    pub fn code_sum(&self) -> &Tensor {
        &self.code_sum
    }

    /// Index of the nearest code (L2) of every vector of `z` (`..., D` → `...`, u32),
    /// computed as `||z||² − 2 z·c + ||c||²` with one matmul.
    pub fn nearest(&self, z: &Tensor) -> Result<Tensor, TokenizerError> {
        let (flat, lead) = self.flatten(z)?;
        let flat = flat.detach();
        let c_sq = self.codebook.sqr()?.sum(1)?.unsqueeze(0)?;
        let codebook_t = self.codebook.t()?;
        // Rows in chunks so the rows × K distance matrix stays near 64 MB even for 2^16 codes.
        let chunk = (DISTANCE_CHUNK / self.config.codebook_size).max(1);
        let rows = flat.dim(0)?;
        let mut parts = Vec::with_capacity(rows.div_ceil(chunk));
        for start in (0..rows).step_by(chunk) {
            let part = flat.narrow(0, start, chunk.min(rows - start))?;
            let z_sq = part.sqr()?.sum_keepdim(1)?;
            let cross = part.matmul(&codebook_t)?;
            let dist = z_sq
                .broadcast_sub(&cross.affine(2.0, 0.0)?)?
                .broadcast_add(&c_sq)?;
            parts.push(dist.argmin(D::Minus1)?);
        }
        Ok(Tensor::cat(&parts, 0)?.reshape(lead)?)
    }

    /// Code vectors of `indices` (`...`, u32 → `..., D`).
    pub fn lookup(&self, indices: &Tensor) -> Result<Tensor, TokenizerError> {
        let mut shape = indices.dims().to_vec();
        let flat = indices.flatten_all()?;
        shape.push(self.config.dim);
        Ok(self.codebook.index_select(&flat, 0)?.reshape(shape)?)
    }

    /// Quantize `z` (`..., D`, f32) to its nearest codes, without touching the codebook.
    pub fn forward(&self, z: &Tensor) -> Result<VqOutput, TokenizerError> {
        let indices = self.nearest(z)?;
        let q = self.lookup(&indices)?;
        let commitment_loss = (z - q.detach())?
            .sqr()?
            .mean_all()?
            .affine(self.config.beta, 0.0)?;
        Ok(VqOutput {
            quantized: straight_through(z, &q)?,
            indices,
            commitment_loss,
        })
    }

    /// Training step: [`Self::forward`] with the current codebook, then
    /// [`Self::ema_update`] on this batch (T2M-GPT's order). Returns the output and the
    /// number of codes reset.
    pub fn forward_train(&mut self, z: &Tensor) -> Result<(VqOutput, usize), TokenizerError> {
        let out = self.forward(z)?;
        let reset = self.ema_update(z, &out.indices)?;
        Ok((out, reset))
    }

    /// One EMA step from encoder outputs `z` (`..., D`) assigned to `indices` (`...`):
    /// `code_sum ← decay·code_sum + (1 − decay)·Σ_assigned z`, likewise `code_count` with
    /// the assignment counts; then each live code (EMA count ≥ `reset_below`) becomes
    /// `code_sum / w` with Laplace-smoothed sizes `w = (count + ε) / (n + K·ε) · n`
    /// (`n = Σ count`), and each dead code is replaced by a row of `z` drawn uniformly with
    /// the seeded generator. As in T2M-GPT the EMA statistics of a reset code are kept, so
    /// it stays eligible for reset until it wins enough assignments. Returns the number of
    /// codes reset.
    pub fn ema_update(&mut self, z: &Tensor, indices: &Tensor) -> Result<usize, TokenizerError> {
        let (flat, _) = self.flatten(z)?;
        let flat = flat.detach().to_dtype(DType::F32)?;
        let rows = flat.dim(0)?;
        let indices = indices.flatten_all()?.to_dtype(DType::U32)?;
        if indices.dim(0)? != rows {
            return Err(TokenizerError::Argument(format!(
                "VQ update got {rows} vectors but {} indices",
                indices.dim(0)?
            )));
        }
        if rows == 0 {
            return Err(TokenizerError::Argument(
                "VQ update needs at least one vector".into(),
            ));
        }
        let k = self.config.codebook_size;
        let device = flat.device();
        // Scatter-adds, not a K × rows one-hot matmul (a gigabyte at 2^16 codes).
        let batch_sum = Tensor::zeros((k, self.config.dim), DType::F32, device)?
            .index_add(&indices, &flat, 0)?;
        let ones = Tensor::ones(rows, DType::F32, device)?;
        let batch_count = Tensor::zeros(k, DType::F32, device)?.index_add(&indices, &ones, 0)?;
        let mu = self.config.decay;
        self.code_sum = (self.code_sum.affine(mu, 0.0)? + batch_sum.affine(1.0 - mu, 0.0)?)?;
        self.code_count =
            (self.code_count.affine(mu, 0.0)? + batch_count.affine(1.0 - mu, 0.0)?)?;

        let n = self.code_count.sum_all()?.to_scalar::<f32>()? as f64;
        let weights = self
            .code_count
            .affine(1.0, LAPLACE_EPS)?
            .affine(n / (n + k as f64 * LAPLACE_EPS), 0.0)?;
        let updated = self.code_sum.broadcast_div(&weights.unsqueeze(1)?)?;
        // One draw per code, dead or not, so the generator's stream depends only on K.
        let random = self.random_rows(&flat, k)?;
        let live = self.code_count.ge(self.config.reset_below)?;
        let dead = k - live.to_dtype(DType::U32)?.sum_all()?.to_scalar::<u32>()? as usize;
        self.codebook = live
            .unsqueeze(1)?
            .broadcast_as((k, self.config.dim))?
            .where_cond(&updated, &random)?;
        Ok(dead)
    }

    /// `z` as rows of width D, and its leading shape.
    /// Restore a saved codebook and its EMA statistics (K×D, K×D, K).
    pub fn set_state(
        &mut self,
        codebook: Tensor,
        code_sum: Tensor,
        code_count: Tensor,
    ) -> Result<(), TokenizerError> {
        let (k, d) = (self.config.codebook_size, self.config.dim);
        for (name, t, dims) in [
            ("codebook", &codebook, vec![k, d]),
            ("code_sum", &code_sum, vec![k, d]),
            ("code_count", &code_count, vec![k]),
        ] {
            if t.dims() != dims.as_slice() {
                return Err(TokenizerError::Argument(format!(
                    "VQ {name} has shape {:?}, expected {dims:?}",
                    t.dims()
                )));
            }
        }
        self.codebook = codebook.to_dtype(DType::F32)?;
        self.code_sum = code_sum.to_dtype(DType::F32)?;
        self.code_count = code_count.to_dtype(DType::F32)?;
        Ok(())
    }

    /// State of the generator that draws reset codes (saved with training checkpoints).
    pub fn rng_state(&self) -> u64 {
        self.rng.0
    }

    /// Restore the generator state saved by [`Self::rng_state`].
    pub fn set_rng_state(&mut self, state: u64) {
        self.rng = SplitMix64(state);
    }

    /// Replace the codebook by `K` random vectors of `z` (`..., D`) and restart the EMA
    /// statistics from it, as T2M-GPT initialises its codebook from the first batch.
    pub fn init_from(&mut self, z: &Tensor) -> Result<(), TokenizerError> {
        let (flat, _) = self.flatten(z)?;
        let flat = flat.detach().to_dtype(DType::F32)?;
        self.codebook = self.random_rows(&flat, self.config.codebook_size)?;
        self.code_sum = self.codebook.clone();
        self.code_count = Tensor::ones(self.config.codebook_size, DType::F32, flat.device())?;
        Ok(())
    }

    /// `count` rows drawn from `flat` (rows × D) with the quantizer's generator; with fewer
    /// rows than wanted, repeated draws get N(0, (0.01/√D)²) noise (as T2M-GPT's
    /// `_tile`) so reset codes do not collapse onto identical vectors.
    fn random_rows(&mut self, flat: &Tensor, count: usize) -> Result<Tensor, TokenizerError> {
        let rows = flat.dim(0)?;
        if rows == 0 {
            return Err(TokenizerError::Argument(
                "VQ needs at least one vector to draw codes from".into(),
            ));
        }
        let picks: Vec<u32> = (0..count).map(|_| self.rng.index(rows) as u32).collect();
        let drawn = flat.index_select(&Tensor::new(picks, flat.device())?, 0)?;
        if rows >= count {
            return Ok(drawn);
        }
        let sigma = 0.01 / (self.config.dim as f64).sqrt();
        let noise: Vec<f32> = (0..count * self.config.dim)
            .map(|_| (self.rng.normal() * sigma) as f32)
            .collect();
        Ok((drawn + Tensor::from_vec(noise, (count, self.config.dim), flat.device())?)?)
    }

    fn flatten(&self, z: &Tensor) -> Result<(Tensor, Vec<usize>), TokenizerError> {
        let dims = z.dims();
        match dims.split_last() {
            Some((&d, lead)) if d == self.config.dim => Ok((z.reshape(((), d))?, lead.to_vec())),
            _ => Err(TokenizerError::Argument(format!(
                "VQ input has shape {dims:?}, expected (..., {})",
                self.config.dim
            ))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Var;

    /// c0 = (0, 0), c1 = (10, 0), c2 = (0, 10).
    fn three_codes(seed: u64) -> VqQuantizer {
        let codebook = Tensor::new(&[[0f32, 0.0], [10.0, 0.0], [0.0, 10.0]], &Device::Cpu).unwrap();
        VqQuantizer::from_codebook(&VqConfig::new(3, 2), codebook, seed).unwrap()
    }

    fn rows(t: &Tensor) -> Vec<Vec<f32>> {
        t.to_vec2::<f32>().unwrap()
    }

    #[test]
    fn nearest_code_on_a_three_code_codebook() {
        let vq = three_codes(0);
        let z = Tensor::new(
            &[[1f32, 1.0], [9.0, 1.0], [2.0, 7.0], [-5.0, -5.0]],
            &Device::Cpu,
        )
        .unwrap();
        let idx = vq.nearest(&z).unwrap();
        assert_eq!(idx.to_vec1::<u32>().unwrap(), vec![0, 1, 2, 0]);
        let back = vq.lookup(&idx).unwrap();
        assert_eq!(
            rows(&back),
            vec![
                vec![0.0, 0.0],
                vec![10.0, 0.0],
                vec![0.0, 10.0],
                vec![0.0, 0.0]
            ]
        );
        // Leading dimensions are kept.
        let batched = vq.nearest(&z.reshape((2, 2, 2)).unwrap()).unwrap();
        assert_eq!(
            batched.to_vec2::<u32>().unwrap(),
            vec![vec![0, 1], vec![2, 0]]
        );
    }

    #[test]
    fn commitment_loss_and_straight_through() {
        let vq = three_codes(0);
        let z = Var::new(&[[1f32, 1.0], [9.0, 1.0]], &Device::Cpu).unwrap();
        let out = vq.forward(z.as_tensor()).unwrap();
        // z - q = (1, 1), (-1, 1): mean square 1, times β = 0.02.
        let loss = out.commitment_loss.to_scalar::<f32>().unwrap();
        assert!((loss - 0.02).abs() < 1e-7, "{loss}");
        assert_eq!(rows(&out.quantized), vec![vec![0.0, 0.0], vec![10.0, 0.0]]);
        let grads = out.quantized.sum_all().unwrap().backward().unwrap();
        assert_eq!(
            rows(grads.get(&z).unwrap()),
            vec![vec![1.0, 1.0], vec![1.0, 1.0]]
        );
    }

    #[test]
    fn one_ema_step_matches_hand_computation() {
        let mut vq = three_codes(7);
        let z = Tensor::new(
            &[[1f32, 1.0], [-1.0, 1.0], [9.0, 1.0], [11.0, -1.0]],
            &Device::Cpu,
        )
        .unwrap();
        let (out, reset) = vq.forward_train(&z).unwrap();
        assert_eq!(out.indices.to_vec1::<u32>().unwrap(), vec![0, 0, 1, 1]);
        // Counts 0.99 + 0.01·(2, 2, 0) = (1.01, 1.01, 0.99): code 2 is dead.
        assert_eq!(reset, 1);
        let count = vq.code_count().to_vec1::<f32>().unwrap();
        for (c, e) in count.iter().zip([1.01f32, 1.01, 0.99]) {
            assert!((c - e).abs() < 1e-6, "{count:?}");
        }
        // Sums 0.99·c + 0.01·Σz: (0, 0.02), (10.1, 0), (0, 9.9).
        let sum = rows(vq.code_sum());
        let expected_sum = [[0.0f32, 0.02], [10.1, 0.0], [0.0, 9.9]];
        for (r, e) in sum.iter().zip(expected_sum) {
            assert!(
                (r[0] - e[0]).abs() < 1e-5 && (r[1] - e[1]).abs() < 1e-5,
                "{sum:?}"
            );
        }
        // n = 3.01, w = (1.01 + 1e-5)·3.01 / (3.01 + 3e-5) = 1.0099999335:
        // c0 = (0, 0.02 / w) = (0, 0.0198020), c1 = (10.1 / w, 0) = (10.0000007, 0).
        let book = rows(vq.codebook());
        assert!(
            book[0][0].abs() < 1e-7 && (book[0][1] - 0.019_802_0).abs() < 1e-6,
            "{book:?}"
        );
        assert!(
            (book[1][0] - 10.0).abs() < 1e-5 && book[1][1].abs() < 1e-7,
            "{book:?}"
        );
        // The dead code became one of the batch's vectors.
        assert!(rows(&z).contains(&book[2]), "{book:?}");
    }

    #[test]
    fn dead_codes_reset_deterministically() {
        let config = VqConfig::new(4, 3);
        let z = Tensor::new(
            &[
                [0.1f32, 0.2, 0.3],
                [0.4, 0.5, 0.6],
                [0.7, 0.8, 0.9],
                [1.0, 1.1, 1.2],
                [1.3, 1.4, 1.5],
            ],
            &Device::Cpu,
        )
        .unwrap();
        let run = |seed: u64| {
            let mut vq = VqQuantizer::new(&config, &Device::Cpu, seed).unwrap();
            // Every vector goes to code 0, so codes 1..3 decay to 0.99 and are reset.
            let idx = Tensor::zeros(5, DType::U32, &Device::Cpu).unwrap();
            let reset = vq.ema_update(&z, &idx).unwrap();
            (reset, rows(vq.codebook()))
        };
        let (reset, book) = run(42);
        assert_eq!(reset, 3);
        let batch = rows(&z);
        for code in &book[1..] {
            assert!(batch.contains(code), "{code:?} is not a batch vector");
        }
        // Code 0 is live: it moved to the smoothed mean, not to a batch vector copy.
        assert!(!batch.contains(&book[0]));
        assert_eq!(run(42), (reset, book));
    }

    #[test]
    fn rejected_shapes() {
        let vq = three_codes(0);
        let wrong = Tensor::zeros((2, 3), DType::F32, &Device::Cpu).unwrap();
        assert!(vq.nearest(&wrong).is_err());
        let bad_book = Tensor::zeros((2, 2), DType::F32, &Device::Cpu).unwrap();
        assert!(VqQuantizer::from_codebook(&VqConfig::new(3, 2), bad_book, 0).is_err());
    }
}
