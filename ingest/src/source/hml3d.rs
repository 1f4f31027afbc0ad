//! Import of a HumanML3D-layout folder: `new_joints/<id>.npy` (T×22×3, 20 fps, already
//! processed), `texts/<id>.txt` (`caption#tok/POS ...#start#end`, seconds) and the optional
//! split files `train.txt`, `val.txt`, `test.txt`.
//!
//! Only the joints are read: the corpus recomputes the 263 features from them with the same
//! pipeline as every other source, so `new_joint_vecs/` is not needed. A caption with a time
//! span becomes a clip of its own that remembers the span, so `export hml3d` can write it back
//! as a `#start#end` line of the whole clip.

use super::joints::poses_of;
use super::CaptionSpan;
use super::{RawClip, Reject};
use crate::error::IngestError;
use crate::npy;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

/// Frame rate of HumanML3D's processed joints.
pub const FPS: f64 = 20.0;

/// Captioned spans of a clip: frame range `[start, end)` at 20 fps → its distinct captions, each
/// with its span in seconds as written.
type Spans = BTreeMap<(usize, usize), Vec<(String, (f64, f64))>>;

const CONVERSION: &str = "HumanML3D new_joints (metres, Y up)";

/// An opened HumanML3D folder: its root and the split of every id listed in a split file.
#[derive(Debug, Clone)]
pub struct Hml3dFolder {
    root: PathBuf,
    splits: HashMap<String, String>,
}

/// One caption line of `texts/<id>.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptionLine {
    /// The caption text.
    pub caption: String,
    /// Start of the captioned span in seconds (`None`: the whole clip).
    pub start: Option<f64>,
    /// End of the captioned span in seconds (`None`: the whole clip).
    pub end: Option<f64>,
}

impl Hml3dFolder {
    /// Open `dir`: it must hold `new_joints/`; split files are read when present.
    pub fn open(dir: &Path) -> Result<Self, IngestError> {
        let joints = dir.join("new_joints");
        if !joints.is_dir() {
            return Err(IngestError::file(
                dir,
                "not a HumanML3D folder (no new_joints/ folder)",
            ));
        }
        let splits = crate::corpus::split::read_split_lists(dir)?;
        Ok(Self {
            root: dir.to_path_buf(),
            splits,
        })
    }

    /// The `new_joints/*.npy` files, sorted.
    pub fn discover(&self) -> Result<Vec<PathBuf>, IngestError> {
        let dir = self.root.join("new_joints");
        let entries = std::fs::read_dir(&dir).map_err(|e| IngestError::io(&dir, e))?;
        let mut files = Vec::new();
        for entry in entries {
            let path = entry.map_err(|e| IngestError::io(&dir, e))?.path();
            if path.extension().is_some_and(|e| e == "npy") && path.is_file() {
                files.push(path);
            }
        }
        files.sort();
        Ok(files)
    }

    /// The clips of one joints file: the whole clip (with its whole-clip captions) and one clip
    /// per distinct captioned span (`<id>_<startframe>_<endframe>`). A file that cannot be read
    /// gives a single `Err`; a span that does not fit the clip gives an `Err` for that span only.
    pub fn read_clips(&self, joints_file: &Path) -> Vec<Result<RawClip, Reject>> {
        match self.read_whole(joints_file) {
            Ok((whole, spans)) => {
                let mut out = Vec::with_capacity(1 + spans.len());
                let segments = spans
                    .into_iter()
                    .map(|((start, end), captions)| {
                        segment(&whole, joints_file, start, end, captions)
                    })
                    .collect::<Vec<_>>();
                out.push(Ok(whole));
                out.extend(segments);
                out
            }
            Err(reject) => vec![Err(reject)],
        }
    }

    /// The whole clip and its captioned spans.
    fn read_whole(&self, joints_file: &Path) -> Result<(RawClip, Spans), Reject> {
        let id = joints_file
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .ok_or_else(|| {
                Reject::new("read", format!("{}: no file name", joints_file.display()))
            })?;
        let array = npy::read(joints_file).map_err(|e| Reject::new("read", e))?;
        let poses = poses_of(&array)
            .map_err(|r| Reject::new("parse", format!("{}: {r}", joints_file.display())))?;
        let text_file = self.root.join("texts").join(format!("{id}.txt"));
        let lines = if text_file.is_file() {
            let text = std::fs::read_to_string(&text_file)
                .map_err(|e| Reject::new("read", format!("{}: {e}", text_file.display())))?;
            parse_texts(&text)
                .map_err(|r| Reject::new("parse", format!("{}: {r}", text_file.display())))?
        } else {
            Vec::new()
        };
        let mut captions = Vec::new();
        let mut spans = Spans::new();
        for line in lines {
            match (line.start, line.end) {
                (Some(start), Some(end)) => {
                    // HumanML3D's loaders slice `motion[int(start*20):int(end*20)]`.
                    let key = ((start * FPS) as usize, (end * FPS) as usize);
                    let entry = spans.entry(key).or_default();
                    if !entry.iter().any(|(c, _)| *c == line.caption) {
                        entry.push((line.caption, (start, end)));
                    }
                }
                _ => {
                    if !captions.contains(&line.caption) {
                        captions.push(line.caption);
                    }
                }
            }
        }
        let whole = RawClip {
            split: self.splits.get(&id).cloned(),
            clip_id: id,
            source: "hml3d".into(),
            source_path: joints_file.to_path_buf(),
            fps: FPS,
            poses,
            labels: Default::default(),
            captions,
            conversion: CONVERSION.into(),
            span: None,
        };
        Ok((whole, spans))
    }
}

/// The sub-clip `[start, end)` (frames) of `whole` with its captions; the end is clamped to the
/// clip as Python slicing does, and fewer than 2 frames left (no feature row) is a reject.
fn segment(
    whole: &RawClip,
    joints_file: &Path,
    start: usize,
    end: usize,
    captions: Vec<(String, (f64, f64))>,
) -> Result<RawClip, Reject> {
    let stop = end.min(whole.poses.len());
    if stop < start.saturating_add(2) {
        return Err(Reject::new(
            "parse",
            format!(
                "{}: caption span frames {start}..{end} leaves {} of the clip's {} frames (at least 2 needed): {:?}",
                joints_file.display(),
                stop.saturating_sub(start),
                whole.poses.len(),
                captions.first().map(|(c, _)| c.as_str()).unwrap_or("")
            ),
        ));
    }
    let (captions, seconds) = captions.into_iter().unzip();
    Ok(RawClip {
        clip_id: format!("{}_{start}_{end}", whole.clip_id),
        poses: whole.poses[start..stop].to_vec(),
        captions,
        span: Some(CaptionSpan {
            of: whole.clip_id.clone(),
            seconds,
        }),
        source: whole.source.clone(),
        source_path: whole.source_path.clone(),
        fps: whole.fps,
        labels: whole.labels.clone(),
        conversion: whole.conversion.clone(),
        split: whole.split.clone(),
    })
}

/// Parse the lines of a HumanML3D text file (`caption#tokens#start#end`); a span whose start and
/// end are both 0 or NaN covers the whole clip. Errors name the 1-based line.
pub fn parse_texts(text: &str) -> Result<Vec<CaptionLine>, IngestError> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split('#').collect();
        let [caption, _tokens, start, end] = fields.as_slice() else {
            return Err(format!(
                "line {}: expected 4 '#'-separated fields (caption#tokens#start#end), found {}",
                n + 1,
                fields.len()
            )
            .into());
        };
        let seconds = |s: &str, what: &str| {
            s.trim()
                .parse::<f64>()
                .map_err(|_| format!("line {}: {what} {s:?} is not a number of seconds", n + 1))
        };
        let (start, end) = (seconds(start, "start")?, seconds(end, "end")?);
        let whole = (start.is_nan() || start == 0.0) && (end.is_nan() || end == 0.0);
        if !(whole || start >= 0.0 && end > start) {
            return Err(format!(
                "line {}: span {start}..{end} s is not a forward span",
                n + 1
            )
            .into());
        }
        out.push(CaptionLine {
            caption: caption.trim().to_string(),
            start: (!whole).then_some(start),
            end: (!whole).then_some(end),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caption_lines_parse() {
        let lines = parse_texts(
            "a man walks.#a/DET man/NOUN walk/VERB#0.0#0.0\n\
             he waves.#he/PRON wave/VERB#1.5#3.25\n\
             spins#spin/VERB#nan#nan\n",
        )
        .unwrap();
        assert_eq!(lines.len(), 3);
        assert_eq!(lines[0].start, None);
        assert_eq!((lines[1].start, lines[1].end), (Some(1.5), Some(3.25)));
        assert_eq!(lines[2].caption, "spins");
        assert_eq!(lines[2].end, None);
        let err = parse_texts("ok#ok/X#0#0\nbad line#x\n")
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("line 2: expected 4"), "{err}");
        let err = parse_texts("x#x/X#2.0#1.0").unwrap_err().to_string();
        assert!(err.contains("not a forward span"), "{err}");
    }
}
