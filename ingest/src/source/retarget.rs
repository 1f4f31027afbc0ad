//! Retargeting named BVH rigs to SMPL-22: rig maps (built-in Bandai Namco, CMU and Mixamo,
//! or a TOML file), rig detection by joint names, and automatic unit and up-axis conversion.
//!
//! A TOML map names, for every SMPL-22 joint (names as in [`crate::skeleton::JOINT_NAMES`]),
//! the source joint that sits there, or a point between two source joints:
//!
//! ```toml
//! name = "my-rig"
//! [joints]
//! pelvis = "Hips"
//! spine2 = { between = ["Spine", "Chest"], t = 0.5 }   # t = 0 at Spine, 1 at Chest
//! # ... all 22 joints
//! ```
//!
//! End Sites can be named as `<joint>_End`. `t` defaults to 0.5.

use super::bvh::{parse_bytes, Bvh};
use super::{Labels, RawClip, Reject};
use crate::error::IngestError;
use crate::quat::{self, Quat, Vec3};
use crate::skeleton::{Pose, JOINT_NAMES, NUM_JOINTS};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;

/// Where one SMPL joint comes from in the source rig.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged, deny_unknown_fields)]
pub enum JointSource {
    /// A source joint by name.
    Joint(String),
    /// The point `a + t·(b − a)` between two source joints.
    Between {
        /// The two source joints `[a, b]`.
        between: [String; 2],
        /// Interpolation parameter (0 = a, 1 = b).
        #[serde(default = "half")]
        t: f64,
    },
}

fn half() -> f64 {
    0.5
}

impl JointSource {
    fn names(&self) -> Vec<&str> {
        match self {
            Self::Joint(n) => vec![n.as_str()],
            Self::Between { between, .. } => between.iter().map(String::as_str).collect(),
        }
    }

    fn describe(&self) -> String {
        match self {
            Self::Joint(n) => format!("'{n}'"),
            Self::Between { between, t } => {
                format!("between '{}' and '{}' (t = {t})", between[0], between[1])
            }
        }
    }
}

/// How a source rig maps onto the 22 SMPL joints.
#[derive(Debug, Clone, PartialEq)]
pub struct RigMap {
    /// Rig name, reported in the conversion string.
    pub name: String,
    /// Source of each SMPL joint, in SMPL-22 order.
    pub joints: Vec<JointSource>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MapFile {
    name: String,
    joints: BTreeMap<String, JointSource>,
}

fn j(name: &str) -> JointSource {
    JointSource::Joint(name.to_string())
}

fn between(a: &str, b: &str, t: f64) -> JointSource {
    JointSource::Between {
        between: [a.to_string(), b.to_string()],
        t,
    }
}

/// Build a map from SMPL-order sources for the trunk and a per-side function for limbs.
fn symmetric(
    name: &str,
    trunk: [JointSource; 6],
    side: impl Fn(&str) -> [JointSource; 8],
) -> RigMap {
    let [pelvis, spine1, spine2, spine3, neck, head] = trunk;
    let [l_hip, l_knee, l_ankle, l_foot, l_collar, l_shoulder, l_elbow, l_wrist] = side("L");
    let [r_hip, r_knee, r_ankle, r_foot, r_collar, r_shoulder, r_elbow, r_wrist] = side("R");
    RigMap {
        name: name.to_string(),
        joints: vec![
            pelvis, l_hip, r_hip, spine1, l_knee, r_knee, spine2, l_ankle, r_ankle, spine3, l_foot,
            r_foot, neck, l_collar, r_collar, head, l_shoulder, r_shoulder, l_elbow, r_elbow,
            l_wrist, r_wrist,
        ],
    }
}

impl RigMap {
    /// Bandai Namco Research Motion Dataset rig (`Hips`, `Spine`, `Chest`, `UpperLeg_L`, ...).
    ///
    /// Measured on `walk_normal_001` (frame 0, cm above Hips): Spine 15.7, Chest 24.7,
    /// Neck 41, Head 47.4. SMPL's spine1/spine2/spine3 sit at about 11/23/28 at that body
    /// size, so spine1 = Spine, spine2 = Chest and spine3 a quarter of the way from Chest
    /// to Neck; Shoulder_* are the collars (5 cm lateral of the spine).
    pub fn bandai() -> Self {
        symmetric(
            "bandai",
            [
                j("Hips"),
                j("Spine"),
                j("Chest"),
                between("Chest", "Neck", 0.25),
                j("Neck"),
                j("Head"),
            ],
            |s| {
                [
                    j(&format!("UpperLeg_{s}")),
                    j(&format!("LowerLeg_{s}")),
                    j(&format!("Foot_{s}")),
                    j(&format!("Toes_{s}")),
                    j(&format!("Shoulder_{s}")),
                    j(&format!("UpperArm_{s}")),
                    j(&format!("LowerArm_{s}")),
                    j(&format!("Hand_{s}")),
                ]
            },
        )
    }

    /// CMU motion capture database rig as converted to BVH (`LHipJoint`, `LowerBack`, `Neck1`, ...).
    ///
    /// CMU's `LeftShoulder` starts at the spine, so the collar is taken half way to `LeftArm`;
    /// `Neck` starts at `Spine1`, so SMPL's neck is `Neck1`.
    pub fn cmu() -> Self {
        symmetric(
            "cmu",
            [
                j("Hips"),
                j("Spine"),
                j("Spine1"),
                between("Spine1", "Neck1", 0.3),
                j("Neck1"),
                j("Head"),
            ],
            |s| {
                let side = if s == "L" { "Left" } else { "Right" };
                [
                    j(&format!("{side}UpLeg")),
                    j(&format!("{side}Leg")),
                    j(&format!("{side}Foot")),
                    j(&format!("{side}ToeBase")),
                    between(&format!("{side}Shoulder"), &format!("{side}Arm"), 0.5),
                    j(&format!("{side}Arm")),
                    j(&format!("{side}ForeArm")),
                    j(&format!("{side}Hand")),
                ]
            },
        )
    }

    /// The SMPL-22 rig of our own BVH export (`export bvh`, `generate`): joint names as in
    /// [`JOINT_NAMES`].
    pub fn smpl22() -> Self {
        RigMap {
            name: "smpl22".to_string(),
            joints: JOINT_NAMES.iter().map(|n| j(n)).collect(),
        }
    }

    /// Mixamo rig with joint names prefixed by `prefix` (`"mixamorig:"`, `""`, or another `name:`).
    pub fn mixamo(prefix: &str) -> Self {
        let p = |n: &str| j(&format!("{prefix}{n}"));
        let mut map = symmetric(
            "mixamo",
            [
                p("Hips"),
                p("Spine"),
                p("Spine1"),
                p("Spine2"),
                p("Neck"),
                p("Head"),
            ],
            |s| {
                let side = if s == "L" { "Left" } else { "Right" };
                [
                    p(&format!("{side}UpLeg")),
                    p(&format!("{side}Leg")),
                    p(&format!("{side}Foot")),
                    p(&format!("{side}ToeBase")),
                    p(&format!("{side}Shoulder")),
                    p(&format!("{side}Arm")),
                    p(&format!("{side}ForeArm")),
                    p(&format!("{side}Hand")),
                ]
            },
        );
        if !prefix.is_empty() {
            map.name = format!("mixamo ({prefix})");
        }
        map
    }

    /// Parse a TOML map (format in the module docs); the error names what is wrong.
    pub fn from_toml(text: &str) -> Result<Self, IngestError> {
        let file: MapFile = toml::from_str(text).map_err(|e| e.to_string())?;
        if let Some(unknown) = file
            .joints
            .keys()
            .find(|k| !JOINT_NAMES.contains(&k.as_str()))
        {
            return Err(format!(
                "unknown SMPL joint '{unknown}' (expected one of {})",
                JOINT_NAMES.join(", ")
            )
            .into());
        }
        let missing: Vec<&str> = JOINT_NAMES
            .iter()
            .copied()
            .filter(|n| !file.joints.contains_key(*n))
            .collect();
        if !missing.is_empty() {
            return Err(format!("missing SMPL joints: {}", missing.join(", ")).into());
        }
        if let Some((k, t)) = file.joints.iter().find_map(|(k, s)| match s {
            JointSource::Between { t, .. } if !t.is_finite() => Some((k, *t)),
            _ => None,
        }) {
            return Err(format!("joint '{k}': t must be finite, found {t}").into());
        }
        let mut joints = file.joints;
        Ok(Self {
            name: file.name,
            joints: JOINT_NAMES
                .iter()
                .filter_map(|n| joints.remove(*n))
                .collect(),
        })
    }

    /// Read a TOML map file; errors name the file.
    pub fn load(path: &Path) -> Result<Self, IngestError> {
        let text = std::fs::read_to_string(path).map_err(|e| IngestError::io(path, e))?;
        Self::from_toml(&text).map_err(IngestError::at(path))
    }

    /// SMPL joints whose source names are absent from `names`, with what was expected.
    fn missing(&self, names: &[&str]) -> Vec<String> {
        JOINT_NAMES
            .iter()
            .zip(&self.joints)
            .filter(|(_, src)| src.names().iter().any(|n| !names.contains(n)))
            .map(|(smpl, src)| format!("{smpl} (expects {})", src.describe()))
            .collect()
    }
}

/// Pick the built-in rig map whose joint names are all present, or reject naming the
/// SMPL joints the closest built-in map could not find.
pub fn detect(names: &[&str]) -> Result<RigMap, Reject> {
    let mut candidates = vec![RigMap::bandai(), RigMap::cmu()];
    let mut prefixes: Vec<&str> = names
        .iter()
        .filter_map(|n| n.strip_suffix("Hips"))
        .filter(|p| p.is_empty() || p.ends_with(':'))
        .collect();
    if prefixes.is_empty() {
        prefixes.push("mixamorig:");
    }
    candidates.extend(prefixes.into_iter().map(RigMap::mixamo));
    // Our own export rig last: on a tie, the error should name a common capture rig.
    candidates.push(RigMap::smpl22());
    let mut best: Option<(Vec<String>, &RigMap)> = None;
    for map in &candidates {
        let missing = map.missing(names);
        if missing.is_empty() {
            return Ok(map.clone());
        }
        if best.as_ref().is_none_or(|(m, _)| missing.len() < m.len()) {
            best = Some((missing, map));
        }
    }
    let (missing, map) = best.expect("there is always at least one candidate map");
    Err(Reject::new(
        "retarget",
        format!(
            "unknown rig: no built-in map fits (bandai, cmu, mixamo, smpl22); closest is {} with {} of 22 \
             SMPL joints missing: {}; use a TOML map (--map) for this rig",
            map.name,
            missing.len(),
            missing.join(", ")
        ),
    ))
}

/// Candidate file units: name and metres per unit.
const UNITS: [(&str, f64); 5] = [
    ("m", 1.0),
    ("cm", 0.01),
    ("mm", 0.001),
    ("inch", 0.0254),
    // CMU ASF/AMC length unit: 1/0.45 inch.
    ("CMU unit", 0.0254 / 0.45),
];

/// Sum of SMPL leg (hip–knee–ankle) and trunk (pelvis–…–head) bone lengths, in metres,
/// for the HumanML3D target skeleton; an adult's stature is about 1.15 times this.
const TARGET_LEG_TRUNK: f64 = 1.4806;
/// Stature of an adult whose leg + trunk sum is [`TARGET_LEG_TRUNK`].
const TARGET_STATURE: f64 = 1.70;
/// Bones summed for the size estimate: (parent, child) in SMPL-22 indices.
const SIZE_BONES: [(usize, usize); 7] = [(1, 4), (4, 7), (0, 3), (3, 6), (6, 9), (9, 12), (12, 15)];

/// Estimated stature from one SMPL-22 pose, in the pose's units: the leg and trunk bone
/// lengths summed and scaled by the adult ratio (pose-invariant; used to choose the unit).
pub fn estimate_stature(pose: &Pose) -> f64 {
    let sum: f64 = SIZE_BONES
        .iter()
        .map(|&(a, b)| quat::norm(quat::sub(pose[b], pose[a])))
        .sum();
    sum * TARGET_STATURE / TARGET_LEG_TRUNK
}

/// Choose the unit giving the most plausible adult stature; `None` when no unit gives
/// a stature between 0.8 and 2.6 m.
fn choose_unit(stature_units: f64) -> Option<(&'static str, f64)> {
    UNITS
        .iter()
        .copied()
        .min_by(|a, b| {
            let da = (stature_units * a.1 / TARGET_STATURE).ln().abs();
            let db = (stature_units * b.1 / TARGET_STATURE).ln().abs();
            da.total_cmp(&db)
        })
        .filter(|(_, f)| (0.8..=2.6).contains(&(stature_units * f)))
}

/// Rotation taking the detected up axis to +Y, and its description.
fn up_rotation(up: Vec3) -> (Quat, &'static str) {
    let (axis, _) = up.iter().enumerate().fold((0, 0.0f64), |best, (i, v)| {
        if v.abs() > best.1 {
            (i, v.abs())
        } else {
            best
        }
    });
    let positive = up[axis] >= 0.0;
    let h = std::f64::consts::FRAC_1_SQRT_2;
    match (axis, positive) {
        (1, true) => (quat::IDENTITY, "Y up"),
        // −90° about X: (x, y, z) → (x, z, −y).
        (2, true) => ([h, -h, 0.0, 0.0], "Z up → Y up"),
        (2, false) => ([h, h, 0.0, 0.0], "−Z up → Y up"),
        // +90° about Z: (x, y, z) → (−y, x, z).
        (0, true) => ([h, 0.0, 0.0, h], "X up → Y up"),
        (0, false) => ([h, 0.0, 0.0, -h], "−X up → Y up"),
        _ => ([0.0, 1.0, 0.0, 0.0], "−Y up → Y up"),
    }
}

/// Map a parsed BVH onto SMPL-22: returns poses (metres, Y up) and the conversion description.
pub fn retarget(bvh: &Bvh, map: &RigMap) -> Result<(Vec<Pose>, String), Reject> {
    let names = bvh.joint_names();
    let missing = map.missing(&names);
    if !missing.is_empty() {
        return Err(Reject::new(
            "retarget",
            format!(
                "rig map '{}' does not fit: missing source joints for {}",
                map.name,
                missing.join(", ")
            ),
        ));
    }
    // Resolved as (a, b, t): the point a + t·(b − a).
    let index = |n: &str| bvh.joint_index(n).unwrap_or(0);
    let sources: Vec<(usize, usize, f64)> = map
        .joints
        .iter()
        .map(|src| match src {
            JointSource::Joint(n) => (index(n), index(n), 0.0),
            JointSource::Between { between, t } => (index(&between[0]), index(&between[1]), *t),
        })
        .collect();
    let world = bvh.world_positions();
    let nj = bvh.joints.len();
    let mut poses: Vec<Pose> = world
        .chunks_exact(nj)
        .map(|frame| {
            let mut pose = [[0.0; 3]; NUM_JOINTS];
            for (p, &(a, b, t)) in pose.iter_mut().zip(&sources) {
                *p = quat::add(frame[a], quat::scale(quat::sub(frame[b], frame[a]), t));
            }
            pose
        })
        .collect();
    let Some(first) = poses.first() else {
        return Err(Reject::new("retarget", "no frames"));
    };
    let size = estimate_stature(first);
    let Some((unit, factor)) = choose_unit(size) else {
        return Err(Reject::new(
            "retarget",
            format!(
                "implausible body size: estimated stature {size:.4} file units fits none of \
                 m, cm, mm, inch, CMU units"
            ),
        ));
    };
    let (rotation, axes) = up_rotation(quat::sub(first[15], first[0]));
    for pose in poses.iter_mut() {
        for p in pose.iter_mut() {
            *p = quat::scale(quat::rot(rotation, *p), factor);
        }
    }
    let units = if factor == 1.0 {
        "m".to_string()
    } else {
        format!("{unit}→m")
    };
    Ok((
        poses,
        format!(
            "{} rig, {units} (stature ≈ {:.2} m), {axes}",
            map.name,
            size * factor
        ),
    ))
}

/// Read a BVH file and retarget it to SMPL-22.
///
/// `path` is the file to read and becomes `source_path`; `rel_path` (its path inside the
/// source folder) gives `clip_id` (the file stem). With `map` = `None` the rig is detected
/// from the joint names. Labels and captions are left empty.
pub fn read_clip(path: &Path, rel_path: &Path, map: Option<&RigMap>) -> Result<RawClip, Reject> {
    let bytes =
        std::fs::read(path).map_err(|e| Reject::new("read", format!("{}: {e}", path.display())))?;
    clip_from_bytes(&bytes, path, rel_path, map)
}

/// [`read_clip`] on the bytes of the file at `path`.
pub fn clip_from_bytes(
    bytes: &[u8],
    path: &Path,
    rel_path: &Path,
    map: Option<&RigMap>,
) -> Result<RawClip, Reject> {
    if let Err(e) = std::str::from_utf8(bytes) {
        return Err(Reject::new(
            "read",
            format!(
                "{}: not UTF-8 text (invalid byte at offset {})",
                path.display(),
                e.valid_up_to()
            ),
        ));
    }
    let bvh =
        parse_bytes(bytes).map_err(|e| Reject::new("parse", format!("{}: {e}", path.display())))?;
    let detected;
    let map = match map {
        Some(m) => m,
        None => {
            detected = detect(&bvh.joint_names())
                .map_err(|r| Reject::new(&r.stage, format!("{}: {}", path.display(), r.reason)))?;
            &detected
        }
    };
    let (poses, conversion) = retarget(&bvh, map)
        .map_err(|r| Reject::new(&r.stage, format!("{}: {}", path.display(), r.reason)))?;
    let clip_id = rel_path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    Ok(RawClip {
        clip_id,
        source: "bvh".to_string(),
        source_path: path.to_path_buf(),
        fps: bvh.fps(),
        poses,
        labels: Labels::default(),
        captions: Vec::new(),
        conversion,
        split: None,
        span: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn target_leg_trunk_sum_matches_skeleton() {
        use crate::skeleton::TARGET_OFFSETS;
        let sum: f64 = SIZE_BONES
            .iter()
            .map(|&(_, b)| quat::norm(TARGET_OFFSETS[b]))
            .sum();
        assert!((sum - TARGET_LEG_TRUNK).abs() < 1e-3, "{sum}");
    }

    #[test]
    fn units_are_chosen_by_plausible_stature() {
        assert_eq!(choose_unit(1.75).map(|u| u.0), Some("m"));
        assert_eq!(choose_unit(160.0).map(|u| u.0), Some("cm"));
        assert_eq!(choose_unit(1800.0).map(|u| u.0), Some("mm"));
        assert_eq!(choose_unit(68.0).map(|u| u.0), Some("inch"));
        assert_eq!(choose_unit(30.0).map(|u| u.0), Some("CMU unit"));
        assert_eq!(choose_unit(1e7), None);
        assert_eq!(choose_unit(0.0), None);
    }

    #[test]
    fn up_rotations_are_proper_and_map_up_to_y() {
        for up in [
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, -1.0, 0.0],
        ] {
            let (q, _) = up_rotation(up);
            let r = quat::rot(q, up);
            assert!((r[1] - 1.0).abs() < 1e-12, "{up:?} → {r:?}");
            let m = quat::to_matrix(q);
            let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
                - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
            assert!((det - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn toml_map_round_trips_and_reports_missing_joints() {
        let mut text = String::from("name = \"x\"\n[joints]\n");
        for n in JOINT_NAMES {
            if n == "spine2" {
                text.push_str("spine2 = { between = [\"Spine\", \"Chest\"], t = 0.25 }\n");
            } else {
                text.push_str(&format!("{n} = \"src_{n}\"\n"));
            }
        }
        let map = RigMap::from_toml(&text).unwrap();
        assert_eq!(map.name, "x");
        assert_eq!(map.joints[0], j("src_pelvis"));
        assert_eq!(map.joints[6], between("Spine", "Chest", 0.25));
        assert_eq!(map.joints[21], j("src_r_wrist"));
        let short = text.replace("l_knee = \"src_l_knee\"\n", "");
        let e = RigMap::from_toml(&short).unwrap_err().to_string();
        assert!(e.contains("missing SMPL joints: l_knee"), "{e}");
        let bad = text.replace("l_knee =", "left_knee =");
        assert!(RigMap::from_toml(&bad)
            .unwrap_err()
            .to_string()
            .contains("unknown SMPL joint 'left_knee'"));
    }

    #[test]
    fn detection_picks_the_rig_whose_names_are_present() {
        let map = RigMap::mixamo("mixamorig:");
        let names: Vec<String> = map
            .joints
            .iter()
            .flat_map(|s| s.names().into_iter().map(str::to_string))
            .collect();
        let refs: Vec<&str> = names.iter().map(String::as_str).collect();
        assert_eq!(detect(&refs).unwrap(), map);
        let plain: Vec<String> = names.iter().map(|n| n.replace("mixamorig:", "")).collect();
        let refs: Vec<&str> = plain.iter().map(String::as_str).collect();
        assert_eq!(detect(&refs).unwrap().name, "mixamo");
        let e = detect(&refs[1..]).unwrap_err();
        assert!(e.reason.contains("pelvis (expects 'Hips')"), "{}", e.reason);
        // Our own SMPL-22 export reads back.
        assert_eq!(detect(&JOINT_NAMES).unwrap(), RigMap::smpl22());
    }
}
