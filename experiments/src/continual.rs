//! Continual (lifelong) training over scenario datasets (`../shared/docs/continual.md`):
//! the datasets D_1..D_n of `motionscale scenarios` arrive in a fixed order; after each step
//! the model animates the test captions of every dataset and the evaluator scores them, which
//! fills the matrices f (FID), r (top-1 R-precision), d (diversity), mm (multimodality) and
//! wf (emotion weighted F1), indexed [step][dataset position in the order]; AF/AR/AD/AMM/AWF
//! average the last row and FR = mean over j < N of (max_{k ∈ [j, N−1]} r[k][j] − r[N][j]).
//!
//! Methods (LoRA experts on a frozen trained backbone, `lm::lora`): `seq-lora` (one adapter
//! fine-tuned through the sequence), `replay` (the same, with a seeded buffer of each earlier
//! dataset's train clips added to every step), `o-lora` (a new adapter per dataset on the
//! model with the earlier ones merged in, its `lora_A` subspaces kept orthogonal to theirs)
//! `lwf-lora` (sequential LoRA distilled towards the previous step's model on the new data),
//! `es-moe` (a new expert per dataset mixed per caption by a gate with emotion decoupling,
//! `lm::es_moe`; its ablations switch off CGED, the mixture or the emotion loss) and `mtl`
//! (one adapter on all datasets at once: the joint reference, one row).
//!
//! ```text
//! OUT/config.json                        the run (a different one is refused)
//! OUT/order-<o>/order.json               the datasets in this order
//! OUT/order-<o>/step-<k>/lists/          {train,val,test}.txt the step trained on
//! OUT/order-<o>/step-<k>/train/          the `motionscale train` folder (resumable)
//! OUT/order-<o>/step-<k>/gen-<dataset>/  generated motions (HumanML3D layout; removed once
//!                                        scored unless `keep_motions`)
//! OUT/order-<o>/step-<k>/eval-<dataset>.json   `eval` report
//! OUT/order-<o>/{fid,r_precision}.{svg,png}     the matrices as heat maps (the paper's Fig. 5)
//! OUT/summary.json, OUT/summary.csv      matrices and summary metrics per order, and their mean
//! ```
//!
//! Every file is written atomically and reused when present, so a killed run resumes.

use crate::backbone::BackboneChoice;
use crate::error::SweepError;
use crate::plan::lm_targets;
use crate::seeds;
use evaluator::model::TrainedEvaluator;
use evaluator::score::{
    corpus_split, evaluate_motions, hml3d_folder, EvalOptions, EvalReport, MotionSet,
};
use evaluator::train::LabelledClip;
use ingest::corpus::split::{read_ids, SplitAssignment, SPLITS};
use ingest::scenarios::ScenarioDatasets;
use lm::caption_set::{generate_caption_set, CaptionSetOptions};
use lm::es_moe::EsMoeConfig;
use lm::generate::Sampling;
use lm::lora::LoraConfig;
use lm::prefix_lm::Compute;
use lm::train::{load_lm, load_model, run_tokenizer, train, ModelShape, RunConfig, TrainConfig};
use motionscale_core::files::{check_same_run, read_json, write_json};
use motionscale_core::rng::SplitMix64;
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use tokenizer::model::MotionTokenizer;

/// A continual-learning method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// One LoRA adapter fine-tuned on each dataset in turn.
    SeqLora,
    /// Sequential LoRA with a buffer of earlier datasets' clips.
    Replay,
    /// One LoRA adapter on every dataset at once (the joint reference).
    Mtl,
    /// A new adapter per dataset, its `lora_A` subspaces kept orthogonal to the earlier
    /// adapters' (which stay merged in, frozen).
    OLora,
    /// Sequential LoRA distilled towards the previous step's model on the new data (LwF).
    LwfLora,
    /// ES-MoE: a new LoRA expert per dataset, mixed per caption by an emotion-aware gate.
    EsMoe,
}

impl Method {
    /// Every method.
    pub const ALL: [Method; 6] = [
        Method::SeqLora,
        Method::Replay,
        Method::Mtl,
        Method::OLora,
        Method::LwfLora,
        Method::EsMoe,
    ];

    /// Its CLI (and serialised) name.
    pub fn name(self) -> &'static str {
        match self {
            Method::SeqLora => "seq-lora",
            Method::Replay => "replay",
            Method::Mtl => "mtl",
            Method::OLora => "o-lora",
            Method::LwfLora => "lwf-lora",
            Method::EsMoe => "es-moe",
        }
    }

    /// Parse a CLI name (`seq-lora`, `replay`, `mtl`, `o-lora`, `lwf-lora`, `es-moe`).
    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }
}

/// Everything a continual run depends on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContinualConfig {
    /// Scenario datasets folder (`motionscale scenarios --out`).
    pub scenarios: PathBuf,
    /// Token set of the whole corpus (`motionscale tokenize`).
    pub tokens: PathBuf,
    /// Trained backbone run (frozen).
    pub base: PathBuf,
    /// Evaluator folder.
    pub evaluator: PathBuf,
    /// The method.
    pub method: Method,
    /// Dataset orders (order 0 is the listed one, the others seeded shuffles).
    pub orders: usize,
    /// Seed of replay buffers, training and evaluation (the orders do not depend on it).
    pub seed: u64,
    /// Motion tokens trained on per step.
    pub tokens_budget: u64,
    /// Instead: epochs of each step's train clips (their loss positions) trained per step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expert_epochs: Option<f64>,
    /// Clips per batch.
    pub batch_size: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Adapter rank and scale.
    pub lora: LoraConfig,
    /// Share of each earlier dataset's train clips replayed (`replay`).
    pub replay_fraction: f64,
    /// Weight of the orthogonality loss (`o-lora`).
    #[serde(default)]
    pub orthogonality: f64,
    /// Weight of the distillation loss (`lwf-lora`).
    #[serde(default)]
    pub distillation: f64,
    /// Experts, gate and ablation switches (`es-moe`; its `lora` is the run's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub es_moe: Option<EsMoeConfig>,
    /// Evaluation repeats.
    pub repeats: usize,
    /// R-precision pool size.
    pub pool: usize,
    /// Texts with 10 samples each for multimodality, per dataset.
    pub mm_texts: usize,
    /// Score only the datasets learned so far after each step (the lower triangle that AF,
    /// AR, FR and plasticity read); the others' cells stay empty.
    #[serde(default)]
    pub eval_learned_only: bool,
    /// Split of every dataset that is evaluated.
    pub eval_split: String,
    /// Keep the generated motions after scoring (about 200 MB per step and dataset at
    /// Bandai + synth scale; by default only the eval JSON stays).
    #[serde(default)]
    pub keep_motions: bool,
    /// Output folder.
    pub out: PathBuf,
    /// The backbone sized by a law (`--fits --budget`): the fit, C and the model chosen
    /// (`base` is its run); absent for a backbone given by hand.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub backbone: Option<BackboneChoice>,
}

impl ContinualConfig {
    /// The method with its ablation, as tables name it (`es-moe w/o CGED`…).
    pub fn label(&self) -> String {
        let Some(moe) = self.es_moe.filter(|_| self.method == Method::EsMoe) else {
            return self.method.name().to_string();
        };
        let off: Vec<&str> = [
            (!moe.mixture, "w/o MoE (single LoRA)"),
            (!moe.cged, "w/o CGED"),
            (moe.cged && moe.emotion_weight == 0.0, "w/o L_emo"),
        ]
        .into_iter()
        .filter_map(|(on, name)| on.then_some(name))
        .collect();
        match off.as_slice() {
            [] => "es-moe".to_string(),
            _ => format!("es-moe {}", off.join(", ")),
        }
    }
}

/// Metric matrices and summary of one order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OrderResult {
    /// Dataset names in the order learned.
    pub datasets: Vec<String>,
    /// FID [step][position] (`None`: not scored, a dataset not yet learned with
    /// `eval_learned_only`).
    pub f: Vec<Vec<Option<f64>>>,
    /// Top-1 R-precision [step][position] (`None` as for `f`).
    pub r: Vec<Vec<Option<f64>>>,
    /// Diversity (`None` with too few motions).
    pub d: Vec<Vec<Option<f64>>>,
    /// Multimodality (`None` without multi-sample texts).
    pub mm: Vec<Vec<Option<f64>>>,
    /// Emotion weighted F1 (`None` without emotion labels).
    pub wf: Vec<Vec<Option<f64>>>,
    /// ES-MoE: after each step, the gate's mean weight on every expert for the test captions
    /// of the dataset that step learned (the last is the new expert's); `None` for the other
    /// methods. Each step's `train/eval.json` holds the same (`expert_weights`).
    #[serde(default)]
    pub gate: Vec<Option<Vec<f64>>>,
    /// AF, AR, AD, AMM, AWF and FR.
    pub summary: Summary,
}

/// The paper's summary metrics after the last step.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Summary {
    /// Mean final FID.
    pub af: f64,
    /// Mean final top-1 R-precision.
    pub ar: f64,
    /// Mean final diversity.
    pub ad: Option<f64>,
    /// Mean final multimodality.
    pub amm: Option<f64>,
    /// Mean final emotion weighted F1.
    pub awf: Option<f64>,
    /// Forgetting rate of R-precision (`None` with one step).
    pub fr: Option<f64>,
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n.max(1) as f64
}

fn mean_known(row: &[Option<f64>]) -> Option<f64> {
    let known: Vec<f64> = row.iter().flatten().copied().collect();
    (!known.is_empty()).then(|| mean(known.into_iter()))
}

impl Summary {
    /// The summary of matrices whose last row is after the last step; FR over the rows
    /// (row k is after learning position k, when there is one row per position).
    /// Every cell these read is a learned dataset's, so it is scored (an unscored one, `None`,
    /// would make the metric NaN).
    pub fn of(
        f: &[Vec<Option<f64>>],
        r: &[Vec<Option<f64>>],
        d: &[Vec<Option<f64>>],
        mm: &[Vec<Option<f64>>],
        wf: &[Vec<Option<f64>>],
    ) -> Self {
        let scored = |v: &Option<f64>| v.unwrap_or(f64::NAN);
        let last = r.len() - 1;
        let n = r[last].len();
        let fr = (r.len() == n && n > 1).then(|| {
            mean((0..n - 1).map(|j| {
                let best = (j..n - 1)
                    .map(|k| scored(&r[k][j]))
                    .fold(f64::MIN, f64::max);
                best - scored(&r[last][j])
            }))
        });
        Self {
            af: mean(f[last].iter().map(scored)),
            ar: mean(r[last].iter().map(scored)),
            ad: mean_known(&d[last]),
            amm: mean_known(&mm[last]),
            awf: mean_known(&wf[last]),
            fr,
        }
    }

    /// The mean of several summaries (orders); an optional metric is kept when all have it.
    pub fn mean_of(all: &[Summary]) -> Self {
        let opt = |f: fn(&Summary) -> Option<f64>| {
            let v: Option<Vec<f64>> = all.iter().map(f).collect();
            v.map(|v| mean(v.into_iter()))
        };
        Self {
            af: mean(all.iter().map(|s| s.af)),
            ar: mean(all.iter().map(|s| s.ar)),
            ad: opt(|s| s.ad),
            amm: opt(|s| s.amm),
            awf: opt(|s| s.awf),
            fr: opt(|s| s.fr),
        }
    }
}

/// `OUT/summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContinualReport {
    /// The run.
    pub config: ContinualConfig,
    /// Content id of the evaluator that scored every cell (`evaluator train` prints it).
    #[serde(default)]
    pub evaluator_id: String,
    /// Each order's matrices and summary.
    pub orders: Vec<OrderResult>,
    /// The summaries averaged over orders.
    pub mean: Summary,
}

/// The dataset positions of order `o`: order 0 as listed, the others shuffles by a fixed
/// seed. The orders are the same whatever the run's seed, so runs that differ only in
/// `seed` measure training and sampling noise, not a change of orders.
pub fn order(n: usize, o: usize) -> Vec<usize> {
    let mut positions: Vec<usize> = (0..n).collect();
    if o > 0 {
        SplitMix64::stream(0, o as u64).shuffle(&mut positions);
    }
    positions
}

/// Write `{train,val,test}.txt` into `dir`.
fn write_lists(dir: &Path, lists: &HashMap<&str, Vec<String>>) -> Result<(), SweepError> {
    for split in SPLITS {
        let path = dir.join(format!("{split}.txt"));
        let text: String = lists
            .get(split)
            .map(|ids| ids.iter().map(|id| format!("{id}\n")).collect())
            .unwrap_or_default();
        motionscale_core::write_atomic(&path, text.as_bytes())
            .map_err(|e| SweepError::io(&path, e))?;
    }
    Ok(())
}

/// The clip lists of a dataset folder.
fn dataset_lists(dir: &Path) -> Result<HashMap<&'static str, Vec<String>>, SweepError> {
    SPLITS
        .iter()
        .map(|&s| {
            let path = dir.join(format!("{s}.txt"));
            Ok((
                s,
                read_ids(&path)
                    .map_err(|e| SweepError::invalid(&path, e))?
                    .unwrap_or_default(),
            ))
        })
        .collect()
}

/// Refuse a backbone that trained on a clip some dataset holds out for validation or test:
/// its scores there would measure memory, not continual learning.
fn check_backbone_held_out(
    base: &RunConfig,
    scenarios: &Path,
    names: &[String],
) -> Result<(), SweepError> {
    let assignment = SplitAssignment::from_dir(base.train.splits.as_deref())
        .map_err(|e| SweepError::Argument(e.to_string()))?;
    let tokens = &base.train.tokens;
    let set = tokenizer::TokenSet::open(tokens).map_err(|e| SweepError::invalid(tokens, e))?;
    let trained: HashSet<&str> = set
        .clips
        .iter()
        .filter(|c| assignment.split_of(&c.motion_id, &c.split) == Some("train"))
        .map(|c| c.motion_id.as_str())
        .collect();
    for name in names {
        for (split, ids) in dataset_lists(&scenarios.join(name))? {
            let seen: Vec<&String> = ids
                .iter()
                .filter(|id| split != "train" && trained.contains(id.as_str()))
                .collect();
            if let Some(first) = seen.first() {
                return Err(SweepError::invalid(
                    &scenarios.join(name).join(format!("{split}.txt")),
                    format!(
                        "{} of its {} clips (e.g. {first}) are train clips of the backbone's \
                         token set {}; a held-out clip must be one the backbone never trained \
                         on (`motionscale scenarios` keeps each clip's corpus split)",
                        seen.len(),
                        ids.len(),
                        tokens.display()
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// What every step of a continual run reads: the datasets, the evaluator, the base run's
/// corpus and tokenizer, each dataset's reference motions and the corpus clips' labels.
struct Setup {
    names: Vec<String>,
    evaluator: TrainedEvaluator,
    corpus: PathBuf,
    tokenizer: MotionTokenizer,
    references: HashMap<String, MotionSet>,
    labels: HashMap<String, LabelledClip>,
    /// Where every network of the run trains and runs.
    device: candle_core::Device,
    /// Loss positions per epoch of each clip of the token set (with `expert_epochs`).
    positions: HashMap<String, u64>,
}

/// Loss positions of one epoch of the train list in `lists_dir`.
fn step_positions(setup: &Setup, lists_dir: &Path) -> Result<u64, SweepError> {
    let path = lists_dir.join("train.txt");
    let ids = read_ids(&path)
        .map_err(|e| SweepError::invalid(&path, e))?
        .unwrap_or_default();
    Ok(ids.iter().filter_map(|id| setup.positions.get(id)).sum())
}

/// Run (or resume) `config`, every network on `device`; `log` receives one line per finished
/// piece of work.
pub fn run_continual(
    config: &ContinualConfig,
    device: &candle_core::Device,
    mut log: impl FnMut(&str),
) -> Result<ContinualReport, SweepError> {
    std::fs::create_dir_all(&config.out).map_err(|e| SweepError::io(&config.out, e))?;
    let config_path = config.out.join("config.json");
    check_same_run(&config_path, "a continual run", |old: ContinualConfig| {
        old == *config
    })?;
    write_json(&config_path, config)?;
    let setup = prepare(config, device)?;
    let mut results = Vec::new();
    for o in 0..config.orders {
        results.push(run_order(config, &setup, o, &mut log)?);
    }
    let report = ContinualReport {
        config: config.clone(),
        evaluator_id: setup.evaluator.id.clone(),
        mean: Summary::mean_of(&results.iter().map(|r| r.summary).collect::<Vec<_>>()),
        orders: results,
    };
    write_json(&config.out.join("summary.json"), &report)?;
    let csv_path = config.out.join("summary.csv");
    motionscale_core::write_atomic(&csv_path, summary_csv(&report).as_bytes())
        .map_err(|e| SweepError::io(&csv_path, e))?;
    Ok(report)
}

/// The evaluation options of `dataset`'s split.
fn eval_options(config: &ContinualConfig, dataset: &str) -> EvalOptions {
    EvalOptions {
        split: config.eval_split.clone(),
        repeats: config.repeats,
        seed: config.seed,
        splits: Some(config.scenarios.join(dataset)),
        pool: config.pool,
        ..EvalOptions::default()
    }
}

/// Load what every step reads, refusing a backbone that trained on a held-out clip.
fn prepare(config: &ContinualConfig, device: &candle_core::Device) -> Result<Setup, SweepError> {
    let sets: ScenarioDatasets = read_json(&config.scenarios.join("datasets.json"))?;
    let names: Vec<String> = sets.datasets.iter().map(|d| d.name.clone()).collect();
    let evaluator = TrainedEvaluator::load(&config.evaluator, device)?;
    let (_, base_run) = load_model(&config.base, device)?;
    check_backbone_held_out(&base_run, &config.scenarios, &names)?;
    let corpus = base_run.corpus.clone();
    let tokenizer = run_tokenizer(&base_run, None, device)?;
    let mut references = HashMap::new();
    for name in &names {
        let reference = corpus_split(&corpus, &eval_options(config, name))?;
        references.insert(name.clone(), reference);
    }
    let labels = evaluator::train::corpus_clips(&corpus, |_| true)?
        .into_iter()
        .map(|c| (c.motion_id.clone(), c))
        .collect();
    let positions = match config.expert_epochs {
        Some(_) => {
            let set = tokenizer::TokenSet::open(&config.tokens)
                .map_err(|e| SweepError::invalid(&config.tokens, e))?;
            let max = lm::run_config::HYPERPARAMS.max_motion_tokens;
            set.clips
                .iter()
                .map(|c| (c.motion_id.clone(), lm_targets(c.tokens.len(), max)))
                .collect()
        }
        None => HashMap::new(),
    };
    Ok(Setup {
        names,
        evaluator,
        corpus,
        tokenizer,
        references,
        labels,
        device: device.clone(),
        positions,
    })
}

/// Order `o`: every step trained and scored on every dataset, as matrices and heat maps.
fn run_order(
    config: &ContinualConfig,
    setup: &Setup,
    o: usize,
    log: &mut impl FnMut(&str),
) -> Result<OrderResult, SweepError> {
    let positions = order(setup.names.len(), o);
    let ordered: Vec<String> = positions.iter().map(|&p| setup.names[p].clone()).collect();
    let order_dir = config.out.join(format!("order-{o}"));
    std::fs::create_dir_all(&order_dir).map_err(|e| SweepError::io(&order_dir, e))?;
    write_json(&order_dir.join("order.json"), &ordered)?;
    let steps = if config.method == Method::Mtl {
        1
    } else {
        ordered.len()
    };
    let mut rows: Vec<Vec<Option<EvalReport>>> = Vec::new();
    let mut gate = Vec::new();
    let mut previous: Option<PathBuf> = None;
    let mut adapters: Vec<PathBuf> = Vec::new();
    for k in 0..steps {
        let step_dir = order_dir.join(format!("step-{}", k + 1));
        let lists_dir = step_dir.join("lists");
        let learned = write_step_lists(config, &ordered, (o, k), &lists_dir)?;
        let train_dir = step_dir.join("train");
        let shape = step_shape(config, &ordered, k, previous.as_deref(), &adapters)?;
        let budget = match config.expert_epochs {
            Some(epochs) => (epochs * step_positions(setup, &lists_dir)? as f64).round() as u64,
            None => config.tokens_budget,
        };
        let mut train_config = TrainConfig::new(&config.tokens, shape, budget, &train_dir);
        train_config.splits = Some(lists_dir.clone());
        train_config.hyper.batch_size = config.batch_size;
        train_config.hyper.lr = config.lr;
        train_config.hyper.seed = config.seed;
        let report = train(&train_config, &setup.device, &mut |_| {})?;
        let weights = report
            .eval
            .expert_weights
            .as_ref()
            .map_or_else(String::new, |w| {
                let w: Vec<String> = w.iter().map(|v| format!("{v:.2}")).collect();
                format!(", gate weights on its test captions [{}]", w.join(", "))
            });
        log(&format!(
            "order {o} step {}: trained on {} (test CE {:.3}{weights})",
            k + 1,
            learned.join("+"),
            report.eval.test.cross_entropy
        ));
        gate.push(report.eval.expert_weights.clone());
        previous = Some(train_dir.join(lm::lora::ADAPTER_FILE));
        adapters.extend(previous.clone());
        let scored = match (config.eval_learned_only, config.method) {
            (true, m) if m != Method::Mtl => k + 1,
            _ => ordered.len(),
        };
        let step = (o, k, step_dir.as_path());
        rows.push(score_step(
            config,
            setup,
            &ordered[..scored],
            step,
            &train_dir,
            log,
        )?);
        rows.last_mut().unwrap().resize(ordered.len(), None);
    }
    let result = order_result(ordered, &rows, gate);
    write_heatmaps(&order_dir, o, &result)?;
    Ok(result)
}

/// Write step `k`'s clip lists (of order `o`) into `lists_dir`: the datasets it learns (all of
/// them for MTL) plus, for replay, a share of every earlier dataset's train clips. Returns the
/// datasets it learns.
fn write_step_lists(
    config: &ContinualConfig,
    ordered: &[String],
    (o, k): (usize, usize),
    lists_dir: &Path,
) -> Result<Vec<String>, SweepError> {
    std::fs::create_dir_all(lists_dir).map_err(|e| SweepError::io(lists_dir, e))?;
    let mut lists = HashMap::new();
    let learned: Vec<String> = match config.method {
        Method::Mtl => ordered.to_vec(),
        _ => vec![ordered[k].clone()],
    };
    for name in &learned {
        for (split, ids) in dataset_lists(&config.scenarios.join(name))? {
            lists.entry(split).or_insert_with(Vec::new).extend(ids);
        }
    }
    if config.method == Method::Replay {
        for (i, earlier) in ordered[..k].iter().enumerate() {
            let mut train = dataset_lists(&config.scenarios.join(earlier))?
                .remove("train")
                .unwrap_or_default();
            let mut rng = SplitMix64::stream(config.seed ^ 0xbeef, (o * 1000 + k * 10 + i) as u64);
            rng.shuffle(&mut train);
            let keep =
                ((train.len() as f64 * config.replay_fraction).ceil() as usize).min(train.len());
            lists
                .entry("train")
                .or_default()
                .extend(train.into_iter().take(keep));
        }
    }
    write_lists(lists_dir, &lists)?;
    Ok(learned)
}

/// The model step `k` trains: a new ES-MoE expert; for O-LoRA a new adapter on the model with
/// every earlier one merged in, kept orthogonal to them; otherwise one adapter continued from
/// the `previous` step's (distilled towards that step's model for LwF).
fn step_shape(
    config: &ContinualConfig,
    ordered: &[String],
    k: usize,
    previous: Option<&Path>,
    adapters: &[PathBuf],
) -> Result<ModelShape, SweepError> {
    let previous_run = previous.and_then(Path::parent).map(Path::to_path_buf);
    Ok(match config.method {
        Method::EsMoe => {
            let moe = EsMoeConfig {
                lora: config.lora,
                ..config.es_moe.unwrap_or_default()
            };
            if moe.mixture && ordered.len() > moe.max_experts {
                return Err(SweepError::Argument(format!(
                    "{} datasets need {} ES-MoE experts; the gate has keys for {}",
                    ordered.len(),
                    ordered.len(),
                    moe.max_experts
                )));
            }
            ModelShape::EsMoe {
                base: config.base.clone(),
                previous: previous_run,
                expert: if moe.mixture {
                    ordered[k].clone()
                } else {
                    "shared".to_string()
                },
                moe,
            }
        }
        Method::OLora => ModelShape::Lora {
            base: previous_run.unwrap_or_else(|| config.base.clone()),
            lora: config.lora,
            expert: format!("{}-{}", config.method.name(), k + 1),
            init: None,
            orthogonal_to: adapters.to_vec(),
            orthogonality: config.orthogonality,
            distill_from: None,
            distillation: 0.0,
        },
        _ => ModelShape::Lora {
            base: config.base.clone(),
            lora: config.lora,
            expert: config.method.name().to_string(),
            init: previous.map(Path::to_path_buf),
            orthogonal_to: Vec::new(),
            orthogonality: 0.0,
            distill_from: match config.method {
                Method::LwfLora => previous_run,
                _ => None,
            },
            distillation: match (config.method, previous) {
                (Method::LwfLora, Some(_)) => config.distillation,
                _ => 0.0,
            },
        },
    })
}

/// Score the model step `k` trained (in `train_dir`) on each dataset of `ordered` (the whole
/// order, or its learned head with `eval_learned_only`): its captions animated, then evaluated against the dataset's reference; finished datasets are
/// read back, so a re-run resumes.
fn score_step(
    config: &ContinualConfig,
    setup: &Setup,
    ordered: &[String],
    (o, k, step_dir): (usize, usize, &Path),
    train_dir: &Path,
    log: &mut impl FnMut(&str),
) -> Result<Vec<Option<EvalReport>>, SweepError> {
    let (model, run) = load_lm(train_dir, &setup.device, Compute::default())?;
    let mut row = Vec::new();
    for name in ordered {
        let eval_path = step_dir.join(format!("eval-{name}.json"));
        if let Ok(report) = read_json::<EvalReport>(&eval_path) {
            row.push(Some(report));
            continue;
        }
        let gen_dir = step_dir.join(format!("gen-{name}"));
        let options = CaptionSetOptions {
            corpus: setup.corpus.clone(),
            split: config.eval_split.clone(),
            splits: Some(config.scenarios.join(name)),
            mm_texts: config.mm_texts,
            mm_samples: 10,
            batch: 32,
            sampling: Sampling {
                seed: config.seed,
                min_tokens: 1,
                ..Sampling::default()
            },
        };
        generate_caption_set(
            model.as_ref(),
            &run,
            &setup.tokenizer,
            None,
            &options,
            &gen_dir,
            |_, _| {},
        )?;
        let set = hml3d_folder(&gen_dir, &eval_options(config, name), &setup.labels)?;
        let report = evaluate_motions(
            &setup.evaluator,
            &config.evaluator,
            &setup.references[name],
            &set,
            &eval_options(config, name),
            None,
        )?;
        write_json(&eval_path, &report)?;
        if !config.keep_motions {
            std::fs::remove_dir_all(&gen_dir).map_err(|e| SweepError::io(&gen_dir, e))?;
        }
        log(&format!(
            "order {o} step {}: {name} FID {:.4}, R-precision@1 {:.3}",
            k + 1,
            report.fid.mean,
            report.r_precision[0].mean
        ));
        row.push(Some(report));
    }
    Ok(row)
}

/// The FID and R-precision matrices of one order as heat maps (the paper's Figure 5):
/// `order-<o>/fid.{svg,png}` and `order-<o>/r_precision.{svg,png}`.
fn write_heatmaps(dir: &Path, o: usize, result: &OrderResult) -> Result<(), SweepError> {
    let short = |name: &String| {
        name.split_once('_')
            .map_or(name.clone(), |(_, s)| s.to_string())
    };
    let rows: Vec<String> = if result.f.len() == 1 {
        vec!["joint".into()]
    } else {
        result
            .datasets
            .iter()
            .map(|d| format!("after {}", short(d)))
            .collect()
    };
    for (stem, what, values) in [
        ("fid", "FID", &result.f),
        ("r_precision", "top-1 R-precision", &result.r),
    ] {
        let map = plot::Heatmap {
            title: format!("{what}, order {o} (rows: after step; columns: dataset)"),
            rows: rows.clone(),
            columns: result.datasets.iter().map(short).collect(),
            values: values
                .iter()
                .map(|row| row.iter().map(|v| v.unwrap_or(f64::NAN)).collect())
                .collect(),
        };
        let path = dir.join(stem);
        map.write(&path)
            .map_err(|e| SweepError::invalid(&path, e))?;
    }
    Ok(())
}

fn order_result(
    datasets: Vec<String>,
    rows: &[Vec<Option<EvalReport>>],
    gate: Vec<Option<Vec<f64>>>,
) -> OrderResult {
    let take = |f: &dyn Fn(&EvalReport) -> Option<f64>| -> Vec<Vec<Option<f64>>> {
        rows.iter()
            .map(|row| row.iter().map(|e| e.as_ref().and_then(f)).collect())
            .collect()
    };
    let f = take(&|e| Some(e.fid.mean));
    let r = take(&|e| Some(e.r_precision[0].mean));
    let d = take(&|e| e.diversity.as_ref().map(|i| i.mean));
    let mm = take(&|e| e.multimodality.as_ref().map(|i| i.mean));
    let wf = take(&|e| e.emotion_weighted_f1.as_ref().map(|i| i.mean));
    let summary = Summary::of(&f, &r, &d, &mm, &wf);
    OrderResult {
        datasets,
        f,
        r,
        d,
        mm,
        wf,
        gate,
        summary,
    }
}

fn cell(v: Option<f64>) -> String {
    v.map_or_else(String::new, |v| format!("{v}"))
}

/// `summary.csv`: one row per order and their mean.
pub fn summary_csv(report: &ContinualReport) -> String {
    let mut csv = String::from("order,AF,AR,AD,AMM,AWF,FR\n");
    let rows = report
        .orders
        .iter()
        .enumerate()
        .map(|(o, r)| (o.to_string(), r.summary))
        .chain([("mean".to_string(), report.mean)]);
    for (name, s) in rows {
        csv.push_str(&format!(
            "{name},{},{},{},{},{},{}\n",
            s.af,
            s.ar,
            cell(s.ad),
            cell(s.amm),
            cell(s.awf),
            cell(s.fr)
        ));
    }
    csv
}

/// A table shaped like the paper's Table 2: one row per method, the summary metrics averaged
/// over its orders. Runs that differ only in their seed share a row: the mean over seeds and,
/// with two or more, the 95% Student-t interval over them. Runs scored by different
/// evaluators are refused unless `mixed_evaluators` (their numbers are not comparable).
pub fn compare_table(runs: &[PathBuf], mixed_evaluators: bool) -> Result<String, SweepError> {
    let scored = seeds::read_runs(runs, |r: &ContinualReport| &r.evaluator_id)?;
    let seedless = |r: &ContinualReport| ContinualConfig {
        seed: 0,
        out: PathBuf::new(),
        ..r.config.clone()
    };
    let mut out = String::from(
        "| run | method | orders | seeds | AF ↓ | AR ↑ | AD | AMM | AWF ↑ | FR ↓ | new expert's weight | evaluator |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for members in seeds::group(scored, seedless, mixed_evaluators)? {
        let metric = |f: fn(&Summary) -> Option<f64>, digits| {
            seeds::cell(members.iter().map(|r| f(&r.report.mean)).collect(), digits)
        };
        let first = &members[0];
        let routed = members
            .iter()
            .map(|r| new_expert_weight(&r.report))
            .collect();
        out.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            seeds::run_label(&members),
            first.report.config.label(),
            first.report.orders.len(),
            members.len(),
            metric(|s| Some(s.af), 4),
            metric(|s| Some(s.ar), 3),
            metric(|s| s.ad, 3),
            metric(|s| s.amm, 3),
            metric(|s| s.awf, 3),
            metric(|s| s.fr, 3),
            seeds::cell(routed, 3),
            seeds::evaluator_label(&first.evaluator_id)
        ));
    }
    Ok(out)
}

/// ES-MoE: the gate's mean weight on the newest expert for the test captions of the dataset
/// it just learned, over every order's steps after the first that added an expert (`None`
/// for other methods and for the single-LoRA ablation, whose one expert is shared).
fn new_expert_weight(report: &ContinualReport) -> Option<f64> {
    let newest: Vec<f64> = report
        .orders
        .iter()
        .flat_map(|o| o.gate.iter().enumerate().skip(1))
        .filter_map(|(k, w)| w.as_ref().filter(|w| w.len() == k + 1)?.last().copied())
        .collect();
    (!newest.is_empty()).then(|| newest.iter().sum::<f64>() / newest.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn forgetting_rate_and_averages_match_a_hand_case() {
        // Three tasks. r[k][j]: after step k (0-based rows), task j.
        let r = vec![
            vec![0.5, 0.1, 0.1],
            vec![0.4, 0.6, 0.1],
            vec![0.3, 0.2, 0.7],
        ];
        let f = vec![vec![1.0; 3], vec![1.0; 3], vec![0.1, 0.2, 0.3]];
        let some = |m: &[Vec<f64>]| -> Vec<Vec<Option<f64>>> {
            m.iter()
                .map(|row| row.iter().map(|&v| Some(v)).collect())
                .collect()
        };
        let (f, r) = (some(&f), some(&r));
        let none = vec![vec![None; 3]; 3];
        let s = Summary::of(&f, &r, &none, &none, &none);
        // Scoring only the learned datasets (the cells above the diagonal empty) changes none.
        let learned = |m: &[Vec<Option<f64>>]| -> Vec<Vec<Option<f64>>> {
            let cell = |(k, row): (usize, &Vec<Option<f64>>)| {
                row.iter()
                    .enumerate()
                    .map(|(j, v)| v.filter(|_| j <= k))
                    .collect()
            };
            m.iter().enumerate().map(cell).collect()
        };
        assert_eq!(
            Summary::of(&learned(&f), &learned(&r), &none, &none, &none),
            s
        );
        // Task 0: best of rows 0..=1 is 0.5, final 0.3 → 0.2; task 1: best of row 1 is 0.6,
        // final 0.2 → 0.4. FR = 0.3.
        assert!((s.fr.unwrap() - 0.3).abs() < 1e-12);
        assert!((s.ar - 0.4).abs() < 1e-12);
        assert!((s.af - 0.2).abs() < 1e-12);
        assert_eq!(s.ad, None);
        // One row (MTL): no forgetting rate.
        let one = Summary::of(&f[2..], &r[2..], &none[2..], &none[2..], &none[2..]);
        assert_eq!(one.fr, None);
        let m = Summary::mean_of(&[s, one]);
        assert!((m.ar - 0.4).abs() < 1e-12);
        assert_eq!(m.fr, None, "kept only when every order has it");
    }

    #[test]
    fn orders_are_permutations_and_order_zero_is_as_listed() {
        assert_eq!(order(5, 0), vec![0, 1, 2, 3, 4]);
        let mut o = order(5, 1);
        assert_ne!(o, vec![0, 1, 2, 3, 4]);
        o.sort();
        assert_eq!(o, vec![0, 1, 2, 3, 4]);
        assert_ne!(order(5, 1), order(5, 2));
    }

    #[test]
    fn method_names_round_trip() {
        for (name, m) in [
            ("seq-lora", Method::SeqLora),
            ("replay", Method::Replay),
            ("mtl", Method::Mtl),
            ("o-lora", Method::OLora),
            ("lwf-lora", Method::LwfLora),
            ("es-moe", Method::EsMoe),
        ] {
            assert_eq!(Method::parse(name), Some(m));
            assert_eq!(
                serde_json::to_value(m).unwrap(),
                name,
                "serialised as named"
            );
        }
        assert_eq!(Method::parse("es-moe-x"), None);
    }
}
