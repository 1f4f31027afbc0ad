//! The settings and records of a prefix-LM run ([`train()`](crate::train::train)): the model
//! shape ([`ModelShape`]), the optimisation settings ([`Hyperparams`]) and the whole training
//! config ([`TrainConfig`]); what a run folder records (`config.json`'s [`RunConfig`],
//! `state.json`'s [`TrainState`]); and what a run reports ([`TrainEvent`], [`TrainReport`]).
//! All of them are also reachable as `lm::train::…`.

use crate::accounting::Accounting;
use crate::es_moe::EsMoeConfig;
use crate::eval_record::{BestEval, EvalRecord};
use crate::lora::LoraConfig;
use crate::prefix_lm::{Compute, PrefixLmConfig};
use ingest::corpus::Origin;
use motionscale_core::files::read_json;
use nn::optim::LrSchedule;
use nn::ModelError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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
                    return Err(ModelError::argument("base model", format!(
                        "{}: the base model has {} codes and {}-d text, the data {codebook_size} and {text_dim}",
                        base.display(),
                        run.model.codebook_size,
                        run.model.text_dim
                    )));
                }
                run.model
            }
            Self::Preset(name) => PrefixLmConfig::preset(name, codebook_size, text_dim)
                .ok_or_else(|| {
                    ModelError::argument("model preset", format!("no preset {name:?}"))
                })?,
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
    /// Residual dropout: the probability of dropping each value of every block's attention
    /// and FFN outputs while training (0: none; not with ES-MoE experts).
    #[arg(long, default_value_t = HYPERPARAMS.dropout)]
    #[serde(default, skip_serializing_if = "is_zero")]
    pub dropout: f64,
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

fn is_zero(value: &f64) -> bool {
    *value == 0.0
}

/// The defaults: batch 32, lr 1e-3 → 1e-4 with 5% warm-up, weight decay 0.1, clip 1.0, no
/// dropout, seed 0, 64 text and 64 motion tokens.
pub const HYPERPARAMS: Hyperparams = Hyperparams {
    batch_size: 32,
    lr: 1e-3,
    final_lr_ratio: 0.1,
    warmup_fraction: 0.05,
    weight_decay: 0.1,
    grad_clip: 1.0,
    dropout: 0.0,
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
    /// Executor and precision (the device is the caller's: see [`train`](crate::train::train)).
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

/// Result of [`train`](crate::train::train).
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
