//! Motion tokenizers (issue 3): T2M-GPT convolutional VAEs with an FSQ or VQ bottleneck that
//! turn HumanML3D-263 motion into one token per 4 frames, and everything around them.
//!
//! - [`ConvEncoder`] / [`ConvDecoder`]: the T2M-GPT networks, channels-last, on the fused
//!   convolution of `nn::conv_op` (im2col + AVX-512 gemm with ReLU and up-sampling fused in).
//! - [`FsqQuantizer`] (Mentzer et al.'s finite scalar quantization, tanh or ScaMo's sigmoid
//!   bound) and [`VqQuantizer`] (EMA codebook with dead-code reset); [`CodeUsage`] metrics.
//! - [`model::MotionTokenizer`]: encoder + quantizer + decoder + normalisation statistics,
//!   saved as a checkpoint PyTorch loads; [`train`], [`evaluate`] and [`tokens`]
//!   (token sets, the transformer stage's input).
//!
//! The `cuda` feature (off by default) builds candle with CUDA; the fused CPU ops then fall
//! back to candle's own ops on GPU tensors.

pub mod conv;
pub mod error;
pub mod evaluate;
pub mod fsq;
pub mod loss;
pub mod model;
pub mod ste;
pub mod tokens;
pub mod train;
pub mod usage;
pub mod vq;

pub use conv::{ConvConfig, ConvDecoder, ConvEncoder};
pub use error::TokenizerError;
pub use fsq::{levels_for, Bound, FsqConfig, FsqOutput, FsqQuantizer};
pub use tokens::{TokenClip, TokenManifest, TokenSet, TokenizerInfo, UnigramCounts};
pub use usage::CodeUsage;
pub use vq::{VqConfig, VqOutput, VqQuantizer};
