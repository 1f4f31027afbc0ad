//! The shard schema, declared once: every writer and reader goes through these fields.

use arrow_schema::{DataType, Field, FieldRef, Schema};
use std::sync::Arc;

pub use crate::hml263::FEATURE_DIM;
/// Number of f32 values per joint frame (22 joints × xyz).
pub const JOINT_FRAME_DIM: usize = 66;

/// Column names, in schema order.
pub mod col {
    /// Unique clip id.
    pub const MOTION_ID: &str = "motion_id";
    /// Source kind.
    pub const SOURCE: &str = "source";
    /// Input file.
    pub const SOURCE_PATH: &str = "source_path";
    /// Source clip id before segmenting/mirroring.
    pub const SOURCE_CLIP: &str = "source_clip";
    /// Segment index.
    pub const SEGMENT: &str = "segment";
    /// Corpus frame rate.
    pub const FPS: &str = "fps";
    /// Source frame rate.
    pub const SOURCE_FPS: &str = "source_fps";
    /// Feature rows.
    pub const NUM_FRAMES: &str = "num_frames";
    /// Flat num_frames × 263 features.
    pub const FEATURES: &str = "features";
    /// Flat (num_frames + 1) × 22 × 3 joints.
    pub const JOINTS: &str = "joints";
    /// Captions.
    pub const CAPTIONS: &str = "captions";
    /// Action label.
    pub const ACTION: &str = "action";
    /// Style label.
    pub const STYLE: &str = "style";
    /// Emotion label.
    pub const EMOTION: &str = "emotion";
    /// Scenario label.
    pub const SCENARIO: &str = "scenario";
    /// train / val / test.
    pub const SPLIT: &str = "split";
    /// Mirrored copy flag.
    pub const MIRRORED: &str = "mirrored";
    /// Motion id of the clip this one is a captioned time span of (nullable).
    pub const SPAN_OF: &str = "span_of";
    /// With `span_of`: start and end seconds of each caption's span in that clip (nullable).
    pub const CAPTION_SPANS: &str = "caption_spans";
}

/// Columns added after the first corpora were written: shards without them still read.
pub const OPTIONAL_COLUMNS: [&str; 2] = [col::SPAN_OF, col::CAPTION_SPANS];

/// The non-null `item` field of a list column holding `item` values.
pub fn list_item(item: DataType) -> FieldRef {
    Arc::new(Field::new("item", item, false))
}

fn list_of(item: DataType) -> DataType {
    DataType::List(list_item(item))
}

/// The Arrow schema of a corpus shard.
pub fn shard_schema() -> Arc<Schema> {
    use col::*;
    let utf8 = |name: &str, nullable| Field::new(name, DataType::Utf8, nullable);
    Arc::new(Schema::new(vec![
        utf8(MOTION_ID, false),
        utf8(SOURCE, false),
        utf8(SOURCE_PATH, false),
        utf8(SOURCE_CLIP, false),
        Field::new(SEGMENT, DataType::UInt32, false),
        Field::new(FPS, DataType::Float32, false),
        Field::new(SOURCE_FPS, DataType::Float32, false),
        Field::new(NUM_FRAMES, DataType::UInt32, false),
        Field::new(FEATURES, list_of(DataType::Float32), false),
        Field::new(JOINTS, list_of(DataType::Float32), false),
        Field::new(CAPTIONS, list_of(DataType::Utf8), false),
        utf8(ACTION, true),
        utf8(STYLE, true),
        utf8(EMOTION, true),
        utf8(SCENARIO, true),
        utf8(SPLIT, false),
        Field::new(MIRRORED, DataType::Boolean, false),
        utf8(SPAN_OF, true),
        Field::new(CAPTION_SPANS, list_of(DataType::Float64), true),
    ]))
}

/// The shard schema as written before [`OPTIONAL_COLUMNS`] existed.
pub fn legacy_shard_schema() -> Arc<Schema> {
    let full = shard_schema();
    let fields = full
        .fields()
        .iter()
        .filter(|f| !OPTIONAL_COLUMNS.contains(&f.name().as_str()))
        .cloned()
        .collect::<Vec<_>>();
    Arc::new(Schema::new(fields))
}
