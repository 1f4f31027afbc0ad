//! The T2M-GPT convolutional motion encoder and decoder, mirroring
//! `shared/bench/pytorch_vqvae.py` layer for layer so that its `state_dict` and our
//! safetensors share every key and shape.
//!
//! Both networks are an `nn.Sequential` called `net` in PyTorch, so parameter keys are
//! `net.{index}.…` where `index` counts every layer, parameter-free ones (ReLU, Upsample)
//! included. With `D = down_t` and `u` running over the `depth` residual units of a stack:
//!
//! | layer                               | encoder key                    | decoder key                    |
//! |-------------------------------------|--------------------------------|--------------------------------|
//! | input conv (k3)                     | `net.0`                        | `net.0`                        |
//! | stage `s` stride-2 conv (k4)        | `net.{2+2s}`                   | —                              |
//! | stage `s` residual unit `u`         | `net.{3+2s}.units.{u}.conv{1,2}` | `net.{2+3s}.units.{u}.conv{1,2}` |
//! | stage `s` conv after upsampling     | —                              | `net.{4+3s}`                   |
//! | conv before the output (k3)         | —                              | `net.{2+3D}`                   |
//! | output conv (k3)                    | `net.{2+2D}`                   | `net.{4+3D}`                   |
//!
//! each with `.weight` (`out, in, kernel`, the layout of both PyTorch and candle) and
//! `.bias`. Inside `MotionVQVAE` the two networks sit under `encoder.` and `decoder.`:
//! build them with `vb.pp("encoder")` and `vb.pp("decoder")`.
//!
//! Tensors are (batch, frames, features) everywhere: the convolutions run channels-last
//! ([`crate::conv_op`]), with the ReLUs and up-samplings of the PyTorch `net` fused into the
//! input reads of the convolutions that follow them.

use crate::error::TokenizerError;
use candle_core::{Module, Tensor};
use candle_nn::{Init, VarBuilder};
use nn::conv_op::{conv1d, ConvGeometry};
use serde::{Deserialize, Serialize};

/// Shape of a T2M-GPT encoder/decoder pair.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct ConvConfig {
    /// Features per frame of the motion representation (263 for HumanML3D).
    pub input_dim: usize,
    /// Channels of every hidden convolution.
    pub width: usize,
    /// Channels of the latent (encoder output, decoder input).
    pub code_dim: usize,
    /// Number of stride-2 stages; time is down-sampled by `2^down_t`.
    pub down_t: usize,
    /// Residual units per dilated stack.
    pub depth: usize,
    /// Ratio between the dilations of consecutive residual units.
    pub dilation_growth: usize,
}

impl Default for ConvConfig {
    fn default() -> Self {
        Self {
            input_dim: 263,
            width: 512,
            code_dim: 512,
            down_t: 2,
            depth: 3,
            dilation_growth: 3,
        }
    }
}

impl ConvConfig {
    /// Temporal down-sampling factor of the encoder, `2^down_t`.
    pub fn downsample_factor(&self) -> usize {
        1 << self.down_t
    }

    /// Dilations of the residual units in application order: `growth^(depth-1), …, growth, 1`
    /// (T2M-GPT's `reverse_dilation=True`).
    pub fn dilations(&self) -> Vec<usize> {
        (0..self.depth)
            .rev()
            .map(|i| self.dilation_growth.pow(i as u32))
            .collect()
    }

    /// Multiply-accumulates of one encoder + decoder forward pass over `frames` frames of
    /// one clip (convolutions only, as PyTorch forward hooks count them).
    pub fn forward_macs(&self, frames: usize) -> u64 {
        let (w, c, f) = (
            self.width as u64,
            self.code_dim as u64,
            self.input_dim as u64,
        );
        let conv = |frames: u64, inp: u64, out: u64, k: u64| frames * inp * out * k;
        let unit = |frames: u64| conv(frames, w, w, 3) + conv(frames, w, w, 1);
        let units = |frames: u64| self.depth as u64 * unit(frames);
        let mut macs = conv(frames as u64, f, w, 3);
        let mut t = frames as u64;
        for _ in 0..self.down_t {
            t /= 2;
            macs += conv(t, w, w, 4) + units(t);
        }
        macs += conv(t, w, c, 3) + conv(t, c, w, 3);
        for _ in 0..self.down_t {
            macs += units(t);
            t *= 2;
            macs += conv(t, w, w, 3);
        }
        macs + conv(t, w, w, 3) + conv(t, w, f, 3)
    }

    fn validate(&self) -> Result<(), TokenizerError> {
        let sizes = [
            ("input_dim", self.input_dim),
            ("width", self.width),
            ("code_dim", self.code_dim),
            ("dilation_growth", self.dilation_growth),
        ];
        if let Some((name, _)) = sizes.iter().find(|(_, v)| *v == 0) {
            return Err(TokenizerError::Argument(format!(
                "conv {name} must be positive"
            )));
        }
        // Keeps 2^down_t and growth^(depth-1) far from overflow.
        if self.down_t > 16 || self.depth > 16 {
            return Err(TokenizerError::Argument(format!(
                "conv down_t ({}) and depth ({}) must be at most 16",
                self.down_t, self.depth
            )));
        }
        Ok(())
    }
}

/// A `Conv1d(in, out, kernel, stride, padding, dilation)` with PyTorch's parameters
/// (`weight` (out, in, kernel), `bias` (out), initialised as `nn.Conv1d` does) applied
/// channels-last by the fused op, with the input pre-ops of its geometry.
#[derive(Debug, Clone)]
struct Conv {
    weight: Tensor,
    bias: Tensor,
    geometry: ConvGeometry,
}

impl Conv {
    #[allow(clippy::too_many_arguments)]
    fn new(
        (inp, out, kernel): (usize, usize, usize),
        stride: usize,
        padding: usize,
        dilation: usize,
        relu_input: bool,
        upsample_input: bool,
        vb: VarBuilder,
    ) -> candle_core::Result<Self> {
        // PyTorch's default: U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weight and bias.
        let bound = 1.0 / ((inp * kernel) as f64).sqrt();
        let init = Init::Uniform {
            lo: -bound,
            up: bound,
        };
        Ok(Self {
            weight: vb.get_with_hints((out, inp, kernel), "weight", init)?,
            bias: vb.get_with_hints(out, "bias", init)?,
            geometry: ConvGeometry {
                kernel,
                stride,
                dilation,
                padding,
                relu_input,
                upsample_input,
            },
        })
    }

    /// A stride-1 convolution that keeps the length (`padding = dilation·(k-1)/2`).
    fn same(
        channels: (usize, usize),
        kernel: usize,
        dilation: usize,
        relu_input: bool,
        vb: VarBuilder,
    ) -> candle_core::Result<Self> {
        let (inp, out) = channels;
        let padding = dilation * (kernel - 1) / 2;
        Self::new(
            (inp, out, kernel),
            1,
            padding,
            dilation,
            relu_input,
            false,
            vb,
        )
    }
}

impl Module for Conv {
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        conv1d(x, &self.weight, &self.bias, self.geometry)
    }
}

/// One residual unit: `x + conv2(relu(conv1(relu(x))))`, `conv1` of kernel 3 and dilation
/// `d` (padding `d` keeps the length), `conv2` of kernel 1; no normalisation. Both ReLUs
/// are fused into the convolutions' input reads.
#[derive(Debug, Clone)]
struct ResUnit {
    conv1: Conv,
    conv2: Conv,
}

impl ResUnit {
    fn new(width: usize, dilation: usize, vb: VarBuilder) -> candle_core::Result<Self> {
        Ok(Self {
            conv1: Conv::same((width, width), 3, dilation, true, vb.pp("conv1"))?,
            conv2: Conv::same((width, width), 1, 1, true, vb.pp("conv2"))?,
        })
    }
}

impl Module for ResUnit {
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        x + self.conv2.forward(&self.conv1.forward(x)?)?
    }
}

/// A stack of residual units with dilations [`ConvConfig::dilations`], keys `units.{u}`.
#[derive(Debug, Clone)]
struct Resnet1d {
    units: Vec<ResUnit>,
}

impl Resnet1d {
    fn new(config: &ConvConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let vb = vb.pp("units");
        let units = config
            .dilations()
            .into_iter()
            .enumerate()
            .map(|(u, d)| ResUnit::new(config.width, d, vb.pp(u)))
            .collect::<candle_core::Result<_>>()?;
        Ok(Self { units })
    }
}

impl Module for Resnet1d {
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        self.units
            .iter()
            .try_fold(x.clone(), |h, unit| unit.forward(&h))
    }
}

/// Check `x` is (batch, frames, `features`) with `frames` a positive multiple of `multiple`.
fn check_input(
    x: &Tensor,
    features: usize,
    multiple: usize,
    what: &str,
) -> Result<(), TokenizerError> {
    let (_, frames, channels) = x.dims3()?;
    if channels != features {
        return Err(TokenizerError::Argument(format!(
            "{what} expects {features} features per frame, got {channels}"
        )));
    }
    if frames == 0 || frames % multiple != 0 {
        return Err(TokenizerError::Argument(format!(
            "{what} needs a positive multiple of {multiple} frames, got {frames}"
        )));
    }
    Ok(())
}

/// T2M-GPT motion encoder: (batch, frames, `input_dim`) → (batch, frames / 2^down_t, `code_dim`).
#[derive(Debug, Clone)]
pub struct ConvEncoder {
    input: Conv,
    /// Per stage: the stride-2 down-sampling conv, then its residual stack.
    stages: Vec<(Conv, Resnet1d)>,
    output: Conv,
    config: ConvConfig,
}

impl ConvEncoder {
    /// Build from `config` with the PyTorch keys `net.{i}.…` under `vb` (see the module docs).
    pub fn new(config: &ConvConfig, vb: VarBuilder) -> Result<Self, TokenizerError> {
        config.validate()?;
        let (w, net) = (config.width, vb.pp("net"));
        let input = Conv::same((config.input_dim, w), 3, 1, false, net.pp(0))?;
        let stages = (0..config.down_t)
            .map(|s| {
                // The ReLU after the input conv (net.1) is fused into the first down conv.
                let down = Conv::new((w, w, 4), 2, 1, 1, s == 0, false, net.pp(2 + 2 * s))?;
                Ok((down, Resnet1d::new(config, net.pp(3 + 2 * s))?))
            })
            .collect::<candle_core::Result<_>>()?;
        let output = Conv::same(
            (w, config.code_dim),
            3,
            1,
            config.down_t == 0,
            net.pp(2 + 2 * config.down_t),
        )?;
        Ok(Self {
            input,
            stages,
            output,
            config: config.clone(),
        })
    }

    /// The configuration this encoder was built from.
    pub fn config(&self) -> &ConvConfig {
        &self.config
    }

    /// Encode `x` (batch, frames, `input_dim`); `frames` must be a positive multiple of
    /// `2^down_t`, so the decoder restores exactly the input length.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor, TokenizerError> {
        let factor = self.config.downsample_factor();
        check_input(x, self.config.input_dim, factor, "conv encoder")?;
        let h = self.input.forward(x)?;
        let h = self
            .stages
            .iter()
            .try_fold(h, |h, (down, res)| res.forward(&down.forward(&h)?))?;
        Ok(self.output.forward(&h)?)
    }
}

/// One decoder stage: residual stack, then a k3 conv reading the ×2 nearest up-sampled input.
#[derive(Debug, Clone)]
struct UpStage {
    resnet: Resnet1d,
    conv: Conv,
}

/// T2M-GPT motion decoder: (batch, latents, `code_dim`) → (batch, latents · 2^down_t, `input_dim`).
#[derive(Debug, Clone)]
pub struct ConvDecoder {
    input: Conv,
    stages: Vec<UpStage>,
    post: Conv,
    output: Conv,
    config: ConvConfig,
}

impl ConvDecoder {
    /// Build from `config` with the PyTorch keys `net.{i}.…` under `vb` (see the module docs).
    pub fn new(config: &ConvConfig, vb: VarBuilder) -> Result<Self, TokenizerError> {
        config.validate()?;
        let (w, net) = (config.width, vb.pp("net"));
        let input = Conv::same((config.code_dim, w), 3, 1, false, net.pp(0))?;
        let stages = (0..config.down_t)
            .map(|s| {
                Ok(UpStage {
                    resnet: Resnet1d::new(config, net.pp(2 + 3 * s))?,
                    // Index 3 + 3s is the parameter-free Upsample, fused into this conv.
                    conv: Conv::new((w, w, 3), 1, 1, 1, false, true, net.pp(4 + 3 * s))?,
                })
            })
            .collect::<candle_core::Result<_>>()?;
        let last = 2 + 3 * config.down_t;
        let post = Conv::same((w, w), 3, 1, false, net.pp(last))?;
        // net.{last+1} is the ReLU fused into the output conv.
        let output = Conv::same((w, config.input_dim), 3, 1, true, net.pp(last + 2))?;
        Ok(Self {
            input,
            stages,
            post,
            output,
            config: config.clone(),
        })
    }

    /// The configuration this decoder was built from.
    pub fn config(&self) -> &ConvConfig {
        &self.config
    }

    /// Decode `z` (batch, latents, `code_dim`) to (batch, latents · 2^down_t, `input_dim`).
    pub fn forward(&self, z: &Tensor) -> Result<Tensor, TokenizerError> {
        check_input(z, self.config.code_dim, 1, "conv decoder")?;
        // The ReLU after the input conv (net.1) feeds the residual path too: not fusable.
        let h = self.input.forward(z)?.relu()?;
        let h = self
            .stages
            .iter()
            .try_fold(h, |h, stage| stage.conv.forward(&stage.resnet.forward(&h)?))?;
        Ok(self.output.forward(&self.post.forward(&h)?)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fsq::{FsqConfig, FsqQuantizer};
    use candle_core::{DType, Device};
    use candle_nn::VarMap;

    fn tiny() -> ConvConfig {
        ConvConfig {
            width: 16,
            code_dim: 8,
            ..ConvConfig::default()
        }
    }

    fn build(config: &ConvConfig) -> (VarMap, ConvEncoder, ConvDecoder) {
        let map = VarMap::new();
        let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
        let enc = ConvEncoder::new(config, vb.pp("encoder")).unwrap();
        let dec = ConvDecoder::new(config, vb.pp("decoder")).unwrap();
        (map, enc, dec)
    }

    fn motion(batch: usize, frames: usize) -> Tensor {
        Tensor::randn(0f32, 1.0, (batch, frames, 263), &Device::Cpu).unwrap()
    }

    #[test]
    fn encoder_downsamples_by_four_and_decoder_restores_the_shape() {
        let config = tiny();
        assert_eq!(config.downsample_factor(), 4);
        let (_map, enc, dec) = build(&config);
        for frames in [64, 32] {
            let x = motion(2, frames);
            let z = enc.forward(&x).unwrap();
            assert_eq!(z.dims(), &[2, frames / 4, 8]);
            let y = dec.forward(&z).unwrap();
            assert_eq!(y.dims(), x.dims());
        }
    }

    #[test]
    fn each_latent_sees_only_its_neighbourhood() {
        // Down-sampling by 4 means latent t summarises frames near 4t: perturbing the last
        // frame leaves the first latent (receptive field well under 64 frames) unchanged.
        let (_map, enc, _dec) = build(&tiny());
        let x = motion(1, 256);
        let last = (x.narrow(1, 255, 1).unwrap() + 5.0).unwrap();
        let bumped = Tensor::cat(&[&x.narrow(1, 0, 255).unwrap(), &last], 1).unwrap();
        let (a, b) = (enc.forward(&x).unwrap(), enc.forward(&bumped).unwrap());
        let diff = |t: usize| {
            (a.narrow(1, t, 1).unwrap() - b.narrow(1, t, 1).unwrap())
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap()
        };
        assert_eq!(diff(0), 0.0);
        assert!(diff(63) > 0.0);
    }

    #[test]
    fn dilations_are_reversed_powers_of_the_growth() {
        assert_eq!(ConvConfig::default().dilations(), vec![9, 3, 1]);
    }

    #[test]
    fn bad_inputs_are_rejected() {
        let (_map, enc, dec) = build(&tiny());
        assert!(enc.forward(&motion(1, 30)).is_err());
        let wrong = Tensor::zeros((1, 32, 262), DType::F32, &Device::Cpu).unwrap();
        assert!(enc.forward(&wrong).is_err());
        let wrong = Tensor::zeros((1, 8, 9), DType::F32, &Device::Cpu).unwrap();
        assert!(dec.forward(&wrong).is_err());
        let zero = ConvConfig { width: 0, ..tiny() };
        let map = VarMap::new();
        let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
        assert!(ConvEncoder::new(&zero, vb).is_err());
    }

    #[test]
    fn parameter_count_matches_the_hand_count() {
        let (map, _enc, _dec) = build(&tiny());
        let total: usize = map.all_vars().iter().map(|v| v.elem_count()).sum();
        // Conv1d(i, o, k) has o·i·k + o parameters. Width 16, code_dim 8, 263 features.
        // A residual unit: (16·16·3 + 16) + (16·16·1 + 16) = 784 + 272 = 1056; six per net.
        // Encoder: (263·16·3 + 16) + 2·(16·16·4 + 16) + 6·1056 + (16·8·3 + 8)
        //        = 12640 + 2080 + 6336 + 392 = 21448.
        // Decoder: (8·16·3 + 16) + 6·1056 + 2·784 + 784 + (16·263·3 + 263)
        //        = 400 + 6336 + 1568 + 784 + 12887 = 21975.
        assert_eq!(total, 21448 + 21975);
    }

    #[test]
    fn keys_match_the_pytorch_state_dict() {
        let (map, _enc, _dec) = build(&tiny());
        let units = |prefix: &str| -> Vec<String> {
            (0..3)
                .flat_map(|u| ["conv1", "conv2"].map(|c| format!("{prefix}.units.{u}.{c}")))
                .collect()
        };
        // Layer indices of `Encoder.net` / `Decoder.net` in pytorch_vqvae.py (down_t = 2).
        let mut layers: Vec<String> = ["encoder.net.0", "encoder.net.2"]
            .map(String::from)
            .into_iter()
            .chain(units("encoder.net.3"))
            .chain(["encoder.net.4".to_string()])
            .chain(units("encoder.net.5"))
            .chain(["encoder.net.6", "decoder.net.0"].map(String::from))
            .chain(units("decoder.net.2"))
            .chain(["decoder.net.4".to_string()])
            .chain(units("decoder.net.5"))
            .chain(["decoder.net.7", "decoder.net.8", "decoder.net.10"].map(String::from))
            .collect();
        layers.sort();
        let mut expected: Vec<String> = layers
            .iter()
            .flat_map(|l| [format!("{l}.bias"), format!("{l}.weight")])
            .collect();
        expected.sort();
        let data = map.data().lock().unwrap();
        let mut keys: Vec<String> = data.keys().cloned().collect();
        keys.sort();
        assert_eq!(keys, expected);
        let shape = |k: &str| data[k].dims().to_vec();
        assert_eq!(shape("encoder.net.0.weight"), vec![16, 263, 3]);
        assert_eq!(shape("encoder.net.2.weight"), vec![16, 16, 4]);
        assert_eq!(shape("encoder.net.3.units.0.conv1.weight"), vec![16, 16, 3]);
        assert_eq!(shape("encoder.net.3.units.0.conv2.weight"), vec![16, 16, 1]);
        assert_eq!(shape("encoder.net.6.weight"), vec![8, 16, 3]);
        assert_eq!(shape("decoder.net.0.weight"), vec![16, 8, 3]);
        assert_eq!(shape("decoder.net.10.weight"), vec![263, 16, 3]);
        assert_eq!(shape("decoder.net.10.bias"), vec![263]);
    }

    #[test]
    fn gradient_reaches_the_first_encoder_conv_through_fsq() {
        let config = tiny();
        let map = VarMap::new();
        let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
        let enc = ConvEncoder::new(&config, vb.pp("encoder")).unwrap();
        let fsq = FsqQuantizer::new(
            &FsqConfig {
                dim: config.code_dim,
                levels: vec![8, 5, 5, 5],
                bound: Default::default(),
            },
            vb.pp("quant"),
        )
        .unwrap();
        let dec = ConvDecoder::new(&config, vb.pp("decoder")).unwrap();
        let x = motion(2, 32);
        let q = fsq.forward(&enc.forward(&x).unwrap()).unwrap().quantized;
        let y = dec.forward(&q).unwrap();
        let loss = (y - &x).unwrap().abs().unwrap().mean_all().unwrap();
        let grads = loss.backward().unwrap();
        let first = map.data().lock().unwrap()["encoder.net.0.weight"].clone();
        let g = grads
            .get(first.as_tensor())
            .expect("no gradient for encoder.net.0.weight");
        assert_eq!(g.dims(), &[16, 263, 3]);
        let norm = g
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(norm.is_finite() && norm > 0.0, "gradient norm {norm}");
    }
}
