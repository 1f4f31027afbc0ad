//! The SMPL-22 skeleton used by HumanML3D: joint order, kinematic chains, raw offset
//! directions and the target bone lengths every clip is retargeted to.

/// Number of body joints in the HumanML3D (t2m) skeleton.
pub const NUM_JOINTS: usize = 22;

/// One frame of joint positions (metres, Y up), in SMPL-22 order.
pub type Pose = [[f64; 3]; NUM_JOINTS];

/// Joint names in SMPL-22 order.
pub const JOINT_NAMES: [&str; NUM_JOINTS] = [
    "pelvis",
    "l_hip",
    "r_hip",
    "spine1",
    "l_knee",
    "r_knee",
    "spine2",
    "l_ankle",
    "r_ankle",
    "spine3",
    "l_foot",
    "r_foot",
    "neck",
    "l_collar",
    "r_collar",
    "head",
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
];

/// Kinematic chains; within a chain each joint's parent is the previous entry.
pub const CHAINS: [&[usize]; 5] = [
    &[0, 2, 5, 8, 11],
    &[0, 1, 4, 7, 10],
    &[0, 3, 6, 9, 12, 15],
    &[9, 14, 17, 19, 21],
    &[9, 13, 16, 18, 20],
];

/// Parent of each joint (the root's parent is itself), derived from [`CHAINS`].
pub const PARENTS: [usize; NUM_JOINTS] = [
    0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19,
];

/// Unit rest-pose directions of each bone (joint minus parent), as in HumanML3D's `t2m_raw_offsets`.
pub const RAW_OFFSETS: [[f64; 3]; NUM_JOINTS] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 0.0, 1.0],
    [0.0, 1.0, 0.0],
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
];

/// Target skeleton offsets (metres): raw direction × HumanML3D bone length (fixtures README table).
pub const TARGET_OFFSETS: [[f64; 3]; NUM_JOINTS] = [
    [0.0, 0.0, 0.0],
    [0.103073947, 0.0, 0.0],
    [-0.109883353, 0.0, 0.0],
    [0.0, 0.131568253, 0.0],
    [0.0, -0.393623143, 0.0],
    [0.0, -0.390188128, 0.0],
    [0.0, 0.143190265, 0.0],
    [0.0, -0.432432979, 0.0],
    [0.0, -0.425643325, 0.0],
    [0.0, 0.057364706, 0.0],
    [0.0, 0.0, 0.143381745],
    [0.0, 0.0, 0.149418667],
    [0.0, 0.219359994, 0.0],
    [0.13748683, 0.0, 0.0],
    [-0.143382832, 0.0, 0.0],
    [0.0, 0.0, 0.103039272],
    [0.0, -0.131613985, 0.0],
    [0.0, -0.122984305, 0.0],
    [0.0, -0.256839842, 0.0],
    [0.0, -0.263091862, 0.0],
    [0.0, -0.266011864, 0.0],
    [0.0, -0.269876301, 0.0],
];

/// Face joints (r_hip, l_hip, r_shoulder, l_shoulder) used to find the facing direction.
pub const FACE_JOINTS: [usize; 4] = [2, 1, 17, 16];

/// Foot joints: left (ankle, foot) then right (ankle, foot).
pub const FEET_LEFT: [usize; 2] = [7, 10];
/// Right foot joints (ankle, foot).
pub const FEET_RIGHT: [usize; 2] = [8, 11];

/// Left/right joint pairs swapped when a clip is mirrored (HumanML3D `swap_left_right`).
pub const MIRROR_PAIRS: [(usize, usize); 8] = [
    (1, 2),
    (4, 5),
    (7, 8),
    (10, 11),
    (13, 14),
    (16, 17),
    (18, 19),
    (20, 21),
];

/// Mirror a pose left↔right: negate X, then swap left and right joints (HumanML3D's convention).
pub fn mirror_pose(pose: &Pose) -> Pose {
    let mut out = *pose;
    for p in out.iter_mut() {
        p[0] = -p[0];
    }
    for &(l, r) in &MIRROR_PAIRS {
        out.swap(l, r);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parents_follow_the_chains() {
        for chain in CHAINS {
            for w in chain.windows(2) {
                assert_eq!(PARENTS[w[1]], w[0], "joint {}", w[1]);
            }
        }
    }

    #[test]
    fn target_offsets_point_along_raw_directions() {
        for j in 1..NUM_JOINTS {
            let len: f64 = TARGET_OFFSETS[j].iter().map(|v| v * v).sum::<f64>().sqrt();
            for k in 0..3 {
                assert!((TARGET_OFFSETS[j][k] - RAW_OFFSETS[j][k] * len).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn mirroring_twice_is_identity() {
        let mut pose = [[0.0; 3]; NUM_JOINTS];
        for (j, p) in pose.iter_mut().enumerate() {
            *p = [j as f64, 2.0 * j as f64, -(j as f64)];
        }
        let once = mirror_pose(&pose);
        assert_eq!(once[1], [-2.0, 4.0, -2.0]);
        assert_eq!(mirror_pose(&once), pose);
    }
}
