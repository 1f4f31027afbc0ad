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
//! ([`nn::conv_op`]), with the ReLUs and up-samplings of the PyTorch `net` fused into the
//! input reads of the convolutions that follow them. Both networks are one list of layers
//! that runs two ways: on candle tensors (any device, candle's autograd), and for training on
//! the CPU on plain values with a tape and a hand-written backward pass (`forward_tape`,
//! `backward`), which spares candle's per-activation gradient buffers.

use crate::error::TokenizerError;
use candle_core::{Module, Tensor, Var};
use candle_nn::{Init, VarBuilder};
use nn::conv_op::{conv1d, ConvCpu, ConvGeometry, ConvOutput, ConvWeights};
use nn::cpu_f32::F32Values;
use rayon::prelude::*;
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

    /// The op on CPU values, with the weight in its gemm layout.
    fn cpu(&self) -> candle_core::Result<(ConvCpu, ConvWeights)> {
        let weights = ConvWeights::new(
            &F32Values::of(&self.weight)?,
            &F32Values::of(&self.bias)?,
            self.weight.dims3()?,
        );
        let op = ConvCpu {
            geometry: self.geometry,
            output: ConvOutput::default(),
        };
        Ok((op, weights))
    }
}

impl Module for Conv {
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        conv1d(x, &self.weight, &self.bias, self.geometry)
    }
}

/// One layer of an encoder or decoder, as both executors ([`ConvNet::forward`] on candle
/// tensors, [`ConvNet::forward_tape`] on CPU values) run it.
#[derive(Debug, Clone)]
enum Layer {
    /// `h = conv(h)`.
    Conv(Conv),
    /// A residual unit `h + conv2(relu(conv1(relu(h))))`: `conv1` of kernel 3 and dilation
    /// `d` (padding `d` keeps the length), `conv2` of kernel 1, no normalisation; both ReLUs
    /// are fused into the convolutions' input reads.
    Residual(Conv, Conv),
    /// `h = relu(h)`, where the ReLU's output also feeds a residual path (not fusable).
    Relu,
}

/// The residual stack `units.{u}` of a `Resnet1d`, dilations [`ConvConfig::dilations`].
fn residual_stack(config: &ConvConfig, vb: VarBuilder) -> candle_core::Result<Vec<Layer>> {
    let (w, vb) = (config.width, vb.pp("units"));
    config
        .dilations()
        .into_iter()
        .enumerate()
        .map(|(u, d)| {
            let vb = vb.pp(u);
            Ok(Layer::Residual(
                Conv::same((w, w), 3, d, true, vb.pp("conv1"))?,
                Conv::same((w, w), 1, 1, true, vb.pp("conv2"))?,
            ))
        })
        .collect()
}

/// What a CPU forward pass keeps for its backward pass, per layer.
enum Saved {
    /// The conv's input, its frames, the op and its weights.
    Conv(Box<ConvStep>),
    /// Both convs' steps of a residual unit (the second's input is the first's output).
    Residual(Box<[ConvStep; 2]>),
    /// The ReLU's output.
    Relu(Vec<f32>),
}

/// One convolution as run forward: its input values, im2col matrix and frames, op and weights.
struct ConvStep {
    input: Vec<f32>,
    columns: Option<Vec<f32>>,
    frames: usize,
    op: ConvCpu,
    weights: ConvWeights,
    /// The weight and bias tensors the gradients belong to.
    params: (Tensor, Tensor),
}

impl ConvStep {
    /// Run `conv` on `input` (batch × frames rows), keeping what its backward needs.
    fn run(
        conv: &Conv,
        input: Vec<f32>,
        (batch, frames): (usize, usize),
    ) -> candle_core::Result<(Self, Vec<f32>)> {
        let (op, weights) = conv.cpu()?;
        let (y, columns) = op.forward_keeping_columns(&input, (batch, frames), &weights);
        let step = Self {
            input,
            columns,
            frames,
            op,
            weights,
            params: (conv.weight.clone(), conv.bias.clone()),
        };
        Ok((step, y))
    }

    fn out_frames(&self) -> usize {
        self.op.geometry.out_len(self.frames)
    }

    /// The input gradient (when asked for), pushing the parameter gradients onto `grads`.
    fn backward(
        self,
        batch: usize,
        dy: &[f32],
        input_grad: bool,
        grads: &mut ParamGrads,
    ) -> candle_core::Result<Option<Vec<f32>>> {
        let g = self.op.backward(
            (&self.input, None, self.columns.as_deref()),
            (batch, self.frames),
            &self.weights,
            dy,
            input_grad,
        );
        let (weight, bias) = self.params;
        let dw = Tensor::from_vec(g.weight, weight.shape(), weight.device())?;
        let db = Tensor::from_vec(g.bias, bias.shape(), bias.device())?;
        grads.extend([(weight, dw), (bias, db)]);
        Ok(g.input)
    }
}

/// Gradients of parameters, keyed by the parameter tensors (as a `GradStore` keys them).
pub type ParamGrads = Vec<(Tensor, Tensor)>;

/// A CPU forward pass's activations, for its backward pass.
pub struct Tape {
    /// (batch, frames, channels) of the input.
    input: (usize, usize, usize),
    saved: Vec<Saved>,
}

impl Tape {
    /// The backward pass of the [`ConvNet::forward_tape`] that recorded this tape, for the
    /// output gradient `dy`: the input's gradient (when `input_grad`) and every parameter's.
    fn backward(
        self,
        dy: Vec<f32>,
        input_grad: bool,
    ) -> candle_core::Result<(Option<Vec<f32>>, ParamGrads)> {
        let Tape { input, saved } = self;
        let batch = input.0;
        let mut grads = ParamGrads::new();
        let mut dh = dy;
        for (i, step) in saved.into_iter().enumerate().rev() {
            // The first layer's input gradient only when asked for (not for the data).
            let wanted = input_grad || i > 0;
            match step {
                Saved::Conv(conv) => match conv.backward(batch, &dh, wanted, &mut grads)? {
                    Some(dx) => dh = dx,
                    None => return Ok((None, grads)),
                },
                Saved::Residual(steps) => {
                    let [first, second] = *steps;
                    let dmid = second
                        .backward(batch, &dh, true, &mut grads)?
                        .expect("asked for");
                    let dx = first
                        .backward(batch, &dmid, true, &mut grads)?
                        .expect("asked for");
                    add_assign(&mut dh, &dx);
                }
                Saved::Relu(out) => dh
                    .par_iter_mut()
                    .zip(out.par_iter())
                    .for_each(|(d, &o)| *d = if o > 0.0 { *d } else { 0.0 }),
            }
        }
        Ok((Some(dh), grads))
    }
}

/// `a += b`, in parallel chunks.
fn add_assign(a: &mut [f32], b: &[f32]) {
    a.par_chunks_mut(1 << 14)
        .zip(b.par_chunks(1 << 14))
        .for_each(|(a, b)| a.iter_mut().zip(b).for_each(|(a, b)| *a += b));
}

/// The layers of an encoder or decoder, in order.
#[derive(Debug, Clone)]
struct ConvNet {
    layers: Vec<Layer>,
}

impl ConvNet {
    /// Forward pass on candle tensors (any device; gradients by candle's autograd).
    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        self.layers
            .iter()
            .try_fold(x.clone(), |h, layer| match layer {
                Layer::Conv(conv) => conv.forward(&h),
                Layer::Residual(conv1, conv2) => &h + conv2.forward(&conv1.forward(&h)?)?,
                Layer::Relu => h.relu(),
            })
    }

    /// Forward pass on CPU values `x` (batch × frames × channels, row-major): the output
    /// values and frames, and the tape its hand-written backward pass reads. Off candle's
    /// graph, so no gradient buffer is allocated and zero-filled per activation.
    fn forward_tape(
        &self,
        x: Vec<f32>,
        (batch, frames): (usize, usize),
    ) -> candle_core::Result<(Vec<f32>, usize, Tape)> {
        let input = (batch, frames, x.len() / (batch * frames));
        let (mut h, mut frames) = (x, frames);
        let mut saved = Vec::with_capacity(self.layers.len());
        for layer in &self.layers {
            match layer {
                Layer::Conv(conv) => {
                    let (step, y) = ConvStep::run(conv, h, (batch, frames))?;
                    frames = step.out_frames();
                    saved.push(Saved::Conv(Box::new(step)));
                    h = y;
                }
                Layer::Residual(conv1, conv2) => {
                    let (first, mid) = ConvStep::run(conv1, h, (batch, frames))?;
                    let (second, mut y) = ConvStep::run(conv2, mid, (batch, frames))?;
                    add_assign(&mut y, &first.input);
                    saved.push(Saved::Residual(Box::new([first, second])));
                    h = y;
                }
                Layer::Relu => {
                    h.par_iter_mut().for_each(|v| *v = v.max(0.0));
                    saved.push(Saved::Relu(h.clone()));
                }
            }
        }
        Ok((h, frames, Tape { input, saved }))
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

/// `net` run on CPU values from `x`, its output as a fresh variable (so that candle's autograd
/// of what follows stops there) and the tape of the pass.
fn forward_tape(net: &ConvNet, x: &Tensor) -> Result<(Var, Tape), TokenizerError> {
    let (batch, frames, _) = x.dims3()?;
    let (y, frames, tape) = net.forward_tape(F32Values::of(x)?.to_vec(), (batch, frames))?;
    let channels = y.len() / (batch * frames);
    Ok((
        Var::from_vec(y, (batch, frames, channels), x.device())?,
        tape,
    ))
}

/// The hand-written backward pass recorded in `tape`, for the output gradient `dy`.
fn backward(
    tape: Tape,
    dy: &Tensor,
    input_grad: bool,
) -> Result<(Option<Tensor>, ParamGrads), TokenizerError> {
    let input = tape.input;
    let (dx, grads) = tape.backward(F32Values::of(dy)?.to_vec(), input_grad)?;
    let dx = dx
        .map(|dx| Tensor::from_vec(dx, input, dy.device()))
        .transpose()?;
    Ok((dx, grads))
}

/// T2M-GPT motion encoder: (batch, frames, `input_dim`) → (batch, frames / 2^down_t, `code_dim`).
#[derive(Debug, Clone)]
pub struct ConvEncoder {
    /// Input conv; per stage the stride-2 down-sampling conv and its residual stack; output conv.
    net: ConvNet,
    config: ConvConfig,
}

impl ConvEncoder {
    /// Build from `config` with the PyTorch keys `net.{i}.…` under `vb` (see the module docs).
    pub fn new(config: &ConvConfig, vb: VarBuilder) -> Result<Self, TokenizerError> {
        config.validate()?;
        let (w, net) = (config.width, vb.pp("net"));
        let mut layers = vec![Layer::Conv(Conv::same(
            (config.input_dim, w),
            3,
            1,
            false,
            net.pp(0),
        )?)];
        for s in 0..config.down_t {
            // The ReLU after the input conv (net.1) is fused into the first down conv.
            let down = Conv::new((w, w, 4), 2, 1, 1, s == 0, false, net.pp(2 + 2 * s))?;
            layers.push(Layer::Conv(down));
            layers.extend(residual_stack(config, net.pp(3 + 2 * s))?);
        }
        layers.push(Layer::Conv(Conv::same(
            (w, config.code_dim),
            3,
            1,
            config.down_t == 0,
            net.pp(2 + 2 * config.down_t),
        )?));
        Ok(Self {
            net: ConvNet { layers },
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
        Ok(self.net.forward(x)?)
    }

    /// [`Self::forward`] on the CPU for training: the latents as a fresh variable and the
    /// tape for [`Self::backward`].
    pub fn forward_tape(&self, x: &Tensor) -> Result<(Var, Tape), TokenizerError> {
        check_input(
            x,
            self.config.input_dim,
            self.config.downsample_factor(),
            "conv encoder",
        )?;
        forward_tape(&self.net, x)
    }

    /// Every parameter's gradient for the latents' gradient `dz` (the input gets none).
    pub fn backward(&self, tape: Tape, dz: &Tensor) -> Result<ParamGrads, TokenizerError> {
        Ok(backward(tape, dz, false)?.1)
    }
}

/// T2M-GPT motion decoder: (batch, latents, `code_dim`) → (batch, latents · 2^down_t, `input_dim`).
#[derive(Debug, Clone)]
pub struct ConvDecoder {
    /// Input conv and ReLU; per stage a residual stack, then a k3 conv reading the ×2 nearest
    /// up-sampled input; a k3 conv; the output conv.
    net: ConvNet,
    config: ConvConfig,
}

impl ConvDecoder {
    /// Build from `config` with the PyTorch keys `net.{i}.…` under `vb` (see the module docs).
    pub fn new(config: &ConvConfig, vb: VarBuilder) -> Result<Self, TokenizerError> {
        config.validate()?;
        let (w, net) = (config.width, vb.pp("net"));
        let input = Conv::same((config.code_dim, w), 3, 1, false, net.pp(0))?;
        // The ReLU after the input conv (net.1) feeds the residual path too: not fusable.
        let mut layers = vec![Layer::Conv(input), Layer::Relu];
        for s in 0..config.down_t {
            layers.extend(residual_stack(config, net.pp(2 + 3 * s))?);
            // Index 3 + 3s is the parameter-free Upsample, fused into this conv.
            let up = Conv::new((w, w, 3), 1, 1, 1, false, true, net.pp(4 + 3 * s))?;
            layers.push(Layer::Conv(up));
        }
        let last = 2 + 3 * config.down_t;
        layers.push(Layer::Conv(Conv::same((w, w), 3, 1, false, net.pp(last))?));
        // net.{last+1} is the ReLU fused into the output conv.
        let output = Conv::same((w, config.input_dim), 3, 1, true, net.pp(last + 2))?;
        layers.push(Layer::Conv(output));
        Ok(Self {
            net: ConvNet { layers },
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
        Ok(self.net.forward(z)?)
    }

    /// [`Self::forward`] on the CPU for training: the motion as a fresh variable and the tape
    /// for [`Self::backward`].
    pub fn forward_tape(&self, z: &Tensor) -> Result<(Var, Tape), TokenizerError> {
        check_input(z, self.config.code_dim, 1, "conv decoder")?;
        forward_tape(&self.net, z)
    }

    /// The latents' gradient and every parameter's, for the motion's gradient `dy`.
    pub fn backward(
        &self,
        tape: Tape,
        dy: &Tensor,
    ) -> Result<(Tensor, ParamGrads), TokenizerError> {
        let (dz, grads) = backward(tape, dy, true)?;
        Ok((
            dz.expect("the decoder's input gradient was asked for"),
            grads,
        ))
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
