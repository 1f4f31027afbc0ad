//! IsoFLOP sweeps of the text-prefix motion transformer: [`plan`] every (budget, model,
//! vocabulary) point with D = C / (6·(N_nv + N_v)) from `model::accounting`, [`prepare`]
//! each vocabulary's token set once, [`run`] every point resumably in its own folder
//! (locally with a bounded worker pool, [`local`], or as a Slurm job array, [`slurm`]) and
//! keep the [`results`] table whole and duplicate-free however the process is stopped.
//!
//! ```text
//! RUNS/plan.toml                 the plan the folder belongs to
//! RUNS/tokenizers/<V>/           tokenizers the plan trains
//! RUNS/tokens/<V>/               token sets shared by all points of vocabulary V
//! RUNS/<run_id>/                 one point: .lock, train/, wall.json, error.json, result.json
//! RUNS/results.csv, .parquet     every result.json, rebuilt after each run
//! RUNS/slurm/                    sbatch scripts, job ids, logs (Slurm backend)
//! ```

pub mod centring;
pub mod cl2gen;
pub mod continual;
pub mod error;
pub mod local;
pub mod lock;
pub mod plan;
pub mod prepare;
pub mod results;
pub mod run;
pub mod seeds;
pub mod slurm;
pub mod status;

pub use error::SweepError;
pub use plan::{IsoFlopPlan, PlanPoint, PlanRequest, TrainSettings, VocabSource, Vocabulary};
pub use results::RunRow;

/// Write `value` as pretty JSON to `path`, atomically.
pub(crate) fn write_json(
    path: &std::path::Path,
    value: &impl serde::Serialize,
) -> Result<(), error::SweepError> {
    let text =
        serde_json::to_string_pretty(value).map_err(|e| error::SweepError::invalid(path, e))?;
    ingest::npy::write_atomic(path, text.as_bytes()).map_err(|e| error::SweepError::io(path, e))
}

/// Parse the JSON file at `path`.
pub(crate) fn read_json<T: serde::de::DeserializeOwned>(
    path: &std::path::Path,
) -> Result<T, error::SweepError> {
    let text = std::fs::read_to_string(path).map_err(|e| error::SweepError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| error::SweepError::invalid(path, e))
}
