//! `embed-text` through the binary on a machine without the fetched encoder (an empty
//! `MOTIONSCALE_CACHE`): it stops with exit 1 and names the fetch script, writes no
//! embeddings, and embeds with the untrained table only when `--fallback` is given.

mod common;

use common::*;
use std::path::Path;
use std::process::{Command, Output};

/// `motionscale embed-text ARGS` with the encoder cache pointed at `cache`.
fn embed_text(cache: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_motionscale"))
        .arg("embed-text")
        .args(args)
        .env("MOTIONSCALE_CACHE", cache)
        .output()
        .expect("motionscale runs")
}

#[test]
fn embed_text_without_an_encoder_refuses_unless_fallback() {
    let tmp = tempfile::tempdir().unwrap();
    let (corpus, cache) = (tmp.path().join("corpus"), tmp.path().join("empty-cache"));
    std::fs::create_dir(&cache).unwrap();
    motionscale_ok(&[
        "synth",
        "--clips",
        "8",
        "--seed",
        "1",
        "--out",
        arg(&corpus),
    ]);

    let refused = embed_text(&cache, &["--corpus", arg(&corpus)]);
    let message = text(&refused);
    assert_eq!(code(&refused), 1, "{message}");
    assert!(
        message.contains("scripts/fetch-text-encoder.sh")
            && message.contains("--fallback")
            && message.contains(arg(&cache.join("all-MiniLM-L6-v2"))),
        "the refusal names the fetch script, the folder looked in and --fallback: {message}"
    );
    assert!(
        !corpus.join("text").exists(),
        "a refused run writes no embeddings"
    );

    let fallback = embed_text(
        &cache,
        &[
            "--corpus",
            arg(&corpus),
            "--fallback",
            "--fallback-dim",
            "16",
            "--json",
        ],
    );
    assert_eq!(code(&fallback), 0, "{}", text(&fallback));
    let report: serde_json::Value = serde_json::from_slice(&fallback.stdout).unwrap();
    assert_eq!(report["dim"], 16);
    assert!(report["embedded"].as_u64().unwrap() > 0, "{report}");
    assert_eq!(report["embedded"], report["captions"]);
}
