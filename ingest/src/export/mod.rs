//! Exports of corpus clips to formats other tools read: the HumanML3D folder layout and BVH,
//! and one motion's features as `.npy` or `.bvh` ([`motion`]).

pub mod builtin_tagger;
pub mod bvh;
pub mod hml3d;
pub mod motion;
pub mod spacy;
pub mod text_process;
pub mod token;
