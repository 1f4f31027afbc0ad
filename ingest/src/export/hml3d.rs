//! Export of corpus clips to the HumanML3D folder layout that T2M / T2M-GPT style loaders read:
//! `new_joint_vecs/<id>.npy`, `new_joints/<id>.npy` (= `recover_from_ric` of the vectors, as
//! HumanML3D writes it), `texts/<id>.txt`, `Mean.npy`, `Std.npy` and the split files. Motion
//! files are written as clips are added; the texts are written at the end, when every caption
//! has been tagged in one batch (one spaCy process for the whole export).

use super::text_process::{PosTagger, TaggedCaptions};
use crate::corpus::ClipRecord;
use crate::hml263::recover_joints_f32;
use crate::npy;
use crate::skeleton::NUM_JOINTS;
use std::collections::BTreeMap;
use std::io;
use std::path::{Path, PathBuf};

/// A line of `generated.jsonl`, written beside a generated set in this layout: how each
/// motion was made (the evaluator reads it to pair a motion with its caption).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GeneratedEntry {
    /// Motion id (its file stem).
    pub id: String,
    /// Corpus clip whose caption it was generated from.
    pub source_motion_id: String,
    /// That caption.
    pub caption: String,
    /// Sample index for that caption.
    pub sample: usize,
}

/// Width of a HumanML3D feature row.
pub const FEATURE_DIM: usize = 263;

/// Caption given to clips that have none, so text-conditioned loaders do not drop them.
pub const GENERIC_CAPTION: &str = "a person moves.";

/// Shortest clip (feature rows) the T2M-GPT / MoMask HumanML3D loaders keep.
pub const LOADER_MIN_FRAMES: usize = 40;
/// The loaders drop clips of this many feature rows or more (longer ones never reach the crop
/// to 196 rows).
pub const LOADER_MAX_FRAMES: usize = 200;
/// The evaluation batch of those loaders (`drop_last`: a smaller split yields no batch).
pub const EVAL_BATCH: usize = 32;

/// The captions of one exported clip.
#[derive(Debug)]
struct ClipTexts {
    split: String,
    frames: usize,
    whole: Vec<String>,
    /// (caption, start s, end s) of captions that time a span of the clip.
    spans: Vec<(String, f64, f64)>,
}

/// Writes clips into a HumanML3D-layout folder.
#[derive(Debug)]
pub struct Hml3dWriter {
    out: PathBuf,
    tagger: PosTagger,
    clips: BTreeMap<String, ClipTexts>,
}

/// What an export wrote.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct ExportSummary {
    /// Output folder.
    pub out: PathBuf,
    /// Clips written.
    pub clips: usize,
    /// Clips per split (`train`, `val`, `test`, or any other split name found).
    pub per_split: BTreeMap<String, usize>,
    /// Clips without captions, which were given [`GENERIC_CAPTION`].
    pub generic_captions: usize,
    /// Span clips written back as `#start#end` caption lines of the clip they were cut from.
    pub span_captions: usize,
    /// Motions per split that the loaders keep: whole clips with a whole-clip caption and
    /// captioned spans, each of [`LOADER_MIN_FRAMES`]..[`LOADER_MAX_FRAMES`] feature rows.
    pub loader_clips: BTreeMap<String, usize>,
    /// The tagger that wrote the `word/POS` tokens.
    pub pos_tagger: PosTagger,
    /// Problems a user of the folder should know about (e.g. a split smaller than a batch).
    pub warnings: Vec<String>,
}

impl Hml3dWriter {
    /// Start an export into `out` (created with its sub-folders), tagging captions with `tagger`.
    pub fn new(out: &Path, tagger: PosTagger) -> io::Result<Self> {
        for sub in ["new_joint_vecs", "new_joints", "texts"] {
            std::fs::create_dir_all(out.join(sub))?;
        }
        Ok(Self {
            out: out.to_path_buf(),
            tagger,
            clips: BTreeMap::new(),
        })
    }

    /// Write one clip's features and recovered joints and keep its captions for the texts.
    /// A clip cut from a captioned span of a clip already added (corpus order puts it after:
    /// its id extends that clip's) becomes `#start#end` caption lines of that clip instead.
    pub fn add(&mut self, clip: &ClipRecord) -> io::Result<()> {
        let id = &clip.motion_id;
        let invalid = |what: String| io::Error::new(io::ErrorKind::InvalidInput, what);
        if id.is_empty() || id.contains(['/', '\\']) || id.starts_with('.') {
            return Err(invalid(format!(
                "motion id {id:?} cannot be used as a file name"
            )));
        }
        let frames = clip.num_frames as usize;
        if clip.features.len() != frames * FEATURE_DIM {
            return Err(invalid(format!(
                "{id}: {} feature values, expected {frames}×{FEATURE_DIM}",
                clip.features.len()
            )));
        }
        if let Some(span) = &clip.span {
            if span.seconds.len() != clip.captions.len() {
                return Err(invalid(format!(
                    "{id}: {} caption spans for {} captions",
                    span.seconds.len(),
                    clip.captions.len()
                )));
            }
            if let Some(parent) = self.clips.get_mut(&span.of) {
                let lines = clip.captions.iter().zip(&span.seconds);
                parent
                    .spans
                    .extend(lines.map(|(c, &(start, end))| (one_line(c), start, end)));
                return Ok(());
            }
        }
        npy::write_f32(
            &self.out.join("new_joint_vecs").join(format!("{id}.npy")),
            &[frames, FEATURE_DIM],
            &clip.features,
        )?;
        npy::write_f32(
            &self.out.join("new_joints").join(format!("{id}.npy")),
            &[frames, NUM_JOINTS, 3],
            &recover_joints_f32(&clip.features),
        )?;
        let texts = ClipTexts {
            split: clip.split.clone(),
            frames,
            whole: clip.captions.iter().map(|c| one_line(c)).collect(),
            spans: Vec::new(),
        };
        self.clips.insert(id.clone(), texts);
        Ok(())
    }

    /// Tag every caption, write the texts, `Mean.npy`, `Std.npy` (263 values each) and the
    /// split files (`train.txt`, `val.txt`, `test.txt` always; `train_val.txt` = train then
    /// val; `all.txt` = every id; ids sorted within a split).
    pub fn finish(self, mean: &[f32], std: &[f32]) -> io::Result<ExportSummary> {
        for (name, stats) in [("Mean", mean), ("Std", std)] {
            if stats.len() != FEATURE_DIM {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidInput,
                    format!("{name} has {} values, expected {FEATURE_DIM}", stats.len()),
                ));
            }
            npy::write_f32(&self.out.join(format!("{name}.npy")), &[FEATURE_DIM], stats)?;
        }
        let generic_captions = self.write_texts()?;
        let mut splits: BTreeMap<String, Vec<String>> = ["train", "val", "test"]
            .into_iter()
            .map(|s| (s.to_string(), Vec::new()))
            .collect();
        let mut loader_clips: BTreeMap<String, usize> = BTreeMap::new();
        for (id, texts) in &self.clips {
            splits
                .entry(texts.split.clone())
                .or_default()
                .push(id.clone());
            *loader_clips.entry(texts.split.clone()).or_default() += texts.loader_motions();
        }
        for (split, ids) in &splits {
            write_ids(&self.out.join(format!("{split}.txt")), ids.iter())?;
            loader_clips.entry(split.clone()).or_default();
        }
        write_ids(
            &self.out.join("train_val.txt"),
            splits["train"].iter().chain(&splits["val"]),
        )?;
        write_ids(&self.out.join("all.txt"), self.clips.keys())?;
        let warnings = ["train", "val", "test"]
            .into_iter()
            .filter(|s| loader_clips[*s] < EVAL_BATCH)
            .map(|s| {
                format!(
                    "{s}: {} motions of {LOADER_MIN_FRAMES}..{LOADER_MAX_FRAMES} frames, fewer than \
                     the evaluation batch of {EVAL_BATCH}: T2M-GPT/MoMask evaluation loaders \
                     (drop_last) yield no batch from this split",
                    loader_clips[s]
                )
            })
            .collect();
        Ok(ExportSummary {
            out: self.out,
            clips: self.clips.len(),
            per_split: splits.into_iter().map(|(s, ids)| (s, ids.len())).collect(),
            generic_captions,
            span_captions: self.clips.values().map(|t| t.spans.len()).sum(),
            loader_clips,
            pos_tagger: self.tagger,
            warnings,
        })
    }

    /// Write `texts/<id>.txt` for every clip; returns how many got [`GENERIC_CAPTION`].
    fn write_texts(&self) -> io::Result<usize> {
        let captions = self.clips.values().flat_map(|t| {
            let spans = t.spans.iter().map(|(c, _, _)| c.as_str());
            t.whole.iter().map(String::as_str).chain(spans)
        });
        let tagged = TaggedCaptions::new(self.tagger, captions.chain([GENERIC_CAPTION]))
            .map_err(|e| io::Error::other(format!("tagging captions: {e}")))?;
        let mut generic = 0;
        for (id, texts) in &self.clips {
            let mut text = String::new();
            if texts.whole.is_empty() && texts.spans.is_empty() {
                generic += 1;
                text += &tagged.line(GENERIC_CAPTION, 0.0, 0.0);
            }
            for caption in &texts.whole {
                text += &tagged.line(caption, 0.0, 0.0);
            }
            let mut spans: Vec<_> = texts.spans.iter().collect();
            spans.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.2.total_cmp(&b.2)));
            for (caption, start, end) in spans {
                text += &tagged.line(caption, *start, *end);
            }
            motionscale_core::write_atomic(
                &self.out.join("texts").join(format!("{id}.txt")),
                text.as_bytes(),
            )?;
        }
        Ok(generic)
    }
}

impl ClipTexts {
    /// How many motions the loaders make of this clip: the whole clip when it has a whole-clip
    /// caption line, plus one per captioned span (`motion[int(start*20):int(end*20)]`), each
    /// kept when its length is within the loaders' bounds.
    fn loader_motions(&self) -> usize {
        let fits = |n: usize| (LOADER_MIN_FRAMES..LOADER_MAX_FRAMES).contains(&n);
        let has_whole_line = !self.whole.is_empty() || self.spans.is_empty();
        let whole = usize::from(has_whole_line && fits(self.frames));
        let frame = |seconds: f64| ((seconds * 20.0) as usize).min(self.frames);
        let spans = self.spans.iter();
        whole
            + spans
                .filter(|(_, s, e)| fits(frame(*e).saturating_sub(frame(*s))))
                .count()
    }
}

fn write_ids<'a>(path: &Path, ids: impl Iterator<Item = &'a String>) -> io::Result<()> {
    let text: String = ids.map(|id| format!("{id}\n")).collect();
    motionscale_core::write_atomic(path, text.as_bytes())
}

/// One `texts/<id>.txt` line for a caption covering the whole clip, tagged by the built-in
/// tagger: `caption#word/POS …#0.0#0.0`.
pub fn caption_line(caption: &str) -> String {
    let caption = one_line(caption);
    TaggedCaptions::new(PosTagger::BuiltIn, [caption.as_str()])
        .expect("the built-in tagger does not fail")
        .line(&caption, 0.0, 0.0)
}

/// A caption on one line without the `#` field separator.
fn one_line(caption: &str) -> String {
    caption
        .split(['\n', '\r', '#'])
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn captions_stay_on_one_line() {
        assert_eq!(one_line("a #1 move\nthen\r\nstop"), "a 1 move then stop");
    }

    #[test]
    fn loader_motions_follow_the_loaders_rule() {
        let texts = |frames, whole: &[&str], spans: &[(f64, f64)]| ClipTexts {
            split: "val".into(),
            frames,
            whole: whole.iter().map(|s| s.to_string()).collect(),
            spans: spans.iter().map(|&(s, e)| ("x".into(), s, e)).collect(),
        };
        assert_eq!(texts(40, &[], &[]).loader_motions(), 1, "generic caption");
        assert_eq!(texts(39, &["a"], &[]).loader_motions(), 0);
        assert_eq!(texts(200, &["a"], &[]).loader_motions(), 0);
        assert_eq!(texts(199, &["a"], &[]).loader_motions(), 1);
        // Spans only: the whole clip has no line of its own; 0.5..2.5 s = 40 rows, 1..2 s = 20,
        // and 8..30 s is clamped to the clip's 199 rows (160..199 = 39).
        let spans = [(0.5, 2.5), (1.0, 2.0), (8.0, 30.0)];
        assert_eq!(texts(199, &[], &spans).loader_motions(), 1);
        assert_eq!(texts(199, &["a"], &spans).loader_motions(), 2);
    }
}
