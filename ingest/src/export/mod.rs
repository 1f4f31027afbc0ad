//! Exports of corpus clips to formats other tools read: the HumanML3D folder layout and BVH.

pub mod builtin_tagger;
pub mod bvh;
pub mod hml3d;
pub mod spacy;
pub mod text_process;
