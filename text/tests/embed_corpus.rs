//! Caption embeddings of a tiny demo corpus: every caption once, re-runs skip, interrupted
//! runs resume.

use ingest::corpus::manifest::Manifest;
use ingest::corpus::Corpus;
use ingest::pipeline::{ingest, IngestOptions, SourceKind, SourceSpec};
use std::cell::RefCell;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use text::embed::{corpus_captions, INDEX_FILE, META_ENCODER};
use text::{embed_corpus, embed_corpus_sharded, CaptionEmbeddings, FallbackEncoder, TextEncoder};

mod common;

/// A demo corpus (BVH clips with captions, mirrored copies add mirrored captions).
fn demo_corpus(root: &Path) -> PathBuf {
    let inputs = root.join("inputs");
    ingest::demo::write_demo_inputs(&inputs).unwrap();
    let corpus = root.join("corpus");
    let spec = SourceSpec {
        kind: SourceKind::Bvh,
        path: inputs,
    };
    let opts = IngestOptions {
        mirror: true,
        ..IngestOptions::default()
    };
    ingest(&[spec], &corpus, &opts, &|_, _| {}).unwrap();
    corpus
}

/// Every caption of every clip, decoded through the corpus reader.
fn all_captions(corpus: &Path) -> BTreeSet<String> {
    let c = Corpus::open(corpus).unwrap();
    (0..c.manifest().shards.len())
        .flat_map(|s| c.shard_records(s).unwrap())
        .flat_map(|r| r.captions)
        .collect()
}

/// Read an encoder's shards with pyarrow; prints rows, the first caption's length and the
/// sum of its embedding values.
fn python_check(corpus: &Path, encoder: &str) -> String {
    const SCRIPT: &str = r#"
import json, sys, numpy as np, pyarrow.parquet as pq
corpus, encoder = sys.argv[1], sys.argv[2]
entry = next(e for e in json.load(open(f"{corpus}/manifest.json"))["text_embeddings"] if e["encoder"] == encoder)
index = json.load(open(f"{corpus}/{entry['dir']}/index.json"))
rows, first = 0, None
for shard in index["shards"]:
    t = pq.read_table(f"{corpus}/{entry['dir']}/{shard['file']}")
    meta = t.schema.metadata
    assert meta[b"motionscale.text_encoder"].decode() == encoder, meta
    assert int(meta[b"motionscale.text_dim"]) == entry["dim"], meta
    for cap, toks, n, emb in zip(*(t.column(c).to_pylist() for c in ["caption", "tokens", "num_tokens", "embeddings"])):
        assert len(toks) == n and len(emb) == n * entry["dim"], cap
        if first is None:
            first = (cap, np.asarray(emb, dtype=np.float64).sum())
    rows += t.num_rows
print(rows, len(first[0]), repr(float(first[1])))
"#;
    let out = std::process::Command::new("python3")
        .args(["-c", SCRIPT])
        .arg(corpus)
        .arg(encoder)
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "pyarrow check failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn index_shards(dir: &Path) -> Vec<serde_json::Value> {
    let index: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join(INDEX_FILE)).unwrap()).unwrap();
    index["shards"].as_array().unwrap().clone()
}

#[test]
fn fallback_embeddings_resume_and_read_back() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = demo_corpus(tmp.path());
    let captions = corpus_captions(&corpus).unwrap();
    assert_eq!(
        captions.iter().cloned().collect::<BTreeSet<_>>(),
        all_captions(&corpus)
    );
    assert!(captions.windows(2).all(|w| w[0] < w[1]));
    let n = captions.len() as u64;
    assert!(n >= 10, "{n} captions");

    let encoder = FallbackEncoder::for_corpus(&corpus, 32, 5).unwrap();
    let built = FallbackEncoder::build(captions.iter().map(String::as_str), 32, 5).unwrap();
    assert_eq!(encoder.id(), built.id());
    let calls = RefCell::new(Vec::new());
    let record = |d, t| calls.borrow_mut().push((d, t));
    let report = embed_corpus_sharded(&corpus, &encoder, 2, 3, &record).unwrap();
    assert_eq!(report.captions, n);
    assert_eq!(report.embedded, n);
    assert_eq!(report.shards, n.div_ceil(3));
    assert_eq!(report.skipped_shards, 0);
    let calls = calls.into_inner();
    assert_eq!(calls.last(), Some(&(n, n)));
    assert!(calls.windows(2).all(|w| w[0].0 <= w[1].0));

    let manifest = Manifest::read(&corpus).unwrap();
    assert_eq!(manifest.text_embeddings.len(), 1);
    let entry = &manifest.text_embeddings[0];
    assert_eq!(entry.encoder, encoder.id());
    assert!(entry.encoder.starts_with("fallback-untrained-"));
    assert_eq!((entry.dim, entry.captions), (32, n));
    assert_eq!(entry.dir, format!("text/{}", encoder.id()));

    let read = CaptionEmbeddings::open(&corpus, encoder.id()).unwrap();
    assert_eq!(
        (read.len(), read.dim(), read.encoder()),
        (n as usize, 32, encoder.id())
    );
    for c in &captions {
        let expected = encoder.encode(&[c]).unwrap().remove(0);
        assert_eq!(read.get(c).unwrap().as_ref(), Some(&expected), "{c}");
    }
    assert_eq!(read.get("no such caption").unwrap(), None);
    // The bulk read gives the same rows, and leaves out what was never embedded.
    let many = read
        .get_many(
            captions
                .iter()
                .map(String::as_str)
                .chain(["no such caption"]),
        )
        .unwrap();
    assert_eq!(many.len(), captions.len());
    for c in &captions {
        assert_eq!(many.get(c.as_str()), read.get(c).unwrap().as_ref(), "{c}");
    }

    // The shard file carries its encoder and stores embeddings byte-stream-split.
    let dir = corpus.join(&entry.dir);
    let file = std::fs::File::open(dir.join("shard-00000.parquet")).unwrap();
    let builder =
        parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(file).unwrap();
    assert_eq!(builder.schema().metadata()[META_ENCODER], encoder.id());
    let chunk = builder.metadata().row_group(0).column(3);
    assert!(chunk
        .encodings()
        .any(|e| e == parquet::basic::Encoding::BYTE_STREAM_SPLIT));

    // Other tools read the shards: pyarrow sees the encoder, the width and every row.
    let out = python_check(&corpus, encoder.id());
    let first = read.get(&captions[0]).unwrap().unwrap();
    let sum: f64 = first.embeddings.iter().map(|&v| v as f64).sum();
    assert_eq!(
        out.split_whitespace().collect::<Vec<_>>()[..2],
        [n.to_string(), captions[0].chars().count().to_string()]
    );
    let py_sum: f64 = out.split_whitespace().nth(2).unwrap().parse().unwrap();
    assert!((py_sum - sum).abs() < 1e-4, "pyarrow {py_sum} vs {sum}");

    // A re-run skips everything and keeps a single manifest entry.
    let again = embed_corpus_sharded(&corpus, &encoder, 2, 3, &|_, _| {}).unwrap();
    assert_eq!((again.skipped_shards, again.embedded), (report.shards, 0));
    assert_eq!(Manifest::read(&corpus).unwrap().text_embeddings.len(), 1);

    // Interrupted run: the last shard and its index entry are gone; a middle shard is corrupt.
    let mut shards = index_shards(&dir);
    let last = shards.pop().unwrap();
    std::fs::remove_file(dir.join(last["file"].as_str().unwrap())).unwrap();
    let mut index: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join(INDEX_FILE)).unwrap()).unwrap();
    index["shards"] = shards.into();
    std::fs::write(dir.join(INDEX_FILE), index.to_string()).unwrap();
    std::fs::write(dir.join("shard-00001.parquet"), b"truncated").unwrap();
    let resumed = embed_corpus_sharded(&corpus, &encoder, 2, 3, &|_, _| {}).unwrap();
    assert_eq!(resumed.skipped_shards, report.shards - 2);
    assert_eq!(resumed.embedded, 3 + last["rows"].as_u64().unwrap());
    let read = CaptionEmbeddings::open(&corpus, encoder.id()).unwrap();
    assert_eq!(read.len(), n as usize);
    for c in &captions {
        assert_eq!(
            read.get(c).unwrap(),
            Some(encoder.encode(&[c]).unwrap().remove(0))
        );
    }

    // Another shard size redoes everything under the same encoder folder.
    let resized = embed_corpus(&corpus, &encoder, 4, &|_, _| {}).unwrap();
    assert_eq!(
        (resized.shards, resized.skipped_shards, resized.embedded),
        (1, 0, n)
    );
    assert_eq!(index_shards(&dir).len(), 1);
    let files = std::fs::read_dir(&dir).unwrap().count();
    assert_eq!(
        files, 2,
        "stale shards are removed: one shard and the index remain"
    );
    assert_eq!(
        CaptionEmbeddings::open(&corpus, encoder.id())
            .unwrap()
            .len(),
        n as usize
    );
    assert!(CaptionEmbeddings::open(&corpus, "unknown-encoder").is_err());
}

#[test]
fn minilm_embeddings_match_single_encodes() {
    let Some(dir) = common::minilm_dir() else {
        return;
    };
    let encoder = text::BertEncoder::load(&dir, &candle_core::Device::Cpu).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let corpus = demo_corpus(tmp.path());
    let report = embed_corpus(&corpus, &encoder, 4, &|_, _| {}).unwrap();
    let read = CaptionEmbeddings::open(&corpus, encoder.id()).unwrap();
    assert_eq!(read.len() as u64, report.captions);
    for c in corpus_captions(&corpus).unwrap() {
        let got = read.get(&c).unwrap().unwrap();
        let single = encoder.encode(&[&c]).unwrap().remove(0);
        assert_eq!(got.tokens, single.tokens);
        let worst = got
            .embeddings
            .iter()
            .zip(&single.embeddings)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-4, "{c}: padded batch vs single max |Δ| {worst}");
    }
}
