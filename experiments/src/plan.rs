//! The IsoFLOP plan: every (budget C, model, vocabulary) point with its token budget
//! D = C / (6·(N_nv + N_v)) (`lm::accounting`), written as TOML.
//!
//! ```toml
//! format = "motionscale-isoflop-plan-v1"
//! corpus = "/abs/corpus"              # captions (and tokenizer training data)
//! text_encoder = "all-MiniLM-L6-v2-…" # caption embeddings used by every run
//! text_dim = 384
//!
//! [train]                             # prefix-LM settings shared by every point
//! batch_size = 32
//! lr = 0.001
//! …
//! checkpoint_every = 100              # steps; the test split is evaluated at each checkpoint
//!
//! [[vocabularies]]                    # one per --vocabs entry, shared by all its points
//! codebook = 256                      # nominal size (the key points refer to)
//! codebook_size = 240                 # codes the model sees (FSQ 2^8 = [8,6,5])
//! train_clips = 8186
//! train_tokens = 231012               # loss positions in one epoch of the train split
//! [vocabularies.source]
//! kind = "train"                      # or "tokenizer" (dir = …), or "token_set" (dir = …)
//! …                                   # "train": the tokenizer config and its training settings
//!
//! [[points]]
//! index = 0                           # the Slurm array task id
//! run_id = "c1e12-cpu-50K-v256"       # RUNS/<run_id>/
//! budget = 1e12
//! model = "cpu-50K"
//! codebook = 256
//! d_model = 64
//! n_layers = 1
//! n_heads = 1
//! n_nv = 49728
//! n_v = 31104                         # 2·V·d: untied embedding + head, V = K + 3
//! tokens = 5361254                    # D
//! epochs = 23.2                       # D / train_tokens
//! flags = ["exceeds-data"]            # or "below-one-step" (not run)
//! seed = 1                            # only on a repeat (`--repeat`): its training seed
//! ```
//!
//! A plan grows by `--extend`: the earlier plan's points come first, unchanged, so a sweep
//! folder that ran it adopts the longer plan and trains only the new points (repeats over
//! seeds, a forward budget), and the final plan file reproduces every run.
//!
//! A vocabulary is trained (`kind = "train"`) into `RUNS/tokenizers/<codebook>/` and
//! tokenized into `RUNS/tokens/<codebook>/` by the first stage of `sweep run`, a given
//! tokenizer (`kind = "tokenizer"`) is only tokenized there, and a given token set
//! (`kind = "token_set"`) is used as it is.

use crate::centring::{self, Centre};
use crate::data_ladder::{self, DataSource, DataSubset};
use crate::recipe::Recipe;
use crate::SweepError;
use ingest::corpus::manifest::Manifest;
use ingest::corpus::reader::ClipMeta;
use ingest::corpus::Corpus;
use lm::accounting;
use lm::prefix_lm::{PrefixLmConfig, PRESETS};
use lm::train::{Hyperparams, ModelShape, TrainConfig, HYPERPARAMS};
use nn::device::Precision;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use tokenizer::model::TokenizerConfig;
use tokenizer::TokenSet;

/// Format tag of a plan file.
pub const FORMAT: &str = "motionscale-isoflop-plan-v1";

/// A whole IsoFLOP sweep: shared settings, vocabularies and points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IsoFlopPlan {
    /// Always [`FORMAT`].
    pub format: String,
    /// Corpus with the caption embeddings (and the tokenizers' training data).
    pub corpus: PathBuf,
    /// Text encoder id of the caption embeddings.
    pub text_encoder: String,
    /// Width of the caption embeddings (it sizes the text projection, part of N_nv).
    pub text_dim: usize,
    /// Things to look at before running: sizes that do not bracket the predicted N_opt,
    /// points dropped above `--max-epochs`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Training settings shared by every point.
    pub train: TrainSettings,
    /// The vocabularies, one per codebook size.
    pub vocabularies: Vec<Vocabulary>,
    /// The train-split subsets of the unique-data axis (`--data-fractions`), by name.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub data: Vec<DataSubset>,
    /// The whole train split described as a subset (`all-1`): the hours of the points planned
    /// without `--data-fractions` (absent from plans written before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_split: Option<DataSubset>,
    /// Every (budget, model, vocabulary, data) point, in index order.
    pub points: Vec<PlanPoint>,
    /// Each budget's predicted N_opt, when the sizes were centred on an earlier fit.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub centres: Vec<Centre>,
}

/// Prefix-LM training settings shared by every point (the rest of `lm::train::TrainConfig`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainSettings {
    /// The optimisation settings (`train`'s).
    #[serde(flatten)]
    pub hyper: Hyperparams,
    /// Checkpoint (and evaluate the test split) every this many steps, and at the end.
    pub checkpoint_every: u64,
    /// Arithmetic of every point (written only when not f32, so earlier plans read alike).
    #[serde(default, skip_serializing_if = "is_f32")]
    pub precision: Precision,
    /// A recipe per size (`--recipe`): each point's peak rate from its N_nv and the recipe's
    /// shared settings in place of the ones above.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recipe: Option<Recipe>,
}

fn is_f32(p: &Precision) -> bool {
    *p == Precision::F32
}

impl Default for TrainSettings {
    /// `lm::train`'s defaults, checkpointing every 100 steps, f32.
    fn default() -> Self {
        Self {
            hyper: HYPERPARAMS,
            checkpoint_every: 100,
            precision: Precision::F32,
            recipe: None,
        }
    }
}

/// One vocabulary (codebook size) and where its token set comes from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Vocabulary {
    /// Nominal codebook size (`--vocabs` entry; FSQ level sets are named by 2^k).
    pub codebook: usize,
    /// Motion codes K the model sees (the vocabulary adds BOS, EOS, PAD).
    pub codebook_size: usize,
    /// Train clips.
    pub train_clips: u64,
    /// Loss positions of one epoch of the train split (tokens + EOS, cut at
    /// `max_motion_tokens`): the data available without repetition.
    pub train_tokens: u64,
    /// Where the token set comes from.
    pub source: VocabSource,
}

/// Where a vocabulary's token set comes from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum VocabSource {
    /// A token set made beforehand (`motionscale tokenize`).
    TokenSet {
        /// Token set folder.
        dir: PathBuf,
    },
    /// A trained tokenizer; the sweep tokenizes the corpus into `RUNS/tokens/<codebook>/`.
    Tokenizer {
        /// Tokenizer checkpoint folder.
        dir: PathBuf,
    },
    /// Trained by the sweep into `RUNS/tokenizers/<codebook>/`, then tokenized.
    Train {
        /// Architecture.
        tokenizer: Box<TokenizerConfig>,
        /// Training settings.
        train: Box<tokenizer::train::TrainConfig>,
    },
}

/// Whether two paths name the same folder: equal, or equal once resolved. A plan committed
/// with paths relative to the data folder names the same corpus and token sets as the absolute
/// paths a new plan records.
fn same_path(a: &Path, b: &Path) -> bool {
    a == b
        || matches!(
            (std::fs::canonicalize(a), std::fs::canonicalize(b)),
            (Ok(x), Ok(y)) if x == y
        )
}

impl Vocabulary {
    /// Whether `other` is this vocabulary, its folders compared by [`same_path`].
    fn same_as(&self, other: &Vocabulary) -> bool {
        let folders_agree = match (&self.source, &other.source) {
            (VocabSource::TokenSet { dir: a }, VocabSource::TokenSet { dir: b })
            | (VocabSource::Tokenizer { dir: a }, VocabSource::Tokenizer { dir: b }) => {
                same_path(a, b)
            }
            (a, b) => a == b,
        };
        let with_other_source = Vocabulary {
            source: other.source.clone(),
            ..self.clone()
        };
        folders_agree && with_other_source == *other
    }

    /// The token set folder of this vocabulary in the sweep folder `runs`.
    pub fn tokens_dir(&self, runs: &Path) -> PathBuf {
        match &self.source {
            VocabSource::TokenSet { dir } => dir.clone(),
            _ => runs.join("tokens").join(self.codebook.to_string()),
        }
    }

    /// The tokenizer folder to tokenize with (none for a given token set).
    pub fn tokenizer_dir(&self, runs: &Path) -> Option<PathBuf> {
        match &self.source {
            VocabSource::TokenSet { .. } => None,
            VocabSource::Tokenizer { dir } => Some(dir.clone()),
            VocabSource::Train { .. } => {
                Some(runs.join("tokenizers").join(self.codebook.to_string()))
            }
        }
    }
}

/// Why a point is marked.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PointFlag {
    /// D exceeds one epoch of the train split: the run repeats data.
    ExceedsData,
    /// D is less than one batch of mean-length clips: the point is not run.
    BelowOneStep,
    /// D is more epochs of the train split than `--max-epochs` allows (kept, flagged).
    AboveMaxEpochs,
}

/// One run of the sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanPoint {
    /// Row of the plan (the Slurm array task id).
    pub index: usize,
    /// Run folder name, `c<budget>-<model>-v<codebook>`.
    pub run_id: String,
    /// Compute budget C in FLOPs (6·N·D convention).
    pub budget: f64,
    /// Model preset.
    pub model: String,
    /// Nominal codebook size (a [`Vocabulary::codebook`]).
    pub codebook: usize,
    /// Width d.
    pub d_model: usize,
    /// Blocks.
    pub n_layers: usize,
    /// Heads.
    pub n_heads: usize,
    /// Non-vocabulary parameters.
    pub n_nv: u64,
    /// Vocabulary parameters (2·V·d, untied).
    pub n_v: u64,
    /// Token budget D = C / (6·(N_nv + N_v)).
    pub tokens: u64,
    /// D over one epoch of the train split.
    pub epochs: f64,
    /// Marks (data repetition, too small to run).
    pub flags: Vec<PointFlag>,
    /// Training seed of a repeat (`run_id` ends in `-s<seed>`); `[train]`'s seed otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// The train subset it learns from (a [`DataSubset::name`]; `run_id` has `-d<name>`);
    /// the whole train split otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data: Option<String>,
    /// Loss positions of one epoch of its subset (with `data`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unique_tokens: Option<u64>,
}

impl PointFlag {
    /// The flag as the plan and the results table spell it.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::ExceedsData => "exceeds-data",
            Self::BelowOneStep => "below-one-step",
            Self::AboveMaxEpochs => "above-max-epochs",
        }
    }
}

impl PlanPoint {
    /// Whether the point is trained (not below one step).
    pub fn runnable(&self) -> bool {
        !self.flags.contains(&PointFlag::BelowOneStep)
    }

    /// The seed this point trains with, in `plan`.
    pub fn seed(&self, plan: &IsoFlopPlan) -> u64 {
        self.seed.unwrap_or(plan.train.hyper.seed)
    }

    /// Loss positions of one epoch of the data it learns from, in `plan`.
    pub fn unique_tokens(&self, plan: &IsoFlopPlan) -> u64 {
        self.unique_tokens
            .unwrap_or_else(|| plan.vocabulary(self.codebook).map_or(0, |v| v.train_tokens))
    }
}

/// What to plan.
#[derive(Debug, Clone)]
pub struct PlanRequest {
    /// Corpus with caption embeddings.
    pub corpus: PathBuf,
    /// Text encoder id (default: the corpus's only one).
    pub text_encoder: Option<String>,
    /// Compute budgets C.
    pub budgets: Vec<f64>,
    /// Model presets, ladder names or `WxL[xH]` shapes (see [`expand_models`]).
    pub models: Vec<String>,
    /// Nominal codebook size and token source of each vocabulary.
    pub vocabularies: Vec<(usize, VocabSource)>,
    /// Shared training settings.
    pub train: TrainSettings,
    /// Centre each budget's sizes on an earlier fit's N_opt.
    pub centring: Option<Centring>,
    /// The most epochs of the train split a point may take.
    pub max_epochs: Option<EpochLimit>,
    /// An earlier plan whose points come first, unchanged (its settings must be the same).
    pub extend: Option<IsoFlopPlan>,
    /// Points (by run id) to repeat with each of `repeat_seeds`.
    pub repeat: Vec<String>,
    /// Training seeds of the repeats.
    pub repeat_seeds: Vec<u64>,
    /// The unique-data axis: fractions of the train hours (each point at each), none for the
    /// whole split only.
    pub data_fractions: Vec<f64>,
    /// The clips the fractions draw from.
    pub data_source: DataSource,
    /// Seed of the clip order of the fractions.
    pub data_seed: u64,
    /// Keep only these run ids of the grid (the active planner's picks); empty keeps all.
    pub only: Vec<String>,
}

/// Sizes per budget, taken from the model list around an earlier fit's N_opt.
#[derive(Debug, Clone)]
pub struct Centring {
    /// The earlier fit (`fits.json`).
    pub fits: fits::Fits,
    /// Models per budget.
    pub sizes: usize,
}

/// A limit on data repetition.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpochLimit {
    /// Epochs over the unique train tokens.
    pub epochs: f64,
    /// Drop points above it (else keep them flagged `above-max-epochs`).
    pub drop: bool,
}

/// The shape a plan's model name stands for: a preset, or `WxL` / `WxLxH` (width W, L
/// blocks, H heads; by default heads of width 64 as in the CPU ladder, at least one).
pub fn model_shape(name: &str) -> Result<ModelShape, SweepError> {
    if lm::prefix_lm::preset(name).is_some() {
        return Ok(ModelShape::Preset(name.to_string()));
    }
    let numbers: Option<Vec<usize>> = name.split('x').map(|n| n.parse().ok()).collect();
    match numbers.as_deref() {
        Some(&[d_model, n_layers]) => Ok((d_model, n_layers, (d_model / 64).max(1))),
        Some(&[d_model, n_layers, n_heads]) => Ok((d_model, n_layers, n_heads)),
        _ => Err(SweepError::Argument(format!(
            "model {name:?}: not a preset (known: cpu, scamo, {}) nor WIDTHxLAYERS[xHEADS]",
            PRESETS.map(|p| p.name).join(", ")
        ))),
    }
    .map(|(d_model, n_layers, n_heads)| ModelShape::Custom {
        d_model,
        n_layers,
        n_heads,
        ffn_hidden: None,
    })
}

/// Model names for `names`, where `cpu` stands for the whole CPU ladder and `scamo` for
/// ScaMo's six sizes; presets and `WxL[xH]` shapes stand for themselves, anything else is an
/// error.
pub fn expand_models(names: &[String]) -> Result<Vec<String>, SweepError> {
    let mut out = Vec::new();
    for name in names {
        let ladder: Vec<&str> = match name.as_str() {
            "cpu" => PRESETS
                .iter()
                .filter(|p| p.name.starts_with("cpu-"))
                .map(|p| p.name)
                .collect(),
            "scamo" => PRESETS
                .iter()
                .filter(|p| p.nominal_params.is_some())
                .map(|p| p.name)
                .collect(),
            n => {
                model_shape(n)?;
                vec![n]
            }
        };
        out.extend(ladder.into_iter().map(String::from));
    }
    out.dedup();
    Ok(out)
}

/// Loss positions of a clip of `tokens` tokens when at most `max` are kept: the kept tokens,
/// plus EOS when the clip ends within them (as `lm::lm_data::Example::targets`).
pub(crate) fn lm_targets(tokens: usize, max: usize) -> u64 {
    let keep = tokens.min(max);
    keep as u64 + u64::from(keep == tokens)
}

/// Train clips (by id) and their loss positions per epoch for a vocabulary, from its token
/// set or, before tokenizing, from the corpus clip lengths and the tokenizer's down-sampling.
fn train_data(
    source: &VocabSource,
    codebook: usize,
    corpus: &Path,
    max_motion: usize,
) -> Result<(usize, Vec<(String, u64)>), SweepError> {
    let from_corpus = |downsample: usize| -> Result<Vec<(String, u64)>, SweepError> {
        let c = Corpus::open(corpus).map_err(|e| SweepError::invalid(corpus, e))?;
        Ok(c.clips()
            .iter()
            .filter(|clip| clip.split == "train")
            .map(|clip| {
                let targets = lm_targets(clip.num_frames as usize / downsample, max_motion);
                (clip.motion_id.clone(), targets)
            })
            .collect())
    };
    let (codes, nominal, targets) = match source {
        VocabSource::TokenSet { dir } => {
            let set = TokenSet::open(dir)?;
            let t = &set.manifest.tokenizer;
            let targets = set
                .split("train")
                .map(|c| (c.motion_id.clone(), lm_targets(c.tokens.len(), max_motion)))
                .collect();
            (t.codebook_size, t.nominal_codebook, targets)
        }
        VocabSource::Tokenizer { dir } => {
            // Its shape only: the weights are read where the sweep tokenizes.
            let path = dir.join(tokenizer::model::CONFIG_FILE);
            let c: TokenizerConfig = motionscale_core::files::read_json(&path)?;
            (
                c.codebook_size(),
                c.nominal_codebook,
                from_corpus(c.conv.downsample_factor())?,
            )
        }
        VocabSource::Train { tokenizer, .. } => (
            tokenizer.codebook_size(),
            tokenizer.nominal_codebook,
            from_corpus(tokenizer.conv.downsample_factor())?,
        ),
    };
    if codebook != nominal && codebook != codes {
        return Err(SweepError::Argument(format!(
            "vocabulary {codebook}: its tokenizer has {codes} codes (nominal {nominal})"
        )));
    }
    Ok((codes, targets))
}

/// Run folder name of a point: `c<budget>-<model>-v<codebook>`, e.g. `c3e12-cpu-800K-v1024`.
pub fn run_id(budget: f64, model: &str, codebook: usize) -> String {
    format!("c{budget:e}-{model}-v{codebook}")
}

/// The subsets of `request`'s data fractions of the corpus `clips`, each with its train
/// clips' ids.
fn data_subsets<'a>(
    request: &PlanRequest,
    clips: &'a [ClipMeta],
) -> Result<Vec<(DataSubset, Vec<&'a str>)>, SweepError> {
    let (source, seed) = (request.data_source, request.data_seed);
    let mut subsets = Vec::new();
    for &fraction in &request.data_fractions {
        let chosen = data_ladder::select(clips, source, fraction, seed);
        if chosen.is_empty() {
            return Err(SweepError::Argument(format!(
                "--data-source {source}: the corpus has no such train clips"
            )));
        }
        let ids = chosen.iter().map(|c| c.motion_id.as_str()).collect();
        subsets.push((data_ladder::describe(&chosen, source, fraction, seed), ids));
    }
    Ok(subsets)
}

/// Loss positions of one epoch of each subset (its train clips' ids) for a vocabulary's
/// per-clip targets.
fn subset_tokens(subsets: &[(DataSubset, Vec<&str>)], targets: &[(String, u64)]) -> Vec<u64> {
    let by_id: std::collections::HashMap<&str, u64> =
        targets.iter().map(|(id, t)| (id.as_str(), *t)).collect();
    subsets
        .iter()
        .map(|(_, ids)| ids.iter().filter_map(|id| by_id.get(id)).sum())
        .collect()
}

/// Vocabularies, data subsets, each vocabulary's loss positions per epoch of each subset, and
/// the whole train split described as a subset.
type VocabulariesAndData = (Vec<Vocabulary>, Vec<DataSubset>, Vec<Vec<u64>>, DataSubset);

/// The vocabularies of `request` with their train data in `corpus`, the data subsets, each
/// vocabulary's loss positions per epoch of each subset, and the whole train split.
fn vocabularies_and_data(
    request: &PlanRequest,
    corpus: &Path,
) -> Result<VocabulariesAndData, SweepError> {
    let clips = Corpus::open(corpus)
        .and_then(|c| c.clip_metadata())
        .map_err(|e| SweepError::invalid(corpus, e))?;
    let data = data_subsets(request, &clips)?;
    let (all, seed) = (DataSource::All, request.data_seed);
    let train_split =
        data_ladder::describe(&data_ladder::select(&clips, all, 1.0, seed), all, 1.0, seed);
    let (mut vocabularies, mut unique) = (Vec::new(), Vec::new());
    for (codebook, source) in &request.vocabularies {
        let source = absolute_source(source)?;
        let max_motion = request.train.hyper.max_motion_tokens;
        let (codebook_size, targets) = train_data(&source, *codebook, corpus, max_motion)?;
        unique.push(subset_tokens(&data, &targets));
        vocabularies.push(Vocabulary {
            codebook: *codebook,
            codebook_size,
            train_clips: targets.len() as u64,
            train_tokens: targets.iter().map(|(_, t)| t).sum(),
            source,
        });
    }
    Ok((
        vocabularies,
        data.into_iter().map(|(d, _)| d).collect(),
        unique,
        train_split,
    ))
}

/// Plan every (budget, model, vocabulary) point of `request`.
pub fn plan(request: &PlanRequest) -> Result<IsoFlopPlan, SweepError> {
    check_grid(request)?;
    let grid = !request.budgets.is_empty();
    let corpus =
        std::fs::canonicalize(&request.corpus).map_err(|e| SweepError::io(&request.corpus, e))?;
    let text_encoder = text::resolve_encoder(&corpus, request.text_encoder.as_deref())?;
    let manifest = Manifest::read(&corpus).map_err(|e| SweepError::invalid(&corpus, e))?;
    let text_dim = manifest
        .text_embeddings
        .iter()
        .find(|e| e.encoder == text_encoder)
        .map(|e| e.dim)
        .expect("resolve_encoder found it in the manifest");
    let models = expand_models(&request.models)?;
    let settings = &request.train;
    let (vocabularies, data, unique, train_split) = vocabularies_and_data(request, &corpus)?;
    // Without fractions every point learns from the whole train split.
    let subsets: Vec<Option<usize>> = match data.is_empty() {
        true => vec![None],
        false => (0..data.len()).map(Some).collect(),
    };
    let mut warnings = Vec::new();
    let mut centres = Vec::new();
    let mut points = Vec::new();
    // N_nv does not depend on the vocabulary: the sizes of the first one serve every budget.
    let sized = match &request.centring {
        Some(_) if grid => sized_models(&models, &vocabularies[0], text_dim)?,
        _ => Vec::new(),
    };
    for &budget in &request.budgets {
        let names = match &request.centring {
            None => models.clone(),
            Some(c) => {
                let (names, centre) = centred_models(&sized, c, budget)?;
                let sizes: Vec<f64> = names.iter().map(|(_, n)| *n).collect();
                warnings.extend(centring::bracket_warning(&sizes, centre.n_opt, budget));
                centres.push(centre);
                names.into_iter().map(|(name, _)| name).collect()
            }
        };
        for name in &names {
            for ((vocab, unique), &subset) in vocabularies
                .iter()
                .zip(&unique)
                .flat_map(|v| subsets.iter().map(move |s| (v, s)))
            {
                let of = subset.map(|i| (&data[i], unique[i]));
                let mut point = plan_point(budget, name, vocab, of, settings, text_dim)?;
                if !(request.only.is_empty() || request.only.contains(&point.run_id)) {
                    continue;
                }
                if !within_max_epochs(&mut point, request, &mut warnings) {
                    continue;
                }
                point.index = points.len();
                points.push(point);
            }
        }
    }
    let new = IsoFlopPlan {
        format: FORMAT.into(),
        corpus,
        text_encoder,
        text_dim,
        warnings,
        train: settings.clone(),
        vocabularies,
        data,
        train_split: Some(train_split),
        points,
        centres,
    };
    let mut plan = match &request.extend {
        None => new,
        Some(base) => base.extended_by(new)?,
    };
    plan.add_repeats(&request.repeat, &request.repeat_seeds)?;
    plan.validate(Path::new("plan"))?;
    Ok(plan)
}

/// Fails unless `request` has a grid to plan (a budget, a model and a vocabulary) or a plan
/// to extend, and only positive budgets.
fn check_grid(request: &PlanRequest) -> Result<(), SweepError> {
    let grid = !request.budgets.is_empty();
    if (grid || request.extend.is_none())
        && (!grid || request.models.is_empty() || request.vocabularies.is_empty())
    {
        return Err(SweepError::Argument(
            "a plan needs at least one budget, model and vocabulary (or --extend)".into(),
        ));
    }
    if let Some(b) = request
        .budgets
        .iter()
        .find(|b| !(b.is_finite() && **b > 0.0))
    {
        return Err(SweepError::Argument(format!(
            "budget {b} must be a positive number"
        )));
    }
    Ok(())
}

/// Whether `point` stays in the plan under `--max-epochs`: one above the limit is flagged, or
/// dropped with a warning when the request says so.
fn within_max_epochs(
    point: &mut PlanPoint,
    request: &PlanRequest,
    warnings: &mut Vec<String>,
) -> bool {
    match request.max_epochs {
        Some(limit) if point.epochs > limit.epochs && limit.drop => {
            warnings.push(format!(
                "dropped {}: {:.1} epochs of the train split > --max-epochs {}",
                point.run_id, point.epochs, limit.epochs
            ));
            false
        }
        Some(limit) if point.epochs > limit.epochs => {
            point.flags.push(PointFlag::AboveMaxEpochs);
            true
        }
        _ => true,
    }
}

/// The point of `budget`, model `name` and `vocab`, on `data` (a subset and its loss
/// positions per epoch) or the whole train split (index 0; the caller numbers it).
fn plan_point(
    budget: f64,
    name: &str,
    vocab: &Vocabulary,
    data: Option<(&DataSubset, u64)>,
    settings: &TrainSettings,
    text_dim: usize,
) -> Result<PlanPoint, SweepError> {
    let config: PrefixLmConfig = model_shape(name)?.resolve(vocab.codebook_size, text_dim)?;
    let params = accounting::param_count(&config);
    let tokens = accounting::tokens_for_budget(&config, budget).round() as u64;
    let per_step = settings.hyper.batch_size as f64 * vocab.train_tokens as f64
        / vocab.train_clips.max(1) as f64;
    let unique = data.map_or(vocab.train_tokens, |(_, u)| u);
    let mut flags = Vec::new();
    if tokens > unique {
        flags.push(PointFlag::ExceedsData);
    }
    if (tokens as f64) < per_step {
        flags.push(PointFlag::BelowOneStep);
    }
    let mut id = run_id(budget, name, vocab.codebook);
    if let Some((subset, _)) = data {
        id = format!("{id}-d{}", subset.name);
    }
    Ok(PlanPoint {
        index: 0,
        run_id: id,
        budget,
        model: name.to_string(),
        codebook: vocab.codebook,
        d_model: config.d_model,
        n_layers: config.n_layers,
        n_heads: config.n_heads,
        n_nv: params.n_nv,
        n_v: params.n_v,
        tokens,
        epochs: tokens as f64 / unique.max(1) as f64,
        flags,
        seed: None,
        data: data.map(|(s, _)| s.name.clone()),
        unique_tokens: data.map(|(_, u)| u),
    })
}

/// Each model with its N_nv, smallest first.
fn sized_models(
    models: &[String],
    vocab: &Vocabulary,
    text_dim: usize,
) -> Result<Vec<(String, f64)>, SweepError> {
    let mut sized = Vec::new();
    for name in models {
        let config = model_shape(name)?.resolve(vocab.codebook_size, text_dim)?;
        sized.push((name.clone(), accounting::param_count(&config).n_nv as f64));
    }
    sized.sort_by(|a, b| a.1.total_cmp(&b.1));
    Ok(sized)
}

/// The `centring.sizes` models of `sized` (smallest first) around the N_opt that the earlier
/// fit predicts at `budget`, and that prediction.
fn centred_models(
    sized: &[(String, f64)],
    centring: &Centring,
    budget: f64,
) -> Result<(Vec<(String, f64)>, Centre), SweepError> {
    let centre = centring::of_fit(&centring.fits, budget).map_err(SweepError::Argument)?;
    let sizes: Vec<f64> = sized.iter().map(|(_, n)| *n).collect();
    let range = centring::window(&sizes, centre.n_opt, centring.sizes);
    Ok((sized[range].to_vec(), centre))
}

/// `source` with its folder made absolute (plans are run from other folders, e.g. by Slurm).
fn absolute_source(source: &VocabSource) -> Result<VocabSource, SweepError> {
    let abs = |dir: &PathBuf| std::fs::canonicalize(dir).map_err(|e| SweepError::io(dir, e));
    Ok(match source {
        VocabSource::TokenSet { dir } => VocabSource::TokenSet { dir: abs(dir)? },
        VocabSource::Tokenizer { dir } => VocabSource::Tokenizer { dir: abs(dir)? },
        train @ VocabSource::Train { .. } => train.clone(),
    })
}

impl IsoFlopPlan {
    /// Read a plan file.
    pub fn read(path: &Path) -> Result<Self, SweepError> {
        let text = std::fs::read_to_string(path).map_err(|e| SweepError::io(path, e))?;
        let plan: Self = toml::from_str(&text).map_err(|e| SweepError::invalid(path, e))?;
        plan.validate(path)?;
        Ok(plan)
    }

    /// Write the plan as TOML, atomically.
    pub fn write(&self, path: &Path) -> Result<(), SweepError> {
        let text = toml::to_string(self).map_err(|e| SweepError::invalid(path, e))?;
        motionscale_core::write_atomic(path, text.as_bytes()).map_err(|e| SweepError::io(path, e))
    }

    /// This plan followed by the points of `new` it lacks (by run id), `new`'s vocabularies it
    /// lacks, and `new`'s warnings and centres; corpus, encoder and settings must match.
    fn extended_by(&self, new: IsoFlopPlan) -> Result<IsoFlopPlan, SweepError> {
        let differs = |what: String| {
            Err(SweepError::Argument(format!(
                "--extend: {what} not as in the extended plan (give the same flags)"
            )))
        };
        if !same_path(&new.corpus, &self.corpus) || new.text_encoder != self.text_encoder {
            return differs("the corpus or its text encoder".into());
        }
        if new.train != self.train {
            return differs("the training settings".into());
        }
        let mut plan = self.clone();
        for vocab in new.vocabularies {
            match plan.vocabulary(vocab.codebook) {
                Some(old) if !old.same_as(&vocab) => {
                    return differs(format!("vocabulary {} (its source)", vocab.codebook))
                }
                Some(_) => {}
                None => plan.vocabularies.push(vocab),
            }
        }
        for subset in new.data {
            match plan.data.iter().find(|d| d.name == subset.name) {
                Some(old) if *old != subset => {
                    return differs(format!("data subset {} (its seed or clips)", subset.name))
                }
                Some(_) => {}
                None => plan.data.push(subset),
            }
        }
        plan.train_split = plan.train_split.or(new.train_split);
        plan.warnings.extend(new.warnings);
        plan.centres.extend(new.centres);
        for mut point in new.points {
            if plan.points.iter().all(|p| p.run_id != point.run_id) {
                point.index = plan.points.len();
                plan.points.push(point);
            }
        }
        Ok(plan)
    }

    /// Append a copy of each point in `run_ids` per seed of `seeds` (run id `<id>-s<seed>`),
    /// skipping copies the plan already has.
    fn add_repeats(&mut self, run_ids: &[String], seeds: &[u64]) -> Result<(), SweepError> {
        if run_ids.is_empty() != seeds.is_empty() {
            return Err(SweepError::Argument(
                "--repeat and --seeds go together".into(),
            ));
        }
        for id in run_ids {
            let Some(point) = self.points.iter().find(|p| p.run_id == *id).cloned() else {
                return Err(SweepError::Argument(format!(
                    "--repeat {id}: the plan has no such point"
                )));
            };
            if point.seed.is_some() {
                return Err(SweepError::Argument(format!(
                    "--repeat {id}: that point is itself a repeat"
                )));
            }
            for &seed in seeds {
                if seed == self.train.hyper.seed {
                    return Err(SweepError::Argument(format!(
                        "--seeds {seed}: that is the plan's own seed ([train] seed)"
                    )));
                }
                let run_id = format!("{id}-s{seed}");
                if self.points.iter().any(|p| p.run_id == run_id) {
                    continue;
                }
                self.points.push(PlanPoint {
                    index: self.points.len(),
                    run_id,
                    seed: Some(seed),
                    ..point.clone()
                });
            }
        }
        Ok(())
    }

    /// Whether this plan is `base` with points (and vocabularies) appended: a sweep folder
    /// that holds `base` may adopt it.
    pub fn extends(&self, base: &IsoFlopPlan) -> bool {
        self.format == base.format
            && self.corpus == base.corpus
            && self.text_encoder == base.text_encoder
            && self.text_dim == base.text_dim
            && self.train == base.train
            && self.vocabularies.starts_with(&base.vocabularies)
            && self.data.starts_with(&base.data)
            && self.points.starts_with(&base.points)
    }

    /// The vocabulary with nominal size `codebook`.
    pub fn vocabulary(&self, codebook: usize) -> Option<&Vocabulary> {
        self.vocabularies.iter().find(|v| v.codebook == codebook)
    }

    /// Check the format tag, that indices are 0..n, run ids unique and every point's
    /// vocabulary listed.
    pub fn validate(&self, path: &Path) -> Result<(), SweepError> {
        let bad = |m: String| Err(SweepError::invalid(path, m));
        if self.format != FORMAT {
            return bad(format!("format {:?}, expected {FORMAT:?}", self.format));
        }
        let mut ids = std::collections::HashSet::new();
        for (i, p) in self.points.iter().enumerate() {
            if p.index != i {
                return bad(format!(
                    "point {} has index {} (want 0..n in order)",
                    p.run_id, p.index
                ));
            }
            if !ids.insert(&p.run_id) {
                return bad(format!("run id {} appears twice", p.run_id));
            }
            if self.vocabulary(p.codebook).is_none() {
                return bad(format!("point {}: no vocabulary {}", p.run_id, p.codebook));
            }
            if let Err(e) = model_shape(&p.model) {
                return bad(format!("point {}: {e}", p.run_id));
            }
            if let Some(name) = &p.data {
                if self.data.iter().all(|d| d.name != *name) {
                    return bad(format!("point {}: no data subset {name}", p.run_id));
                }
            }
        }
        Ok(())
    }

    /// The data subset named `name`.
    pub fn subset(&self, name: &str) -> Option<&DataSubset> {
        self.data.iter().find(|d| d.name == name)
    }

    /// The source of `point`'s train clips (all for a point on the whole train split).
    pub fn data_source(&self, point: &PlanPoint) -> DataSource {
        point
            .data
            .as_deref()
            .and_then(|n| self.subset(n))
            .map_or(DataSource::All, |s| s.source)
    }

    /// The name of the plan's recipe (empty without one).
    pub fn recipe_name(&self) -> String {
        let recipe = self.train.recipe.as_ref();
        recipe.map(|r| r.name.clone()).unwrap_or_default()
    }

    /// The optimisation settings `point` trains with: the plan's, or its recipe's for the
    /// point's size, with the point's seed.
    pub fn hyper(&self, point: &PlanPoint) -> Hyperparams {
        let s = &self.train;
        let mut hyper = match &s.recipe {
            Some(recipe) => recipe.apply(&s.hyper, point.n_nv),
            None => s.hyper.clone(),
        };
        hyper.seed = point.seed(self);
        hyper
    }

    /// The training configuration of `point` writing into `out`, reading `tokens` and, for a
    /// point on a data subset, the split lists in `splits`.
    pub fn train_config(
        &self,
        point: &PlanPoint,
        tokens: &Path,
        splits: Option<&Path>,
        out: &Path,
    ) -> Result<TrainConfig, SweepError> {
        let s = &self.train;
        let mut c = TrainConfig::new(tokens, model_shape(&point.model)?, point.tokens, out);
        c.corpus = Some(self.corpus.clone());
        c.splits = splits.map(Path::to_path_buf);
        c.select_on = self.data_source(point).origin();
        c.text_encoder = Some(self.text_encoder.clone());
        c.hyper = self.hyper(point);
        c.eval_every = Some(s.checkpoint_every);
        c.checkpoint_every = Some(s.checkpoint_every);
        c.compute.precision = s.precision;
        Ok(c)
    }
}

/// File name of the plan copy inside a sweep folder.
pub const PLAN_FILE: &str = "plan.toml";

/// Create the sweep folder `runs` (made absolute) and give it `plan`: write `runs/plan.toml`,
/// or check that the one there is the same plan, or one that `plan` extends (then `plan`
/// replaces it: its first points are the ones already run), or one that extends `plan` (then
/// the folder keeps its own: `plan`'s points are its first ones, so a run of an older plan
/// can go on beside one of its extension).
pub fn adopt_plan(plan: &IsoFlopPlan, runs: &Path) -> Result<PathBuf, SweepError> {
    std::fs::create_dir_all(runs).map_err(|e| SweepError::io(runs, e))?;
    let runs = std::fs::canonicalize(runs).map_err(|e| SweepError::io(runs, e))?;
    let path = runs.join(PLAN_FILE);
    if path.exists() {
        let adopted = IsoFlopPlan::read(&path)?;
        if adopted != *plan {
            if plan.extends(&adopted) {
                plan.write(&path)?;
            } else if !adopted.extends(plan) {
                return Err(SweepError::invalid(
                    &path,
                    "this sweep folder holds a different plan (neither one this plan extends nor an extension of it); use another --out",
                ));
            }
        }
    } else {
        plan.write(&path)?;
    }
    Ok(runs)
}

/// The sweep folder's own plan (`runs/plan.toml`).
pub fn read_adopted_plan(runs: &Path) -> Result<IsoFlopPlan, SweepError> {
    IsoFlopPlan::read(&runs.join(PLAN_FILE))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ladders_expand_and_unknown_models_fail() {
        let cpu = expand_models(&["cpu".into()]).unwrap();
        assert_eq!(cpu.first().map(String::as_str), Some("cpu-50K"));
        assert!(cpu.iter().all(|m| m.starts_with("cpu-")) && cpu.len() == 9);
        assert_eq!(expand_models(&["scamo".into()]).unwrap().len(), 6);
        let two = expand_models(&["cpu-50K".into(), "cpu-400K".into()]).unwrap();
        assert_eq!(two, ["cpu-50K", "cpu-400K"]);
        assert!(expand_models(&["cpu-1B".into()]).is_err());
        assert!(expand_models(&["32x1x1x1".into()]).is_err());
        assert_eq!(expand_models(&["32x1".into()]).unwrap(), ["32x1"]);
        let custom = |d_model, n_layers, n_heads| ModelShape::Custom {
            d_model,
            n_layers,
            n_heads,
            ffn_hidden: None,
        };
        assert_eq!(model_shape("32x1").unwrap(), custom(32, 1, 1));
        assert_eq!(model_shape("256x4").unwrap(), custom(256, 4, 4));
        assert_eq!(model_shape("96x2x3").unwrap(), custom(96, 2, 3));
        assert_eq!(
            model_shape("cpu-3M").unwrap(),
            ModelShape::Preset("cpu-3M".into())
        );
    }

    #[test]
    fn loss_positions_follow_the_lm_data_rule() {
        assert_eq!(lm_targets(10, 64), 11, "tokens + EOS");
        assert_eq!(lm_targets(64, 64), 65, "exactly the limit still ends");
        assert_eq!(lm_targets(100, 64), 64, "cut: no EOS");
        assert_eq!(lm_targets(0, 64), 1, "EOS only");
    }

    fn small_plan() -> IsoFlopPlan {
        let conv = tokenizer::ConvConfig::default();
        let tokenizer = TokenizerConfig::new("fsq", 256, tokenizer::Bound::Tanh, conv).unwrap();
        let train = tokenizer::train::TrainConfig::default();
        let vocab = |codebook, codebook_size, source| Vocabulary {
            codebook,
            codebook_size,
            train_clips: 10,
            train_tokens: 300,
            source,
        };
        let point = |index, codebook, flags| PlanPoint {
            index,
            run_id: run_id(1e12, "cpu-50K", codebook),
            budget: 1e12,
            model: "cpu-50K".into(),
            codebook,
            d_model: 64,
            n_layers: 1,
            n_heads: 1,
            n_nv: 74_048,
            n_v: 31_104,
            tokens: 1_587_000,
            epochs: 5290.0,
            flags,
            seed: None,
            data: None,
            unique_tokens: None,
        };
        IsoFlopPlan {
            format: FORMAT.into(),
            corpus: "/corpus".into(),
            text_encoder: "encoder".into(),
            text_dim: 384,
            warnings: vec!["budget 1e12: a warning".into()],
            train: TrainSettings::default(),
            vocabularies: vec![
                vocab(
                    256,
                    240,
                    VocabSource::Train {
                        tokenizer: Box::new(tokenizer),
                        train: Box::new(train),
                    },
                ),
                vocab(
                    1024,
                    1000,
                    VocabSource::TokenSet {
                        dir: "/tokens".into(),
                    },
                ),
            ],
            data: Vec::new(),
            train_split: None,
            points: vec![
                point(0, 256, vec![PointFlag::ExceedsData]),
                point(
                    1,
                    1024,
                    vec![PointFlag::ExceedsData, PointFlag::BelowOneStep],
                ),
            ],
            centres: vec![Centre {
                budget: 1e12,
                n_opt: 1.5e5,
                source: "the fit's law".into(),
            }],
        }
    }

    #[test]
    fn a_plan_round_trips_through_toml_and_is_validated() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plan.toml");
        let plan = small_plan();
        plan.write(&path).unwrap();
        assert_eq!(IsoFlopPlan::read(&path).unwrap(), plan);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("kind = \"train\"") && text.contains("kind = \"token_set\""));
        assert!(
            text.contains("flags = [\"exceeds-data\", \"below-one-step\"]"),
            "{text}"
        );
        for flag in [PointFlag::ExceedsData, PointFlag::BelowOneStep] {
            assert_eq!(serde_json::to_value(flag).unwrap(), flag.as_str());
        }
        assert!(plan.points[0].runnable() && !plan.points[1].runnable());
        assert_eq!(
            plan.vocabularies[0].tokens_dir(Path::new("/runs")),
            Path::new("/runs/tokens/256")
        );
        assert_eq!(
            plan.vocabularies[1].tokens_dir(Path::new("/runs")),
            Path::new("/tokens")
        );
        assert_eq!(
            plan.vocabularies[0].tokenizer_dir(Path::new("/runs")),
            Some(PathBuf::from("/runs/tokenizers/256"))
        );

        let mut bad = plan.clone();
        bad.points[1].index = 5;
        assert!(bad
            .validate(&path)
            .unwrap_err()
            .to_string()
            .contains("index 5"));
        let mut bad = plan.clone();
        bad.points[1].run_id = bad.points[0].run_id.clone();
        assert!(bad
            .validate(&path)
            .unwrap_err()
            .to_string()
            .contains("twice"));
        let mut bad = plan;
        bad.points[1].codebook = 4096;
        assert!(bad
            .validate(&path)
            .unwrap_err()
            .to_string()
            .contains("no vocabulary 4096"));
    }

    #[test]
    fn a_plan_grows_by_new_points_and_seed_repeats_and_its_folder_adopts_it() {
        let base = small_plan();
        let forward = PlanPoint {
            run_id: run_id(3e12, "cpu-50K", 256),
            budget: 3e12,
            ..base.points[0].clone()
        };
        let mut new = small_plan();
        new.points = vec![forward, base.points[1].clone()];
        new.warnings = vec!["a new warning".into()];
        let mut plan = base.extended_by(new.clone()).unwrap();
        assert!(
            plan.points.starts_with(&base.points),
            "earlier points first, unchanged"
        );
        assert_eq!(
            plan.points.len(),
            3,
            "a point the base has is not planned twice"
        );
        assert_eq!((plan.points[2].index, plan.points[2].budget), (2, 3e12));
        assert_eq!(plan.warnings.len(), 2);

        plan.add_repeats(&["c1e12-cpu-50K-v256".into()], &[1, 2])
            .unwrap();
        let ids: Vec<&str> = plan.points[3..].iter().map(|p| p.run_id.as_str()).collect();
        assert_eq!(ids, ["c1e12-cpu-50K-v256-s1", "c1e12-cpu-50K-v256-s2"]);
        assert_eq!((plan.points[3].index, plan.points[4].seed(&plan)), (3, 2));
        assert_eq!(plan.points[0].seed(&plan), plan.train.hyper.seed);
        let config = plan
            .train_config(&plan.points[3], Path::new("/t"), None, Path::new("/o"))
            .unwrap();
        assert_eq!(config.hyper.seed, 1, "a repeat trains with its own seed");
        assert!(plan.extends(&base) && !base.extends(&plan));

        let refused = |plan: Result<IsoFlopPlan, SweepError>, why: &str| {
            let e = plan.unwrap_err().to_string();
            assert!(e.contains(why), "{e}");
        };
        let mut other = new.clone();
        other.train.checkpoint_every += 1;
        refused(base.extended_by(other), "training settings");
        let mut other = new;
        other.vocabularies[1].source = VocabSource::TokenSet {
            dir: "/elsewhere".into(),
        };
        refused(base.extended_by(other), "vocabulary 1024");
        // The same corpus and token set named through another path (a plan committed with
        // paths relative to the data folder, extended with absolute ones) is no difference.
        let data = tempfile::tempdir().unwrap();
        let (corpus, tokens) = (data.path().join("corpus"), data.path().join("tokens"));
        std::fs::create_dir(&corpus).unwrap();
        std::fs::create_dir(&tokens).unwrap();
        let (alias, tokens_alias) = (data.path().join("alias"), data.path().join("tokens-alias"));
        std::os::unix::fs::symlink(&corpus, &alias).unwrap();
        std::os::unix::fs::symlink(&tokens, &tokens_alias).unwrap();
        let named = |corpus: &Path, tokens: &Path| {
            let mut p = small_plan();
            p.corpus = corpus.into();
            p.vocabularies[1].source = VocabSource::TokenSet { dir: tokens.into() };
            p
        };
        let extended = named(&alias, &tokens_alias).extended_by(named(&corpus, &tokens));
        assert_eq!(
            extended.unwrap().corpus,
            alias,
            "the base plan's paths are kept"
        );
        let repeat = |ids: &[&str], seeds: &[u64]| {
            let ids: Vec<String> = ids.iter().map(|s| s.to_string()).collect();
            plan.clone().add_repeats(&ids, seeds).map(|()| plan.clone())
        };
        refused(repeat(&["c9e99-x-v1"], &[1]), "no such point");
        refused(repeat(&["c1e12-cpu-50K-v256"], &[0]), "own seed");
        refused(repeat(&["c1e12-cpu-50K-v256-s1"], &[3]), "itself a repeat");
        refused(repeat(&["c1e12-cpu-50K-v256"], &[]), "go together");

        let dir = tempfile::tempdir().unwrap();
        adopt_plan(&base, dir.path()).unwrap();
        adopt_plan(&plan, dir.path()).unwrap();
        assert_eq!(read_adopted_plan(dir.path()).unwrap(), plan);
        // The base plan may still run there (its points are the extension's first ones); the
        // folder keeps the extension.
        adopt_plan(&base, dir.path()).unwrap();
        assert_eq!(read_adopted_plan(dir.path()).unwrap(), plan);
        let mut other = base.clone();
        other.train.checkpoint_every += 1;
        let e = adopt_plan(&other, dir.path()).unwrap_err();
        assert!(e.to_string().contains("different plan"), "{e}");
    }

    #[test]
    fn run_ids_name_budget_model_and_vocabulary() {
        assert_eq!(run_id(1e12, "cpu-50K", 256), "c1e12-cpu-50K-v256");
        assert_eq!(run_id(3e12, "cpu-800K", 1024), "c3e12-cpu-800K-v1024");
        assert_eq!(run_id(2.5e11, "cpu-3M", 4096), "c2.5e11-cpu-3M-v4096");
    }
}
