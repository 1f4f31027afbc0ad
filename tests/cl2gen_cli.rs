//! `motionscale cl2gen` on a synthetic corpus: class-incremental tasks of two classes, replay
//! counts (generated and real), the offline reference, the per-class accuracy plot, and a
//! re-run that resumes to the same summary.

mod common;

use common::*;
use serde_json::Value;
use std::path::Path;

fn cl2gen(corpus: &Path, evaluator: &Path, out: &Path, extra: &[&str]) -> Value {
    let mut args = vec![
        "cl2gen",
        "--corpus",
        arg(corpus),
        "--evaluator",
        arg(evaluator),
        "--min-clips",
        "10",
        "--layers",
        "1",
        "--hidden",
        "8",
        "--latent",
        "4",
        "--steps-per-task",
        "3",
        "--batch",
        "4",
        "--samples-per-class",
        "4",
        "--min-frames",
        "12",
        "--max-frames",
        "20",
        "--out",
        arg(out),
    ];
    if !extra.contains(&"--repeats") {
        args.extend_from_slice(&["--repeats", "3"]);
    }
    args.extend_from_slice(extra);
    motionscale_ok(&args);
    read_json(&out.join("summary.json"))
}

fn replayed(report: &Value) -> Vec<u64> {
    report["evals"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["replayed"].as_u64().unwrap())
        .collect()
}

#[test]
fn cl2gen_learns_tasks_of_two_classes_with_replay_and_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    synth_corpus(&corpus, 300);
    let evaluator = tmp.path().join("evaluator");
    train_evaluator(&corpus, &evaluator, &[]);

    let gen = tmp.path().join("gen");
    let report = cl2gen(&corpus, &evaluator, &gen, &["--replay", "1/5", "--aux"]);
    let tasks = report["tasks"].as_array().unwrap();
    let classes = report["config"]["model"]["classes"]
        .as_array()
        .unwrap()
        .len();
    assert!(classes >= 4, "{classes} classes");
    assert_eq!(tasks.len(), classes.div_ceil(2));
    assert!(tasks.iter().all(|t| t.as_array().unwrap().len() <= 2));
    let evals = report["evals"].as_array().unwrap();
    for (k, e) in evals.iter().enumerate() {
        assert_eq!(
            e["seen"].as_array().unwrap().len(),
            (2 * (k + 1)).min(classes)
        );
        assert_eq!(e["class_accuracy"].as_array().unwrap().len(), classes);
        let accuracy = e["accuracy"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&accuracy));
        assert!(e["fid"].as_f64().unwrap().is_finite());
        assert!(
            e["loss"]["aux"].as_f64().unwrap() > 0.0,
            "the auxiliary loss is on"
        );
    }
    // Task 1 replays nothing; task k replays 1/5 of its clips for each of the 2(k−1)
    // earlier classes, so the count grows with k.
    let counts = replayed(&report);
    assert_eq!(counts[0], 0);
    assert!(counts[1] > 0 && counts[1] % 2 == 0, "{counts:?}");
    assert!(counts[2] > counts[1], "{counts:?}");
    assert!(gen.join("accuracy.svg").is_file() && gen.join("accuracy.png").is_file());
    assert!(gen.join("task-1/model.safetensors").is_file());
    // The final model and the real windows over 3 evaluation repeats: mean inside its interval.
    for key in ["final_intervals", "ground_truth_intervals"] {
        let accuracy = &report[key]["accuracy"];
        assert_eq!(accuracy["values"].as_array().unwrap().len(), 3, "{key}");
        let (low, mean, high) = (
            accuracy["low"].as_f64().unwrap(),
            accuracy["mean"].as_f64().unwrap(),
            accuracy["high"].as_f64().unwrap(),
        );
        assert!(
            low <= mean && mean <= high && high <= 1.5,
            "{key}: {accuracy}"
        );
    }
    // A re-run finds every task done and writes the same summary.
    let first = std::fs::read(gen.join("summary.json")).unwrap();
    cl2gen(&corpus, &evaluator, &gen, &["--replay", "1/5", "--aux"]);
    assert_eq!(std::fs::read(gen.join("summary.json")).unwrap(), first);
    // Another repeat count only re-evaluates the finished run.
    let again = cl2gen(
        &corpus,
        &evaluator,
        &gen,
        &["--replay", "1/5", "--aux", "--repeats", "2"],
    );
    assert_eq!(again["evals"], report["evals"]);
    let values = |r: &Value| {
        r["final_intervals"]["accuracy"]["values"]
            .as_array()
            .unwrap()
            .clone()
    };
    assert_eq!(values(&again)[..], values(&report)[..2]);

    // Real replay draws the same counts from the corpus; no replay draws none.
    let real = cl2gen(
        &corpus,
        &evaluator,
        &tmp.path().join("real"),
        &["--replay", "1/5", "--replay-source", "real"],
    );
    assert_eq!(replayed(&real), counts);
    let none = cl2gen(&corpus, &evaluator, &tmp.path().join("none"), &[]);
    assert!(replayed(&none).iter().all(|&c| c == 0));

    // Offline: one task of every class.
    let offline = cl2gen(
        &corpus,
        &evaluator,
        &tmp.path().join("offline"),
        &["--offline"],
    );
    assert_eq!(offline["tasks"].as_array().unwrap().len(), 1);
    assert_eq!(
        offline["evals"][0]["seen"].as_array().unwrap().len(),
        classes
    );

    // compare: one row per experiment, labelled by its replay, with the evaluator's id; a run
    // of another evaluator is refused.
    let (real_dir, none_dir) = (tmp.path().join("real"), tmp.path().join("none"));
    let table = motionscale_ok(&[
        "cl2gen",
        "compare",
        arg(&gen),
        arg(&real_dir),
        arg(&none_dir),
    ]);
    let id = report["evaluator_id"].as_str().unwrap();
    assert_eq!(id.len(), 12, "{report}");
    for row in [
        "| gen 1/5 + aux | 1 |",
        "| real 1/5 | 1 |",
        "| no replay | 1 |",
    ] {
        assert!(table.contains(row), "{row}: {table}");
    }
    assert!(table.contains(&format!("| {id} |")), "{table}");
    let other = tmp.path().join("other-evaluator");
    std::fs::create_dir_all(&other).unwrap();
    let mut summary = none.clone();
    summary["evaluator_id"] = Value::from("000000000000");
    std::fs::write(other.join("summary.json"), summary.to_string()).unwrap();
    let out = motionscale(&["cl2gen", "compare", arg(&none_dir), arg(&other)]);
    assert_eq!(code(&out), 1);
    assert!(
        text(&out).contains("different evaluators"),
        "{}",
        text(&out)
    );

    let out = motionscale(&[
        "cl2gen",
        "--corpus",
        arg(&corpus),
        "--evaluator",
        arg(&evaluator),
        "--replay",
        "1/x",
        "--out",
        arg(&tmp.path().join("bad")),
    ]);
    assert_eq!(code(&out), 1);
    assert!(text(&out).contains("--replay"), "{}", text(&out));
}
