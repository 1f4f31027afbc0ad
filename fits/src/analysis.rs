//! The whole fit of a results table: columns → budget groups → IsoFLOP minima → power laws,
//! log law and the parametric L(N, D) with bootstrap → [`Fits`] (written as `fits.json`).

use crate::isoflop::{self, BudgetMinimum, Columns, IsoMinimum};
use crate::laws::{Estimate, LogLaw, PowerLaw};
use crate::lbfgs::LbfgsOptions;
use crate::parametric::{self, LogRuns, StartGrid};
use crate::table::Table;
use crate::FitError;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

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

/// The parametric fit L(N, D) = E + A/N^α + B/D^β.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Parametric {
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
    /// Power laws by name: `n_opt_vs_c`, `d_opt_vs_c`, `nv_opt_vs_c`, `nv_vs_n`.
    pub power_laws: BTreeMap<String, PowerLaw>,
    /// L_opt = α·log10 C + β over the interior budget minima.
    pub log_law: Option<LogLaw>,
    /// The parametric fit.
    pub parametric: Option<Parametric>,
    /// Fits not done, and why.
    pub skipped: Vec<String>,
    /// Things to look at before trusting the numbers.
    pub warnings: Vec<String>,
    /// Plot files written (stems; each has .svg and .png).
    pub plots: Vec<String>,
}

/// A power law to fit: key, x name, y name, and the (x, y) minima.
type LawPoints = (&'static str, &'static str, &'static str, Vec<(f64, f64)>);

/// Reads a column the user may or may not have named; `Ok(None)` for a missing default.
fn optional(t: &Table, col: &ColumnChoice, flag: &str) -> Result<Option<Vec<f64>>, FitError> {
    if t.has(&col.name) || col.explicit {
        t.numbers(&col.name, flag).map(Some)
    } else {
        Ok(None)
    }
}

/// Every value must be > 0 (the column goes on a log axis).
fn positive(t: &Table, name: &str, values: &[f64]) -> Result<(), FitError> {
    match values.iter().position(|&v| v <= 0.0) {
        None => Ok(()),
        Some(row) => Err(FitError::BadCell {
            path: t.path().to_path_buf(),
            column: name.into(),
            row: row + 1,
            problem: format!("{} must be > 0 (it goes on a log scale)", values[row]),
        }),
    }
}

/// Fits every law the table's columns allow.
pub fn fit_table(t: &Table, opts: &FitOptions) -> Result<Fits, FitError> {
    let cs = &opts.columns;
    let mut notes = Vec::new();
    let mut skipped = Vec::new();
    let mut warnings = Vec::new();
    let mut used: BTreeMap<String, Option<String>> = BTreeMap::new();

    let n = t.numbers(&cs.n.name, "--n-col")?;
    positive(t, &cs.n.name, &n)?;
    let loss = t.numbers(&cs.loss.name, "--loss-col")?;
    used.insert("N".into(), Some(cs.n.name.clone()));
    used.insert("loss".into(), Some(cs.loss.name.clone()));
    let d = optional(t, &cs.d, "--d-col")?;
    let v = optional(t, &cs.v, "--v-col")?;
    let nv = optional(t, &cs.nv, "--nv-col")?;
    let width_col = optional(t, &cs.width, "--width-col")?;
    let group = optional(t, &cs.group, "--group-col")?;
    for (role, col, values) in [
        ("D", &cs.d, &d),
        ("V", &cs.v, &v),
        ("N_v", &cs.nv, &nv),
        ("width", &cs.width, &width_col),
    ] {
        if let Some(vals) = values {
            positive(t, &col.name, vals)?;
        }
        used.insert(role.into(), values.as_ref().map(|_| col.name.clone()));
    }
    let c = match optional(t, &cs.c, "--c-col")? {
        Some(c) => {
            positive(t, &cs.c.name, &c)?;
            used.insert("C".into(), Some(cs.c.name.clone()));
            c
        }
        None => {
            let Some(d) = &d else {
                return Err(FitError::MissingColumn {
                    path: t.path().to_path_buf(),
                    column: cs.c.name.clone(),
                    available: t.names().join(", "),
                    hint: "pick the compute column with --c-col (or give --d-col so C = 6·N·D)"
                        .into(),
                });
            };
            let extra = nv.as_deref();
            notes.push(format!(
                "no column {:?}: C computed as 6·({}{})·{}",
                cs.c.name,
                cs.n.name,
                extra.map_or(String::new(), |_| format!(" + {}", cs.nv.name)),
                cs.d.name
            ));
            used.insert("C".into(), None);
            (0..n.len())
                .map(|i| 6.0 * (n[i] + extra.map_or(0.0, |x| x[i])) * d[i])
                .collect()
        }
    };
    let width: Option<Vec<f64>> = match (&width_col, &v, &nv) {
        (Some(w), _, _) => Some(w.clone()),
        (None, Some(v), Some(nv)) => {
            notes.push(format!(
                "no column {:?}: width = {} / {}",
                cs.width.name, cs.nv.name, cs.v.name
            ));
            Some(nv.iter().zip(v).map(|(a, b)| a / b).collect())
        }
        _ => None,
    };

    let groups = isoflop::group_rows(&c, group.as_deref(), opts.group_tol_dex);
    used.insert(
        "group".into(),
        group.as_ref().map(|_| cs.group.name.clone()),
    );
    let grouping = match &group {
        Some(_) => format!("equal values of column {:?}", cs.group.name),
        None => format!(
            "C values within {} dex of each other (no column {:?})",
            opts.group_tol_dex, cs.group.name
        ),
    };
    let cols = Columns {
        c: &c,
        n: &n,
        loss: &loss,
        d: d.as_deref(),
        v: v.as_deref(),
        width: width.as_deref(),
    };
    let vocab_minima = isoflop::vocab_minima(&cols, &groups);
    let budgets = isoflop::budget_minima(&cols, &groups, &vocab_minima);
    for b in &budgets {
        if let (false, Some(reason)) = (b.min.interior, &b.min.reason) {
            warnings.push(format!(
                "budget {:.3e}: no interior minimum over N ({reason}); excluded from the laws",
                b.min.budget
            ));
        }
    }
    let excluded_v = vocab_minima.iter().filter(|m| !m.interior).count();
    if excluded_v > 0 {
        warnings.push(format!(
            "{excluded_v} of {} minima over V at fixed N are not interior; excluded from N_v ∝ N^γ",
            vocab_minima.len()
        ));
    }

    let mut power_laws = BTreeMap::new();
    let interior: Vec<&BudgetMinimum> = budgets.iter().filter(|b| b.min.interior).collect();
    let mut candidates: Vec<LawPoints> = vec![(
        "n_opt_vs_c",
        "C",
        "N_opt",
        interior
            .iter()
            .filter_map(|b| Some((b.min.budget, b.min.opt?)))
            .collect(),
    )];
    if d.is_some() {
        candidates.push((
            "d_opt_vs_c",
            "C",
            "D_opt",
            interior
                .iter()
                .filter_map(|b| Some((b.min.budget, b.d_opt?)))
                .collect(),
        ));
    } else {
        skipped.push(format!("d_opt_vs_c: no tokens column {:?}", cs.d.name));
    }
    if v.is_some() && width.is_some() {
        candidates.push((
            "nv_opt_vs_c",
            "C",
            "N_v_opt",
            interior
                .iter()
                .filter_map(|b| Some((b.min.budget, b.nv_opt?)))
                .collect(),
        ));
        candidates.push((
            "nv_vs_n",
            "N",
            "N_v_opt",
            vocab_minima
                .iter()
                .filter_map(|m| Some((m.fixed_n?, m.nv_opt?)))
                .collect(),
        ));
    } else {
        skipped.push(format!(
            "nv_opt_vs_c, nv_vs_n: need a vocabulary column {:?} and a width ({:?}, or {:?} to divide by V)",
            cs.v.name, cs.width.name, cs.nv.name
        ));
    }
    for (key, x_name, y_name, pts) in candidates {
        if pts.len() < 3 {
            skipped.push(format!(
                "{key} ({y_name} ∝ {x_name}^k): {} usable minima, need 3",
                pts.len()
            ));
            continue;
        }
        let (x, y): (Vec<f64>, Vec<f64>) = pts.into_iter().unzip();
        match PowerLaw::fit(x_name, y_name, &x, &y) {
            Some(l) => {
                power_laws.insert(key.to_string(), l);
            }
            None => skipped.push(format!("{key}: the minima share one {x_name}")),
        }
    }
    let log_law = if interior.len() >= 3 {
        let (x, y): (Vec<f64>, Vec<f64>) = interior
            .iter()
            .map(|b| (b.min.budget, b.min.loss_opt.unwrap_or(f64::NAN)))
            .unzip();
        LogLaw::fit(&x, &y)
    } else {
        skipped.push(format!(
            "log law: {} interior IsoFLOP minima, need 3",
            interior.len()
        ));
        None
    };

    // The parametric fit.
    let (name, pl) = match optional(t, &cs.param_loss, "--param-loss-col")? {
        Some(l) => (cs.param_loss.name.clone(), l),
        None => {
            notes.push(format!(
                "no column {:?}: the parametric fit uses {:?}",
                cs.param_loss.name, cs.loss.name
            ));
            (cs.loss.name.clone(), loss.clone())
        }
    };
    used.insert("parametric_loss".into(), Some(name.clone()));
    let parametric = match &d {
        None => {
            skipped.push(format!(
                "parametric L(N, D): no tokens column {:?}",
                cs.d.name
            ));
            None
        }
        Some(d) => {
            if let Some(row) = pl.iter().position(|&l| l <= 0.0) {
                skipped.push(format!(
                    "parametric L(N, D): {name:?} has a non-positive loss ({}) at row {}; fit a positive loss with --param-loss-col",
                    pl[row],
                    row + 1
                ));
                None
            } else if n.len() < 6 {
                skipped.push(format!(
                    "parametric L(N, D): {} runs, need at least 6 for 5 parameters",
                    n.len()
                ));
                None
            } else {
                let p = fit_parametric(&LogRuns::new(&n, d, &pl), &name, opts)?;
                if p.bootstrap.succeeded < p.bootstrap.resamples {
                    warnings.push(format!(
                        "parametric bootstrap: {} of {} refits failed",
                        p.bootstrap.resamples - p.bootstrap.succeeded,
                        p.bootstrap.resamples
                    ));
                }
                Some(p)
            }
        }
    };
    if power_laws.is_empty() && log_law.is_none() && parametric.is_none() {
        return Err(FitError::TooFew {
            path: t.path().to_path_buf(),
            fit: "any law".into(),
            message: format!(
                "{} rows in {} budget group(s), {} interior IsoFLOP minima; {}",
                n.len(),
                groups.len(),
                interior.len(),
                skipped.join("; ")
            ),
        });
    }
    Ok(Fits {
        input: Input {
            file: t.path().display().to_string(),
            rows: t.rows(),
            columns: used,
            grouping,
            groups: groups.len(),
            notes,
        },
        settings: Settings {
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
        },
        budgets,
        vocab_minima,
        power_laws,
        log_law,
        parametric,
        skipped,
        warnings,
        plots: Vec::new(),
    })
}

/// Grid fit, then bootstrap, of L(N, D) on `runs`.
pub fn fit_parametric(
    runs: &LogRuns,
    loss_column: &str,
    opts: &FitOptions,
) -> Result<Parametric, FitError> {
    let delta = opts.huber_delta;
    let starts = opts.grid.points();
    let ms = parametric::multi_start(runs, delta, &starts, &opts.lbfgs)?;
    let best = *ms.best();
    let boot_starts = match opts.bootstrap_starts {
        Some(k) => ms.distinct_best(k),
        None => starts.clone(),
    };
    let draws = parametric::bootstrap(
        runs,
        delta,
        &boot_starts,
        opts.bootstrap,
        opts.seed,
        &opts.lbfgs,
    );
    let samples = parametric::finite_draws(&draws);
    let nat = parametric::natural(&best.x);
    let exps = |s: &[f64; 5]| [s[4] / (s[3] + s[4]), s[3] / (s[3] + s[4])];
    let interval = |value: f64, f: &dyn Fn(&[f64; 5]) -> f64| {
        let vals: Vec<f64> = samples.iter().map(f).collect();
        Estimate {
            value,
            se: None,
            ci_low: parametric::percentile(&vals, 0.025),
            ci_high: parametric::percentile(&vals, 0.975),
        }
    };
    let est = |k: usize| interval(nat[k], &|s| s[k]);
    let best_exps = exps(&nat);
    let residuals = runs.residuals(&best.x);
    let mean = runs.ln_l.iter().sum::<f64>() / runs.len() as f64;
    let tss: f64 = runs.ln_l.iter().map(|v| (v - mean).powi(2)).sum();
    let rss: f64 = residuals.iter().map(|r| r * r).sum();
    let mut terminations = BTreeMap::new();
    for m in &ms.ends {
        let key = serde_json::to_value(m.termination)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default();
        *terminations.entry(key).or_insert(0) += 1;
    }
    Ok(Parametric {
        e: est(0),
        a: est(1),
        b: est(2),
        alpha: est(3),
        beta: est(4),
        n_opt_exponent: interval(best_exps[0], &|s| exps(s)[0]),
        d_opt_exponent: interval(best_exps[1], &|s| exps(s)[1]),
        n_runs: runs.len(),
        loss_column: loss_column.into(),
        objective: best.f,
        theta: best.x,
        r2_log: (tss > 0.0).then(|| 1.0 - rss / tss),
        residuals_log: residuals,
        starts: starts.len(),
        starts_at_optimum: ms.at_optimum(1e-6),
        terminations,
        evaluations: ms.ends.iter().map(|m| m.evaluations).sum(),
        bootstrap: Bootstrap {
            resamples: opts.bootstrap,
            succeeded: samples.len(),
            seed: opts.seed,
            starts_per_resample: boot_starts.len(),
            samples,
        },
    })
}
