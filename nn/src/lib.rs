//! The CPU numerics every model of motionscale shares, below the models themselves:
//!
//! - [`matmul`] (gemm with the AVX-512 kernels) and [`cpu_f32`] (f32 views of candle tensors);
//! - [`conv_op`]: the fused 1-D convolution (im2col + gemm, ReLU and up-sampling fused in) of
//!   the tokenizer and the evaluator;
//! - [`lm_kernels`] and [`seq_layout`]: the prefix LM's fused forward/backward kernels and the
//!   batch layout they read; [`head_loss`]: the LM head fused with its cross-entropy;
//! - [`gru`] and [`gru_kernel`]: the GRU layer (PyTorch's gate layout and names) and its fused
//!   scan with a hand-written backward through time;
//! - [`optim`] (AdamW with saveable state, warm-up + cosine schedule), [`checkpoint`]
//!   (safetensors written atomically, resumable run files), [`kmeans`], and [`gradcheck`]
//!   (the finite-difference reference of the gradient tests).
//!
//! The `cuda` feature (off by default) builds candle with CUDA; the fused CPU ops then fall
//! back to candle's own ops on GPU tensors.

pub mod checkpoint;
pub mod conv_op;
pub mod cpu_f32;
pub mod error;
pub mod fast_exp;
pub mod gradcheck;
pub mod gru;
pub mod gru_kernel;
pub mod head_loss;
pub mod kmeans;
pub mod lm_kernels;
pub mod matmul;
pub mod model_error;
pub mod optim;
pub mod seq_layout;

pub use error::NnError;
pub use model_error::ModelError;

/// The device models load onto: the first CUDA GPU when built with `cuda` and one is
/// present, else the CPU.
///
/// Opened once per process: each `Device::new_cuda` is a new device (its own context, handles
/// and kernels), and candle refuses to combine tensors of two of them.
pub fn default_device() -> candle_core::Device {
    #[cfg(feature = "cuda")]
    {
        static DEVICE: std::sync::OnceLock<candle_core::Device> = std::sync::OnceLock::new();
        DEVICE
            .get_or_init(|| candle_core::Device::new_cuda(0).unwrap_or(candle_core::Device::Cpu))
            .clone()
    }
    #[cfg(not(feature = "cuda"))]
    candle_core::Device::Cpu
}
