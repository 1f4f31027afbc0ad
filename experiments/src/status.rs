//! Where every point of a sweep stands, read from its folder: done (`result.json`), running
//! (another process holds its lock), failed (`error.json`), pending, or not runnable (the
//! plan flags it below one step).

use crate::plan::IsoFlopPlan;
use crate::results::{read_row, run_dir};
use crate::run::RunError;
use crate::SweepError;
use motionscale_core::lock::FileLock;
use serde::Serialize;
use std::path::Path;

/// The state of one point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum PointState {
    /// `result.json` exists.
    Done,
    /// A process holds the point's lock.
    Running,
    /// The last attempt failed.
    Failed,
    /// Not started, or interrupted (a re-run resumes it).
    Pending,
    /// Below one step: never run.
    NotRunnable,
}

impl PointState {
    /// The state as `sweep status` prints it.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Done => "done",
            Self::Running => "running",
            Self::Failed => "failed",
            Self::Pending => "pending",
            Self::NotRunnable => "not-runnable",
        }
    }
}

/// One point's state with what its folder says about it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PointStatus {
    /// Plan row.
    pub index: usize,
    /// Run folder name.
    pub run_id: String,
    /// State.
    pub state: PointState,
    /// Last checkpointed step, when training has started.
    pub step: Option<u64>,
    /// Test cross-entropy (done) or the error (failed).
    pub detail: Option<String>,
}

/// The state of every point of `plan` in the sweep folder `runs`.
pub fn status(plan: &IsoFlopPlan, runs: &Path) -> Result<Vec<PointStatus>, SweepError> {
    plan.points
        .iter()
        .map(|point| {
            let dir = run_dir(runs, &point.run_id);
            let step = std::fs::read_to_string(dir.join("train/state.json"))
                .ok()
                .and_then(|t| serde_json::from_str::<lm::train::TrainState>(&t).ok())
                .map(|s| s.step);
            let error = std::fs::read_to_string(dir.join("error.json"))
                .ok()
                .and_then(|t| serde_json::from_str::<RunError>(&t).ok());
            let (state, detail) = if let Some(row) = read_row(runs, &point.run_id)? {
                let detail = format!(
                    "test CE {:.4}, L_u {:.4}",
                    row.test_loss, row.norm_test_loss
                );
                (PointState::Done, Some(detail))
            } else if !point.runnable() {
                (PointState::NotRunnable, None)
            } else if FileLock::is_held(&dir.join(".lock"))? {
                (PointState::Running, None)
            } else if let Some(e) = error {
                (PointState::Failed, Some(e.error))
            } else {
                (PointState::Pending, None)
            };
            Ok(PointStatus {
                index: point.index,
                run_id: point.run_id.clone(),
                state,
                step,
                detail,
            })
        })
        .collect()
}
