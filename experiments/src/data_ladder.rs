//! The unique-data axis of a sweep: nested subsets of the train split.
//!
//! A subset takes the first `fraction` of a source's train hours in one seeded order of its
//! source clips (segments and mirrored copies of a clip stay together), so every fraction
//! contains the smaller ones of the same source and seed. Validation and test splits are the
//! corpus's own, whole, in every subset: losses compare across fractions. A point trains on
//! its subset through `{train,val,test}.txt` lists in `RUNS/data/<name>/`
//! (`lm::train::TrainConfig::splits`).

use crate::SweepError;
use ingest::corpus::reader::ClipMeta;
use ingest::corpus::Origin;
use motionscale_core::rng::SplitMix64;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The clips a subset draws from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DataSource {
    /// Captured motion only.
    Real,
    /// Synthetic motion only.
    Synth,
    /// Both.
    #[default]
    All,
}

impl DataSource {
    /// Whether clips of `origin` belong to this source.
    pub fn admits(self, origin: Origin) -> bool {
        match self {
            Self::Real => origin == Origin::Real,
            Self::Synth => origin == Origin::Synth,
            Self::All => true,
        }
    }

    /// The one origin of its clips (none for both): a run on it selects its checkpoint on
    /// that origin's validation clips.
    pub fn origin(self) -> Option<Origin> {
        match self {
            Self::Real => Some(Origin::Real),
            Self::Synth => Some(Origin::Synth),
            Self::All => None,
        }
    }

    /// `real`, `synth` or `all`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Real => "real",
            Self::Synth => "synth",
            Self::All => "all",
        }
    }
}

impl fmt::Display for DataSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for DataSource {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "real" => Ok(Self::Real),
            "synth" => Ok(Self::Synth),
            "all" => Ok(Self::All),
            _ => Err(format!("data source {s:?}: want real, synth or all")),
        }
    }
}

/// A fraction of the train hours, `1/8` or `0.125` (in (0, 1]).
pub fn parse_fraction(text: &str) -> Result<f64, String> {
    let value = match text.split_once('/') {
        Some((a, b)) => match (a.trim().parse::<f64>(), b.trim().parse::<f64>()) {
            (Ok(a), Ok(b)) => a / b,
            _ => f64::NAN,
        },
        None => text.trim().parse().unwrap_or(f64::NAN),
    };
    if value > 0.0 && value <= 1.0 {
        Ok(value)
    } else {
        Err(format!(
            "data fraction {text:?}: want a number in (0, 1], e.g. 1/8"
        ))
    }
}

/// One subset of the train split, as the plan records it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataSubset {
    /// `<source>-<fraction>`, e.g. `real-1_4` (run ids end in `-d<name>`).
    pub name: String,
    /// The clips it draws from.
    pub source: DataSource,
    /// Share of the source's train hours.
    pub fraction: f64,
    /// Seed of the clip order.
    pub seed: u64,
    /// Train clips (mirrored copies included).
    pub train_clips: u64,
    /// Train hours (mirrored copies included).
    pub hours: f64,
    /// Of which synthetic.
    pub synth_hours: f64,
}

/// The subset name of `source` and `fraction`: `all-1`, `real-1_8`, `synth-0.3`.
pub fn subset_name(source: DataSource, fraction: f64) -> String {
    let inverse = 1.0 / fraction;
    let part = if (inverse - inverse.round()).abs() < 1e-9 {
        format!("1_{}", inverse.round())
    } else {
        format!("{fraction}")
    };
    let part = if part == "1_1" { "1".into() } else { part };
    format!("{source}-{part}")
}

/// Seconds of a clip.
fn seconds(clip: &ClipMeta) -> f64 {
    f64::from(clip.num_frames) / f64::from(clip.fps)
}

/// The train clips of `source` in a subset of `fraction` of their hours, in motion-id order:
/// the source clips (with their segments and mirrored copies) in a seeded order, taken until
/// their hours reach `fraction` of the source's.
pub fn select(clips: &[ClipMeta], source: DataSource, fraction: f64, seed: u64) -> Vec<&ClipMeta> {
    let mut groups: BTreeMap<&str, Vec<&ClipMeta>> = BTreeMap::new();
    for clip in clips {
        if clip.split == "train" && source.admits(Origin::of(&clip.source)) {
            groups.entry(&clip.source_clip).or_default().push(clip);
        }
    }
    let mut order: Vec<Vec<&ClipMeta>> = groups.into_values().collect();
    SplitMix64::stream(seed, 0x00da_7a1a_dde2).shuffle(&mut order);
    let total: f64 = order.iter().flatten().map(|c| seconds(c)).sum();
    let target = fraction * total * (1.0 - 1e-12);
    let (mut taken, mut chosen) = (0.0, Vec::new());
    for group in order {
        if taken >= target {
            break;
        }
        taken += group.iter().map(|c| seconds(c)).sum::<f64>();
        chosen.extend(group);
    }
    chosen.sort_by(|a, b| a.motion_id.cmp(&b.motion_id));
    chosen
}

/// The plan's record of the subset of `source`, `fraction` and `seed` whose train clips
/// ([`select`]) are `chosen`.
pub fn describe(chosen: &[&ClipMeta], source: DataSource, fraction: f64, seed: u64) -> DataSubset {
    // A fold from +0 (an empty `sum` of floats is −0).
    let hours = |keep: fn(&ClipMeta) -> bool| {
        chosen
            .iter()
            .filter(|c| keep(c))
            .fold(0.0, |h, c| h + seconds(c) / 3600.0)
    };
    DataSubset {
        name: subset_name(source, fraction),
        source,
        fraction,
        seed,
        train_clips: chosen.len() as u64,
        hours: hours(|_| true),
        synth_hours: hours(|c| Origin::of(&c.source) == Origin::Synth),
    }
}

/// The lists folder of subset `name` in the sweep folder `runs`.
pub fn lists_dir(runs: &Path, name: &str) -> PathBuf {
    runs.join("data").join(name)
}

/// Write `RUNS/data/<name>/{train,val,test}.txt` of `subset` (train: the subset; val and
/// test: the corpus's whole splits) unless the folder exists. The folder appears whole (made
/// beside it, then renamed); the lists are a function of the corpus and the subset, so a
/// process that loses the race to another leaves the same lists.
pub fn write_lists(
    runs: &Path,
    clips: &[ClipMeta],
    subset: &DataSubset,
) -> Result<PathBuf, SweepError> {
    let dir = lists_dir(runs, &subset.name);
    if dir.is_dir() {
        return Ok(dir);
    }
    let chosen = select(clips, subset.source, subset.fraction, subset.seed);
    if chosen.is_empty() {
        return Err(SweepError::Argument(format!(
            "data subset {}: the corpus has no {} train clips",
            subset.name, subset.source
        )));
    }
    let parent = runs.join("data");
    let staging = parent.join(format!(".{}.{}", subset.name, std::process::id()));
    std::fs::create_dir_all(&staging).map_err(|e| SweepError::io(&staging, e))?;
    let lines = |ids: Vec<&str>| ids.join("\n") + "\n";
    let split = |name: &str| {
        let mut ids: Vec<&str> = clips
            .iter()
            .filter(|c| c.split == name)
            .map(|c| c.motion_id.as_str())
            .collect();
        ids.sort_unstable();
        lines(ids)
    };
    let files = [
        (
            "train.txt",
            lines(chosen.iter().map(|c| c.motion_id.as_str()).collect()),
        ),
        ("val.txt", split("val")),
        ("test.txt", split("test")),
    ];
    for (file, text) in files {
        let path = staging.join(file);
        std::fs::write(&path, text).map_err(|e| SweepError::io(&path, e))?;
    }
    if let Err(e) = std::fs::rename(&staging, &dir) {
        let _ = std::fs::remove_dir_all(&staging);
        if !dir.is_dir() {
            return Err(SweepError::io(&dir, e));
        }
    }
    Ok(dir)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ingest::source::Labels;

    /// Clip `id` of source clip `source_clip`, 20 fps.
    fn clip(id: &str, source_clip: &str, source: &str, split: &str, frames: u32) -> ClipMeta {
        ClipMeta {
            motion_id: id.into(),
            source: source.into(),
            source_clip: source_clip.into(),
            split: split.into(),
            fps: 20.0,
            num_frames: frames,
            labels: Labels::default(),
            mirrored: id.starts_with('M'),
        }
    }

    fn corpus() -> Vec<ClipMeta> {
        let mut clips = Vec::new();
        for i in 0..40 {
            let (source, frames) = if i % 3 == 0 {
                ("synth", 60)
            } else {
                ("bvh", 100 + i)
            };
            let name = format!("c{i:02}");
            let split = ["train", "train", "train", "val", "test"][i as usize % 5];
            clips.push(clip(&name, &name, source, split, frames));
            clips.push(clip(&format!("M{name}"), &name, source, split, frames));
            clips.push(clip(&format!("{name}_s01"), &name, source, split, 40));
        }
        clips
    }

    #[test]
    fn fractions_are_nested_keep_mirrors_together_and_reach_their_hours() {
        let clips = corpus();
        for source in [DataSource::All, DataSource::Real, DataSource::Synth] {
            let ids = |f: f64| -> Vec<String> {
                select(&clips, source, f, 7)
                    .iter()
                    .map(|c| c.motion_id.clone())
                    .collect()
            };
            let total: f64 = select(&clips, source, 1.0, 7)
                .iter()
                .map(|c| seconds(c))
                .sum();
            let mut smaller: Vec<String> = Vec::new();
            for f in [0.125, 0.25, 0.5, 1.0] {
                let chosen = select(&clips, source, f, 7);
                let got: f64 = chosen.iter().map(|c| seconds(c)).sum();
                assert!(
                    got >= f * total * (1.0 - 1e-9),
                    "{source} {f}: {got} of {total}"
                );
                let largest_group = 100.0 + 40.0 + 40.0;
                assert!(got < f * total + largest_group / 20.0 * 2.0, "{source} {f}");
                let these = ids(f);
                assert!(
                    smaller.iter().all(|id| these.contains(id)),
                    "{source}: {f} does not contain the smaller fraction"
                );
                for c in &chosen {
                    assert!(c.split == "train" && source.admits(Origin::of(&c.source)));
                    let group = clips.iter().filter(|o| o.source_clip == c.source_clip);
                    assert!(
                        group.clone().all(|o| these.contains(&o.motion_id)),
                        "{}: its mirror or segment is missing",
                        c.motion_id
                    );
                }
                smaller = these;
            }
            let every: Vec<String> = clips
                .iter()
                .filter(|c| c.split == "train" && source.admits(Origin::of(&c.source)))
                .map(|c| c.motion_id.clone())
                .collect();
            assert_eq!(smaller.len(), every.len(), "{source}: 1 takes every clip");
        }
        assert_ne!(
            ids_of(select(&clips, DataSource::All, 0.25, 7)),
            ids_of(select(&clips, DataSource::All, 0.25, 8)),
            "the seed orders the clips"
        );
        assert_eq!(
            ids_of(select(&clips, DataSource::All, 0.25, 7)),
            ids_of(select(&clips, DataSource::All, 0.25, 7))
        );
    }

    fn ids_of(clips: Vec<&ClipMeta>) -> Vec<&str> {
        clips.iter().map(|c| c.motion_id.as_str()).collect()
    }

    #[test]
    fn subsets_are_described_named_and_written_as_split_lists() {
        let clips = corpus();
        let described =
            |source, fraction| describe(&select(&clips, source, fraction, 7), source, fraction, 7);
        let s = described(DataSource::Real, 0.5);
        assert_eq!((s.name.as_str(), s.synth_hours), ("real-1_2", 0.0));
        assert!(s.synth_hours.is_sign_positive(), "+0, not −0");
        let all = described(DataSource::All, 1.0);
        assert_eq!(all.name, "all-1");
        let synth: f64 = clips
            .iter()
            .filter(|c| c.split == "train" && c.source == "synth")
            .map(seconds)
            .sum();
        assert!((all.synth_hours - synth / 3600.0).abs() < 1e-12);
        assert_eq!(subset_name(DataSource::Synth, 0.3), "synth-0.3");
        assert_eq!(parse_fraction("1/8"), Ok(0.125));
        assert_eq!(parse_fraction("0.5"), Ok(0.5));
        for bad in ["0", "3/2", "x", "1/0"] {
            assert!(parse_fraction(bad).is_err(), "{bad}");
        }
        assert_eq!("real".parse(), Ok(DataSource::Real));
        assert!("bvh".parse::<DataSource>().is_err());

        let runs = tempfile::tempdir().unwrap();
        let dir = write_lists(runs.path(), &clips, &s).unwrap();
        let read = |f: &str| std::fs::read_to_string(dir.join(f)).unwrap();
        let train: Vec<String> = read("train.txt").lines().map(String::from).collect();
        assert_eq!(train, ids_of(select(&clips, DataSource::Real, 0.5, 7)));
        let val = clips.iter().filter(|c| c.split == "val").count();
        assert_eq!(read("val.txt").lines().count(), val, "val is whole");
        let test = clips.iter().filter(|c| c.split == "test").count();
        assert_eq!(read("test.txt").lines().count(), test, "test is whole");
        let again = write_lists(runs.path(), &clips, &s).unwrap();
        assert_eq!(again, dir);
        let assigned = ingest::corpus::split::SplitAssignment::from_dir(Some(&dir)).unwrap();
        assert_eq!(assigned.split_of(&train[0], "train"), Some("train"));
        let none = described(DataSource::Synth, 1.0);
        let only_real: Vec<ClipMeta> = clips.into_iter().filter(|c| c.source != "synth").collect();
        let e = write_lists(runs.path(), &only_real, &none).unwrap_err();
        assert!(e.to_string().contains("no synth train clips"), "{e}");
    }
}
