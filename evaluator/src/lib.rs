//! The text–motion evaluator and the generation metrics read in its space.
//!
//! - [`model`]: the matching model (T2M's movement convolutions + bidirectional GRUs for
//!   motion and text, emotion and action classifiers), saved as a checkpoint PyTorch loads;
//! - [`train`]: its contrastive training on a corpus, resumable;
//! - [`metrics`]: FID, R-precision, matching score, diversity, multimodality, F1, as the
//!   T2M / T2M-GPT evaluation scripts compute them;
//! - [`score`]: `motionscale eval`, the metrics of a motion set (a corpus split or a
//!   HumanML3D-layout folder) against a corpus split, with intervals over repeats.

pub mod metrics;
pub mod model;
pub mod score;
pub mod train;
