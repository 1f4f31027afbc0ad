//! Motion sources: each reads one kind of input into [`RawClip`]s of SMPL-22 joint
//! positions (metres, Y up, at the source frame rate), or rejects it with a reason.

pub mod amass;
pub mod bandai;
pub mod bvh;
pub mod hml3d;
pub mod joints;
pub mod retarget;
pub mod synth;

use crate::skeleton::Pose;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Kinds of `--source`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SourceKind {
    /// BVH files, searched recursively.
    Bvh,
    /// `.npy` joint arrays (T × J × 3).
    Joints,
    /// AMASS `.npz` sequences (needs a body model).
    Amass,
    /// A HumanML3D-layout folder.
    Hml3d,
    /// Procedural labelled motion, `synth:CLIPS[:SEED]`.
    Synth,
}

impl SourceKind {
    /// Name used on the command line and in outputs.
    pub fn name(self) -> &'static str {
        match self {
            Self::Bvh => "bvh",
            Self::Joints => "joints",
            Self::Amass => "amass",
            Self::Hml3d => "hml3d",
            Self::Synth => "synth",
        }
    }

    /// Extension of the input files searched for in a source folder of this kind (empty for
    /// `synth`, which reads no files).
    pub(crate) fn extension(self) -> &'static str {
        match self {
            Self::Bvh => "bvh",
            Self::Joints | Self::Hml3d => "npy",
            Self::Amass => "npz",
            Self::Synth => "",
        }
    }
}

/// Where a clip cut from a captioned time span sits in the clip it was cut from.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptionSpan {
    /// Motion id (or, before ingest, source clip id) of the clip the span was cut from.
    pub of: String,
    /// Start and end in seconds of each caption's span, in caption order.
    pub seconds: Vec<(f64, f64)>,
}

/// Labels attached to a clip (any may be absent).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Labels {
    /// What is done (Bandai content, synthetic action).
    pub action: Option<String>,
    /// How it is done (Bandai style, persona).
    pub style: Option<String>,
    /// Emotion (DESIGN.md mapping from styles).
    pub emotion: Option<String>,
    /// Scenario for the continual study (DESIGN.md mapping from contents).
    pub scenario: Option<String>,
}

/// A motion read from a source, before resampling and the 263 pipeline.
#[derive(Debug, Clone)]
pub struct RawClip {
    /// Stable id of the source clip (file stem, or stem plus a segment suffix); decides the split.
    pub clip_id: String,
    /// Source kind: `bvh`, `joints`, `amass`, `hml3d`, `synth`.
    pub source: String,
    /// Input file, as given on the command line joined with the path inside the source folder.
    pub source_path: PathBuf,
    /// Frame rate of `poses`.
    pub fps: f64,
    /// Joint positions per frame, SMPL-22 order, metres, Y up.
    pub poses: Vec<Pose>,
    /// Labels, when a sidecar or the source provides them.
    pub labels: Labels,
    /// Captions, when a sidecar or the source provides them.
    pub captions: Vec<String>,
    /// How the source's units and axes were converted (e.g. "cm→m, Y up"), for the manifest.
    pub conversion: String,
    /// Split fixed by the source (HumanML3D split files); otherwise chosen by hash of `clip_id`.
    pub split: Option<String>,
    /// For a clip cut from a captioned time span of another clip: that clip's id and the spans.
    pub span: Option<CaptionSpan>,
}

/// Why an input was not ingested: the stage that refused it and a human-readable reason.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
#[error("{stage}: {reason}")]
pub struct Reject {
    /// Pipeline stage (`read`, `parse`, `retarget`, `filter`, `features`).
    pub stage: String,
    /// What was wrong, naming the line/frame where known.
    pub reason: String,
}

impl Reject {
    /// A rejection at `stage` with `reason`.
    pub fn new(stage: &str, reason: impl Into<String>) -> Self {
        Self {
            stage: stage.to_string(),
            reason: reason.into(),
        }
    }
}

/// Clip id of a file from its path inside the source folder: the components without the
/// extension, joined by `_` (the file stem for a file at the top; sub-folders keep ids unique,
/// e.g. AMASS subjects that reuse file names).
pub fn clip_id_of(rel_path: &std::path::Path) -> String {
    let stemmed = rel_path.with_extension("");
    stemmed
        .components()
        .filter_map(|c| match c {
            std::path::Component::Normal(s) => Some(s.to_string_lossy().into_owned()),
            _ => None,
        })
        .collect::<Vec<_>>()
        .join("_")
}
