//! A budget held out of the fit and predicted: the laws fitted on the other budgets predict
//! its N_opt and loss (with their 95% intervals), and its own runs say what training found.

use crate::fitted::{Fits, Holdout, HoldoutCheck, Parametric};
use crate::isoflop::{self};
use crate::laws::Estimate;
use crate::predict::parametric_at;
use crate::runs::Runs;
use crate::FitError;

/// Row indices of `runs` outside and inside the budget group at `c` (within `tol_dex`, at
/// least 0.05 dex); an error names the budgets there are.
pub fn split(runs: &Runs, c: f64, tol_dex: f64) -> Result<(Vec<usize>, Vec<usize>), FitError> {
    let bad = |problem: String| FitError::BadOption {
        flag: format!("--holdout-budget {c:.3e}"),
        problem,
    };
    if !(c.is_finite() && c > 0.0) {
        return Err(bad("must be a positive number of FLOPs".into()));
    }
    let groups = isoflop::group_rows(&runs.c, runs.group.as_deref(), tol_dex);
    let budgets: Vec<f64> = groups
        .iter()
        .map(|g| isoflop::group_budget(&runs.c, g))
        .collect();
    let close = |b: f64| (b.log10() - c.log10()).abs() <= tol_dex.max(0.05);
    let Some(held) = budgets.iter().position(|&b| close(b)) else {
        let list: Vec<String> = budgets.iter().map(|b| format!("{b:.3e}")).collect();
        return Err(bad(format!(
            "no budget group there (budgets: {})",
            list.join(", ")
        )));
    };
    let kept = groups
        .iter()
        .enumerate()
        .filter(|&(i, _)| i != held)
        .flat_map(|(_, g)| g.iter().copied())
        .collect();
    Ok((kept, groups[held].clone()))
}

/// Scores the laws in `fits` (fitted without `held`) on the held-out runs.
pub fn score(held: &Runs, fits: &Fits) -> Result<Holdout, FitError> {
    let all: Vec<usize> = (0..held.len()).collect();
    let budget = isoflop::group_budget(&held.c, &all);
    let trained = isoflop::parabola_minimum(budget, "N", None, &held.n, &held.loss);
    let best = (0..held.len())
        .min_by(|&i, &j| held.loss[i].total_cmp(&held.loss[j]))
        .ok_or_else(|| FitError::Invalid("the held-out budget has no runs".into()))?;
    let mut checks = Vec::new();
    let mut missing = Vec::new();
    let trained_n = match (trained.interior, trained.opt) {
        (true, Some(n)) => Some(n),
        _ => {
            missing.push(format!(
                "N_opt: the held-out runs have no interior minimum ({})",
                trained.reason.as_deref().unwrap_or("?")
            ));
            None
        }
    };
    let mut push = |quantity: &str,
                    predicted: Option<Estimate>,
                    trained: Option<f64>,
                    note: &str| match (predicted, trained) {
        (Some(predicted), Some(trained)) => checks.push(check(quantity, predicted, trained, note)),
        (None, _) => missing.push(format!(
            "{quantity}: the fit without this budget has no such law"
        )),
        (Some(_), None) => {}
    };
    push(
        "N_opt (IsoFLOP law)",
        fits.power_laws.get("n_opt_vs_c").map(|l| l.predict_at(budget)),
        trained_n,
        "N_opt ∝ C^b of the other budgets, 95% prediction interval (the law's residual scatter included), vs the vertex of the held-out budget's own parabola",
    );
    push(
        "loss at N_opt (log law)",
        fits.log_law.as_ref().map(|l| l.predict_at(budget)),
        trained.loss_opt.filter(|_| trained.interior),
        "the log law of the other budgets, 95% prediction interval, vs the held-out parabola's minimum (the loss column)",
    );
    // The form leave-one-budget-out chose, where it is not the log law (no interval).
    if let Some(form) = fits
        .loss_shape
        .as_ref()
        .and_then(|s| s.chosen_fit())
        .filter(|f| f.form != "log")
    {
        push(
            &format!("loss at N_opt ({} form)", form.form),
            Some(Estimate::exact(form.at(budget.log10()))),
            trained.loss_opt.filter(|_| trained.interior),
            "the form of the loss law the other budgets chose by leave-one-budget-out error (no interval) vs the held-out parabola's minimum",
        );
    }
    let param = fits
        .parametric
        .as_ref()
        .map(|p| (p, parametric_at(p, budget)));
    // The held-out vertex is itself uncertain: its t interval widens the bootstrap one.
    let vertex_spread = trained
        .log10_opt
        .and_then(|e| Some(e.ci_high? - e.value))
        .unwrap_or(0.0);
    push(
        "N_opt (parametric)",
        param.as_ref().map(|(_, q)| widen(q.n_opt, vertex_spread)),
        trained_n,
        "the parametric fit's compute-optimal N under C = 6·N·D (bootstrap interval widened by the held-out vertex's own 95% interval) vs the held-out parabola's vertex",
    );
    // The smoothed best loss of the parametric column (the lowest run's loss is biased low:
    // it is selected by its noise).
    let param_min = isoflop::parabola_minimum(budget, "N", None, &held.n, &held.param_loss.1);
    push(
        "best loss (parametric)",
        param.as_ref().map(|(p, q)| widen(q.loss, run_scatter(p))),
        param_min.loss_opt.filter(|_| param_min.interior),
        "L(N_opt, D_opt) of the parametric fit (bootstrap interval widened by 1.96 × the fit's RMS log residual) vs the minimum of a parabola over the held-out runs' parametric loss column",
    );
    Ok(Holdout {
        budget,
        runs: held.len(),
        trained,
        best_run: [held.n[best], held.loss[best]],
        checks,
        missing,
    })
}

/// 1.96 × the RMS log residual of the parametric fit, in log10: the scatter of one run's loss.
fn run_scatter(p: &Parametric) -> f64 {
    let r = &p.residuals_log;
    let rms = (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt();
    1.96 * rms / std::f64::consts::LN_10
}

/// `e` with each end of its interval moved out, in log10, by `extra` added in quadrature.
fn widen(e: Estimate, extra: f64) -> Estimate {
    let out = |end: Option<f64>, sign: f64| {
        end.map(|v| {
            let h = (e.value.log10() - v.log10()).abs();
            10f64.powf(e.value.log10() + sign * (h * h + extra * extra).sqrt())
        })
    };
    Estimate {
        ci_low: out(e.ci_low, -1.0),
        ci_high: out(e.ci_high, 1.0),
        ..e
    }
}

fn check(quantity: &str, predicted: Estimate, trained: f64, note: &str) -> HoldoutCheck {
    HoldoutCheck {
        quantity: quantity.into(),
        predicted,
        trained,
        ratio: predicted.value / trained,
        inside: match (predicted.ci_low, predicted.ci_high) {
            (Some(lo), Some(hi)) => Some(lo <= trained && trained <= hi),
            _ => None,
        },
        note: note.into(),
    }
}
