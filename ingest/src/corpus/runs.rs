//! Sorted runs of clips and their k-way merge into shards, so a corpus larger than memory
//! can be built: each chunk of clips is sorted by id and kept in memory (small builds) or
//! spilled to a temporary Parquet file, then all runs are merged in id order.

use super::manifest::ShardEntry;
use super::reader::records_from_batch;
use super::writer::{encode_run, write_shard, ROW_GROUP_ROWS};
use super::ClipRecord;
use crate::error::IngestError;
use parquet::arrow::arrow_reader::{ParquetRecordBatchReader, ParquetRecordBatchReaderBuilder};
use rayon::prelude::*;
use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};
use std::path::{Path, PathBuf};

enum Run {
    Memory(Vec<ClipRecord>),
    File(PathBuf),
}

/// Runs collected so far.
pub struct RunSet {
    dir: PathBuf,
    spill: bool,
    runs: Vec<Run>,
}

enum Cursor {
    Memory(std::vec::IntoIter<ClipRecord>),
    File {
        path: PathBuf,
        reader: ParquetRecordBatchReader,
        buffered: VecDeque<ClipRecord>,
    },
}

impl Cursor {
    fn next(&mut self) -> Result<Option<ClipRecord>, IngestError> {
        match self {
            Cursor::Memory(it) => Ok(it.next()),
            Cursor::File {
                path,
                reader,
                buffered,
            } => {
                if buffered.is_empty() {
                    if let Some(batch) = reader.next() {
                        let batch = batch.map_err(IngestError::at(path))?;
                        buffered.extend(records_from_batch(&batch)?);
                    }
                }
                Ok(buffered.pop_front())
            }
        }
    }
}

impl RunSet {
    /// Runs spilled under `dir` when `spill` is set (the folder is created on first spill).
    pub fn new(dir: &Path, spill: bool) -> Self {
        Self {
            dir: dir.to_path_buf(),
            spill,
            runs: Vec::new(),
        }
    }

    /// Add a chunk of clips (any order).
    pub fn push(&mut self, mut records: Vec<ClipRecord>) -> Result<(), IngestError> {
        records.sort_by(|a, b| a.motion_id.cmp(&b.motion_id));
        if !self.spill {
            self.runs.push(Run::Memory(records));
            return Ok(());
        }
        let path = self.dir.join(format!("run-{:05}.parquet", self.runs.len()));
        let bytes = encode_run(&records)?;
        motionscale_core::write_atomic(&path, &bytes).map_err(|e| IngestError::io(&path, e))?;
        self.runs.push(Run::File(path));
        Ok(())
    }

    /// Merge every run in id order into `shards/shard-NNNNN.parquet` files of `rows_per_shard`
    /// clips under `out_dir`, encoding up to one shard per worker thread at a time. Spilled
    /// runs are deleted afterwards.
    pub fn merge_into_shards(
        self,
        out_dir: &Path,
        rows_per_shard: usize,
    ) -> Result<Vec<ShardEntry>, IngestError> {
        let mut cursors = Vec::with_capacity(self.runs.len());
        for run in self.runs {
            cursors.push(match run {
                Run::Memory(v) => Cursor::Memory(v.into_iter()),
                Run::File(path) => {
                    let file = std::fs::File::open(&path).map_err(|e| IngestError::io(&path, e))?;
                    let reader = ParquetRecordBatchReaderBuilder::try_new(file)
                        .and_then(|b| b.with_batch_size(ROW_GROUP_ROWS).build())
                        .map_err(IngestError::at(&path))?;
                    Cursor::File {
                        path,
                        reader,
                        buffered: VecDeque::new(),
                    }
                }
            });
        }
        let mut heads: Vec<Option<ClipRecord>> = Vec::with_capacity(cursors.len());
        let mut heap = BinaryHeap::new();
        for (i, c) in cursors.iter_mut().enumerate() {
            let head = c.next()?;
            if let Some(r) = &head {
                heap.push(Reverse((r.motion_id.clone(), i)));
            }
            heads.push(head);
        }
        let rows_per_shard = rows_per_shard.max(1);
        let batch = rayon::current_num_threads().max(1);
        let mut shards = Vec::new();
        let mut pending: Vec<Vec<ClipRecord>> = Vec::new();
        let mut current = Vec::with_capacity(rows_per_shard);
        let flush = |pending: &mut Vec<Vec<ClipRecord>>,
                     shards: &mut Vec<ShardEntry>|
         -> Result<(), IngestError> {
            let first = shards.len();
            let written: Vec<ShardEntry> = pending
                .par_iter()
                .enumerate()
                .map(|(k, clips)| {
                    write_shard(
                        out_dir,
                        &format!("shards/shard-{:05}.parquet", first + k),
                        clips,
                    )
                })
                .collect::<Result<_, _>>()?;
            shards.extend(written);
            pending.clear();
            Ok(())
        };
        while let Some(Reverse((_, i))) = heap.pop() {
            let record = heads[i].take().expect("a head for every heap entry");
            heads[i] = cursors[i].next()?;
            if let Some(r) = &heads[i] {
                heap.push(Reverse((r.motion_id.clone(), i)));
            }
            current.push(record);
            if current.len() == rows_per_shard {
                pending.push(std::mem::replace(
                    &mut current,
                    Vec::with_capacity(rows_per_shard),
                ));
                if pending.len() == batch {
                    flush(&mut pending, &mut shards)?;
                }
            }
        }
        if !current.is_empty() {
            pending.push(current);
        }
        flush(&mut pending, &mut shards)?;
        if self.spill && self.dir.is_dir() {
            std::fs::remove_dir_all(&self.dir).map_err(|e| IngestError::io(&self.dir, e))?;
        }
        Ok(shards)
    }
}
