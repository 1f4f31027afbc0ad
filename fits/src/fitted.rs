//! What a fit writes (`fits.json`) and the options that steer it: the column choices, the
//! fitted laws and parametric L(N, D), the agreement of the two approaches, the seed noise,
//! the data-constrained fit and the held-out budget's check. The computations live in
//! [`crate::analysis`], [`crate::holdout`], [`crate::repeated`] and [`crate::replicates`].

use crate::isoflop::{BudgetMinimum, IsoMinimum};
use crate::laws::{Estimate, LogLaw, PowerLaw};
use crate::lbfgs::{LbfgsOptions, Termination};
use crate::parametric::StartGrid;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

impl Fits {
    /// The seed SD of the parametric loss at the largest budget with repeated runs (√ of the
    /// mean variance over its sizes): the noise nearest the budgets a verdict is about.
    pub fn param_seed_sd(&self) -> Option<f64> {
        let top = self
            .seed_noise
            .iter()
            .filter(|s| s.param_sd.is_some())
            .map(|s| s.budget)
            .max_by(f64::total_cmp)?;
        let v: Vec<f64> = self
            .seed_noise
            .iter()
            .filter(|s| s.budget == top)
            .filter_map(|s| s.param_sd)
            .map(|s| s * s)
            .collect();
        Some((v.iter().sum::<f64>() / v.len() as f64).sqrt())
    }
}

/// A column choice: its name and whether the user named it. A missing column the user named
/// is an error; a missing default disables only what needs it (recorded under `skipped`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ColumnChoice {
    /// Column name.
    pub name: String,
    /// True when given on the command line.
    pub explicit: bool,
}

impl ColumnChoice {
    /// The default `name`, not named by the user.
    pub fn default_name(name: &str) -> Self {
        Self {
            name: name.into(),
            explicit: false,
        }
    }

    /// `Some(name)` from the user, else the default.
    pub fn or_default(given: Option<String>, default: &str) -> Self {
        match given {
            Some(name) => Self {
                name,
                explicit: true,
            },
            None => Self::default_name(default),
        }
    }
}

/// Which columns hold what. Defaults follow the sweep's results table (scaling-laws.md).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ColumnSpec {
    /// Model size N (default `n_nv`, non-vocabulary parameters).
    pub n: ColumnChoice,
    /// Training tokens D (default `tokens`).
    pub d: ColumnChoice,
    /// Compute C (default `budget`; if absent, C = 6·(N + N_v)·D).
    pub c: ColumnChoice,
    /// Loss for minima, power laws and the log law (default `norm_test_loss`).
    pub loss: ColumnChoice,
    /// Loss for the parametric L(N, D) (default `test_loss`, else the loss column); must be > 0.
    pub param_loss: ColumnChoice,
    /// Vocabulary size V (default `vocab`).
    pub v: ColumnChoice,
    /// Vocabulary parameters N_v (default `n_v`).
    pub nv: ColumnChoice,
    /// Model width d (default `d_model`; if absent, N_v / V).
    pub width: ColumnChoice,
    /// Budget group (default `budget`; if absent, C values within `group_tol_dex` are grouped).
    pub group: ColumnChoice,
    /// Epochs over the unique training tokens (default `epochs`; the data-constrained fit).
    pub epochs: ColumnChoice,
    /// Synthetic share of the unique training data (default `synth_share`; the exchange rate
    /// of the data-constrained fit).
    pub synth_share: ColumnChoice,
    /// Training seed (default `seed`): rows differing only in it are averaged for the minima.
    pub seed: ColumnChoice,
}

impl Default for ColumnSpec {
    fn default() -> Self {
        let d = ColumnChoice::default_name;
        Self {
            n: d("n_nv"),
            d: d("tokens"),
            c: d("budget"),
            loss: d("norm_test_loss"),
            param_loss: d("test_loss"),
            v: d("vocab"),
            nv: d("n_v"),
            width: d("d_model"),
            group: d("budget"),
            epochs: d("epochs"),
            synth_share: d("synth_share"),
            seed: d("seed"),
        }
    }
}

/// Fit settings.
#[derive(Debug, Clone)]
pub struct FitOptions {
    /// Column mapping.
    pub columns: ColumnSpec,
    /// Without a group column, C values this close in log10 form one budget.
    pub group_tol_dex: f64,
    /// L-BFGS starts for the parametric fit.
    pub grid: StartGrid,
    /// The grid's name or spec, for the record.
    pub grid_name: String,
    /// Bootstrap resamples (0: none).
    pub bootstrap: usize,
    /// Starts per bootstrap refit: the k best distinct local optima of the full-data grid, or
    /// `None` for the whole grid.
    pub bootstrap_starts: Option<usize>,
    /// Seed of the bootstrap.
    pub seed: u64,
    /// Huber threshold δ.
    pub huber_delta: f64,
    /// L-BFGS settings.
    pub lbfgs: LbfgsOptions,
    /// Fit without the runs of this budget group and score the prediction on them.
    pub holdout_budget: Option<f64>,
    /// Fit only the runs of this vocabulary size (the V column), so that the parametric
    /// fit's raw loss is one vocabulary's and comparable between runs.
    pub vocab: Option<f64>,
    /// Also fit the data-constrained L(N, D') of Muennighoff et al. (needs an epochs column).
    pub repeated_data: bool,
    /// In it, the effective parameters N' too (R*_N fitted).
    pub effective_params: bool,
    /// In it, early stopping: the law fitted on the tokens of each run's validation-selected
    /// checkpoint and a stopping rule beside it (needs `best_step` and `steps` columns).
    pub early_stopping: bool,
    /// In it, the exchange forms to fit: more than one are scored on the data subsets left
    /// out in turn and the lowest error adopted.
    pub exchange_forms: Vec<ExchangeForm>,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            columns: ColumnSpec::default(),
            group_tol_dex: 0.05,
            grid: StartGrid::epoch(),
            grid_name: "epoch".into(),
            bootstrap: 500,
            bootstrap_starts: Some(16),
            seed: 0,
            huber_delta: 1e-3,
            lbfgs: LbfgsOptions::default(),
            holdout_budget: None,
            vocab: None,
            repeated_data: false,
            effective_params: false,
            early_stopping: false,
            exchange_forms: vec![ExchangeForm::TokenWorth],
        }
    }
}

/// Where the data came from and how columns were mapped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Input {
    /// Results file.
    pub file: String,
    /// Data rows.
    pub rows: usize,
    /// Role → column used (`null`: not used).
    pub columns: BTreeMap<String, Option<String>>,
    /// How budgets were formed.
    pub grouping: String,
    /// Budget groups.
    pub groups: usize,
    /// Notes on defaults that were substituted or computed.
    pub notes: Vec<String>,
}

/// L-BFGS settings as recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LbfgsRecord {
    /// Correction pairs.
    pub memory: usize,
    /// Iteration cap.
    pub max_iter: usize,
    /// Gradient tolerance (max-norm, absolute).
    pub gtol: f64,
}

/// The settings a fit ran with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Settings {
    /// Bootstrap seed.
    pub seed: u64,
    /// Huber δ.
    pub huber_delta: f64,
    /// Number of L-BFGS starts.
    pub starts: usize,
    /// Grid name or spec.
    pub starts_grid: String,
    /// The grid's values.
    pub grid: StartGrid,
    /// Bootstrap resamples requested.
    pub bootstrap: usize,
    /// Starts per bootstrap refit (`full`, or the best K distinct local optima).
    pub bootstrap_starts: String,
    /// L-BFGS settings.
    pub lbfgs: LbfgsRecord,
    /// Grouping tolerance in log10 C (used without a group column).
    pub group_tol_dex: f64,
}

impl Settings {
    /// The settings of `opts`, as recorded.
    pub(crate) fn of(opts: &FitOptions) -> Self {
        Self {
            seed: opts.seed,
            huber_delta: opts.huber_delta,
            starts: opts.grid.len(),
            starts_grid: opts.grid_name.clone(),
            grid: opts.grid.clone(),
            bootstrap: opts.bootstrap,
            bootstrap_starts: match opts.bootstrap_starts {
                Some(k) => {
                    format!("the best (up to {k}) distinct local optima of the full-data grid")
                }
                None => "full".into(),
            },
            lbfgs: LbfgsRecord {
                memory: opts.lbfgs.memory,
                max_iter: opts.lbfgs.max_iter,
                gtol: opts.lbfgs.gtol,
            },
            group_tol_dex: opts.group_tol_dex,
        }
    }
}

/// One exponent from approach 2 (IsoFLOP minima, OLS interval) beside approach 3 (parametric,
/// bootstrap interval).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Agreement {
    /// `N_opt` or `D_opt` (∝ C^exponent).
    pub quantity: String,
    /// The IsoFLOP power law's exponent.
    pub isoflop: Estimate,
    /// The parametric fit's exponent.
    pub parametric: Estimate,
    /// Whether the two 95% intervals overlap (`None` when one has no interval).
    pub overlap: Option<bool>,
}

/// Bootstrap draws of the parametric fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Bootstrap {
    /// Resamples drawn.
    pub resamples: usize,
    /// Resamples whose refit gave a finite objective and finite parameters.
    pub succeeded: usize,
    /// Seed (resample i uses stream i).
    pub seed: u64,
    /// Starts per refit.
    pub starts_per_resample: usize,
    /// Each successful draw as [E, A, B, alpha, beta].
    pub samples: Vec<[f64; 5]>,
}

/// E, A, B, α and β of L(N, D) = E + A/N^α + B/D^β, each with its bootstrap 95% percentile
/// interval.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LawEstimates {
    /// E with bootstrap 95% percentile interval.
    #[serde(rename = "E")]
    pub e: Estimate,
    /// A.
    #[serde(rename = "A")]
    pub a: Estimate,
    /// B.
    #[serde(rename = "B")]
    pub b: Estimate,
    /// α.
    pub alpha: Estimate,
    /// β.
    pub beta: Estimate,
}

impl LawEstimates {
    /// The five parameters from `est(k)`, k = 0..5 in the order E, A, B, α, β.
    pub fn from_fn(est: impl Fn(usize) -> Estimate) -> Self {
        Self {
            e: est(0),
            a: est(1),
            b: est(2),
            alpha: est(3),
            beta: est(4),
        }
    }
}

/// The parametric fit L(N, D) = E + A/N^α + B/D^β.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Parametric {
    /// The law's parameters.
    #[serde(flatten)]
    pub law: LawEstimates,
    /// Compute-optimal N ∝ C^(β/(α+β)).
    pub n_opt_exponent: Estimate,
    /// Compute-optimal D ∝ C^(α/(α+β)).
    pub d_opt_exponent: Estimate,
    /// Runs fitted.
    pub n_runs: usize,
    /// Loss column fitted.
    pub loss_column: String,
    /// Σ Huber at the optimum.
    pub objective: f64,
    /// Optimum in the fitted parametrisation [a, b, e, alpha, beta].
    pub theta: [f64; 5],
    /// R² of log L.
    pub r2_log: Option<f64>,
    /// Residuals in ln L (prediction − observation), in row order.
    pub residuals_log: Vec<f64>,
    /// Starts run.
    pub starts: usize,
    /// Starts that ended within 1e-6 (relative) of the best objective.
    pub starts_at_optimum: usize,
    /// Why each start stopped (counts).
    pub terminations: BTreeMap<String, usize>,
    /// Objective evaluations over all starts.
    pub evaluations: usize,
    /// Bootstrap draws.
    pub bootstrap: Bootstrap,
}

/// Everything `motionscale fit` computes: the content of `fits.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Fits {
    /// Input file and column mapping.
    pub input: Input,
    /// Settings.
    pub settings: Settings,
    /// IsoFLOP minimum over N at each budget.
    pub budgets: Vec<BudgetMinimum>,
    /// IsoFLOP minima over V at each (budget, N).
    pub vocab_minima: Vec<IsoMinimum>,
    /// Power laws by name: `n_opt_vs_c`, `d_opt_vs_c`, `v_opt_vs_c`, `nv_opt_vs_c`, `nv_vs_n`.
    pub power_laws: BTreeMap<String, PowerLaw>,
    /// L_opt = α·log10 C + β over the interior budget minima.
    pub log_law: Option<LogLaw>,
    /// The parametric fit.
    pub parametric: Option<Parametric>,
    /// Approaches 2 and 3 side by side on the N_opt and D_opt exponents.
    #[serde(default)]
    pub agreement: Vec<Agreement>,
    /// The loss over training seeds where runs were repeated (averaged for the minima).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub seed_noise: Vec<SeedNoise>,
    /// Fits not done, and why.
    pub skipped: Vec<String>,
    /// Things to look at before trusting the numbers.
    pub warnings: Vec<String>,
    /// Plot files written (stems; each has .svg and .png).
    pub plots: Vec<String>,
    /// The same fit with N counted as every parameter (N + N_v), beside this one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub total_n: Option<Box<Fits>>,
    /// The data-constrained parametric fit (`--repeated-data`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repeated_data: Option<RepeatedData>,
    /// The loss law's shape: straight, curved or with a floor, each scored by leaving each
    /// interior minimum out (three minima or more).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_shape: Option<crate::loss_shape::LossShape>,
    /// The held-out budget's prediction against its runs (`--holdout-budget`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout: Option<Holdout>,
}

/// The loss over training seeds at one (budget, N, V).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeedNoise {
    /// The budget group's C.
    pub budget: f64,
    /// N.
    pub n: f64,
    /// V, when the table has a vocabulary column.
    pub v: Option<f64>,
    /// The seeds.
    pub seeds: Vec<f64>,
    /// Mean loss (the loss column).
    pub mean: f64,
    /// Sample standard deviation over the seeds.
    pub sd: f64,
    /// The same of the parametric loss column (the data-constrained law's loss).
    #[serde(default)]
    pub param_sd: Option<f64>,
    /// The budget's parabola rise one sampled size step (the median gap in log10 N) from its
    /// vertex: the loss difference that separates the minimum from its neighbours.
    pub resolved_gap: Option<f64>,
}

/// The data-constrained fit's Laplace (Gauss–Newton) approximation at its optimum: what the
/// planner's `hour_value` target narrows. The log residuals are modelled as a budget's shared
/// misfit (variance τ²) plus each run's own (σ²), so runs of one budget inform less than
/// independent ones would.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Information {
    /// The coordinates of θ = (ln A, ln B, ln E, α, β, ln R*_D, ln ρ, ln R*_N) it covers: those
    /// fitted and identified.
    pub free: Vec<usize>,
    /// Each budget group's runs, JᵀJ and ΣJ (J: the runs' gradients of ln L̂ over `free`).
    pub budgets: Vec<BudgetInformation>,
    /// Within-budget variance of the log residuals.
    pub sigma2: f64,
    /// Variance of the budgets' shared misfit (one-way random-effects moments, at least 0).
    pub tau2: f64,
}

/// One budget group's share of [`Information`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BudgetInformation {
    /// Budget C of the group.
    pub budget: f64,
    /// Runs in it.
    pub runs: usize,
    /// JᵀJ over its runs.
    pub jtj: Vec<Vec<f64>>,
    /// Σ J over its runs.
    pub sum: Vec<f64>,
}

/// Leave-one-budget-out error of the plain and the data-constrained fits, in ln L.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldOutError {
    /// Budgets left out in turn.
    pub folds: usize,
    /// RMS log residual of the plain L(N, D) on the left-out budgets.
    pub plain_rms: f64,
    /// RMS log residual of L(N, D') on the left-out budgets.
    pub repeated_rms: f64,
    /// `plain` or `repeated`: the lower held-out error.
    pub better: String,
}

/// The lowest loss of the runs at one budget on one unique-data set, over model sizes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataFrontierPoint {
    /// The budget (the group's geometric mean C).
    pub budget: f64,
    /// Unique tokens U of the set.
    pub unique_tokens: f64,
    /// Hours of motion in it (none without the `hours` column).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hours: Option<f64>,
    /// Its synthetic share s.
    pub synth_share: f64,
    /// The lowest loss (the data-constrained fit's loss column).
    pub loss: f64,
    /// N of the run that scored it.
    pub n: f64,
}

/// How synthetic tokens count against captured ones in the data-constrained law.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ExchangeForm {
    /// Each token is worth k = 1 − s + ρ·s captured ones: U and D both scale by k and the
    /// repetitions R = D/U − 1 are unchanged.
    #[default]
    TokenWorth,
    /// Repetitions count against the effective pool U·k = U_real + ρ·U_synth; the tokens seen
    /// count in full, so R = D/(U·k) − 1.
    EffectivePool,
}

/// k = 1 − s + ρ·s, the captured tokens a token of a pool with synthetic share `s` is worth
/// at exchange rate `rho`, and ∂ln k/∂ln ρ = ρ·s/k.
pub fn exchange_factor(s: f64, rho: f64) -> (f64, f64) {
    let k = 1.0 - s + rho * s;
    (k, rho * s / k)
}

/// The synthetic shares' range (lo, hi), and whether it is wide enough (more than 0.05) for
/// the exchange rate ρ to be identified: with one share, ρ is a constant factor of U.
pub fn share_range(shares: &[f64]) -> ((f64, f64), bool) {
    let (lo, hi) = shares
        .iter()
        .fold((f64::MAX, f64::MIN), |(lo, hi), &s| (lo.min(s), hi.max(s)));
    ((lo, hi), hi - lo > 0.05)
}

impl ExchangeForm {
    /// The name `fit --exchange-form` takes.
    pub fn name(self) -> &'static str {
        match self {
            ExchangeForm::TokenWorth => "token-worth",
            ExchangeForm::EffectivePool => "effective-pool",
        }
    }
}

/// How often the law's 95% prediction interval holds the best loss of a (budget, data subset)
/// cell of the runs it was fitted on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InSampleCoverage {
    /// Cells: the budgets × unique-data sets of the fit's frontier.
    pub cells: usize,
    /// Cells whose best loss lies inside the interval.
    pub covered: usize,
    /// The log-space SD of one run about the law that the intervals add to the refits'
    /// spread: √(σ² + τ²), within-budget scatter and the budgets' shared misfit.
    pub scatter: f64,
    /// The cells outside their interval.
    pub misses: Vec<CellMiss>,
}

/// A cell whose best loss fell outside the law's 95% prediction interval.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellMiss {
    /// The budget.
    pub budget: f64,
    /// Unique tokens of the cell's data.
    pub unique_tokens: f64,
    /// Its synthetic share.
    pub synth_share: f64,
    /// The best loss the runs reached.
    pub loss: f64,
    /// The law's prediction and its 95% prediction interval.
    pub predicted: Estimate,
}

/// One exchange form fitted and scored on held-out runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FormScore {
    /// The form.
    pub form: ExchangeForm,
    /// ρ at its full-data optimum, where ρ is fitted.
    pub exchange: Option<f64>,
    /// Its error on held-out runs (absent where there are too few folds).
    pub held_out: Option<FormError>,
}

/// A fit's RMS log error on clusters of runs left out in turn.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FormError {
    /// What was left out: `data subsets` or `budgets`.
    pub clusters: String,
    /// How many folds.
    pub folds: usize,
    /// RMS log residual on the left-out runs.
    pub rms: f64,
}

/// R*_D's and ρ's 95% intervals with whole clusters of runs resampled.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BlockInterval {
    /// What a cluster is: `budgets` or `data subsets`.
    pub clusters: String,
    /// How many clusters there are.
    pub count: usize,
    /// Resamples whose refit converged.
    pub refits: usize,
    /// R*_D's interval.
    pub r_star: [f64; 2],
    /// ρ's interval, where ρ is fitted.
    pub exchange: Option<[f64; 2]>,
}

/// The data-constrained fit as recorded in `fits.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RepeatedData {
    /// The law's parameters.
    #[serde(flatten)]
    pub law: LawEstimates,
    /// R*_D's and ρ's intervals with budgets, and data subsets, resampled whole (beside the
    /// single-run bootstrap of `r_star` and `exchange`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub block_intervals: Vec<BlockInterval>,
    /// R*_D, the repetitions of data after which extra epochs are worth 1/e of fresh data.
    pub r_star: Estimate,
    /// R*_N, the same for parameters past U_N, the size the law allocates to the unique data
    /// (absent unless asked for: then no parameter is in excess).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub r_star_n: Option<Estimate>,
    /// Runs whose N exceeds U_N at the optimum (those that identify R*_N).
    #[serde(default)]
    pub past_base_size: usize,
    /// How to read R*_N (set when it is far beyond the excess the runs have).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note_n: Option<String>,
    /// Effective captured tokens per synthetic token, ρ: the unique data counts as
    /// U·(1 − s + ρ·s) for a synthetic share s (Hernandez et al. 2021's effective data
    /// transferred, as a ratio). Fitted only when the runs' synthetic shares differ.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exchange: Option<Estimate>,
    /// How synthetic tokens count (fits written before the forms are token-worth).
    #[serde(default)]
    pub exchange_form: ExchangeForm,
    /// With more than one form asked for: each form's held-out error, the adopted (lowest)
    /// first.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub exchange_forms: Vec<FormScore>,
    /// The law's 95% prediction intervals against the best loss of each (budget, data subset)
    /// cell it was fitted on (absent without the Laplace information or tokens per hour).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub in_sample: Option<InSampleCoverage>,
    /// Runs fitted.
    pub n_runs: usize,
    /// Runs that saw some token more than once (epochs > 1).
    pub repeated_runs: usize,
    /// The most epochs of any run.
    pub max_epochs: f64,
    /// Σ Huber at the optimum.
    pub objective: f64,
    /// Why the best start stopped.
    pub termination: Termination,
    /// Bootstrap resamples drawn and those that refitted to finite values.
    pub bootstrap: [usize; 2],
    /// The plain and data-constrained fits on budgets they did not see.
    pub held_out: Option<HeldOutError>,
    /// How to read R* (set when it is far beyond the repetitions the runs have).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    /// The bootstrap refits, (E, A, B, α, β, R*_D, ρ, R*_N) each: `predict --hours` carries
    /// them through to its intervals.
    #[serde(
        default,
        skip_serializing_if = "Vec::is_empty",
        serialize_with = "refits_with_r_star_n_if_fitted",
        deserialize_with = "refits_with_r_star_n_or_without"
    )]
    pub draws: Vec<[f64; 8]>,
    /// The lowest loss of each budget on each unique-data set (over model sizes): the points
    /// of the data-law charts.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frontier: Vec<DataFrontierPoint>,
    /// The runs' unique loss positions per hour of motion (median over runs; needs the
    /// `hours` column): turns hours into U.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tokens_per_hour: Option<f64>,
    /// log10 N_v = c0 + c1·log10 N over the runs (one vocabulary: N_v grows with the width),
    /// so that a predicted N spends C = 6·(N + N_v)·D.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nv_line: Option<[f64; 2]>,
    /// The runs' vocabulary size, when they share one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vocab: Option<f64>,
    /// The Laplace approximation at the optimum (absent in fits written before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub information: Option<Information>,
    /// With early stopping (`--early-stopping`): when a run's validation loss stops improving.
    /// The law is then fitted on the selected checkpoints' tokens, and a run of D tokens is
    /// predicted at min(D, e*·U).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stopping: Option<StoppingRule>,
}

/// When a run's validation loss stops improving: ln e* = c₀ + c_N·ln N + c_U·ln U, e* the
/// epochs over the U unique tokens at the selected checkpoint, fitted by OLS on the runs whose
/// selected step comes before the end of their schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StoppingRule {
    /// (c₀, c_N, c_U).
    pub coef: [f64; 3],
    /// Standard errors of the coefficients.
    pub se: [f64; 3],
    /// Runs that stopped early (those fitted).
    pub runs: usize,
    /// Residual standard deviation in ln e*.
    pub residual_sd: f64,
    /// The rule refitted on each bootstrap resample of the law's `draws`, in the same order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub draws: Vec<[f64; 3]>,
}

/// One predicted quantity against the held-out runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HoldoutCheck {
    /// What is compared.
    pub quantity: String,
    /// The prediction from the other budgets, with its 95% interval.
    pub predicted: Estimate,
    /// What the held-out runs give.
    pub trained: f64,
    /// predicted / trained.
    pub ratio: f64,
    /// Whether `trained` lies inside the predicted interval (`None` without an interval).
    pub inside: Option<bool>,
    /// Where each number comes from.
    pub note: String,
}

/// The held-out budget's record in `fits.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Holdout {
    /// The budget held out (the group's C).
    pub budget: f64,
    /// Its runs.
    pub runs: usize,
    /// The parabola over its own runs (what the IsoFLOP fit would have found there).
    pub trained: IsoMinimum,
    /// (N, loss) of its lowest-loss run.
    pub best_run: [f64; 2],
    /// Predictions against the runs.
    pub checks: Vec<HoldoutCheck>,
    /// Predictions that could not be made, and why.
    pub missing: Vec<String>,
}

/// Refits as 8 parameters, or as 7 where R*_N was not fitted (it is ∞, which JSON cannot hold).
fn refits_with_r_star_n_if_fitted<S: serde::Serializer>(
    draws: &[[f64; 8]],
    s: S,
) -> Result<S::Ok, S::Error> {
    use serde::ser::SerializeSeq;
    let mut seq = s.serialize_seq(Some(draws.len()))?;
    for t in draws {
        let kept = if t[7].is_finite() { 8 } else { 7 };
        seq.serialize_element(&t[..kept])?;
    }
    seq.end()
}

/// Refits of 8 parameters, or of 7 (R*_N not fitted, read as ∞: no parameter in excess).
fn refits_with_r_star_n_or_without<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Vec<[f64; 8]>, D::Error> {
    use serde::de::Error;
    let rows: Vec<Vec<f64>> = Vec::deserialize(d)?;
    rows.into_iter()
        .map(|r| {
            let mut t = [f64::INFINITY; 8];
            match r.len() {
                7 | 8 => {
                    t[..r.len()].copy_from_slice(&r);
                    Ok(t)
                }
                n => Err(D::Error::custom(format!(
                    "a refit has {n} parameters; expected 8 (E, A, B, α, β, R*_D, ρ, R*_N) or 7 (before R*_N)"
                ))),
            }
        })
        .collect()
}
