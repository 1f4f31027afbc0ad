//! Sources: joints `.npy`, AMASS `.npz` with a body model, and HumanML3D-layout folders.

mod common;

use common::data_dir;
use ingest::npy;
use ingest::quat;
use ingest::skeleton::{Pose, NUM_JOINTS, PARENTS, TARGET_OFFSETS};
use ingest::source::{amass, hml3d, joints};
use ingest::IngestError;
use std::io::Write;
use std::path::Path;

/// `.npy` bytes of `payload` under another 3-character dtype (the header length is unchanged).
fn encode_as(shape: &[usize], dtype: &str, payload: &[u8]) -> Vec<u8> {
    let count: usize = shape.iter().product();
    let mut bytes = npy::encode_f32(shape, &vec![0.0; count]);
    let at = bytes.windows(3).position(|w| w == b"<f4").unwrap();
    bytes[at..at + 3].copy_from_slice(dtype.as_bytes());
    bytes.truncate(bytes.len() - count * 4);
    bytes.extend_from_slice(payload);
    bytes
}

fn encode_f64(shape: &[usize], data: &[f64]) -> Vec<u8> {
    let payload: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    encode_as(shape, "<f8", &payload)
}

fn close(a: [f64; 3], b: [f64; 3], tol: f64, what: &str) {
    let d = quat::norm(quat::sub(a, b));
    assert!(d < tol, "{what}: {a:?} vs {b:?} (|d| = {d:e})");
}

// ---------------------------------------------------------------- joints

#[test]
fn joints_reads_the_humanml3d_fixture() {
    let Some(data) = data_dir() else { return };
    let file = data.join("humanml3d-fixtures/humanml3d_new_joints_012314.npy");
    let clip = joints::read_clip(&file, Path::new("012314.npy"), 20.0).unwrap();
    let raw = npy::read(&file).unwrap();
    assert_eq!(clip.poses.len(), 170);
    assert_eq!(clip.clip_id, "012314");
    assert_eq!(clip.source, "joints");
    assert_eq!(clip.fps, 20.0);
    assert_eq!(clip.conversion, "metres, Y up (as given)");
    assert_eq!(
        clip.poses[169][21],
        [
            raw.data[169 * 66 + 63],
            raw.data[169 * 66 + 64],
            raw.data[169 * 66 + 65]
        ]
    );
    assert_eq!(clip.poses[0][0][1], raw.data[1]);
}

#[test]
fn joints_reads_f64_with_extra_joints_and_keeps_sub_folders_in_the_id() {
    let dir = tempfile::tempdir().unwrap();
    let (frames, joints_in) = (3, 24);
    let data: Vec<f64> = (0..frames * joints_in * 3)
        .map(|i| i as f64 * 0.001)
        .collect();
    let file = dir.path().join("walk.npy");
    std::fs::write(&file, encode_f64(&[frames, joints_in, 3], &data)).unwrap();
    let clip = joints::read_clip(&file, Path::new("subject1/walk.npy"), 30.0).unwrap();
    assert_eq!(clip.clip_id, "subject1_walk");
    assert_eq!(clip.fps, 30.0);
    assert_eq!(clip.poses.len(), 3);
    // Frame 1, joint 21: the first 22 of 24 joints are kept.
    let at = (joints_in + 21) * 3;
    assert_eq!(clip.poses[1][21], [data[at], data[at + 1], data[at + 2]]);
}

#[test]
fn joints_rejects_bad_files_with_reasons() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, bytes: Vec<u8>| {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    let cases = [
        (
            write("flat.npy", npy::encode_f32(&[5, 66], &[0.0; 330])),
            "parse",
            "shape [5, 66]",
        ),
        (
            write("few.npy", npy::encode_f32(&[2, 21, 3], &[0.0; 126])),
            "parse",
            "21 joints",
        ),
        (
            write("empty.npy", npy::encode_f32(&[0, 22, 3], &[])),
            "parse",
            "zero frames",
        ),
        (
            write("junk.npy", b"not numpy".to_vec()),
            "parse",
            "not a .npy",
        ),
        (dir.path().join("absent.npy"), "read", "absent.npy"),
    ];
    for (path, stage, needle) in cases {
        let err = joints::read_clip(&path, Path::new("x.npy"), 20.0).unwrap_err();
        assert_eq!(err.stage, stage, "{err}");
        assert!(err.reason.contains(needle), "{err}");
        assert!(err.reason.contains(&path.display().to_string()), "{err}");
    }
}

// ---------------------------------------------------------------- HumanML3D folders

fn write_joints(path: &Path, frames: usize, seed: f32) {
    let data: Vec<f32> = (0..frames * NUM_JOINTS * 3)
        .map(|i| seed + i as f32 * 1e-3)
        .collect();
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    npy::write_f32(path, &[frames, NUM_JOINTS, 3], &data).unwrap();
}

#[test]
fn hml3d_folder_yields_whole_clips_and_captioned_segments() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    write_joints(&root.join("new_joints/000001.npy"), 60, 0.0);
    write_joints(&root.join("new_joints/000002.npy"), 10, 5.0);
    std::fs::create_dir_all(root.join("texts")).unwrap();
    std::fs::write(
        root.join("texts/000001.txt"),
        "a person walks.#a/DET person/NOUN walk/VERB#0.0#0.0\n\
         someone strolls.#someone/PRON stroll/VERB#nan#nan\n\
         he waves.#he/PRON wave/VERB#0.5#2.0\n\
         a wave.#a/DET wave/NOUN#0.5#2.0\n\
         he stops.#he/PRON stop/VERB#2.5#10.0\n\
         he is gone.#he/PRON be/AUX go/VERB#4.0#5.0\n",
    )
    .unwrap();
    std::fs::write(root.join("train.txt"), "000001\n").unwrap();
    std::fs::write(root.join("test.txt"), "000002\n").unwrap();

    let folder = hml3d::Hml3dFolder::open(root).unwrap();
    let files = folder.discover().unwrap();
    assert_eq!(files.len(), 2);
    assert!(files[0].ends_with("new_joints/000001.npy"));

    let clips = folder.read_clips(&files[0]);
    assert_eq!(clips.len(), 4, "whole + 3 spans");
    let whole = clips[0].as_ref().unwrap();
    assert_eq!(whole.clip_id, "000001");
    assert_eq!(whole.poses.len(), 60);
    assert_eq!(whole.captions, ["a person walks.", "someone strolls."]);
    assert_eq!(whole.split.as_deref(), Some("train"));
    assert_eq!((whole.source.as_str(), whole.fps), ("hml3d", 20.0));
    assert_eq!(whole.conversion, "HumanML3D new_joints (metres, Y up)");

    let wave = clips[1].as_ref().unwrap();
    assert_eq!(wave.clip_id, "000001_10_40");
    assert_eq!(wave.captions, ["he waves.", "a wave."]);
    let span = wave.span.as_ref().expect("a span clip remembers its span");
    assert_eq!(span.of, "000001");
    assert_eq!(span.seconds, [(0.5, 2.0), (0.5, 2.0)]);
    assert_eq!(whole.span, None);
    assert_eq!(wave.poses.len(), 30);
    assert_eq!(wave.poses[0], whole.poses[10]);
    assert_eq!(wave.split.as_deref(), Some("train"));

    // End beyond the clip is clamped as Python slicing does.
    let stop = clips[2].as_ref().unwrap();
    assert_eq!(stop.clip_id, "000001_50_200");
    assert_eq!(stop.poses.len(), 10);
    assert_eq!(stop.poses[9], whole.poses[59]);

    let gone = clips[3].as_ref().unwrap_err();
    assert!(gone.reason.contains("frames 80..100"), "{gone}");
    assert!(gone.reason.contains("he is gone."), "{gone}");

    // No text file: the whole clip without captions; split from test.txt.
    let second = folder.read_clips(&files[1]);
    assert_eq!(second.len(), 1);
    let second = second[0].as_ref().unwrap();
    assert!(second.captions.is_empty());
    assert_eq!(second.split.as_deref(), Some("test"));
}

#[test]
fn hml3d_folder_errors_name_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let err = hml3d::Hml3dFolder::open(dir.path()).unwrap_err();
    match &err {
        IngestError::File(e) => assert_eq!(e.path(), dir.path(), "the error names the folder"),
        other => panic!("expected a file error, got {other:?}"),
    }
    let err = err.to_string();
    assert!(err.contains("no new_joints/"), "{err}");
    assert!(err.contains(&dir.path().display().to_string()), "{err}");

    write_joints(&dir.path().join("new_joints/a.npy"), 5, 0.0);
    std::fs::create_dir_all(dir.path().join("texts")).unwrap();
    std::fs::write(
        dir.path().join("texts/a.txt"),
        "fine#f/X#0#0\nbroken line\n",
    )
    .unwrap();
    std::fs::write(
        dir.path().join("new_joints/b.npy"),
        npy::encode_f32(&[5, 3], &[0.0; 15]),
    )
    .unwrap();
    let folder = hml3d::Hml3dFolder::open(dir.path()).unwrap();
    let files = folder.discover().unwrap();
    let a = folder.read_clips(&files[0]);
    let err = a[0].as_ref().unwrap_err();
    assert!(err.reason.contains("a.txt: line 2"), "{err}");
    let b = folder.read_clips(&files[1]);
    let err = b[0].as_ref().unwrap_err();
    assert!(
        err.reason.contains("b.npy") && err.reason.contains("[5, 3]"),
        "{err}"
    );

    std::fs::write(dir.path().join("train.txt"), "a\n").unwrap();
    std::fs::write(dir.path().join("val.txt"), "a\n").unwrap();
    let err = hml3d::Hml3dFolder::open(dir.path())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("a is listed in train.txt and val.txt"),
        "{err}"
    );
}

#[test]
fn hml3d_folder_reads_the_real_fixture_clip() {
    let Some(data) = data_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(dir.path().join("new_joints")).unwrap();
    std::fs::copy(
        data.join("humanml3d-fixtures/humanml3d_new_joints_012314.npy"),
        dir.path().join("new_joints/012314.npy"),
    )
    .unwrap();
    std::fs::create_dir_all(dir.path().join("texts")).unwrap();
    std::fs::write(
        dir.path().join("texts/012314.txt"),
        "a person moves.#a/DET person/NOUN move/VERB#0.0#0.0\nstep.#step/VERB#1.0#3.0\n",
    )
    .unwrap();
    let folder = hml3d::Hml3dFolder::open(dir.path()).unwrap();
    let files = folder.discover().unwrap();
    let clips: Vec<_> = folder
        .read_clips(&files[0])
        .into_iter()
        .map(Result::unwrap)
        .collect();
    assert_eq!(clips[0].poses.len(), 170);
    assert_eq!(clips[0].split, None);
    assert_eq!(clips[1].clip_id, "012314_20_60");
    assert_eq!(clips[1].poses[..], clips[0].poses[20..60]);
}

// ---------------------------------------------------------------- AMASS

/// Rest joints of the test body model (SMPL's own frame, Y up): the target skeleton.
fn model_rest() -> [[f64; 3]; NUM_JOINTS] {
    let mut rest = [[0.01, -0.2, 0.03]; NUM_JOINTS];
    for j in 1..NUM_JOINTS {
        rest[j] = quat::add(rest[PARENTS[j]], TARGET_OFFSETS[j]);
    }
    // f32 storage: compare against what the file holds.
    rest.map(|p| p.map(|v| v as f32 as f64))
}

fn write_npz(path: &Path, entries: &[(&str, Vec<u8>)], deflate: bool) {
    let file = std::fs::File::create(path).unwrap();
    let mut zip = zip::ZipWriter::new(file);
    let method = if deflate {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    let options = zip::write::SimpleFileOptions::default().compression_method(method);
    for (key, bytes) in entries {
        zip.start_file(format!("{key}.npy"), options).unwrap();
        zip.write_all(bytes).unwrap();
    }
    zip.finish().unwrap();
}

/// A 22-joint body model with 2 vertices per joint (the regressor averages them) and 2 shape
/// directions: beta 0 scales the whole body about the origin by (1 + 0.1·beta0), beta 1 is 0.
fn write_model(path: &Path, kintree_parent_of_5: Option<i64>, drop: Option<&str>) {
    let rest = model_rest();
    let verts = 2 * NUM_JOINTS;
    let e = [0.01, 0.02, -0.01];
    let mut v_template = Vec::new();
    let mut shapedirs = Vec::new();
    for p in rest {
        for sign in [1.0, -1.0] {
            for k in 0..3 {
                v_template.push((p[k] + sign * e[k]) as f32);
                shapedirs.extend([(0.1 * (p[k] + sign * e[k])) as f32, 0.0]);
            }
        }
    }
    let mut regressor = vec![0.0f32; NUM_JOINTS * verts];
    for j in 0..NUM_JOINTS {
        regressor[j * verts + 2 * j] = 0.5;
        regressor[j * verts + 2 * j + 1] = 0.5;
    }
    // Two extra joints (hands) as SMPL+H has more than 22; root's parent = 2^32 - 1 (int64).
    let tree_joints = NUM_JOINTS + 2;
    let mut parents: Vec<i64> = PARENTS.iter().map(|&p| p as i64).collect();
    parents[0] = u32::MAX as i64;
    if let Some(p) = kintree_parent_of_5 {
        parents[5] = p;
    }
    parents.extend([20, 21]);
    let ids: Vec<i64> = (0..tree_joints as i64).collect();
    let kintree: Vec<u8> = parents
        .iter()
        .chain(&ids)
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let mut full_regressor = regressor.clone();
    full_regressor.extend(vec![0.0f32; 2 * verts]);
    let entries = vec![
        ("v_template", npy::encode_f32(&[verts, 3], &v_template)),
        ("shapedirs", npy::encode_f32(&[verts, 3, 2], &shapedirs)),
        (
            "J_regressor",
            npy::encode_f32(&[tree_joints, verts], &full_regressor),
        ),
        (
            "kintree_table",
            encode_as(&[2, tree_joints], "<i8", &kintree),
        ),
    ];
    let entries: Vec<_> = entries
        .into_iter()
        .filter(|(k, _)| Some(*k) != drop)
        .collect();
    write_npz(path, &entries, true);
}

struct Motion {
    poses: Vec<f32>,
    width: usize,
    trans: Vec<f32>,
    betas: Vec<f32>,
    fps_key: Option<&'static str>,
    skip: Option<&'static str>,
}

impl Motion {
    fn new(frames: usize, width: usize) -> Self {
        Self {
            poses: vec![0.0; frames * width],
            width,
            trans: vec![0.0; frames * 3],
            betas: vec![0.0; 16],
            fps_key: Some("mocap_framerate"),
            skip: None,
        }
    }

    fn write(&self, path: &Path) {
        let frames = self.trans.len() / 3;
        let mut entries = vec![
            ("poses", npy::encode_f32(&[frames, self.width], &self.poses)),
            ("trans", npy::encode_f32(&[frames, 3], &self.trans)),
            ("betas", npy::encode_f32(&[self.betas.len()], &self.betas)),
            // A string array as AMASS stores `gender`: never parsed.
            (
                "gender",
                encode_as(&[], "<U1", &u32::from(b'f').to_le_bytes()),
            ),
        ];
        if let Some(key) = self.fps_key {
            entries.push((key, npy::encode_f32(&[], &[120.0])));
        }
        entries.retain(|(k, _)| Some(*k) != self.skip);
        write_npz(path, &entries, false);
    }
}

/// HumanML3D's axis change of a Z-up SMPL point: (x, y, z) → (−x, z, y).
fn y_up(p: [f64; 3]) -> [f64; 3] {
    [-p[0], p[2], p[1]]
}

fn model(dir: &Path) -> amass::BodyModel {
    let path = dir.join("model.npz");
    write_model(&path, None, None);
    amass::BodyModel::load(&path).unwrap()
}

#[test]
fn amass_zero_pose_gives_rest_joints_plus_trans_axis_swapped() {
    let dir = tempfile::tempdir().unwrap();
    let model = model(dir.path());
    let mut motion = Motion::new(2, 156);
    motion.trans = vec![0.0, 0.0, 0.0, 1.0, 2.0, 3.0];
    let path = dir.path().join("01_01_poses.npz");
    motion.write(&path);
    let clip = amass::read_clip(&path, Path::new("CMU/01/01_01_poses.npz"), &model).unwrap();
    assert_eq!(clip.clip_id, "CMU_01_01_01_poses");
    assert_eq!((clip.source.as_str(), clip.fps), ("amass", 120.0));
    assert!(clip.conversion.contains("(-x, z, y)"));
    let rest = model_rest();
    for (j, r) in rest.into_iter().enumerate() {
        close(clip.poses[0][j], y_up(r), 1e-6, "frame 0");
        close(
            clip.poses[1][j],
            y_up(quat::add(r, [1.0, 2.0, 3.0])),
            1e-6,
            "frame 1",
        );
    }
}

#[test]
fn amass_rotations_move_children_as_computed_by_hand() {
    let dir = tempfile::tempdir().unwrap();
    let model = model(dir.path());
    let quarter = std::f32::consts::FRAC_PI_2;
    let mut motion = Motion::new(2, 165);
    // SMPL-X layout, with junk in the hand/face columns that must be ignored.
    for t in 0..2 {
        for v in &mut motion.poses[t * 165 + 66..(t + 1) * 165] {
            *v = 0.7;
        }
    }
    // Frame 0: l_knee (joint 4) +90° about X.
    motion.poses[4 * 3] = quarter;
    // Frame 1: root +90° about X (SMPL's Y up → Z up, as AMASS files start).
    motion.poses[165] = quarter;
    motion.fps_key = Some("mocap_frame_rate");
    let path = dir.path().join("knee.npz");
    motion.write(&path);
    let clip = amass::read_clip(&path, Path::new("knee.npz"), &model).unwrap();
    assert_eq!(clip.fps, 120.0, "SMPL-X frame-rate key");
    let rest = model_rest();
    let pose: Pose = clip.poses[0];
    // Rx(90°) maps (x, y, z) → (x, −z, y): the shin (0, −0.4324, 0) turns to (0, 0, −0.4324),
    // the foot bone (0, 0, 0.1434) to (0, −0.1434, 0).
    let ankle = quat::add(rest[4], [0.0, 0.0, -0.432432979]);
    let foot = quat::add(ankle, [0.0, -0.143381745, 0.0]);
    close(pose[7], y_up(ankle), 1e-6, "l_ankle");
    close(pose[10], y_up(foot), 1e-6, "l_foot");
    for j in (0..NUM_JOINTS).filter(|j| ![7, 10].contains(j)) {
        close(pose[j], y_up(rest[j]), 1e-6, "unmoved joint");
    }
    // Root rotation turns about the root joint: the root stays, spine1 (0, 0.1316, 0) → (0, 0, 0.1316).
    let turned = clip.poses[1];
    close(turned[0], y_up(rest[0]), 1e-6, "root");
    close(
        turned[3],
        y_up(quat::add(rest[0], [0.0, 0.0, 0.131568253])),
        1e-6,
        "spine1",
    );
    // Facing: SMPL's forward (+Z) became AMASS's −Y, i.e. −Z after the axis change, and left
    // (+X) became −X: a proper rotation (a 180° turn about Y), not a mirror image.
    let across = quat::sub(turned[1], turned[2]);
    assert!(across[0] < 0.0, "left hip on −X: {across:?}");
}

#[test]
fn amass_betas_change_bone_lengths_through_shapedirs() {
    let dir = tempfile::tempdir().unwrap();
    let model = model(dir.path());
    let thigh = |betas: Vec<f32>| {
        let mut motion = Motion::new(1, 156);
        motion.betas = betas;
        let path = dir.path().join("shape_test.npz");
        motion.write(&path);
        let clip = amass::read_clip(&path, Path::new("s.npz"), &model).unwrap();
        quat::norm(quat::sub(clip.poses[0][4], clip.poses[0][1]))
    };
    let base = thigh(vec![0.0; 16]);
    assert!((base - 0.393623143).abs() < 1e-6, "{base}");
    // beta0 = 1 scales the body by 1.1; betas beyond the model's 2 are ignored.
    let mut sixteen = vec![5.0f32; 16];
    sixteen[0] = 1.0;
    sixteen[1] = 0.3;
    assert!((thigh(sixteen) - 1.1 * base).abs() < 1e-6);
    // Fewer betas than the model has: the rest are zero.
    assert!((thigh(vec![-1.0]) - 0.9 * base).abs() < 1e-6);
}

#[test]
fn amass_rejects_name_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let model = model(dir.path());
    let reject = |motion: Motion| {
        let path = dir.path().join("bad.npz");
        motion.write(&path);
        amass::read_clip(&path, Path::new("bad.npz"), &model).unwrap_err()
    };
    let mut m = Motion::new(3, 156);
    m.skip = Some("poses");
    let err = reject(m);
    assert!(
        err.reason.contains("no `poses` array") && err.reason.contains("bad.npz"),
        "{err}"
    );
    let mut m = Motion::new(3, 156);
    m.skip = Some("trans");
    assert!(reject(m).reason.contains("no `trans` array"));
    let mut m = Motion::new(3, 156);
    m.fps_key = None;
    let err = reject(m);
    assert!(
        err.reason.contains("mocap_framerate") && err.reason.contains("mocap_frame_rate"),
        "{err}"
    );
    let err = reject(Motion::new(3, 60));
    assert!(err.reason.contains("60 values per frame"), "{err}");
    let mut m = Motion::new(3, 156);
    m.poses[156 + 7] = f32::NAN;
    assert!(reject(m).reason.contains("frame 1: non-finite"));

    let junk = dir.path().join("junk.npz");
    std::fs::write(&junk, b"not a zip").unwrap();
    let err = amass::read_clip(&junk, Path::new("junk.npz"), &model).unwrap_err();
    assert_eq!(err.stage, "read");

    let bad_tree = dir.path().join("bad_tree.npz");
    write_model(&bad_tree, Some(7), None);
    let err = amass::BodyModel::load(&bad_tree).unwrap_err().to_string();
    assert!(err.contains("joint 5 has parent 7"), "{err}");
    let no_regressor = dir.path().join("no_regressor.npz");
    write_model(&no_regressor, None, Some("J_regressor"));
    let err = amass::BodyModel::load(&no_regressor)
        .unwrap_err()
        .to_string();
    assert!(err.contains("no `J_regressor` array"), "{err}");
}
