//! Finite scalar quantization (Mentzer et al., 2023): project to `d_q = levels.len()`
//! channels, bound channel `i` so that rounding yields exactly `L_i` integer levels, round
//! with a straight-through gradient, normalise to [-1, 1] and project back. The codebook is
//! implicit: every combination of levels, `Π L_i` codes in all.
//!
//! Integer levels are centred: for `L` levels with `half_width = L / 2` (integer division)
//! they are `-half_width ..= L - 1 - half_width`, i.e. `-2..=2` for `L = 5` and `-4..=3`
//! for `L = 8`; the normalised code is `level / half_width`.

use crate::error::TokenizerError;
use crate::ste::straight_through;
use candle_core::{DType, Module, Tensor, D};
use candle_nn::{Linear, VarBuilder};
use serde::{Deserialize, Serialize};

/// Margin of the tanh bound (Mentzer et al.'s `eps`): the bound reaches just past the centres of
/// the outer levels, so they are reachable with finite inputs, and still rounds to `L` levels.
pub const TANH_EPS: f64 = 1e-3;

/// Mentzer et al.'s level sets, keyed by their nominal codebook size `2^k`.
const LEVEL_SETS: [(usize, &[usize]); 5] = [
    (1 << 8, &[8, 6, 5]),
    (1 << 10, &[8, 5, 5, 5]),
    (1 << 12, &[7, 5, 5, 5, 5]),
    (1 << 14, &[8, 8, 8, 6, 5]),
    (1 << 16, &[8, 8, 8, 5, 5, 5]),
];

/// The level set Mentzer et al. use for the nominal codebook size `codebook` (2^8, 2^10,
/// 2^12, 2^14 or 2^16), or `None` for any other size.
///
/// The names are nominal: the real codebook is `Π L`, e.g. 8·6·5 = 240 for "2^8" and
/// 8·8·8·5·5·5 = 64000 for "2^16"; use [`FsqQuantizer::codebook_size`] for the real size.
pub fn levels_for(codebook: usize) -> Option<&'static [usize]> {
    LEVEL_SETS
        .iter()
        .find(|(size, _)| *size == codebook)
        .map(|(_, levels)| *levels)
}

/// How each channel is squashed before rounding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Bound {
    /// Mentzer et al.: with `half_l = (L - 1)(1 + eps) / 2`, `offset = 0.5` if `L` is even
    /// else 0 and `shift = atanh(offset / half_l)`, `bounded = tanh(z + shift)·half_l - offset`.
    /// The range `(-half_l - offset, half_l - offset)` rounds to exactly the `L` centred
    /// levels, and `z = 0` maps to level 0 (the shift cancels the offset there).
    #[default]
    Tanh,
    /// ScaMo: `bounded = sigmoid(z)·(L - 1) - half_width`. Rounding `sigmoid(z)·(L - 1)`
    /// gives `0..=L-1`; subtracting the integer `half_width` commutes with rounding and
    /// yields the same centred levels as [`Bound::Tanh`]. The two end levels get half-width
    /// bins in sigmoid space.
    Sigmoid,
}

/// Configuration of an [`FsqQuantizer`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FsqConfig {
    /// Channels of the encoder output and of the decoder input.
    pub dim: usize,
    /// Levels per quantized channel (each at least 2); `d_q = levels.len()`.
    pub levels: Vec<usize>,
    /// Bounding function applied before rounding.
    #[serde(default)]
    pub bound: Bound,
}

/// What [`FsqQuantizer::forward`] returns.
#[derive(Debug, Clone)]
pub struct FsqOutput {
    /// Quantized latents projected back to `dim` channels (`..., dim`), straight-through.
    pub quantized: Tensor,
    /// Normalised codes in [-1, 1] (`..., d_q`), straight-through.
    pub codes: Tensor,
    /// One codebook index per position (`...`, u32).
    pub indices: Tensor,
}

/// An FSQ bottleneck: `Linear(dim → d_q)`, bound, round, normalise, `Linear(d_q → dim)`.
#[derive(Debug, Clone)]
pub struct FsqQuantizer {
    proj_in: Linear,
    proj_out: Linear,
    levels: Vec<usize>,
    bound: Bound,
}

impl FsqQuantizer {
    /// Build from `config`, with weights `proj_in.{weight,bias}` and
    /// `proj_out.{weight,bias}` under `vb`.
    pub fn new(config: &FsqConfig, vb: VarBuilder) -> Result<Self, TokenizerError> {
        if config.dim == 0 {
            return Err(TokenizerError::Argument("FSQ dim must be positive".into()));
        }
        if config.levels.is_empty() || config.levels.iter().any(|&l| l < 2) {
            return Err(TokenizerError::Argument(format!(
                "FSQ levels must be a non-empty list of values >= 2, got {:?}",
                config.levels
            )));
        }
        let codebook = config
            .levels
            .iter()
            .try_fold(1usize, |acc, &l| acc.checked_mul(l));
        // Indices travel as u32 and pass through f32 arithmetic, exact below 2^24.
        if codebook.is_none_or(|size| size > 1 << 24) {
            return Err(TokenizerError::Argument(format!(
                "FSQ codebook {:?} exceeds 2^24 codes",
                config.levels
            )));
        }
        let d_q = config.levels.len();
        Ok(Self {
            proj_in: candle_nn::linear(config.dim, d_q, vb.pp("proj_in"))?,
            proj_out: candle_nn::linear(d_q, config.dim, vb.pp("proj_out"))?,
            levels: config.levels.clone(),
            bound: config.bound,
        })
    }

    /// Levels per quantized channel.
    pub fn levels(&self) -> &[usize] {
        &self.levels
    }

    /// Number of codes, `Π L_i`.
    pub fn codebook_size(&self) -> usize {
        self.levels.iter().product()
    }

    /// Project `x` (`..., dim`), quantize, and project back.
    pub fn forward(&self, x: &Tensor) -> Result<FsqOutput, TokenizerError> {
        let z = self.proj_in.forward(x)?;
        let codes = self.quantize(&z)?;
        let indices = self.codes_to_indices(&codes)?;
        let quantized = self.proj_out.forward(&codes)?;
        Ok(FsqOutput {
            quantized,
            codes,
            indices,
        })
    }

    /// Project normalised codes (`..., d_q`) back to `dim` channels (the decoder's input).
    pub fn project_out(&self, codes: &Tensor) -> Result<Tensor, TokenizerError> {
        Ok(self.proj_out.forward(codes)?)
    }

    /// The constant buffers of the PyTorch reference's `FSQ` module (`L`, `half_l`, `offset`,
    /// `shift`, `half_width`, `basis`), so a saved state dict loads there strictly.
    pub fn buffers(&self) -> Vec<(&'static str, Vec<f32>)> {
        let levels: Vec<f64> = self.levels.iter().map(|&l| l as f64).collect();
        let TanhConstants {
            half_l,
            offset,
            shift,
        } = self.tanh_constants();
        let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        vec![
            ("L", f32s(&levels)),
            ("half_l", f32s(&half_l)),
            ("offset", f32s(&offset)),
            ("shift", f32s(&shift)),
            ("half_width", f32s(&self.half_widths())),
            ("basis", f32s(&self.basis())),
        ]
    }

    /// Bound `z` (`..., d_q`) channel-wise so rounding yields the centred integer levels.
    pub fn bound(&self, z: &Tensor) -> Result<Tensor, TokenizerError> {
        let bounded = match self.bound {
            Bound::Tanh => {
                let TanhConstants {
                    half_l,
                    offset,
                    shift,
                } = self.tanh_constants();
                z.broadcast_add(&channel_const(&shift, z)?)?
                    .tanh()?
                    .broadcast_mul(&channel_const(&half_l, z)?)?
                    .broadcast_sub(&channel_const(&offset, z)?)?
            }
            Bound::Sigmoid => {
                let span: Vec<f64> = self.levels.iter().map(|&l| l as f64 - 1.0).collect();
                candle_nn::ops::sigmoid(z)?
                    .broadcast_mul(&channel_const(&span, z)?)?
                    .broadcast_sub(&channel_const(&self.half_widths(), z)?)?
            }
        };
        Ok(bounded)
    }

    /// Bound, round (straight-through) and normalise `z` (`..., d_q`) to codes in [-1, 1].
    pub fn quantize(&self, z: &Tensor) -> Result<Tensor, TokenizerError> {
        let bounded = self.bound(z)?;
        let rounded = straight_through(&bounded, &bounded.round()?)?;
        Ok(rounded.broadcast_div(&channel_const(&self.half_widths(), z)?)?)
    }

    /// Codebook index of each normalised code vector (`..., d_q` → `...`, u32): the
    /// mixed-radix number whose digit `i` is `level_i + half_width_i` in base `L_i`, with
    /// place values (basis) `1, L_0, L_0·L_1, …`.
    pub fn codes_to_indices(&self, codes: &Tensor) -> Result<Tensor, TokenizerError> {
        let codes = codes.detach().to_dtype(DType::F32)?;
        let half = channel_const(&self.half_widths(), &codes)?;
        let digits = codes.broadcast_mul(&half)?.broadcast_add(&half)?.round()?;
        let index = digits
            .broadcast_mul(&channel_const(&self.basis(), &codes)?)?
            .sum(D::Minus1)?;
        Ok(index.to_dtype(DType::U32)?)
    }

    /// Normalised code vectors of codebook indices (`...`, u32 → `..., d_q`, f32): the
    /// inverse of [`Self::codes_to_indices`].
    pub fn indices_to_codes(&self, indices: &Tensor) -> Result<Tensor, TokenizerError> {
        let index = indices.to_dtype(DType::F32)?.unsqueeze(D::Minus1)?;
        let basis = channel_const(&self.basis(), &index)?;
        let levels: Vec<f64> = self.levels.iter().map(|&l| l as f64).collect();
        let levels = channel_const(&levels, &index)?;
        let half = channel_const(&self.half_widths(), &index)?;
        // Exact in f32: indices stay below 2^24 and quotients are floored before use.
        let place = index.broadcast_div(&basis)?.floor()?;
        let digits = (&place
            - place
                .broadcast_div(&levels)?
                .floor()?
                .broadcast_mul(&levels)?)?;
        Ok(digits.broadcast_sub(&half)?.broadcast_div(&half)?)
    }

    /// Per-channel constants of the tanh bound (see [`Bound::Tanh`]).
    fn tanh_constants(&self) -> TanhConstants {
        let half_l: Vec<f64> = self
            .levels
            .iter()
            .map(|&l| (l as f64 - 1.0) * (1.0 + TANH_EPS) / 2.0)
            .collect();
        let offset: Vec<f64> = self
            .levels
            .iter()
            .map(|&l| if l % 2 == 0 { 0.5 } else { 0.0 })
            .collect();
        let shift = offset
            .iter()
            .zip(&half_l)
            .map(|(o, h)| (o / h).atanh())
            .collect();
        TanhConstants {
            half_l,
            offset,
            shift,
        }
    }

    /// `L_i / 2` (integer division) per channel: the divisor that normalises levels.
    fn half_widths(&self) -> Vec<f64> {
        self.levels.iter().map(|&l| (l / 2) as f64).collect()
    }

    /// Place value of each channel's digit in the mixed-radix index.
    fn basis(&self) -> Vec<f64> {
        self.levels
            .iter()
            .scan(1usize, |acc, &l| {
                let place = *acc;
                *acc *= l;
                Some(place as f64)
            })
            .collect()
    }
}

/// `half_l`, `offset` and `shift` of the tanh bound, per channel.
struct TanhConstants {
    half_l: Vec<f64>,
    offset: Vec<f64>,
    shift: Vec<f64>,
}

/// A per-channel constant (`d_q`) on the device and in the dtype of `like`, broadcasting
/// against its last dimension.
fn channel_const(values: &[f64], like: &Tensor) -> candle_core::Result<Tensor> {
    Tensor::new(values, like.device())?.to_dtype(like.dtype())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn quantizer(levels: &[usize], bound: Bound) -> FsqQuantizer {
        let config = FsqConfig {
            dim: 4,
            levels: levels.to_vec(),
            bound,
        };
        let vb = VarBuilder::zeros(DType::F32, &Device::Cpu);
        FsqQuantizer::new(&config, vb).unwrap()
    }

    /// Quantize one column of inputs through a single-channel quantizer with `levels` levels.
    fn integer_levels(levels: usize, bound: Bound, z: &[f32]) -> Vec<f32> {
        let q = quantizer(&[levels], bound);
        let z = Tensor::new(z, &Device::Cpu).unwrap().unsqueeze(1).unwrap();
        let codes = q.quantize(&z).unwrap().squeeze(1).unwrap();
        let half = (levels / 2) as f64;
        codes.affine(half, 0.0).unwrap().to_vec1::<f32>().unwrap()
    }

    #[test]
    fn level_sets_and_nominal_sizes() {
        assert_eq!(levels_for(256), Some(&[8usize, 6, 5][..]));
        assert_eq!(levels_for(1024), Some(&[8usize, 5, 5, 5][..]));
        assert_eq!(levels_for(4096), Some(&[7usize, 5, 5, 5, 5][..]));
        assert_eq!(levels_for(16384), Some(&[8usize, 8, 8, 6, 5][..]));
        assert_eq!(levels_for(65536), Some(&[8usize, 8, 8, 5, 5, 5][..]));
        assert_eq!(levels_for(512), None);
        let sizes: Vec<usize> = [256, 1024, 4096, 16384, 65536]
            .iter()
            .map(|&n| quantizer(levels_for(n).unwrap(), Bound::Tanh).codebook_size())
            .collect();
        assert_eq!(sizes, vec![240, 1000, 4375, 15360, 64000]);
    }

    #[test]
    fn tanh_bound_rounds_to_known_levels() {
        // L = 5: half_l = 1.998, no shift; tanh(0.2)·1.998 = 0.394 → 0,
        // tanh(0.5)·1.998 = 0.923 → 1, tanh(10)·1.998 = 1.998 → 2.
        assert_eq!(
            integer_levels(5, Bound::Tanh, &[-10.0, -0.5, 0.2, 0.5, 10.0]),
            vec![-2.0, -1.0, 0.0, 1.0, 2.0]
        );
        // L = 8: half_l = 3.4965, offset 0.5, the shift puts z = 0 at exactly 0;
        // the extremes reach 3.4965 - 0.5 → 3 and -3.4965 - 0.5 → -4.
        // z = 0.2: tanh(0.344)·3.4965 - 0.5 = 0.658 → 1.
        assert_eq!(
            integer_levels(8, Bound::Tanh, &[-10.0, 0.0, 0.2, 10.0]),
            vec![-4.0, 0.0, 1.0, 3.0]
        );
    }

    #[test]
    fn sigmoid_bound_rounds_to_known_levels() {
        // L = 5: sigmoid(z)·4 - 2; sigmoid(1) = 0.731 → 0.924 → 1, sigmoid(0.3) = 0.574 → 0.298 → 0.
        assert_eq!(
            integer_levels(5, Bound::Sigmoid, &[-10.0, -1.0, 0.3, 1.0, 10.0]),
            vec![-2.0, -1.0, 0.0, 1.0, 2.0]
        );
        // L = 8: sigmoid(z)·7 - 4; sigmoid(0.1)·7 = 3.675 → -0.325 → 0.
        assert_eq!(
            integer_levels(8, Bound::Sigmoid, &[-10.0, 0.1, 10.0]),
            vec![-4.0, 0.0, 3.0]
        );
    }

    #[test]
    fn codes_are_normalised_to_unit_range() {
        let q = quantizer(&[8, 5], Bound::Tanh);
        let z = Tensor::new(&[[-10f32, -10.0], [10.0, 10.0]], &Device::Cpu).unwrap();
        let codes = q.quantize(&z).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(codes, vec![vec![-1.0, -1.0], vec![0.75, 1.0]]);
        // Level digits (0, 0) and (7, 4): index 0 and 7 + 4·8 = 39.
        let idx = q.codes_to_indices(&q.quantize(&z).unwrap()).unwrap();
        assert_eq!(idx.to_vec1::<u32>().unwrap(), vec![0, 39]);
    }

    #[test]
    fn index_code_bijection_over_every_level_set() {
        for nominal in [256, 1024, 4096, 16384, 65536] {
            let levels = levels_for(nominal).unwrap();
            let q = quantizer(levels, Bound::Tanh);
            let n = q.codebook_size() as u32;
            let all = Tensor::arange(0u32, n, &Device::Cpu).unwrap();
            let codes = q.indices_to_codes(&all).unwrap();
            assert_eq!(codes.dims(), &[n as usize, levels.len()]);
            let back = q
                .codes_to_indices(&codes)
                .unwrap()
                .to_vec1::<u32>()
                .unwrap();
            assert_eq!(back, (0..n).collect::<Vec<_>>(), "level set {levels:?}");
            // Every code is a valid level combination in [-1, 1].
            for row in codes.to_vec2::<f32>().unwrap() {
                for (c, &l) in row.iter().zip(levels) {
                    let level = c * (l / 2) as f32;
                    assert!((-1.0..=1.0).contains(c), "{c} outside [-1, 1]");
                    assert_eq!(level, level.round());
                    assert!(level >= -((l / 2) as f32) && level <= (l - 1 - l / 2) as f32);
                }
            }
        }
    }

    #[test]
    fn straight_through_gradient_is_the_bound_derivative() {
        // Through the rounding the gradient is the identity, so d code / dz is the bound's
        // derivative over half_width: (1 - tanh²(z + shift))·half_l / half_width.
        for (levels, z) in [(5usize, 0.3f64), (8, -0.4)] {
            let q = quantizer(&[levels], Bound::Tanh);
            let var = Var::new(&[[z as f32]], &Device::Cpu).unwrap();
            let codes = q.quantize(var.as_tensor()).unwrap();
            let grads = codes.sum_all().unwrap().backward().unwrap();
            let g = grads.get(&var).unwrap().to_vec2::<f32>().unwrap()[0][0] as f64;
            let half_l = (levels as f64 - 1.0) * (1.0 + TANH_EPS) / 2.0;
            let offset = if levels % 2 == 0 { 0.5 } else { 0.0 };
            let t = (z + (offset / half_l).atanh()).tanh();
            let expected = (1.0 - t * t) * half_l / (levels / 2) as f64;
            assert!(g != 0.0);
            assert!((g - expected).abs() < 1e-5, "L={levels}: {g} vs {expected}");
        }
        // Sigmoid bound, L = 5, z = 0: sigmoid'(0)·4 / 2 = 0.5.
        let q = quantizer(&[5], Bound::Sigmoid);
        let var = Var::new(&[[0f32]], &Device::Cpu).unwrap();
        let grads = q.quantize(var.as_tensor()).unwrap().sum_all().unwrap();
        let g = grads
            .backward()
            .unwrap()
            .get(&var)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        assert!((g[0][0] - 0.5).abs() < 1e-6);
    }

    #[test]
    fn forward_shapes_and_rejected_configs() {
        let q = quantizer(&[8, 6, 5], Bound::Tanh);
        let x = Tensor::ones((2, 7, 4), DType::F32, &Device::Cpu).unwrap();
        let out = q.forward(&x).unwrap();
        assert_eq!(out.quantized.dims(), &[2, 7, 4]);
        assert_eq!(out.codes.dims(), &[2, 7, 3]);
        assert_eq!(out.indices.dims(), &[2, 7]);
        // Zero weights and biases: z = 0 → levels (0, 0, 0) → digits (4, 3, 2) → 4 + 3·8 + 2·48.
        assert!(out
            .indices
            .flatten_all()
            .unwrap()
            .to_vec1::<u32>()
            .unwrap()
            .iter()
            .all(|&i| i == 124));
        let vb = VarBuilder::zeros(DType::F32, &Device::Cpu);
        for levels in [vec![], vec![5, 1]] {
            let config = FsqConfig {
                dim: 4,
                levels,
                bound: Bound::Tanh,
            };
            assert!(FsqQuantizer::new(&config, vb.clone()).is_err());
        }
    }
}
