//! One motion of de-normalised HumanML3D-263 features (decoded or generated) written as a
//! file other tools open, chosen by the extension: `.npy` features (n × 263) or joints
//! (n × 22 × 3, with `joints`), or `.bvh` (20 fps).

use crate::hml263::{recover_joints, recover_joints_f32, FEATURE_DIM};
use std::path::Path;

/// Write `features` (n × 263, row-major) to `out` as features/joints `.npy` or BVH, atomically.
pub fn write_motion(out: &Path, features: &[f32], joints: bool) -> std::io::Result<()> {
    let frames = features.len() / FEATURE_DIM;
    match out.extension().and_then(|e| e.to_str()) {
        Some("bvh") => super::bvh::write_bvh_file(out, &recover_joints(features), 20.0),
        Some("npy") if joints => {
            let flat = recover_joints_f32(features);
            crate::npy::write_f32(out, &[frames, 22, 3], &flat)
        }
        Some("npy") => crate::npy::write_f32(out, &[frames, FEATURE_DIM], features),
        _ => Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "the output must end in .npy or .bvh",
        )),
    }
}
