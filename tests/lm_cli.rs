//! The prefix LM through the binary: synthetic corpus → fallback caption embeddings → tiny
//! tokenizer → token set → `train` → `generate` (tokens, features, BVH), and the BVH read back
//! by our own `ingest bvh:` without rejects; `model info --json` accounting; a LoRA adapter
//! trained on the model (only the adapted projections change; stopped and resumed exactly).

mod common;

use common::*;
use std::path::Path;

#[test]
fn train_then_generate_a_bvh_that_ingest_reads_back() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    tiny_lm_corpus(&corpus);
    let (run, report) = tiny_lm_run(&corpus, tmp.path());
    let report: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert_eq!(report["steps"], report["total_steps"]);
    let eval = &report["eval"];
    assert!(eval["tokens_seen"].as_u64().unwrap() >= 3000);
    assert!(eval["test"]["cross_entropy"].as_f64().unwrap().is_finite());
    assert_eq!(eval["tied"], false);
    assert_eq!(
        &read_json::<serde_json::Value>(&run.join("eval.json")),
        eval
    );

    // Every generation: the same caption and seed, written to `out`.
    let generate = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "generate",
            "--model",
            arg(&run),
            "--text",
            "a person walks forward, looking sad",
            "--seed",
            "1",
            "--out",
            arg(out),
        ];
        args.extend_from_slice(extra);
        motionscale_ok(&args);
    };
    let json = tmp.path().join("gen.json");
    generate(&json, &[]);
    let gen: serde_json::Value = read_json(&json);
    let n = gen["tokens"].as_array().unwrap().len();
    assert!(
        n > 0
            && gen["tokens"]
                .as_array()
                .unwrap()
                .iter()
                .all(|t| t.as_u64().unwrap() < 240)
    );
    // The same seed without the cache draws the same tokens.
    let again = tmp.path().join("again.json");
    generate(&again, &["--no-cache"]);
    let again: serde_json::Value = read_json(&again);
    assert_eq!(again["tokens"], gen["tokens"]);

    let npy = tmp.path().join("gen.npy");
    generate(&npy, &[]);
    let header = std::fs::read(&npy).unwrap();
    let header = String::from_utf8_lossy(&header[..128]);
    assert!(header.contains(&format!("({}, 263)", 4 * n)), "{header}");

    let bvh_dir = tmp.path().join("bvh");
    std::fs::create_dir_all(&bvh_dir).unwrap();
    generate(&bvh_dir.join("gen.bvh"), &[]);
    let back = tmp.path().join("back");
    let out = motionscale(&[
        "ingest",
        "--source",
        &format!("bvh:{}", arg(&bvh_dir)),
        "--out",
        arg(&back),
        "--min-frames",
        "4",
        "--static-threshold",
        "0",
        "--json",
    ]);
    assert_eq!(
        code(&out),
        0,
        "ingest rejected the generated BVH: {}",
        text(&out)
    );
    let rejects = std::fs::read_to_string(back.join("rejects.jsonl")).unwrap();
    assert!(rejects.trim().is_empty(), "{rejects}");

    // The same run on the graph executor (candle's autograd) ends at the same test loss, and
    // the run records where and how it trained.
    let config: serde_json::Value = read_json(&run.join("config.json"));
    assert_eq!(config["device"], "cpu");
    assert_eq!(config["train"]["compute"]["precision"], "f32");
    let tokens = tmp.path().join("tokens");
    let graph_run = tmp.path().join("graph-run");
    let train = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "train",
            "--tokens",
            arg(&tokens),
            "--preset",
            "cpu-50K",
            "--tokens-budget",
            "3000",
            "--batch",
            "8",
            "--out",
            arg(out),
            "--json",
        ];
        args.extend_from_slice(extra);
        motionscale(&args)
    };
    let graph = train(&graph_run, &["--executor", "graph"]);
    assert_eq!(code(&graph), 0, "{}", text(&graph));
    let graph: serde_json::Value =
        serde_json::from_str(&String::from_utf8_lossy(&graph.stdout)).unwrap();
    let ce = |r: &serde_json::Value| r["eval"]["test"]["cross_entropy"].as_f64().unwrap();
    assert!(
        (ce(&graph) - ce(&report)).abs() < 1e-3,
        "graph {} vs cpu {}",
        ce(&graph),
        ce(&report)
    );
    // `model loss` scores a run's final weights as training did, and an ensemble of the two
    // runs at most at the mean of their cross-entropies (the two executors' weights are close:
    // the strict inequality is lm's test, on two seeds).
    let loss = |models: &[&Path]| -> serde_json::Value {
        let mut args = vec!["model", "loss", "--json"];
        for m in models {
            args.extend(["--model", arg(m)]);
        }
        serde_json::from_str(&motionscale_ok(&args)).unwrap()
    };
    let alone = loss(&[&run])["cross_entropy"].as_f64().unwrap();
    assert!(
        (alone - ce(&report)).abs() < 1e-9,
        "{alone} vs {}",
        ce(&report)
    );
    let both = loss(&[&run, &graph_run])["cross_entropy"].as_f64().unwrap();
    assert!(both <= 0.5 * (ce(&report) + ce(&graph)) + 1e-9, "{both}");
    // No GPU in this build: a clear error, exit 1, nothing trained.
    for args in [
        vec![
            "train",
            "--tokens",
            arg(&tokens),
            "--preset",
            "cpu-50K",
            "--tokens-budget",
            "3000",
            "--out",
            arg(&tmp.path().join("gpu-run")),
            "--device",
            "cuda",
        ],
        vec![
            "generate",
            "--model",
            arg(&run),
            "--text",
            "a person walks",
            "--out",
            arg(&tmp.path().join("gpu.json")),
            "--device",
            "cuda:1",
        ],
        vec!["model", "executors", "--device", "cuda"],
    ] {
        let out = motionscale(&args);
        assert_eq!(code(&out), 1, "{args:?}: {}", text(&out));
        assert!(
            text(&out).contains("built without CUDA"),
            "{args:?}: {}",
            text(&out)
        );
        assert!(!text(&out).contains("panicked"), "{}", text(&out));
    }
    assert!(!tmp.path().join("gpu-run").exists());
}

#[test]
fn model_info_prints_the_accounting() {
    let out = motionscale_ok(&[
        "model", "info", "--preset", "343M", "--vocab", "65536", "--json",
    ]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let p = &v["accounting"]["params"];
    let (n_nv, n_v) = (p["n_nv"].as_u64().unwrap(), p["n_v"].as_u64().unwrap());
    assert_eq!(n_v, 2 * 65539 * 1024);
    assert_eq!(p["total"].as_u64().unwrap(), n_nv + n_v);
    assert_eq!(p["tied"], false);
    let six_n = v["accounting"]["flops_6n_per_token"].as_f64().unwrap();
    assert_eq!(six_n, 6.0 * (n_nv + n_v) as f64);
    assert!(v["accounting"]["flops_exact_per_token"].as_f64().unwrap() > 0.0);
}

#[test]
fn lora_trains_only_the_adapted_projections_and_resumes_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    tiny_lm_corpus(&corpus);
    let (base, _) = tiny_lm_run(&corpus, tmp.path());
    let tokens = tmp.path().join("tokens");
    let lora = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "train",
            "--tokens",
            arg(&tokens),
            "--base",
            arg(&base),
            "--lora-rank",
            "4",
            "--expert",
            "walking",
            "--tokens-budget",
            "2000",
            "--batch",
            "8",
            "--out",
            arg(out),
        ];
        args.extend_from_slice(extra);
        motionscale_ok(&args)
    };
    let (whole, split) = (tmp.path().join("whole"), tmp.path().join("split"));
    lora(&whole, &[]);
    let adapter: serde_json::Value = python(
        r#"
import json, sys
from safetensors.numpy import load_file
a = load_file(sys.argv[1])
m, b = load_file(sys.argv[2]), load_file(sys.argv[3])
print(json.dumps({"keys": sorted(a), "changed": sorted(k for k in m if (m[k] != b[k]).any())}))
"#,
        &[
            arg(&whole.join("adapter.safetensors")),
            arg(&whole.join("model.safetensors")),
            arg(&base.join("model.safetensors")),
        ],
    )
    .parse()
    .unwrap();
    let keys = adapter["keys"].as_array().unwrap();
    assert_eq!(keys.len(), 8, "A and B of 4 projections in one block");
    assert!(keys.contains(&"experts.walking.blocks.0.attn.wqkv.lora_A.weight".into()));
    let changed: Vec<&str> = adapter["changed"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(
        changed,
        [
            "blocks.0.attn.wo.weight",
            "blocks.0.attn.wqkv.weight",
            "blocks.0.ffn.w13.weight",
            "blocks.0.ffn.w2.weight"
        ],
        "only the adapted projections differ from the base"
    );
    // Started from that adapter with a zero learning rate: the adapter is kept as it was.
    let kept = tmp.path().join("kept");
    let init = whole.join("adapter.safetensors");
    lora(&kept, &["--lora-init", arg(&init), "--lr", "0"]);
    assert_eq!(
        std::fs::read(kept.join("adapter.safetensors")).unwrap(),
        std::fs::read(&init).unwrap()
    );
    // Stopped after 4 steps and resumed: the same adapter as the uninterrupted run.
    lora(&split, &["--stop-after", "4"]);
    lora(&split, &[]);
    assert_eq!(
        std::fs::read(split.join("adapter.safetensors")).unwrap(),
        std::fs::read(whole.join("adapter.safetensors")).unwrap()
    );
}
