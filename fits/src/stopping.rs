//! Early stopping in the data-constrained law. A run on repeated data stops improving on
//! validation after a number of epochs that falls with its size (6–16 on the data-law ladder,
//! whatever its schedule's length), and the loss a sweep reports is the selected checkpoint's.
//! Fed the whole run's tokens, Muennighoff et al.'s law (2023) reads that plateau as repetition
//! still worth something; fed the selected checkpoint's tokens, it spends every FLOP on fresh
//! repetitions. The two-part law keeps both: the law on the selected tokens, and a stopping
//! rule ln e* = c₀ + c_N·ln N + c_U·ln U (OLS over the runs that stopped before the end of
//! their schedule), so that a run of D tokens is predicted at min(D, e*·U).

use crate::fitted::StoppingRule;
use crate::ols::{distinct, Ols};
use crate::FitError;

/// A selected step before this share of a run's steps counts as stopped early.
pub const STOPPED_BEFORE: f64 = 0.98;

/// The runs as the stopping rule sees them.
#[derive(Debug, Clone, PartialEq)]
pub struct StopRuns {
    ln_n: Vec<f64>,
    ln_u: Vec<f64>,
    /// ln of the epochs at the selected checkpoint.
    ln_epochs: Vec<f64>,
    stopped: Vec<bool>,
}

impl StopRuns {
    /// From N, U, the run's epochs and the share of its steps at the selected checkpoint.
    pub fn new(n: &[f64], u: &[f64], epochs: &[f64], selected: &[f64]) -> Self {
        Self {
            ln_n: n.iter().map(|v| v.ln()).collect(),
            ln_u: u.iter().map(|v| v.ln()).collect(),
            ln_epochs: epochs
                .iter()
                .zip(selected)
                .map(|(e, s)| (e * s).ln())
                .collect(),
            stopped: selected.iter().map(|&s| s < STOPPED_BEFORE).collect(),
        }
    }

    /// The rule fitted on the rows `idx` (repeats allowed) that stopped early: with c_U = 0
    /// where their U does not vary. `None` below 5 such rows or at fewer than 2 sizes.
    pub fn fit(&self, idx: &[usize]) -> Option<(Ols, [f64; 3])> {
        let rows: Vec<usize> = idx.iter().copied().filter(|&i| self.stopped[i]).collect();
        let pick = |v: &[f64]| rows.iter().map(|&i| v[i]).collect::<Vec<f64>>();
        let (ln_n, ln_u) = (pick(&self.ln_n), pick(&self.ln_u));
        if rows.len() < 5 || distinct(&ln_n) < 2 {
            return None;
        }
        let with_u = distinct(&ln_u) >= 2;
        let x: Vec<Vec<f64>> = (0..rows.len())
            .map(|k| match with_u {
                true => vec![1.0, ln_n[k], ln_u[k]],
                false => vec![1.0, ln_n[k]],
            })
            .collect();
        let ols = Ols::fit(&x, &pick(&self.ln_epochs))?;
        let coef = [
            ols.coef[0],
            ols.coef[1],
            ols.coef.get(2).copied().unwrap_or(0.0),
        ];
        coef.iter().all(|c| c.is_finite()).then_some((ols, coef))
    }

    /// The rule on every run, as recorded (its bootstrap refits added by the caller).
    pub fn rule(&self) -> Result<StoppingRule, FitError> {
        let all: Vec<usize> = (0..self.ln_n.len()).collect();
        let (ols, coef) = self.fit(&all).ok_or_else(|| FitError::CannotFit {
            fit: "the stopping rule",
            needs:
                "at least 5 runs that stopped before the end of their schedule, at 2 or more sizes"
                    .into(),
        })?;
        let se = |i: usize| ols.se(i).unwrap_or(0.0);
        let n = ols.residuals.len();
        let rss: f64 = ols.residuals.iter().map(|r| r * r).sum();
        Ok(StoppingRule {
            coef,
            se: [se(0), se(1), if ols.coef.len() > 2 { se(2) } else { 0.0 }],
            runs: n,
            residual_sd: (rss / ols.dof.max(1) as f64).sqrt(),
            draws: Vec::new(),
        })
    }
}

/// e*, the epochs over U unique tokens after which a run of N parameters stops improving.
pub fn stop_epochs(coef: &[f64; 3], n: f64, u: f64) -> f64 {
    (coef[0] + coef[1] * n.ln() + coef[2] * u.ln()).exp()
}

/// The tokens a run of N parameters on D tokens of U unique ones trains before it stops
/// improving: min(D, e*·U).
pub fn tokens_used(coef: &[f64; 3], n: f64, d: f64, u: f64) -> f64 {
    d.min(stop_epochs(coef, n, u) * u)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rule_is_fitted_on_the_runs_that_stopped_early_and_caps_the_tokens() {
        // e* = 1000·N^−0.3·U^0.1; the runs that ran out of steps first (selected at their end)
        // say only that e* is larger, and are left out.
        let coef = [1000f64.ln(), -0.3, 0.1];
        let (mut n, mut u, mut epochs, mut selected) = (vec![], vec![], vec![], vec![]);
        for (k, &size) in [1e4, 3e4, 1e5, 3e5, 1e6].iter().enumerate() {
            for (j, &unique) in [1e5, 4e5].iter().enumerate() {
                let planned = [5.0, 400.0][(k + j) % 2];
                let stop = stop_epochs(&coef, size, unique);
                n.push(size);
                u.push(unique);
                epochs.push(planned);
                selected.push((stop / planned).min(1.0));
            }
        }
        let runs = StopRuns::new(&n, &u, &epochs, &selected);
        let rule = runs.rule().unwrap();
        for (got, want) in rule.coef.iter().zip(coef) {
            assert!((got - want).abs() < 1e-9, "{:?} vs {coef:?}", rule.coef);
        }
        assert_eq!(
            rule.runs, 5,
            "only the runs planned for 400 epochs stopped early"
        );
        let d = 100.0 * 1e5;
        assert!(
            (tokens_used(&coef, 1e5, d, 1e5) / (stop_epochs(&coef, 1e5, 1e5) * 1e5) - 1.0).abs()
                < 1e-12
        );
        assert_eq!(
            tokens_used(&coef, 1e5, 2e5, 1e5),
            2e5,
            "a short run uses all its tokens"
        );
        // Four stopped runs are too few.
        let few = StopRuns::new(&n[..8], &u[..8], &epochs[..8], &selected[..8]);
        assert!(few
            .rule()
            .unwrap_err()
            .to_string()
            .contains("at least 5 runs"));
    }
}
