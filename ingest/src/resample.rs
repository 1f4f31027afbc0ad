//! Resampling joint sequences by time (linear interpolation), so any source frame rate
//! becomes the corpus rate without the drift of an integer frame stride.

use crate::skeleton::Pose;

/// Resample `poses` recorded at `src_fps` to `dst_fps`.
///
/// Output frame k sits at time k / dst_fps and is interpolated linearly between the two
/// source frames around it; frames run while that time is within the source clip, so a
/// clip of duration (T−1)/src_fps keeps its duration up to one target frame.
pub fn resample(poses: &[Pose], src_fps: f64, dst_fps: f64) -> Vec<Pose> {
    if poses.is_empty() || (src_fps - dst_fps).abs() < 1e-9 {
        return poses.to_vec();
    }
    let last = (poses.len() - 1) as f64;
    let ratio = src_fps / dst_fps;
    // Tolerance so a time that lands on the last frame up to rounding is kept.
    let count = (last / ratio + 1e-9).floor() as usize + 1;
    (0..count)
        .map(|k| {
            let pos = k as f64 * ratio;
            let i = (pos.floor() as usize).min(poses.len() - 1);
            let frac = pos - i as f64;
            if frac < 1e-12 || i + 1 >= poses.len() {
                return poses[i];
            }
            let (a, b) = (&poses[i], &poses[i + 1]);
            let mut out = *a;
            for (o, (pa, pb)) in out.iter_mut().zip(a.iter().zip(b)) {
                for c in 0..3 {
                    o[c] = pa[c] + (pb[c] - pa[c]) * frac;
                }
            }
            out
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::NUM_JOINTS;

    fn ramp(n: usize, fps: f64) -> Vec<Pose> {
        (0..n)
            .map(|t| [[t as f64 / fps, 1.0, -2.0 * t as f64 / fps]; NUM_JOINTS])
            .collect()
    }

    #[test]
    fn thirty_to_twenty_keeps_time() {
        // 31 frames at 30 fps = 1 s → 21 frames at 20 fps, each at k/20 s.
        let out = resample(&ramp(31, 30.0), 30.0, 20.0);
        assert_eq!(out.len(), 21);
        for (k, pose) in out.iter().enumerate() {
            let t = k as f64 / 20.0;
            assert!((pose[5][0] - t).abs() < 1e-12);
            assert!((pose[5][2] + 2.0 * t).abs() < 1e-12);
        }
    }

    #[test]
    fn upsampling_and_identity() {
        let src = ramp(11, 10.0);
        assert_eq!(resample(&src, 20.0, 20.0), src);
        let up = resample(&src, 10.0, 20.0);
        assert_eq!(up.len(), 21);
        assert!((up[1][0][0] - 0.05).abs() < 1e-12);
        assert!(resample(&[], 30.0, 20.0).is_empty());
    }
}
