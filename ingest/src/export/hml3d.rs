//! Export of corpus clips to the HumanML3D folder layout that T2M / T2M-GPT style loaders read:
//! `new_joint_vecs/<id>.npy`, `new_joints/<id>.npy`, `texts/<id>.txt`, `Mean.npy`, `Std.npy`
//! and the split files. Clips are added one at a time, so the corpus need not fit in memory.

use crate::corpus::ClipRecord;
use crate::npy;
use crate::skeleton::NUM_JOINTS;
use std::collections::BTreeMap;
use std::io;
use std::path::{Path, PathBuf};

/// Width of a HumanML3D feature row.
pub const FEATURE_DIM: usize = 263;

/// Caption given to clips that have none, so text-conditioned loaders do not drop them.
pub const GENERIC_CAPTION: &str = "a person moves.";

/// Writes clips into a HumanML3D-layout folder.
#[derive(Debug)]
pub struct Hml3dWriter {
    out: PathBuf,
    splits: BTreeMap<String, Vec<String>>,
    uncaptioned: usize,
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
}

impl Hml3dWriter {
    /// Start an export into `out` (created with its sub-folders).
    pub fn new(out: &Path) -> io::Result<Self> {
        for sub in ["new_joint_vecs", "new_joints", "texts"] {
            std::fs::create_dir_all(out.join(sub))?;
        }
        Ok(Self {
            out: out.to_path_buf(),
            splits: BTreeMap::new(),
            uncaptioned: 0,
        })
    }

    /// Write one clip's features, joints and captions.
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
        if clip.joints.len() != (frames + 1) * NUM_JOINTS * 3 {
            return Err(invalid(format!(
                "{id}: {} joint values, expected ({frames}+1)×{NUM_JOINTS}×3",
                clip.joints.len()
            )));
        }
        npy::write_f32(
            &self.out.join("new_joint_vecs").join(format!("{id}.npy")),
            &[frames, FEATURE_DIM],
            &clip.features,
        )?;
        npy::write_f32(
            &self.out.join("new_joints").join(format!("{id}.npy")),
            &[frames + 1, NUM_JOINTS, 3],
            &clip.joints,
        )?;
        let captions: Vec<&str> = if clip.captions.is_empty() {
            self.uncaptioned += 1;
            vec![GENERIC_CAPTION]
        } else {
            clip.captions.iter().map(String::as_str).collect()
        };
        let text: String = captions.iter().map(|c| caption_line(c)).collect();
        npy::write_atomic(
            &self.out.join("texts").join(format!("{id}.txt")),
            text.as_bytes(),
        )?;
        self.splits
            .entry(clip.split.clone())
            .or_default()
            .push(id.clone());
        Ok(())
    }

    /// Write `Mean.npy`, `Std.npy` (263 values each) and the split files (`train.txt`,
    /// `val.txt`, `test.txt` always; `all.txt` = every id; ids sorted).
    pub fn finish(mut self, mean: &[f32], std: &[f32]) -> io::Result<ExportSummary> {
        for (name, stats) in [("Mean", mean), ("Std", std)] {
            if stats.len() != FEATURE_DIM {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidInput,
                    format!("{name} has {} values, expected {FEATURE_DIM}", stats.len()),
                ));
            }
            npy::write_f32(&self.out.join(format!("{name}.npy")), &[FEATURE_DIM], stats)?;
        }
        for split in ["train", "val", "test"] {
            self.splits.entry(split.to_string()).or_default();
        }
        let mut all = Vec::new();
        for (split, ids) in self.splits.iter_mut() {
            ids.sort();
            all.extend(ids.iter().cloned());
            npy::write_atomic(
                &self.out.join(format!("{split}.txt")),
                id_list(ids).as_bytes(),
            )?;
        }
        all.sort();
        npy::write_atomic(&self.out.join("all.txt"), id_list(&all).as_bytes())?;
        Ok(ExportSummary {
            out: self.out,
            clips: all.len(),
            per_split: self
                .splits
                .into_iter()
                .map(|(split, ids)| (split, ids.len()))
                .collect(),
            generic_captions: self.uncaptioned,
        })
    }
}

fn id_list(ids: &[String]) -> String {
    ids.iter().map(|id| format!("{id}\n")).collect()
}

/// A caption on one line without the `#` field separator.
/// One `texts/<id>.txt` line for a caption covering the whole clip:
/// `caption#word/POS …#0.0#0.0`.
pub fn caption_line(caption: &str) -> String {
    format!("{}#{}#0.0#0.0\n", one_line(caption), tag_caption(caption))
}

fn one_line(caption: &str) -> String {
    caption
        .split(['\n', '\r', '#'])
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}

/// `word/POS` tokens of a caption, space-separated: lower-case words, punctuation dropped,
/// verbs and plural nouns reduced to the lemma HumanML3D's spaCy step stores.
pub fn tag_caption(caption: &str) -> String {
    caption
        .to_lowercase()
        .split(|c: char| !c.is_alphanumeric())
        .filter(|w| !w.is_empty())
        .map(|w| {
            let (lemma, pos) = tag_word(w);
            format!("{lemma}/{pos}")
        })
        .collect::<Vec<_>>()
        .join(" ")
}

const VERBS: &[&str] = &[
    "walk", "run", "jog", "jump", "hop", "skip", "step", "turn", "spin", "rotate", "wave", "raise",
    "lift", "lower", "kick", "punch", "throw", "catch", "bow", "dance", "sit", "stand", "squat",
    "crouch", "kneel", "lie", "crawl", "climb", "bend", "lean", "stretch", "swing", "shake",
    "clap", "reach", "pick", "put", "place", "hold", "push", "pull", "move", "go", "come", "stop",
    "start", "look", "point", "slash", "strike", "hit", "call", "guide", "respond", "greet",
    "march", "stumble", "fall", "balance", "twist", "rise", "get", "sway", "tap", "stomp",
    "shuffle", "sprint", "dash", "pace", "wander", "limp", "wobble", "rest", "bounce", "swim",
    "fly", "drink", "eat", "wipe", "cross", "extend", "flap", "perform", "do", "make", "take",
    "use", "seem", "appear", "begin", "continue", "repeat", "return", "cover", "touch", "grab",
    "open", "close", "carry", "drop", "brush", "scratch", "salute",
];
const IRREGULAR_VERBS: &[(&str, &str)] = &[
    ("ran", "run"),
    ("running", "run"),
    ("went", "go"),
    ("goes", "go"),
    ("came", "come"),
    ("does", "do"),
    ("did", "do"),
    ("doing", "do"),
    ("sat", "sit"),
    ("sitting", "sit"),
    ("stood", "stand"),
    ("lying", "lie"),
    ("lay", "lie"),
    ("held", "hold"),
    ("threw", "throw"),
    ("thrown", "throw"),
    ("caught", "catch"),
    ("fell", "fall"),
    ("fallen", "fall"),
    ("rose", "rise"),
    ("got", "get"),
    ("getting", "get"),
    ("took", "take"),
    ("made", "make"),
    ("spun", "spin"),
    ("spinning", "spin"),
    ("jogging", "jog"),
    ("hopping", "hop"),
    ("skipping", "skip"),
    ("stepping", "step"),
    ("stopping", "stop"),
    ("swimming", "swim"),
    ("flew", "fly"),
    ("flies", "fly"),
    ("began", "begin"),
    ("hit", "hit"),
    ("hitting", "hit"),
    ("dancing", "dance"),
    ("waving", "wave"),
    ("raising", "raise"),
    ("moving", "move"),
    ("placing", "place"),
    ("squatting", "squat"),
    ("rising", "rise"),
    ("making", "make"),
    ("taking", "take"),
    ("using", "use"),
    ("continuing", "continue"),
    ("closing", "close"),
    ("balancing", "balance"),
    ("bouncing", "bounce"),
    ("shuffling", "shuffle"),
    ("wobbling", "wobble"),
    ("stumbling", "stumble"),
    ("saluting", "salute"),
    ("circling", "circle"),
    ("pacing", "pace"),
    ("limping", "limp"),
];
const NOUNS: &[&str] = &[
    "person",
    "man",
    "woman",
    "human",
    "figure",
    "body",
    "hand",
    "arm",
    "leg",
    "foot",
    "feet",
    "head",
    "knee",
    "elbow",
    "shoulder",
    "hip",
    "waist",
    "torso",
    "chest",
    "back",
    "finger",
    "wrist",
    "ankle",
    "toe",
    "side",
    "circle",
    "ground",
    "floor",
    "air",
    "direction",
    "position",
    "motion",
    "movement",
    "step",
    "way",
    "place",
    "time",
    "times",
    "front",
    "line",
    "path",
    "stair",
    "stairs",
    "ball",
    "object",
    "chair",
    "door",
    "wall",
    "table",
    "boxer",
    "dancer",
    "child",
    "kid",
    "style",
    "pose",
    "stance",
    "jump",
    "kick",
    "punch",
    "bow",
    "dance",
    "walk",
    "run",
    "wave",
    "turn",
    "spin",
    "hands",
    "arms",
    "legs",
    "fist",
    "palm",
];
const ADJECTIVES: &[&str] = &[
    "left",
    "right",
    "other",
    "both",
    "big",
    "small",
    "large",
    "high",
    "low",
    "fast",
    "slow",
    "quick",
    "happy",
    "sad",
    "angry",
    "proud",
    "tired",
    "exhausted",
    "energetic",
    "active",
    "old",
    "elderly",
    "young",
    "youthful",
    "childish",
    "feminine",
    "masculine",
    "confident",
    "nervous",
    "anxious",
    "calm",
    "straight",
    "full",
    "half",
    "whole",
    "same",
    "few",
    "several",
    "giant",
    "heavy",
    "light",
    "casual",
    "normal",
    "musical",
    "wide",
    "long",
    "short",
    "upper",
    "lower",
    "neutral",
    "excited",
    "slight",
    "gentle",
    "powerful",
    "strong",
    "weak",
];
const ADVERBS: &[&str] = &[
    "forward",
    "forwards",
    "backward",
    "backwards",
    "back",
    "up",
    "down",
    "around",
    "away",
    "then",
    "again",
    "slowly",
    "quickly",
    "fast",
    "together",
    "sideways",
    "twice",
    "once",
    "briefly",
    "repeatedly",
    "while",
    "also",
    "still",
    "very",
    "gently",
    "slightly",
    "here",
    "there",
    "counterclockwise",
    "clockwise",
    "diagonally",
    "straight",
    "now",
    "finally",
    "carefully",
    "happily",
    "sadly",
    "angrily",
    "proudly",
    "energetically",
    "confidently",
];
const ADPOSITIONS: &[&str] = &[
    "to", "with", "on", "in", "at", "of", "from", "into", "onto", "over", "under", "by", "for",
    "across", "along", "through", "towards", "toward", "behind", "above", "below", "between",
    "about", "like", "off", "out", "before", "after", "near", "against", "upon", "as", "until",
];
const DETERMINERS: &[&str] = &[
    "a", "an", "the", "this", "that", "these", "those", "each", "every", "some", "any", "another",
    "all", "no",
];
const PRONOUNS: &[&str] = &[
    "he",
    "she",
    "it",
    "they",
    "his",
    "her",
    "hers",
    "its",
    "their",
    "them",
    "him",
    "himself",
    "herself",
    "themselves",
    "itself",
    "i",
    "you",
    "we",
    "who",
    "which",
    "what",
    "someone",
    "something",
    "everyone",
    "anyone",
];
const AUXILIARIES: &[&str] = &[
    "is", "are", "was", "were", "be", "been", "being", "has", "have", "had", "can", "will",
    "would", "could", "should", "may", "might",
];
const NUMBERS: &[&str] = &[
    "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten",
];

/// Lemma and POS tag (T2M's `POS_enumerator` names) of one lower-case word.
fn tag_word(word: &str) -> (String, &'static str) {
    let has = |list: &[&str], w: &str| list.contains(&w);
    if word.chars().all(|c| c.is_ascii_digit()) || has(NUMBERS, word) {
        return (word.to_string(), "NUM");
    }
    for (list, pos) in [
        (DETERMINERS, "DET"),
        (PRONOUNS, "PRON"),
        (AUXILIARIES, "AUX"),
        (ADPOSITIONS, "ADP"),
    ] {
        if has(list, word) {
            return (word.to_string(), pos);
        }
    }
    if let Some((_, lemma)) = IRREGULAR_VERBS.iter().find(|(form, _)| *form == word) {
        return (lemma.to_string(), "VERB");
    }
    // "left" and "right" are directions here, never the verb "leave".
    for (list, pos) in [(ADJECTIVES, "ADJ"), (ADVERBS, "ADV")] {
        if has(list, word) {
            return (word.to_string(), pos);
        }
    }
    if has(NOUNS, word) && !has(VERBS, word) {
        return (word.to_string(), "NOUN");
    }
    if has(VERBS, word) {
        return (word.to_string(), "VERB");
    }
    for suffix in ["ing", "es", "ed", "s", "d"] {
        if let Some(stem) = word.strip_suffix(suffix) {
            if has(VERBS, stem) {
                return (stem.to_string(), "VERB");
            }
            if suffix == "s" && has(NOUNS, stem) {
                return (stem.to_string(), "NOUN");
            }
        }
    }
    (word.to_string(), "OTHER")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn captions_are_tagged() {
        assert_eq!(
            tag_caption("A person walks forward, then waves his left hand!"),
            "a/DET person/NOUN walk/VERB forward/ADV then/ADV wave/VERB his/PRON left/ADJ hand/NOUN"
        );
        assert_eq!(
            tag_caption("The man ran in 2 circles."),
            "the/DET man/NOUN run/VERB in/ADP 2/NUM circle/NOUN"
        );
        assert_eq!(tag_caption("zigzag"), "zigzag/OTHER");
        assert_eq!(tag_caption("jumped"), "jump/VERB");
    }

    #[test]
    fn captions_stay_on_one_line() {
        assert_eq!(one_line("a #1 move\nthen\r\nstop"), "a 1 move then stop");
    }
}
