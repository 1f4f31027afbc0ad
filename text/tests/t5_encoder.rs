//! T5Encoder on a tiny randomly initialised T5 (seeded weights and a WordLevel tokenizer
//! made here), since no T5 checkpoint is available offline.

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use candle_transformers::models::t5::{Config, T5EncoderModel};
use motionscale_core::rng::SplitMix64;
use serde_json::json;
use std::path::Path;
use text::{T5Encoder, TextEncoder};

const WORDS: [&str; 12] = [
    "a", "person", "walks", "runs", "forward", "backward", "then", "turns", "left", "right", ".",
    ",",
];
const D_MODEL: usize = 16;

fn config(d_model: usize) -> serde_json::Value {
    json!({
        "vocab_size": WORDS.len() + 3, "d_model": d_model, "d_kv": 4, "d_ff": 32,
        "num_layers": 2, "num_heads": 4, "relative_attention_num_buckets": 8,
        "relative_attention_max_distance": 16, "dropout_rate": 0.0,
        "layer_norm_epsilon": 1e-6, "initializer_factor": 1.0,
        "feed_forward_proj": "gated-gelu", "is_encoder_decoder": true,
        "pad_token_id": 0, "eos_token_id": 1, "decoder_start_token_id": 0
    })
}

fn special(id: usize, content: &str) -> serde_json::Value {
    json!({"id": id, "content": content, "single_word": false, "lstrip": false,
           "rstrip": false, "normalized": false, "special": true})
}

fn tokenizer() -> serde_json::Value {
    let mut vocab = serde_json::Map::new();
    for (i, w) in ["<pad>", "</s>", "<unk>"].iter().chain(&WORDS).enumerate() {
        vocab.insert(w.to_string(), i.into());
    }
    let eos = |seq: &str| json!([{"Sequence": {"id": seq, "type_id": 0}}, {"SpecialToken": {"id": "</s>", "type_id": 0}}]);
    let pair: Vec<serde_json::Value> = [eos("A"), eos("B")]
        .iter()
        .flat_map(|v| v.as_array().cloned().unwrap_or_default())
        .collect();
    json!({
        "version": "1.0", "truncation": null, "padding": null,
        "added_tokens": [special(0, "<pad>"), special(1, "</s>"), special(2, "<unk>")],
        "normalizer": {"type": "Lowercase"},
        "pre_tokenizer": {"type": "Whitespace"},
        "post_processor": {"type": "TemplateProcessing", "single": eos("A"), "pair": pair,
            "special_tokens": {"</s>": {"id": "</s>", "ids": [1], "tokens": ["</s>"]}}},
        "decoder": null,
        "model": {"type": "WordLevel", "vocab": vocab, "unk_token": "<unk>"}
    })
}

/// Write config.json, tokenizer.json and seeded random weights into `dir`. Final layer-norm
/// weights are ones, so every output row has unit RMS.
fn write_model(dir: &Path) {
    let config_json = config(D_MODEL);
    let cfg: Config = serde_json::from_value(config_json.clone()).unwrap();
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    T5EncoderModel::load(vb, &cfg).unwrap();
    let mut rng = SplitMix64(42);
    let data = varmap.data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var = &data[name];
        let n = var.elem_count();
        let values: Vec<f32> = if name.ends_with("final_layer_norm.weight") {
            vec![1.0; n]
        } else {
            (0..n)
                .map(|_| (rng.next_u64() >> 40) as f32 / (1u64 << 24) as f32 - 0.5)
                .collect()
        };
        var.set(&Tensor::from_vec(values, var.shape(), &Device::Cpu).unwrap())
            .unwrap();
    }
    drop(data);
    varmap.save(dir.join("model.safetensors")).unwrap();
    std::fs::write(dir.join("config.json"), config_json.to_string()).unwrap();
    std::fs::write(dir.join("tokenizer.json"), tokenizer().to_string()).unwrap();
}

#[test]
fn tiny_t5_encodes_real_tokens_in_order() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("tiny-t5");
    std::fs::create_dir(&dir).unwrap();
    write_model(&dir);
    let encoder = T5Encoder::load(&dir, &Device::Cpu).unwrap();
    assert_eq!(encoder.dim(), D_MODEL);
    assert!(encoder.id().starts_with("tiny-t5-"), "{}", encoder.id());
    assert_eq!(
        T5Encoder::load(&dir, &Device::Cpu).unwrap().id(),
        encoder.id()
    );

    let texts = [
        "A person walks forward.",
        "a person runs forward.",
        "a person walks forward , then turns left .",
        "someone waves",
    ];
    let batch = encoder.encode(&texts).unwrap();
    assert_eq!(batch.len(), texts.len());
    assert_eq!(
        batch[0].tokens,
        ["a", "person", "walks", "forward", ".", "</s>"]
    );
    assert_eq!(batch[3].tokens, ["<unk>", "<unk>", "</s>"]);
    assert_eq!(batch[2].len(), 10);
    for (text, emb) in texts.iter().zip(&batch) {
        assert_eq!(emb.embeddings.len(), emb.len() * D_MODEL);
        let single = encoder.encode(&[text]).unwrap().remove(0);
        assert_eq!(single.tokens, emb.tokens);
        let worst = single
            .embeddings
            .iter()
            .zip(&emb.embeddings)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-5, "{text:?}: batched vs single max |Δ| {worst}");
        for row in emb.embeddings.chunks_exact(D_MODEL) {
            let rms = (row.iter().map(|v| v * v).sum::<f32>() / D_MODEL as f32).sqrt();
            assert!((rms - 1.0).abs() < 1e-3, "{text:?}: row RMS {rms}");
        }
    }
    // Bidirectional attention: a later word changes the first token's embedding.
    assert_ne!(
        batch[0].embeddings[..D_MODEL],
        batch[1].embeddings[..D_MODEL]
    );
    assert!(encoder.encode(&[]).unwrap().is_empty());
}

#[test]
fn wrong_weight_shapes_name_the_weights_file() {
    let tmp = tempfile::tempdir().unwrap();
    write_model(tmp.path());
    std::fs::write(tmp.path().join("config.json"), config(24).to_string()).unwrap();
    let err = T5Encoder::load(tmp.path(), &Device::Cpu)
        .err()
        .expect("shape mismatch fails");
    assert!(err.to_string().contains("model.safetensors"), "{err}");
    std::fs::remove_file(tmp.path().join("tokenizer.json")).unwrap();
    let err = T5Encoder::load(tmp.path(), &Device::Cpu)
        .err()
        .expect("missing tokenizer fails");
    assert!(err.to_string().contains("tokenizer.json"), "{err}");
}
