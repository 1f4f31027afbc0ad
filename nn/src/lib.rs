//! The CPU numerics every model of motionscale shares, below the models themselves:
//!
//! - [`device`]: the devices and precisions the command line names, each device opened once;
//! - [`matmul`] (gemm with the AVX-512 kernels), [`panels`] (decoding's few-row products by
//!   weights packed once), [`kernels`] (what every hand-written executor shares), [`par`]
//!   (their parallel writers) and [`cpu_f32`] (f32 views of candle tensors);
//! - [`conv_op`]: the fused 1-D convolution (im2col + gemm, ReLU and up-sampling fused in) of
//!   the tokenizer and the evaluator;
//! - [`lm_kernels`] and [`seq_layout`]: the prefix LM's fused forward/backward kernels and the
//!   batch layout they read; [`head_loss`]: the LM head fused with its cross-entropy;
//! - [`gru`] and [`gru_kernel`]: the GRU layer (PyTorch's gate layout and names) and its fused
//!   op (projection and recurrence) with a hand-written backward through time;
//! - [`fused_ops`]: RMSNorm, SwiGLU, rotary QKV heads, the masked softmax and the
//!   cross-entropy as single ops with a backward, on the CPU and (`cuda`) the GPU, for the
//!   graph executor; [`device_check`]: those ops and the AdamW step on a device against the CPU;
//! - [`simd`]: the row kernels' vector level (AVX-512, AVX2 + FMA or baseline) chosen at run
//!   time, every level giving the same bits ([`vectorised!`]);
//! - [`optim`] (AdamW with saveable state, warm-up + cosine schedule), [`checkpoint`]
//!   (safetensors written atomically, resumable run files), [`kmeans`], and [`gradcheck`]
//!   (the finite-difference reference of the gradient tests).
//!
//! The `cuda` feature (off by default) builds candle with CUDA and `kernels/fused_ops.cu`
//! (the GPU side of [`fused_ops`], compiled to PTX by `build.rs`); the other fused CPU ops fall
//! back to candle's own ops on GPU tensors.

pub mod checkpoint;
pub mod conv_op;
pub mod cpu_f32;
pub mod device;
pub mod device_check;
pub mod dropout;
pub mod error;
pub mod fast_exp;
pub mod fused_ops;
pub mod gradcheck;
pub mod gru;
pub mod gru_kernel;
pub mod head_loss;
pub mod kernels;
pub mod kmeans;
pub mod lm_kernels;
pub mod matmul;
pub mod model_error;
pub mod optim;
pub mod panels;
pub mod par;
pub mod seq_layout;
pub mod simd;

pub use error::NnError;
pub use model_error::ModelError;
