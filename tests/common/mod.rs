//! Helpers shared by the end-to-end tests: the binary, the shared data folder, Python checks.

#![allow(dead_code)] // each test binary uses a different subset of these helpers

mod skip;

pub use skip::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Run the motionscale binary with arguments.
pub fn motionscale(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_motionscale"))
        .args(args)
        .output()
        .expect("motionscale runs")
}

/// Run the motionscale binary, panic with its output unless it exits 0, return its stdout.
pub fn motionscale_ok(args: &[&str]) -> String {
    let out = motionscale(args);
    assert_eq!(code(&out), 0, "{args:?}: {}", text(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Parse the JSON file at `p` (panics naming the file).
pub fn read_json<T: serde::de::DeserializeOwned>(p: &Path) -> T {
    let text = std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// A path as a command-line argument (tests use UTF-8 temporary paths).
pub fn arg(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// Exit code of a finished command, with its output in the panic message if it was killed.
pub fn code(out: &Output) -> i32 {
    out.status
        .code()
        .unwrap_or_else(|| panic!("killed: {}", text(out)))
}

/// Assert that a finished command exited 1 and said `needle` (stdout or stderr).
pub fn fails_with(out: &Output, needle: &str) {
    assert_eq!(code(out), 1, "{}", text(out));
    assert!(text(out).contains(needle), "{}", text(out));
}

/// stdout and stderr of a command as text.
pub fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// Write the built-in demo BVH inputs into `dir` (panics with the output on failure).
pub fn demo_inputs(dir: &Path) {
    let out = motionscale(&["demo", "--out", dir.to_str().expect("utf-8 path")]);
    assert_eq!(code(&out), 0, "{}", text(&out));
}

/// `../shared/data`, or `None` (a recorded skip) when it is missing; fails when [`strict`].
pub fn shared_data() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if dir.is_dir() {
        return Some(dir);
    }
    not_run(&format!("the shared data {} is missing", dir.display()));
    None
}

/// Run a Python snippet (numpy/pyarrow checks of our files); panics with its output on failure.
pub fn python(script: &str, args: &[&str]) -> String {
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("python3 runs");
    assert!(out.status.success(), "python check failed:\n{}", text(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// `sweep plan` on `corpus` for `budgets` × `models` × `vocabs` (tokenizers of width 32 trained
/// 30 steps, when it runs), plus `extra`; returns its output.
pub fn sweep_plan(
    corpus: &Path,
    budgets: &str,
    models: &str,
    vocabs: &str,
    extra: &[&str],
    out: &Path,
) -> String {
    let mut args = vec![
        "sweep",
        "plan",
        "--corpus",
        arg(corpus),
        "--budgets",
        budgets,
        "--models",
        models,
        "--vocabs",
        vocabs,
        "--tokenizer-flags=--width 32 --batch 8 --steps 30",
        "--out",
        arg(out),
    ];
    args.extend_from_slice(extra);
    motionscale_ok(&args)
}

/// Read `rejects.jsonl` as JSON values.
pub fn rejects(corpus: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(corpus.join("rejects.jsonl"))
        .expect("rejects.jsonl")
        .lines()
        .map(|l| serde_json::from_str(l).expect("reject line is JSON"))
        .collect()
}

/// Bytes of every shard file and the manifest, for determinism checks.
pub fn corpus_bytes(corpus: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(corpus.join("shards"))
        .expect("shards folder")
        .map(|e| e.expect("entry").path())
        .collect();
    files.push(corpus.join("manifest.json"));
    files.push(corpus.join("stats/mean.npy"));
    files.push(corpus.join("stats/std.npy"));
    files.sort();
    files
        .into_iter()
        .map(|p| {
            let name = p
                .strip_prefix(corpus)
                .expect("inside")
                .display()
                .to_string();
            (name, std::fs::read(&p).expect("readable"))
        })
        .collect()
}

/// Python that reads every shard with pyarrow and checks the feature and joint shapes.
pub const PYARROW_CHECK: &str = r#"
import json, sys, numpy as np, pyarrow.parquet as pq
corpus = sys.argv[1]
manifest = json.load(open(f"{corpus}/manifest.json"))
rows = frames = 0
for shard in manifest["shards"]:
    t = pq.read_table(f"{corpus}/{shard['file']}")
    assert t.num_rows == shard["rows"], (shard, t.num_rows)
    for n, f, j in zip(t.column("num_frames").to_pylist(), t.column("features").to_pylist(), t.column("joints").to_pylist()):
        assert np.asarray(f, dtype=np.float32).reshape(-1, 263).shape == (n, 263)
        assert np.asarray(j, dtype=np.float32).reshape(-1, 22, 3).shape == (n + 1, 22, 3)
        frames += n
    all_feats = t.column("features").combine_chunks().flatten().to_numpy().reshape(-1, 263)
    assert np.isfinite(all_feats).all()
    rows += t.num_rows
print(rows, frames)
"#;

/// A 40-clip synthetic corpus with 32-d fallback caption embeddings in `dir`: the smallest
/// input the prefix LM trains on (sweep tests).
pub fn tiny_lm_corpus(dir: &Path) {
    synth_corpus(dir, 40);
}

/// A `clips`-clip synthetic corpus (seed 2) with 32-d fallback caption embeddings in `dir`.
pub fn synth_corpus(dir: &Path, clips: usize) {
    let (path, clips) = (dir.to_str().expect("utf-8 path"), clips.to_string());
    for args in [
        &["synth", "--clips", &clips, "--seed", "2", "--out", path][..],
        &[
            "embed-text",
            "--corpus",
            path,
            "--fallback",
            "--fallback-dim",
            "32",
        ][..],
    ] {
        let out = motionscale(args);
        assert_eq!(code(&out), 0, "{args:?}: {}", text(&out));
    }
}

/// A tiny prefix LM on `corpus` (FSQ 2^8 tokenizer of width 32 trained 6 steps, its token
/// set, `cpu-50K` trained on 3,000 tokens) in `dir/{tok,tokens,run}`; returns the run folder
/// and the `train --json` report.
pub fn tiny_lm_run(corpus: &Path, dir: &Path) -> (PathBuf, String) {
    let (tok, tokens, run) = (dir.join("tok"), dir.join("tokens"), dir.join("run"));
    motionscale_ok(&[
        "tokenizer",
        "train",
        "--corpus",
        arg(corpus),
        "--quantizer",
        "fsq",
        "--codebook",
        "256",
        "--steps",
        "6",
        "--width",
        "32",
        "--batch",
        "8",
        "--out",
        arg(&tok),
    ]);
    motionscale_ok(&[
        "tokenize",
        "--tokenizer",
        arg(&tok),
        "--corpus",
        arg(corpus),
        "--out",
        arg(&tokens),
    ]);
    let report = motionscale_ok(&[
        "train",
        "--tokens",
        arg(&tokens),
        "--preset",
        "cpu-50K",
        "--vocab",
        "240",
        "--tokens-budget",
        "3000",
        "--batch",
        "8",
        "--out",
        arg(&run),
        "--json",
    ]);
    (run, report)
}

/// A tiny evaluator (width 16, 30 steps) on `corpus` in `out`; returns the command's output.
pub fn train_evaluator(corpus: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec![
        "evaluator",
        "train",
        "--corpus",
        arg(corpus),
        "--out",
        arg(out),
        "--hidden",
        "16",
        "--embed-dim",
        "16",
        "--max-frames",
        "64",
        "--batch",
        "16",
        "--steps",
        "30",
        "--eval-every",
        "15",
    ];
    args.extend_from_slice(extra);
    motionscale_ok(&args)
}
