//! The corpus on disk: Parquet shards, manifest, statistics, splits and rejects.

pub mod integrity;
pub mod manifest;
pub mod reader;
pub mod runs;
pub mod schema;
pub mod split;
pub mod staging;
pub mod stats;
pub mod verify;
pub mod writer;

pub use manifest::Manifest;
pub use reader::Corpus;

pub use crate::source::CaptionSpan;
use crate::source::Labels;
use serde::{Deserialize, Serialize};

/// Where a clip's motion comes from: captured (every source kind but `synth`) or generated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Origin {
    /// Motion capture (`bvh`, `joints`, `amass`, `hml3d`).
    Real,
    /// Procedural motion (`synth`).
    Synth,
}

impl Origin {
    /// The origin of a clip of source kind `source` (the `source` column).
    pub fn of(source: &str) -> Self {
        if source == crate::source::SourceKind::Synth.name() {
            Self::Synth
        } else {
            Self::Real
        }
    }

    /// `real` or `synth`, as tables and file names spell it.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Real => "real",
            Self::Synth => "synth",
        }
    }
}

/// One clip of the corpus: a row of a shard.
#[derive(Debug, Clone, PartialEq)]
pub struct ClipRecord {
    /// Unique id (`<source clip id>[_sNN]`, `M` prefix for mirrored copies).
    pub motion_id: String,
    /// Source kind (`bvh`, `joints`, `amass`, `hml3d`, `synth`).
    pub source: String,
    /// Input file the clip came from.
    pub source_path: String,
    /// Id of the source clip before segmenting and mirroring (decides the split).
    pub source_clip: String,
    /// Segment index within the source clip (0 when it was not split).
    pub segment: u32,
    /// Frame rate of `features` and `joints` (20).
    pub fps: f32,
    /// Frame rate of the source before resampling.
    pub source_fps: f32,
    /// Number of feature rows; `joints` has one frame more.
    pub num_frames: u32,
    /// num_frames × 263 HumanML3D features, row-major.
    pub features: Vec<f32>,
    /// (num_frames + 1) × 22 × 3 joint positions (metres, Y up), row-major.
    pub joints: Vec<f32>,
    /// Captions (may be empty).
    pub captions: Vec<String>,
    /// Action, style, emotion and scenario labels.
    pub labels: Labels,
    /// `train`, `val` or `test`.
    pub split: String,
    /// Whether this is a left/right mirrored copy.
    pub mirrored: bool,
    /// For a clip cut from a captioned time span of another clip (HumanML3D `#start#end`
    /// captions): that clip and each caption's span.
    pub span: Option<CaptionSpan>,
}

impl ClipRecord {
    /// The `joints` column as poses (num_frames + 1 frames).
    pub fn poses(&self) -> Vec<crate::skeleton::Pose> {
        self.joints
            .chunks_exact(schema::JOINT_FRAME_DIM)
            .map(|f| std::array::from_fn(|j| std::array::from_fn(|k| f[3 * j + k] as f64)))
            .collect()
    }
}
