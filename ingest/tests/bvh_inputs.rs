//! BVH parsing, forward kinematics and retargeting on hand-written, generated and real
//! (Bandai Namco) inputs, and the rejection reasons for bad inputs.

mod common;

use common::data_dir;
use ingest::bvh_fuzzing::{write_bvh, Layout, SeedJoint};
use ingest::quat;
use ingest::skeleton::{Pose, PARENTS};
use ingest::source::bvh::{self, Bvh, Channel};
use ingest::source::retarget::{self, estimate_stature, RigMap};
use std::path::{Path, PathBuf};

fn close(a: [f64; 3], b: [f64; 3], tol: f64) {
    for k in 0..3 {
        assert!((a[k] - b[k]).abs() < tol, "{a:?} vs {b:?}");
    }
}

fn parse_err(text: &str) -> String {
    match bvh::parse(text) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e.to_string(),
    }
}

const TWO_JOINTS: &str = "HIERARCHY
ROOT A
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT B
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.05
1 2 3 90 0 0 0 90 0
1 2 3 0 90 90 0 0 0
";

#[test]
fn hand_computed_forward_kinematics() {
    let b = bvh::parse(TWO_JOINTS).unwrap();
    assert_eq!(b.num_frames(), 2);
    assert_eq!(b.joint_names(), ["A", "B", "B_End"]);
    assert!((b.fps() - 20.0).abs() < 1e-12);
    let w = b.world_positions();
    // Frame 1: root Rz(90°) takes B's offset (0,10,0) to (−10,0,0); B's Rx(90°) takes the
    // End Site offset (0,5,0) to (0,0,5), which Rz(90°) leaves alone.
    close(w[0], [1.0, 2.0, 3.0], 1e-12);
    close(w[1], [-9.0, 2.0, 3.0], 1e-12);
    close(w[2], [-9.0, 2.0, 8.0], 1e-12);
    // Frame 2: channels Z, Y, X compose as Rz·Ry·Rx: Rx(90°)(0,10,0) = (0,0,10), then
    // Ry(90°) gives (10,0,0). The other order (Rx·Ry) would give (0,0,10). B does not
    // rotate, so the End Site offset (0,5,0) turns the same way, to (5,0,0).
    close(w[4], [11.0, 2.0, 3.0], 1e-12);
    close(w[5], [16.0, 2.0, 3.0], 1e-12);
}

#[test]
fn channel_orders_layouts_and_number_formats_agree() {
    // The same motion with the root's channels in two orders, 3-channel and 1-channel joints.
    let orders: [Vec<Channel>; 2] = [
        vec![
            Channel::Xposition,
            Channel::Yposition,
            Channel::Zposition,
            Channel::Zrotation,
            Channel::Xrotation,
            Channel::Yrotation,
        ],
        vec![
            Channel::Zrotation,
            Channel::Zposition,
            Channel::Xrotation,
            Channel::Yposition,
            Channel::Yrotation,
            Channel::Xposition,
        ],
    ];
    let root_vals = [0.5, 1.5, -2.0, 30.0, -45.0, 60.0]; // X Y Z pos, Z X Y rot
    let perm = [[0, 1, 2, 3, 4, 5], [3, 2, 4, 1, 5, 0]];
    let mut results = Vec::new();
    for (order, perm) in orders.iter().zip(perm) {
        let joints = vec![
            SeedJoint {
                name: "root".into(),
                parent: None,
                offset: [0.0; 3],
                channels: order.clone(),
            },
            SeedJoint {
                name: "mid".into(),
                parent: Some(0),
                offset: [0.0, 3.0, 1.0],
                channels: vec![Channel::Yrotation, Channel::Xrotation, Channel::Zrotation],
            },
            SeedJoint {
                name: "tip".into(),
                parent: Some(1),
                offset: [2.0, 0.0, 0.0],
                channels: vec![Channel::Zrotation],
            },
        ];
        let mut motion: Vec<f64> = perm.iter().map(|&i| root_vals[i]).collect();
        motion.extend([10.0, 1.87007e-05, -25.0, 33.0]);
        for layout in [
            Layout::default(),
            Layout {
                crlf: true,
                tabs: true,
                wrap: Some(4),
            },
            Layout {
                crlf: false,
                tabs: true,
                wrap: Some(1),
            },
        ] {
            let text = write_bvh(&joints, 1.0 / 30.0, &motion, layout);
            results.push(bvh::parse(&text).unwrap().world_positions());
        }
    }
    for r in &results[1..] {
        for (a, b) in r.iter().zip(&results[0]) {
            close(*a, *b, 1e-12);
        }
    }
}

#[test]
fn messy_whitespace_exponents_and_wrapped_values() {
    let text = "HIERARCHY\r\n\r\nROOT\tHips\r\n{\r\n\t OFFSET   0.0\t1E+1  -0.0\r\n\tCHANNELS 3 Xrotation Yrotation Zrotation\r\n\tEnd Site\r\n\t{\r\n\t\tOFFSET 0 1.5e0 0\r\n\t}\r\n}\r\n\r\nMOTION\r\nFrames:\t3\r\nFrame Time: 3.33333e-02\r\n0 0\r\n0\r\n  90 0 0  \r\n\r\n0 -9e1 0\r\n";
    let b = bvh::parse(&format!("\u{feff}{text}")).unwrap();
    assert_eq!(b.num_frames(), 3);
    assert_eq!(b.joints[0].offset, [0.0, 10.0, 0.0]);
    let w = b.world_positions();
    close(w[1], [0.0, 11.5, 0.0], 1e-12);
    // Rx(90°) takes (0,1.5,0) to (0,0,1.5).
    close(w[3], [0.0, 10.0, 1.5], 1e-12);
    // Ry(−90°) leaves a Y offset alone.
    close(w[5], [0.0, 11.5, 0.0], 1e-12);
}

fn with_motion(motion: &str) -> String {
    TWO_JOINTS.replace(
        "Frames: 2\nFrame Time: 0.05\n1 2 3 90 0 0 0 90 0\n1 2 3 0 90 90 0 0 0\n",
        motion,
    )
}

#[test]
fn bad_inputs_are_rejected_with_reasons() {
    let e = parse_err(&with_motion(
        "Frames: 2\nFrame Time: 0.05\n1 2 3 90 0 0 0 90 0\n1 2 3\n",
    ));
    assert!(
        e.contains("truncated: expected 18 values (2 frames × 9 channels), found 12; frame 2 of 2"),
        "{e}"
    );
    let e = parse_err(&with_motion(
        "Frames: 2\nFrame Time: 0.05\n1 2 3 90 0 0 0 90 0\n1 2 abc 0 90 90 0 0 0\n",
    ));
    assert!(
        e.starts_with("line 20: text in a numeric field 'abc' at frame 2 channel 3 (A Zposition)"),
        "{e}"
    );
    let e = parse_err(&with_motion(
        "Frames: 1\nFrame Time: 0.05\n1 2 3 nan 0 0 0 90 0\n",
    ));
    assert!(
        e.starts_with("line 19: non-finite value 'nan' at frame 1 channel 4 (A Zrotation)"),
        "{e}"
    );
    let e = parse_err(&with_motion(
        "Frames: 1\nFrame Time: 0.05\n1 2 3 1e999 0 0 0 90 0\n",
    ));
    assert!(e.contains("non-finite value '1e999'"), "{e}");
    let e = parse_err(&with_motion("Frames: 0\nFrame Time: 0.05\n"));
    assert_eq!(e, "line 17: zero frames: the file has no motion");
    let e = parse_err(&with_motion("Frames: -5\nFrame Time: 0.05\n"));
    assert!(
        e.contains("Frames must be a non-negative integer, found '-5'"),
        "{e}"
    );
    let e = parse_err(&with_motion(
        "Frames: 2\nFrame Time: 0.05\n1 2 3 90 0 0 0 90 0\n1 2 3 0 90 90 0 0 0 7\n",
    ));
    assert!(e.starts_with("line 20: extra data '7'"), "{e}");
    // Absurd Frames: rejected by the size budget before anything is allocated for them.
    let e = parse_err(&with_motion("Frames: 2000000\nFrame Time: 0.0001\n1 2 3\n"));
    assert!(
        e.starts_with("line 17: Frames: 2000000 × 9 channels")
            && e.contains("over the 16777216-value budget"),
        "{e}"
    );
    let e = parse_err(&with_motion(
        "Frames: 4000000000000000000\nFrame Time: 0.05\n1\n",
    ));
    assert!(e.contains("years") || e.contains("days"), "{e}");
    // Truncated motion names what is missing.
    let e = parse_err(&with_motion("Frames: 3\nFrame Time: 0.05\n1 2 3\n"));
    assert!(
        e.contains("expected 27 values") && e.contains("found 3"),
        "{e}"
    );
    let e = parse_err(&TWO_JOINTS.replace(
        "CHANNELS 3 Zrotation Xrotation Yrotation",
        "CHANNELS 3 Zrotation Xrotation",
    ));
    assert!(
        e.starts_with(
            "line 10: wrong channel count or unknown channel name: CHANNELS 3 for 'B' has 'End'"
        ),
        "{e}"
    );
    let e = parse_err(&TWO_JOINTS.replace("CHANNELS 3 Zrotation", "CHANNELS 2 Zrotation"));
    assert!(
        e.starts_with("line 9: wrong channel count: channel name 'Yrotation'"),
        "{e}"
    );
    let e = parse_err(&TWO_JOINTS.replace("CHANNELS 3 Zrotation", "CHANNELS 9 Zrotation"));
    assert!(
        e.starts_with("line 9: wrong channel count '9' for 'B'"),
        "{e}"
    );
    let e = parse_err(&TWO_JOINTS.replace("Xrotation Yrotation\n", "Xrotation Wrotation\n"));
    assert!(
        e.contains("unknown channel name") && e.contains("'Wrotation'"),
        "{e}"
    );
    let e = parse_err(&TWO_JOINTS.replacen("  }\n}\n", "  }\n", 1));
    assert!(
        e.contains("unbalanced braces: MOTION while 'A' opened on line 3 is still open"),
        "{e}"
    );
    let e = parse_err(&TWO_JOINTS.replace("}\nMOTION", "}\n}\nMOTION"));
    assert!(
        e.contains("line 16: unbalanced braces: '}' without a matching '{'"),
        "{e}"
    );
    let e = parse_err(&TWO_JOINTS[..TWO_JOINTS.find("MOTION").unwrap()]);
    assert_eq!(e, "line 16: missing MOTION section");
    let e = parse_err(&TWO_JOINTS.replace("JOINT B", "JOINT A"));
    assert_eq!(e, "line 6: duplicate joint name 'A'");
    let e = parse_err("");
    assert_eq!(e, "line 1: unexpected end of file, expected 'HIERARCHY'");
}

/// A T-pose skeleton: (name, parent, position in metres, Y up, facing +Z, left at +X).
type Rig = Vec<(String, Option<usize>, [f64; 3])>;

fn humanoid(names: [&str; 22], spine_extra: Option<&str>, prefix: &str) -> Rig {
    // names: Hips, Spine, Spine1, Spine2, Neck, Head, then per side (L then R):
    // UpLeg, Leg, Foot, ToeBase, Shoulder, Arm, ForeArm, Hand.
    let p = |n: &str| format!("{prefix}{n}");
    let mut rig: Rig = vec![(p(names[0]), None, [0.0, 1.0, 0.0])];
    let mut last = 0;
    if let Some(lb) = spine_extra {
        rig.push((p(lb), Some(0), [0.0, 1.0, 0.0]));
        last = 1;
    }
    for (k, y) in [(1, 1.1), (2, 1.25), (3, 1.35), (4, 1.5), (5, 1.62)] {
        rig.push((p(names[k]), Some(last), [0.0, y, 0.0]));
        last = rig.len() - 1;
    }
    let chest = rig.len() - 3;
    for (side, sx) in [(6, 1.0), (14, -1.0)] {
        let leg: [(f64, f64, f64); 4] = [
            (0.1, 0.95, 0.0),
            (0.1, 0.52, 0.0),
            (0.1, 0.1, 0.0),
            (0.1, 0.02, 0.12),
        ];
        let mut parent = 0;
        for (k, (x, y, z)) in leg.into_iter().enumerate() {
            rig.push((p(names[side + k]), Some(parent), [sx * x, y, z]));
            parent = rig.len() - 1;
        }
        let arm = [0.05, 0.18, 0.45, 0.7];
        let mut parent = chest;
        for (k, x) in arm.into_iter().enumerate() {
            rig.push((p(names[side + 4 + k]), Some(parent), [sx * x, 1.45, 0.0]));
            parent = rig.len() - 1;
        }
    }
    rig
}

/// BVH text of `rig` scaled to `unit` metres per file unit, optionally Z up, 3 still frames.
fn rig_bvh(rig: &Rig, unit: f64, z_up: bool) -> String {
    let conv = |p: [f64; 3]| {
        let p = quat::scale(p, 1.0 / unit);
        if z_up {
            [p[0], -p[2], p[1]]
        } else {
            p
        }
    };
    let rot = vec![Channel::Zrotation, Channel::Xrotation, Channel::Yrotation];
    let joints: Vec<SeedJoint> = rig
        .iter()
        .map(|(name, parent, pos)| SeedJoint {
            name: name.clone(),
            parent: *parent,
            offset: conv(parent.map_or(*pos, |q| quat::sub(*pos, rig[q].2))),
            channels: if parent.is_none() {
                [
                    vec![Channel::Xposition, Channel::Yposition, Channel::Zposition],
                    rot.clone(),
                ]
                .concat()
            } else {
                rot.clone()
            },
        })
        .collect();
    let mut frame = conv(rig[0].2).to_vec();
    frame.resize(3 + 3 * rig.len(), 0.0);
    write_bvh(&joints, 1.0 / 60.0, &frame.repeat(3), Layout::default())
}

/// Retarget through `read_clip` from a temp file, checking poses against the T-pose.
fn retarget_tpose(rig: &Rig, unit: f64, z_up: bool, map: Option<&RigMap>) -> (Vec<Pose>, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tpose.bvh");
    std::fs::write(&path, rig_bvh(rig, unit, z_up)).unwrap();
    let clip = retarget::read_clip(&path, Path::new("sub/tpose.bvh"), map).unwrap();
    assert_eq!(clip.clip_id, "tpose");
    assert_eq!(clip.source, "bvh");
    assert!((clip.fps - 60.0).abs() < 1e-9);
    assert_eq!(clip.poses.len(), 3);
    (clip.poses, clip.conversion)
}

fn check_tpose(pose: &Pose, map: &RigMap, rig: &Rig) {
    use ingest::source::retarget::JointSource;
    let at = |n: &str| rig.iter().find(|r| r.0 == n).unwrap().2;
    for (p, src) in pose.iter().zip(&map.joints) {
        let want = match src {
            JointSource::Joint(n) => at(n),
            JointSource::Between { between, t } => {
                let (a, b) = (at(&between[0]), at(&between[1]));
                quat::add(a, quat::scale(quat::sub(b, a), *t))
            }
        };
        close(*p, want, 1e-9);
    }
    // The person's left (SMPL l_hip, l_shoulder) is at +X when facing +Z.
    assert!(pose[1][0] > 0.0 && pose[16][0] > 0.0 && pose[2][0] < 0.0);
}

const MIXAMO: [&str; 22] = [
    "Hips",
    "Spine",
    "Spine1",
    "Spine2",
    "Neck",
    "Head",
    "LeftUpLeg",
    "LeftLeg",
    "LeftFoot",
    "LeftToeBase",
    "LeftShoulder",
    "LeftArm",
    "LeftForeArm",
    "LeftHand",
    "RightUpLeg",
    "RightLeg",
    "RightFoot",
    "RightToeBase",
    "RightShoulder",
    "RightArm",
    "RightForeArm",
    "RightHand",
];

#[test]
fn mixamo_in_centimetres_and_metres() {
    let rig = humanoid(MIXAMO, None, "mixamorig:");
    let (poses, conv) = retarget_tpose(&rig, 0.01, false, None);
    assert!(conv.starts_with("mixamo (mixamorig:) rig, cm→m"), "{conv}");
    assert!(conv.ends_with("Y up"), "{conv}");
    check_tpose(&poses[2], &RigMap::mixamo("mixamorig:"), &rig);

    let rig = humanoid(MIXAMO, None, "");
    let (poses, conv) = retarget_tpose(&rig, 1.0, false, None);
    assert!(conv.starts_with("mixamo rig, m ("), "{conv}");
    check_tpose(&poses[0], &RigMap::mixamo(""), &rig);
    let stature = estimate_stature(&poses[0]);
    assert!((1.5..1.9).contains(&stature), "{stature}");
}

#[test]
fn cmu_z_up_in_inches() {
    let names = MIXAMO.map(|n| match n {
        "Spine" => "Spine",
        "Spine1" => "Spine1",
        "Spine2" => "Neck",
        "Neck" => "Neck1",
        other => other,
    });
    // CMU has LowerBack between Hips and Spine and an extra LHipJoint/RHipJoint.
    let mut rig = humanoid(names, Some("LowerBack"), "");
    for (side, x) in [("Left", 0.05), ("Right", -0.05)] {
        rig.push((format!("{}HipJoint", &side[..1]), Some(0), [x, 0.98, 0.0]));
    }
    let (poses, conv) = retarget_tpose(&rig, 0.0254, true, None);
    assert!(conv.starts_with("cmu rig, inch→m"), "{conv}");
    assert!(conv.ends_with("Z up → Y up"), "{conv}");
    check_tpose(&poses[1], &RigMap::cmu(), &rig);
}

#[test]
fn toml_map_for_another_rig_and_unknown_rigs() {
    let rig: Rig = humanoid(MIXAMO, None, "")
        .into_iter()
        .map(|(n, p, x)| (format!("bone_{n}"), p, x))
        .collect();
    let mut toml = String::from("name = \"custom\"\n[joints]\n");
    for (smpl, src) in ingest::skeleton::JOINT_NAMES
        .iter()
        .zip(&RigMap::mixamo("bone_").joints)
    {
        if let ingest::source::retarget::JointSource::Joint(n) = src {
            toml.push_str(&format!("{smpl} = \"{n}\"\n"));
        }
    }
    let toml = toml.replace(
        "spine2 = \"bone_Spine1\"",
        "spine2 = { between = [\"bone_Spine\", \"bone_Spine2\"] }",
    );
    let dir = tempfile::tempdir().unwrap();
    let map_path = dir.path().join("custom.toml");
    std::fs::write(&map_path, &toml).unwrap();
    let map = RigMap::load(&map_path).unwrap();
    let (poses, conv) = retarget_tpose(&rig, 0.001, false, Some(&map));
    assert!(conv.starts_with("custom rig, mm→m"), "{conv}");
    check_tpose(&poses[0], &map, &rig);

    // The same rig without a map: no built-in fits; the reason lists what was expected.
    let path = dir.path().join("custom.bvh");
    std::fs::write(&path, rig_bvh(&rig, 1.0, false)).unwrap();
    let e = retarget::read_clip(&path, Path::new("custom.bvh"), None).unwrap_err();
    assert_eq!(e.stage, "retarget");
    assert!(
        e.reason.contains("unknown rig: no built-in map fits"),
        "{}",
        e.reason
    );
    assert!(
        e.reason.contains("pelvis (expects 'Hips')")
            || e.reason.contains("pelvis (expects 'mixamorig:Hips')"),
        "{}",
        e.reason
    );
    assert!(e.reason.contains("l_knee (expects"), "{}", e.reason);
    // A map that does not fit the file names the missing joints too.
    let e =
        retarget::read_clip(&path, Path::new("custom.bvh"), Some(&RigMap::bandai())).unwrap_err();
    assert!(
        e.reason.contains(
            "rig map 'bandai' does not fit: missing source joints for pelvis (expects 'Hips')"
        ),
        "{}",
        e.reason
    );
}

#[test]
fn unreadable_files_are_rejected_at_read() {
    let dir = tempfile::tempdir().unwrap();
    let as_dir = dir.path().join("x.bvh");
    std::fs::create_dir(&as_dir).unwrap();
    let e = retarget::read_clip(&as_dir, Path::new("x.bvh"), None).unwrap_err();
    assert_eq!(e.stage, "read");
    assert!(e.reason.contains("x.bvh"), "{}", e.reason);
    let bad = dir.path().join("bad.bvh");
    std::fs::write(&bad, b"HIERARCHY\nROOT \xff\xfe\n").unwrap();
    let e = retarget::read_clip(&bad, Path::new("bad.bvh"), None).unwrap_err();
    assert_eq!(e.stage, "read");
    assert!(
        e.reason
            .contains("not UTF-8 text (invalid byte at offset 15)"),
        "{}",
        e.reason
    );
    let trunc = dir.path().join("trunc.bvh");
    std::fs::write(&trunc, &TWO_JOINTS[..TWO_JOINTS.len() - 10]).unwrap();
    let e = retarget::read_clip(&trunc, Path::new("trunc.bvh"), None).unwrap_err();
    assert_eq!(e.stage, "parse");
    assert!(
        e.reason.contains("trunc.bvh: line 20: truncated"),
        "{}",
        e.reason
    );
}

/// Extract Bandai set-1 files whose names contain one of `patterns` into a temp dir.
fn extract_bandai(patterns: &[&str]) -> Option<(tempfile::TempDir, Vec<PathBuf>)> {
    let archive = data_dir()?.join("bandai-namco/bandai-namco-1.tar.zst");
    let dir = tempfile::tempdir().unwrap();
    let mut cmd = std::process::Command::new("tar");
    cmd.arg("--zstd")
        .arg("-xf")
        .arg(&archive)
        .arg("-C")
        .arg(dir.path())
        .arg("--wildcards");
    for p in patterns {
        cmd.arg(format!("*{p}.bvh"));
    }
    let status = cmd.status().unwrap();
    assert!(status.success(), "tar failed on {}", archive.display());
    let files = patterns
        .iter()
        .map(|p| {
            dir.path().join(format!(
                "Bandai-Namco-Research-Motiondataset-1/data/dataset-1_{p}.bvh"
            ))
        })
        .collect();
    Some((dir, files))
}

#[test]
fn bandai_clips_retarget_with_rigid_bones_on_the_floor_and_left_on_the_left() {
    let Some((_dir, files)) =
        extract_bandai(&["walk_normal_001", "run_happy_001", "walk-back_sad_001"])
    else {
        return;
    };
    for path in &files {
        let clip = retarget::read_clip(path, path, None).unwrap();
        let name = clip.clip_id.clone();
        assert!(
            clip.conversion.starts_with("bandai rig, cm→m"),
            "{}",
            clip.conversion
        );
        assert!(clip.conversion.ends_with("Y up"), "{}", clip.conversion);
        assert!((clip.fps - 30.0).abs() < 1e-3, "{name}: {}", clip.fps);
        let poses = &clip.poses;
        assert!(poses.len() > 30, "{name}");
        // Bone lengths are constant over frames.
        for j in 1..22 {
            let len = |p: &Pose| quat::norm(quat::sub(p[j], p[PARENTS[j]]));
            let l0 = len(&poses[0]);
            assert!(l0 > 0.01, "{name}: bone {j} has length {l0}");
            for p in poses {
                assert!((len(p) - l0).abs() <= 1e-6 * l0, "{name}: bone {j}");
            }
        }
        let stature = estimate_stature(&poses[0]);
        assert!((1.4..2.0).contains(&stature), "{name}: stature {stature}");
        // Feet reach the floor (Y ≈ 0) and never sink far below it.
        let lowest = poses
            .iter()
            .flat_map(|p| [p[7][1], p[8][1], p[10][1], p[11][1]])
            .fold(f64::INFINITY, f64::min);
        assert!(
            (-0.03..0.1).contains(&lowest),
            "{name}: lowest foot at {lowest} m"
        );
        let head = poses[0][15][1] - lowest;
        assert!(
            (1.2..1.9).contains(&head),
            "{name}: head joint {head} m above the floor"
        );
        // Left is left: with Y up, (l_hip − r_hip) × up points where the person faces.
        let facing = |p: &Pose| quat::cross(quat::sub(p[1], p[2]), [0.0, 1.0, 0.0]);
        let travel = quat::sub(poses[poses.len() - 1][0], poses[0][0]);
        let travel = [travel[0], 0.0, travel[2]];
        assert!(quat::norm(travel) > 0.5, "{name}: travelled {travel:?}");
        let forward = if name.contains("walk-back") {
            -1.0
        } else {
            1.0
        };
        let agree = poses
            .iter()
            .filter(|p| forward * quat::dot(facing(p), travel) > 0.0)
            .count();
        assert!(
            agree * 10 >= poses.len() * 9,
            "{name}: facing agrees with travel in {agree} of {} frames",
            poses.len()
        );
    }
}

#[test]
fn bandai_parse_matches_its_own_world_positions_frame_count() {
    let Some((_dir, files)) = extract_bandai(&["bow_active_001"]) else {
        return;
    };
    let text = std::fs::read_to_string(&files[0]).unwrap();
    let b: Bvh = bvh::parse(&text).unwrap();
    assert_eq!(b.joints.iter().filter(|j| !j.end_site).count(), 22);
    assert!(b
        .joints
        .iter()
        .filter(|j| !j.end_site)
        .all(|j| j.channels.len() == 6));
    let declared: usize = text
        .lines()
        .find_map(|l| l.strip_prefix("Frames:"))
        .and_then(|n| n.trim().parse().ok())
        .unwrap();
    assert_eq!(b.num_frames(), declared);
    assert_eq!(b.world_positions().len(), declared * b.joints.len());
}

#[test]
fn huge_hierarchies_are_refused_by_the_budgets() {
    // 50,000 nested joints: refused at the depth budget, before any motion is read.
    let n = 50_000;
    let mut text = String::from("HIERARCHY\nROOT j0 { OFFSET 0 0 0 CHANNELS 1 Xrotation\n");
    for k in 1..n {
        text.push_str(&format!(
            "JOINT j{k} {{ OFFSET 0 1 0 CHANNELS 1 Zrotation\n"
        ));
    }
    text.push_str(&"}".repeat(n));
    text.push_str("\nMOTION\nFrames: 1\nFrame Time: 0.01\n");
    text.push_str(&"0 ".repeat(n));
    let e = parse_err(&text);
    assert_eq!(e, "line 66: joints nested deeper than the 64-level budget");
    // 50,000 sibling joints: refused at the channel budget.
    let mut text = String::from("HIERARCHY\nROOT j0 { OFFSET 0 0 0 CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n");
    for k in 1..n {
        text.push_str(&format!(
            "JOINT j{k} {{ OFFSET 0 1 0 CHANNELS 3 Zrotation Xrotation Yrotation }}\n"
        ));
    }
    text.push_str("}\nMOTION\nFrames: 1\nFrame Time: 0.01\n");
    let e = parse_err(&text);
    assert_eq!(
        e,
        "line 342: 1026 channels per frame, over the 1024-channel budget"
    );
}

#[test]
fn frame_times_and_rotations_beyond_the_budgets_are_named() {
    let e = parse_err(&with_motion(
        "Frames: 2\nFrame Time:\n-11.609772 2 3 90 0 0 0 90 0\n1 2 3 0 90 90 0 0 0\n",
    ));
    assert_eq!(
        e,
        "line 18: empty Frame Time: no value after 'Frame Time:' on its line"
    );
    let e = parse_err(&with_motion(
        "Frames: 187\nFrame Time: 100000\n1 2 3 90 0 0 0 90 0\n",
    ));
    assert!(
        e.starts_with("line 18: frame time 100000 s is outside") && e.contains("215 days"),
        "{e}"
    );
    let e = parse_err(&with_motion(
        "Frames: 2\nFrame Time: 0.05\n1 2 3 90 0 0 0 90 0\n1 2 3 0 1e26 90 0 0 0\n",
    ));
    assert_eq!(
        e,
        "line 20: implausible rotation 1e26° at frame 2 channel 5 (A Yrotation), beyond ±1e6°"
    );
}
