//! `motionscale eval`: the metrics of a set of motions against the ground truth of a corpus
//! split, in a trained evaluator's space, with mean and 95% interval over repeats.
//!
//! A motion set is a corpus split (ground truth) or a HumanML3D-layout folder
//! (`new_joint_vecs/<id>.npy` de-normalised features, `texts/<id>.txt`, optional
//! `<split>.txt`), such as `motionscale generate --captions-from` writes. Such a folder may
//! carry `generated.jsonl` (one `{"id", "source_motion_id", "caption", "sample"}` per motion):
//! then motions of one source clip form one group (one is drawn per repeat; groups of
//! ≥ 10 give multimodality), the caption is the one generated from, and labels come from the
//! source clip. Without it, ids that match corpus clips take those clips' labels.
//! [`EvalOptions::splits`] (e.g. a scenario dataset) decides which clips (or, for generated
//! motions, which source clips) form the split, in both sets.

use crate::metrics::{self, Interval};
use crate::model::{EvaluatorConfig, MotionPredictions, TrainedEvaluator};
use crate::train::{class_of, corpus_clips, LabelledClip};
use ingest::corpus::schema::FEATURE_DIM;
use ingest::corpus::split::SplitAssignment;
use ingest::export::hml3d::GeneratedEntry;
use motionscale_core::rng::SplitMix64;
use nn::ModelError;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use text::embed::CaptionEmbeddings;
use text::TextEncoder;

/// How to evaluate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalOptions {
    /// Split of the reference corpus (and of the motion set).
    pub split: String,
    /// Repeats (each redraws captions, samples, pools and pairs).
    pub repeats: usize,
    /// Seed of every draw.
    pub seed: u64,
    /// Only clips of this source kind (`bvh`, `synth`…), in both sets.
    pub source: Option<String>,
    /// Folder of `{train,val,test}.txt` clip lists (e.g. a scenario dataset) that decides
    /// which clips form `split`, in both sets.
    #[serde(default)]
    pub splits: Option<PathBuf>,
    /// Compare two disjoint random halves of the motion set with each other instead of the
    /// set with the reference (a floor for FID on ground truth).
    pub halves: bool,
    /// Give each motion another motion's caption (R-precision should fall to chance).
    pub shuffle_captions: bool,
    /// Standard deviation of Gaussian noise added to every normalised feature.
    pub noise: f64,
    /// R-precision pool size.
    pub pool: usize,
    /// Diversity pairs.
    pub diversity_pairs: usize,
    /// Samples per text for multimodality.
    pub multimodality_samples: usize,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            split: "test".into(),
            repeats: 20,
            seed: 0,
            source: None,
            splits: None,
            halves: false,
            shuffle_captions: false,
            noise: 0.0,
            pool: 32,
            diversity_pairs: 300,
            multimodality_samples: 10,
        }
    }
}

/// One motion to evaluate: the clip (id, features, captions it should match, labels it
/// should show) and its group (the source clip: motions of one group are samples for one
/// text).
#[derive(Debug, Clone)]
pub struct EvalMotion {
    /// Group.
    pub group: String,
    /// The motion.
    pub clip: LabelledClip,
}

/// A loaded motion set and where it came from.
#[derive(Debug, Clone)]
pub struct MotionSet {
    /// `corpus` or `hml3d`.
    pub kind: String,
    /// Its folder.
    pub path: PathBuf,
    /// The motions.
    pub motions: Vec<EvalMotion>,
}

impl MotionSet {
    /// Short sha256 of the ids and features, in order.
    pub fn content_id(&self) -> String {
        let mut hasher = Sha256::new();
        for m in &self.motions {
            hasher.update(m.clip.motion_id.as_bytes());
            for v in &m.clip.features {
                hasher.update(v.to_le_bytes());
            }
        }
        motionscale_core::hex(&hasher.finalize()[..6])
    }
}

fn from_clip(clip: LabelledClip) -> EvalMotion {
    EvalMotion {
        group: clip.motion_id.clone(),
        clip,
    }
}

/// The split lists of `options` (the clips' own splits without them).
fn splits(options: &EvalOptions) -> Result<SplitAssignment, ModelError> {
    let dir = options.splits.as_deref();
    SplitAssignment::from_dir(dir)
        .map_err(|e| ModelError::invalid(dir.unwrap_or(Path::new(".")), e))
}

/// The ground-truth clips of `split` in the corpus at `dir` (those with a caption).
pub fn corpus_split(dir: &Path, options: &EvalOptions) -> Result<MotionSet, ModelError> {
    let source = options.source.as_deref();
    let splits = splits(options)?;
    let clips = corpus_clips(dir, |m| {
        splits.split_of(&m.motion_id, &m.split) == Some(options.split.as_str())
            && source.is_none_or(|s| m.source == s)
    })?;
    Ok(MotionSet {
        kind: "corpus".into(),
        path: dir.to_path_buf(),
        motions: clips
            .into_iter()
            .filter(|c| !c.captions.is_empty())
            .map(from_clip)
            .collect(),
    })
}

/// The motions of a HumanML3D-layout folder; labels come from `labels` (corpus clips by id).
pub fn hml3d_folder(
    dir: &Path,
    options: &EvalOptions,
    labels: &HashMap<String, LabelledClip>,
) -> Result<MotionSet, ModelError> {
    let vecs = dir.join("new_joint_vecs");
    if !vecs.is_dir() {
        return Err(ModelError::Missing {
            path: vecs,
            what: "HumanML3D features folder (or pass a corpus folder)",
        });
    }
    let splits = splits(options)?;
    let split_file = dir.join(format!("{}.txt", options.split));
    let listed = ingest::corpus::split::read_ids(&split_file)
        .map_err(|e| ModelError::invalid(&split_file, e))?;
    let mut ids: Vec<String> = if let Some(ids) = listed {
        ids
    } else {
        let entries = std::fs::read_dir(&vecs).map_err(|e| ModelError::io(&vecs, e))?;
        let mut ids = Vec::new();
        for entry in entries {
            let path = entry.map_err(|e| ModelError::io(&vecs, e))?.path();
            if path.extension().is_some_and(|e| e == "npy") {
                if let Some(stem) = path.file_stem() {
                    ids.push(stem.to_string_lossy().into_owned());
                }
            }
        }
        ids
    };
    ids.sort();
    let sidecar = dir.join("generated.jsonl");
    let mut generated = HashMap::new();
    if sidecar.is_file() {
        let text = std::fs::read_to_string(&sidecar).map_err(|e| ModelError::io(&sidecar, e))?;
        for (n, line) in text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
        {
            let entry: GeneratedEntry = serde_json::from_str(line)
                .map_err(|e| ModelError::invalid(&sidecar, format!("line {}: {e}", n + 1)))?;
            generated.insert(entry.id.clone(), entry);
        }
    }
    let mut motions = Vec::with_capacity(ids.len());
    for id in ids {
        let path = vecs.join(format!("{id}.npy"));
        let array = ingest::npy::read(&path).map_err(|e| ModelError::invalid(&path, e))?;
        if array.shape.len() != 2 || array.shape[1] != FEATURE_DIM || array.shape[0] == 0 {
            return Err(ModelError::invalid(
                &path,
                format!(
                    "shape {:?}, expected (frames ≥ 1, {FEATURE_DIM})",
                    array.shape
                ),
            ));
        }
        let features = array.data.iter().map(|&v| v as f32).collect();
        let (group, captions) = match generated.get(&id) {
            Some(g) => (g.source_motion_id.clone(), vec![g.caption.clone()]),
            None => {
                let texts = dir.join("texts").join(format!("{id}.txt"));
                let text =
                    std::fs::read_to_string(&texts).map_err(|e| ModelError::io(&texts, e))?;
                let lines = ingest::source::hml3d::parse_texts(&text)
                    .map_err(|e| ModelError::invalid(&texts, e))?;
                (id.clone(), lines.into_iter().map(|l| l.caption).collect())
            }
        };
        // Generated motions belong to the split of the clip they were generated from.
        if splits.split_of(&group, &options.split) != Some(options.split.as_str()) {
            continue;
        }
        let label = labels.get(&group);
        if options
            .source
            .as_deref()
            .is_some_and(|s| label.is_none_or(|l| l.source != s))
        {
            continue;
        }
        motions.push(EvalMotion {
            clip: LabelledClip {
                motion_id: id,
                source: label.map_or_else(|| "hml3d".into(), |l| l.source.clone()),
                features,
                captions,
                emotion: label.and_then(|l| l.emotion.clone()),
                action: label.and_then(|l| l.action.clone()),
            },
            group,
        });
    }
    Ok(MotionSet {
        kind: "hml3d".into(),
        path: dir.to_path_buf(),
        motions,
    })
}

/// The metrics over repeats, and what they were computed on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Evaluator folder.
    pub evaluator: PathBuf,
    /// Evaluator content id (sha256 of its config, weights and statistics).
    pub evaluator_id: String,
    /// Reference corpus folder.
    pub corpus: PathBuf,
    /// Reference corpus id (sha256 of its manifest).
    pub corpus_id: String,
    /// Motion set kind (`corpus` or `hml3d`).
    pub motions_kind: String,
    /// Motion set folder.
    pub motions: PathBuf,
    /// Motion set content id (sha256 of ids and features).
    pub motions_id: String,
    /// Motions evaluated, and groups (texts) among them.
    pub motion_count: usize,
    /// Distinct groups.
    pub group_count: usize,
    /// Reference clips (ground truth of the split).
    pub reference_count: usize,
    /// Options, split, seed and repeats included.
    pub options: EvalOptions,
    /// Device the evaluator ran on (`cpu`, `cuda:N`); empty in older reports.
    #[serde(default)]
    pub device: String,
    /// FID against the reference (or between the halves).
    pub fid: Interval,
    /// R-precision top-1, top-2, top-3.
    pub r_precision: [Interval; 3],
    /// Mean text–motion distance.
    pub matching_score: Interval,
    /// Diversity (`None` with fewer motions than pairs).
    pub diversity: Option<Interval>,
    /// Multimodality (`None` without groups of enough samples).
    pub multimodality: Option<Interval>,
    /// Groups that had enough samples for multimodality.
    pub multimodality_groups: usize,
    /// Emotion classifier weighted F1 on motions with an emotion label known to it.
    pub emotion_weighted_f1: Option<Interval>,
    /// Action classifier accuracy on motions with an action label known to it.
    pub action_accuracy: Option<Interval>,
    /// Chance level of top-1 R-precision (1 / pool).
    pub r_precision_chance: f64,
}

/// Per-token caption embeddings: from the reference corpus, else encoded with `encoder`.
pub fn caption_embeddings(
    captions: &[String],
    stored: &CaptionEmbeddings,
    encoder: Option<&dyn TextEncoder>,
) -> Result<HashMap<String, Vec<f32>>, ModelError> {
    let mut found = stored.get_many(captions.iter().map(String::as_str))?;
    let mut table = HashMap::new();
    let mut missing = Vec::new();
    for caption in captions {
        // A caption listed twice was taken from `found` the first time.
        if table.contains_key(caption) {
            continue;
        }
        match found.remove(caption) {
            Some(t) => {
                table.insert(caption.clone(), t.embeddings);
            }
            None => missing.push(caption.as_str()),
        }
    }
    if missing.is_empty() {
        return Ok(table);
    }
    let encoder = encoder.ok_or_else(|| {
        ModelError::argument(
            "text encoder",
            format!(
                "{} captions (e.g. {:?}) are not embedded in the corpus; pass the text encoder \
             ({}) with --encoder",
                missing.len(),
                missing[0],
                stored.encoder()
            ),
        )
    })?;
    for chunk in missing.chunks(64) {
        for (caption, t) in chunk.iter().zip(encoder.encode(chunk)?) {
            table.insert(caption.to_string(), t.embeddings);
        }
    }
    Ok(table)
}

/// The motions of `set` by text group (a group is one source clip's samples), refused when
/// there are fewer groups than the R-precision pools need.
fn text_groups<'a>(
    set: &'a MotionSet,
    options: &EvalOptions,
) -> Result<BTreeMap<&'a str, Vec<usize>>, ModelError> {
    let need = if options.halves { 2 } else { 1 } * options.pool;
    let mut groups: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, m) in set.motions.iter().enumerate() {
        groups.entry(m.group.as_str()).or_default().push(i);
    }
    if groups.len() < need {
        return Err(ModelError::argument(
            "split",
            format!(
                "{}: {} texts in split {:?}, fewer than {need} (R-precision pools of {})",
                set.path.display(),
                groups.len(),
                options.split,
                options.pool
            ),
        ));
    }
    Ok(groups)
}

/// Every caption of `set` in the evaluator's space, from the reference corpus's stored token
/// embeddings (else `encoder`).
fn caption_space(
    evaluator: &TrainedEvaluator,
    reference: &MotionSet,
    set: &MotionSet,
    encoder: Option<&dyn TextEncoder>,
) -> Result<HashMap<String, Vec<f32>>, ModelError> {
    let stored = CaptionEmbeddings::open(&reference.path, &evaluator.file.text_encoder)?;
    let mut captions: Vec<String> = set
        .motions
        .iter()
        .flat_map(|m| m.clip.captions.clone())
        .collect();
    captions.sort();
    captions.dedup();
    let tokens = caption_embeddings(&captions, &stored, encoder)?;
    let rows: Vec<&[f32]> = captions.iter().map(|c| tokens[c].as_slice()).collect();
    let embedded = evaluator.embed_texts(&rows, 128)?;
    Ok(captions.into_iter().zip(embedded).collect())
}

/// The classifiers' weighted F1 on emotion and accuracy on action over the `picks` of `set`
/// that carry a label the evaluator knows (None where none does).
fn classifier_scores(
    config: &EvaluatorConfig,
    set: &MotionSet,
    picks: &[usize],
    predictions: &MotionPredictions,
) -> (Option<f64>, Option<f64>) {
    let scored = |classes: &[String],
                  label: fn(&LabelledClip) -> &Option<String>,
                  predicted: &[usize]| {
        let (p, t): (Vec<usize>, Vec<usize>) = picks
            .iter()
            .filter_map(|&i| {
                class_of(classes, label(&set.motions[i].clip)).map(|t| (predicted[i], t as usize))
            })
            .unzip();
        (!t.is_empty()).then_some((p, t))
    };
    let emotion = scored(&config.emotions, |m| &m.emotion, &predictions.emotion)
        .map(|(p, t)| metrics::weighted_f1(&p, &t));
    let action = scored(&config.actions, |m| &m.action, &predictions.action)
        .map(|(p, t)| metrics::accuracy(&p, &t));
    (emotion, action)
}

/// The report of `set` against `reference`: each metric's values over the repeats as a mean
/// and interval; `counts` are the text groups and the multimodality groups.
fn report(
    evaluator: &TrainedEvaluator,
    evaluator_dir: &Path,
    (reference, set): (&MotionSet, &MotionSet),
    options: &EvalOptions,
    mut values: BTreeMap<&str, Vec<f64>>,
    (group_count, multimodality_groups): (usize, usize),
) -> Result<EvalReport, ModelError> {
    let mut take = |name: &str| values.remove(name).map(Interval::of);
    let required = |v: Option<Interval>| v.expect("computed every repeat");
    Ok(EvalReport {
        evaluator: evaluator_dir.to_path_buf(),
        evaluator_id: evaluator.id.clone(),
        corpus: reference.path.clone(),
        corpus_id: crate::model::corpus_id(&reference.path)?,
        motions_kind: set.kind.clone(),
        motions: set.path.clone(),
        motions_id: set.content_id(),
        motion_count: set.motions.len(),
        group_count,
        reference_count: reference.motions.len(),
        options: options.clone(),
        device: nn::device::device_name(evaluator.net.device()),
        fid: required(take("fid")),
        r_precision: [
            required(take("top1")),
            required(take("top2")),
            required(take("top3")),
        ],
        matching_score: required(take("matching")),
        diversity: take("diversity"),
        multimodality: take("multimodality"),
        multimodality_groups,
        emotion_weighted_f1: take("emotion_f1"),
        action_accuracy: take("action_accuracy"),
        r_precision_chance: 1.0 / options.pool as f64,
    })
}

/// Evaluate `set` against the ground truth `reference` with `evaluator`.
pub fn evaluate_motions(
    evaluator: &TrainedEvaluator,
    evaluator_dir: &Path,
    reference: &MotionSet,
    set: &MotionSet,
    options: &EvalOptions,
    encoder: Option<&dyn TextEncoder>,
) -> Result<EvalReport, ModelError> {
    let groups = text_groups(set, options)?;
    let text_embedding = caption_space(evaluator, reference, set, encoder)?;
    let reference_embeddings = match options.halves {
        true => Vec::new(),
        false => motion_predictions(evaluator, reference)?.embeddings,
    };
    let clean = match options.noise > 0.0 {
        true => None,
        false => Some(motion_predictions(evaluator, set)?),
    };
    let config = &evaluator.net.config;
    let group_list: Vec<&Vec<usize>> = groups.values().collect();
    let mut values: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    let mut push = |name: &'static str, v: f64| values.entry(name).or_default().push(v);
    let mut multimodality_groups = 0;
    for repeat in 0..options.repeats {
        let mut rng = SplitMix64::stream(options.seed, repeat as u64);
        let noisy_predictions;
        let predictions = match &clean {
            Some(p) => p,
            None => {
                noisy_predictions =
                    noisy_motion_predictions(evaluator, set, options.noise, &mut rng)?;
                &noisy_predictions
            }
        };
        let (picks, texts) = draw_pairs(&group_list, set, options.shuffle_captions, &mut rng);
        let embedding = |i: usize| predictions.embeddings[i].clone();
        let (matched, fid) = match options.halves {
            true => fid_of_halves(&picks, predictions),
            false => {
                let a: Vec<Vec<f32>> = picks.iter().map(|&i| embedding(i)).collect();
                (picks.len(), metrics::fid(&a, &reference_embeddings))
            }
        };
        push("fid", fid);
        let pairs = (&picks[..matched], &texts[..matched]);
        let (r, matching) = text_metrics(pairs, predictions, &text_embedding, options.pool);
        push("top1", r[0]);
        push("top2", r[1]);
        push("top3", r[2]);
        push("matching", matching);
        let all: Vec<Vec<f32>> = picks.iter().map(|&i| embedding(i)).collect();
        if let Some(d) = metrics::diversity(&all, options.diversity_pairs, &mut rng) {
            push("diversity", d);
        }
        let samples = options.multimodality_samples;
        let (groups_scored, mm) = multimodality(&group_list, predictions, samples, &mut rng);
        multimodality_groups = groups_scored;
        if let Some(mm) = mm {
            push("multimodality", mm);
        }
        let (emotion_f1, action_accuracy) = classifier_scores(config, set, &picks, predictions);
        if let Some(v) = emotion_f1 {
            push("emotion_f1", v);
        }
        if let Some(v) = action_accuracy {
            push("action_accuracy", v);
        }
    }
    let counts = (groups.len(), multimodality_groups);
    report(
        evaluator,
        evaluator_dir,
        (reference, set),
        options,
        values,
        counts,
    )
}

/// The evaluator's predictions for every motion of `set`.
fn motion_predictions(
    evaluator: &TrainedEvaluator,
    set: &MotionSet,
) -> Result<MotionPredictions, ModelError> {
    let motions: Vec<&[f32]> = set.motions.iter().map(features).collect();
    evaluator.embed_motions(&motions, 128)
}

/// The evaluator's predictions for every motion of `set` with Gaussian noise of standard
/// deviation `noise` added to its normalised features (the check that FID grows with noise).
fn noisy_motion_predictions(
    evaluator: &TrainedEvaluator,
    set: &MotionSet,
    noise: f64,
    rng: &mut SplitMix64,
) -> Result<MotionPredictions, ModelError> {
    let noisy: Vec<Vec<f32>> = set
        .motions
        .iter()
        .map(|m| add_noise(&m.clip.features, evaluator, noise, rng))
        .collect();
    let motions: Vec<&[f32]> = noisy.iter().map(Vec::as_slice).collect();
    evaluator.embed_motions(&motions, 128)
}

/// One motion per group and one of its captions, in a random order (the captions shuffled
/// apart from their motions when `shuffle_captions`, the check that retrieval falls to chance).
fn draw_pairs<'a>(
    groups: &[&Vec<usize>],
    set: &'a MotionSet,
    shuffle_captions: bool,
    rng: &mut SplitMix64,
) -> (Vec<usize>, Vec<&'a str>) {
    let mut picks: Vec<usize> = groups.iter().map(|g| g[rng.index(g.len())]).collect();
    rng.shuffle(&mut picks);
    let mut texts: Vec<&str> = picks
        .iter()
        .map(|&i| {
            let c = &set.motions[i].clip.captions;
            c[rng.index(c.len())].as_str()
        })
        .collect();
    if shuffle_captions {
        rng.shuffle(&mut texts);
    }
    (picks, texts)
}

/// FID between the two halves of `picks` (the set against itself), with the half's size:
/// the number of pairs the text metrics use.
fn fid_of_halves(picks: &[usize], predictions: &MotionPredictions) -> (usize, f64) {
    let embedding = |i: usize| predictions.embeddings[i].clone();
    let half = picks.len() / 2;
    let a: Vec<Vec<f32>> = picks[..half].iter().map(|&i| embedding(i)).collect();
    let b: Vec<Vec<f32>> = picks[half..2 * half]
        .iter()
        .map(|&i| embedding(i))
        .collect();
    (half, metrics::fid(&a, &b))
}

/// R-precision at 1–3 and the matching score of the motions `pairs.0` against their captions
/// `pairs.1`, in retrieval pools of `pool`.
fn text_metrics(
    pairs: (&[usize], &[&str]),
    predictions: &MotionPredictions,
    text_embedding: &HashMap<String, Vec<f32>>,
    pool: usize,
) -> ([f64; 3], f64) {
    let (picks, texts) = pairs;
    let motion_rows: Vec<Vec<f32>> = picks
        .iter()
        .map(|&i| predictions.embeddings[i].clone())
        .collect();
    let text_rows: Vec<Vec<f32>> = texts.iter().map(|t| text_embedding[*t].clone()).collect();
    let r = metrics::r_precision::<3>(&text_rows, &motion_rows, pool);
    (r, metrics::matching_score(&text_rows, &motion_rows))
}

/// Multimodality over the groups with at least `samples` motions, with how many there are.
fn multimodality(
    groups: &[&Vec<usize>],
    predictions: &MotionPredictions,
    samples: usize,
    rng: &mut SplitMix64,
) -> (usize, Option<f64>) {
    let mm_groups: Vec<Vec<Vec<f32>>> = groups
        .iter()
        .filter(|g| g.len() >= samples)
        .map(|g| {
            g.iter()
                .map(|&i| predictions.embeddings[i].clone())
                .collect()
        })
        .collect();
    let mm = metrics::multimodality(&mm_groups, samples, rng);
    (mm_groups.len(), mm)
}

/// Every motion of a set in the evaluator's space, with the first caption's embedding and
/// the classifiers' predictions (for inspection, retrieval, or checking against PyTorch).
pub struct SetEmbeddings {
    /// Motion embeddings, in set order.
    pub motions: MotionPredictions,
    /// Embedding of each motion's first caption.
    pub texts: Vec<Vec<f32>>,
}

/// Embed every motion of `set` and its first caption (caption token embeddings from the
/// corpus at `reference`, else from `encoder`).
pub fn embed_set(
    evaluator: &TrainedEvaluator,
    reference: &Path,
    set: &MotionSet,
    encoder: Option<&dyn TextEncoder>,
) -> Result<SetEmbeddings, ModelError> {
    let stored = CaptionEmbeddings::open(reference, &evaluator.file.text_encoder)?;
    let first: Vec<String> = set
        .motions
        .iter()
        .map(|m| m.clip.captions[0].clone())
        .collect();
    let tokens = caption_embeddings(&first, &stored, encoder)?;
    let rows: Vec<&[f32]> = first.iter().map(|c| tokens[c].as_slice()).collect();
    Ok(SetEmbeddings {
        motions: motion_predictions(evaluator, set)?,
        texts: evaluator.embed_texts(&rows, 128)?,
    })
}

fn features(m: &EvalMotion) -> &[f32] {
    &m.clip.features
}

/// `features` plus Gaussian noise of `sd` in normalised units (σ scaled by each feature's
/// standard deviation).
fn add_noise(
    features: &[f32],
    evaluator: &TrainedEvaluator,
    sd: f64,
    rng: &mut SplitMix64,
) -> Vec<f32> {
    let std = evaluator.std();
    features
        .iter()
        .enumerate()
        .map(|(k, &v)| v + (sd * rng.normal()) as f32 * std[k % FEATURE_DIM])
        .collect()
}
