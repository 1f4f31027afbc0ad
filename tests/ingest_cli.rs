//! End-to-end: demo inputs and deliberately bad inputs through `motionscale ingest`,
//! `corpus verify`, `corpus stats` and the exports, checked with numpy/pyarrow.

mod common;

use common::*;
use ingest::corpus::Corpus;
use std::path::Path;

#[test]
fn demo_corpus_end_to_end_and_byte_identical_rerun() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = tmp.path().join("inputs");
    demo_inputs(&inputs);
    let corpus = tmp.path().join("corpus");
    let src = format!("bvh:{}", inputs.display());
    let run = |out: &Path| {
        motionscale(&[
            "ingest",
            "--source",
            &src,
            "--out",
            out.to_str().unwrap(),
            "--mirror",
            "--json",
        ])
    };
    let out = run(&corpus);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["inputs"], 6);
    assert_eq!(report["rejects"], 0);
    assert_eq!(report["clips"], 12, "6 clips and their mirrored copies");

    let manifest: serde_json::Value = read_json(&corpus.join("manifest.json"));
    assert_eq!(manifest["feature_convention"], "humanml3d-263");
    assert_eq!(manifest["sources"][0]["files"], 6);
    assert_eq!(manifest["sources"][0]["ingested_files"], 6);

    let verify = motionscale(&["corpus", "verify", corpus.to_str().unwrap()]);
    assert_eq!(code(&verify), 0, "{}", text(&verify));
    let stats = motionscale(&["corpus", "stats", corpus.to_str().unwrap(), "--json"]);
    assert_eq!(code(&stats), 0, "{}", text(&stats));
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert_eq!(stats["clips"], 12);
    assert_eq!(stats["by"]["mirrored"]["true"]["clips"], 6);

    // Python tools read the shards; features reshape to (n, 263).
    let counts = python(PYARROW_CHECK, &[corpus.to_str().unwrap()]);
    assert!(counts.starts_with("12 "), "{counts}");

    // Same inputs, fresh folder → identical bytes; a re-run into the same folder too.
    let again = tmp.path().join("again");
    assert_eq!(code(&run(&again)), 0);
    assert_eq!(corpus_bytes(&corpus), corpus_bytes(&again));
    assert_eq!(code(&run(&corpus)), 0);
    assert_eq!(corpus_bytes(&corpus), corpus_bytes(&again));
    // Spilling sorted runs of 2 inputs and merging them gives the same bytes too.
    let spilled = tmp.path().join("spilled");
    let out = motionscale(&[
        "ingest",
        "--source",
        &src,
        "--out",
        spilled.to_str().unwrap(),
        "--mirror",
        "--chunk-units",
        "2",
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    assert_eq!(corpus_bytes(&corpus), corpus_bytes(&spilled));
    assert!(
        !spilled.join(".ingest-runs").exists(),
        "runs are cleaned up"
    );

    // HumanML3D layout loads with numpy with the HumanML3D shapes.
    let hml = tmp.path().join("hml3d");
    let out = motionscale(&[
        "export",
        "hml3d",
        corpus.to_str().unwrap(),
        hml.to_str().unwrap(),
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let check = r##"
import sys, os, numpy as np
d = sys.argv[1]
ids = [l.strip() for f in ("train.txt", "val.txt", "test.txt") for l in open(os.path.join(d, f)) if l.strip()]
assert len(ids) == 12, ids
for i in ids:
    v = np.load(os.path.join(d, "new_joint_vecs", i + ".npy"))
    j = np.load(os.path.join(d, "new_joints", i + ".npy"))
    assert v.ndim == 2 and v.shape[1] == 263 and v.dtype == np.float32, v.shape
    assert j.shape == (v.shape[0] + 1, 22, 3), j.shape
    lines = open(os.path.join(d, "texts", i + ".txt")).read().strip().splitlines()
    assert lines and all(len(l.split("#")) == 4 for l in lines), lines
assert np.load(os.path.join(d, "Mean.npy")).shape == (263,)
assert (np.load(os.path.join(d, "Std.npy")) > 0).all()
print("ok")
"##;
    assert_eq!(python(check, &[hml.to_str().unwrap()]).trim(), "ok");

    // The export imports back (hml3d: source) with the same splits and the same features.
    let reimported = tmp.path().join("reimported");
    let out = motionscale(&[
        "ingest",
        "--source",
        &format!("hml3d:{}", hml.display()),
        "--out",
        reimported.to_str().unwrap(),
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let (a, b) = (
        Corpus::open(&corpus).unwrap(),
        Corpus::open(&reimported).unwrap(),
    );
    assert_eq!(b.clips().len(), 12);
    for id in ["demo_walk", "Mdemo_turn"] {
        let x = a.clip(a.find(id).unwrap()).unwrap();
        let y = b.clip(b.find(id).unwrap()).unwrap();
        assert_eq!(
            (x.split.as_str(), x.num_frames),
            (y.split.as_str(), y.num_frames)
        );
        let worst = x
            .features
            .iter()
            .zip(&y.features)
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-3, "{id}: re-imported features differ by {worst}");
    }

    let bvh = tmp.path().join("walk.bvh");
    let out = motionscale(&[
        "export",
        "bvh",
        corpus.to_str().unwrap(),
        "demo_walk",
        bvh.to_str().unwrap(),
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let bvh_text = std::fs::read_to_string(&bvh).unwrap();
    assert!(bvh_text.starts_with("HIERARCHY") && bvh_text.contains("Frames: "));
    let missing = motionscale(&[
        "export",
        "bvh",
        corpus.to_str().unwrap(),
        "nope",
        bvh.to_str().unwrap(),
    ]);
    assert_eq!(code(&missing), 1);
    assert!(text(&missing).contains("no clip with motion_id \"nope\""));
}

#[test]
fn bad_inputs_are_rejected_with_reasons_and_good_ones_kept() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = tmp.path().join("inputs");
    demo_inputs(&inputs);
    let good = std::fs::read_to_string(inputs.join("demo_walk.bvh")).unwrap();
    let write = |name: &str, text: &str| std::fs::write(inputs.join(name), text).unwrap();
    write("bad_truncated.bvh", &good[..good.len() * 2 / 3]);
    write(
        "bad_text_number.bvh",
        &good.replacen("0.0000 93.1404", "0.0000 abc", 1),
    );
    write(
        "bad_channels.bvh",
        &good.replacen(
            "CHANNELS 3 Zrotation Xrotation Yrotation",
            "CHANNELS 3 Zrotation Xrotation",
            1,
        ),
    );
    let header_end = good.find("Frames:").unwrap();
    write(
        "bad_zero_frames.bvh",
        &format!("{}Frames: 0\nFrame Time: 0.0333333\n", &good[..header_end]),
    );
    let mut lines: Vec<&str> = good.lines().collect();
    let first_motion = lines
        .iter()
        .position(|l| l.starts_with("Frame Time"))
        .unwrap()
        + 5;
    let nan_line = lines[first_motion].replacen("0.0000", "nan", 1);
    lines[first_motion] = &nan_line;
    write("bad_nan.bvh", &(lines.join("\n") + "\n"));
    write(
        "bad_unknown_rig.bvh",
        &good
            .replace("LeftUpLeg", "Thigh_A")
            .replace("RightUpLeg", "Thigh_B"),
    );
    std::fs::create_dir(inputs.join("bad_unreadable.bvh")).unwrap();

    let corpus = tmp.path().join("corpus");
    let out = motionscale(&[
        "ingest",
        "--source",
        &format!("bvh:{}", inputs.display()),
        "--out",
        corpus.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(code(&out), 2, "partial ingest exits 2: {}", text(&out));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let rejects = rejects(&corpus);
    assert_eq!(
        report["clips"], 6,
        "every good clip is kept; rejects: {rejects:#?}"
    );
    let reason = |file: &str| -> String {
        let r = rejects
            .iter()
            .find(|r| r["path"].as_str().unwrap().ends_with(file))
            .unwrap_or_else(|| panic!("{file} not in rejects: {rejects:?}"));
        format!(
            "{}: {}",
            r["stage"].as_str().unwrap(),
            r["reason"].as_str().unwrap()
        )
    };
    assert_eq!(rejects.len(), 7, "{rejects:#?}");
    let expect = [
        ("bad_truncated.bvh", "truncated"),
        ("bad_text_number.bvh", "abc"),
        ("bad_channels.bvh", "channel"),
        ("bad_zero_frames.bvh", "zero frames"),
        ("bad_nan.bvh", "nan"),
        ("bad_unknown_rig.bvh", "l_hip"),
        ("bad_unreadable.bvh", "directory"),
    ];
    for (file, needle) in expect {
        let r = reason(file);
        assert!(r.to_lowercase().contains(needle), "{file}: {r}");
    }
    let verify = motionscale(&["corpus", "verify", corpus.to_str().unwrap()]);
    assert_eq!(code(&verify), 0, "{}", text(&verify));
}

#[test]
fn static_and_short_clips_are_rejected_and_corruption_is_caught() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = tmp.path().join("joints");
    std::fs::create_dir_all(&inputs).unwrap();
    // A standing skeleton (HumanML3D target offsets stacked by parent) held still for 3 s.
    let mut pose = [[0f64; 3]; 22];
    for j in 1..22 {
        pose[j] = ingest::quat::add(
            pose[ingest::skeleton::PARENTS[j]],
            ingest::skeleton::TARGET_OFFSETS[j],
        );
    }
    let pose: Vec<f32> = pose.iter().flatten().map(|&v| v as f32).collect();
    let still: Vec<f32> = (0..60).flat_map(|_| pose.iter().copied()).collect();
    ingest::npy::write_f32(&inputs.join("still.npy"), &[60, 22, 3], &still).unwrap();
    let short: Vec<f32> = (0..8).flat_map(|_| pose.iter().copied()).collect();
    ingest::npy::write_f32(&inputs.join("short.npy"), &[8, 22, 3], &short).unwrap();
    let demo = tmp.path().join("demo");
    demo_inputs(&demo);
    let corpus = tmp.path().join("corpus");
    let out = motionscale(&[
        "ingest",
        "--source",
        &format!("joints:{}", inputs.display()),
        "--source",
        &format!("bvh:{}", demo.display()),
        "--out",
        corpus.to_str().unwrap(),
    ]);
    assert_eq!(code(&out), 2, "{}", text(&out));
    let rejects = rejects(&corpus);
    let find = |name: &str| {
        rejects
            .iter()
            .find(|r| r["path"].as_str().unwrap().ends_with(name))
            .unwrap()
    };
    assert!(find("still.npy")["reason"]
        .as_str()
        .unwrap()
        .starts_with("static"));
    assert!(
        !rejects
            .iter()
            .any(|r| r["path"].as_str().unwrap().contains("demo_wave")),
        "a one-arm wave is not static"
    );
    assert!(find("short.npy")["reason"]
        .as_str()
        .unwrap()
        .starts_with("too short"));

    // Flip one byte in a shard: verify names the file and fails.
    let shard = corpus.join("shards/shard-00000.parquet");
    let mut bytes = std::fs::read(&shard).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xFF;
    std::fs::write(&shard, bytes).unwrap();
    let verify = motionscale(&["corpus", "verify", corpus.to_str().unwrap()]);
    assert_eq!(code(&verify), 1);
    assert!(
        text(&verify).contains("shard-00000.parquet: sha256"),
        "{}",
        text(&verify)
    );
}

#[test]
fn synth_corpus_is_labelled_deterministic_and_rejects_bad_specs() {
    let tmp = tempfile::tempdir().unwrap();
    let build = |name: &str| {
        let dir = tmp.path().join(name);
        let out = motionscale(&[
            "synth",
            "--clips",
            "72",
            "--seed",
            "5",
            "--out",
            dir.to_str().unwrap(),
            "--mirror",
            "--json",
        ]);
        assert_eq!(code(&out), 0, "{}", text(&out));
        dir
    };
    let (a, b) = (build("a"), build("b"));
    assert_eq!(corpus_bytes(&a), corpus_bytes(&b), "same seed, same bytes");
    let stats = motionscale(&["corpus", "stats", a.to_str().unwrap(), "--json"]);
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert_eq!(stats["clips"], 144);
    // 72 consecutive clips hold every (action, emotion) pair once: 12 actions × 6 emotions.
    assert_eq!(stats["by"]["action"].as_object().unwrap().len(), 12);
    assert_eq!(stats["by"]["emotion"].as_object().unwrap().len(), 6);
    assert!(stats["by"]["scenario"].as_object().unwrap().len() >= 5);
    assert_eq!(
        code(&motionscale(&["corpus", "verify", a.to_str().unwrap()])),
        0
    );

    let bad = motionscale(&[
        "ingest",
        "--source",
        "synth:abc",
        "--out",
        tmp.path().join("c").to_str().unwrap(),
    ]);
    assert_eq!(
        code(&bad),
        1,
        "a usage error is a failure, not a partial ingest"
    );
    assert!(text(&bad).contains("clip count \"abc\""), "{}", text(&bad));
}
