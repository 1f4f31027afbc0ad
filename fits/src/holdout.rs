//! A budget held out of the fit and predicted: the laws fitted on the other budgets predict
//! its N_opt and loss (with their 95% intervals), and its own runs say what training found.

use crate::analysis::Fits;
use crate::isoflop::{self, IsoMinimum};
use crate::laws::Estimate;
use crate::predict::{predict, Laws, PredictOptions};
use crate::runs::Runs;
use crate::FitError;
use serde::{Deserialize, Serialize};

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

/// Row indices of `runs` outside and inside the budget group at `c` (within `tol_dex`, at
/// least 0.05 dex); an error names the budgets there are.
pub fn split(runs: &Runs, c: f64, tol_dex: f64) -> Result<(Vec<usize>, Vec<usize>), String> {
    if !(c.is_finite() && c > 0.0) {
        return Err(format!(
            "--holdout-budget {c}: must be a positive number of FLOPs"
        ));
    }
    let groups = isoflop::group_rows(&runs.c, runs.group.as_deref(), tol_dex);
    let budgets: Vec<f64> = groups
        .iter()
        .map(|g| isoflop::group_budget(&runs.c, g))
        .collect();
    let close = |b: f64| (b.log10() - c.log10()).abs() <= tol_dex.max(0.05);
    let Some(held) = budgets.iter().position(|&b| close(b)) else {
        let list: Vec<String> = budgets.iter().map(|b| format!("{b:.3e}")).collect();
        return Err(format!(
            "--holdout-budget {c:.3e}: no budget group there (budgets: {})",
            list.join(", ")
        ));
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
    let best_param_loss = held
        .param_loss
        .1
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min);
    let laws = Laws::from_fits(fits, "the fit without the held-out budget");
    let mut checks = Vec::new();
    let mut missing = Vec::new();
    let mut notes = Vec::new();
    let p = match predict(
        &laws,
        &PredictOptions {
            budget,
            width: None,
            vocab: None,
        },
    ) {
        Ok(p) => Some(p),
        Err(e) => {
            missing.push(e.to_string());
            None
        }
    };
    let trained_n = match (trained.interior, trained.opt) {
        (true, Some(n)) => Some(n),
        _ => {
            notes.push(format!(
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
    let p = p.as_ref();
    push(
        "N_opt (IsoFLOP law)",
        p.and_then(|p| p.n_nv),
        trained_n,
        "N_opt ∝ C^b of the other budgets vs the vertex of the held-out budget's own parabola",
    );
    push(
        "loss at N_opt (log law)",
        p.and_then(|p| p.loss),
        trained.loss_opt.filter(|_| trained.interior),
        "the log law of the other budgets vs the held-out parabola's minimum (the loss column)",
    );
    let param = p.and_then(|p| p.parametric.as_ref());
    push(
        "N_opt (parametric)",
        param.map(|q| q.n_opt),
        trained_n,
        "the parametric fit's compute-optimal N under C = 6·N·D vs the held-out parabola's vertex",
    );
    push(
        "lowest loss (parametric)",
        param.map(|q| q.loss),
        Some(best_param_loss),
        "L(N_opt, D_opt) of the parametric fit vs the held-out budget's lowest loss (the parametric loss column)",
    );
    missing.extend(notes);
    Ok(Holdout {
        budget,
        runs: held.len(),
        trained,
        best_run: [held.n[best], held.loss[best]],
        checks,
        missing,
    })
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
