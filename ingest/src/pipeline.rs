//! The ingest pipeline: discover inputs → read (per source kind) → resample → segment →
//! mirror → HumanML3D-263 → filter → sorted Parquet shards, stats, manifest and rejects.

use crate::corpus::manifest::{
    BuildOptions, Manifest, ShardEntry, SourceEntry, FORMAT, FORMAT_VERSION,
};
use crate::corpus::runs::RunSet;
use crate::corpus::split::{split_of, SPLITS};
use crate::corpus::stats::FeatureStats;
use crate::corpus::{CaptionSpan, ClipRecord};
use crate::error::IngestError;
use crate::hml263::{Hml263, Hml263Extractor, Hml263Options, FEATURE_DIM};
use crate::resample::resample;
use crate::skeleton::{mirror_pose, Pose};
use crate::source::retarget::{self, RigMap};
use crate::source::{amass, bandai, hml3d, joints, synth, RawClip, Reject};
use rayon::prelude::*;
use serde::Serialize;
use sha2::Digest;
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::str::FromStr;

pub use crate::source::SourceKind;

/// A parsed `KIND:PATH` source argument.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SourceSpec {
    /// Source kind.
    pub kind: SourceKind,
    /// Folder (or single file) to read; `CLIPS[:SEED]` for `synth`.
    pub path: PathBuf,
}

impl FromStr for SourceSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, path) = s.split_once(':').ok_or_else(|| {
            format!("source {s:?} is not KIND:PATH (kinds: bvh, joints, amass, hml3d, synth)")
        })?;
        let kind = match kind {
            "bvh" => SourceKind::Bvh,
            "joints" => SourceKind::Joints,
            "amass" => SourceKind::Amass,
            "hml3d" => SourceKind::Hml3d,
            "synth" => {
                path.parse::<synth::SynthSpec>()?;
                SourceKind::Synth
            }
            other => {
                return Err(format!(
                "unknown source kind {other:?} in {s:?} (kinds: bvh, joints, amass, hml3d, synth)"
            ))
            }
        };
        if path.is_empty() {
            return Err(format!("source {s:?} has an empty path"));
        }
        Ok(Self {
            kind,
            path: PathBuf::from(path),
        })
    }
}

/// Everything that shapes a corpus build.
#[derive(Debug, Clone)]
pub struct IngestOptions {
    /// Corpus frame rate.
    pub fps: f64,
    /// Add left/right mirrored copies.
    pub mirror: bool,
    /// Clips longer than this are split into balanced consecutive segments.
    pub max_seconds: f64,
    /// Clips with fewer feature rows are rejected.
    pub min_frames: usize,
    /// Mean speed (m/s) of the fastest joint under which a clip is rejected as static.
    pub static_threshold: f64,
    /// HumanML3D feature options.
    pub features: Hml263Options,
    /// Frame rate of `joints:` inputs.
    pub src_fps: f64,
    /// Rig map for BVH rigs the built-in maps do not know.
    pub map: Option<RigMap>,
    /// Body model for `amass:` sources.
    pub body_model: Option<PathBuf>,
    /// Clips per shard file.
    pub rows_per_shard: usize,
    /// Input units processed (and held in memory) at a time; larger builds spill sorted
    /// runs to disk and merge them.
    pub chunk_units: usize,
}

impl Default for IngestOptions {
    fn default() -> Self {
        Self {
            fps: 20.0,
            mirror: false,
            max_seconds: 10.0,
            min_frames: 20,
            static_threshold: DEFAULT_STATIC_THRESHOLD,
            features: Hml263Options::default(),
            src_fps: 20.0,
            map: None,
            body_model: None,
            rows_per_shard: 512,
            chunk_units: 4096,
        }
    }
}

/// Default static-clip threshold (m/s) on the mean speed of a clip's fastest joint. Standing
/// still (breathing, sway) stays around 0.01–0.02 m/s; the slowest clip of the Bandai set
/// (a sad bow) measures 0.135 m/s, a single waving hand far more.
pub const DEFAULT_STATIC_THRESHOLD: f64 = 0.05;

/// One line of `rejects.jsonl`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct RejectRecord {
    /// Input file (or folder for whole-source failures).
    pub path: String,
    /// Source kind.
    pub source: String,
    /// Clip or segment id when the reject concerns part of a file.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub clip: Option<String>,
    /// Stage that refused it.
    pub stage: String,
    /// Why.
    pub reason: String,
}

/// Summary of an ingest run.
#[derive(Debug, Clone, Serialize)]
pub struct IngestReport {
    /// Input files found.
    pub inputs: u64,
    /// Clips written (mirrored copies included).
    pub clips: u64,
    /// Feature rows written.
    pub frames: u64,
    /// Frames read from the sources (before resampling).
    pub source_frames: u64,
    /// Bytes of input files read.
    pub source_bytes: u64,
    /// Entries in `rejects.jsonl`.
    pub rejects: u64,
    /// Shard files written.
    pub shards: u64,
}

/// Running totals over the clips kept: training statistics and per-split counts.
struct Totals {
    stats: FeatureStats,
    clips_by_split: BTreeMap<String, u64>,
    frames_by_split: BTreeMap<String, u64>,
}

impl Default for Totals {
    fn default() -> Self {
        let zero = || SPLITS.iter().map(|s| (s.to_string(), 0)).collect();
        Self {
            stats: FeatureStats::new(FEATURE_DIM),
            clips_by_split: zero(),
            frames_by_split: zero(),
        }
    }
}

impl Totals {
    fn add(&mut self, r: &ClipRecord) {
        if r.split == "train" {
            self.stats.add(&r.features);
        }
        *self.clips_by_split.entry(r.split.clone()).or_default() += 1;
        *self.frames_by_split.entry(r.split.clone()).or_default() += r.num_frames as u64;
    }
}

/// What processing one input file produced.
#[derive(Default)]
struct UnitOutcome {
    records: Vec<ClipRecord>,
    rejects: Vec<RejectRecord>,
    source_frames: u64,
    bytes: u64,
    conversions: BTreeMap<String, u64>,
}

/// One input: a file of a file source, or one clip of a synthetic stream.
enum Item {
    File(PathBuf),
    Synth(usize),
}

struct Unit {
    source: usize,
    item: Item,
}

fn discover(spec: &SourceSpec, reader: &Reader) -> Result<Vec<Item>, IngestError> {
    match reader {
        Reader::Hml3d(folder) => {
            return Ok(folder.discover()?.into_iter().map(Item::File).collect())
        }
        Reader::Synth(stream) => return Ok((0..stream.clips).map(Item::Synth).collect()),
        _ => {}
    }
    if spec.path.is_file() {
        return Ok(vec![Item::File(spec.path.clone())]);
    }
    if !spec.path.is_dir() {
        return Err(IngestError::file(
            &spec.path,
            format!("no such file or folder for source {}", spec.kind.name()),
        ));
    }
    let mut out = Vec::new();
    let mut stack = vec![spec.path.clone()];
    while let Some(dir) = stack.pop() {
        let entries = std::fs::read_dir(&dir).map_err(|e| IngestError::io(&dir, e))?;
        for entry in entries {
            let path = entry.map_err(|e| IngestError::io(&dir, e))?.path();
            let matches = path
                .extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| e.eq_ignore_ascii_case(spec.kind.extension()));
            // A folder named like an input (x.bvh/) is an input that cannot be read: keep it
            // so it lands in the rejects instead of vanishing.
            if path.is_dir() && !matches {
                stack.push(path);
            } else if matches {
                out.push(path);
            }
        }
    }
    out.sort();
    Ok(out.into_iter().map(Item::File).collect())
}

fn caption_sidecar(path: &Path) -> Result<Option<Vec<String>>, Reject> {
    crate::corpus::split::read_ids(&path.with_extension("txt"))
        .map_err(|e| Reject::new("captions", e))
}

/// Attach labels and captions from sidecar files (Bandai `.json` + `cfg/`, `<clip>.txt`).
fn attach_sidecars(clip: &mut RawClip, path: &Path) -> Result<(), Reject> {
    if let Some((labels, captions)) = bandai::sidecar(path)? {
        clip.labels = labels;
        clip.captions = captions;
    }
    if let Some(captions) = caption_sidecar(path)? {
        clip.captions = captions;
    }
    Ok(())
}

/// Swap the words left and right (keeping capitalisation) for a mirrored clip's caption.
pub fn mirror_caption(caption: &str) -> String {
    let mut out = String::with_capacity(caption.len());
    let mut word = String::new();
    let flush = |word: &mut String, out: &mut String| {
        let swapped = match word.as_str() {
            "left" => "right",
            "right" => "left",
            "Left" => "Right",
            "Right" => "Left",
            "LEFT" => "RIGHT",
            "RIGHT" => "LEFT",
            w => w,
        };
        out.push_str(swapped);
        word.clear();
    };
    for ch in caption.chars() {
        if ch.is_alphanumeric() {
            word.push(ch);
        } else {
            flush(&mut word, &mut out);
            out.push(ch);
        }
    }
    flush(&mut word, &mut out);
    out
}

fn first_non_finite(poses: &[Pose]) -> Option<(usize, usize)> {
    poses.iter().enumerate().find_map(|(t, pose)| {
        pose.iter()
            .position(|p| p.iter().any(|v| !v.is_finite()))
            .map(|j| (t, j))
    })
}

/// Mean speed (m/s) of the clip's fastest joint: the static-clip measure. A mean over all
/// joints would call one-handed gestures static; the fastest joint does not.
pub fn fastest_joint_speed(poses: &[Pose], fps: f64) -> f64 {
    if poses.len() < 2 {
        return 0.0;
    }
    let mut per_joint = [0.0f64; crate::skeleton::NUM_JOINTS];
    for w in poses.windows(2) {
        for (acc, (a, b)) in per_joint.iter_mut().zip(w[0].iter().zip(&w[1])) {
            *acc += crate::quat::norm(crate::quat::sub(*b, *a));
        }
    }
    let steps = (poses.len() - 1) as f64;
    per_joint.iter().fold(0.0f64, |m, &d| m.max(d)) * fps / steps
}

/// Balanced consecutive segments of `rows` feature rows, none longer than `max_rows`:
/// returns (first joint frame, last joint frame inclusive) per segment.
fn segments(rows: usize, max_rows: usize) -> Vec<(usize, usize)> {
    let n = rows.div_ceil(max_rows.max(1)).max(1);
    (0..n).map(|k| (k * rows / n, (k + 1) * rows / n)).collect()
}

/// `raw`'s poses checked (finite, within the input budgets, plausible) and resampled to the
/// corpus rate, or why the clip is rejected (including too few frames).
fn checked_and_resampled(raw: &RawClip, opts: &IngestOptions) -> Result<Vec<Pose>, Reject> {
    if let Some((t, j)) = first_non_finite(&raw.poses) {
        return Err(Reject::new(
            "validate",
            format!("non-finite joint position at frame {t}, joint {j}"),
        ));
    }
    crate::budget::check_resampled(raw.poses.len(), raw.fps, opts.fps)
        .map_err(|e| Reject::new("budget", e))?;
    crate::budget::check_plausible(&raw.poses).map_err(|e| Reject::new("validate", e))?;
    let poses = resample(&raw.poses, raw.fps, opts.fps);
    let rows = poses.len().saturating_sub(1);
    if rows < opts.min_frames.max(1) {
        return Err(Reject::new(
            "filter",
            format!(
                "too short: {rows} frames at {} fps after resampling from {} source frames at {:.2} fps (minimum {})",
                opts.fps,
                raw.poses.len(),
                raw.fps,
                opts.min_frames
            ),
        ));
    }
    Ok(poses)
}

fn clip_records(
    raw: &RawClip,
    opts: &IngestOptions,
    extractor: &mut Hml263Extractor,
    out: &mut UnitOutcome,
) {
    let reject = |clip: &str, r: Reject| RejectRecord {
        path: raw.source_path.display().to_string(),
        source: raw.source.clone(),
        clip: Some(clip.to_string()),
        stage: r.stage,
        reason: r.reason,
    };
    let poses = match checked_and_resampled(raw, opts) {
        Ok(poses) => poses,
        Err(r) => {
            out.rejects.push(reject(&raw.clip_id, r));
            return;
        }
    };
    let rows = poses.len().saturating_sub(1);
    let max_rows = (opts.max_seconds * opts.fps).round() as usize;
    let parts = segments(rows, max_rows);
    let split = raw
        .split
        .clone()
        .unwrap_or_else(|| split_of(&raw.clip_id).to_string());
    *out.conversions.entry(raw.conversion.clone()).or_default() += 1;
    for (k, &(a, b)) in parts.iter().enumerate() {
        let id = if parts.len() == 1 {
            raw.clip_id.clone()
        } else {
            format!("{}_s{k:02}", raw.clip_id)
        };
        let segment = &poses[a..=b];
        let speed = fastest_joint_speed(segment, opts.fps);
        if speed < opts.static_threshold {
            let r = Reject::new(
                "filter",
                format!(
                    "static: the fastest joint moves {speed:.4} m/s on average, below {} m/s",
                    opts.static_threshold
                ),
            );
            out.rejects.push(reject(&id, r));
            continue;
        }
        let variants: &[bool] = if opts.mirror {
            &[false, true]
        } else {
            &[false]
        };
        for &mirrored in variants {
            let prefix = if mirrored { "M" } else { "" };
            let motion_id = format!("{prefix}{id}");
            let input: Vec<Pose> = if mirrored {
                segment.iter().map(mirror_pose).collect()
            } else {
                segment.to_vec()
            };
            let mut feats = Hml263 {
                features: Vec::new(),
                joints: Vec::new(),
            };
            let result = extractor.process_into(&input, &opts.features, &mut feats);
            match result {
                Ok(()) if feats.features.iter().all(|v| v.is_finite()) => {}
                Ok(_) => {
                    let r = Reject::new("features", "non-finite feature values");
                    out.rejects.push(reject(&motion_id, r));
                    continue;
                }
                Err(e) => {
                    out.rejects
                        .push(reject(&motion_id, Reject::new("features", e)));
                    continue;
                }
            };
            let captions = if mirrored {
                raw.captions.iter().map(|c| mirror_caption(c)).collect()
            } else {
                raw.captions.clone()
            };
            // A span cut into segments no longer matches its captions' times: keep them as clips.
            let span = raw
                .span
                .as_ref()
                .filter(|_| parts.len() == 1)
                .map(|s| CaptionSpan {
                    of: format!("{prefix}{}", s.of),
                    seconds: s.seconds.clone(),
                });
            out.records.push(ClipRecord {
                motion_id,
                source: raw.source.clone(),
                source_path: raw.source_path.display().to_string(),
                source_clip: raw.clip_id.clone(),
                segment: k as u32,
                fps: opts.fps as f32,
                source_fps: raw.fps as f32,
                num_frames: (feats.features.len() / FEATURE_DIM) as u32,
                joints: feats
                    .joints
                    .iter()
                    .flat_map(|p| p.iter().flat_map(|v| v.map(|x| x as f32)))
                    .collect(),
                features: feats.features,
                captions,
                labels: raw.labels.clone(),
                split: split.clone(),
                mirrored,
                span,
            });
        }
    }
}

/// The per-input path after reading, for one clip: budgets and plausibility → resample →
/// segment → mirror → HumanML3D-263 features; returns the clips kept and the rejects.
pub fn process_clip(raw: &RawClip, opts: &IngestOptions) -> (Vec<ClipRecord>, Vec<RejectRecord>) {
    let mut out = UnitOutcome::default();
    clip_records(raw, opts, &mut Hml263Extractor::default(), &mut out);
    (out.records, out.rejects)
}

enum Reader<'a> {
    Bvh(Option<&'a RigMap>),
    Joints(f64),
    Amass(&'a amass::BodyModel),
    Hml3d(hml3d::Hml3dFolder),
    Synth(synth::SynthSpec),
}

fn read_file(kind: &Reader, spec: &SourceSpec, path: &Path) -> Vec<Result<RawClip, Reject>> {
    // Ids come from the path inside the source folder, so equal file names in different
    // sub-folders (AMASS subjects) stay distinct.
    let rel = path.strip_prefix(&spec.path).unwrap_or(path);
    let rel = if rel.as_os_str().is_empty() {
        Path::new(path.file_name().unwrap_or_default())
    } else {
        rel
    };
    match kind {
        Reader::Bvh(map) => vec![retarget::read_clip(path, rel, *map)],
        Reader::Joints(fps) => vec![joints::read_clip(path, rel, *fps)],
        Reader::Amass(model) => vec![amass::read_clip(path, rel, model)],
        Reader::Hml3d(folder) => folder.read_clips(path),
        Reader::Synth(_) => unreachable!("synthetic clips are not files"),
    }
}

fn process_unit(
    kind: &Reader,
    spec: &SourceSpec,
    item: &Item,
    opts: &IngestOptions,
    extractor: &mut Hml263Extractor,
) -> UnitOutcome {
    let mut out = UnitOutcome::default();
    let (results, path) = match (item, kind) {
        (Item::Synth(index), Reader::Synth(stream)) => (
            vec![Ok(synth::generate(stream.seed, *index))],
            PathBuf::from(format!("synth:{}", stream.seed)),
        ),
        (Item::File(path), _) => {
            out.bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
            let results = if out.bytes > crate::budget::MAX_FILE_BYTES {
                let reason = format!(
                    "{} bytes, over the {}-byte budget for one input",
                    out.bytes,
                    crate::budget::MAX_FILE_BYTES
                );
                vec![Err(Reject::new("budget", reason))]
            } else {
                read_file(kind, spec, path)
            };
            let results = results
                .into_iter()
                .map(|result| {
                    result.and_then(|mut clip| {
                        if !matches!(kind, Reader::Hml3d(_)) {
                            attach_sidecars(&mut clip, path)?;
                        }
                        Ok(clip)
                    })
                })
                .collect();
            (results, path.clone())
        }
        (Item::Synth(_), _) => unreachable!("synthetic items come from synth sources"),
    };
    for clip in results {
        match clip {
            Ok(clip) => {
                out.source_frames += clip.poses.len() as u64;
                clip_records(&clip, opts, extractor, &mut out);
            }
            Err(r) => out.rejects.push(RejectRecord {
                path: path.display().to_string(),
                source: spec.kind.name().to_string(),
                clip: None,
                stage: r.stage,
                reason: r.reason,
            }),
        }
    }
    out
}

/// Build (or rebuild) a corpus in `out` from `sources`. Calls `progress(done, total)` as
/// input files finish. Returns the report; the caller turns rejects into an exit code.
///
/// The output folder is locked for the whole run and the corpus is built beside it, then
/// swapped in when complete ([`crate::corpus::staging`]): an old corpus there stays
/// readable until the new one replaces it.
pub fn ingest(
    sources: &[SourceSpec],
    out_dir: &Path,
    opts: &IngestOptions,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<IngestReport, IngestError> {
    let staging = crate::corpus::staging::Staging::begin(out_dir)?;
    let report = build(sources, staging.dir(), opts, progress)?;
    staging.commit()?;
    Ok(report)
}

/// Build a corpus in the empty folder `out_dir`.
fn build(
    sources: &[SourceSpec],
    out_dir: &Path,
    opts: &IngestOptions,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<IngestReport, IngestError> {
    let body_model = match (
        &opts.body_model,
        sources.iter().any(|s| s.kind == SourceKind::Amass),
    ) {
        (Some(p), true) => Some(amass::BodyModel::load(p)?),
        (None, true) => return Err("amass sources need --body-model FILE.npz".into()),
        _ => None,
    };
    let readers: Vec<Reader> = sources
        .iter()
        .map(|s| {
            Ok(match s.kind {
                SourceKind::Bvh => Reader::Bvh(opts.map.as_ref()),
                SourceKind::Joints => Reader::Joints(opts.src_fps),
                SourceKind::Amass => Reader::Amass(body_model.as_ref().expect("loaded above")),
                SourceKind::Hml3d => Reader::Hml3d(hml3d::Hml3dFolder::open(&s.path)?),
                SourceKind::Synth => Reader::Synth(s.path.to_string_lossy().parse()?),
            })
        })
        .collect::<Result<_, IngestError>>()?;
    let mut units = Vec::new();
    let mut entries: Vec<SourceEntry> = Vec::new();
    for (i, spec) in sources.iter().enumerate() {
        let files = discover(spec, &readers[i])?;
        entries.push(SourceEntry {
            kind: spec.kind.name().to_string(),
            path: spec.path.display().to_string(),
            files: files.len() as u64,
            ..Default::default()
        });
        units.extend(files.into_iter().map(|item| Unit { source: i, item }));
    }
    let total = units.len() as u64;
    let done = std::sync::atomic::AtomicU64::new(0);
    let chunk = opts.chunk_units.max(1);
    let tmp = out_dir.join(".ingest-runs");
    let mut runs = RunSet::new(&tmp, units.len() > chunk);
    let mut totals = Totals::default();
    let mut rejects = Vec::new();
    let mut report = IngestReport {
        inputs: total,
        clips: 0,
        frames: 0,
        source_frames: 0,
        source_bytes: 0,
        rejects: 0,
        shards: 0,
    };
    let mut seen = HashSet::new();
    for part in units.chunks(chunk) {
        let outcomes: Vec<UnitOutcome> = part
            .par_iter()
            .map_init(Hml263Extractor::default, |extractor, u| {
                let o = process_unit(
                    &readers[u.source],
                    &sources[u.source],
                    &u.item,
                    opts,
                    extractor,
                );
                let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                progress(n, total);
                o
            })
            .collect();
        let mut records = Vec::new();
        for (unit, mut o) in part.iter().zip(outcomes) {
            let entry = &mut entries[unit.source];
            // Two inputs with the same id would collide: the first (in input order) wins.
            o.records.retain(|r| {
                let fresh = seen.insert(r.motion_id.clone());
                if !fresh {
                    o.rejects.push(RejectRecord {
                        path: r.source_path.clone(),
                        source: r.source.clone(),
                        clip: Some(r.motion_id.clone()),
                        stage: "dedupe".into(),
                        reason: format!(
                            "motion id {} already taken by an earlier input",
                            r.motion_id
                        ),
                    });
                }
                fresh
            });
            entry.ingested_files += u64::from(!o.records.is_empty());
            entry.rejects += o.rejects.len() as u64;
            for (k, v) in o.conversions {
                *entry.conversions.entry(k).or_default() += v;
            }
            report.source_frames += o.source_frames;
            report.source_bytes += o.bytes;
            o.records.iter().for_each(|r| totals.add(r));
            records.extend(o.records);
            rejects.extend(o.rejects);
        }
        runs.push(records)?;
    }
    rejects.sort_by(|a, b| (&a.path, &a.clip).cmp(&(&b.path, &b.clip)));
    report.rejects = rejects.len() as u64;
    report.clips = totals.clips_by_split.values().sum();
    report.frames = totals.frames_by_split.values().sum();
    let shards = runs.merge_into_shards(out_dir, opts.rows_per_shard)?;
    report.shards = shards.len() as u64;
    write_corpus(out_dir, shards, &totals, &rejects, opts, entries)?;
    Ok(report)
}

fn write_corpus(
    out_dir: &Path,
    shards: Vec<ShardEntry>,
    totals: &Totals,
    rejects: &[RejectRecord],
    opts: &IngestOptions,
    sources: Vec<SourceEntry>,
) -> Result<(), IngestError> {
    let shard_dir = out_dir.join("shards");
    std::fs::create_dir_all(&shard_dir).map_err(|e| IngestError::io(&shard_dir, e))?;
    let stats = &totals.stats;
    let (mean, std, degenerate) = stats.finish();
    let stats_json = serde_json::json!({
        "split": "train",
        "rows": stats.rows(),
        "mirrored_included": opts.mirror,
        "nan_clips": "rejected at ingest, so none enter the statistics",
        "convention": "mean per dimension over all frames of the train split; std per dimension (population), then replaced by its block average over [0:1],[1:3],[3:4],[4:67],[67:193],[193:259],[259:263] (HumanML3D). The HumanML3D release computed them over every clip, mirrored and test ones included.",
        "degenerate_blocks_set_to_one": degenerate,
    });
    let mut lines = String::new();
    for r in rejects {
        lines.push_str(&serde_json::to_string(r).expect("reject serialises"));
        lines.push('\n');
    }
    let files = [
        (
            "stats/mean.npy",
            crate::npy::encode_f32(&[FEATURE_DIM], &mean),
        ),
        (
            "stats/std.npy",
            crate::npy::encode_f32(&[FEATURE_DIM], &std),
        ),
        (
            "stats/stats.json",
            serde_json::to_string_pretty(&stats_json)
                .expect("json")
                .into_bytes(),
        ),
        ("rejects.jsonl", lines.into_bytes()),
    ];
    let mut file_sha256 = BTreeMap::new();
    for (rel, bytes) in files {
        let path = out_dir.join(rel);
        motionscale_core::write_atomic(&path, &bytes).map_err(|e| IngestError::io(&path, e))?;
        let sha = motionscale_core::hex(&sha2::Sha256::digest(&bytes));
        file_sha256.insert(rel.to_string(), sha);
    }

    let compatible = !opts.features.fix_facing;
    let manifest = Manifest {
        format: FORMAT.into(),
        format_version: FORMAT_VERSION,
        feature_convention: if compatible {
            "humanml3d-263".into()
        } else {
            "humanml3d-263-fixed-facing".into()
        },
        humanml3d_compatible: compatible,
        feature_dim: FEATURE_DIM,
        joint_set: "smpl-22".into(),
        units: "metres".into(),
        up_axis: "Y".into(),
        fps: opts.fps,
        options: BuildOptions {
            fps: opts.fps,
            mirror: opts.mirror,
            max_seconds: opts.max_seconds,
            min_frames: opts.min_frames,
            static_threshold: opts.static_threshold,
            feet_threshold: opts.features.feet_threshold,
            fix_facing: opts.features.fix_facing,
        },
        sources,
        shards,
        clips_by_split: totals.clips_by_split.clone(),
        frames_by_split: totals.frames_by_split.clone(),
        rejects: rejects.len() as u64,
        stats: [
            ("mean", "stats/mean.npy"),
            ("std", "stats/std.npy"),
            ("info", "stats/stats.json"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect(),
        file_sha256,
        text_embeddings: Vec::new(),
    };
    manifest.write(out_dir)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn source_spec_parses_and_explains() {
        let s: SourceSpec = "bvh:data/mocap".parse().unwrap();
        assert_eq!(s.kind, SourceKind::Bvh);
        assert_eq!(s.path, PathBuf::from("data/mocap"));
        assert!("fbx:x"
            .parse::<SourceSpec>()
            .unwrap_err()
            .contains("unknown source kind"));
        assert!("nocolon"
            .parse::<SourceSpec>()
            .unwrap_err()
            .contains("KIND:PATH"));
    }

    #[test]
    fn mirrored_captions_swap_sides() {
        assert_eq!(
            mirror_caption("A person waves the left hand, then Right."),
            "A person waves the right hand, then Left."
        );
        assert_eq!(mirror_caption("leftover"), "leftover");
    }

    #[test]
    fn segments_are_balanced_and_consecutive() {
        assert_eq!(segments(150, 200), vec![(0, 150)]);
        assert_eq!(segments(210, 200), vec![(0, 105), (105, 210)]);
        let s = segments(1000, 200);
        assert_eq!(s.len(), 5);
        assert!(s.windows(2).all(|w| w[0].1 == w[1].0));
        assert!(s.iter().all(|(a, b)| b - a <= 200));
    }
}
