//! `--device` through the binary: every command that trains or runs the evaluator, a text
//! encoder, the tokenizer or BI-CTVAE takes it; a GPU asked of a build without CUDA is a clear
//! error (exit 1, nothing written), and an unknown device a usage error naming the choices.

mod common;

use common::*;

/// The commands that take `--device`, with what they need besides it to get past parsing.
const COMMANDS: [&[&str]; 14] = [
    &["tokenizer", "train"],
    &["tokenizer", "eval"],
    &["tokenizer", "decode"],
    &["tokenizer", "sweep"],
    &["tokenize"],
    &["evaluator", "train"],
    &["evaluator", "embed"],
    &["eval"],
    &["embed-text"],
    &["cl2gen"],
    &["bench", "tokenizer"],
    &["bench", "evaluator"],
    &["bench", "embed"],
    &["bench", "ctvae"],
];

#[test]
fn an_unknown_device_is_a_usage_error_naming_the_choices() {
    for command in COMMANDS {
        let args = [command, &["--device", "bogus"]].concat();
        let out = motionscale(&args);
        let message = text(&out);
        assert_eq!(code(&out), 1, "{args:?}: {message}");
        assert!(
            message.contains("invalid value 'bogus' for '--device")
                && message.contains("expected cpu, cuda or cuda:N"),
            "{args:?}: {message}"
        );
    }
}

#[cfg(not(feature = "cuda"))]
#[test]
fn a_gpu_without_cuda_is_a_clear_error_before_any_work() {
    let tmp = tempfile::tempdir().unwrap();
    let (corpus, out) = (tmp.path().join("corpus"), tmp.path().join("out"));
    let files = ["--corpus", arg(&corpus), "--out", arg(&out)];
    let runs: [(&[&str], &str); 3] = [
        (&["tokenizer", "train", "--quantizer", "fsq"], "cuda"),
        (&["evaluator", "train"], "cuda"),
        (&["evaluator", "train"], "cuda:1"),
    ];
    for (command, device) in runs {
        let args = [command, &files, &["--device", device]].concat();
        let result = motionscale(&args);
        let message = text(&result);
        assert_eq!(code(&result), 1, "{args:?}: {message}");
        assert!(
            message.contains("built without CUDA"),
            "{args:?}: {message}"
        );
        assert!(message.contains("--device cpu"), "{args:?}: {message}");
        assert!(!message.contains("panicked"), "{args:?}: {message}");
        assert!(!out.exists(), "{args:?} wrote its output");
    }
}

/// Rewrite the `device` field of the JSON file at `path` (`None`: remove it, as in files
/// written before it existed).
fn set_device(path: &std::path::Path, device: Option<&str>) {
    let mut json: serde_json::Value = read_json(path);
    let fields = json.as_object_mut().expect("a JSON object");
    match device {
        Some(d) => fields.insert("device".into(), d.into()),
        None => fields.remove("device"),
    };
    std::fs::write(path, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
}

#[test]
fn the_device_is_recorded_and_a_resume_may_change_it() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    synth_corpus(&corpus, 40);
    let (tok, evaluator) = (tmp.path().join("tok"), tmp.path().join("evaluator"));
    let tokenizer_run = [
        "tokenizer",
        "train",
        "--corpus",
        arg(&corpus),
        "--quantizer",
        "fsq",
        "--codebook",
        "256",
        "--width",
        "16",
        "--batch",
        "4",
        "--steps",
        "2",
        "--out",
        arg(&tok),
        "--device",
        "cpu",
    ];
    motionscale_ok(&tokenizer_run);
    let spec = tok.join("train.json");
    assert_eq!(read_json::<serde_json::Value>(&spec)["device"], "cpu");
    // A finished run from before the field, or trained on a GPU, is the same run on the CPU,
    // and keeps the device it trained on.
    for earlier in [None, Some("cuda:0")] {
        set_device(&spec, earlier);
        motionscale_ok(&tokenizer_run);
        let device = &read_json::<serde_json::Value>(&spec)["device"];
        assert_eq!(device.as_str(), earlier, "{}", spec.display());
    }

    // An evaluator started on a GPU goes on on the CPU; once finished, its config.json (and
    // so its content id) stays as it is.
    train_evaluator(&corpus, &evaluator, &["--stop-after", "15"]);
    let config = evaluator.join("config.json");
    assert_eq!(read_json::<serde_json::Value>(&config)["device"], "cpu");
    set_device(&config, Some("cuda:0"));
    train_evaluator(&corpus, &evaluator, &["--device", "cpu"]);
    assert_eq!(read_json::<serde_json::Value>(&config)["device"], "cpu");
    let finished = std::fs::read(&config).unwrap();
    train_evaluator(&corpus, &evaluator, &["--device", "cpu"]);
    assert_eq!(std::fs::read(&config).unwrap(), finished);
    let report = tmp.path().join("eval.json");
    motionscale_ok(&[
        "eval",
        "--evaluator",
        arg(&evaluator),
        "--motions",
        arg(&corpus),
        "--split",
        "train",
        "--repeats",
        "1",
        "--out",
        arg(&report),
        "--device",
        "cpu",
    ]);
    assert_eq!(read_json::<serde_json::Value>(&report)["device"], "cpu");
}
