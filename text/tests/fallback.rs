//! The untrained word-level fallback encoder.

use text::fallback::{words, FallbackEncoder, ID_PREFIX, UNK};
use text::TextEncoder;

const CAPTIONS: [&str; 3] = [
    "A person walks forward, looking sad.",
    "someone waves the LEFT hand",
    "a person jumps; then walks back",
];

#[test]
fn vocabulary_and_table_statistics() {
    assert_eq!(
        words("Walks, FORWARD!  twice2"),
        ["walks", "forward", "twice2"]
    );
    let enc = FallbackEncoder::build(CAPTIONS, 64, 1).unwrap();
    assert!(enc.id().starts_with(ID_PREFIX), "{}", enc.id());
    assert_eq!(enc.vocab()[0], UNK);
    let rest = &enc.vocab()[1..];
    assert!(
        rest.windows(2).all(|w| w[0] < w[1]),
        "sorted and distinct: {rest:?}"
    );
    assert_eq!(rest.len(), 14);
    assert_eq!(enc.table().len(), 15 * 64);

    // N(0, 1/dim): check mean and variance on a larger table.
    let big = FallbackEncoder::build(["w"; 1], 4096, 9).unwrap();
    let t = big.table();
    let mean = t.iter().map(|&v| v as f64).sum::<f64>() / t.len() as f64;
    let var = t.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / t.len() as f64;
    assert!(mean.abs() < 3.0 / 4096.0, "mean {mean}");
    assert!(
        (var * 4096.0 - 1.0).abs() < 0.05,
        "variance × dim = {}",
        var * 4096.0
    );
}

#[test]
fn seeded_build_save_load_round_trip() {
    let a = FallbackEncoder::build(CAPTIONS, 8, 7).unwrap();
    let b = FallbackEncoder::build(CAPTIONS, 8, 7).unwrap();
    let c = FallbackEncoder::build(CAPTIONS, 8, 8).unwrap();
    assert_eq!(a.table(), b.table());
    assert_eq!(a.id(), b.id());
    assert_ne!(a.id(), c.id());

    let tmp = tempfile::tempdir().unwrap();
    a.save(tmp.path()).unwrap();
    let loaded = FallbackEncoder::load(tmp.path()).unwrap();
    assert_eq!(loaded.id(), a.id());
    assert_eq!(loaded.vocab(), a.vocab());
    let texts = ["a person waves, unknownword", "walks"];
    assert_eq!(loaded.encode(&texts).unwrap(), a.encode(&texts).unwrap());

    let out = a.encode(&texts).unwrap();
    assert_eq!(out[0].tokens, ["a", "person", "waves", UNK]);
    let row = |w: &str| {
        let i = a.vocab().iter().position(|v| v == w).unwrap();
        a.table()[i * 8..(i + 1) * 8].to_vec()
    };
    assert_eq!(out[0].embeddings[8..16], row("person")[..]);
    assert_eq!(out[0].embeddings[24..32], row(UNK)[..]);

    // A table whose rows do not match the vocabulary is refused, naming the file.
    std::fs::write(tmp.path().join("vocab.json"), r#"["<unk>", "a"]"#).unwrap();
    let err = FallbackEncoder::load(tmp.path())
        .err()
        .expect("mismatch fails");
    assert!(err.to_string().contains("model.safetensors"), "{err}");
    assert!(FallbackEncoder::build(CAPTIONS, 0, 1).is_err());
}
