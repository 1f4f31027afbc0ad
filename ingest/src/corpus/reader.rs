//! Corpus reader: memory-maps the shards and decodes single clips or feature windows on
//! demand (row-group and page skipping), so the corpus is never loaded whole.

use super::manifest::Manifest;
use super::schema::{col, FEATURE_DIM};
use super::{CaptionSpan, ClipRecord};
use crate::error::IngestError;
use crate::source::Labels;
use arrow_array::cast::AsArray;
use arrow_array::types::{Float32Type, Float64Type, UInt32Type};
use arrow_array::{Array, RecordBatch};
use bytes::Bytes;
use motionscale_core::rng::SplitMix64;
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelection,
    RowSelector,
};
use parquet::arrow::ProjectionMask;
use parquet::file::metadata::PageIndexPolicy;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Where a clip lives and what a sampler needs to know about it without decoding it.
#[derive(Debug, Clone, PartialEq)]
pub struct ClipEntry {
    /// Clip id.
    pub motion_id: String,
    /// Split.
    pub split: String,
    /// Feature rows.
    pub num_frames: u32,
    shard: usize,
    row_group: usize,
    row: usize,
}

/// The small columns of a clip (no features or joints).
#[derive(Debug, Clone, PartialEq)]
pub struct ClipMeta {
    /// Clip id.
    pub motion_id: String,
    /// Source kind.
    pub source: String,
    /// Source clip id (shared by segments and mirrored copies).
    pub source_clip: String,
    /// Split.
    pub split: String,
    /// Frame rate.
    pub fps: f32,
    /// Feature rows.
    pub num_frames: u32,
    /// Labels.
    pub labels: Labels,
    /// Mirrored copy flag.
    pub mirrored: bool,
}

struct Shard {
    bytes: Bytes,
    metadata: ArrowReaderMetadata,
}

/// An opened corpus.
pub struct Corpus {
    dir: PathBuf,
    manifest: Manifest,
    shards: Vec<Shard>,
    clips: Vec<ClipEntry>,
    by_id: HashMap<String, usize>,
    mean: Vec<f32>,
    std: Vec<f32>,
}

fn ctx<E: std::fmt::Display>(path: &Path) -> impl Fn(E) -> IngestError + '_ {
    IngestError::at(path)
}

fn column<'a>(batch: &'a RecordBatch, name: &str) -> Result<&'a dyn Array, IngestError> {
    batch
        .column_by_name(name)
        .map(|c| c.as_ref())
        .ok_or_else(|| IngestError::from(format!("column {name} missing")))
}

fn strings(batch: &RecordBatch, name: &str) -> Result<Vec<Option<String>>, IngestError> {
    let arr = column(batch, name)?
        .as_string_opt::<i32>()
        .ok_or_else(|| format!("column {name} is not utf8"))?;
    Ok(arr.iter().map(|v| v.map(str::to_string)).collect())
}

fn required(v: Option<String>, name: &str) -> Result<String, IngestError> {
    v.ok_or_else(|| IngestError::from(format!("null in required column {name}")))
}

fn float_lists(batch: &RecordBatch, name: &str) -> Result<Vec<Vec<f32>>, IngestError> {
    let list = column(batch, name)?
        .as_list_opt::<i32>()
        .ok_or_else(|| format!("column {name} is not a list"))?;
    (0..list.len())
        .map(|i| {
            let v = list.value(i);
            v.as_primitive_opt::<Float32Type>()
                .map(|p| p.values().to_vec())
                .ok_or_else(|| IngestError::from(format!("column {name} does not hold f32")))
        })
        .collect()
}

/// The caption spans of every row: `None` where `span_of` is null or the shard predates it.
fn caption_spans(batch: &RecordBatch) -> Result<Vec<Option<CaptionSpan>>, IngestError> {
    let rows = batch.num_rows();
    if batch.column_by_name(col::SPAN_OF).is_none() {
        return Ok(vec![None; rows]);
    }
    let of = strings(batch, col::SPAN_OF)?;
    let seconds = column(batch, col::CAPTION_SPANS)?
        .as_list_opt::<i32>()
        .ok_or("column caption_spans is not a list")?;
    (0..rows)
        .map(|i| {
            let Some(of) = of[i].clone() else {
                return Ok(None);
            };
            let values = seconds.value(i);
            let values = values
                .as_primitive_opt::<Float64Type>()
                .ok_or("column caption_spans does not hold f64")?;
            let seconds = values
                .values()
                .chunks_exact(2)
                .map(|p| (p[0], p[1]))
                .collect();
            Ok(Some(CaptionSpan { of, seconds }))
        })
        .collect()
}

/// Decode a record batch of the shard schema (with or without its optional columns) into clips.
pub fn records_from_batch(batch: &RecordBatch) -> Result<Vec<ClipRecord>, IngestError> {
    let ids = strings(batch, col::MOTION_ID)?;
    let sources = strings(batch, col::SOURCE)?;
    let paths = strings(batch, col::SOURCE_PATH)?;
    let source_clips = strings(batch, col::SOURCE_CLIP)?;
    let u32s = |name| -> Result<Vec<u32>, IngestError> {
        Ok(column(batch, name)?
            .as_primitive_opt::<UInt32Type>()
            .ok_or_else(|| format!("column {name} is not u32"))?
            .values()
            .to_vec())
    };
    let f32s = |name| -> Result<Vec<f32>, IngestError> {
        Ok(column(batch, name)?
            .as_primitive_opt::<Float32Type>()
            .ok_or_else(|| format!("column {name} is not f32"))?
            .values()
            .to_vec())
    };
    let segments = u32s(col::SEGMENT)?;
    let num_frames = u32s(col::NUM_FRAMES)?;
    let fps = f32s(col::FPS)?;
    let source_fps = f32s(col::SOURCE_FPS)?;
    let features = float_lists(batch, col::FEATURES)?;
    let joints = float_lists(batch, col::JOINTS)?;
    let captions_list = column(batch, col::CAPTIONS)?
        .as_list_opt::<i32>()
        .ok_or("column captions is not a list")?;
    let actions = strings(batch, col::ACTION)?;
    let styles = strings(batch, col::STYLE)?;
    let emotions = strings(batch, col::EMOTION)?;
    let scenarios = strings(batch, col::SCENARIO)?;
    let splits = strings(batch, col::SPLIT)?;
    let mirrored = column(batch, col::MIRRORED)?
        .as_boolean_opt()
        .ok_or("column mirrored is not boolean")?;
    let mut spans = caption_spans(batch)?;
    let mut out = Vec::with_capacity(batch.num_rows());
    for (i, (features, joints)) in features.into_iter().zip(joints).enumerate() {
        let caps = captions_list.value(i);
        let caps = caps.as_string_opt::<i32>().ok_or("captions are not utf8")?;
        out.push(ClipRecord {
            motion_id: required(ids[i].clone(), col::MOTION_ID)?,
            source: required(sources[i].clone(), col::SOURCE)?,
            source_path: required(paths[i].clone(), col::SOURCE_PATH)?,
            source_clip: required(source_clips[i].clone(), col::SOURCE_CLIP)?,
            segment: segments[i],
            fps: fps[i],
            source_fps: source_fps[i],
            num_frames: num_frames[i],
            features,
            joints,
            captions: caps.iter().flatten().map(str::to_string).collect(),
            labels: Labels {
                action: actions[i].clone(),
                style: styles[i].clone(),
                emotion: emotions[i].clone(),
                scenario: scenarios[i].clone(),
            },
            split: required(splits[i].clone(), col::SPLIT)?,
            mirrored: mirrored.value(i),
            span: spans[i].take(),
        });
    }
    Ok(out)
}

impl Corpus {
    /// Open a corpus folder: read the manifest, refuse the corpus unless its files match it
    /// ([`super::integrity::check`]), map every shard, index clips from the small columns.
    pub fn open(dir: &Path) -> Result<Self, IngestError> {
        let manifest = super::integrity::read_checked(dir)?;
        let mut shards = Vec::with_capacity(manifest.shards.len());
        let mut clips = Vec::new();
        for (shard_idx, entry) in manifest.shards.iter().enumerate() {
            let path = dir.join(&entry.file);
            let file = std::fs::File::open(&path).map_err(ctx(&path))?;
            // SAFETY: shards are written once (temp + rename) and never modified in place.
            let map = unsafe { memmap2::Mmap::map(&file) }.map_err(ctx(&path))?;
            let bytes = Bytes::from_owner(map);
            let options =
                ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Optional);
            let metadata = ArrowReaderMetadata::load(&bytes, options).map_err(ctx(&path))?;
            let shard = Shard { bytes, metadata };
            let mask = shard.projection(&[col::MOTION_ID, col::SPLIT, col::NUM_FRAMES]);
            let reader = shard
                .builder()
                .with_projection(mask)
                .build()
                .map_err(ctx(&path))?;
            let group_rows: Vec<usize> = shard
                .metadata
                .metadata()
                .row_groups()
                .iter()
                .map(|g| g.num_rows() as usize)
                .collect();
            let mut locations = group_rows
                .iter()
                .enumerate()
                .flat_map(|(g, &n)| (0..n).map(move |r| (g, r)));
            for batch in reader {
                let batch = batch.map_err(ctx(&path))?;
                let ids = strings(&batch, col::MOTION_ID).map_err(ctx(&path))?;
                let splits = strings(&batch, col::SPLIT).map_err(ctx(&path))?;
                let frames = column(&batch, col::NUM_FRAMES)
                    .map_err(ctx(&path))?
                    .as_primitive_opt::<UInt32Type>()
                    .ok_or_else(|| IngestError::file(&path, "num_frames is not u32"))?;
                for ((id, split), &n) in ids.into_iter().zip(splits).zip(frames.values()) {
                    let (row_group, row) = locations
                        .next()
                        .ok_or_else(|| IngestError::file(&path, "more rows than metadata"))?;
                    clips.push(ClipEntry {
                        motion_id: required(id, col::MOTION_ID).map_err(ctx(&path))?,
                        split: required(split, col::SPLIT).map_err(ctx(&path))?,
                        num_frames: n,
                        shard: shard_idx,
                        row_group,
                        row,
                    });
                }
            }
            shards.push(shard);
        }
        let mut by_id = HashMap::with_capacity(clips.len());
        for (i, c) in clips.iter().enumerate() {
            if let Some(first) = by_id.insert(c.motion_id.clone(), i) {
                let file = |k: usize| dir.join(&manifest.shards[clips[k].shard].file);
                return Err(format!(
                    "corpus refused: {}: motion id {} is already in {} (two writers or a \
                     duplicated shard)",
                    file(i).display(),
                    c.motion_id,
                    file(first).display()
                )
                .into());
            }
        }
        let read_stat = |name: &str| -> Result<Vec<f32>, IngestError> {
            let path = dir.join("stats").join(name);
            let arr = crate::npy::read(&path)?;
            match stats_problem(name, &arr) {
                Some(problem) => {
                    Err(format!("corpus refused: {}: {problem}", path.display()).into())
                }
                None => Ok(arr.data.iter().map(|&v| v as f32).collect()),
            }
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            mean: read_stat("mean.npy")?,
            std: read_stat("std.npy")?,
            manifest,
            shards,
            clips,
            by_id,
        })
    }

    /// The corpus folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Every clip, in shard order (sorted by id).
    pub fn clips(&self) -> &[ClipEntry] {
        &self.clips
    }

    /// Training-split feature mean (263).
    pub fn mean(&self) -> &[f32] {
        &self.mean
    }

    /// Training-split block-averaged feature std (263).
    pub fn std(&self) -> &[f32] {
        &self.std
    }

    /// Index of a clip by id.
    pub fn find(&self, motion_id: &str) -> Option<usize> {
        self.by_id.get(motion_id).copied()
    }

    /// Decode one whole clip.
    pub fn clip(&self, index: usize) -> Result<ClipRecord, IngestError> {
        let batch = self.read_row(index, None)?;
        records_from_batch(&batch)?
            .pop()
            .ok_or_else(|| IngestError::from(format!("clip {index} not found in its shard")))
    }

    /// Decode only the (num_frames × 263) features of one clip.
    pub fn features(&self, index: usize) -> Result<Vec<f32>, IngestError> {
        let batch = self.read_row(index, Some(&[col::FEATURES]))?;
        float_lists(&batch, col::FEATURES)?
            .pop()
            .ok_or_else(|| IngestError::from(format!("clip {index} not found in its shard")))
    }

    /// Decode the features of every clip whose index `keep` accepts, a whole shard at a time
    /// (far faster than one [`Corpus::features`] call per clip): (clip index, num_frames × 263
    /// values), in index order.
    pub fn features_where(
        &self,
        keep: impl Fn(usize) -> bool,
    ) -> Result<Vec<(usize, Vec<f32>)>, IngestError> {
        let mut out = Vec::new();
        let mut first = 0;
        for (i, shard) in self.shards.iter().enumerate() {
            let rows = self.manifest.shards[i].rows as usize;
            let range = first..first + rows;
            first += rows;
            if !range.clone().any(&keep) {
                continue;
            }
            let path = self.dir.join(&self.manifest.shards[i].file);
            let reader = shard
                .builder()
                .with_projection(shard.projection(&[col::FEATURES]))
                .build()
                .map_err(ctx(&path))?;
            let mut index = range.start;
            for batch in reader {
                for feats in float_lists(&batch.map_err(ctx(&path))?, col::FEATURES)? {
                    if keep(index) {
                        out.push((index, feats));
                    }
                    index += 1;
                }
            }
        }
        Ok(out)
    }

    /// Decode every clip of one shard, in order (for export, stats and verification).
    pub fn shard_records(&self, shard: usize) -> Result<Vec<ClipRecord>, IngestError> {
        let s = &self.shards[shard];
        let path = self.dir.join(&self.manifest.shards[shard].file);
        let reader = s.builder().build().map_err(ctx(&path))?;
        let mut out = Vec::new();
        for batch in reader {
            out.extend(records_from_batch(&batch.map_err(ctx(&path))?).map_err(ctx(&path))?);
        }
        Ok(out)
    }

    /// Ids, labels and sizes of every clip, decoding only the small columns.
    pub fn clip_metadata(&self) -> Result<Vec<ClipMeta>, IngestError> {
        let mut out = Vec::with_capacity(self.clips.len());
        for (i, shard) in self.shards.iter().enumerate() {
            let path = self.dir.join(&self.manifest.shards[i].file);
            let mask = shard.projection(&[
                col::MOTION_ID,
                col::SOURCE,
                col::SOURCE_CLIP,
                col::FPS,
                col::NUM_FRAMES,
                col::ACTION,
                col::STYLE,
                col::EMOTION,
                col::SCENARIO,
                col::SPLIT,
                col::MIRRORED,
            ]);
            let reader = shard
                .builder()
                .with_projection(mask)
                .build()
                .map_err(ctx(&path))?;
            for batch in reader {
                let b = batch.map_err(ctx(&path))?;
                let get = |name| strings(&b, name).map_err(ctx(&path));
                let (ids, sources, splits) =
                    (get(col::MOTION_ID)?, get(col::SOURCE)?, get(col::SPLIT)?);
                let source_clips = get(col::SOURCE_CLIP)?;
                let (actions, styles) = (get(col::ACTION)?, get(col::STYLE)?);
                let (emotions, scenarios) = (get(col::EMOTION)?, get(col::SCENARIO)?);
                let fps = column(&b, col::FPS)?
                    .as_primitive_opt::<Float32Type>()
                    .ok_or("fps is not f32")?;
                let frames = column(&b, col::NUM_FRAMES)?
                    .as_primitive_opt::<UInt32Type>()
                    .ok_or("num_frames is not u32")?;
                let mirrored = column(&b, col::MIRRORED)?
                    .as_boolean_opt()
                    .ok_or("mirrored is not boolean")?;
                for r in 0..b.num_rows() {
                    out.push(ClipMeta {
                        motion_id: required(ids[r].clone(), col::MOTION_ID)?,
                        source: required(sources[r].clone(), col::SOURCE)?,
                        source_clip: required(source_clips[r].clone(), col::SOURCE_CLIP)?,
                        split: required(splits[r].clone(), col::SPLIT)?,
                        fps: fps.value(r),
                        num_frames: frames.value(r),
                        labels: Labels {
                            action: actions[r].clone(),
                            style: styles[r].clone(),
                            emotion: emotions[r].clone(),
                            scenario: scenarios[r].clone(),
                        },
                        mirrored: mirrored.value(r),
                    });
                }
            }
        }
        Ok(out)
    }

    fn read_row(&self, index: usize, columns: Option<&[&str]>) -> Result<RecordBatch, IngestError> {
        let entry = self
            .clips
            .get(index)
            .ok_or_else(|| format!("no clip {index}"))?;
        let shard = &self.shards[entry.shard];
        let path = self.dir.join(&self.manifest.shards[entry.shard].file);
        let mut builder = shard
            .builder()
            .with_row_groups(vec![entry.row_group])
            .with_row_selection(RowSelection::from(vec![
                RowSelector::skip(entry.row),
                RowSelector::select(1),
            ]));
        if let Some(cols) = columns {
            builder = builder.with_projection(shard.projection(cols));
        }
        let mut reader = builder.build().map_err(ctx(&path))?;
        reader
            .next()
            .ok_or_else(|| IngestError::file(&path, format!("row {} missing", entry.row)))?
            .map_err(ctx(&path))
    }

    /// A seeded sampler of normalised feature windows from one split.
    pub fn window_sampler(&self, split: &str, window: usize, seed: u64) -> WindowSampler<'_> {
        let eligible: Vec<usize> = (0..self.clips.len())
            .filter(|&i| {
                self.clips[i].split == split && self.clips[i].num_frames as usize >= window
            })
            .collect();
        // Weight clips by their number of windows so every window is equally likely.
        let mut cumulative = Vec::with_capacity(eligible.len());
        let mut total = 0u64;
        for &i in &eligible {
            total += (self.clips[i].num_frames as usize - window + 1) as u64;
            cumulative.push(total);
        }
        WindowSampler {
            corpus: self,
            window,
            eligible,
            cumulative,
            rng: SplitMix64(seed),
            cache: None,
        }
    }
}

/// What is wrong with the statistics file `name` (`mean.npy` or `std.npy`), if anything:
/// 263 finite values, and a positive std (features are divided by it).
pub fn stats_problem(name: &str, arr: &crate::npy::NpyArray) -> Option<String> {
    if arr.shape != [FEATURE_DIM] {
        return Some(format!("shape {:?}, expected [{FEATURE_DIM}]", arr.shape));
    }
    if let Some(i) = arr.data.iter().position(|x| !x.is_finite()) {
        return Some(format!("non-finite value {} at dimension {i}", arr.data[i]));
    }
    match arr.data.iter().position(|&x| x <= 0.0) {
        Some(i) if name == "std.npy" => {
            Some(format!("non-positive std {} at dimension {i}", arr.data[i]))
        }
        _ => None,
    }
}

impl Shard {
    fn builder(&self) -> ParquetRecordBatchReaderBuilder<Bytes> {
        ParquetRecordBatchReaderBuilder::new_with_metadata(
            self.bytes.clone(),
            self.metadata.clone(),
        )
    }

    fn projection(&self, names: &[&str]) -> ProjectionMask {
        let fields = self.metadata.schema().fields();
        let roots = names
            .iter()
            .filter_map(|n| fields.iter().position(|f| f.name() == n));
        ProjectionMask::roots(self.metadata.parquet_schema(), roots)
    }
}

/// Seeded random windows of normalised features; see [`Corpus::window_sampler`].
pub struct WindowSampler<'a> {
    corpus: &'a Corpus,
    window: usize,
    eligible: Vec<usize>,
    cumulative: Vec<u64>,
    rng: SplitMix64,
    /// Normalised features of every eligible clip, when preloaded.
    cache: Option<Vec<Vec<f32>>>,
}

/// Where a sampled window came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowOrigin {
    /// Clip index in the corpus.
    pub clip: usize,
    /// First feature row of the window.
    pub start: usize,
}

impl WindowSampler<'_> {
    /// Number of clips long enough for a window.
    pub fn eligible_clips(&self) -> usize {
        self.eligible.len()
    }

    /// Decode and normalise every eligible clip once, into memory, so that [`Self::sample`]
    /// decodes nothing (training loops draw thousands of batches).
    pub fn preload(mut self) -> Result<Self, IngestError> {
        let eligible: HashMap<usize, usize> = self
            .eligible
            .iter()
            .enumerate()
            .map(|(k, &i)| (i, k))
            .collect();
        let mut cache = vec![Vec::new(); self.eligible.len()];
        let (mean, std) = (self.corpus.mean(), self.corpus.std());
        for (index, mut feats) in self.corpus.features_where(|i| eligible.contains_key(&i))? {
            feats.chunks_exact_mut(FEATURE_DIM).for_each(|row| {
                row.iter_mut()
                    .enumerate()
                    .for_each(|(d, v)| *v = (*v - mean[d]) / std[d])
            });
            cache[eligible[&index]] = feats;
        }
        self.cache = Some(cache);
        Ok(self)
    }

    /// Restart the generator from `seed` (e.g. a per-step seed, so that a resumed run draws
    /// the same batches as an uninterrupted one).
    pub fn reseed(&mut self, seed: u64) {
        self.rng = SplitMix64(seed);
    }

    /// Draw `batch` windows: returns (batch × window × 263) normalised features and their origins.
    /// Each distinct clip in the batch is decoded once (not at all when preloaded).
    pub fn sample(&mut self, batch: usize) -> Result<(Vec<f32>, Vec<WindowOrigin>), IngestError> {
        let total = *self
            .cumulative
            .last()
            .ok_or("no clip in this split is as long as the window")?;
        // (position in `eligible`, first row) of each window.
        let picks: Vec<(usize, usize)> = (0..batch)
            .map(|_| {
                let pick = self.rng.below(total);
                let k = self.cumulative.partition_point(|&c| c <= pick);
                let before = if k == 0 { 0 } else { self.cumulative[k - 1] };
                (k, (pick - before) as usize)
            })
            .collect();
        let origins: Vec<WindowOrigin> = picks
            .iter()
            .map(|&(k, start)| WindowOrigin {
                clip: self.eligible[k],
                start,
            })
            .collect();
        let row = self.window * FEATURE_DIM;
        let mut out = vec![0f32; batch * row];
        if let Some(cache) = &self.cache {
            for (dst, &(k, start)) in out.chunks_exact_mut(row).zip(&picks) {
                dst.copy_from_slice(&cache[k][start * FEATURE_DIM..][..row]);
            }
            return Ok((out, origins));
        }
        let mut order: Vec<usize> = (0..batch).collect();
        order.sort_by_key(|&b| origins[b].clip);
        let (mean, std) = (self.corpus.mean(), self.corpus.std());
        let mut cached: Option<(usize, Vec<f32>)> = None;
        for b in order {
            let o = origins[b];
            if cached.as_ref().map(|c| c.0) != Some(o.clip) {
                cached = Some((o.clip, self.corpus.features(o.clip)?));
            }
            let feats = &cached.as_ref().expect("just filled").1;
            let src = &feats[o.start * FEATURE_DIM..(o.start + self.window) * FEATURE_DIM];
            for (dst, chunk) in out[b * row..(b + 1) * row]
                .chunks_exact_mut(FEATURE_DIM)
                .zip(src.chunks_exact(FEATURE_DIM))
            {
                for d in 0..FEATURE_DIM {
                    dst[d] = (chunk[d] - mean[d]) / std[d];
                }
            }
        }
        Ok((out, origins))
    }
}
