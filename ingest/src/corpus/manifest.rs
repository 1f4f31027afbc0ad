//! `manifest.json`: what a corpus holds, how it was made, and the checksums that `verify` checks.

use crate::error::IngestError;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// Format name written in every manifest.
pub const FORMAT: &str = "motionscale-corpus";
/// Version of the on-disk layout.
pub const FORMAT_VERSION: u32 = 1;

/// One shard file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// Path relative to the corpus folder.
    pub file: String,
    /// Number of rows (clips).
    pub rows: u64,
    /// Number of feature rows over all clips.
    pub frames: u64,
    /// sha256 of the file bytes, hex.
    pub sha256: String,
}

/// One `--source KIND:PATH` argument and what became of its inputs.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SourceEntry {
    /// Source kind (`bvh`, `joints`, `amass`, `hml3d`).
    pub kind: String,
    /// Path as given.
    pub path: String,
    /// Input files found.
    pub files: u64,
    /// Input files with at least one clip in the corpus.
    pub ingested_files: u64,
    /// Entries in `rejects.jsonl` from this source.
    pub rejects: u64,
    /// Unit/axis conversions applied, with how many clips each.
    pub conversions: BTreeMap<String, u64>,
}

/// Text embeddings of the corpus captions made by one encoder (written by `embed-text`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TextEmbeddingEntry {
    /// Encoder id (model name and a hash of its weights and tokenizer).
    pub encoder: String,
    /// Folder of the embedding shards, relative to the corpus folder.
    pub dir: String,
    /// Embedding width.
    pub dim: usize,
    /// Distinct captions embedded.
    pub captions: u64,
}

/// Options the corpus was built with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BuildOptions {
    /// Target frame rate.
    pub fps: f64,
    /// Whether mirrored copies were added.
    pub mirror: bool,
    /// Longest clip in seconds before splitting.
    pub max_seconds: f64,
    /// Shortest clip kept, in feature rows.
    pub min_frames: usize,
    /// Mean speed (m/s) of the fastest joint under which a clip is rejected as static.
    pub static_threshold: f64,
    /// Foot-contact threshold (squared metres per frame).
    pub feet_threshold: f64,
    /// Whether the HumanML3D hip-order quirk was corrected.
    pub fix_facing: bool,
}

/// The corpus manifest.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// Layout version.
    pub format_version: u32,
    /// `humanml3d-263`, or `humanml3d-263-fixed-facing` (not HumanML3D-compatible).
    pub feature_convention: String,
    /// Whether features can be mixed with HumanML3D's own.
    pub humanml3d_compatible: bool,
    /// Features per frame (263).
    pub feature_dim: usize,
    /// Joint set of the `joints` column.
    pub joint_set: String,
    /// Units of the `joints` column.
    pub units: String,
    /// Up axis of the `joints` column.
    pub up_axis: String,
    /// Frame rate of every clip.
    pub fps: f64,
    /// Build options.
    pub options: BuildOptions,
    /// Sources and their outcome.
    pub sources: Vec<SourceEntry>,
    /// Shard files.
    pub shards: Vec<ShardEntry>,
    /// Clip counts per split.
    pub clips_by_split: BTreeMap<String, u64>,
    /// Feature rows per split.
    pub frames_by_split: BTreeMap<String, u64>,
    /// Number of entries in `rejects.jsonl`.
    pub rejects: u64,
    /// Statistics files, relative to the corpus folder.
    pub stats: BTreeMap<String, String>,
    /// sha256 (hex) of the corpus files besides the shards (statistics, rejects), by path
    /// relative to the corpus folder; empty in corpora written before it existed.
    #[serde(default)]
    pub file_sha256: BTreeMap<String, String>,
    /// Caption embeddings, one entry per encoder (empty until `embed-text` runs).
    #[serde(default)]
    pub text_embeddings: Vec<TextEmbeddingEntry>,
}

impl Manifest {
    /// Read `manifest.json` from a corpus folder.
    pub fn read(dir: &Path) -> Result<Self, IngestError> {
        let path = dir.join("manifest.json");
        let text = std::fs::read_to_string(&path).map_err(|e| IngestError::io(&path, e))?;
        let manifest: Manifest = serde_json::from_str(&text).map_err(IngestError::at(&path))?;
        if manifest.format != FORMAT || manifest.format_version != FORMAT_VERSION {
            return Err(IngestError::file(
                &path,
                format!(
                    "format {} v{} is not {FORMAT} v{FORMAT_VERSION}",
                    manifest.format, manifest.format_version
                ),
            ));
        }
        Ok(manifest)
    }

    /// Write `manifest.json` into a corpus folder atomically.
    pub fn write(&self, dir: &Path) -> Result<(), IngestError> {
        let path = dir.join("manifest.json");
        let text = serde_json::to_string_pretty(self).map_err(|e| e.to_string())?;
        motionscale_core::write_atomic(&path, text.as_bytes())
            .map_err(|e| IngestError::io(&path, e))
    }

    /// Total number of clips.
    pub fn clips(&self) -> u64 {
        self.shards.iter().map(|s| s.rows).sum()
    }
}
