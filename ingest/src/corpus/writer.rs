//! Shard writer: clips → zstd Parquet (byte-stream-split floats), written atomically.

use super::schema::{col, list_item, shard_schema};
use super::ClipRecord;
use crate::corpus::manifest::ShardEntry;
use crate::error::IngestError;
use arrow_array::builder::{
    BooleanBuilder, Float32Builder, Float64Builder, ListBuilder, StringBuilder, UInt32Builder,
};
use arrow_array::{ArrayRef, RecordBatch};
use arrow_schema::DataType;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, Encoding, ZstdLevel};
use parquet::file::properties::WriterProperties;
use parquet::schema::types::ColumnPath;
use sha2::{Digest, Sha256};
use std::path::Path;
use std::sync::Arc;

/// Clips per row group: small groups let readers decode one clip without its neighbours.
pub const ROW_GROUP_ROWS: usize = 32;

fn properties(compression: Compression) -> WriterProperties {
    let float_list = |name: &str| ColumnPath::new(vec![name.into(), "list".into(), "item".into()]);
    let mut props = WriterProperties::builder()
        .set_compression(compression)
        .set_max_row_group_row_count(Some(ROW_GROUP_ROWS));
    // Byte-stream-split groups the float bytes by significance, which zstd compresses far
    // better than plain IEEE values; dictionaries are useless for continuous data.
    for name in [col::FEATURES, col::JOINTS] {
        props = props
            .set_column_dictionary_enabled(float_list(name), false)
            .set_column_encoding(float_list(name), Encoding::BYTE_STREAM_SPLIT);
    }
    props.build()
}

fn batch(clips: &[ClipRecord]) -> Result<RecordBatch, IngestError> {
    let n = clips.len();
    let strings = |f: &dyn Fn(&ClipRecord) -> Option<&str>| {
        let mut b = StringBuilder::with_capacity(n, n * 16);
        clips.iter().for_each(|c| b.append_option(f(c)));
        Arc::new(b.finish()) as ArrayRef
    };
    let u32s = |f: &dyn Fn(&ClipRecord) -> u32| {
        let mut b = UInt32Builder::with_capacity(n);
        clips.iter().for_each(|c| b.append_value(f(c)));
        Arc::new(b.finish()) as ArrayRef
    };
    let f32s = |f: &dyn Fn(&ClipRecord) -> f32| {
        let mut b = Float32Builder::with_capacity(n);
        clips.iter().for_each(|c| b.append_value(f(c)));
        Arc::new(b.finish()) as ArrayRef
    };
    let float_lists = |f: &dyn Fn(&ClipRecord) -> &[f32]| {
        let total = clips.iter().map(|c| f(c).len()).sum();
        let mut b = ListBuilder::with_capacity(Float32Builder::with_capacity(total), n)
            .with_field(list_item(DataType::Float32));
        for c in clips {
            b.values().append_slice(f(c));
            b.append(true);
        }
        Arc::new(b.finish()) as ArrayRef
    };
    let mut captions = ListBuilder::new(StringBuilder::new()).with_field(list_item(DataType::Utf8));
    for c in clips {
        c.captions
            .iter()
            .for_each(|s| captions.values().append_value(s));
        captions.append(true);
    }
    let mut mirrored = BooleanBuilder::with_capacity(n);
    clips.iter().for_each(|c| mirrored.append_value(c.mirrored));
    let mut spans =
        ListBuilder::new(Float64Builder::new()).with_field(list_item(DataType::Float64));
    for c in clips {
        match &c.span {
            Some(span) => {
                for &(start, end) in &span.seconds {
                    spans.values().append_slice(&[start, end]);
                }
                spans.append(true);
            }
            None => spans.append_null(),
        }
    }
    let columns: Vec<ArrayRef> = vec![
        strings(&|c| Some(&c.motion_id)),
        strings(&|c| Some(&c.source)),
        strings(&|c| Some(&c.source_path)),
        strings(&|c| Some(&c.source_clip)),
        u32s(&|c| c.segment),
        f32s(&|c| c.fps),
        f32s(&|c| c.source_fps),
        u32s(&|c| c.num_frames),
        float_lists(&|c| &c.features),
        float_lists(&|c| &c.joints),
        Arc::new(captions.finish()),
        strings(&|c| c.labels.action.as_deref()),
        strings(&|c| c.labels.style.as_deref()),
        strings(&|c| c.labels.emotion.as_deref()),
        strings(&|c| c.labels.scenario.as_deref()),
        strings(&|c| Some(&c.split)),
        Arc::new(mirrored.finish()),
        strings(&|c| c.span.as_ref().map(|s| s.of.as_str())),
        Arc::new(spans.finish()),
    ];
    RecordBatch::try_new(shard_schema(), columns).map_err(|e| IngestError::from(e.to_string()))
}

/// Encode clips as one zstd Parquet file in memory.
pub fn encode_shard(clips: &[ClipRecord]) -> Result<Vec<u8>, IngestError> {
    encode(
        clips,
        Compression::ZSTD(ZstdLevel::try_new(3).expect("valid level")),
    )
}

/// Encode clips as an uncompressed Parquet file (temporary runs, read back once).
pub fn encode_run(clips: &[ClipRecord]) -> Result<Vec<u8>, IngestError> {
    encode(clips, Compression::UNCOMPRESSED)
}

fn encode(clips: &[ClipRecord], compression: Compression) -> Result<Vec<u8>, IngestError> {
    let mut out = Vec::new();
    let mut writer = ArrowWriter::try_new(&mut out, shard_schema(), Some(properties(compression)))
        .map_err(|e| e.to_string())?;
    for chunk in clips.chunks(ROW_GROUP_ROWS) {
        writer.write(&batch(chunk)?).map_err(|e| e.to_string())?;
    }
    writer.close().map_err(|e| e.to_string())?;
    Ok(out)
}

/// Write clips as the shard `corpus_dir/rel_file` (temp file + rename) and describe it.
pub fn write_shard(
    corpus_dir: &Path,
    rel_file: &str,
    clips: &[ClipRecord],
) -> Result<ShardEntry, IngestError> {
    let bytes = encode_shard(clips)?;
    let path = corpus_dir.join(rel_file);
    motionscale_core::write_atomic(&path, &bytes).map_err(|e| IngestError::io(&path, e))?;
    Ok(ShardEntry {
        file: rel_file.to_string(),
        rows: clips.len() as u64,
        frames: clips.iter().map(|c| c.num_frames as u64).sum(),
        sha256: motionscale_core::hex(&Sha256::digest(&bytes)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::corpus::reader::records_from_batch;
    use crate::corpus::schema::legacy_shard_schema;
    use crate::corpus::CaptionSpan;
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;

    fn clip(id: &str, span: Option<CaptionSpan>) -> ClipRecord {
        ClipRecord {
            motion_id: id.into(),
            source: "hml3d".into(),
            source_path: "a.npy".into(),
            source_clip: id.into(),
            segment: 0,
            fps: 20.0,
            source_fps: 20.0,
            num_frames: 1,
            features: vec![0.5; super::super::schema::FEATURE_DIM],
            joints: vec![0.25; 2 * super::super::schema::JOINT_FRAME_DIM],
            captions: vec!["he waves.".into(), "a wave.".into()],
            labels: Default::default(),
            split: "train".into(),
            mirrored: false,
            span,
        }
    }

    #[test]
    fn spans_round_trip_and_shards_without_them_still_read() {
        let span = CaptionSpan {
            of: "a".into(),
            seconds: vec![(0.5, 2.0), (0.5, 2.25)],
        };
        let clips = vec![clip("a", None), clip("a_10_40", Some(span))];
        let bytes = bytes::Bytes::from(encode_shard(&clips).unwrap());
        let mut reader = ParquetRecordBatchReaderBuilder::try_new(bytes)
            .unwrap()
            .build()
            .unwrap();
        let batch = reader.next().unwrap().unwrap();
        assert_eq!(records_from_batch(&batch).unwrap(), clips);
        // A shard written before the span columns existed: the same clips, without spans.
        let legacy_fields = legacy_shard_schema().fields().len();
        let legacy = batch
            .project(&(0..legacy_fields).collect::<Vec<_>>())
            .unwrap();
        assert_eq!(legacy.schema().fields(), legacy_shard_schema().fields());
        let read = records_from_batch(&legacy).unwrap();
        assert!(read.iter().all(|c| c.span.is_none()));
        assert_eq!(read[1].captions, clips[1].captions);
    }
}
