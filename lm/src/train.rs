//! Training of the prefix LM: AdamW (`nn::optim`) with linear warm-up and cosine decay
//! sized to the token budget D, global gradient-norm clipping, seeded batches, periodic
//! evaluation on the test split, and atomic checkpoints a re-run resumes from.
//!
//! ```text
//! OUT/config.json           format, the train config, the resolved model config, text encoder,
//!                           tokenizer, schedule (total/warm-up steps), accounting
//! OUT/model.safetensors     weights (PyTorch key names, see prefix_lm)
//! OUT/state.json            step, tokens seen, executed FLOPs, data position (written last:
//!                           it commits the checkpoint)
//! OUT/resume/<step>/        that step's model.safetensors and optimizer.safetensors (AdamW)
//! OUT/eval.json             the latest evaluation (test, validation, and the validation-selected
//!                           evaluation so far); OUT/evals.jsonl every evaluation
//! ```
//!
//! A run is a pure function of its config: batch k is fixed by the seed, every kernel reduces
//! in a fixed order, so killing a run and re-running the same command ends with the same
//! weights as an uninterrupted run.

use crate::accounting::{self, Accounting, SequenceShape};
use crate::es_moe::train::{EsMoeTrainer, MoeExample};
use crate::es_moe::{EsMoe, EsMoeConfig};
use crate::eval_record::{BestEval, EvalRecord};
use crate::lm_data::{Limits, LmData};
use crate::lora::{adapter_a_matrices, base_weights, LoraAdapter, LoraConfig, ADAPTER_FILE};
use crate::prefix_lm::{init_model, Compute, LmBatch, PrefixLm, PrefixLmConfig};
use crate::selection;
use crate::test_loss::evaluate;
use crate::MotionLm;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use ingest::corpus::Origin;
use motionscale_core::files::{append_json_line, check_same_run, read_json, write_json};
use motionscale_core::rng::SplitMix64;
use motionscale_core::write_atomic;
use nn::checkpoint::{save_safetensors, ResumeFiles};
use nn::ModelError;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The weights file of a run folder and of each resume step.
const MODEL_FILE: &str = "model.safetensors";
/// The optimiser state inside a resume step.
const OPTIMIZER_FILE: &str = "optimizer.safetensors";
use nn::optim::{AdamW, AdamWConfig, LrSchedule};
use std::time::Instant;

/// Stream of the generator that masks older ES-MoE experts (per step).
const MASK_STREAM: u64 = 0x6d61_736b;

/// Format tag of `config.json`.
pub const FORMAT: &str = "motionscale-prefix-lm-v1";

/// The model shape to train: a named preset or explicit sizes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelShape {
    /// A preset of [`crate::prefix_lm::PRESETS`].
    Preset(String),
    /// Explicit width, depth and heads (SwiGLU width by the reference rule unless given).
    Custom {
        /// Width.
        d_model: usize,
        /// Blocks.
        n_layers: usize,
        /// Heads.
        n_heads: usize,
        /// SwiGLU width (default round(8d/3)).
        ffn_hidden: Option<usize>,
    },
    /// A LoRA adapter on every attention and FFN projection of a trained model, whose own
    /// weights stay frozen (the run's `model.safetensors` is the merged model, and
    /// `adapter.safetensors` the adapter alone).
    Lora {
        /// The trained run folder.
        base: PathBuf,
        /// Rank and scale.
        lora: LoraConfig,
        /// Expert name (the adapter's key prefix).
        expert: String,
        /// Adapter file to start from (this expert's A and B, e.g. the previous scenario's
        /// `adapter.safetensors` for sequential fine-tuning) instead of a new adapter.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        init: Option<PathBuf>,
        /// Adapter files whose `lora_A` subspaces this adapter is kept orthogonal to (O-LoRA).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        orthogonal_to: Vec<PathBuf>,
        /// Weight λ of the orthogonality loss.
        #[serde(default)]
        orthogonality: f64,
        /// A trained run whose outputs the model is distilled towards on the new data
        /// (LwF), with weight `distillation`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        distill_from: Option<PathBuf>,
        /// Weight of the distillation loss (temperature [`DISTILLATION_TEMPERATURE`]).
        #[serde(default)]
        distillation: f64,
    },
    /// An ES-MoE step ([`crate::es_moe`]): a new LoRA expert (or, without the mixture, the
    /// shared one continued) on a trained model's frozen weights, mixed with the earlier
    /// experts of `previous` by the gate, which trains too. The run folder holds every expert
    /// (`adapter.safetensors`) and the gate, not a single model.
    EsMoe {
        /// The trained run folder of the frozen base.
        base: PathBuf,
        /// The previous step's ES-MoE run (its experts, gate and dictionary), if any.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        previous: Option<PathBuf>,
        /// Name of the expert this step trains.
        expert: String,
        /// Experts, gate and ablation switches.
        moe: EsMoeConfig,
    },
}

/// Softmax temperature of the LwF distillation loss (Hinton et al.'s usual 2).
pub const DISTILLATION_TEMPERATURE: f32 = 2.0;

impl ModelShape {
    /// The model configuration for `codebook_size` codes and `text_dim`-wide text.
    pub fn resolve(
        &self,
        codebook_size: usize,
        text_dim: usize,
    ) -> Result<PrefixLmConfig, ModelError> {
        let config = match self {
            Self::Lora { base, .. } | Self::EsMoe { base, .. } => {
                let run: RunConfig = read_json(&base.join("config.json"))?;
                if (run.model.codebook_size, run.model.text_dim) != (codebook_size, text_dim) {
                    return Err(ModelError::Argument(format!(
                        "{}: the base model has {} codes and {}-d text, the data {codebook_size} and {text_dim}",
                        base.display(),
                        run.model.codebook_size,
                        run.model.text_dim
                    )));
                }
                run.model
            }
            Self::Preset(name) => PrefixLmConfig::preset(name, codebook_size, text_dim)
                .ok_or_else(|| ModelError::Argument(format!("no model preset {name:?}")))?,
            Self::Custom {
                d_model,
                n_layers,
                n_heads,
                ffn_hidden,
            } => {
                let mut c =
                    PrefixLmConfig::new(*d_model, *n_layers, *n_heads, codebook_size, text_dim);
                c.ffn_hidden = ffn_hidden.unwrap_or(c.ffn_hidden);
                c
            }
        };
        config.validate()?;
        Ok(config)
    }
}

/// The optimisation settings of a prefix-LM run, declared once: `train`'s flags, a sweep
/// plan's `[train]` table (both flatten it) and a run's `config.json` spell them alike.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct Hyperparams {
    /// Clips per batch.
    #[arg(long = "batch", default_value_t = HYPERPARAMS.batch_size)]
    pub batch_size: usize,
    /// Peak learning rate.
    #[arg(long, default_value_t = HYPERPARAMS.lr)]
    pub lr: f64,
    /// Final learning rate as a fraction of the peak.
    #[arg(long, default_value_t = HYPERPARAMS.final_lr_ratio)]
    pub final_lr_ratio: f64,
    /// Warm-up steps as a fraction of all steps (at least one step).
    #[arg(long = "warmup", default_value_t = HYPERPARAMS.warmup_fraction)]
    pub warmup_fraction: f64,
    /// AdamW decoupled weight decay (all parameters, as the reference).
    #[arg(long, default_value_t = HYPERPARAMS.weight_decay)]
    pub weight_decay: f64,
    /// Global gradient-norm clip.
    #[arg(long, default_value_t = HYPERPARAMS.grad_clip)]
    pub grad_clip: f64,
    /// Seed of the initial weights and of the batch order.
    #[arg(long, default_value_t = HYPERPARAMS.seed)]
    pub seed: u64,
    /// Text tokens kept per caption.
    #[arg(long, default_value_t = HYPERPARAMS.max_text_tokens)]
    pub max_text_tokens: usize,
    /// Motion tokens kept per clip.
    #[arg(long, default_value_t = HYPERPARAMS.max_motion_tokens)]
    pub max_motion_tokens: usize,
}

/// The defaults: batch 32, lr 1e-3 → 1e-4 with 5% warm-up, weight decay 0.1, clip 1.0, seed 0,
/// 64 text and 64 motion tokens.
pub const HYPERPARAMS: Hyperparams = Hyperparams {
    batch_size: 32,
    lr: 1e-3,
    final_lr_ratio: 0.1,
    warmup_fraction: 0.05,
    weight_decay: 0.1,
    grad_clip: 1.0,
    seed: 0,
    max_text_tokens: 64,
    max_motion_tokens: 64,
};

/// Everything a training run depends on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Token set folder.
    pub tokens: PathBuf,
    /// Corpus folder with the caption embeddings (default: the token set's corpus).
    pub corpus: Option<PathBuf>,
    /// Text encoder id of the embeddings (default: the corpus's only one).
    pub text_encoder: Option<String>,
    /// Folder of `{train,val,test}.txt` clip lists (e.g. a scenario dataset) replacing the
    /// token set's own splits: only the listed clips train and evaluate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub splits: Option<PathBuf>,
    /// Select the best checkpoint on the validation clips of this origin only (a run trained
    /// on one source); none: on all of them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub select_on: Option<Origin>,
    /// Model shape.
    pub model: ModelShape,
    /// Token budget D: motion loss positions to train on (rounded up to whole batches).
    pub tokens_budget: u64,
    /// AdamW (β1, β2).
    pub betas: (f64, f64),
    /// The optimisation settings.
    #[serde(flatten)]
    pub hyper: Hyperparams,
    /// Executor and precision (the device is the caller's: see [`train`]).
    #[serde(default)]
    pub compute: Compute,
    /// Evaluate every this many steps (default: ten times per run, and at the end).
    #[serde(skip)]
    pub eval_every: Option<u64>,
    /// Checkpoint every this many steps (default: ten times per run, and at the end).
    #[serde(skip)]
    pub checkpoint_every: Option<u64>,
    /// Stop (with a checkpoint) after this many steps of the schedule; a re-run continues.
    #[serde(skip)]
    pub stop_after: Option<u64>,
    /// Output folder.
    #[serde(skip)]
    pub out: PathBuf,
}

impl TrainConfig {
    /// Defaults for everything but the token set, model, budget and output folder:
    /// [`HYPERPARAMS`], AdamW (0.9, 0.95), 10 evaluations and checkpoints per run.
    pub fn new(tokens: &Path, model: ModelShape, tokens_budget: u64, out: &Path) -> Self {
        Self {
            tokens: tokens.to_path_buf(),
            corpus: None,
            text_encoder: None,
            splits: None,
            select_on: None,
            model,
            tokens_budget,
            betas: (0.9, 0.95),
            hyper: HYPERPARAMS,
            compute: Compute::default(),
            eval_every: None,
            checkpoint_every: None,
            stop_after: None,
            out: out.to_path_buf(),
        }
    }
}

/// `OUT/config.json`: the run as resolved.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunConfig {
    /// Always [`FORMAT`].
    pub format: String,
    /// The training configuration.
    pub train: TrainConfig,
    /// The model as built.
    pub model: PrefixLmConfig,
    /// Corpus folder of the captions.
    pub corpus: PathBuf,
    /// Text encoder id.
    pub text_encoder: String,
    /// The tokenizer of the token set.
    pub tokenizer: tokenizer::TokenizerInfo,
    /// The learning-rate schedule (total steps = the whole budget).
    pub schedule: LrSchedule,
    /// Parameters and FLOPs per token (exact count at the configured maximum lengths).
    pub accounting: Accounting,
    /// The device the run trained on (`cpu`, `cuda:N`); a run may resume on another.
    #[serde(default = "cpu_name")]
    pub device: String,
}

/// The device name of runs recorded before devices were.
fn cpu_name() -> String {
    "cpu".into()
}

/// `OUT/state.json`: how far the checkpoint beside it got.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Optimiser steps taken.
    pub step: u64,
    /// Motion loss positions trained on (D so far).
    pub tokens_seen: u64,
    /// Exact FLOPs of the real (unpadded) slots so far.
    pub flops_exact: f64,
    /// Train-stream items consumed (batch k holds items k·B..(k+1)·B).
    pub data_position: u64,
    /// Sum of the training losses since the last evaluation (checkpointed, so a resumed run
    /// logs the same `train_loss` as an uninterrupted one).
    #[serde(default)]
    pub loss_sum: f64,
    /// Steps summed in `loss_sum`.
    #[serde(default)]
    pub loss_steps: u64,
    /// The evaluation with the lowest validation cross-entropy so far.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub best: Option<BestEval>,
}

/// What a training run reports as it goes.
#[derive(Debug, Clone)]
pub enum TrainEvent {
    /// About to train steps `from..total`.
    Started {
        /// First step (non-zero when resuming).
        from: u64,
        /// Steps of the whole schedule.
        total: u64,
        /// The resolved run.
        run: Box<RunConfig>,
    },
    /// One optimiser step done.
    Step {
        /// Steps done.
        step: u64,
        /// Training loss of the step.
        loss: f32,
        /// Learning rate used.
        lr: f64,
        /// Motion tokens trained on so far.
        tokens_seen: u64,
        /// Motion tokens of this step per second.
        tokens_per_s: f64,
    },
    /// An evaluation finished.
    Eval(Box<EvalRecord>),
}

/// Result of [`train`].
#[derive(Debug, Clone, Serialize)]
pub struct TrainReport {
    /// Steps done (less than the schedule when stopped early).
    pub steps: u64,
    /// Steps of the whole schedule.
    pub total_steps: u64,
    /// The last evaluation.
    pub eval: EvalRecord,
    /// Output folder.
    pub out: PathBuf,
    /// The device it trained on (`cpu`, `cuda:N`).
    pub device: String,
}

/// The trained model in `dir` (`model.safetensors`, memory-mapped on the CPU, else copied to
/// `device`) and its run config.
pub fn load_model(dir: &Path, device: &Device) -> Result<(PrefixLm, RunConfig), ModelError> {
    let run: RunConfig = read_json(&dir.join("config.json"))?;
    if matches!(run.train.model, ModelShape::EsMoe { .. }) {
        return Err(ModelError::invalid(
            dir,
            "an ES-MoE run has a model per caption, not one model file (load it with load_lm)",
        ));
    }
    let weights = dir.join(MODEL_FILE);
    // SAFETY: the checkpoint is only read; it must not change while the model lives.
    let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[&weights], DType::F32, device) }
        .map_err(|e| ModelError::invalid(&weights, e))?;
    let model = PrefixLm::new(&run.model, vb).map_err(|e| ModelError::invalid(&weights, e))?;
    Ok((model, run))
}

/// The trained LM in `dir` as generation and evaluation use it (one model, or ES-MoE's
/// experts and gate on their base), on `device`, run with `compute`, and its run config.
pub fn load_lm(
    dir: &Path,
    device: &Device,
    compute: Compute,
) -> Result<(Box<dyn MotionLm>, RunConfig), ModelError> {
    let run: RunConfig = read_json(&dir.join("config.json"))?;
    if let ModelShape::EsMoe { base, moe, .. } = &run.train.model {
        let mut lm = EsMoe::load(dir, &base.join(MODEL_FILE), &run.model, *moe, device)?;
        lm.set_compute(compute);
        return Ok((Box::new(lm), run));
    }
    let (model, run) = load_model(dir, device)?;
    Ok((Box::new(model.with_compute(compute)), run))
}

/// The emotion label of every labelled clip of a corpus, by motion id.
fn clip_emotions(corpus_dir: &Path) -> Result<HashMap<String, String>, ModelError> {
    let corpus = ingest::corpus::reader::Corpus::open(corpus_dir)
        .map_err(|e| ModelError::Corpus(e.to_string()))?;
    Ok(corpus
        .clip_metadata()
        .map_err(|e| ModelError::Corpus(e.to_string()))?
        .into_iter()
        .filter_map(|m| Some((m.motion_id, m.labels.emotion?)))
        .collect())
}

/// The run's tokenizer (or the one in `dir`, which must be the same checkpoint) on `device`,
/// for decoding its tokens.
pub fn run_tokenizer(
    run: &RunConfig,
    dir: Option<&Path>,
    device: &Device,
) -> Result<tokenizer::model::MotionTokenizer, ModelError> {
    use tokenizer::model::MotionTokenizer;
    let dir = dir.unwrap_or(&run.tokenizer.dir);
    let id = MotionTokenizer::content_id(dir).map_err(|e| ModelError::invalid(dir, e))?;
    if id != run.tokenizer.id {
        return Err(ModelError::invalid(
            dir,
            format!(
                "tokenizer {id} is not the model's {} (pass --tokenizer DIR)",
                run.tokenizer.id
            ),
        ));
    }
    MotionTokenizer::load(dir, device).map_err(|e| ModelError::invalid(dir, e))
}

/// Train (or resume) the run `config` describes on `device`, calling `on_event` as it goes.
pub fn train(
    config: &TrainConfig,
    device: &Device,
    on_event: &mut dyn FnMut(&TrainEvent),
) -> Result<TrainReport, ModelError> {
    let mut run = Run::start(config, device)?;
    let total = run.config.schedule.total;
    on_event(&TrainEvent::Started {
        from: run.state.step,
        total,
        run: Box::new(run.config.clone()),
    });
    let end = config.stop_after.map_or(total, |s| total.min(s));
    let every = |n: Option<u64>| n.unwrap_or(total.div_ceil(10)).max(1);
    let mut last_eval = None;
    while run.state.step < end {
        let event = run.step()?;
        if let TrainEvent::Step { loss, .. } = event {
            run.state.loss_sum += f64::from(loss);
            run.state.loss_steps += 1;
        }
        on_event(&event);
        let (step, done) = (run.state.step, run.state.step == end);
        let scheduled = step % every(config.eval_every) == 0 || step == total;
        if scheduled || done {
            let mean = run.state.loss_sum / run.state.loss_steps.max(1) as f64;
            let record = run.evaluate(mean, scheduled)?;
            // An evaluation only because `stop_after` ends the run early keeps the window:
            // the resumed run's next evaluation then averages the same steps as it would have.
            if scheduled {
                (run.state.loss_sum, run.state.loss_steps) = (0.0, 0);
            }
            on_event(&TrainEvent::Eval(Box::new(record.clone())));
            last_eval = Some(record);
        }
        if step % every(config.checkpoint_every) == 0 || done {
            run.checkpoint()?;
        }
    }
    let eval = match last_eval {
        Some(e) => e,
        None => read_json(&run.paths.eval)?,
    };
    Ok(TrainReport {
        steps: run.state.step,
        total_steps: total,
        eval,
        out: config.out.clone(),
        device: run.config.device.clone(),
    })
}

/// What a run trains.
enum Trainee {
    /// A whole model.
    Model(PrefixLm),
    /// A LoRA adapter on a frozen base.
    Lora(Box<LoraRun>),
    /// An ES-MoE expert and the gate on a frozen base.
    Moe(Box<EsMoeTrainer>),
}

/// A run in progress: data, what it trains, optimiser and where it stands.
struct Run {
    config: RunConfig,
    data: LmData,
    trainee: Trainee,
    /// The trained variables: the model's, or the adapter's (and gate's) on a frozen base.
    vars: HashMap<String, candle_core::Var>,
    opt: AdamW,
    state: TrainState,
    paths: Paths,
}

/// The variables a run trains and how: a new model, a LoRA adapter on a frozen base (with
/// its orthogonality and distillation partners), or an ES-MoE expert and the gate.
fn build_trainee(
    config: &TrainConfig,
    run: &RunConfig,
    data: &LmData,
    device: &Device,
) -> Result<(Trainee, HashMap<String, candle_core::Var>), ModelError> {
    let compute = config.compute;
    Ok(match &config.model {
        ModelShape::Lora {
            base,
            lora,
            expert,
            init,
            orthogonal_to,
            orthogonality,
            distill_from,
            distillation,
        } => {
            let adapter = LoraAdapter::new(&run.model, *lora, expert, config.hyper.seed, device)
                .map_err(ModelError::inference)?;
            if let Some(file) = init {
                adapter.load(file)?;
            }
            let mut previous = Vec::new();
            for file in orthogonal_to {
                previous.extend(adapter_a_matrices(file, device)?);
            }
            let teacher = match distill_from {
                Some(dir) => Some(load_model(dir, device)?.0.with_compute(compute)),
                None => None,
            };
            let vars = adapter.vars();
            let lora = LoraRun {
                adapter,
                base: base_weights(&base.join(MODEL_FILE), device)?,
                compute,
                previous,
                orthogonality: *orthogonality,
                teacher,
                distillation: *distillation as f32,
            };
            (Trainee::Lora(Box::new(lora)), vars)
        }
        ModelShape::EsMoe {
            base,
            previous,
            expert,
            moe,
        } => {
            let train_texts: Vec<&[f32]> = data
                .split("train")
                .iter()
                .flat_map(|e| &e.captions)
                .map(|&c| data.text[c].as_slice())
                .collect();
            let mut trainer = EsMoeTrainer::new(
                &run.model,
                *moe,
                &base.join(MODEL_FILE),
                previous.as_deref(),
                expert,
                &clip_emotions(&run.corpus)?,
                &train_texts,
                config.hyper.seed,
                device,
            )?;
            trainer.moe.set_compute(compute);
            let vars = trainer.vars();
            (Trainee::Moe(Box::new(trainer)), vars)
        }
        ModelShape::Preset(_) | ModelShape::Custom { .. } => {
            let (model, varmap) =
                init_model(&run.model, config.hyper.seed, device).map_err(ModelError::inference)?;
            let vars = varmap.data().lock().expect("varmap lock").clone();
            (Trainee::Model(model.with_compute(compute)), vars)
        }
    })
}

impl Run {
    /// Load the data, resolve the run, build the model and optimiser, and restore the
    /// checkpoint in the output folder if there is one.
    fn start(config: &TrainConfig, device: &Device) -> Result<Self, ModelError> {
        let corpus = match &config.corpus {
            Some(c) => c.clone(),
            None => {
                tokenizer::TokenSet::open(&config.tokens)
                    .map_err(|e| ModelError::invalid(&config.tokens, e))?
                    .manifest
                    .corpus
            }
        };
        let limits = Limits {
            text_tokens: config.hyper.max_text_tokens,
            motion_tokens: config.hyper.max_motion_tokens,
        };
        let encoder = config.text_encoder.as_deref();
        let splits = ingest::corpus::split::SplitAssignment::from_dir(config.splits.as_deref())
            .map_err(|e| ModelError::Argument(e.to_string()))?;
        let data = LmData::load(&config.tokens, &corpus, encoder, limits, &splits)?;
        let model_config = config.model.resolve(data.codebook_size(), data.text_dim)?;
        let total = data
            .steps_for_tokens(
                config.tokens_budget,
                config.hyper.batch_size,
                config.hyper.seed,
            )
            .ok_or_else(|| ModelError::Argument("no train clips with motion tokens".into()))?;
        let seq = SequenceShape {
            prefix: config.hyper.max_text_tokens,
            motion: config.hyper.max_motion_tokens + 1,
        };
        let run = RunConfig {
            format: FORMAT.into(),
            train: config.clone(),
            accounting: Accounting::of(&model_config, seq),
            model: model_config,
            corpus,
            text_encoder: data.encoder.clone(),
            tokenizer: data.tokens.tokenizer.clone(),
            schedule: LrSchedule {
                peak: config.hyper.lr,
                warmup: ((total as f64 * config.hyper.warmup_fraction).round() as u64).max(1),
                total,
                final_ratio: config.hyper.final_lr_ratio,
            },
            device: nn::device::device_name(device),
        };
        std::fs::create_dir_all(&config.out).map_err(|e| ModelError::io(&config.out, e))?;
        let (trainee, vars) = build_trainee(config, &run, &data, device)?;
        let (beta1, beta2) = config.betas;
        let adamw = AdamWConfig {
            beta1,
            beta2,
            eps: 1e-8,
            weight_decay: config.hyper.weight_decay,
        };
        let mut opt = AdamW::new(&vars, adamw);
        let paths = Paths::new(&config.out);
        let state = resume(&paths, &run, &vars, &mut opt, device)?;
        write_json(&paths.config, &run)?;
        Ok(Self {
            config: run,
            data,
            trainee,
            vars,
            opt,
            state,
            paths,
        })
    }

    /// One optimiser step on the next batch.
    fn step(&mut self) -> Result<TrainEvent, ModelError> {
        let (c, started) = (&self.config.train, Instant::now());
        let items = self
            .data
            .train_items(self.state.step, c.hyper.batch_size, c.hyper.seed);
        let batch = self.data.batch(&self.config.model, &items);
        let (loss, grads) = match &self.trainee {
            Trainee::Model(model) => model.loss_and_grads(&batch),
            Trainee::Lora(l) => l.loss_and_grads(&self.config.model, &batch),
            Trainee::Moe(t) => {
                let examples: Vec<MoeExample> = items
                    .iter()
                    .map(|item| MoeExample {
                        motion_id: &item.0.motion_id,
                        text: self.data.text_of(item),
                        tokens: &item.0.tokens,
                        ends: item.0.ends,
                    })
                    .collect();
                // Older experts are masked less and less as the step's schedule runs.
                let progress = self.state.step as f64 / self.config.schedule.total as f64;
                let p = t.moe.config.mask_probability * (1.0 - progress);
                let mut rng = SplitMix64::stream(c.hyper.seed ^ MASK_STREAM, self.state.step);
                t.loss_and_grads(&examples, Some((&mut rng, p)))
                    .map(|(l, g)| (l.total(t.moe.config.emotion_weight), g))
            }
        }
        .map_err(ModelError::inference)?;
        let lr = self.config.schedule.at(self.state.step);
        self.opt
            .step(&grads, lr, Some(c.hyper.grad_clip))
            .map_err(ModelError::inference)?;
        let tokens: u64 = items.iter().map(|(e, _)| e.targets()).sum();
        let layout = &batch.layout;
        let flops: f64 = (layout.prefix_lens.iter().zip(&layout.motion_lens))
            .map(|(&prefix, &motion)| {
                let shape = SequenceShape { prefix, motion };
                accounting::train_flops_exact(&self.config.model, shape)
            })
            .sum();
        let s = &mut self.state;
        s.step += 1;
        s.tokens_seen += tokens;
        s.data_position += c.hyper.batch_size as u64;
        s.flops_exact += flops;
        Ok(TrainEvent::Step {
            step: s.step,
            loss,
            lr,
            tokens_seen: s.tokens_seen,
            tokens_per_s: tokens as f64 / started.elapsed().as_secs_f64(),
        })
    }

    /// Evaluate the test (and validation) split and record it in `eval.json` and
    /// `evals.jsonl`; a `scheduled` evaluation may become the validation-selected one (one only
    /// because `stop_after` ends the run early may not: a resumed run would not have made it).
    fn evaluate(&mut self, train_loss: f64, scheduled: bool) -> Result<EvalRecord, ModelError> {
        // A LoRA run evaluates the base with the adapter as it now stands merged in.
        let merged;
        let (lm, expert_weights): (&dyn MotionLm, _) = match &self.trainee {
            Trainee::Model(model) => (model, None),
            Trainee::Lora(l) => {
                merged = l
                    .model(&self.config.model)
                    .map_err(ModelError::inference)?
                    .0;
                (&merged, None)
            }
            Trainee::Moe(t) => (&t.moe, Some(self.expert_weights(&t.moe)?)),
        };
        let batch = self.config.train.hyper.batch_size;
        let test = evaluate(lm, &self.data, "test", batch)?;
        let val = match self.data.split("val").is_empty() {
            true => None,
            false => Some(evaluate(lm, &self.data, "val", batch)?),
        };
        let params = self.config.accounting.params;
        let mut record = EvalRecord {
            step: self.state.step,
            tokens_seen: self.state.tokens_seen,
            train_loss,
            test,
            val,
            best: None,
            unscheduled: !scheduled,
            flops_6n: accounting::budget(&self.config.model, self.state.tokens_seen as f64),
            flops_exact: self.state.flops_exact,
            n_nv: params.n_nv,
            n_v: params.n_v,
            tied: params.tied,
            expert_weights,
        };
        if let Some(c) = selection::candidate(&record, self.config.train.select_on) {
            self.state.best = Some(selection::keep_better(self.state.best.take(), c));
        }
        record.best = self.state.best.clone();
        write_json(&self.paths.eval, &record)?;
        append_json_line(&self.paths.evals, &record)?;
        Ok(record)
    }

    /// The gate's mean weight of each expert over the test clips' first captions.
    fn expert_weights(&self, moe: &EsMoe) -> Result<Vec<f64>, ModelError> {
        let items = self.data.eval_items("test");
        let mut sum = vec![0f64; moe.experts()];
        for item in &items {
            let w = moe
                .weights(self.data.text_of(item))
                .map_err(ModelError::inference)?;
            sum.iter_mut().zip(w).for_each(|(s, w)| *s += f64::from(w));
        }
        Ok(sum.iter().map(|s| s / items.len().max(1) as f64).collect())
    }

    /// Write the weights others load, then the resume files, committed by `state.json`.
    fn checkpoint(&mut self) -> Result<(), ModelError> {
        let paths = &self.paths;
        let weights = nn::checkpoint::var_tensors(&self.vars);
        let model = match &self.trainee {
            Trainee::Model(_) => Some(weights.clone()),
            Trainee::Lora(l) => {
                let adapter = self.config.train.out.join(ADAPTER_FILE);
                save_safetensors(&weights, &adapter)
                    .map_err(|e| ModelError::invalid(&adapter, e))?;
                Some(
                    l.model(&self.config.model)
                        .map_err(ModelError::inference)?
                        .1,
                )
            }
            Trainee::Moe(t) => {
                t.moe.save(&self.config.train.out)?;
                None
            }
        };
        if let Some(model) = model {
            save_safetensors(&model, &paths.model)
                .map_err(|e| ModelError::invalid(&paths.model, e))?;
        }
        let invalid = |e: &dyn std::fmt::Display| ModelError::invalid(paths.resume.state_path(), e);
        let stage = paths.resume.stage().map_err(|e| invalid(&e))?;
        save_safetensors(&weights, &stage.join(MODEL_FILE)).map_err(|e| invalid(&e))?;
        self.opt
            .save(&stage.join(OPTIMIZER_FILE))
            .map_err(|e| invalid(&e))?;
        paths
            .resume
            .commit(self.state.step, &self.state)
            .map_err(|e| invalid(&e))
    }
}

/// A LoRA run: the adapter being trained, the frozen base weights (merged models run with
/// `compute`), the earlier adapters' `lora_A` matrices it is kept orthogonal to (with weight
/// `orthogonality`), and the model it is distilled towards (with weight `distillation`).
struct LoraRun {
    adapter: LoraAdapter,
    base: HashMap<String, Tensor>,
    compute: Compute,
    previous: Vec<HashMap<String, Tensor>>,
    orthogonality: f64,
    teacher: Option<PrefixLm>,
    distillation: f32,
}

impl LoraRun {
    /// The merged model and its weights.
    fn model(
        &self,
        config: &PrefixLmConfig,
    ) -> candle_core::Result<(PrefixLm, HashMap<String, Tensor>)> {
        self.adapter.merged_model(config, &self.base, self.compute)
    }

    /// Loss of `batch` and the adapter's gradients.
    fn loss_and_grads(
        &self,
        config: &PrefixLmConfig,
        batch: &LmBatch,
    ) -> candle_core::Result<(f32, candle_core::backprop::GradStore)> {
        let (model, merged) = self.model(config)?;
        let (loss, grads) = match &self.teacher {
            None => model.loss_and_grads(batch)?,
            Some(teacher) => {
                let soft: Vec<f32> = teacher.forward(batch)?.flatten_all()?.to_vec1()?;
                let vocab = config.vocab_size();
                model.loss_and_grads_with(batch, &|logits| {
                    Some(nn::lm_kernels::distillation(
                        logits,
                        &soft,
                        vocab,
                        &batch.targets,
                        self.distillation,
                        DISTILLATION_TEMPERATURE,
                    ))
                })?
            }
        };
        let mut grads = self.adapter.grads(&merged, &grads)?;
        let penalty = if self.previous.is_empty() {
            0.0
        } else {
            self.adapter
                .orthogonality(&self.previous, self.orthogonality, &mut grads)?
        };
        Ok((loss + penalty, grads))
    }
}

/// The files of a run folder.
struct Paths {
    config: PathBuf,
    model: PathBuf,
    resume: ResumeFiles,
    eval: PathBuf,
    evals: PathBuf,
}

impl Paths {
    fn new(out: &Path) -> Self {
        Self {
            config: out.join("config.json"),
            model: out.join(MODEL_FILE),
            resume: ResumeFiles::new(out),
            eval: out.join("eval.json"),
            evals: out.join("evals.jsonl"),
        }
    }
}

/// Restore the checkpoint in the run folder, if any, after checking it belongs to `run`;
/// evaluations recorded after it are dropped (they will be redone).
fn resume(
    paths: &Paths,
    run: &RunConfig,
    vars: &HashMap<String, candle_core::Var>,
    opt: &mut AdamW,
    device: &Device,
) -> Result<TrainState, ModelError> {
    let fresh = TrainState {
        step: 0,
        tokens_seen: 0,
        flops_exact: 0.0,
        data_position: 0,
        loss_sum: 0.0,
        loss_steps: 0,
        best: None,
    };
    if !paths.resume.state_path().is_file() {
        let _ = std::fs::remove_file(&paths.evals);
        return Ok(fresh);
    }
    // The same run on another device resumes: only what was computed must match. The old
    // config is read as today's (a run recorded before devices and precisions were has the
    // defaults: CPU, f32).
    // Compared as written (TrainConfig skips its per-invocation fields).
    check_same_run(&paths.config, "a run", |old: RunConfig| {
        let old = RunConfig {
            device: run.device.clone(),
            ..old
        };
        serde_json::to_value(&old).ok() == serde_json::to_value(run).ok()
    })?;
    let state: TrainState = read_json(paths.resume.state_path())?;
    let files = paths.resume.files(state.step);
    let (weights, moments) = (files.join(MODEL_FILE), files.join(OPTIMIZER_FILE));
    let saved = base_weights(&weights, device)?;
    for (name, var) in vars {
        let t = saved
            .get(name)
            .ok_or_else(|| ModelError::invalid(&weights, format!("no tensor {name}")))?;
        var.set(t).map_err(|e| ModelError::invalid(&weights, e))?;
    }
    opt.load(&moments)
        .map_err(|e| ModelError::invalid(&moments, e))?;
    if paths.evals.is_file() {
        let text =
            std::fs::read_to_string(&paths.evals).map_err(|e| ModelError::io(&paths.evals, e))?;
        let kept: String = text
            .lines()
            .filter(|l| serde_json::from_str::<EvalRecord>(l).is_ok_and(|r| r.step <= state.step))
            .map(|l| format!("{l}\n"))
            .collect();
        write_atomic(&paths.evals, kept.as_bytes()).map_err(|e| ModelError::io(&paths.evals, e))?;
    }
    Ok(state)
}
