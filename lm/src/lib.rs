//! The text-prefix autoregressive motion transformer ([`PrefixLm`]) with its parameter/FLOP
//! [`accounting`], training ([`train()`](train::train), with the run's settings and records in
//! [`run_config`] and the loaders of a trained run in [`load`]) and generation
//! ([`generate()`](generate::generate)), conditioned on the caption embeddings of the `text`
//! crate.

pub mod accounting;
pub mod caption_set;
pub mod es_moe;
pub mod eval_record;
pub mod executor_check;
pub mod generate;
pub mod lm_data;
pub mod load;
pub mod lora;
pub mod prefix_lm;
pub mod run_config;
pub mod selection;
pub mod test_loss;
pub mod train;

pub use prefix_lm::{LmBatch, PrefixLm, PrefixLmConfig};

/// A trained motion LM as generation and evaluation use it: one [`PrefixLm`] for every
/// caption, or a family whose weights depend on the caption (ES-MoE's gated experts).
pub trait MotionLm: Send + Sync {
    /// The model configuration (shared by every caption's model).
    fn config(&self) -> &PrefixLmConfig;
    /// Whether captions get different weights (callers then run one sequence at a time).
    fn per_caption(&self) -> bool;
    /// The model that animates the caption whose token embeddings are `text`.
    fn for_caption(&self, text: &[f32]) -> candle_core::Result<std::borrow::Cow<'_, PrefixLm>>;
}

impl MotionLm for PrefixLm {
    fn config(&self) -> &PrefixLmConfig {
        PrefixLm::config(self)
    }

    fn per_caption(&self) -> bool {
        false
    }

    fn for_caption(&self, _: &[f32]) -> candle_core::Result<std::borrow::Cow<'_, PrefixLm>> {
        Ok(std::borrow::Cow::Borrowed(self))
    }
}
