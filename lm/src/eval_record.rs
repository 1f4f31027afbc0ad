//! The records of a run's evaluations: `OUT/eval.json` (the latest) and `OUT/evals.jsonl`
//! (every one) hold [`EvalRecord`]s, each with the validation-selected evaluation so far
//! ([`BestEval`], chosen by [`crate::selection`]).

use crate::test_loss::SplitLoss;
use ingest::corpus::Origin;
use serde::{Deserialize, Serialize};

/// The validation-selected checkpoint: the evaluation whose validation cross-entropy is the
/// lowest so far (the earliest of equals), with its test losses (see [`crate::selection`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BestEval {
    /// Step of that evaluation.
    pub step: u64,
    /// Its validation cross-entropy (on the clips of `selected_on`).
    pub val_cross_entropy: f64,
    /// Its test losses.
    pub test: SplitLoss,
    /// The origin of the validation clips it was selected on (none: all of them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub selected_on: Option<Origin>,
}

/// `OUT/eval.json`: one evaluation with the accounting of the run so far.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalRecord {
    /// Step of the evaluation.
    pub step: u64,
    /// Motion tokens trained on so far (D).
    pub tokens_seen: u64,
    /// Mean training loss since the previous evaluation.
    pub train_loss: f64,
    /// Test losses (cross-entropy, L_u, unigram entropy…).
    pub test: SplitLoss,
    /// Validation losses (none when the run has no validation clips).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub val: Option<SplitLoss>,
    /// The validation-selected evaluation so far, this one included (none without
    /// validation clips).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub best: Option<BestEval>,
    /// Made only because `stop_after` ended this invocation early, off the schedule: never
    /// selected (a resumed run would not have made it).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub unscheduled: bool,
    /// C = 6·(N_nv + N_v)·D.
    pub flops_6n: f64,
    /// Exact FLOPs of the real (unpadded) slots.
    pub flops_exact: f64,
    /// Non-vocabulary parameters.
    pub n_nv: u64,
    /// Vocabulary parameters (2·V·d: untied).
    pub n_v: u64,
    /// Whether embedding and head are tied (false).
    pub tied: bool,
    /// ES-MoE: the gate's mean weight of each expert (oldest first) over the test captions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expert_weights: Option<Vec<f64>>,
}
