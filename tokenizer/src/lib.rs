//! Quantizers of the motion tokenizers (issue 3) and their codebook metrics.
//!
//! [`FsqQuantizer`] (finite scalar quantization, Mentzer et al.) and [`VqQuantizer`]
//! (nearest-code VQ with an EMA codebook and dead-code reset, as in T2M-GPT) both map
//! encoder outputs (`..., dim`) to a straight-through quantized tensor and one code index
//! per position; [`CodeUsage`] turns those indices into utilisation and perplexity.
//! [`ConvEncoder`] and [`ConvDecoder`] are the T2M-GPT convolutional networks around them.
//! The `cuda` feature (off by default) builds candle with CUDA.

pub mod checkpoint;
pub mod conv;
pub mod conv_op;
pub mod error;
pub mod evaluate;
pub mod fsq;
pub mod loss;
pub mod model;
pub mod optim;
pub mod ste;
pub mod sweep;
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
