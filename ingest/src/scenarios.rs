//! L²-EMG scenario datasets from a labelled corpus (`../shared/docs/continual.md`):
//! **Unseen** (one dataset per scenario label) and **Mixed** (equal-size chunks, each with a
//! primary scenario plus fewer clips of the others).
//!
//! A source clip's segments and mirrored copies always land in the same dataset. Each clip
//! keeps its corpus split (train/val/test by a hash of the source clip, so a clip and its
//! mirror never sit in two splits): the backbone LM and the evaluator train on the corpus
//! train split, and a scenario's val/test clips must be clips neither of them has seen.

use crate::corpus::reader::ClipMeta;
use crate::corpus::split::SPLITS;
use crate::corpus::Corpus;
use crate::error::IngestError;
use motionscale_core::rng::SplitMix64;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// How the corpus is cut into datasets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ScenarioSplit {
    /// One dataset per scenario label.
    Unseen,
    /// Equal-size chunks with a primary scenario each.
    Mixed,
}

impl std::str::FromStr for ScenarioSplit {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "unseen" => Ok(Self::Unseen),
            "mixed" => Ok(Self::Mixed),
            other => Err(format!(
                "unknown scenario split {other:?} (unseen or mixed)"
            )),
        }
    }
}

/// One scenario dataset D_i.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScenarioDataset {
    /// `D01_locomotion`, …
    pub name: String,
    /// The scenario it is about (Unseen) or mostly about (Mixed).
    pub primary_scenario: String,
    /// Clip ids per split (`train`, `val`, `test`), sorted.
    pub clips: BTreeMap<String, Vec<String>>,
    /// Clip counts per emotion label.
    pub emotions: BTreeMap<String, u64>,
    /// Clip counts per scenario label (Mixed datasets hold several).
    pub scenarios: BTreeMap<String, u64>,
}

impl ScenarioDataset {
    /// Number of clips over all splits.
    pub fn len(&self) -> usize {
        self.clips.values().map(Vec::len).sum()
    }

    /// Whether the dataset has no clip.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The datasets of one split kind, with what made them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScenarioDatasets {
    /// Unseen or mixed.
    pub split: ScenarioSplit,
    /// Seed of the Mixed chunking (recorded for Unseen too).
    pub seed: u64,
    /// Share of a Mixed chunk's clips taken from its primary scenario.
    pub primary_fraction: f64,
    /// Corpus folder and the sha256 of its first shard, to tie the datasets to the corpus.
    pub corpus: String,
    /// Only clips of this source kind (`synth`, `bvh`…) were used, when set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// Clips without a scenario label, left out.
    pub unlabelled_clips: u64,
    /// The datasets D_1..D_n (in scenario-name order; continual runs shuffle the order).
    pub datasets: Vec<ScenarioDataset>,
}

/// A source clip with its segments and mirrored copies: the unit datasets are built from,
/// so related clips always travel together.
struct Group<'a> {
    scenario: &'a str,
    clips: Vec<&'a ClipMeta>,
}

fn groups(meta: &[ClipMeta]) -> (Vec<Group<'_>>, u64) {
    let mut by_source: BTreeMap<&str, Group> = BTreeMap::new();
    let mut unlabelled = 0;
    for m in meta {
        let Some(scenario) = m.labels.scenario.as_deref() else {
            unlabelled += 1;
            continue;
        };
        by_source
            .entry(&m.source_clip)
            .or_insert_with(|| Group {
                scenario,
                clips: Vec::new(),
            })
            .clips
            .push(m);
    }
    (by_source.into_values().collect(), unlabelled)
}

fn pools<'a>(groups: &'a [Group<'a>]) -> BTreeMap<&'a str, Vec<&'a Group<'a>>> {
    let mut by_scenario: BTreeMap<&str, Vec<&Group>> = BTreeMap::new();
    for g in groups {
        by_scenario.entry(g.scenario).or_default().push(g);
    }
    by_scenario
}

fn dataset(index: usize, primary: &str, members: &[&Group]) -> ScenarioDataset {
    let mut emotions = BTreeMap::new();
    let mut scenarios = BTreeMap::new();
    let mut clips: BTreeMap<String, Vec<String>> =
        SPLITS.iter().map(|s| (s.to_string(), Vec::new())).collect();
    for g in members {
        for m in &g.clips {
            // The corpus split, never a fresh one: the backbone LM and the evaluator trained
            // on the corpus train split, so a scenario test clip must be a corpus test clip.
            // Mirrored copies share their source clip's split in the corpus already.
            clips
                .entry(m.split.clone())
                .or_default()
                .push(m.motion_id.clone());
            let emotion = m.labels.emotion.clone().unwrap_or_else(|| "(none)".into());
            *emotions.entry(emotion).or_default() += 1;
            *scenarios.entry(g.scenario.to_string()).or_default() += 1;
        }
    }
    clips.values_mut().for_each(|v| v.sort());
    ScenarioDataset {
        name: format!("D{:02}_{primary}", index + 1),
        primary_scenario: primary.to_string(),
        clips,
        emotions,
        scenarios,
    }
}

fn shuffle<T>(items: &mut [T], rng: &mut SplitMix64) {
    for i in (1..items.len()).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        items.swap(i, j);
    }
}

/// Build the scenario datasets of a corpus (of its clips of kind `source` only, when given).
pub fn build(
    corpus: &Corpus,
    split: ScenarioSplit,
    seed: u64,
    primary_fraction: f64,
    source: Option<&str>,
) -> Result<ScenarioDatasets, IngestError> {
    let mut meta = corpus.clip_metadata()?;
    if let Some(kind) = source {
        meta.retain(|m| m.source == kind);
    }
    let (groups, unlabelled) = groups(&meta);
    let by_scenario = pools(&groups);
    if by_scenario.len() < 2 {
        return Err(IngestError::file(
            corpus.dir(),
            format!(
                "{} scenario label(s) in the corpus; scenario datasets need at least 2",
                by_scenario.len()
            ),
        ));
    }
    let datasets = match split {
        ScenarioSplit::Unseen => by_scenario
            .iter()
            .enumerate()
            .map(|(i, (name, members))| dataset(i, name, members))
            .collect(),
        ScenarioSplit::Mixed => mixed(&by_scenario, seed, primary_fraction),
    };
    let first_shard = corpus
        .manifest()
        .shards
        .first()
        .map(|s| s.sha256.clone())
        .unwrap_or_default();
    Ok(ScenarioDatasets {
        split,
        seed,
        primary_fraction,
        corpus: format!(
            "{} (shard-00000 sha256 {first_shard})",
            corpus.dir().display()
        ),
        source: source.map(str::to_string),
        unlabelled_clips: unlabelled,
        datasets,
    })
}

/// Mixed: n chunks of equal clip count; chunk i first takes up to `primary_fraction` of its
/// size from scenario i, then every chunk is topped up from the shuffled remainder.
fn mixed<'a>(
    by_scenario: &BTreeMap<&'a str, Vec<&'a Group<'a>>>,
    seed: u64,
    primary_fraction: f64,
) -> Vec<ScenarioDataset> {
    let mut rng = SplitMix64(seed);
    let n = by_scenario.len();
    let total: usize = by_scenario.values().flatten().map(|g| g.clips.len()).sum();
    let target = total / n;
    let mut chunks: Vec<Vec<&Group>> = vec![Vec::new(); n];
    let mut sizes = vec![0usize; n];
    let mut rest: Vec<&Group> = Vec::new();
    for (i, pool) in by_scenario.values().enumerate() {
        let mut pool = pool.clone();
        shuffle(&mut pool, &mut rng);
        let quota = (primary_fraction * target as f64).round() as usize;
        for g in pool {
            if sizes[i] < quota {
                sizes[i] += g.clips.len();
                chunks[i].push(g);
            } else {
                rest.push(g);
            }
        }
    }
    shuffle(&mut rest, &mut rng);
    // Top up the smallest chunk first so the sizes come out equal up to one group; the last
    // chunk in order takes whatever is left once every chunk has reached the target.
    for g in rest {
        let i = (0..n)
            .filter(|&i| sizes[i] < target)
            .min_by_key(|&i| (sizes[i], i))
            .unwrap_or(n - 1);
        sizes[i] += g.clips.len();
        chunks[i].push(g);
    }
    by_scenario
        .keys()
        .zip(&chunks)
        .enumerate()
        .map(|(i, (name, members))| dataset(i, name, members))
        .collect()
}

/// Write `datasets.json` and `D??_name/{train,val,test}.txt` under `out`, atomically.
pub fn write(out: &Path, sets: &ScenarioDatasets) -> Result<(), IngestError> {
    for d in &sets.datasets {
        for (split, ids) in &d.clips {
            let path = out.join(&d.name).join(format!("{split}.txt"));
            let text: String = ids.iter().map(|id| format!("{id}\n")).collect();
            motionscale_core::write_atomic(&path, text.as_bytes())
                .map_err(|e| IngestError::io(&path, e))?;
        }
    }
    let path = out.join("datasets.json");
    let text = serde_json::to_string_pretty(sets).map_err(|e| e.to_string())?;
    motionscale_core::write_atomic(&path, text.as_bytes()).map_err(|e| IngestError::io(&path, e))
}

/// A table like the L²-EMG paper's Table 1: clips per dataset and split, then per emotion.
pub fn table(sets: &ScenarioDatasets) -> String {
    let emotions: Vec<String> = {
        let mut all: Vec<String> = sets
            .datasets
            .iter()
            .flat_map(|d| d.emotions.keys().cloned())
            .collect();
        all.sort();
        all.dedup();
        all
    };
    let mut out = format!(
        "{:<22} {:>7} {:>6} {:>6} {:>7}",
        format!("{:?}", sets.split),
        "train",
        "val",
        "test",
        "total"
    );
    for e in &emotions {
        out.push_str(&format!(" {:>9}", truncate(e, 9)));
    }
    out.push('\n');
    let mut totals = vec![0u64; 4 + emotions.len()];
    for d in &sets.datasets {
        let counts: Vec<u64> = SPLITS
            .iter()
            .map(|s| d.clips.get(*s).map_or(0, |v| v.len() as u64))
            .chain(std::iter::once(d.len() as u64))
            .chain(
                emotions
                    .iter()
                    .map(|e| d.emotions.get(e).copied().unwrap_or(0)),
            )
            .collect();
        out.push_str(&row(&d.name, &counts));
        totals.iter_mut().zip(&counts).for_each(|(t, c)| *t += c);
    }
    out.push_str(&row("Total", &totals));
    out
}

fn truncate(s: &str, n: usize) -> &str {
    s.char_indices().nth(n).map_or(s, |(i, _)| &s[..i])
}

fn row(name: &str, counts: &[u64]) -> String {
    let mut line = format!(
        "{:<22} {:>7} {:>6} {:>6} {:>7}",
        name, counts[0], counts[1], counts[2], counts[3]
    );
    for c in &counts[4..] {
        line.push_str(&format!(" {c:>9}"));
    }
    line.push('\n');
    line
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::Labels;

    fn meta(id: &str, source: &str, scenario: &str, split: &str) -> ClipMeta {
        ClipMeta {
            motion_id: id.into(),
            source: "test".into(),
            source_clip: source.into(),
            split: split.into(),
            fps: 20.0,
            num_frames: 40,
            labels: Labels {
                scenario: Some(scenario.into()),
                emotion: Some("sad".into()),
                ..Labels::default()
            },
            mirrored: id.starts_with('M'),
        }
    }

    fn corpus_meta() -> Vec<ClipMeta> {
        let mut out = Vec::new();
        for (scenario, n) in [("a", 60), ("b", 30), ("c", 10)] {
            for k in 0..n {
                let src = format!("{scenario}{k:03}");
                let split = crate::corpus::split::split_of(&src);
                out.push(meta(&src, &src, scenario, split));
                out.push(meta(&format!("M{src}"), &src, scenario, split));
            }
        }
        out
    }

    #[test]
    fn mixed_chunks_are_equal_sized_with_a_primary_majority() {
        let meta = corpus_meta();
        let (groups, unlabelled) = groups(&meta);
        assert_eq!(unlabelled, 0);
        let pools = pools(&groups);
        let sets = mixed(&pools, 7, 0.6);
        assert_eq!(sets.len(), 3);
        let sizes: Vec<usize> = sets.iter().map(ScenarioDataset::len).collect();
        assert_eq!(sizes.iter().sum::<usize>(), 200);
        assert!(sizes.iter().all(|&s| (66..=68).contains(&s)), "{sizes:?}");
        // Chunk a: 60% of 66 clips from a; chunk c gets all 20 clips of c as its primary part.
        assert!(sets[0].scenarios["a"] >= 40, "{:?}", sets[0].scenarios);
        assert_eq!(sets[2].scenarios["c"], 20);
        assert!(sets.iter().all(|d| d.scenarios.len() > 1));
        // Every clip sits in its corpus split, so a clip and its mirror stay together.
        let split_of: BTreeMap<&str, &str> = meta
            .iter()
            .map(|m| (m.motion_id.as_str(), m.split.as_str()))
            .collect();
        for d in &sets {
            for (split, ids) in &d.clips {
                assert!(
                    ids.iter().all(|id| split_of[id.as_str()] == split),
                    "{}",
                    d.name
                );
                for id in ids.iter().filter(|id| !id.starts_with('M')) {
                    assert!(ids.contains(&format!("M{id}")), "{id}");
                }
            }
        }
        assert_eq!(mixed(&pools, 7, 0.6), sets, "same seed, same datasets");
        assert_ne!(
            mixed(&pools, 8, 0.6),
            sets,
            "another seed mixes differently"
        );
    }

    #[test]
    fn table_has_one_row_per_dataset_and_totals() {
        let meta = corpus_meta();
        let (groups, _) = groups(&meta);
        let sets = ScenarioDatasets {
            split: ScenarioSplit::Unseen,
            seed: 0,
            primary_fraction: 0.6,
            corpus: "test".into(),
            source: None,
            unlabelled_clips: 0,
            datasets: pools(&groups)
                .iter()
                .enumerate()
                .map(|(i, (k, members))| dataset(i, k, members))
                .collect(),
        };
        let t = table(&sets);
        assert_eq!(t.lines().count(), 5, "{t}");
        assert!(t.lines().last().unwrap().contains(" 200 "), "{t}");
        assert!(t.contains("D03_c"));
    }
}
