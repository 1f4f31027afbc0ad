//! Training the prefix LM end to end on a tiny synthetic corpus: a tiny model overfits 8
//! clips, an interrupted run resumes to the same weights, and a context-free model that
//! predicts the train unigram scores a normalised loss of 0.

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use ingest::pipeline::{ingest, IngestOptions};
use lm::lm_data::{Limits, LmData};
use lm::test_loss::{evaluate, evaluate_ensemble};
use lm::train::{load_model, train, ModelShape, TrainConfig, TrainReport};
use lm::{PrefixLm, PrefixLmConfig};
use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use text::{embed_corpus, FallbackEncoder};
use tokenizer::{TokenClip, TokenSet, TokenizerInfo};

const CODES: usize = 16;

/// A synthetic corpus of 24 clips with fallback caption embeddings (width 16), and a token
/// set over it: 8 train clips with pairwise distinct captions and seeded random tokens, the
/// others test clips.
fn fixture(root: &Path) -> (PathBuf, PathBuf) {
    let corpus = root.join("corpus");
    ingest(
        &["synth:24:5".parse().unwrap()],
        &corpus,
        &IngestOptions::default(),
        &|_, _| {},
    )
    .unwrap();
    let encoder = FallbackEncoder::for_corpus(&corpus, 16, 1).unwrap();
    embed_corpus(&corpus, &encoder, 16, &|_, _| {}).unwrap();
    let captions = text::embed::clip_captions(&corpus).unwrap();
    let mut ids: Vec<&String> = captions.keys().collect();
    ids.sort();
    let mut seen = BTreeSet::new();
    let mut rng = motionscale_core::rng::SplitMix64(7);
    let mut clips = Vec::new();
    for id in ids {
        let distinct = captions[id].iter().all(|c| !seen.contains(c));
        let train = distinct
            && clips
                .iter()
                .filter(|c: &&TokenClip| c.split == "train")
                .count()
                < 8;
        if train {
            seen.extend(captions[id].iter().cloned());
        }
        let n = 6 + rng.index(7);
        clips.push(TokenClip {
            motion_id: id.clone(),
            split: match (train, clips.len() % 3) {
                (true, _) => "train",
                (false, 0) => "val",
                _ => "test",
            }
            .into(),
            tokens: (0..n).map(|_| rng.index(CODES) as u32).collect(),
        });
    }
    assert_eq!(clips.iter().filter(|c| c.split == "train").count(), 8);
    let tokens = root.join("tokens");
    let info = TokenizerInfo {
        dir: "synthetic".into(),
        id: "synthetic".into(),
        quantizer: "fsq".into(),
        codebook_size: CODES,
        nominal_codebook: CODES,
        downsample: 4,
    };
    TokenSet::write(&tokens, info, &corpus, clips).unwrap();
    (corpus, tokens)
}

fn tiny_run(tokens: &Path, out: &Path, budget: u64) -> TrainConfig {
    let mut config = TrainConfig::new(
        tokens,
        ModelShape::Custom {
            d_model: 32,
            n_layers: 2,
            n_heads: 2,
            ffn_hidden: None,
        },
        budget,
        out,
    );
    config.hyper.batch_size = 8;
    config.hyper.lr = 3e-3;
    config.hyper.weight_decay = 0.0;
    config
}

fn run(config: &TrainConfig) -> TrainReport {
    train(config, &Device::Cpu, &mut |_| {}).unwrap()
}

#[test]
fn a_tiny_model_overfits_eight_clips() {
    let root = tempfile::tempdir().unwrap();
    let (_, tokens) = fixture(root.path());
    let config = tiny_run(&tokens, &root.path().join("run"), 8 * 10 * 300);
    let report = run(&config);
    let first = report.eval.train_loss;
    // The mean training loss over the last tenth of the run.
    let evals = std::fs::read_to_string(root.path().join("run/evals.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(evals.lines().last().unwrap()).unwrap();
    let final_loss = last["train_loss"].as_f64().unwrap();
    eprintln!(
        "overfit: {} steps, final train loss {final_loss:.4} (uniform ln 19 = 2.94)",
        report.steps
    );
    assert!(
        final_loss < 0.05,
        "train loss {final_loss} (first eval {first})"
    );
    for name in [
        "config.json",
        "model.safetensors",
        "state.json",
        "eval.json",
        &format!("resume/{}/optimizer.safetensors", report.steps),
    ] {
        assert!(root.path().join("run").join(name).is_file(), "{name}");
    }
    assert_eq!(report.eval.n_v, 2 * (CODES as u64 + 3) * 32);
    assert!(report.eval.flops_exact > 0.0 && report.eval.flops_6n > 0.0);
}

#[test]
fn an_interrupted_run_resumes_to_the_same_weights() {
    let root = tempfile::tempdir().unwrap();
    let (_, tokens) = fixture(root.path());
    let mut whole = tiny_run(&tokens, &root.path().join("whole"), 8 * 9 * 12);
    whole.checkpoint_every = Some(4);
    whole.eval_every = Some(5);
    let full = run(&whole);
    let mut parts = whole.clone();
    parts.out = root.path().join("parts");
    parts.stop_after = Some(6);
    let first = run(&parts);
    assert_eq!(first.steps, 6);
    // As a binary from before devices and precisions wrote it: the run still resumes.
    let config_path = root.path().join("parts/config.json");
    let mut old: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&config_path).unwrap()).unwrap();
    old.as_object_mut().unwrap().remove("device").unwrap();
    old["train"]
        .as_object_mut()
        .unwrap()
        .remove("compute")
        .unwrap();
    std::fs::write(&config_path, serde_json::to_string(&old).unwrap()).unwrap();
    parts.stop_after = None;
    let second = run(&parts);
    assert_eq!(
        (second.steps, full.steps),
        (full.total_steps, full.total_steps)
    );
    let moments = format!("resume/{}/optimizer.safetensors", full.steps);
    for name in ["model.safetensors", &moments] {
        let a = std::fs::read(root.path().join("whole").join(name)).unwrap();
        let b = std::fs::read(root.path().join("parts").join(name)).unwrap();
        assert!(a == b, "{name} differs after resuming");
    }
    assert_eq!(second.eval.test, full.eval.test);
    // The training-loss window is checkpointed: every evaluation of the uninterrupted run is
    // logged with the same train_loss by the interrupted one (which also logged its stop).
    let evals = |dir: &str| -> Vec<serde_json::Value> {
        std::fs::read_to_string(root.path().join(dir).join("evals.jsonl"))
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let resumed = evals("parts");
    let whole = evals("whole");
    assert!(whole.len() >= 2, "{whole:?}");
    for e in &whole {
        let same = resumed.iter().find(|r| r["step"] == e["step"]).unwrap();
        assert_eq!(same["train_loss"], e["train_loss"], "step {}", e["step"]);
    }
    // The validation-selected evaluation is the one of lowest validation loss, resumed alike.
    assert_eq!(second.eval.best, full.eval.best);
    let best = full
        .eval
        .best
        .as_ref()
        .expect("the fixture has validation clips");
    let lowest = whole
        .iter()
        .min_by(|a, b| {
            let ce = |e: &serde_json::Value| e["val"]["cross_entropy"].as_f64().unwrap();
            ce(a).total_cmp(&ce(b))
        })
        .unwrap();
    assert_eq!(lowest["step"], best.step);
    assert_eq!(lowest["test"]["cross_entropy"], best.test.cross_entropy);
    // A different configuration in the same folder is refused.
    let mut other = parts.clone();
    other.hyper.seed = 1;
    assert!(train(&other, &Device::Cpu, &mut |_| {}).is_err());
    let mut other = parts.clone();
    other.compute.precision = nn::device::Precision::Bf16;
    assert!(train(&other, &Device::Cpu, &mut |_| {}).is_err());
}

/// Two seeds of a tiny model and their ensemble: a one-member ensemble is the model, a model
/// twice is itself, and two models score at most the mean of their cross-entropies (the log of
/// a mean probability is at least the mean log-probability, target by target).
#[test]
fn an_ensemble_averages_the_members_probabilities() {
    let root = tempfile::tempdir().unwrap();
    let (corpus, tokens) = fixture(root.path());
    let mut members = Vec::new();
    for seed in [0, 1] {
        let mut config = tiny_run(
            &tokens,
            &root.path().join(format!("run-{seed}")),
            8 * 10 * 30,
        );
        config.hyper.seed = seed;
        run(&config);
        members.push(load_model(&config.out, &Device::Cpu).unwrap().0);
    }
    let limits = Limits {
        text_tokens: 64,
        motion_tokens: 64,
    };
    let data = LmData::load(&tokens, &corpus, None, limits, &Default::default()).unwrap();
    let (a, b) = (&members[0], &members[1]);
    let alone = evaluate(a, &data, "test", 4).unwrap();
    assert_eq!(evaluate_ensemble(&[a], &data, "test", 4).unwrap(), alone);
    let twice = evaluate_ensemble(&[a, a], &data, "test", 4).unwrap();
    assert!((twice.cross_entropy - alone.cross_entropy).abs() < 1e-9);
    let other = evaluate(b, &data, "test", 4).unwrap();
    let both = evaluate_ensemble(&[a, b], &data, "test", 4).unwrap();
    let mean = 0.5 * (alone.cross_entropy + other.cross_entropy);
    assert!(
        both.cross_entropy < mean,
        "{} vs {mean}",
        both.cross_entropy
    );
    assert!(
        alone.cross_entropy != other.cross_entropy,
        "the seeds differ"
    );
    assert_eq!(both.code_targets, alone.code_targets);
    let unigram = both.cross_entropy - both.normalized_loss;
    assert!((unigram - both.unigram_cross_entropy).abs() < 1e-9);
}

#[test]
fn a_model_predicting_the_unigram_has_zero_normalized_loss() {
    let root = tempfile::tempdir().unwrap();
    let (corpus, tokens) = fixture(root.path());
    let limits = Limits {
        text_tokens: 64,
        motion_tokens: 64,
    };
    let data = LmData::load(&tokens, &corpus, None, limits, &Default::default()).unwrap();
    let config = PrefixLmConfig::new(8, 1, 2, CODES, data.text_dim);
    let (d, v) = (config.d_model, config.vocab_size());
    // Blocks whose output projections are zero leave h = the token embedding e0; the final
    // RMSNorm scales e0 by s, and the head turns it into log p_u (specials: −30).
    let s = 1.0 / (1.0 / d as f64 + config.norm_eps).sqrt();
    let unigram = data.unigram.smoothed_probabilities("train");
    let mut head = vec![0f32; v * d];
    for t in 0..v {
        let logit = unigram.get(t).map_or(-30.0, |p| p.ln());
        head[t * d] = (logit / s) as f32;
    }
    let mut emb = vec![0f32; v * d];
    emb.chunks_mut(d).for_each(|row| row[0] = 1.0);
    let zeros = |shape: (usize, usize)| Tensor::zeros(shape, DType::F32, &Device::Cpu).unwrap();
    let ones = |n: usize| Tensor::ones(n, DType::F32, &Device::Cpu).unwrap();
    let mut w: HashMap<String, Tensor> = HashMap::new();
    w.insert(
        "tok_emb.weight".into(),
        Tensor::from_vec(emb, (v, d), &Device::Cpu).unwrap(),
    );
    w.insert(
        "head.weight".into(),
        Tensor::from_vec(head, (v, d), &Device::Cpu).unwrap(),
    );
    w.insert("norm.weight".into(), ones(d));
    w.insert("prefix_proj.weight".into(), zeros((d, data.text_dim)));
    w.insert(
        "prefix_proj.bias".into(),
        Tensor::zeros(d, DType::F32, &Device::Cpu).unwrap(),
    );
    let f = config.ffn_hidden;
    for (name, shape) in [
        ("attn.wqkv.weight", (3 * d, d)),
        ("attn.wo.weight", (d, d)),
        ("ffn.w13.weight", (2 * f, d)),
        ("ffn.w2.weight", (d, f)),
    ] {
        w.insert(format!("blocks.0.{name}"), zeros(shape));
    }
    w.insert("blocks.0.n1.weight".into(), ones(d));
    w.insert("blocks.0.n2.weight".into(), ones(d));
    let model = PrefixLm::new(
        &config,
        VarBuilder::from_tensors(w, DType::F32, &Device::Cpu),
    )
    .unwrap();
    let loss = evaluate(&model, &data, "test", 4).unwrap();
    eprintln!("unigram model: {loss:?}");
    assert!(
        loss.normalized_loss.abs() < 1e-5,
        "{}",
        loss.normalized_loss
    );
    assert!((loss.cross_entropy - loss.unigram_cross_entropy).abs() < 1e-5);
    assert!(loss.code_targets > 0 && loss.unigram_entropy > 2.0);
}

#[test]
fn dropout_is_recorded_seeded_by_step_and_resumes_to_the_same_weights() {
    let root = tempfile::tempdir().unwrap();
    let (_, tokens) = fixture(root.path());
    let mut whole = tiny_run(&tokens, &root.path().join("whole"), 8 * 9 * 12);
    whole.hyper.dropout = 0.2;
    whole.checkpoint_every = Some(4);
    let dropped = run(&whole);
    let config: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root.path().join("whole/config.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(config["train"]["dropout"], 0.2);
    let mut parts = whole.clone();
    parts.out = root.path().join("parts");
    parts.stop_after = Some(5);
    run(&parts);
    parts.stop_after = None;
    run(&parts);
    let weights =
        |dir: &str| std::fs::read(root.path().join(dir).join("model.safetensors")).unwrap();
    assert!(
        weights("whole") == weights("parts"),
        "dropout differs after resuming"
    );
    let mut plain = whole.clone();
    plain.hyper.dropout = 0.0;
    plain.out = root.path().join("plain");
    let kept = run(&plain);
    assert_ne!(dropped.eval.train_loss, kept.eval.train_loss);
    let mut bad = plain.clone();
    bad.hyper.dropout = 1.0;
    bad.out = root.path().join("bad");
    let err = train(&bad, &Device::Cpu, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("dropout") && err.contains("[0, 1)"), "{err}");
}
