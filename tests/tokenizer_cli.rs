//! Motion tokenizers through the binary: train → eval → tokenize → decode on a small synthetic
//! corpus, kill-and-resume equality, the codebook sweep's tables, and the checkpoint as other
//! tools (numpy safetensors, pyarrow) read it.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// 40 synthetic clips + mirrors.
fn synth_corpus(tmp: &Path) -> PathBuf {
    let dir = tmp.join("corpus");
    let out = motionscale(&[
        "synth",
        "--clips",
        "40",
        "--seed",
        "5",
        "--out",
        dir.to_str().unwrap(),
        "--mirror",
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    dir
}

/// Tiny training flags: small batches (the width is chosen per test).
const TINY: [&str; 8] = [
    "--batch",
    "8",
    "--lr",
    "2e-3",
    "--eval-every",
    "4",
    "--seed",
    "3",
];

fn train_args<'a>(
    corpus: &'a str,
    quantizer: &'a str,
    codebook: &'a str,
    steps: &'a str,
    width: &'a str,
    out: &'a str,
) -> Vec<&'a str> {
    let mut args = vec![
        "tokenizer",
        "train",
        "--corpus",
        corpus,
        "--quantizer",
        quantizer,
        "--codebook",
        codebook,
        "--steps",
        steps,
        "--width",
        width,
        "--out",
        out,
    ];
    args.extend(TINY);
    args
}

fn json(out: &std::process::Output) -> serde_json::Value {
    assert_eq!(code(out), 0, "{}", text(out));
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {}", text(out)))
}

#[test]
fn train_eval_tokenize_decode_round_trip() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = synth_corpus(tmp.path());
    let c = corpus.to_str().unwrap();
    let tok = tmp.path().join("fsq");
    let t = tok.to_str().unwrap();
    let out = motionscale(&train_args(c, "fsq", "256", "12", "16", t));
    assert_eq!(code(&out), 0, "{}", text(&out));
    let log = std::fs::read_to_string(tok.join("log.jsonl")).unwrap();
    assert_eq!(
        log.lines().count(),
        3,
        "validation at steps 4, 8, 12:\n{log}"
    );

    let report = json(&motionscale(&[
        "tokenizer",
        "eval",
        "--tokenizer",
        t,
        "--corpus",
        c,
        "--split",
        "test",
    ]));
    assert_eq!(report["quantizer"], "fsq");
    assert_eq!(report["codebook_size"], 240, "FSQ 2^8 is [8, 6, 5]");
    let tokens = report["tokens"].as_u64().unwrap();
    assert!(tokens > 0 && report["frames"].as_u64().unwrap() == 4 * tokens);
    let used = report["used_codes"].as_u64().unwrap() as f64;
    assert!((report["utilization"].as_f64().unwrap() - used / 240.0).abs() < 1e-12);
    let entropy = report["entropy"].as_f64().unwrap();
    assert!((report["perplexity"].as_f64().unwrap() - entropy.exp()).abs() < 1e-9);
    let mpjpe = report["mpjpe_mm"].as_f64().unwrap();
    let mpjpe_root = report["mpjpe_root_mm"].as_f64().unwrap();
    assert!(mpjpe.is_finite() && mpjpe > 0.0);
    assert!(mpjpe_root.is_finite() && mpjpe_root > 0.0);
    // The coverage a uniform tokenizer reaches with as many tokens: 1 − e^(−N/K).
    let per_code = tokens as f64 / 240.0;
    assert!((report["tokens_per_code"].as_f64().unwrap() - per_code).abs() < 1e-12);
    let uniform = report["uniform_coverage"].as_f64().unwrap();
    assert!((uniform - (1.0 - (-per_code).exp())).abs() < 1e-12);

    let set = tmp.path().join("tokens");
    let out = motionscale(&[
        "tokenize",
        "--tokenizer",
        t,
        "--corpus",
        c,
        "--out",
        set.to_str().unwrap(),
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    // pyarrow reads the token table; unigram counts add up to the tokens of each split.
    let checked = python(
        r#"
import sys, json, pyarrow.parquet as pq
t = pq.read_table(sys.argv[1] + '/tokens.parquet')
u = json.load(open(sys.argv[1] + '/unigram.json'))
rows = list(zip(t.column('tokens').to_pylist(), t.column('split').to_pylist()))
for split in ('train', 'test'):
    n = sum(len(x) for x, s in rows if s == split)
    assert n == sum(u['counts'][split]), (split, n)
assert max(max(x) for x, _ in rows if x) < u['vocab_size']
print(sum(len(x) for x, s in rows if s == 'test'))
"#,
        &[set.to_str().unwrap()],
    );
    assert_eq!(checked.trim().parse::<u64>().unwrap(), tokens);

    // Decoding the test split's tokens reproduces the eval's MPJPE.
    let decoded = tmp.path().join("decoded");
    let out = motionscale(&[
        "tokenizer",
        "decode",
        "--tokenizer",
        t,
        "--tokens",
        set.to_str().unwrap(),
        "--split",
        "test",
        "--corpus",
        c,
        "--out",
        decoded.to_str().unwrap(),
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    assert!(
        text(&out).contains(&format!(
            "{mpjpe_root:.3} mm root-aligned, {mpjpe:.3} mm global"
        )),
        "eval said {mpjpe_root:.3} / {mpjpe:.3} mm; decode said:\n{}",
        text(&out)
    );
    let id = std::fs::read_dir(&decoded)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let id = id.file_stem().unwrap().to_str().unwrap().to_string();
    let bvh = tmp.path().join("clip.bvh");
    let out = motionscale(&[
        "tokenizer",
        "decode",
        "--tokenizer",
        t,
        "--tokens",
        set.to_str().unwrap(),
        "--motion-id",
        &id,
        "--out",
        bvh.to_str().unwrap(),
    ]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    assert!(std::fs::read_to_string(&bvh)
        .unwrap()
        .starts_with("HIERARCHY"));

    // The checkpoint as numpy's safetensors reader sees it: the documented keys and shapes.
    let keys = python(
        r#"
import sys, numpy as np
from safetensors.numpy import load_file
s = load_file(sys.argv[1] + '/model.safetensors')
assert s['encoder.net.0.weight'].shape == (16, 263, 3)
assert s['quant.proj_in.weight'].shape == (3, 16)
assert list(s['quant.L']) == [8, 6, 5] and list(s['quant.basis']) == [1, 8, 48]
assert np.load(sys.argv[1] + '/mean.npy').shape == (263,)
print(' '.join(sorted(s)))
"#,
        &[t],
    );
    let keys: Vec<&str> = keys.split_whitespace().collect();
    for prefix in [
        "encoder.net.3.units.2.conv1.weight",
        "decoder.net.10.bias",
        "quant.half_l",
        "quant.shift",
    ] {
        assert!(keys.contains(&prefix), "{prefix} missing from {keys:?}");
    }
    assert_eq!(keys.len(), 76, "{keys:?}");
}

#[test]
fn a_killed_run_resumes_to_the_uninterrupted_result() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = synth_corpus(tmp.path());
    let c = corpus.to_str().unwrap();
    let straight = tmp.path().join("straight");
    let resumed = tmp.path().join("resumed");
    let mut args = train_args(c, "vq", "64", "40", "32", straight.to_str().unwrap());
    args.extend(["--checkpoint-every", "2"]);
    let out = motionscale(&args);
    assert_eq!(code(&out), 0, "{}", text(&out));

    // Kill the same run (SIGKILL) as soon as it has written a checkpoint, then rerun it.
    let mut args = train_args(c, "vq", "64", "40", "32", resumed.to_str().unwrap());
    args.extend(["--checkpoint-every", "2"]);
    let mut child = Command::new(env!("CARGO_BIN_EXE_motionscale"))
        .args(&args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let state = resumed.join("state.json");
    let deadline = Instant::now() + Duration::from_secs(120);
    while !state.exists() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let killed_at: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&state).unwrap()).unwrap();
    assert!(
        killed_at["step"].as_u64().unwrap() < 40,
        "the run finished before it was killed"
    );
    let out = motionscale(&args);
    assert_eq!(code(&out), 0, "{}", text(&out));
    for file in ["model.safetensors", "resume/40/optimizer.safetensors"] {
        assert!(
            std::fs::read(straight.join(file)).unwrap()
                == std::fs::read(resumed.join(file)).unwrap(),
            "{file} differs after resuming from step {}",
            killed_at["step"]
        );
    }
    // A different setting in the same folder is refused, not mixed in.
    let mut other = train_args(c, "vq", "64", "41", "32", resumed.to_str().unwrap());
    other.extend(["--checkpoint-every", "2"]);
    let out = motionscale(&other);
    assert_eq!(code(&out), 1);
    assert!(text(&out).contains("train.json"), "{}", text(&out));
}

#[test]
fn sweep_writes_a_table_that_pyarrow_reads() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = synth_corpus(tmp.path());
    let out_dir = tmp.path().join("sweep");
    let mut args = vec![
        "tokenizer",
        "sweep",
        "--corpus",
        corpus.to_str().unwrap(),
        "--quantizers",
        "fsq,vq",
        "--codebooks",
        "256,1024",
        "--steps",
        "4",
        "--width",
        "16",
        "--out",
        out_dir.to_str().unwrap(),
    ];
    args.extend(TINY);
    let out = motionscale(&args);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let table = python(
        r#"
import sys, pyarrow.parquet as pq
t = pq.read_table(sys.argv[1] + '/sweep.parquet').to_pylist()
for r in t:
    assert 0 < r['utilization'] <= 1 and r['mpjpe_mm'] > 0 and r['steps'] == 4, r
print(' '.join(f"{r['quantizer']}:{r['codebook']}:{r['codebook_size']}" for r in t))
"#,
        &[out_dir.to_str().unwrap()],
    );
    assert_eq!(
        table.trim(),
        "fsq:256:240 fsq:1024:1000 vq:256:256 vq:1024:1024"
    );
    let csv = std::fs::read_to_string(out_dir.join("sweep.csv")).unwrap();
    assert!(csv.starts_with(
        "quantizer,codebook,codebook_size,utilization,perplexity,entropy,recon_l1,mpjpe_mm"
    ));
    assert_eq!(csv.lines().count(), 5);
    // Re-running finds every run done and gives the same table.
    let again = motionscale(&args);
    assert_eq!(code(&again), 0, "{}", text(&again));
    assert_eq!(
        std::fs::read_to_string(out_dir.join("sweep.csv")).unwrap(),
        csv
    );
}
