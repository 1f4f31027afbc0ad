//! The experiments run on top of the stages: the codebook sweep ([`codebook_sweep`], our
//! ScaMo Fig. 6), continual expert training ([`continual`]), continual learning to generate
//! with BI-CTVAE ([`cl2gen`], [`ctvae`], [`ctvae_train`]), and IsoFLOP sweeps of the
//! text-prefix motion transformer: [`plan`] every (budget, model,
//! vocabulary) point with D = C / (6·(N_nv + N_v)) from `lm::accounting`, [`prepare`]
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

pub mod backbone;
pub mod centring;
pub mod cl2gen;
pub mod codebook_sweep;
pub mod continual;
pub mod ctvae;
pub mod ctvae_train;
pub mod data_ladder;
pub mod error;
pub mod local;
pub mod next;
pub mod plan;
pub mod prepare;
pub mod recipe;
pub mod results;
pub mod run;
pub mod seeds;
pub mod slurm;
pub mod status;

pub use error::SweepError;
pub use plan::{IsoFlopPlan, PlanPoint, PlanRequest, TrainSettings, VocabSource, Vocabulary};
pub use results::RunRow;
