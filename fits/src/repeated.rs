//! The data-constrained law of Muennighoff et al. (2023): repeated tokens are worth less than
//! fresh ones. With U unique tokens seen for D tokens in all, R = D/U − 1 repetitions and the
//! effective data D' = U + U·R*·(1 − e^(−R/R*)) replaces D in L(N, D) = E + A/N^α + B/D'^β.
//! R* (the repetitions after which extra epochs are worth 1/e of fresh data) is fitted with the
//! other five parameters (Huber on log residuals, L-BFGS, bootstrap intervals), and both this
//! fit and the plain one are scored on each budget left out in turn.
//!
//! With a second source, the exchange rate ρ (effective captured tokens per synthetic token)
//! is fitted too: a run whose unique data is a share s synthetic counts U·k and D·k with
//! k = 1 − s + ρ·s (each epoch passes over both sources; R is unchanged), so that
//! ln D' gains ln k. It is identified only when the runs' synthetic shares differ.

use crate::fitted::{FitOptions, Fits, HeldOutError, LawEstimates, RepeatedData};
use crate::isoflop;
use crate::laws::Estimate;
use crate::lbfgs::{minimize, Minimum};
use crate::ols::Line;
use crate::parametric::{self, huber, lse3, LogRuns, StartGrid};
use crate::runs::Runs;
use motionscale_core::rng::SplitMix64;
use rayon::prelude::*;

/// Runs for the data-constrained fit.
#[derive(Debug, Clone, PartialEq)]
pub struct DataRuns {
    /// ln N.
    pub ln_n: Vec<f64>,
    /// Tokens seen, D.
    pub d: Vec<f64>,
    /// Unique tokens, U.
    pub u: Vec<f64>,
    /// ln L.
    pub ln_l: Vec<f64>,
    /// Synthetic share of the unique data, s (zeros: one source).
    pub synth: Vec<f64>,
}

impl DataRuns {
    /// From positive N, D, U and L, one source.
    pub fn new(n: &[f64], d: &[f64], u: &[f64], loss: &[f64]) -> Self {
        Self {
            ln_n: n.iter().map(|v| v.ln()).collect(),
            d: d.to_vec(),
            u: u.to_vec(),
            ln_l: loss.iter().map(|v| v.ln()).collect(),
            synth: vec![0.0; n.len()],
        }
    }

    /// The same runs with synthetic shares `synth`.
    pub fn with_synthetic_shares(self, synth: &[f64]) -> Self {
        Self {
            synth: synth.to_vec(),
            ..self
        }
    }

    /// Whether the shares differ enough (by 0.05) for ρ to be identified.
    fn mixes_sources(&self) -> bool {
        let (lo, hi) = self
            .synth
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), &s| (lo.min(s), hi.max(s)));
        hi - lo > 0.05
    }

    /// ln k and d(ln k)/d(ln ρ) of run `i` at ln ρ.
    fn exchange(&self, i: usize, ln_rho: f64) -> (f64, f64) {
        let (s, rho) = (self.synth[i], ln_rho.exp());
        let k = 1.0 - s + rho * s;
        (k.ln(), rho * s / k)
    }

    /// Number of runs.
    pub fn len(&self) -> usize {
        self.ln_l.len()
    }

    /// True without runs.
    pub fn is_empty(&self) -> bool {
        self.ln_l.is_empty()
    }

    fn select(&self, idx: &[usize]) -> Self {
        let pick = |v: &[f64]| idx.iter().map(|&i| v[i]).collect();
        Self {
            ln_n: pick(&self.ln_n),
            d: pick(&self.d),
            u: pick(&self.u),
            ln_l: pick(&self.ln_l),
            synth: pick(&self.synth),
        }
    }

    /// Log-space residuals at θ = (a, b, e, α, β, ln R*, ln ρ), prediction − observation.
    fn residuals(&self, t: &[f64; 7]) -> Vec<f64> {
        (0..self.len())
            .map(|i| {
                let ln_dp = effective_data(self.d[i], self.u[i], t[5]).0 + self.exchange(i, t[6]).0;
                let terms = [t[0] - t[3] * self.ln_n[i], t[1] - t[4] * ln_dp, t[2]];
                lse3(terms).0 - self.ln_l[i]
            })
            .collect()
    }

    /// The plain runs (D' = D).
    fn plain(&self) -> LogRuns {
        LogRuns {
            ln_n: self.ln_n.clone(),
            ln_d: self.d.iter().map(|v| v.ln()).collect(),
            ln_l: self.ln_l.clone(),
        }
    }
}

/// ln D' and d(ln D')/d(ln R*) for one run.
pub fn effective_data(d: f64, u: f64, ln_r_star: f64) -> (f64, f64) {
    let r_star = ln_r_star.exp();
    let r = (d / u - 1.0).max(0.0);
    let x = r / r_star;
    let decay = (-x).exp();
    let dp = d.min(u) + u * r_star * (1.0 - decay);
    let d_dp = u * r_star * ((1.0 - decay) - x * decay);
    (dp.ln(), d_dp / dp)
}

/// Σ Huber_δ of the log residuals at θ = (a, b, e, α, β, ln R*, ln ρ); writes the gradient
/// (none for ln ρ when the runs have one source mix: it is not identified, and stays put).
pub fn objective(runs: &DataRuns, delta: f64, theta: &[f64; 7], grad: &mut [f64; 7]) -> f64 {
    *grad = [0.0; 7];
    let [a, b, e, alpha, beta, r, ln_rho] = *theta;
    let fit_rho = runs.mixes_sources();
    let mut total = 0.0;
    for i in 0..runs.len() {
        let (ln_dp, dln_dp) = effective_data(runs.d[i], runs.u[i], r);
        let (ln_k, dln_k) = runs.exchange(i, ln_rho);
        let ln_dp = ln_dp + ln_k;
        let (lse, w) = lse3([a - alpha * runs.ln_n[i], b - beta * ln_dp, e]);
        let (h, dh) = huber(lse - runs.ln_l[i], delta);
        total += h;
        grad[0] += dh * w[0];
        grad[1] += dh * w[1];
        grad[2] += dh * w[2];
        grad[3] -= dh * w[0] * runs.ln_n[i];
        grad[4] -= dh * w[1] * ln_dp;
        grad[5] -= dh * w[1] * beta * dln_dp;
        if fit_rho {
            grad[6] -= dh * w[1] * beta * dln_k;
        }
    }
    total
}

/// Starts: the plain fit's optimum and the coarse grid, each with several R* (ρ = 1).
fn starts(plain: &[f64; 5]) -> Vec<[f64; 7]> {
    let with_r = |t: &[f64; 5], rs: &[f64]| -> Vec<[f64; 7]> {
        rs.iter()
            .map(|r| [t[0], t[1], t[2], t[3], t[4], r.ln(), 0.0])
            .collect()
    };
    let mut out = with_r(plain, &[0.5, 1.0, 2.0, 5.0, 15.0, 50.0, 200.0]);
    for t in StartGrid::coarse().points() {
        out.extend(with_r(&t, &[2.0, 15.0, 100.0]));
    }
    out
}

/// The best end point of L-BFGS from every start (`None` if none is finite).
fn best_of(runs: &DataRuns, opts: &FitOptions, starts: &[[f64; 7]]) -> Option<Minimum<7>> {
    let delta = opts.huber_delta;
    starts
        .par_iter()
        .map(|&s| minimize(|t, g| objective(runs, delta, t, g), s, &opts.lbfgs))
        .filter(|m| m.f.is_finite() && m.x.iter().all(|v| v.is_finite()))
        .min_by(|a, b| a.f.total_cmp(&b.f))
}

/// The data-constrained fit of `runs` (the plain parametric fit in `fits` seeds it); the error
/// says why it cannot be fitted.
pub fn fit(runs: &Runs, fits: &Fits, opts: &FitOptions) -> Result<RepeatedData, String> {
    let (Some(d), Some(u), Some(epochs)) = (&runs.d, runs.unique_tokens(), &runs.epochs) else {
        return Err(format!(
            "needs a tokens column and an epochs column ({:?}: epochs over the unique tokens)",
            opts.columns.epochs.name
        ));
    };
    let plain = fits
        .parametric
        .as_ref()
        .ok_or("needs the plain parametric fit (see its skip reason)")?;
    let max_epochs = epochs.iter().copied().fold(0.0, f64::max);
    let repeated_runs = epochs.iter().filter(|&&e| e > 1.0).count();
    if repeated_runs == 0 {
        return Err(format!(
            "no run repeats data (at most {max_epochs:.2} epochs): R* cannot be fitted"
        ));
    }
    let mut data = DataRuns::new(&runs.n, d, &u, &runs.param_loss.1);
    if let Some(shares) = &runs.synth_share {
        data = data.with_synthetic_shares(shares);
    }
    let best = best_of(&data, opts, &starts(&plain.theta))
        .ok_or("the objective is not finite at any start")?;
    let draws: Vec<[f64; 7]> = (0..opts.bootstrap)
        .into_par_iter()
        .filter_map(|i| {
            let mut rng = SplitMix64::stream(opts.seed, i as u64);
            let idx: Vec<usize> = (0..data.len()).map(|_| rng.index(data.len())).collect();
            let sample = data.select(&idx);
            let m = minimize(
                |t, g| objective(&sample, opts.huber_delta, t, g),
                best.x,
                &opts.lbfgs,
            );
            let nat = natural(&m.x);
            (m.f.is_finite() && nat.iter().all(|v| v.is_finite())).then_some(nat)
        })
        .collect();
    let value = natural(&best.x);
    // Far past the largest repetition count, e^(−R/R*) ≈ 1 − R/R* and D' ≈ D: no discount.
    let note = (value[5] > 100.0 * (max_epochs - 1.0)).then(|| {
        format!(
            "R* = {:.3e} is more than 100 times the largest repetition count ({:.1}): D' ≈ D for every run, so repetition costs nothing these runs can measure; R* itself is not identified (no interval)",
            value[5],
            max_epochs - 1.0
        )
    });
    let est = |k: usize| {
        let v: Vec<f64> = draws.iter().map(|s| s[k]).collect();
        parametric::with_draws(value[k], &v)
    };
    Ok(RepeatedData {
        law: LawEstimates::from_fn(est),
        // Past the runs' repetitions the objective is flat in R*: refits from the optimum
        // stay where they start, and their spread would be a false interval.
        r_star: match note {
            Some(_) => Estimate::exact(value[5]),
            None => est(5),
        },
        exchange: data.mixes_sources().then(|| est(6)),
        n_runs: data.len(),
        repeated_runs,
        max_epochs,
        objective: best.f,
        termination: best.termination,
        bootstrap: [opts.bootstrap, draws.len()],
        held_out: held_out(runs, &data, opts, &plain.theta, &best.x),
        note,
        tokens_per_hour: runs.hours.as_ref().map(|h| {
            let mut per: Vec<f64> = u.iter().zip(h).map(|(u, h)| u / h).collect();
            per.sort_by(f64::total_cmp);
            per[per.len() / 2]
        }),
        nv_line: runs.nv.as_ref().and_then(|nv| {
            let lx: Vec<f64> = runs.n.iter().map(|v| v.log10()).collect();
            let ly: Vec<f64> = nv.iter().map(|v| v.log10()).collect();
            Line::fit(&lx, &ly).map(|l| [l.intercept, l.slope])
        }),
        vocab: runs
            .v
            .as_ref()
            .and_then(|v| v.iter().all(|&k| k == v[0]).then(|| v[0])),
        draws,
    })
}

/// θ → (E, A, B, α, β, R*, ρ).
fn natural(t: &[f64; 7]) -> [f64; 7] {
    [
        t[2].exp(),
        t[0].exp(),
        t[1].exp(),
        t[3],
        t[4],
        t[5].exp(),
        t[6].exp(),
    ]
}

/// Leave each budget out, refit both forms on the rest (from the full-data optima and the
/// coarse grid), and collect the log residuals on the left-out runs; `None` below 3 budgets.
fn held_out(
    runs: &Runs,
    data: &DataRuns,
    opts: &FitOptions,
    plain: &[f64; 5],
    repeated: &[f64; 7],
) -> Option<HeldOutError> {
    let groups = isoflop::group_rows(&runs.c, runs.group.as_deref(), opts.group_tol_dex);
    if groups.len() < 3 {
        return None;
    }
    let mut plain_starts = StartGrid::coarse().points();
    plain_starts.push(*plain);
    let mut repeated_starts = starts(plain);
    repeated_starts.push(*repeated);
    let (mut sq_plain, mut sq_rep, mut count) = (0.0, 0.0, 0usize);
    for (g, left_out) in groups.iter().enumerate() {
        let kept: Vec<usize> = groups
            .iter()
            .enumerate()
            .filter(|&(k, _)| k != g)
            .flat_map(|(_, rows)| rows.iter().copied())
            .collect();
        let train = data.select(&kept);
        let test = data.select(left_out);
        let p =
            parametric::multi_start(&train.plain(), opts.huber_delta, &plain_starts, &opts.lbfgs)
                .ok()?;
        let r = best_of(&train, opts, &repeated_starts)?;
        let squares = |r: Vec<f64>| r.iter().map(|v| v * v).sum::<f64>();
        sq_plain += squares(test.plain().residuals(&p.best().x));
        sq_rep += squares(test.residuals(&r.x));
        count += test.len();
    }
    let (plain_rms, repeated_rms) = (
        (sq_plain / count as f64).sqrt(),
        (sq_rep / count as f64).sqrt(),
    );
    Some(HeldOutError {
        folds: groups.len(),
        plain_rms,
        repeated_rms,
        better: if repeated_rms < plain_rms {
            "repeated"
        } else {
            "plain"
        }
        .into(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn effective_data_is_d_without_repetition_and_saturates_with_it() {
        let (ln_dp, _) = effective_data(5e8, 1e9, 2.0f64.ln());
        assert!((ln_dp - 5e8f64.ln()).abs() < 1e-12);
        // Many epochs: D' → U·(1 + R*).
        let (ln_dp, _) = effective_data(1e9 * 1e4, 1e9, 15f64.ln());
        assert!((ln_dp.exp() / (1e9 * 16.0) - 1.0).abs() < 1e-9);
        // Few repetitions count almost fully: 2 epochs with R* = 100 are ≈ 2U.
        let (ln_dp, _) = effective_data(2e9, 1e9, 100f64.ln());
        assert!((ln_dp.exp() / 2e9 - 1.0).abs() < 0.01);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let runs = DataRuns::new(
            &[1e5, 3e5, 2e6, 5e5],
            &[1e7, 4e7, 9e6, 3e8],
            &[2e7, 1e7, 1e7, 1e7],
            &[2.1, 1.9, 2.0, 1.8],
        );
        let runs = runs.with_synthetic_shares(&[0.0, 0.5, 0.4, 1.0]);
        let theta = [6.0, 5.5, 0.4, 0.33, 0.27, 1.5, -0.7];
        // Huber with a huge δ is r²/2: the objective and the residuals agree.
        let half_sq: f64 = runs.residuals(&theta).iter().map(|r| 0.5 * r * r).sum();
        let mut g = [0.0; 7];
        assert!((objective(&runs, f64::MAX, &theta, &mut g) - half_sq).abs() < 1e-12);
        for delta in [1e-3, 10.0] {
            let mut g = [0.0; 7];
            objective(&runs, delta, &theta, &mut g);
            for k in 0..7 {
                let h = 1e-6;
                let (mut tp, mut tm) = (theta, theta);
                tp[k] += h;
                tm[k] -= h;
                let mut s = [0.0; 7];
                let fd = (objective(&runs, delta, &tp, &mut s)
                    - objective(&runs, delta, &tm, &mut s))
                    / (2.0 * h);
                assert!(
                    (fd - g[k]).abs() < 1e-6 * (1.0 + g[k].abs()),
                    "δ={delta} k={k}: {fd} vs {}",
                    g[k]
                );
            }
        }
    }
}
