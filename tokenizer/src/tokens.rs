//! Token sets: every clip of a corpus as motion-token ids, the input of the transformer stage.
//!
//! ```text
//! TOKENS/manifest.json   format, tokenizer (dir, content hash, quantizer, codebook sizes,
//!                        down-sampling), corpus dir, per-split clip and token counts, sha256
//! TOKENS/tokens.parquet  motion_id (string), split (string), num_tokens (uint32),
//!                        tokens (list<uint32>), sorted by motion_id
//! TOKENS/unigram.json    {"vocab_size": V, "counts": {"train": [V counts], "val": …, "test": …}}
//! ```
//!
//! Unigram counts feed the normalised loss (ScaMo Eq. 8), which uses the train split's
//! frequencies with add-one smoothing. Files are written to temporary names and renamed.

use crate::error::TokenizerError;
use arrow_array::builder::{ListBuilder, StringBuilder, UInt32Builder};
use arrow_array::cast::AsArray;
use arrow_array::types::UInt32Type;
use arrow_array::{ArrayRef, RecordBatch};
use arrow_schema::{DataType, Field, Schema};
use bytes::Bytes;
use ingest::corpus::schema::list_item;
use motionscale_core::write_atomic;
use motionscale_core::{read_json, write_json};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::properties::WriterProperties;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Format tag of a token set's manifest.
pub const FORMAT: &str = "motionscale-tokens-v1";
/// Manifest file name.
pub const MANIFEST: &str = "manifest.json";
/// Token table file name.
pub const TABLE: &str = "tokens.parquet";
/// Unigram counts file name.
pub const UNIGRAM: &str = "unigram.json";

/// Column names of the token table.
pub mod col {
    /// Clip id, as in the corpus.
    pub const MOTION_ID: &str = "motion_id";
    /// `train`, `val` or `test`.
    pub const SPLIT: &str = "split";
    /// Number of tokens of the clip.
    pub const NUM_TOKENS: &str = "num_tokens";
    /// The token ids.
    pub const TOKENS: &str = "tokens";
}

/// One clip as tokens.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TokenClip {
    /// Clip id, as in the corpus.
    pub motion_id: String,
    /// Split of the clip.
    pub split: String,
    /// Token ids, each below the codebook size.
    pub tokens: Vec<u32>,
}

/// The tokenizer that made a token set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TokenizerInfo {
    /// Tokenizer checkpoint folder, as given.
    pub dir: PathBuf,
    /// Content hash of its weights and config (see `nn::checkpoint`).
    pub id: String,
    /// `fsq` or `vq`.
    pub quantizer: String,
    /// Number of distinct token ids (the real codebook size, e.g. 1000 for FSQ "2^10").
    pub codebook_size: usize,
    /// Codebook size as requested (e.g. 1024 for FSQ's `[8, 5, 5, 5]`).
    pub nominal_codebook: usize,
    /// Frames per token.
    pub downsample: usize,
}

/// Clips and tokens of one split.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitCount {
    /// Clips.
    pub clips: u64,
    /// Tokens.
    pub tokens: u64,
}

/// `TOKENS/manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TokenManifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// The tokenizer.
    pub tokenizer: TokenizerInfo,
    /// The corpus folder the clips came from.
    pub corpus: PathBuf,
    /// Clips and tokens per split.
    pub splits: BTreeMap<String, SplitCount>,
    /// sha256 of `tokens.parquet`.
    pub table_sha256: String,
}

/// `TOKENS/unigram.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UnigramCounts {
    /// Number of distinct token ids.
    pub vocab_size: usize,
    /// Per split, the count of each token id.
    pub counts: BTreeMap<String, Vec<u64>>,
}

impl UnigramCounts {
    /// Count the tokens of `clips` per split; fails on an id outside the vocabulary.
    pub fn of(clips: &[TokenClip], vocab_size: usize) -> Result<Self, TokenizerError> {
        let mut counts: BTreeMap<String, Vec<u64>> = BTreeMap::new();
        for clip in clips {
            let row = counts
                .entry(clip.split.clone())
                .or_insert_with(|| vec![0; vocab_size]);
            for &t in &clip.tokens {
                *row.get_mut(t as usize).ok_or_else(|| {
                    TokenizerError::Argument(format!(
                        "clip {}: token {t} is outside the vocabulary of {vocab_size}",
                        clip.motion_id
                    ))
                })? += 1;
            }
        }
        Ok(Self { vocab_size, counts })
    }

    /// Add-one smoothed unigram probabilities of `split` (uniform when the split is absent):
    /// `p(v) = (count(v) + 1) / (total + V)`, as the normalised loss uses them.
    pub fn smoothed_probabilities(&self, split: &str) -> Vec<f64> {
        let zeros = vec![0; self.vocab_size];
        let counts = self.counts.get(split).unwrap_or(&zeros);
        let total: u64 = counts.iter().sum();
        let denominator = (total + self.vocab_size as u64) as f64;
        counts
            .iter()
            .map(|&c| (c + 1) as f64 / denominator)
            .collect()
    }
}

/// A token set read back into memory (token sets are small: one id per 4 frames).
#[derive(Debug, Clone)]
pub struct TokenSet {
    /// The manifest.
    pub manifest: TokenManifest,
    /// Every clip, sorted by motion id.
    pub clips: Vec<TokenClip>,
    /// Unigram counts per split.
    pub unigram: UnigramCounts,
}

fn io_error(path: &Path, e: impl std::fmt::Display) -> TokenizerError {
    TokenizerError::File {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

fn table_schema() -> Arc<Schema> {
    Arc::new(Schema::new(vec![
        Field::new(col::MOTION_ID, DataType::Utf8, false),
        Field::new(col::SPLIT, DataType::Utf8, false),
        Field::new(col::NUM_TOKENS, DataType::UInt32, false),
        Field::new(
            col::TOKENS,
            DataType::List(list_item(DataType::UInt32)),
            false,
        ),
    ]))
}

fn encode_table(clips: &[TokenClip]) -> Result<Vec<u8>, TokenizerError> {
    let n = clips.len();
    let mut ids = StringBuilder::with_capacity(n, n * 24);
    let mut splits = StringBuilder::with_capacity(n, n * 5);
    let mut counts = UInt32Builder::with_capacity(n);
    let total = clips.iter().map(|c| c.tokens.len()).sum();
    let mut tokens = ListBuilder::with_capacity(UInt32Builder::with_capacity(total), n)
        .with_field(list_item(DataType::UInt32));
    for clip in clips {
        ids.append_value(&clip.motion_id);
        splits.append_value(&clip.split);
        counts.append_value(clip.tokens.len() as u32);
        tokens.values().append_slice(&clip.tokens);
        tokens.append(true);
    }
    let columns: Vec<ArrayRef> = vec![
        Arc::new(ids.finish()),
        Arc::new(splits.finish()),
        Arc::new(counts.finish()),
        Arc::new(tokens.finish()),
    ];
    let schema = table_schema();
    let batch = RecordBatch::try_new(schema.clone(), columns)
        .map_err(|e| TokenizerError::Argument(format!("token table: {e}")))?;
    let props = WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::default()))
        .build();
    let mut bytes = Vec::new();
    let mut writer = ArrowWriter::try_new(&mut bytes, schema, Some(props))
        .map_err(|e| TokenizerError::Argument(format!("token table: {e}")))?;
    writer
        .write(&batch)
        .and_then(|_| writer.close().map(|_| ()))
        .map_err(|e| TokenizerError::Argument(format!("token table: {e}")))?;
    Ok(bytes)
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

impl TokenSet {
    /// Write `clips` (any order; stored sorted by motion id) made by `tokenizer` from the
    /// corpus at `corpus` into `dir`. The manifest is written last, so a folder with a
    /// manifest is complete.
    pub fn write(
        dir: &Path,
        tokenizer: TokenizerInfo,
        corpus: &Path,
        mut clips: Vec<TokenClip>,
    ) -> Result<TokenManifest, TokenizerError> {
        clips.sort_by(|a, b| a.motion_id.cmp(&b.motion_id));
        if let Some(w) = clips.windows(2).find(|w| w[0].motion_id == w[1].motion_id) {
            return Err(TokenizerError::Argument(format!(
                "duplicate motion id {} in a token set",
                w[0].motion_id
            )));
        }
        let unigram = UnigramCounts::of(&clips, tokenizer.codebook_size)?;
        let mut splits: BTreeMap<String, SplitCount> = BTreeMap::new();
        for clip in &clips {
            let count = splits.entry(clip.split.clone()).or_default();
            count.clips += 1;
            count.tokens += clip.tokens.len() as u64;
        }
        std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
        let table = encode_table(&clips)?;
        let table_path = dir.join(TABLE);
        write_atomic(&table_path, &table).map_err(|e| io_error(&table_path, e))?;
        write_json(&dir.join(UNIGRAM), &unigram)?;
        let manifest = TokenManifest {
            format: FORMAT.into(),
            tokenizer,
            corpus: corpus.to_path_buf(),
            splits,
            table_sha256: sha256_hex(&table),
        };
        write_json(&dir.join(MANIFEST), &manifest)?;
        Ok(manifest)
    }

    /// Read a token set written by [`TokenSet::write`], checking its format and checksum.
    pub fn open(dir: &Path) -> Result<Self, TokenizerError> {
        let manifest_path = dir.join(MANIFEST);
        let manifest: TokenManifest = read_json(&manifest_path)?;
        if manifest.format != FORMAT {
            return Err(io_error(
                &manifest_path,
                format!("format {:?}, expected {FORMAT:?}", manifest.format),
            ));
        }
        let table_path = dir.join(TABLE);
        let bytes = std::fs::read(&table_path).map_err(|e| io_error(&table_path, e))?;
        if sha256_hex(&bytes) != manifest.table_sha256 {
            return Err(io_error(
                &table_path,
                "sha256 differs from the manifest's (file changed or truncated)",
            ));
        }
        let clips = decode_table(Bytes::from(bytes), manifest.tokenizer.codebook_size)
            .map_err(|e| io_error(&table_path, e))?;
        let unigram: UnigramCounts = read_json(&dir.join(UNIGRAM))?;
        Ok(Self {
            manifest,
            clips,
            unigram,
        })
    }

    /// Clips of one split, in motion-id order.
    pub fn split<'a>(&'a self, split: &'a str) -> impl Iterator<Item = &'a TokenClip> + 'a {
        self.clips.iter().filter(move |c| c.split == split)
    }

    /// Number of distinct token ids.
    pub fn vocab_size(&self) -> usize {
        self.manifest.tokenizer.codebook_size
    }
}

fn decode_table(bytes: Bytes, vocab_size: usize) -> Result<Vec<TokenClip>, String> {
    let reader = ParquetRecordBatchReaderBuilder::try_new(bytes)
        .and_then(|b| b.build())
        .map_err(|e| e.to_string())?;
    let mut clips = Vec::new();
    for batch in reader {
        let batch = batch.map_err(|e| e.to_string())?;
        let column = |name: &str| {
            batch
                .column_by_name(name)
                .ok_or_else(|| format!("missing column {name}"))
        };
        let ids = column(col::MOTION_ID)?.as_string::<i32>();
        let splits = column(col::SPLIT)?.as_string::<i32>();
        let tokens = column(col::TOKENS)?.as_list::<i32>();
        for row in 0..batch.num_rows() {
            let values = tokens.value(row);
            let values = values.as_primitive::<UInt32Type>().values().to_vec();
            if let Some(bad) = values.iter().find(|&&t| t as usize >= vocab_size) {
                return Err(format!(
                    "clip {}: token {bad} is outside the vocabulary of {vocab_size}",
                    ids.value(row)
                ));
            }
            clips.push(TokenClip {
                motion_id: ids.value(row).to_string(),
                split: splits.value(row).to_string(),
                tokens: values,
            });
        }
    }
    Ok(clips)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(vocab: usize) -> TokenizerInfo {
        TokenizerInfo {
            dir: "tok".into(),
            id: "abc".into(),
            quantizer: "fsq".into(),
            codebook_size: vocab,
            nominal_codebook: vocab,
            downsample: 4,
        }
    }

    fn clip(id: &str, split: &str, tokens: &[u32]) -> TokenClip {
        TokenClip {
            motion_id: id.into(),
            split: split.into(),
            tokens: tokens.to_vec(),
        }
    }

    #[test]
    fn write_then_open_round_trips_sorted_with_counts() {
        let dir = tempfile::tempdir().unwrap();
        let clips = vec![
            clip("b", "train", &[0, 1, 1, 3]),
            clip("a", "test", &[2, 2]),
            clip("c", "train", &[3]),
        ];
        let manifest = TokenSet::write(dir.path(), info(4), Path::new("corpus"), clips).unwrap();
        assert_eq!(
            manifest.splits["train"],
            SplitCount {
                clips: 2,
                tokens: 5
            }
        );
        let set = TokenSet::open(dir.path()).unwrap();
        let ids: Vec<&str> = set.clips.iter().map(|c| c.motion_id.as_str()).collect();
        assert_eq!(ids, ["a", "b", "c"]);
        assert_eq!(set.clips[1].tokens, vec![0, 1, 1, 3]);
        assert_eq!(set.unigram.counts["train"], vec![1, 2, 0, 2]);
        assert_eq!(set.unigram.counts["test"], vec![0, 0, 2, 0]);
        assert_eq!(set.split("train").count(), 2);
    }

    #[test]
    fn smoothed_probabilities_add_one() {
        let counts = UnigramCounts::of(&[clip("a", "train", &[0, 0, 1])], 3).unwrap();
        // (2+1)/(3+3), (1+1)/6, (0+1)/6.
        let p = counts.smoothed_probabilities("train");
        assert_eq!(p, vec![0.5, 2.0 / 6.0, 1.0 / 6.0]);
        assert_eq!(counts.smoothed_probabilities("val"), vec![1.0 / 3.0; 3]);
    }

    #[test]
    fn out_of_vocabulary_duplicates_and_corruption_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let oov = TokenSet::write(
            dir.path(),
            info(2),
            Path::new("c"),
            vec![clip("a", "train", &[2])],
        );
        assert!(oov
            .unwrap_err()
            .to_string()
            .contains("outside the vocabulary"));
        let dup = vec![clip("a", "train", &[0]), clip("a", "test", &[1])];
        assert!(TokenSet::write(dir.path(), info(2), Path::new("c"), dup).is_err());
        TokenSet::write(
            dir.path(),
            info(2),
            Path::new("c"),
            vec![clip("a", "train", &[1])],
        )
        .unwrap();
        let table = dir.path().join(TABLE);
        let mut bytes = std::fs::read(&table).unwrap();
        let last = bytes.len() - 10;
        bytes[last] ^= 0xff;
        std::fs::write(&table, bytes).unwrap();
        let err = TokenSet::open(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("tokens.parquet") && err.contains("sha256"),
            "{err}"
        );
    }
}
