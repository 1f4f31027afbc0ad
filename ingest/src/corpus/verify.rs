//! `corpus verify`: checksums, schema, row counts, shapes, NaN scan and statistics files.

use super::integrity;
use super::manifest::Manifest;
use super::reader::{records_from_batch, stats_problem, Corpus};
use super::schema::{legacy_shard_schema, shard_schema, FEATURE_DIM, JOINT_FRAME_DIM};
use super::split::SPLITS;
use super::ClipRecord;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use std::path::Path;

/// What `verify` checked and every problem it found (empty = the corpus is sound).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Verification {
    /// Shards checked.
    pub shards: usize,
    /// Clips checked.
    pub clips: u64,
    /// Feature rows scanned for NaN/Inf.
    pub frames: u64,
    /// Problems, each naming the file and the clip.
    pub problems: Vec<String>,
}

/// What is wrong with one record on its own: array sizes, non-finite values, its split.
fn record_problems(r: &ClipRecord) -> Vec<String> {
    let mut problems = Vec::new();
    let n = r.num_frames as usize;
    if r.features.len() != n * FEATURE_DIM {
        problems.push(format!(
            "{} feature values, expected {n} × {FEATURE_DIM}",
            r.features.len()
        ));
    }
    if r.joints.len() != (n + 1) * JOINT_FRAME_DIM {
        problems.push(format!(
            "{} joint values, expected ({n} + 1) × 22 × 3",
            r.joints.len()
        ));
    }
    if let Some(i) = r.features.iter().position(|x| !x.is_finite()) {
        problems.push(format!(
            "non-finite feature at frame {}, dim {}",
            i / FEATURE_DIM,
            i % FEATURE_DIM
        ));
    }
    if let Some(i) = r.joints.iter().position(|x| !x.is_finite()) {
        problems.push(format!(
            "non-finite joint value at frame {}",
            i / JOINT_FRAME_DIM
        ));
    }
    if !SPLITS.contains(&r.split.as_str()) {
        problems.push(format!("unknown split {:?}", r.split));
    }
    problems
}

/// Verify a corpus folder.
pub fn verify(dir: &Path) -> Verification {
    let mut v = Verification::default();
    let manifest = match Manifest::read(dir) {
        Ok(m) => m,
        Err(e) => {
            v.problems.push(e.to_string());
            return v;
        }
    };
    v.problems = integrity::problems(dir, &manifest);
    let mut last_id: Option<String> = None;
    for entry in &manifest.shards {
        v.shards += 1;
        let path = dir.join(&entry.file);
        let bytes = match std::fs::read(&path) {
            Ok(b) => b,
            Err(e) => {
                v.problems.push(format!("{}: {e}", path.display()));
                continue;
            }
        };
        let builder = match ParquetRecordBatchReaderBuilder::try_new(bytes::Bytes::from(bytes)) {
            Ok(b) => b,
            Err(e) => {
                v.problems.push(format!(
                    "{}: not a readable Parquet file: {e}",
                    path.display()
                ));
                continue;
            }
        };
        let fields = builder.schema().fields();
        if fields != shard_schema().fields() && fields != legacy_shard_schema().fields() {
            v.problems.push(format!(
                "{}: schema differs from the corpus schema: {:?}",
                path.display(),
                builder.schema().fields()
            ));
            continue;
        }
        let reader = match builder.build() {
            Ok(r) => r,
            Err(e) => {
                v.problems.push(format!("{}: {e}", path.display()));
                continue;
            }
        };
        let (mut rows, mut frames) = (0u64, 0u64);
        for batch in reader {
            let records = match batch
                .map_err(|e| e.to_string())
                .and_then(|b| records_from_batch(&b).map_err(String::from))
            {
                Ok(r) => r,
                Err(e) => {
                    v.problems.push(format!("{}: {e}", path.display()));
                    break;
                }
            };
            for r in records {
                rows += 1;
                frames += r.num_frames as u64;
                let at = |what: String| format!("{}: clip {}: {what}", path.display(), r.motion_id);
                v.problems.extend(record_problems(&r).into_iter().map(at));
                if last_id.as_ref().is_some_and(|prev| prev >= &r.motion_id) {
                    v.problems.push(at(
                        "ids are not strictly increasing (duplicate or unsorted)".into(),
                    ));
                }
                last_id = Some(r.motion_id);
            }
        }
        v.clips += rows;
        v.frames += frames;
        if (rows, frames) != (entry.rows, entry.frames) {
            v.problems.push(format!(
                "{}: {rows} rows and {frames} frames, the manifest says {} and {}",
                path.display(),
                entry.rows,
                entry.frames
            ));
        }
    }
    for name in ["mean.npy", "std.npy"] {
        let path = dir.join("stats").join(name);
        match crate::npy::read(&path) {
            Ok(a) => v
                .problems
                .extend(stats_problem(name, &a).map(|p| format!("{}: {p}", path.display()))),
            Err(e) => v.problems.push(e.to_string()),
        }
    }
    if v.problems.is_empty() {
        if let Err(e) = Corpus::open(dir) {
            v.problems.push(e.to_string());
        }
    }
    v
}
