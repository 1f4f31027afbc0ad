//! Exports: the HumanML3D folder layout and BVH (checked by forward kinematics of the written file).

mod common;

use common::data_dir;
use ingest::corpus::ClipRecord;
use ingest::export::bvh;
use ingest::export::hml3d::{Hml3dWriter, FEATURE_DIM, GENERIC_CAPTION};
use ingest::export::text_process::PosTagger;
use ingest::npy;
use ingest::quat::{self, Quat, Vec3};
use ingest::skeleton::{Pose, JOINT_NAMES, NUM_JOINTS, PARENTS, TARGET_OFFSETS};
use ingest::source::bvh::{Bvh, Channel};
use std::path::Path;

// ---------------------------------------------------------------- HumanML3D layout

fn record(id: &str, frames: usize, split: &str, captions: &[&str]) -> ClipRecord {
    ClipRecord {
        motion_id: id.into(),
        source: "synth".into(),
        source_path: format!("{id}.npy"),
        source_clip: id.into(),
        segment: 0,
        fps: 20.0,
        source_fps: 30.0,
        num_frames: frames as u32,
        features: (0..frames * FEATURE_DIM).map(|i| i as f32 * 0.5).collect(),
        joints: (0..(frames + 1) * NUM_JOINTS * 3)
            .map(|i| -(i as f32))
            .collect(),
        captions: captions.iter().map(|c| c.to_string()).collect(),
        labels: Default::default(),
        split: split.into(),
        mirrored: false,
        span: None,
    }
}

#[test]
fn hml3d_layout_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("export");
    let mut writer = Hml3dWriter::new(&out, PosTagger::BuiltIn).unwrap();
    writer
        .add(&record(
            "walk_001",
            4,
            "train",
            &["A person walks forward.", "Someone walks #1"],
        ))
        .unwrap();
    writer.add(&record("Mwalk_001", 3, "train", &[])).unwrap();
    writer
        .add(&record("bow_002", 2, "test", &["he bows."]))
        .unwrap();
    let bad = record("x/y", 2, "train", &[]);
    assert!(writer
        .add(&bad)
        .unwrap_err()
        .to_string()
        .contains("file name"));
    let mut short = record("short", 2, "train", &[]);
    short.features.pop();
    assert!(writer
        .add(&short)
        .unwrap_err()
        .to_string()
        .contains("525 feature values"));
    let mean: Vec<f32> = (0..FEATURE_DIM).map(|i| i as f32).collect();
    let std = vec![1.5f32; FEATURE_DIM];
    assert!(
        Hml3dWriter::new(&dir.path().join("other"), PosTagger::BuiltIn)
            .unwrap()
            .finish(&mean[..10], &std)
            .is_err()
    );
    let summary = writer.finish(&mean, &std).unwrap();
    assert_eq!(summary.clips, 3);
    assert_eq!(summary.generic_captions, 1);
    assert_eq!(summary.per_split["train"], 2);
    assert_eq!(summary.per_split["val"], 0);
    assert_eq!(summary.per_split["test"], 1);

    let vecs = npy::read(&out.join("new_joint_vecs/walk_001.npy")).unwrap();
    assert_eq!(vecs.shape, [4, FEATURE_DIM]);
    assert_eq!(vecs.data[FEATURE_DIM + 1], (FEATURE_DIM + 1) as f64 * 0.5);
    // new_joints = recover_from_ric(new_joint_vecs): as many frames as the vectors.
    let joints = npy::read(&out.join("new_joints/walk_001.npy")).unwrap();
    assert_eq!(joints.shape, [4, NUM_JOINTS, 3]);
    let features = record("walk_001", 4, "train", &[]).features;
    let recovered = ingest::hml263::recover_joints_f32(&features);
    assert!(joints
        .data
        .iter()
        .zip(&recovered)
        .all(|(a, &b)| *a == b as f64));
    assert_eq!(
        npy::read(&out.join("new_joints/Mwalk_001.npy"))
            .unwrap()
            .shape,
        [3, 22, 3]
    );
    assert_eq!(npy::read(&out.join("Mean.npy")).unwrap().data[262], 262.0);
    assert_eq!(
        npy::read(&out.join("Std.npy")).unwrap().shape,
        [FEATURE_DIM]
    );

    let text = std::fs::read_to_string(out.join("texts/walk_001.txt")).unwrap();
    assert_eq!(
        text,
        "A person walks forward.#A/DET person/NOUN walk/VERB forward/ADV#0.0#0.0\n\
         Someone walks 1#Someone/PRON walk/VERB#0.0#0.0\n"
    );
    for line in text.lines() {
        let fields: Vec<_> = line.split('#').collect();
        assert_eq!(fields.len(), 4);
        // T2M-GPT's WordVectorizer splits every token on '/' into exactly (word, POS).
        assert!(
            fields[1].split(' ').all(|t| t.split('/').count() == 2),
            "{line}"
        );
    }
    let generic = std::fs::read_to_string(out.join("texts/Mwalk_001.txt")).unwrap();
    assert!(
        generic.starts_with(&format!("{GENERIC_CAPTION}#")),
        "{generic}"
    );

    let read = |name: &str| std::fs::read_to_string(out.join(name)).unwrap();
    assert_eq!(read("train.txt"), "Mwalk_001\nwalk_001\n");
    assert_eq!(read("val.txt"), "");
    assert_eq!(read("test.txt"), "bow_002\n");
    assert_eq!(read("train_val.txt"), "Mwalk_001\nwalk_001\n");
    assert_eq!(read("all.txt"), "Mwalk_001\nbow_002\nwalk_001\n");
    assert_eq!(
        summary.loader_clips["train"], 0,
        "every clip is under 40 frames"
    );
    assert_eq!(summary.warnings.len(), 3, "{:?}", summary.warnings);
    let leftovers: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

/// Rows of a fixture `.npy` as f32 values.
fn fixture(data: &Path, name: &str) -> (Vec<usize>, Vec<f32>) {
    let arr = npy::read(&data.join(format!("humanml3d-fixtures/{name}.npy"))).unwrap();
    (arr.shape, arr.data.iter().map(|&v| v as f32).collect())
}

#[test]
fn hml3d_new_joints_are_the_fixtures_recovered_joints() {
    let Some(data) = data_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let mut writer = Hml3dWriter::new(dir.path(), PosTagger::BuiltIn).unwrap();
    let fixtures = ["a_asis", "e_crop10_50"];
    for name in fixtures {
        // The reference's own features, and ours computed from the fixture's joints.
        let (shape, features) = fixture(&data, &format!("{name}_features"));
        let (_, joints) = fixture(&data, &format!("{name}_joints"));
        let poses: Vec<Pose> = joints
            .chunks_exact(NUM_JOINTS * 3)
            .map(|f| std::array::from_fn(|j| std::array::from_fn(|k| f[3 * j + k] as f64)))
            .collect();
        let ours = ingest::hml263::process(&poses, &Default::default()).unwrap();
        for (id, features) in [
            (name.to_string(), features),
            (format!("{name}_ours"), ours.features),
        ] {
            let mut clip = record(&id, shape[0], "test", &["a person moves."]);
            clip.features = features;
            writer.add(&clip).unwrap();
        }
    }
    let mean = vec![0f32; FEATURE_DIM];
    writer.finish(&mean, &vec![1f32; FEATURE_DIM]).unwrap();
    for name in fixtures {
        let (expected_shape, expected) = fixture(&data, &format!("{name}_recovered"));
        for id in [name.to_string(), format!("{name}_ours")] {
            let vecs = npy::read(&dir.path().join(format!("new_joint_vecs/{id}.npy"))).unwrap();
            let joints = npy::read(&dir.path().join(format!("new_joints/{id}.npy"))).unwrap();
            assert_eq!(joints.shape, expected_shape);
            assert_eq!(
                joints.shape[0], vecs.shape[0],
                "as many frames as new_joint_vecs"
            );
            let worst = joints
                .data
                .iter()
                .zip(&expected)
                .map(|(a, &b)| (a - f64::from(b)).abs())
                .fold(0f64, f64::max);
            eprintln!("{id}: new_joints vs {name}_recovered.npy, max difference {worst:.2e} m");
            assert!(worst < 1e-4, "{id}: {worst}");
        }
    }
}

// ---------------------------------------------------------------- BVH

/// Pose by forward kinematics of the target skeleton with the given local rotations.
fn pose_from(locals: &[Quat; NUM_JOINTS], root: Vec3) -> Pose {
    let mut global = [quat::IDENTITY; NUM_JOINTS];
    let mut pose = [[0.0; 3]; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        if j == 0 {
            global[0] = locals[0];
            pose[0] = root;
        } else {
            let p = PARENTS[j];
            global[j] = quat::mul(global[p], locals[j]);
            pose[j] = quat::add(pose[p], quat::rot(global[p], TARGET_OFFSETS[j]));
        }
    }
    pose
}

/// Parses a written BVH with the project's parser and checks the hierarchy (bones out of
/// pelvis and spine3 within `length_tol_cm` of the target lengths), frame count and frame
/// time; returns the file and each file joint's SMPL-22 index.
fn check_structure(text: &str, frames: usize, fps: f64, length_tol_cm: f64) -> (Bvh, Vec<usize>) {
    let bvh = ingest::source::bvh::parse(text).expect("written BVH parses");
    let joints: Vec<_> = bvh.joints.iter().filter(|j| !j.end_site).collect();
    let index = |name: &str| JOINT_NAMES.iter().position(|n| *n == name).unwrap();
    let order: Vec<usize> = joints.iter().map(|j| index(&j.name)).collect();
    assert_eq!(order, bvh::hierarchy_order());
    assert_eq!(order[0], 0);
    let file_index = |i: usize| {
        bvh.joints
            .iter()
            .position(|j| j.name == joints[i].name)
            .unwrap()
    };
    for (i, &j) in order.iter().enumerate().skip(1) {
        let parent = bvh.joints[file_index(i)]
            .parent
            .map(|p| index(&bvh.joints[p].name));
        assert_eq!(parent, Some(PARENTS[j]), "parent of {}", JOINT_NAMES[j]);
        let expected = quat::scale(TARGET_OFFSETS[j], 100.0);
        let siblings = (1..NUM_JOINTS)
            .filter(|&c| PARENTS[c] == PARENTS[j])
            .count();
        if siblings > 1 {
            // The motion's own shape: the target's bone length (cm), any direction.
            let d = quat::norm(joints[i].offset) - quat::norm(expected);
            assert!(d.abs() < length_tol_cm, "{}: {d}", JOINT_NAMES[j]);
        } else {
            assert!(quat::norm(quat::sub(joints[i].offset, expected)) < 1e-5);
        }
        assert_eq!(
            joints[i].channels,
            [Channel::Zrotation, Channel::Yrotation, Channel::Xrotation]
        );
    }
    assert_eq!(joints[0].channels.len(), 6);
    assert_eq!(joints[0].parent, None);
    // Leaves: feet, head, wrists.
    assert_eq!(bvh.joints.iter().filter(|j| j.end_site).count(), 5);
    assert_eq!(bvh.num_frames(), frames);
    assert!((bvh.frame_time - 1.0 / fps).abs() < 1e-8);
    assert_eq!(bvh.num_channels, 6 + 3 * (NUM_JOINTS - 1));
    (bvh, order)
}

/// Forward kinematics of a written BVH (the project's parser), as poses in SMPL-22 order.
fn fk_poses(text: &str, frames: usize, fps: f64, length_tol_cm: f64) -> Vec<Pose> {
    let (bvh, _) = check_structure(text, frames, fps, length_tol_cm);
    let file_index: Vec<usize> = JOINT_NAMES
        .iter()
        .map(|n| bvh.joint_index(n).expect("every SMPL joint is in the file"))
        .collect();
    bvh.world_positions()
        .chunks_exact(bvh.joints.len())
        .map(|frame| std::array::from_fn(|j| quat::scale(frame[file_index[j]], 0.01)))
        .collect()
}

/// Poses of the target skeleton under seeded random local rotations (up to ~1.2 rad per joint).
fn random_poses(frames: usize) -> Vec<Pose> {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut uniform = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    (0..frames)
        .map(|t| {
            let locals: [Quat; NUM_JOINTS] = std::array::from_fn(|_| {
                quat::from_rotvec([uniform() * 0.7, uniform() * 0.7, uniform() * 0.7])
            });
            pose_from(&locals, [0.1 * t as f64, 0.9, -0.05 * t as f64])
        })
        .collect()
}

#[test]
fn bvh_reproduces_rigid_poses_exactly() {
    let poses = random_poses(12);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rigid.bvh");
    bvh::write_bvh_file(&path, &poses, 30.0).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let fk = fk_poses(&text, 12, 30.0, 1e-3);
    let mut max_err: f64 = 0.0;
    for (pose, got) in poses.iter().zip(&fk) {
        for j in 0..NUM_JOINTS {
            max_err = max_err.max(quat::norm(quat::sub(pose[j], got[j])));
        }
    }
    eprintln!("rigid poses: max FK error {max_err:.3e} m");
    assert!(max_err < 1e-6, "max error {max_err}");
}

#[test]
fn bvh_of_real_humanml3d_joints_reproduces_them() {
    let Some(data) = data_dir() else { return };
    let raw = npy::read(&data.join("humanml3d-fixtures/humanml3d_new_joints_012314.npy")).unwrap();
    let poses: Vec<Pose> = raw
        .data
        .chunks_exact(NUM_JOINTS * 3)
        .map(|f| std::array::from_fn(|j| [f[3 * j], f[3 * j + 1], f[3 * j + 2]]))
        .collect();
    let text = bvh::write_bvh(&poses, 20.0);
    let fk = fk_poses(&text, poses.len(), 20.0, 1e-3);
    let mut bone_err: f64 = 0.0;
    let (mut upper_max, mut sum, mut count): (f64, f64, usize) = (0.0, 0.0, 0);
    let mut overall_max: f64 = 0.0;
    let upper = [13, 14, 16, 17, 18, 19, 20, 21];
    let single_child = |p: usize| (1..NUM_JOINTS).filter(|&c| PARENTS[c] == p).count() == 1;
    for (pose, got) in poses.iter().zip(&fk) {
        for j in 0..NUM_JOINTS {
            let err = quat::norm(quat::sub(pose[j], got[j]));
            overall_max = overall_max.max(err);
            sum += err;
            count += 1;
            if upper.contains(&j) {
                upper_max = upper_max.max(err);
            }
            let p = PARENTS[j];
            if j > 0 && p != 0 && single_child(p) {
                let seen = quat::sub(pose[j], pose[p]);
                let rebuilt = quat::sub(got[j], got[p]);
                bone_err = bone_err.max(quat::norm(quat::sub(seen, rebuilt)));
            }
        }
    }
    let mean = sum / count as f64;
    eprintln!(
        "HumanML3D 012314 ({} frames): single-child bones max {bone_err:.2e} m; \
         collars/arms max {:.2e} m; all joints max {:.2e} m, mean {:.2e} m",
        poses.len(),
        upper_max,
        overall_max,
        mean
    );
    // Single-child bones: exact up to the clip's bone-length noise (< 2e-6 m) and text rounding.
    assert!(bone_err < 1e-5, "{bone_err}");
    assert!(upper_max < 0.02, "{upper_max}");
    assert!(mean < 0.01, "{mean}");
}

#[test]
fn bvh_of_a_non_rigid_shoulder_girdle_stays_close() {
    // Move the left collar (and the arm hanging from it) off the rigid spine3 shape by up to
    // 1.5 cm, varying over time: no rotation can match every frame, the fit spreads the error.
    let mut poses = random_poses(40);
    for (t, pose) in poses.iter_mut().enumerate() {
        let phase = t as f64 * 0.3;
        let shift = [0.015 * phase.sin(), 0.01 * phase.cos(), 0.0];
        for j in [13, 16, 18, 20] {
            pose[j] = quat::add(pose[j], shift);
        }
    }
    let fk = fk_poses(&bvh::write_bvh(&poses, 20.0), poses.len(), 20.0, 1.5);
    let (mut max_err, mut sum): (f64, f64) = (0.0, 0.0);
    for (t, (pose, got)) in poses.iter().zip(&fk).enumerate() {
        for j in 0..NUM_JOINTS {
            let err = quat::norm(quat::sub(pose[j], got[j]));
            max_err = max_err.max(err);
            sum += err;
        }
        // Bones of single-child chains stay exact relative to their parent.
        let bone = |c: usize, p: usize| quat::sub(pose[c], pose[p]);
        let got_bone = |c: usize, p: usize| quat::sub(got[c], got[p]);
        for (c, p) in [(18, 16), (20, 18), (4, 1), (15, 12)] {
            let e = quat::norm(quat::sub(bone(c, p), got_bone(c, p)));
            assert!(e < 1e-6, "frame {t}, bone {p}->{c}: {e:e}");
        }
    }
    let mean = sum / (poses.len() * NUM_JOINTS) as f64;
    eprintln!("non-rigid collar: max FK error {max_err:.4} m, mean {mean:.5} m");
    assert!(max_err < 0.02, "{max_err}");
}
