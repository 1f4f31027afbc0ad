//! Exports of corpus clips to formats other tools read: the HumanML3D folder layout and BVH.

pub mod bvh;
pub mod hml3d;
