//! Per-input budgets and plausibility bounds. Every input is checked against the budgets
//! before the memory it would need is allocated, so one absurd header cannot sink a whole
//! ingest; values that are finite but physically impossible are rejected naming the clip
//! and frame instead of being ingested. docs/stages.md "Input budgets" states why each bound is
//! safe for real motion capture.

use crate::error::IngestError;
use crate::skeleton::{Pose, JOINT_NAMES, NUM_JOINTS, PARENTS};

/// Shortest frame time accepted, in seconds (10 kHz; optical systems top out near 2 kHz).
pub const MIN_FRAME_TIME: f64 = 1e-4;
/// Longest frame time accepted, in seconds (1 fps; capture runs at 24 fps or faster).
pub const MAX_FRAME_TIME: f64 = 1.0;
/// Longest clip accepted, in seconds.
pub const MAX_SECONDS: f64 = 3600.0;
/// Most frames a clip may have after resampling to the corpus rate.
pub const MAX_RESAMPLED_FRAMES: usize = 72_000;
/// Largest input file read, in bytes.
pub const MAX_FILE_BYTES: u64 = 256 << 20;
/// Most motion values (frames × channels) in one file.
pub const MAX_VALUES: usize = 1 << 24;
/// Most joint positions (frames × joints) forward kinematics may produce for one file.
pub const MAX_JOINT_FRAMES: usize = 1 << 22;
/// Most channels per frame.
pub const MAX_CHANNELS: usize = 1024;
/// Deepest nesting of joints in a hierarchy.
pub const MAX_DEPTH: usize = 64;
/// Largest joint coordinate accepted, in metres.
pub const MAX_POSITION: f64 = 10_000.0;
/// Largest rotation value accepted in a rotation channel, in degrees (2,778 turns).
pub const MAX_ROTATION_DEGREES: f64 = 1e6;
/// Relative change of a bone's length (against its median over the clip) that rejects it.
pub const BONE_TOLERANCE: f64 = 0.25;
/// Changes of a bone's length below this many metres never reject (short bones, jitter).
pub const BONE_SLACK: f64 = 0.05;

/// A duration in seconds as a person reads it ("216 days", "3.1 h", "12 s").
pub fn human_duration(seconds: f64) -> String {
    match seconds {
        s if s >= 2.0 * 86_400.0 => format!("{:.0} days", s / 86_400.0),
        s if s >= 2.0 * 3600.0 => format!("{:.1} h", s / 3600.0),
        s if s >= 120.0 => format!("{:.1} min", s / 60.0),
        s => format!("{s:.3} s"),
    }
}

/// Check a source frame time (seconds per frame) and the duration of `frames` frames at it.
pub fn check_timing(frames: usize, frame_time: f64) -> Result<(), IngestError> {
    let seconds = frames.saturating_sub(1) as f64 * frame_time;
    if !(MIN_FRAME_TIME..=MAX_FRAME_TIME).contains(&frame_time) {
        return Err(format!(
            "frame time {frame_time} s is outside {MIN_FRAME_TIME}..{MAX_FRAME_TIME} s \
             (1 to 10,000 fps): {frames} frames would last {}",
            human_duration(seconds)
        )
        .into());
    }
    if seconds > MAX_SECONDS {
        return Err(format!(
            "{frames} frames at {frame_time} s last {}, over the {MAX_SECONDS} s budget",
            human_duration(seconds)
        )
        .into());
    }
    Ok(())
}

/// Check that `frames` source frames at `src_fps` resample to at most
/// [`MAX_RESAMPLED_FRAMES`] frames at `dst_fps` (before resampling allocates them).
pub fn check_resampled(frames: usize, src_fps: f64, dst_fps: f64) -> Result<(), IngestError> {
    if !(src_fps.is_finite() && src_fps > 0.0) {
        return Err(format!("source frame rate {src_fps} is not a positive number").into());
    }
    check_timing(frames, 1.0 / src_fps)?;
    let rows = frames.saturating_sub(1) as f64 * dst_fps / src_fps;
    if rows > MAX_RESAMPLED_FRAMES as f64 {
        return Err(format!(
            "{frames} frames at {src_fps:.3} fps resample to {rows:.0} frames at {dst_fps} fps, \
             over the {MAX_RESAMPLED_FRAMES}-frame budget"
        )
        .into());
    }
    Ok(())
}

/// Reject poses with a coordinate beyond [`MAX_POSITION`] or a bone whose length changes
/// along the clip: the message names the frame, the joint or bone, and the values.
pub fn check_plausible(poses: &[Pose]) -> Result<(), IngestError> {
    for (t, pose) in poses.iter().enumerate() {
        if let Some((j, p)) = pose
            .iter()
            .enumerate()
            .find(|(_, p)| p.iter().any(|v| v.abs() > MAX_POSITION))
        {
            return Err(format!(
                "implausible position at frame {t}: {} at ({:.4e}, {:.4e}, {:.4e}) m, beyond \
                 ±{MAX_POSITION} m",
                JOINT_NAMES[j], p[0], p[1], p[2]
            )
            .into());
        }
    }
    if poses.is_empty() {
        return Ok(());
    }
    for j in 1..NUM_JOINTS {
        let parent = PARENTS[j];
        let lengths: Vec<f64> = poses
            .iter()
            .map(|p| crate::quat::norm(crate::quat::sub(p[j], p[parent])))
            .collect();
        let mut sorted = lengths.clone();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        let allowed = (BONE_TOLERANCE * median).max(BONE_SLACK);
        if let Some(t) = lengths.iter().position(|l| (l - median).abs() > allowed) {
            return Err(format!(
                "bone {}–{} changes length: {:.4} m at frame {t}, {median:.4} m over most of \
                 the clip (allowed ±{allowed:.3} m)",
                JOINT_NAMES[parent], JOINT_NAMES[j], lengths[t]
            )
            .into());
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::TARGET_OFFSETS;

    fn rest_pose() -> Pose {
        let mut pose = [[0.0; 3]; NUM_JOINTS];
        for j in 1..NUM_JOINTS {
            pose[j] = crate::quat::add(pose[PARENTS[j]], TARGET_OFFSETS[j]);
        }
        pose
    }

    #[test]
    fn absurd_frame_times_name_the_duration() {
        let e = check_timing(187, 100_000.0).unwrap_err().to_string();
        assert!(
            e.contains("frame time 100000 s") && e.contains("215 days"),
            "{e}"
        );
        let e = check_timing(2_000_000, 0.01).unwrap_err().to_string();
        assert!(e.contains("5.6 h") && e.contains("budget"), "{e}");
        assert!(check_timing(187, 1.0 / 30.0).is_ok());
        let e = check_resampled(187, 1.0 / 1000.0, 20.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("frame time 1000 s"), "{e}");
        assert!(check_resampled(187, 30.0, 20.0).is_ok());
        assert!(check_resampled(187, f64::NAN, 20.0).is_err());
    }

    #[test]
    fn far_positions_and_stretching_bones_are_named() {
        let clip: Vec<Pose> = (0..10).map(|_| rest_pose()).collect();
        assert!(check_plausible(&clip).is_ok());
        let mut far = clip.clone();
        far[3][0][1] = 4e23;
        let e = check_plausible(&far).unwrap_err().to_string();
        assert!(e.contains("frame 3") && e.contains("pelvis"), "{e}");
        let mut stretched = clip.clone();
        stretched[7][20][1] -= 0.3;
        let e = check_plausible(&stretched).unwrap_err().to_string();
        assert!(
            e.contains("l_elbow–l_wrist") && e.contains("frame 7"),
            "{e}"
        );
        // Jitter of a few millimetres is real capture noise, not damage.
        let mut jitter = clip;
        jitter[5][20][1] -= 0.004;
        assert!(check_plausible(&jitter).is_ok());
    }
}
