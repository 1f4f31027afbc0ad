//! Joint-position arrays: `.npy` files of shape T×J×3 (J ≥ 22, the first 22 in SMPL-22 order),
//! metres, Y up, f32 or f64 — e.g. HumanML3D `joints/` or any model's output.

use super::{clip_id_of, RawClip, Reject};
use crate::error::IngestError;
use crate::npy::{self, NpyArray};
use crate::skeleton::{Pose, NUM_JOINTS};
use std::path::Path;

/// Read one T×J×3 joints file recorded at `src_fps`; `rel_path` (inside the source folder) names the clip.
pub fn read_clip(path: &Path, rel_path: &Path, src_fps: f64) -> Result<RawClip, Reject> {
    let bytes =
        std::fs::read(path).map_err(|e| Reject::new("read", format!("{}: {e}", path.display())))?;
    let array =
        npy::parse(&bytes).map_err(|e| Reject::new("parse", format!("{}: {e}", path.display())))?;
    let poses = poses_of(&array)
        .map_err(|reason| Reject::new("parse", format!("{}: {reason}", path.display())))?;
    Ok(RawClip {
        clip_id: clip_id_of(rel_path),
        source: "joints".into(),
        source_path: path.to_path_buf(),
        fps: src_fps,
        poses,
        labels: Default::default(),
        captions: Vec::new(),
        conversion: "metres, Y up (as given)".into(),
        split: None,
        span: None,
    })
}

/// The first 22 joints of each frame of a T×J×3 array (J ≥ 22), or why the shape does not fit.
pub fn poses_of(array: &NpyArray) -> Result<Vec<Pose>, IngestError> {
    let &[frames, joints, 3] = array.shape.as_slice() else {
        return Err(format!("array shape {:?} is not T×J×3 joint positions", array.shape).into());
    };
    if joints < NUM_JOINTS {
        return Err(format!(
            "array shape {:?} has {joints} joints, at least {NUM_JOINTS} are needed",
            array.shape
        )
        .into());
    }
    if frames == 0 {
        return Err(format!("array shape {:?} has zero frames", array.shape).into());
    }
    let poses = array
        .data
        .chunks_exact(joints * 3)
        .map(|frame| {
            let mut pose = [[0.0; 3]; NUM_JOINTS];
            for (j, p) in pose.iter_mut().enumerate() {
                p.copy_from_slice(&frame[j * 3..j * 3 + 3]);
            }
            pose
        })
        .collect::<Vec<_>>();
    if let Some((t, j)) = poses.iter().enumerate().find_map(|(t, pose)| {
        pose.iter()
            .position(|p| p.iter().any(|v| !v.is_finite()))
            .map(|j| (t, j))
    }) {
        return Err(format!("frame {t}, joint {j}: non-finite coordinate").into());
    }
    Ok(poses)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_are_checked() {
        let arr = |shape: Vec<usize>| NpyArray {
            data: vec![0.5; shape.iter().product()],
            shape,
        };
        assert_eq!(poses_of(&arr(vec![4, 24, 3])).unwrap().len(), 4);
        assert!(poses_of(&arr(vec![4, 66]))
            .unwrap_err()
            .to_string()
            .contains("[4, 66]"));
        assert!(poses_of(&arr(vec![4, 21, 3]))
            .unwrap_err()
            .to_string()
            .contains("21 joints"));
        assert!(poses_of(&arr(vec![0, 22, 3]))
            .unwrap_err()
            .to_string()
            .contains("zero frames"));
        let mut nan = arr(vec![2, 22, 3]);
        nan.data[66 + 5 * 3 + 1] = f64::NAN;
        assert_eq!(
            poses_of(&nan).unwrap_err().to_string(),
            "frame 1, joint 5: non-finite coordinate"
        );
    }
}
