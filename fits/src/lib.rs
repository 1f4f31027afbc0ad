//! Scaling-law fits for IsoFLOP sweeps (scaling-laws.md, "Fits"): IsoFLOP minima (Chinchilla
//! approach 2), log–log power laws, the log law, the parametric L(N, D) by Huber + L-BFGS from
//! a grid of starts with bootstrap intervals (approach 3), predictions at a budget, and plots.

pub mod analysis;
pub mod data_value;
mod error;
pub mod family;
mod fastmath;
pub mod fit_file;
pub mod fitted;
pub mod holdout;
pub mod hour_design;
pub mod isoflop;
pub mod laws;
pub mod lbfgs;
pub mod loss_shape;
pub mod ols;
pub mod parametric;
pub mod planner;
pub mod predict;
pub mod repeated;
pub mod replay;
pub mod replicates;
pub mod report;
pub mod runs;
pub mod search;
pub mod stopping;
pub mod synth;
pub mod table;

pub use analysis::fit_table;
pub use error::FitError;
pub use fitted::{ColumnChoice, ColumnSpec, FitOptions, Fits};
pub use predict::{predict, Laws, PredictOptions, Prediction};
pub use table::Table;
