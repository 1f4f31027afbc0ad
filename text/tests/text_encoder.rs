//! The MiniLM encoder against the Python `transformers` reference
//! (`fixtures/minilm_reference.json`, made by `fixtures/make_minilm_reference.py`).

use candle_core::Device;
use nn::ModelError;
use serde::Deserialize;
use text::{BertEncoder, TextEncoder};

mod common;

#[derive(Deserialize)]
struct Reference {
    captions: Vec<RefCaption>,
}

#[derive(Deserialize)]
struct RefCaption {
    caption: String,
    ids: Vec<u32>,
    tokens: Vec<String>,
    hidden: Vec<Vec<f32>>,
    sentence: Vec<f32>,
}

fn reference() -> Reference {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/minilm_reference.json"
    );
    let text = std::fs::read_to_string(path).expect("reference fixture is committed");
    serde_json::from_str(&text).expect("reference fixture parses")
}

fn cosine(a: &[f32], b: &[f32]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum();
    let norm = |v: &[f32]| v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    dot / (norm(a) * norm(b))
}

#[test]
fn minilm_matches_python_reference() {
    let Some(dir) = common::minilm_dir() else {
        return;
    };
    let encoder = BertEncoder::load(&dir, &Device::Cpu).unwrap();
    assert_eq!(encoder.dim(), 384);
    assert!(
        encoder.id().starts_with("all-MiniLM-L6-v2-"),
        "{}",
        encoder.id()
    );
    let reference = reference();
    let tokenizer = tokenizers::Tokenizer::from_file(dir.join("tokenizer.json")).unwrap();
    let texts: Vec<&str> = reference
        .captions
        .iter()
        .map(|c| c.caption.as_str())
        .collect();
    // The whole batch at once (padded to the longest, masked) and one caption at a time.
    let batched = encoder.encode(&texts).unwrap();
    for (r, batch_emb) in reference.captions.iter().zip(&batched) {
        let single = encoder.encode(&[&r.caption]).unwrap().remove(0);
        let mut enc = tokenizer.encode(r.caption.as_str(), true).unwrap();
        // The file pads every text to 128; count only the real tokens.
        let real = enc.get_attention_mask().iter().filter(|&&m| m == 1).count();
        enc.truncate(real, 0, tokenizers::TruncationDirection::Right);
        assert_eq!(enc.get_ids(), r.ids.as_slice(), "{}", r.caption);
        for emb in [&single, batch_emb] {
            assert_eq!(emb.tokens, r.tokens, "{}", r.caption);
            assert_eq!(emb.embeddings.len(), r.ids.len() * 384);
            let worst = emb
                .embeddings
                .chunks_exact(384)
                .zip(&r.hidden)
                .flat_map(|(a, b)| a.iter().zip(b).map(|(x, y)| (x - y).abs()))
                .fold(0f32, f32::max);
            assert!(worst < 1e-4, "{}: max |Δ| {worst}", r.caption);
            let cos = cosine(&emb.sentence_embedding(), &r.sentence);
            assert!(cos >= 0.9999, "{}: sentence cosine {cos}", r.caption);
        }
    }
}

#[test]
fn missing_files_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let err = BertEncoder::load(tmp.path(), &Device::Cpu)
        .err()
        .expect("empty folder fails");
    assert!(matches!(err, ModelError::Missing { .. }), "{err}");
    assert!(err.to_string().contains("config.json"), "{err}");
    let Some(dir) = common::minilm_dir() else {
        return;
    };
    // A real config and tokenizer over weights of the wrong shape.
    for f in ["config.json", "tokenizer.json"] {
        std::fs::copy(dir.join(f), tmp.path().join(f)).unwrap();
    }
    let mut config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("config.json")).unwrap()).unwrap();
    config["hidden_size"] = 256.into();
    std::fs::write(tmp.path().join("config.json"), config.to_string()).unwrap();
    std::fs::copy(
        dir.join("model.safetensors"),
        tmp.path().join("model.safetensors"),
    )
    .unwrap();
    let err = BertEncoder::load(tmp.path(), &Device::Cpu)
        .err()
        .expect("shape mismatch fails");
    assert!(err.to_string().contains("model.safetensors"), "{err}");
    assert!(err.to_string().contains("shape"), "{err}");
}
