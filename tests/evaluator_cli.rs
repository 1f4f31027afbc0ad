//! The evaluator through the binary: `evaluator train` on a synthetic corpus with fallback
//! caption embeddings, `eval` on the corpus (halves, shuffled captions, noise), on its
//! HumanML3D export (same motions → same metrics), and on motions from a tiny prefix LM
//! (`generate --captions-from`), with the recorded split, seed, repeats and hashes.

mod common;

use common::*;
use serde_json::Value;
use std::path::Path;

fn eval(evaluator: &Path, motions: &Path, out: &Path, extra: &[&str]) -> Value {
    let mut args = vec![
        "eval",
        "--evaluator",
        arg(evaluator),
        "--motions",
        arg(motions),
        "--split",
        "train",
        "--repeats",
        "3",
        "--out",
        arg(out),
    ];
    args.extend_from_slice(extra);
    motionscale_ok(&args);
    read_json(out)
}

/// `generate --captions-from` the train split of `corpus` with `model` into `out`; the
/// numbers of motions written and captions rejected.
fn generate(model: &Path, corpus: &Path, out: &Path, extra: &[&str]) -> (usize, usize) {
    let mut args = vec![
        "generate",
        "--model",
        arg(model),
        "--captions-from",
        arg(corpus),
        "--split",
        "train",
        "--out",
        arg(out),
    ];
    args.extend_from_slice(extra);
    let result = motionscale(&args);
    assert!([0, 2].contains(&code(&result)), "{}", text(&result));
    let lines = |name: &str| {
        std::fs::read_to_string(out.join(name))
            .unwrap()
            .lines()
            .count()
    };
    (lines("generated.jsonl"), lines("rejects.jsonl"))
}

fn mean(v: &Value) -> f64 {
    v["mean"]
        .as_f64()
        .unwrap_or_else(|| panic!("no mean in {v}"))
}

#[test]
fn evaluator_trains_resumes_and_scores_corpus_export_and_generated_motions() {
    let tmp = tempfile::tempdir().unwrap();
    let (corpus_dir, evaluator) = (tmp.path().join("corpus"), tmp.path().join("evaluator"));
    // 251 train clips: enough texts for pools of 32 in two halves.
    synth_corpus(&corpus_dir, 300);
    train_evaluator(&corpus_dir, &evaluator, &[]);
    for file in ["config.json", "model.safetensors", "mean.npy", "std.npy"] {
        assert!(evaluator.join(file).is_file(), "{file} missing");
    }
    let log = std::fs::read_to_string(evaluator.join("log.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 2, "{log}");
    let config: Value = read_json(&evaluator.join("config.json"));
    assert_eq!(config["format"], "motionscale-evaluator-v1");
    assert!(config["config"]["emotions"].as_array().unwrap().len() > 1);
    assert!(config["config"]["actions"].as_array().unwrap().len() > 1);
    // Re-running a finished training changes nothing.
    let weights = std::fs::read(evaluator.join("model.safetensors")).unwrap();
    train_evaluator(&corpus_dir, &evaluator, &[]);
    assert_eq!(
        std::fs::read(evaluator.join("model.safetensors")).unwrap(),
        weights
    );

    // Embeddings of every train clip: one row per motion, unit length.
    let embedded = tmp.path().join("embedded");
    motionscale_ok(&[
        "evaluator",
        "embed",
        "--evaluator",
        arg(&evaluator),
        "--motions",
        arg(&corpus_dir),
        "--split",
        "train",
        "--out",
        arg(&embedded),
    ]);
    let listed = std::fs::read_to_string(embedded.join("motions.jsonl")).unwrap();
    assert_eq!(listed.lines().count(), 251);
    for name in ["motion_embeddings.npy", "text_embeddings.npy"] {
        let bytes = std::fs::read(embedded.join(name)).unwrap();
        let header = String::from_utf8_lossy(&bytes[..128]);
        assert!(header.contains("(251, 16)"), "{name}: {header}");
    }

    // Ground truth against itself: two disjoint halves.
    let halves = eval(
        &evaluator,
        &corpus_dir,
        &tmp.path().join("halves.json"),
        &["--halves"],
    );
    assert_eq!(halves["options"]["split"], "train");
    assert_eq!(halves["options"]["seed"], 0);
    assert_eq!(halves["options"]["repeats"], 3);
    assert_eq!(halves["options"]["halves"], true);
    assert_eq!(halves["evaluator_id"].as_str().unwrap().len(), 12);
    assert_eq!(halves["corpus_id"].as_str().unwrap().len(), 12);
    assert_eq!(halves["motions_id"].as_str().unwrap().len(), 12);
    assert_eq!(halves["fid"]["values"].as_array().unwrap().len(), 3);
    assert!(mean(&halves["fid"]) >= 0.0);
    for r in halves["r_precision"].as_array().unwrap() {
        assert!((0.0..=1.0).contains(&mean(r)));
    }
    assert!(mean(&halves["r_precision"][0]) <= mean(&halves["r_precision"][2]));
    assert_eq!(halves["r_precision_chance"], 1.0 / 32.0);
    assert!(halves["multimodality"].is_null(), "one motion per text");
    let f1 = mean(&halves["emotion_weighted_f1"]);
    assert!((0.0..=1.0).contains(&f1));
    // Same seed, same numbers; another seed draws other halves.
    let again = eval(
        &evaluator,
        &corpus_dir,
        &tmp.path().join("again.json"),
        &["--halves"],
    );
    assert_eq!(again["fid"], halves["fid"]);
    let seed1 = eval(
        &evaluator,
        &corpus_dir,
        &tmp.path().join("seed1.json"),
        &["--halves", "--seed", "1"],
    );
    assert_ne!(seed1["fid"]["values"], halves["fid"]["values"]);

    // Against the reference itself FID is 0; noise moves the motions away from it.
    let own = eval(&evaluator, &corpus_dir, &tmp.path().join("own.json"), &[]);
    assert!(mean(&own["fid"]).abs() < 1e-6, "{}", own["fid"]);
    let noisy = eval(
        &evaluator,
        &corpus_dir,
        &tmp.path().join("noisy.json"),
        &["--noise", "1.0"],
    );
    assert!(mean(&noisy["fid"]) > mean(&own["fid"]));
    assert_eq!(noisy["options"]["noise"], 1.0);
    let shuffled = eval(
        &evaluator,
        &corpus_dir,
        &tmp.path().join("shuffled.json"),
        &["--shuffle-captions"],
    );
    assert_eq!(shuffled["options"]["shuffle_captions"], true);
    assert_eq!(shuffled["fid"], own["fid"], "captions do not enter FID");

    // The HumanML3D export of the same corpus scores exactly as the corpus.
    let export = tmp.path().join("hml3d");
    motionscale_ok(&["export", "hml3d", arg(&corpus_dir), arg(&export)]);
    let exported = eval(&evaluator, &export, &tmp.path().join("export.json"), &[]);
    assert_eq!(exported["motions_kind"], "hml3d");
    for key in [
        "fid",
        "r_precision",
        "matching_score",
        "diversity",
        "emotion_weighted_f1",
        "action_accuracy",
    ] {
        assert_eq!(exported[key], own[key], "{key}");
    }

    // Motions generated by a tiny prefix LM, 10 samples for two of the texts.
    let (run, _) = tiny_lm_run(&corpus_dir, tmp.path());
    let generated = tmp.path().join("generated");
    let (written, rejected) = generate(
        &run,
        &corpus_dir,
        &generated,
        &["--mm-texts", "2", "--mm-samples", "10", "--seed", "3"],
    );
    assert_eq!(
        written + rejected,
        251 + 2 * 9,
        "every caption is written or rejected"
    );
    let scored = eval(&evaluator, &generated, &tmp.path().join("gen.json"), &[]);
    assert_eq!(scored["motions_kind"], "hml3d");
    assert!(mean(&scored["fid"]) > 0.0);
    assert!(scored["multimodality_groups"].as_u64().unwrap() >= 1);
    assert!(mean(&scored["multimodality"]) >= 0.0);
    assert!(scored["group_count"].as_u64().unwrap() <= 251);

    // One scenario dataset: a LoRA trained on its clips, generating its captions, scored
    // against its own ground truth.
    let scenarios = tmp.path().join("scenarios");
    motionscale_ok(&[
        "scenarios",
        "--corpus",
        arg(&corpus_dir),
        "--split",
        "unseen",
        "--out",
        arg(&scenarios),
    ]);
    let loco = scenarios.join("D06_locomotion");
    let listed = std::fs::read_to_string(loco.join("train.txt")).unwrap();
    let n = listed.lines().count();
    let expert = tmp.path().join("expert");
    motionscale_ok(&[
        "train",
        "--tokens",
        arg(&tmp.path().join("tokens")),
        "--base",
        arg(&run),
        "--splits",
        arg(&loco),
        "--lora-rank",
        "2",
        "--tokens-budget",
        "500",
        "--batch",
        "8",
        "--out",
        arg(&expert),
    ]);
    let config: Value = read_json(&expert.join("config.json"));
    assert_eq!(config["train"]["splits"], arg(&loco));
    let loco_gen = tmp.path().join("loco-generated");
    let (written, rejected) = generate(
        &expert,
        &corpus_dir,
        &loco_gen,
        &["--splits", arg(&loco), "--mm-texts", "0"],
    );
    assert_eq!(written + rejected, n);
    let scored = eval(
        &evaluator,
        &loco_gen,
        &tmp.path().join("loco.json"),
        &["--splits", arg(&loco)],
    );
    assert_eq!(scored["reference_count"].as_u64().unwrap() as usize, n);
    assert_eq!(scored["group_count"].as_u64().unwrap() as usize, written);
    assert_eq!(scored["options"]["splits"], arg(&loco));
}
