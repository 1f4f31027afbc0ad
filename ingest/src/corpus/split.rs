//! Deterministic train/val/test assignment by hash of the source clip id (80/5/15), so a
//! clip, its segments and its mirrored copy always share a split.

use crate::error::IngestError;
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::Path;

/// The three splits, in manifest order.
pub const SPLITS: [&str; 3] = ["train", "val", "test"];

/// Split of a source clip id: sha256 of the id, first 8 bytes as u64, mod 100.
pub fn split_of(source_clip: &str) -> &'static str {
    let digest = Sha256::digest(source_clip.as_bytes());
    let bucket = u64::from_le_bytes(digest[..8].try_into().expect("8 bytes")) % 100;
    match bucket {
        0..80 => "train",
        80..85 => "val",
        _ => "test",
    }
}

/// Which split each clip belongs to: its own (the corpus's hash split), or the one a folder
/// of `{train,val,test}.txt` lists gives (a scenario dataset), where unlisted clips are in
/// no split.
#[derive(Debug, Clone, Default)]
pub struct SplitAssignment {
    lists: Option<HashMap<String, String>>,
}

impl SplitAssignment {
    /// The lists of `dir`, or the clips' own splits when there is none.
    pub fn from_dir(dir: Option<&Path>) -> Result<Self, IngestError> {
        Ok(Self {
            lists: dir.map(read_split_lists).transpose()?,
        })
    }

    /// The split of clip `id` whose own split is `own`.
    pub fn split_of<'a>(&'a self, id: &str, own: &'a str) -> Option<&'a str> {
        match &self.lists {
            Some(lists) => lists.get(id).map(String::as_str),
            None => Some(own),
        }
    }
}

/// The lines of `path`, trimmed, blank ones dropped (ids of a split list, captions of a
/// sidecar); `None` when it is absent.
pub fn read_ids(path: &Path) -> Result<Option<Vec<String>>, IngestError> {
    if !path.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(path).map_err(|e| IngestError::io(path, e))?;
    Ok(Some(
        text.lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(str::to_string)
            .collect(),
    ))
}

/// The split of every clip listed in `DIR/{train,val,test}.txt` (a scenario dataset's or a
/// HumanML3D folder's layout; a missing file is an empty split). An id listed in two files,
/// or a `dir` that is not a folder, is an error.
pub fn read_split_lists(dir: &Path) -> Result<HashMap<String, String>, IngestError> {
    if !dir.is_dir() {
        return Err(IngestError::file(dir, "not a folder of split lists"));
    }
    let mut splits = HashMap::new();
    for split in SPLITS {
        let path = dir.join(format!("{split}.txt"));
        for id in read_ids(&path)?.unwrap_or_default() {
            if let Some(other) = splits.insert(id.clone(), split.to_string()) {
                if other != split {
                    return Err(IngestError::file(
                        dir,
                        format!("{id} is listed in {other}.txt and {split}.txt"),
                    ));
                }
            }
        }
    }
    Ok(splits)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn proportions_are_close_to_80_5_15() {
        let mut counts = [0usize; 3];
        for i in 0..20_000 {
            let s = split_of(&format!("clip_{i:05}"));
            counts[SPLITS.iter().position(|x| *x == s).unwrap()] += 1;
        }
        let pct = |c: usize| c as f64 / 200.0;
        assert!((pct(counts[0]) - 80.0).abs() < 1.5, "{counts:?}");
        assert!((pct(counts[1]) - 5.0).abs() < 1.0, "{counts:?}");
        assert!((pct(counts[2]) - 15.0).abs() < 1.5, "{counts:?}");
        assert_eq!(split_of("clip_00001"), split_of("clip_00001"));
    }

    #[test]
    fn split_lists_read_every_file_and_refuse_an_id_in_two() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("train.txt"), "a\nb\n\n").unwrap();
        std::fs::write(dir.path().join("test.txt"), "c\n").unwrap();
        let lists = read_split_lists(dir.path()).unwrap();
        assert_eq!(lists.len(), 3);
        assert_eq!(lists["b"], "train");
        assert_eq!(lists["c"], "test");
        std::fs::write(dir.path().join("val.txt"), "a\n").unwrap();
        let err = read_split_lists(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("a is listed in train.txt and val.txt"),
            "{err}"
        );
        let empty = tempfile::tempdir().unwrap();
        assert!(read_split_lists(empty.path()).unwrap().is_empty());
        assert!(read_split_lists(&empty.path().join("missing")).is_err());
    }
}
