//! The whole fit of a results table: columns → budget groups → IsoFLOP minima → power laws,
//! log law and the parametric L(N, D) with bootstrap → [`Fits`] (written as `fits.json`).

use crate::data_value;
use crate::fitted::{
    Agreement, Bootstrap, FitOptions, Fits, Input, LawEstimates, Parametric, Settings,
};
use crate::holdout;
use crate::isoflop::{self, BudgetMinimum, Columns, IsoMinimum};
use crate::laws::{LogLaw, PowerLaw};
use crate::parametric::{self, LogRuns};
use crate::repeated;
use crate::replicates;
use crate::runs::Runs;
use crate::table::Table;
use crate::FitError;
use std::collections::BTreeMap;

/// A power law to fit: key, x name, y name, and the (x, y) minima.
type LawPoints = (&'static str, &'static str, &'static str, Vec<(f64, f64)>);

/// Fits every law the table's columns allow; with `opts.holdout_budget`, without that budget's
/// runs, then scores the prediction on them.
pub fn fit_table(t: &Table, opts: &FitOptions) -> Result<Fits, FitError> {
    let mut all = Runs::read(t, opts)?;
    if let Some(k) = opts.vocab {
        all = all.of_vocabulary(k).map_err(|e| in_file(t, e))?;
    }
    let (runs, held_out) = match opts.holdout_budget {
        None => (all, None),
        Some(c) => {
            let (kept, held) =
                holdout::split(&all, c, opts.group_tol_dex).map_err(|e| in_file(t, e))?;
            (all.select(&kept), Some(all.select(&held)))
        }
    };
    let mut fits = fit_runs(t, &runs, opts)?;
    if let Some(held) = &held_out {
        fits.input.notes.push(format!(
            "budget {:.3e} held out: {} runs not fitted, scored under `holdout`",
            opts.holdout_budget.unwrap_or_default(),
            held.len()
        ));
        fits.holdout = Some(holdout::score(held, &fits)?);
    }
    match runs.total_parameters(opts.group_tol_dex) {
        Some(total) => match fit_runs(t, &total, opts) {
            Ok(f) => fits.total_n = Some(Box::new(f)),
            Err(e) => fits
                .skipped
                .push(format!("total-parameter convention: {e}")),
        },
        None => fits.skipped.push(format!(
            "total-parameter convention (N + N_v): no vocabulary-parameter column {:?}",
            opts.columns.nv.name
        )),
    }
    if opts.repeated_data {
        match repeated::fit(&runs, &fits, opts) {
            Ok(mut r) => {
                r.in_sample = data_value::in_sample_coverage(&r);
                fits.repeated_data = Some(r)
            }
            Err(why) => fits.skipped.push(why.to_string()),
        }
    }
    Ok(fits)
}

/// `e`, said of table `t`'s file.
fn in_file(t: &Table, e: FitError) -> FitError {
    FitError::InFile {
        path: t.path().to_path_buf(),
        source: Box::new(e),
    }
}

/// Fits every law `runs` allow, in one parameter convention.
fn fit_runs(t: &Table, runs: &Runs, opts: &FitOptions) -> Result<Fits, FitError> {
    let mut skipped = Vec::new();
    let mut warnings = Vec::new();
    let all_groups = isoflop::group_rows(&runs.c, runs.group.as_deref(), opts.group_tol_dex);
    let (averaged, mut seed_noise) = replicates::average(runs, &all_groups);
    let groups = isoflop::group_rows(&averaged.c, averaged.group.as_deref(), opts.group_tol_dex);
    let grouping = match &runs.group {
        Some(_) => format!("equal values of column {:?}", opts.columns.group.name),
        None => format!(
            "C values within {} dex of each other (no column {:?})",
            opts.group_tol_dex, opts.columns.group.name
        ),
    };
    let cols = Columns {
        c: &averaged.c,
        n: &averaged.n,
        loss: &averaged.loss,
        d: averaged.d.as_deref(),
        v: averaged.v.as_deref(),
        width: averaged.width.as_deref(),
    };
    let vocab_minima = isoflop::vocab_minima(&cols, &groups);
    let budgets = isoflop::budget_minima(&cols, &groups, &vocab_minima);
    replicates::resolve_gaps(&mut seed_noise, &budgets);
    minima_warnings(&budgets, &vocab_minima, &mut warnings);
    let power_laws = power_laws(&averaged, opts, &budgets, &vocab_minima, &mut skipped);
    let interior: Vec<&BudgetMinimum> = budgets.iter().filter(|b| b.min.interior).collect();
    let log_law = if interior.len() >= 3 {
        let (x, y): (Vec<f64>, Vec<f64>) = interior
            .iter()
            .map(|b| (b.min.budget, b.min.loss_opt.unwrap_or(f64::NAN)))
            .unzip();
        LogLaw::fit(&x, &y)
    } else {
        skipped.push(format!(
            "log law: {} interior IsoFLOP minima in {} budget group(s), need 3 budgets",
            interior.len(),
            groups.len()
        ));
        None
    };
    let loss_shape = (interior.len() >= 3).then(|| {
        let pts: Vec<[f64; 2]> = interior
            .iter()
            .filter_map(|b| Some([b.min.budget.log10(), b.min.loss_opt?]))
            .collect();
        crate::loss_shape::compare(&pts)
    });
    let parametric = parametric_fit(runs, opts, &mut skipped, &mut warnings)?;
    if power_laws.is_empty() && log_law.is_none() && parametric.is_none() {
        return Err(FitError::TooFew {
            path: t.path().to_path_buf(),
            fit: "any law".into(),
            message: format!(
                "{} rows in {} budget group(s), {} interior IsoFLOP minima; {}",
                runs.len(),
                groups.len(),
                interior.len(),
                skipped.join("; ")
            ),
        });
    }
    let agreement = agreement(&power_laws, parametric.as_ref());
    for a in agreement.iter().filter(|a| a.overlap == Some(false)) {
        warnings.push(format!(
            "approaches 2 and 3 disagree on the {} exponent: IsoFLOP {} vs parametric {} (95% intervals do not overlap)",
            a.quantity,
            crate::report::estimate_text(&a.isoflop),
            crate::report::estimate_text(&a.parametric)
        ));
    }
    Ok(Fits {
        input: Input {
            file: t.path().display().to_string(),
            rows: runs.len(),
            columns: runs.columns.clone(),
            grouping,
            groups: groups.len(),
            notes: runs.notes.clone(),
        },
        settings: Settings::of(opts),
        budgets,
        vocab_minima,
        power_laws,
        log_law,
        parametric,
        agreement,
        seed_noise,
        skipped,
        warnings,
        plots: Vec::new(),
        total_n: None,
        repeated_data: None,
        loss_shape,
        holdout: None,
    })
}

/// Budgets without an interior minimum that the warnings name one by one; past this many,
/// one line counts them (the summary names each with its reason).
const NAMED_EXCLUSIONS: usize = 3;

/// Warnings about budgets and vocabulary minima that are not interior: a line per budget on
/// an IsoFLOP grid with a few bad budgets, one line for more, and one line for a table that
/// is not a grid at all (at most two interior minima among more than three budget groups).
fn minima_warnings(budgets: &[BudgetMinimum], vocab: &[IsoMinimum], warnings: &mut Vec<String>) {
    let interior = budgets.iter().filter(|b| b.min.interior).count();
    let excluded = budgets.len() - interior;
    if budgets.len() > 3 && interior <= 2 {
        warnings.push(format!(
            "not an IsoFLOP grid: {interior} of {} budget groups have an interior minimum over N, \
             so approach 2 does not apply (`fit --law` fits the parametric laws to any table)",
            budgets.len()
        ));
        return;
    }
    if excluded > NAMED_EXCLUSIONS {
        warnings.push(format!(
            "{excluded} of {} budget groups have no interior minimum over N and are excluded \
             from the laws (the summary names each with its reason); `fit --law` fits the \
             parametric laws to every run",
            budgets.len()
        ));
    } else {
        for b in budgets {
            if let (false, Some(reason)) = (b.min.interior, &b.min.reason) {
                warnings.push(format!(
                    "budget {:.3e}: no interior minimum over N ({reason}); excluded from the laws",
                    b.min.budget
                ));
            }
        }
    }
    let excluded_v = vocab.iter().filter(|m| !m.interior).count();
    if excluded_v > 0 {
        warnings.push(format!(
            "{excluded_v} of {} minima over V at fixed N are not interior; excluded from N_v ∝ N^γ",
            vocab.len()
        ));
    }
}

/// The power laws over the interior minima: N_opt, D_opt, and the vocabulary laws.
fn power_laws(
    runs: &Runs,
    opts: &FitOptions,
    budgets: &[BudgetMinimum],
    vocab_minima: &[IsoMinimum],
    skipped: &mut Vec<String>,
) -> BTreeMap<String, PowerLaw> {
    let interior: Vec<&BudgetMinimum> = budgets.iter().filter(|b| b.min.interior).collect();
    let along = |f: fn(&BudgetMinimum) -> Option<f64>| -> Vec<(f64, f64)> {
        interior
            .iter()
            .filter_map(|b| Some((b.min.budget, f(b)?)))
            .collect()
    };
    let mut candidates: Vec<LawPoints> = vec![("n_opt_vs_c", "C", "N_opt", along(|b| b.min.opt))];
    if runs.d.is_some() {
        candidates.push(("d_opt_vs_c", "C", "D_opt", along(|b| b.d_opt)));
    } else {
        skipped.push(format!(
            "d_opt_vs_c: no tokens column {:?}",
            opts.columns.d.name
        ));
    }
    match vocabulary_gap(runs, opts) {
        Some(why) => skipped.push(format!("v_opt_vs_c, nv_opt_vs_c, nv_vs_n: {why}")),
        None => {
            candidates.push(("v_opt_vs_c", "C", "V_opt", along(|b| b.v_opt)));
            candidates.push(("nv_opt_vs_c", "C", "N_v_opt", along(|b| b.nv_opt)));
            let at_n = vocab_minima
                .iter()
                .filter_map(|m| Some((m.fixed_n?, m.nv_opt?)))
                .collect();
            candidates.push(("nv_vs_n", "N", "N_v_opt", at_n));
        }
    }
    let budgets_seen = budgets.len();
    let mut laws = BTreeMap::new();
    for (key, x_name, y_name, pts) in candidates {
        if pts.len() < 3 {
            skipped.push(format!(
                "{key} ({y_name} ∝ {x_name}^k): {} usable minima (from {budgets_seen} budget group(s)), need 3",
                pts.len()
            ));
            continue;
        }
        let (x, y): (Vec<f64>, Vec<f64>) = pts.into_iter().unzip();
        match PowerLaw::fit(x_name, y_name, &x, &y) {
            Some(l) => {
                laws.insert(key.to_string(), l);
            }
            None => skipped.push(format!("{key}: the minima share one {x_name}")),
        }
    }
    laws
}

/// Why the vocabulary laws cannot be fitted (`None` when they can be tried).
fn vocabulary_gap(runs: &Runs, opts: &FitOptions) -> Option<String> {
    let cs = &opts.columns;
    let Some(v) = &runs.v else {
        return Some(format!("no vocabulary column {:?}", cs.v.name));
    };
    if runs.width.is_none() {
        return Some(format!(
            "no width ({:?}, or {:?} to divide by V)",
            cs.width.name, cs.nv.name
        ));
    }
    let mut sizes = v.clone();
    sizes.sort_by(f64::total_cmp);
    sizes.dedup();
    (sizes.len() < 3).then(|| {
        let list: Vec<String> = sizes.iter().map(|s| format!("{s}")).collect();
        format!(
            "{} vocabulary size(s) in the table ({}); a minimum over V needs 3",
            sizes.len(),
            list.join(", ")
        )
    })
}

/// The parametric L(N, D) when the runs allow it (else the reason under `skipped`).
fn parametric_fit(
    runs: &Runs,
    opts: &FitOptions,
    skipped: &mut Vec<String>,
    warnings: &mut Vec<String>,
) -> Result<Option<Parametric>, FitError> {
    let (name, pl) = &runs.param_loss;
    let Some(d) = &runs.d else {
        skipped.push(format!(
            "parametric L(N, D): no tokens column {:?}",
            opts.columns.d.name
        ));
        return Ok(None);
    };
    if let Some(row) = pl.iter().position(|&l| l <= 0.0) {
        skipped.push(format!(
            "parametric L(N, D): {name:?} has a non-positive loss ({}) at row {}; fit a positive loss with --param-loss-col",
            pl[row],
            row + 1
        ));
        return Ok(None);
    }
    if runs.len() < 6 {
        skipped.push(format!(
            "parametric L(N, D): {} runs, need at least 6 for 5 parameters",
            runs.len()
        ));
        return Ok(None);
    }
    let p = fit_parametric(&LogRuns::new(&runs.n, d, pl), name, opts)?;
    if p.bootstrap.succeeded < p.bootstrap.resamples {
        warnings.push(format!(
            "parametric bootstrap: {} of {} refits failed",
            p.bootstrap.resamples - p.bootstrap.succeeded,
            p.bootstrap.resamples
        ));
    }
    Ok(Some(p))
}

/// Approach 2 (IsoFLOP minima) against approach 3 (parametric) on the N_opt and D_opt exponents.
fn agreement(laws: &BTreeMap<String, PowerLaw>, p: Option<&Parametric>) -> Vec<Agreement> {
    let Some(p) = p else {
        return Vec::new();
    };
    [
        ("N_opt", "n_opt_vs_c", p.n_opt_exponent),
        ("D_opt", "d_opt_vs_c", p.d_opt_exponent),
    ]
    .into_iter()
    .filter_map(|(quantity, key, parametric)| {
        let isoflop = laws.get(key)?.fit.slope;
        let overlap = match (
            isoflop.ci_low,
            isoflop.ci_high,
            parametric.ci_low,
            parametric.ci_high,
        ) {
            (Some(a), Some(b), Some(c), Some(d)) => Some(a <= d && c <= b),
            _ => None,
        };
        Some(Agreement {
            quantity: quantity.into(),
            isoflop,
            parametric,
            overlap,
        })
    })
    .collect()
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
        parametric::with_draws(value, &vals)
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
        law: LawEstimates::from_fn(est),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fitted::ExchangeForm;
    use crate::parametric::StartGrid;
    use crate::repeated::NaturalLaw;
    use crate::synth::{Law, CHINCHILLA};
    use crate::{data_value, stopping};
    use std::fmt::Write as _;

    /// Writes rows (budget, n_nv, tokens, loss, epochs) as a results CSV and reads it back.
    fn table(dir: &tempfile::TempDir, rows: &[[f64; 5]]) -> Table {
        let mut csv = String::from("budget,n_nv,tokens,test_loss,norm_test_loss,epochs\n");
        for r in rows {
            let _ = writeln!(csv, "{},{},{},{},{},{}", r[0], r[1], r[2], r[3], r[3], r[4]);
        }
        let path = dir.path().join("results.csv");
        std::fs::write(&path, csv).unwrap();
        Table::read(&path).unwrap()
    }

    /// Budgets whose loss falls monotonically in N (`interior` = false) or has a vertex.
    fn budgets(interior: &[bool]) -> Vec<BudgetMinimum> {
        let n = [1e5, 1e6, 1e7, 1e8];
        interior
            .iter()
            .enumerate()
            .map(|(i, &bowl)| {
                let loss: Vec<f64> = n
                    .iter()
                    .map(|x: &f64| match bowl {
                        true => (x.log10() - 6.5).powi(2),
                        false => -x.log10(),
                    })
                    .collect();
                let min = crate::isoflop::parabola_minimum(
                    10f64.powi(i as i32 + 12),
                    "N",
                    None,
                    &n,
                    &loss,
                );
                assert_eq!(min.interior, bowl);
                BudgetMinimum {
                    min,
                    runs: 4,
                    d_opt: None,
                    nv_opt: None,
                    nv_reason: None,
                    v_opt: None,
                }
            })
            .collect()
    }

    #[test]
    fn many_budgets_without_a_minimum_get_one_line_not_one_per_budget() {
        let mut w = Vec::new();
        minima_warnings(&budgets(&[false, false, true, false, false]), &[], &mut w);
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with("not an IsoFLOP grid: 1 of 5 budget groups"),
            "{w:?}"
        );
        let mut w = Vec::new();
        minima_warnings(&budgets(&[true, false, true, true, false]), &[], &mut w);
        assert_eq!(w.len(), 2, "a grid with two bad budgets names each: {w:?}");
        assert!(
            w.iter().all(|l| l.contains("no interior minimum over N")),
            "{w:?}"
        );
        let mut w = Vec::new();
        let partial = [true, false, true, false, true, false, false];
        minima_warnings(&budgets(&partial), &[], &mut w);
        assert_eq!(w.len(), 1, "four bad budgets of seven get one line: {w:?}");
        assert!(
            w[0].starts_with("4 of 7 budget groups have no interior"),
            "{w:?}"
        );
    }

    fn quick() -> FitOptions {
        FitOptions {
            grid: StartGrid::coarse(),
            grid_name: "coarse".into(),
            bootstrap: 40,
            ..FitOptions::default()
        }
    }

    /// Seven sizes per budget, log-spaced over N_opt(C)·10^[−0.6, 0.6], loss from `law`.
    fn isoflop_rows(law: &Law, budgets: &[f64], shift: f64) -> Vec<[f64; 5]> {
        let mut rows = Vec::new();
        for &c in budgets {
            for k in 0..7 {
                let n = law.n_opt(c) * 10f64.powf(-0.6 + 0.2 * k as f64);
                let d = c / (6.0 * n);
                rows.push([c, n, d, law.loss(n * shift, d), 1.0]);
            }
        }
        rows
    }

    #[test]
    fn holdout_budget_is_predicted_inside_its_interval_and_a_moved_optimum_is_caught() {
        let dir = tempfile::tempdir().unwrap();
        let budgets = [1e18, 3e18, 1e19, 3e19, 1e20];
        let opts = FitOptions {
            holdout_budget: Some(1e20),
            ..quick()
        };
        let fits = fit_table(
            &table(&dir, &isoflop_rows(&CHINCHILLA, &budgets, 1.0)),
            &opts,
        )
        .unwrap();
        assert_eq!(fits.budgets.len(), 4, "the held-out budget is not fitted");
        let h = fits.holdout.as_ref().unwrap();
        assert_eq!((h.runs, h.budget), (7, 1e20));
        let n_check = &h.checks[0];
        assert_eq!(n_check.quantity, "N_opt (IsoFLOP law)");
        assert!(
            (n_check.trained / CHINCHILLA.n_opt(1e20) - 1.0).abs() < 0.05,
            "{n_check:?}"
        );
        assert!(
            (n_check.ratio - 1.0).abs() < 0.05 && n_check.inside == Some(true),
            "{n_check:?}"
        );
        let p = h
            .checks
            .iter()
            .find(|c| c.quantity == "N_opt (parametric)")
            .unwrap();
        assert!((p.ratio - 1.0).abs() < 0.05, "{p:?}");
        let best = h
            .checks
            .iter()
            .find(|c| c.quantity == "best loss (parametric)");
        assert!((best.unwrap().ratio - 1.0).abs() < 0.01, "{best:?}");

        // With enough budgets to score every form, the loss is also scored on the chosen one:
        // at the minima Chinchilla's loss is E + k·C^(−γ), the floor form exactly.
        let more = [1e17, 3e17, 1e18, 3e18, 1e19, 3e19, 1e20];
        let fits = fit_table(&table(&dir, &isoflop_rows(&CHINCHILLA, &more, 1.0)), &opts).unwrap();
        assert_eq!(
            fits.loss_shape.as_ref().and_then(|s| s.chosen.as_deref()),
            Some("floor")
        );
        let h = fits.holdout.as_ref().unwrap();
        let floor = h
            .checks
            .iter()
            .find(|c| c.quantity == "loss at N_opt (floor form)")
            .unwrap();
        assert!(
            (floor.ratio - 1.0).abs() < 0.01 && floor.inside.is_none(),
            "{floor:?}"
        );

        // The held-out runs as if their N were 4× larger (their optimum moves about 2× smaller):
        // the prediction must miss it.
        let mut rows = isoflop_rows(&CHINCHILLA, &budgets[..4], 1.0);
        rows.extend(isoflop_rows(&CHINCHILLA, &budgets[4..], 4.0));
        let fits = fit_table(&table(&dir, &rows), &opts).unwrap();
        let n_check = &fits.holdout.as_ref().unwrap().checks[0];
        assert!(
            n_check.ratio > 1.5 && n_check.inside == Some(false),
            "{n_check:?}"
        );

        let none = FitOptions {
            holdout_budget: Some(5e21),
            ..quick()
        };
        let err = fit_table(&table(&dir, &rows), &none)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("no budget group there") && err.contains("1.000e18"),
            "{err}"
        );
    }

    #[test]
    fn data_constrained_fit_recovers_the_exchange_rate_of_synthetic_data() {
        let law = repetition_law();
        let (r_star, rho) = (6.0f64, 0.3f64);
        let dir = tempfile::tempdir().unwrap();
        let loss = |n: f64, d: f64, unique: f64, share: f64| {
            let kk = 1.0 - share + rho * share;
            let (ln_dp, _) = repeated::effective_data(d * kk, unique * kk, r_star.ln());
            law.e + law.a / n.powf(law.alpha) + law.b / ln_dp.exp().powf(law.beta)
        };
        let path = two_source_ladders(dir.path(), |_, _, _| 100_000, loss);
        let opts = FitOptions {
            repeated_data: true,
            ..quick()
        };
        let fits = fit_table(&Table::read(&path).unwrap(), &opts).unwrap();
        let r = fits.repeated_data.as_ref().expect("fitted");
        let exchange = r.exchange.as_ref().expect("two source mixes: ρ is fitted");
        assert!((exchange.value / rho - 1.0).abs() < 0.05, "ρ {exchange:?}");
        assert!(
            (r.r_star.value / r_star - 1.0).abs() < 0.05,
            "R* {:?}",
            r.r_star
        );
        assert!(
            (r.law.beta.value - law.beta).abs() < 0.01,
            "{:?}",
            r.law.beta
        );

        // Budgets and data subsets resampled whole: both clusterings, each interval holding
        // the truth on this exact table.
        let names: Vec<&str> = r
            .block_intervals
            .iter()
            .map(|b| b.clusters.as_str())
            .collect();
        assert_eq!(
            names,
            ["budgets", "data subsets"],
            "{:?}",
            r.block_intervals
        );
        for b in &r.block_intervals {
            assert!(b.count >= 3 && b.refits > 0, "{b:?}");
            assert!(
                b.r_star[0] <= r_star * 1.05 && r_star * 0.95 <= b.r_star[1],
                "{b:?}"
            );
            let [lo, hi] = b.exchange.expect("ρ is fitted");
            assert!(lo <= rho * 1.05 && rho * 0.95 <= hi, "{b:?}");
        }

        // The charts' points: each corpus's lowest loss over the sizes, per budget.
        assert_eq!(r.frontier.len(), 4 * 3, "{:?}", r.frontier);
        let half = r
            .frontier
            .iter()
            .find(|p| {
                (p.budget / 1e14 - 1.0).abs() < 1e-9
                    && p.synth_share == 0.5
                    && p.unique_tokens < 2e7
            })
            .unwrap();
        let lowest = (0..5)
            .map(|k| 10f64.powf(4.0 + 0.5 * k as f64))
            .map(|n| loss(n, 1e14 / (6.0 * n), 1e7, 0.5))
            .fold(f64::INFINITY, f64::min);
        assert!((half.unique_tokens / 1e7 - 1.0).abs() < 1e-9 && half.loss == lowest);
        let charts = crate::report::charts(&fits);
        let chart = |stem: &str| &charts.iter().find(|(s, _)| s == stem).unwrap().1;
        let raw = chart("data_loss_vs_hours");
        assert_eq!(raw.x_label, "unique data (tokens)", "no hours column");
        // Mixed corpora move to U·(1 − s + ρ·s); captured-only ones stay.
        let xs = |c: &plot::Chart, name: &str| -> Vec<f64> {
            let s = c.series.iter().find(|s| s.name == name).unwrap();
            s.points.iter().map(|p| p.0).collect()
        };
        let k = 1.0 - 0.5 + exchange.value * 0.5;
        let moved = chart("data_exchange_rate");
        assert_eq!(xs(moved, "C = 10¹⁴, mixed"), [1e7 * k, 4e7 * k]);
        assert_eq!(xs(moved, "C = 10¹⁴, captured only"), [5e6, 2e7]);
        assert_eq!(xs(raw, "C = 10¹⁴, mixed"), [1e7, 4e7]);
    }

    #[test]
    fn data_constrained_fit_recovers_r_star_d_r_star_n_and_the_exchange_rate() {
        let law = repetition_law();
        // (E, A, B, α, β, R*_D, ρ, R*_N): U_N ≈ 7e-3·U_D^0.86, 1.2e4 for 2e7 unique tokens, so
        // the larger sizes are far past it.
        let truth = repetition_theta(6.0, 0.3, 5.0);
        let dir = tempfile::tempdir().unwrap();
        let path = two_source_ladders(
            dir.path(),
            |_, _, _| 100_000,
            |n, d, unique, share| token_worth(truth).loss(n, d, unique, share),
        );
        let opts = FitOptions {
            repeated_data: true,
            effective_params: true,
            ..quick()
        };
        let fits = fit_table(&Table::read(&path).unwrap(), &opts).unwrap();
        let r = fits.repeated_data.as_ref().expect("fitted");
        let r_star_n = r.r_star_n.as_ref().expect("R*_N is fitted");
        assert!(r.past_base_size > 20 && r.note_n.is_none(), "{r:?}");
        for (name, got, want) in [
            ("R*_D", r.r_star.value, 6.0),
            ("R*_N", r_star_n.value, 5.0),
            ("ρ", r.exchange.as_ref().unwrap().value, 0.3),
        ] {
            assert!((got / want - 1.0).abs() < 0.05, "{name}: {got} vs {want}");
        }
        assert!((r.law.alpha.value - law.alpha).abs() < 0.01, "{:?}", r.law);
    }

    #[test]
    fn early_stopping_recovers_the_stopping_rule_and_predicts_the_plateau() {
        let truth = repetition_theta(6.0, 0.3, f64::INFINITY);
        // e* = 100·N^−0.35·U^0.05: 8.6 epochs at N = 10⁴, 1.7 at 10⁶ (U = 5·10⁶); runs stop
        // early at every budget, so that each budget left out keeps a rule to predict it by.
        let rule = [100f64.ln(), -0.35, 0.05];
        let select = |n: f64, d: f64, unique: f64| {
            let stop = stopping::stop_epochs(&rule, n, unique) * unique;
            (1e5 * (stop / d).min(1.0)).round().max(1.0) as u32
        };
        let dir = tempfile::tempdir().unwrap();
        let path = two_source_ladders(dir.path(), select, |n, d, unique, share| {
            token_worth(truth).loss(n, d, unique, share)
        });
        let opts = FitOptions {
            repeated_data: true,
            early_stopping: true,
            ..quick()
        };
        let fits = fit_table(&Table::read(&path).unwrap(), &opts).unwrap();
        let mut r = fits.repeated_data.clone().expect("fitted");
        let s = r
            .stopping
            .as_ref()
            .expect("early stopping: the rule is fitted");
        // The steps are whole, so e* is recovered to their rounding.
        assert!(
            (s.coef[1] - rule[1]).abs() < 0.01,
            "{:?} vs {rule:?}",
            s.coef
        );
        for (n, unique) in [(1e4, 5e6), (1e5, 1e7), (1e6, 4e7)] {
            let (got, want) = (
                stopping::stop_epochs(&s.coef, n, unique),
                stopping::stop_epochs(&rule, n, unique),
            );
            assert!(
                (got / want - 1.0).abs() < 0.01,
                "e* at N = {n}: {got} vs {want}"
            );
        }
        assert!(s.runs == 37 && s.draws.len() == r.draws.len(), "{s:?}");
        let rho = r.exchange.as_ref().unwrap().value;
        assert!((r.r_star.value / 6.0 - 1.0).abs() < 0.05, "{:?}", r.r_star);
        assert!((rho / 0.3 - 1.0).abs() < 0.05, "ρ {rho}");
        let h = r.held_out.as_ref().unwrap();
        assert!(
            h.repeated_rms < 0.01,
            "held out at the rule's tokens: {h:?}"
        );
        // Past the budget where the optimum stops improving, compute buys nothing, and an hour
        // of captured motion is worth more than any compute.
        r.tokens_per_hour = Some(1e6);
        let hours = data_value::Hours {
            real: 5.0,
            synth: 0.0,
        };
        let at = |c: f64| data_value::predict_data(&r, c, hours).unwrap();
        let (p16, p18) = (at(1e16), at(1e18));
        assert!(
            (p18.loss.value / p16.loss.value - 1.0).abs() < 1e-9,
            "{p16:?}"
        );
        assert!(p18.epochs.value > p18.stop_epochs.as_ref().unwrap().value);
        assert!(p18.verdicts.iter().any(|v| v.contains("buys nothing")));
        let real = &p18.hour_values[0];
        assert!(real.loss_change.value < 0.0 && real.compute_equivalent.value.is_infinite());
    }

    /// A captured-only ladder and a half-synthetic one, each at two corpus sizes, 3 budgets ×
    /// 5 sizes, with `loss(N, D, U, synthetic share)` at the selected checkpoint, which lies at
    /// step `select(N, D, U)` of 100,000, written to `dir/results.csv`.
    fn two_source_ladders(
        dir: &std::path::Path,
        select: impl Fn(f64, f64, f64) -> u32,
        loss: impl Fn(f64, f64, f64, f64) -> f64,
    ) -> std::path::PathBuf {
        let mut csv = String::from(
            "budget,n_nv,tokens,test_loss,norm_test_loss,epochs,synth_share,best_step,steps\n",
        );
        for (unique, share) in [(5e6, 0.0), (2e7, 0.0), (1e7, 0.5), (4e7, 0.5)] {
            for c in [1e13, 1e14, 1e15] {
                for k in 0..5 {
                    let n = 10f64.powf(4.0 + 0.5 * k as f64);
                    let d = c / (6.0 * n);
                    let step = select(n, d, unique);
                    let l = loss(n, d * f64::from(step) / 1e5, unique, share);
                    let _ = writeln!(
                        csv,
                        "{c},{n},{d},{l},{l},{},{share},{step},100000",
                        d / unique
                    );
                }
            }
        }
        let path = dir.join("results.csv");
        std::fs::write(&path, csv).unwrap();
        path
    }

    /// The token-worth law of natural parameters `theta`.
    fn token_worth(theta: [f64; 8]) -> NaturalLaw {
        NaturalLaw {
            theta,
            form: ExchangeForm::TokenWorth,
        }
    }

    /// On runs whose repetitions count against the effective pool (ρ = 0.35), the token-worth
    /// form misreads ρ; with both forms fitted, the effective pool has the lower error on the
    /// data subsets left out, is adopted, and recovers ρ.
    #[test]
    fn both_exchange_forms_fitted_adopt_the_form_the_runs_follow() {
        let truth = NaturalLaw {
            theta: repetition_theta(6.0, 0.35, f64::INFINITY),
            form: ExchangeForm::EffectivePool,
        };
        let dir = tempfile::tempdir().unwrap();
        let path = two_source_ladders(
            dir.path(),
            |_, _, _| 100_000,
            |n, d, unique, share| truth.loss(n, d, unique, share),
        );
        let fit = |forms: Vec<ExchangeForm>| {
            let opts = FitOptions {
                repeated_data: true,
                exchange_forms: forms,
                ..quick()
            };
            let fits = fit_table(&Table::read(&path).unwrap(), &opts).unwrap();
            fits.repeated_data.expect("fitted")
        };
        let one = fit(vec![ExchangeForm::TokenWorth]);
        let misread = one.exchange.as_ref().unwrap().value;
        assert!(
            (misread / 0.35 - 1.0).abs() > 0.2,
            "token worth: ρ {misread}"
        );
        assert!(one.exchange_forms.is_empty(), "one form: nothing scored");
        let both = fit(vec![ExchangeForm::TokenWorth, ExchangeForm::EffectivePool]);
        assert_eq!(both.exchange_form, ExchangeForm::EffectivePool);
        let rho = both.exchange.as_ref().unwrap().value;
        assert!((rho / 0.35 - 1.0).abs() < 0.05, "effective pool: ρ {rho}");
        let errors: Vec<(ExchangeForm, f64, usize)> = both
            .exchange_forms
            .iter()
            .map(|s| {
                let h = s.held_out.as_ref().expect("4 data subsets: scored");
                assert_eq!(h.clusters, "data subsets");
                (s.form, h.rms, h.folds)
            })
            .collect();
        assert_eq!(errors[0].0, ExchangeForm::EffectivePool);
        assert!(
            errors[0].1 < 1e-3 && errors[1].1 > 2.0 * errors[0].1,
            "{errors:?}"
        );
        assert_eq!(errors[0].2, 4);
    }

    /// Runs scattered about the law (log SD 0.03): its 95% prediction intervals hold the best
    /// loss of nearly every cell, the scatter they add is the runs', and a prediction's
    /// interval for one run is wider than the law's own.
    #[test]
    fn prediction_intervals_hold_the_runs_the_law_was_fitted_on() {
        let truth = token_worth(repetition_theta(6.0, 0.3, f64::INFINITY));
        let rng = std::cell::RefCell::new(motionscale_core::rng::SplitMix64::stream(7, 0));
        let dir = tempfile::tempdir().unwrap();
        let path = two_source_ladders(
            dir.path(),
            |_, _, _| 100_000,
            |n, d, unique, share| {
                truth.loss(n, d, unique, share) * (0.03 * rng.borrow_mut().normal()).exp()
            },
        );
        let mut text = std::fs::read_to_string(&path).unwrap().replace(
            "synth_share,best_step,steps\n",
            "synth_share,best_step,steps,hours\n",
        );
        // Hours: 10⁶ unique tokens an hour.
        text = text
            .lines()
            .map(
                |l| match l.split(',').nth(5).and_then(|e| e.parse::<f64>().ok()) {
                    Some(epochs) => {
                        let d: f64 = l.split(',').nth(2).unwrap().parse().unwrap();
                        format!("{l},{}\n", d / epochs / 1e6)
                    }
                    None => format!("{l}\n"),
                },
            )
            .collect();
        std::fs::write(&path, text).unwrap();
        let opts = FitOptions {
            repeated_data: true,
            bootstrap: 40,
            ..quick()
        };
        let fits = fit_table(&Table::read(&path).unwrap(), &opts).unwrap();
        let r = fits.repeated_data.expect("fitted");
        let c = r.in_sample.as_ref().expect("information and hours: scored");
        assert_eq!(c.cells, 12, "4 data sets × 3 budgets");
        assert!(c.covered >= 11, "{c:?}");
        assert!((0.015..0.045).contains(&c.scatter), "{c:?}");
        let h = data_value::Hours {
            real: 20.0,
            synth: 10.0,
        };
        let p = data_value::predict_data(&r, 1e15, h).unwrap();
        let run = p.loss_prediction.as_ref().expect("a run's interval");
        let (lo, hi) = (run.ci_low.unwrap(), run.ci_high.unwrap());
        assert!(
            lo < p.loss.ci_low.unwrap() && hi > p.loss.ci_high.unwrap(),
            "{run:?} vs {:?}",
            p.loss
        );
        assert!((hi / lo).ln() > 3.0 * 0.03, "{run:?}");
    }

    /// The repetition law's natural parameters (E, A, B, α, β) with R*_D, ρ and R*_N.
    fn repetition_theta(r_star_d: f64, rho: f64, r_star_n: f64) -> [f64; 8] {
        let l = repetition_law();
        [l.e, l.a, l.b, l.alpha, l.beta, r_star_d, rho, r_star_n]
    }

    /// The law the data-constrained tests draw their runs from.
    fn repetition_law() -> Law {
        Law {
            e: 1.2,
            a: 60.0,
            b: 400.0,
            alpha: 0.35,
            beta: 0.3,
        }
    }

    #[test]
    fn data_constrained_fit_recovers_r_star_and_wins_on_held_out_budgets() {
        let law = repetition_law();
        let (unique, r_star) = (2e7, 6.0f64);
        let mut rows = Vec::new();
        for c in [1e13, 3e13, 1e14, 3e14, 1e15] {
            for k in 0..7 {
                let n = 10f64.powf(4.0 + 0.33 * k as f64);
                let d = c / (6.0 * n);
                let (ln_dp, _) = repeated::effective_data(d, unique, r_star.ln());
                let loss = law.e + law.a / n.powf(law.alpha) + law.b / ln_dp.exp().powf(law.beta);
                rows.push([c, n, d, loss, d / unique]);
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let opts = FitOptions {
            repeated_data: true,
            ..quick()
        };
        let fits = fit_table(&table(&dir, &rows), &opts).unwrap();
        let r = fits.repeated_data.as_ref().expect("fitted");
        assert!(r.max_epochs > 100.0 && r.repeated_runs > 10, "{r:?}");
        assert_eq!(r.exchange, None, "one source: no exchange rate");
        assert!(
            (r.r_star.value / r_star - 1.0).abs() < 0.02,
            "R* {:?}",
            r.r_star
        );
        assert!(
            (r.law.alpha.value - law.alpha).abs() < 0.01
                && (r.law.beta.value - law.beta).abs() < 0.01
        );
        assert!((r.law.e.value - law.e).abs() < 0.01, "{:?}", r.law.e);
        let h = r.held_out.as_ref().unwrap();
        assert_eq!((h.folds, h.better.as_str()), (5, "repeated"), "{h:?}");
        assert!(h.repeated_rms < 0.2 * h.plain_rms, "{h:?}");

        // Repeated data that costs nothing (the plain law): R* runs off, and is reported as
        // not identified, without an interval.
        let free: Vec<[f64; 5]> = rows
            .iter()
            .map(|r| [r[0], r[1], r[2], law.loss(r[1], r[2]), r[4]])
            .collect();
        let fits = fit_table(&table(&dir, &free), &opts).unwrap();
        let r = fits.repeated_data.as_ref().unwrap();
        assert!(r.note.as_ref().unwrap().contains("not identified"), "{r:?}");
        assert_eq!(r.r_star.ci_low, None);

        // Without any repetition R* is not fitted, and the skip says why.
        let once: Vec<[f64; 5]> = rows.iter().map(|r| [r[0], r[1], r[2], r[3], 0.5]).collect();
        let fits = fit_table(&table(&dir, &once), &opts).unwrap();
        assert!(fits.repeated_data.is_none());
        assert!(
            fits.skipped
                .iter()
                .any(|s| s.contains("no run repeats data")),
            "{:?}",
            fits.skipped
        );
    }

    #[test]
    fn one_budget_and_one_vocabulary_say_which_laws_cannot_be_fitted() {
        let dir = tempfile::tempdir().unwrap();
        let rows = isoflop_rows(&CHINCHILLA, &[1e19], 1.0);
        let mut csv =
            String::from("budget,n_nv,n_v,vocab,d_model,tokens,test_loss,norm_test_loss\n");
        for r in &rows {
            let _ = writeln!(
                csv,
                "{},{},{},{},{},{},{},{}",
                r[0],
                r[1],
                1024.0 * 64.0,
                1024,
                64,
                r[2],
                r[3],
                r[3]
            );
        }
        let path = dir.path().join("one.csv");
        std::fs::write(&path, csv).unwrap();
        let fits = fit_table(&Table::read(&path).unwrap(), &quick()).unwrap();
        assert!(fits.parametric.is_some(), "the parametric fit still runs");
        let said = |needle: &str| fits.skipped.iter().any(|s| s.contains(needle));
        assert!(
            said("n_opt_vs_c (N_opt ∝ C^k): 1 usable minima (from 1 budget group(s))"),
            "{:?}",
            fits.skipped
        );
        assert!(
            said("log law: 1 interior IsoFLOP minima in 1 budget group(s)"),
            "{:?}",
            fits.skipped
        );
        assert!(
            said("1 vocabulary size(s) in the table (1024); a minimum over V needs 3"),
            "{:?}",
            fits.skipped
        );
        let total = fits
            .total_n
            .as_ref()
            .expect("the total-parameter convention is fitted too");
        assert_eq!(total.input.columns["N"].as_deref(), Some("n_nv + n_v"));
    }

    #[test]
    fn seeds_are_averaged_for_the_minima_and_their_noise_reported() {
        let dir = tempfile::tempdir().unwrap();
        let rows = isoflop_rows(&CHINCHILLA, &[1e18, 1e19, 1e20], 1.0);
        let mut csv = String::from("budget,n_nv,tokens,test_loss,norm_test_loss,seed\n");
        for r in &rows {
            let _ = writeln!(csv, "{},{},{},{},{},0", r[0], r[1], r[2], r[3], r[3]);
        }
        // Two more seeds at the middle size of 1e19, 0.03 and 0.06 above seed 0.
        let mid = rows[10];
        for (seed, extra) in [(1, 0.03), (2, 0.06)] {
            let l = mid[3] + extra;
            let _ = writeln!(csv, "{},{},{},{l},{l},{seed}", mid[0], mid[1], mid[2]);
        }
        let path = dir.path().join("seeds.csv");
        std::fs::write(&path, csv).unwrap();
        let fits = fit_table(&Table::read(&path).unwrap(), &quick()).unwrap();
        let noise = &fits.seed_noise;
        assert_eq!(noise.len(), 1, "{noise:?}");
        assert_eq!((noise[0].budget, noise[0].n), (1e19, mid[1]));
        assert_eq!(noise[0].seeds, vec![0.0, 1.0, 2.0]);
        assert!((noise[0].mean - (mid[3] + 0.03)).abs() < 1e-12);
        assert!((noise[0].sd - 0.03).abs() < 1e-12, "{:?}", noise[0]);
        assert!(noise[0].resolved_gap.unwrap() > 0.0);
        // The minimum at 1e19 sees the mean of the three seeds, not the lowest.
        let b = &fits.budgets[1];
        let at_mid = b.min.points.iter().find(|p| p[0] == mid[1]).unwrap();
        assert!((at_mid[1] - (mid[3] + 0.03)).abs() < 1e-12, "{at_mid:?}");
        assert_eq!(fits.budgets[0].min.points.len(), 7);
    }

    #[test]
    fn approaches_two_and_three_agree_on_a_clean_law() {
        let dir = tempfile::tempdir().unwrap();
        let budgets = [1e18, 3e18, 1e19, 3e19, 1e20, 3e20];
        let fits = fit_table(
            &table(&dir, &isoflop_rows(&CHINCHILLA, &budgets, 1.0)),
            &quick(),
        )
        .unwrap();
        let n = fits
            .agreement
            .iter()
            .find(|a| a.quantity == "N_opt")
            .unwrap();
        assert!(
            (n.isoflop.value - CHINCHILLA.n_exponent()).abs() < 0.01,
            "{n:?}"
        );
        assert!(
            (n.parametric.value - CHINCHILLA.n_exponent()).abs() < 0.01,
            "{n:?}"
        );
        assert_eq!(n.overlap, Some(true));
        assert!(
            fits.warnings.iter().all(|w| !w.contains("disagree")),
            "{:?}",
            fits.warnings
        );
    }
}
