//! The data-constrained law of Muennighoff et al. (2023): repeated tokens are worth less than
//! fresh ones. With U unique tokens seen for D tokens in all, R = D/U − 1 repetitions and the
//! effective data D' = U + U·R*·(1 − e^(−R/R*)) replaces D in L(N, D) = E + A/N^α + B/D'^β.
//! R* (the repetitions after which extra epochs are worth 1/e of fresh data) is fitted with the
//! other five parameters (Huber on log residuals, L-BFGS, bootstrap intervals), and both this
//! fit and the plain one are scored on each budget left out in turn.
//!
//! Their effective parameters too: the law's own A, B, α, β allocate
//! U_N = (αA/(βB))^(1/α)·U_D^(β/α) parameters to the U_D = min(D, U) unique tokens seen (the
//! compute-optimal split at D = U_D); parameters past U_N are worth less, as repeated tokens
//! are: N' = U_N + U_N·R*_N·(1 − e^(−R_N/R*_N)) with R_N = N/U_N − 1 replaces N. U_N moves with
//! the law's parameters, and the gradient follows it.
//!
//! With a second source, the exchange rate ρ (effective captured tokens per synthetic token)
//! is fitted too: a run whose unique data is a share s synthetic counts U·k and D·k with
//! k = 1 − s + ρ·s (each epoch passes over both sources; R is unchanged), so that
//! ln D' gains ln k. It is identified only when the runs' synthetic shares differ. That is
//! one form of the exchange (`ExchangeForm::TokenWorth`); in the other
//! (`ExchangeForm::EffectivePool`) repetitions count against the effective pool
//! U·k = U_real + ρ·U_synth while each token seen counts in full, so a run with synthetic data
//! repeats sooner. `fit` fits the forms asked for and adopts the one with the lower error on
//! the data subsets left out in turn.

use crate::fitted::{
    exchange_factor, share_range, BlockInterval, BudgetInformation, DataFrontierPoint,
    ExchangeForm, FitOptions, Fits, FormError, FormScore, HeldOutError, Information, LawEstimates,
    RepeatedData,
};
use crate::isoflop;
use crate::laws::Estimate;
use crate::lbfgs::{minimize, Minimum};
use crate::ols::Line;
use crate::parametric::{self, huber, lse3, percentile, LogRuns, StartGrid};
use crate::runs::Runs;
use crate::stopping::{tokens_used, StopRuns};
use crate::FitError;
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
    /// Whether parameters past U_N count as N' (R*_N is fitted), else in full.
    pub effective_params: bool,
    /// How synthetic tokens count.
    pub form: ExchangeForm,
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
            effective_params: false,
            form: ExchangeForm::TokenWorth,
        }
    }

    /// The same runs under the exchange form `form`.
    pub fn with_exchange_form(self, form: ExchangeForm) -> Self {
        Self { form, ..self }
    }

    /// The same runs with the effective parameters N' (R*_N fitted) or without.
    pub fn with_effective_params(self, on: bool) -> Self {
        Self {
            effective_params: on,
            ..self
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
        share_range(&self.synth).1
    }

    /// ln k and d(ln k)/d(ln ρ) of run `i` at ln ρ.
    fn exchange(&self, i: usize, ln_rho: f64) -> (f64, f64) {
        let (k, dk) = exchange_factor(self.synth[i], ln_rho.exp());
        (k.ln(), dk)
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
            effective_params: self.effective_params,
            form: self.form,
        }
    }

    /// Log-space residuals at θ, prediction − observation.
    fn residuals(&self, t: &[f64; 8]) -> Vec<f64> {
        (0..self.len())
            .map(|i| lse3(self.point(i, t).terms(t)).0 - self.ln_l[i])
            .collect()
    }

    /// Run `i` under the law θ.
    fn point(&self, i: usize, t: &[f64; 8]) -> Point {
        let (ln_k, dln_k) = self.exchange(i, t[6]);
        let mut t = *t;
        if !self.effective_params {
            t[7] = f64::INFINITY;
        }
        Point::new(
            self.ln_n[i],
            self.d[i],
            self.u[i],
            (ln_k, dln_k),
            &t,
            self.form,
        )
    }

    /// Runs whose N exceeds U_N under θ (those that identify R*_N).
    fn past_base_size(&self, t: &[f64; 8]) -> usize {
        (0..self.len())
            .filter(|&i| self.ln_n[i] > self.point(i, t).ln_un)
            .count()
    }

    /// The largest N/U_N − 1 of the runs under θ (0 when none exceeds U_N).
    fn largest_excess_size(&self, t: &[f64; 8]) -> f64 {
        (0..self.len())
            .map(|i| (self.ln_n[i] - self.point(i, t).ln_un).exp() - 1.0)
            .fold(0.0, f64::max)
    }

    /// The Gauss–Newton information at θ over the fitted coordinates (R*_D and R*_N only
    /// where identified: past the runs' excess their columns vanish), by budget group
    /// (`groups`, with their budgets).
    fn information(
        &self,
        t: &[f64; 8],
        identified: [bool; 2],
        groups: &[(f64, Vec<usize>)],
    ) -> Information {
        let fit_rho = self.mixes_sources();
        let free: Vec<usize> = (0..8)
            .filter(|&k| match k {
                5 => identified[0],
                6 => fit_rho,
                7 => self.effective_params && identified[1],
                _ => true,
            })
            .collect();
        let p = free.len();
        let mut residuals = Vec::new();
        let budgets = groups
            .iter()
            .map(|(budget, rows)| {
                let mut b = BudgetInformation {
                    budget: *budget,
                    runs: rows.len(),
                    jtj: vec![vec![0.0; p]; p],
                    sum: vec![0.0; p],
                };
                let mut r = Vec::new();
                for &i in rows {
                    let (lse, g) = self.point(i, t).log_loss(t, fit_rho);
                    r.push(lse - self.ln_l[i]);
                    for (a, &k) in free.iter().enumerate() {
                        b.sum[a] += g[k];
                        for (c, &l) in free.iter().enumerate() {
                            b.jtj[a][c] += g[k] * g[l];
                        }
                    }
                }
                residuals.push(r);
                b
            })
            .collect();
        let (sigma2, tau2) = variance_components(&residuals, p);
        Information {
            free,
            budgets,
            sigma2,
            tau2,
        }
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

/// One run under a law θ = (ln A, ln B, ln E, α, β, ln R*_D, ln ρ, ln R*_N), the coordinates
/// the fit moves in: its effective data and parameters, and how they move with θ.
#[derive(Debug, Clone, Copy)]
struct Point {
    /// ln D' (the exchange rate applied), d(ln D')/d(ln R*_D) and d(ln D')/d(ln ρ).
    ln_dp: f64,
    dp_r: f64,
    dp_rho: f64,
    /// ln U_N, its partials in (ln A, ln B, α, β, ln U_D) and d(ln U_D)/d(ln ρ).
    ln_un: f64,
    un: [f64; 5],
    un_rho: f64,
    /// ln N', d(ln N')/d(ln R*_N) and d(ln N')/d(ln U_N).
    ln_np: f64,
    np_r: f64,
    np_un: f64,
}

impl Point {
    fn new(
        ln_n: f64,
        d: f64,
        u: f64,
        (ln_k, dk_rho): (f64, f64),
        t: &[f64; 8],
        form: ExchangeForm,
    ) -> Self {
        // U_D: the unique tokens the run saw (Muennighoff et al.), to which U_N is allotted.
        let (ln_dp, dp_r, dp_rho, ln_seen, seen_rho) = match form {
            ExchangeForm::TokenWorth => {
                let (ln_dp, dp_r) = effective_data(d, u, t[5]);
                (ln_dp + ln_k, dp_r, dk_rho, d.min(u).ln() + ln_k, dk_rho)
            }
            ExchangeForm::EffectivePool => {
                let ln_pool = u.ln() + ln_k;
                let (ln_dp, dp_r, dp_pool) = effective_size(d.ln(), ln_pool, t[5]);
                let pool_seen = ln_pool < d.ln();
                let (ln_seen, seen_rho) = match pool_seen {
                    true => (ln_pool, dk_rho),
                    false => (d.ln(), 0.0),
                };
                (ln_dp, dp_r, dp_pool * dk_rho, ln_seen, seen_rho)
            }
        };
        let (ln_un, un) = base_size(t, ln_seen);
        let (ln_np, np_r, np_un) = effective_size(ln_n, ln_un, t[7]);
        Self {
            ln_dp,
            dp_r,
            dp_rho,
            ln_un,
            un,
            un_rho: seen_rho,
            ln_np,
            np_r,
            np_un,
        }
    }

    /// The three log terms of the loss: ln(A/N'^α), ln(B/D'^β), ln E.
    fn terms(&self, t: &[f64; 8]) -> [f64; 3] {
        [t[0] - t[3] * self.ln_np, t[1] - t[4] * self.ln_dp, t[2]]
    }

    /// ln L̂ and its gradient in θ (zero in ln ρ unless `fit_rho`).
    fn log_loss(&self, t: &[f64; 8], fit_rho: bool) -> (f64, [f64; 8]) {
        let (alpha, beta) = (t[3], t[4]);
        let (lse, w) = lse3(self.terms(t));
        // The parameter term moves with U_N, which moves with ln A, ln B, α, β and ln U.
        let via_un = -alpha * self.np_un * w[0];
        let rho = match fit_rho {
            true => -w[1] * beta * self.dp_rho + via_un * self.un[4] * self.un_rho,
            false => 0.0,
        };
        let grad = [
            w[0] + via_un * self.un[0],
            w[1] + via_un * self.un[1],
            w[2],
            -w[0] * self.ln_np + via_un * self.un[2],
            -w[1] * self.ln_dp + via_un * self.un[3],
            -w[1] * beta * self.dp_r,
            rho,
            -w[0] * alpha * self.np_r,
        ];
        (lse, grad)
    }
}

/// ln U_N, the size the law θ allocates to e^ln_u unique tokens (αA/N^α = βB/U^β), with its
/// partial derivatives in (ln A, ln B, α, β, ln U); +∞ (no parameter is in excess) where α or
/// β is not positive.
fn base_size(t: &[f64; 8], ln_u: f64) -> (f64, [f64; 5]) {
    let (alpha, beta) = (t[3], t[4]);
    if alpha <= 0.0 || beta <= 0.0 {
        return (f64::INFINITY, [0.0; 5]);
    }
    let ln_un = (alpha.ln() + t[0] - beta.ln() - t[1] + beta * ln_u) / alpha;
    let partials = [
        1.0 / alpha,
        -1.0 / alpha,
        (1.0 - alpha * ln_un) / (alpha * alpha),
        (ln_u - 1.0 / beta) / alpha,
        beta / alpha,
    ];
    (ln_un, partials)
}

/// ln X' with d(ln X')/d(ln R*) and d(ln X')/d(ln U) for X of which U count in full and the
/// rest decays with R*: X' = X up to U, else U + U·R*·(1 − e^(−(X/U − 1)/R*)). Effective
/// data (X = D tokens, U unique) and effective parameters (X = N, U = U_N) alike.
pub fn effective_size(ln_x: f64, ln_u: f64, ln_r_star: f64) -> (f64, f64, f64) {
    if ln_x <= ln_u || !ln_r_star.is_finite() {
        return (ln_x, 0.0, 0.0);
    }
    let (x, u, r_star) = (ln_x.exp(), ln_u.exp(), ln_r_star.exp());
    let z = (x / u - 1.0) / r_star;
    let decay = (-z).exp();
    let xp = u + u * r_star * (1.0 - decay);
    let d_r = u * r_star * ((1.0 - decay) - z * decay) / xp;
    let d_u = u * (1.0 + r_star * (1.0 - decay) - decay * x / u) / xp;
    (xp.ln(), d_r, d_u)
}

/// ln D' and d(ln D')/d(ln R*_D) for one run of D tokens, U of them unique.
pub fn effective_data(d: f64, u: f64, ln_r_star: f64) -> (f64, f64) {
    let (ln_dp, d_r, _) = effective_size(d.ln(), u.ln(), ln_r_star);
    (ln_dp, d_r)
}

/// One-way random-effects moments of residuals grouped by budget: (σ², τ²), the within-group
/// variance (`p` fitted coordinates spent) and the variance of the groups' shared offsets
/// (ANOVA estimator, at least 0).
fn variance_components(groups: &[Vec<f64>], p: usize) -> (f64, f64) {
    let n: usize = groups.iter().map(|g| g.len()).sum();
    let k = groups.len();
    let mean = |g: &[f64]| g.iter().sum::<f64>() / g.len().max(1) as f64;
    let grand = groups.iter().flatten().sum::<f64>() / n.max(1) as f64;
    let within: f64 = groups
        .iter()
        .map(|g| g.iter().map(|r| (r - mean(g)).powi(2)).sum::<f64>())
        .sum();
    let sigma2 = within / n.saturating_sub(k.max(p)).max(1) as f64;
    if k < 2 {
        return (sigma2, 0.0);
    }
    let between: f64 = groups
        .iter()
        .map(|g| g.len() as f64 * (mean(g) - grand).powi(2))
        .sum::<f64>()
        / (k - 1) as f64;
    let n0 = (n as f64 - groups.iter().map(|g| g.len().pow(2)).sum::<usize>() as f64 / n as f64)
        / (k - 1) as f64;
    (sigma2, ((between - sigma2) / n0).max(0.0))
}

/// θ of natural parameters (E, A, B, α, β, R*_D, ρ, R*_N): the inverse of `natural`.
pub fn coordinates(nat: &[f64; 8]) -> [f64; 8] {
    [
        nat[1].ln(),
        nat[2].ln(),
        nat[0].ln(),
        nat[3],
        nat[4],
        nat[5].ln(),
        nat[6].ln(),
        nat[7].ln(),
    ]
}

/// A law in natural parameters (E, A, B, α, β, R*_D, ρ, R*_N) with its exchange form.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NaturalLaw {
    /// (E, A, B, α, β, R*_D, ρ, R*_N).
    pub theta: [f64; 8],
    /// How synthetic tokens count.
    pub form: ExchangeForm,
}

impl NaturalLaw {
    /// One run of N parameters trained on D tokens of U unique ones, a share `synth` of them
    /// synthetic, and θ.
    fn point(&self, n: f64, d: f64, u: f64, synth: f64) -> (Point, [f64; 8]) {
        let nat = &self.theta;
        let t = coordinates(nat);
        let k = 1.0 - synth + nat[6] * synth;
        let exchange = (k.ln(), nat[6] * synth / k);
        (Point::new(n.ln(), d, u, exchange, &t, self.form), t)
    }

    /// The law's loss for N parameters trained on D tokens of U unique ones, a share `synth`
    /// of them synthetic.
    pub fn loss(&self, n: f64, d: f64, u: f64, synth: f64) -> f64 {
        let (p, t) = self.point(n, d, u, synth);
        lse3(p.terms(&t)).0.exp()
    }

    /// The gradient of ln L̂ in θ = (ln A, ln B, ln E, α, β, ln R*_D, ln ρ, ln R*_N) for the
    /// run `loss` describes: one row of the Jacobian a new run would add to the fit.
    pub fn log_loss_gradient(&self, n: f64, d: f64, u: f64, synth: f64) -> [f64; 8] {
        let (p, t) = self.point(n, d, u, synth);
        p.log_loss(&t, true).1
    }
}

/// Σ Huber_δ of the log residuals at θ = (ln A, ln B, ln E, α, β, ln R*_D, ln ρ, ln R*_N);
/// writes the gradient (none for ln ρ when the runs have one source mix: it is not
/// identified, and stays put).
pub fn objective(runs: &DataRuns, delta: f64, theta: &[f64; 8], grad: &mut [f64; 8]) -> f64 {
    *grad = [0.0; 8];
    let fit_rho = runs.mixes_sources();
    let mut total = 0.0;
    for i in 0..runs.len() {
        let (lse, row) = runs.point(i, theta).log_loss(theta, fit_rho);
        let (h, dh) = huber(lse - runs.ln_l[i], delta);
        total += h;
        for (g, r) in grad.iter_mut().zip(row) {
            *g += dh * r;
        }
    }
    total
}

/// Starts: the plain fit's optimum and the coarse grid, each with several R*_D, and R*_N
/// where it is fitted (ρ = 1).
fn starts(plain: &[f64; 5], effective_params: bool) -> Vec<[f64; 8]> {
    let with_r = |t: &[f64; 5], rd: &[f64], rn: &[f64]| -> Vec<[f64; 8]> {
        rd.iter()
            .flat_map(|d| rn.iter().map(move |n| (d, n)))
            .map(|(d, n)| [t[0], t[1], t[2], t[3], t[4], d.ln(), 0.0, n.ln()])
            .collect()
    };
    let r_n: &[f64] = if effective_params {
        &[5.0, 1e4]
    } else {
        &[1e4]
    };
    let mut out = with_r(plain, &[0.5, 1.0, 2.0, 5.0, 15.0, 50.0, 200.0], r_n);
    for t in StartGrid::coarse().points() {
        out.extend(with_r(&t, &[2.0, 15.0, 100.0], &[1e4]));
    }
    out
}

/// A note where a fitted R* lies more than 100 times past the largest excess the runs have:
/// there e^(−R/R*) ≈ 1 − R/R*, the discount vanishes and R* is not identified.
fn unidentified(name: &str, value: f64, largest: f64, what: &str) -> Option<String> {
    (value > 100.0 * largest).then(|| {
        format!(
            "{name} = {value:.3e} is more than 100 times the largest {what} ({largest:.1}): it costs nothing these runs can measure; {name} itself is not identified (no interval)"
        )
    })
}

/// The best end point of L-BFGS from every start (`None` if none is finite).
fn best_of(runs: &DataRuns, opts: &FitOptions, starts: &[[f64; 8]]) -> Option<Minimum<8>> {
    let delta = opts.huber_delta;
    starts
        .par_iter()
        .map(|&s| minimize(|t, g| objective(runs, delta, t, g), s, &opts.lbfgs))
        .filter(|m| m.f.is_finite() && m.x.iter().all(|v| v.is_finite()))
        .min_by(|a, b| a.f.total_cmp(&b.f))
}

/// Unique-data sets whose U differ by less than this (relative) are one set: U is recovered
/// as D / epochs, and D is rounded to whole batches.
const SAME_UNIQUE_DATA: f64 = 0.01;

/// The lowest loss at each budget group on each unique-data set (U within
/// [`SAME_UNIQUE_DATA`] and the same synthetic share), by budget, then U.
fn frontier(runs: &Runs, u: &[f64], groups: &[(f64, Vec<usize>)]) -> Vec<DataFrontierPoint> {
    let loss = &runs.param_loss.1;
    let share = |i: usize| runs.synth_share.as_ref().map_or(0.0, |s| s[i]);
    let mut out: Vec<DataFrontierPoint> = Vec::new();
    for (budget, rows) in groups {
        let first = out.len();
        for &i in rows {
            let same = |p: &DataFrontierPoint| {
                (p.unique_tokens / u[i] - 1.0).abs() < SAME_UNIQUE_DATA
                    && (p.synth_share - share(i)).abs() < SAME_UNIQUE_DATA
            };
            match out[first..].iter_mut().find(|p| same(p)) {
                Some(p) if loss[i] < p.loss => (p.loss, p.n) = (loss[i], runs.n[i]),
                Some(_) => {}
                None => out.push(DataFrontierPoint {
                    budget: *budget,
                    unique_tokens: u[i],
                    hours: runs.hours.as_ref().map(|h| h[i]),
                    synth_share: share(i),
                    loss: loss[i],
                    n: runs.n[i],
                }),
            }
        }
        out[first..].sort_by(|a, b| a.unique_tokens.total_cmp(&b.unique_tokens));
    }
    out
}

/// The data-constrained fit of `runs` (the plain parametric fit in `fits` seeds it); the error
/// says why it cannot be fitted.
pub fn fit(runs: &Runs, fits: &Fits, opts: &FitOptions) -> Result<RepeatedData, FitError> {
    let cannot = |needs: String| FitError::CannotFit {
        fit: "data-constrained L(N, D')",
        needs,
    };
    let (Some(d_run), Some(u), Some(epochs_run)) = (&runs.d, runs.unique_tokens(), &runs.epochs)
    else {
        return Err(cannot(format!(
            "needs a tokens column and an epochs column ({:?}: epochs over the unique tokens)",
            opts.columns.epochs.name
        )));
    };
    // With early stopping the law sees the tokens of each run's selected checkpoint.
    let stop = runs
        .selected
        .as_ref()
        .map(|sel| StopRuns::new(&runs.n, &u, epochs_run, sel));
    let at_selected = |v: &[f64]| match &runs.selected {
        Some(sel) => v.iter().zip(sel).map(|(x, s)| x * s).collect(),
        None => v.to_vec(),
    };
    let (d, epochs): (Vec<f64>, Vec<f64>) = (at_selected(d_run), at_selected(epochs_run));
    let mut stopping = stop.as_ref().map(StopRuns::rule).transpose()?;
    let plain = fits
        .parametric
        .as_ref()
        .ok_or_else(|| cannot("needs the plain parametric fit (see its skip reason)".into()))?;
    let max_epochs = epochs.iter().copied().fold(0.0, f64::max);
    let repeated_runs = epochs.iter().filter(|&&e| e > 1.0).count();
    if repeated_runs == 0 {
        return Err(cannot(format!(
            "no run repeats data (at most {max_epochs:.2} epochs): R* cannot be fitted"
        )));
    }
    let mut data = DataRuns::new(&runs.n, &d, &u, &runs.param_loss.1)
        .with_effective_params(opts.effective_params);
    if let Some(shares) = &runs.synth_share {
        data = data.with_synthetic_shares(shares);
    }
    let stop_tokens = stop.as_ref().map(|s| (s, d_run.as_slice()));
    let forms = score_forms(runs, &data, stop_tokens, opts, &plain.theta);
    let data = data.with_exchange_form(forms[0].form);
    let best = best_of(&data, opts, &starts(&plain.theta, data.effective_params))
        .ok_or_else(|| cannot("the objective is not finite at any start".into()))?;
    let refits = bootstrap(&data, stop.as_ref(), &best.x, opts);
    let draws: Vec<[f64; 8]> = refits.iter().map(|r| r.0).collect();
    if let Some(rule) = &mut stopping {
        rule.draws = refits.iter().filter_map(|r| r.1).collect();
    }
    let value = natural(&best.x, data.effective_params);
    let note = unidentified("R*", value[5], max_epochs - 1.0, "repetition count");
    let note_n = data.effective_params.then(|| {
        let excess = data.largest_excess_size(&best.x);
        unidentified("R*_N", value[7], excess, "excess of N over U_N, N/U_N − 1")
    });
    let groups: Vec<(f64, Vec<usize>)> =
        isoflop::group_rows(&runs.c, runs.group.as_deref(), opts.group_tol_dex)
            .into_iter()
            .map(|rows| (isoflop::group_budget(&runs.c, &rows), rows))
            .collect();
    let block = block_intervals(&data, &best.x, opts, runs, &groups);
    let identified = [note.is_none(), !matches!(note_n, Some(Some(_)))];
    let information = data.information(&best.x, identified, &groups);
    let est = |k: usize| {
        let v: Vec<f64> = draws.iter().map(|s| s[k]).collect();
        parametric::with_draws(value[k], &v)
    };
    // Past the runs' excess the objective is flat in R*: refits from the optimum stay where
    // they start, and their spread would be a false interval.
    let r_star = |k: usize, note: &Option<String>| match note {
        Some(_) => Estimate::exact(value[k]),
        None => est(k),
    };
    Ok(RepeatedData {
        law: LawEstimates::from_fn(est),
        block_intervals: block,
        r_star: r_star(5, &note),
        r_star_n: note_n.as_ref().map(|n| r_star(7, n)),
        past_base_size: match data.effective_params {
            true => data.past_base_size(&best.x),
            false => 0,
        },
        note_n: note_n.flatten(),
        exchange: data.mixes_sources().then(|| est(6)),
        exchange_form: data.form,
        exchange_forms: if forms.len() > 1 { forms } else { Vec::new() },
        in_sample: None,
        n_runs: data.len(),
        repeated_runs,
        max_epochs,
        objective: best.f,
        termination: best.termination,
        bootstrap: [opts.bootstrap, draws.len()],
        held_out: held_out(runs, &data, stop_tokens, opts, (&plain.theta, &best.x)),
        information: Some(information),
        note,
        frontier: frontier(runs, &u, &groups),
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
        stopping,
    })
}

/// The bootstrap refits from the optimum `from`, natural parameters: each resample of the runs
/// refits the law and, with early stopping (`stop`), the stopping rule on the same runs. A
/// resample on which either does not fit is dropped.
fn bootstrap(
    data: &DataRuns,
    stop: Option<&StopRuns>,
    from: &[f64; 8],
    opts: &FitOptions,
) -> Vec<([f64; 8], Option<[f64; 3]>)> {
    let rows = |rng: &mut SplitMix64| (0..data.len()).map(|_| rng.index(data.len())).collect();
    resample(data, stop, from, opts, (0, rows))
}

/// Refits on `opts.bootstrap` resamples of the runs drawn by `draw` (seeded by `opts.seed`
/// and `stream`).
fn resample(
    data: &DataRuns,
    stop: Option<&StopRuns>,
    from: &[f64; 8],
    opts: &FitOptions,
    (stream, draw): (u64, impl Fn(&mut SplitMix64) -> Vec<usize> + Sync),
) -> Vec<([f64; 8], Option<[f64; 3]>)> {
    (0..opts.bootstrap)
        .into_par_iter()
        .filter_map(|i| {
            let mut rng = SplitMix64::stream(opts.seed ^ stream, i as u64);
            let idx: Vec<usize> = draw(&mut rng);
            let sample = data.select(&idx);
            let m = minimize(
                |t, g| objective(&sample, opts.huber_delta, t, g),
                *from,
                &opts.lbfgs,
            );
            let nat = natural(&m.x, sample.effective_params);
            let finite = nat[..7].iter().all(|v| v.is_finite()) && !nat[7].is_nan();
            let rule = match stop {
                Some(s) => Some(s.fit(&idx)?.1),
                None => None,
            };
            (m.f.is_finite() && finite).then_some((nat, rule))
        })
        .collect()
}

/// R*_D's and ρ's 95% intervals with whole budgets (`budgets`: each one's C and rows), and
/// whole data subsets, resampled: runs of one budget share its misfit and runs of one data
/// subset share their clips, so a bootstrap of single runs is too narrow.
fn block_intervals(
    data: &DataRuns,
    from: &[f64; 8],
    opts: &FitOptions,
    runs: &Runs,
    budgets: &[(f64, Vec<usize>)],
) -> Vec<BlockInterval> {
    let exchange_fitted = data.mixes_sources();
    let clusterings = [
        ("budgets", budgets.iter().map(|g| g.1.clone()).collect()),
        ("data subsets", runs.data_subsets().unwrap_or_default()),
    ];
    clusterings
        .into_iter()
        .enumerate()
        .filter(|(_, (_, c))| c.len() > 1)
        .filter_map(|(k, (name, clusters))| {
            let draw = |rng: &mut SplitMix64| {
                (0..clusters.len())
                    .flat_map(|_| clusters[rng.index(clusters.len())].iter().copied())
                    .collect()
            };
            let refits = resample(data, None, from, opts, (0xb10c + k as u64, draw));
            // No refit (no bootstrap asked, or none converged): no interval, rather than NaN.
            if refits.is_empty() {
                return None;
            }
            let interval = |j: usize| {
                let v: Vec<f64> = refits.iter().map(|r| r.0[j]).collect();
                [percentile(&v, 0.025), percentile(&v, 0.975)]
            };
            let [lo, hi] = interval(5);
            Some(BlockInterval {
                clusters: name.to_string(),
                count: clusters.len(),
                refits: refits.len(),
                r_star: [lo.unwrap_or(f64::NAN), hi.unwrap_or(f64::NAN)],
                exchange: exchange_fitted.then(|| interval(6).map(|x| x.unwrap_or(f64::NAN))),
            })
        })
        .collect()
}

/// θ → (E, A, B, α, β, R*_D, ρ, R*_N); R*_N = ∞ where it is not fitted.
pub fn natural(t: &[f64; 8], effective_params: bool) -> [f64; 8] {
    [
        t[2].exp(),
        t[0].exp(),
        t[1].exp(),
        t[3],
        t[4],
        t[5].exp(),
        t[6].exp(),
        if effective_params {
            t[7].exp()
        } else {
            f64::INFINITY
        },
    ]
}

/// Leave each budget out, refit both forms on the rest (from the full-data optima and the
/// coarse grid), and collect the log residuals on the left-out runs; `None` below 3 budgets.
/// With early stopping (`stop`: the rule's runs and each run's whole tokens), the rule is
/// refitted on the rest too, and a left-out run is predicted at the tokens it says the run
/// used, not at those of its selected checkpoint (`None` where the rest leave the rule too
/// few runs that stopped early).
fn held_out(
    runs: &Runs,
    data: &DataRuns,
    stop: Option<(&StopRuns, &[f64])>,
    opts: &FitOptions,
    (plain, repeated): (&[f64; 5], &[f64; 8]),
) -> Option<HeldOutError> {
    let groups = isoflop::group_rows(&runs.c, runs.group.as_deref(), opts.group_tol_dex);
    if groups.len() < 3 {
        return None;
    }
    let mut plain_starts = StartGrid::coarse().points();
    plain_starts.push(*plain);
    let mut repeated_starts = starts(plain, data.effective_params);
    repeated_starts.push(*repeated);
    let (mut sq_plain, mut sq_rep, mut count) = (0.0, 0.0, 0usize);
    for (train, test) in folds(runs, data, stop, &groups)? {
        let p =
            parametric::multi_start(&train.plain(), opts.huber_delta, &plain_starts, &opts.lbfgs)
                .ok()?;
        let r = best_of(&train, opts, &repeated_starts)?;
        sq_plain += squares(&test.plain().residuals(&p.best().x));
        sq_rep += squares(&test.residuals(&r.x));
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

/// Σ r².
fn squares(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Each group of `groups` left out in turn: the runs of the others, and the left-out runs.
/// With early stopping (`stop`: the rule's runs and each run's whole tokens) a left-out run
/// is predicted at the tokens the rule refitted on the others says it used (`None` where
/// they leave it too few runs that stopped early).
fn folds(
    runs: &Runs,
    data: &DataRuns,
    stop: Option<(&StopRuns, &[f64])>,
    groups: &[Vec<usize>],
) -> Option<Vec<(DataRuns, DataRuns)>> {
    let mut out = Vec::with_capacity(groups.len());
    for (g, left_out) in groups.iter().enumerate() {
        let kept: Vec<usize> = groups
            .iter()
            .enumerate()
            .filter(|&(k, _)| k != g)
            .flat_map(|(_, rows)| rows.iter().copied())
            .collect();
        let mut test = data.select(left_out);
        if let Some((rule_runs, d_run)) = stop {
            let coef = rule_runs.fit(&kept)?.1;
            test.d = left_out
                .iter()
                .map(|&i| tokens_used(&coef, runs.n[i], d_run[i], data.u[i]))
                .collect();
        }
        out.push((data.select(&kept), test));
    }
    Some(out)
}

/// Each exchange form of `opts.exchange_forms` fitted, and scored by its RMS log error on
/// the data subsets left out in turn (on the budgets where the runs have fewer than 3
/// subsets); the form with the lowest error first. One form asked for: that form, unscored.
fn score_forms(
    runs: &Runs,
    data: &DataRuns,
    stop: Option<(&StopRuns, &[f64])>,
    opts: &FitOptions,
    plain: &[f64; 5],
) -> Vec<FormScore> {
    let unscored = |form| FormScore {
        form,
        exchange: None,
        held_out: None,
    };
    if opts.exchange_forms.len() < 2 {
        let form = opts.exchange_forms.first().copied().unwrap_or_default();
        return vec![unscored(form)];
    }
    let (clusters, groups) = match runs.data_subsets().filter(|s| s.len() >= 3) {
        Some(subsets) => ("data subsets", subsets),
        None => (
            "budgets",
            isoflop::group_rows(&runs.c, runs.group.as_deref(), opts.group_tol_dex),
        ),
    };
    let mut scores: Vec<FormScore> = opts
        .exchange_forms
        .iter()
        .map(|&form| {
            let data = data.clone().with_exchange_form(form);
            let all = starts(plain, data.effective_params);
            let Some(best) = best_of(&data, opts, &all) else {
                return unscored(form);
            };
            let rms = (groups.len() >= 3).then(|| {
                let mut from = all.clone();
                from.push(best.x);
                let (mut sq, mut count) = (0.0, 0usize);
                for (train, test) in folds(runs, &data, stop, &groups)? {
                    sq += squares(&test.residuals(&best_of(&train, opts, &from)?.x));
                    count += test.len();
                }
                Some((sq / count as f64).sqrt())
            });
            FormScore {
                form,
                exchange: data.mixes_sources().then(|| best.x[6].exp()),
                held_out: rms.flatten().map(|rms| FormError {
                    clusters: clusters.into(),
                    folds: groups.len(),
                    rms,
                }),
            }
        })
        .collect();
    let error = |s: &FormScore| s.held_out.as_ref().map_or(f64::INFINITY, |h| h.rms);
    scores.sort_by(|a, b| error(a).total_cmp(&error(b)));
    scores
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
        for form in [ExchangeForm::TokenWorth, ExchangeForm::EffectivePool] {
            let runs = DataRuns::new(
                &[1e5, 3e5, 2e6, 5e5],
                &[1e7, 4e7, 9e6, 3e8],
                &[2e7, 1e7, 1e7, 1e7],
                &[2.1, 1.9, 2.0, 1.8],
            );
            let runs = runs
                .with_synthetic_shares(&[0.0, 0.5, 0.4, 1.0])
                .with_effective_params(true)
                .with_exchange_form(form);
            // U_N of these runs is 1.6e5–5.1e5: every size but the first exceeds it. In the
            // effective pool, every run but the first repeats its pool U·k.
            let theta = [6.0, 6.4, 0.4, 0.33, 0.27, 1.5, -0.7, 1.2];
            assert_eq!(runs.past_base_size(&theta), 3, "{form:?}");
            // Huber with a huge δ is r²/2: the objective and the residuals agree.
            let half_sq: f64 = runs.residuals(&theta).iter().map(|r| 0.5 * r * r).sum();
            let mut g = [0.0; 8];
            assert!((objective(&runs, f64::MAX, &theta, &mut g) - half_sq).abs() < 1e-12);
            for delta in [1e-3, 10.0] {
                let mut g = [0.0; 8];
                objective(&runs, delta, &theta, &mut g);
                for k in 0..8 {
                    let h = 1e-6;
                    let (mut tp, mut tm) = (theta, theta);
                    tp[k] += h;
                    tm[k] -= h;
                    let mut s = [0.0; 8];
                    let fd = (objective(&runs, delta, &tp, &mut s)
                        - objective(&runs, delta, &tm, &mut s))
                        / (2.0 * h);
                    assert!(
                        (fd - g[k]).abs() < 1e-6 * (1.0 + g[k].abs()),
                        "{form:?} δ={delta} k={k}: {fd} vs {}",
                        g[k]
                    );
                }
            }
        }
    }

    /// The two forms agree on captured-only runs and on runs that see less than their pool;
    /// with synthetic data past its pool, the effective pool repeats sooner.
    #[test]
    fn the_forms_differ_only_where_a_mixed_pool_repeats() {
        let theta = [1.2, 60.0, 400.0, 0.35, 0.3, 6.0, 0.35, f64::INFINITY];
        let law = |form| NaturalLaw { theta, form };
        let (tw, pool) = (
            law(ExchangeForm::TokenWorth),
            law(ExchangeForm::EffectivePool),
        );
        let same = |n: f64, d: f64, u: f64, s: f64| {
            (tw.loss(n, d, u, s) / pool.loss(n, d, u, s) - 1.0).abs()
        };
        assert!(same(1e5, 4e8, 1e7, 0.0) < 1e-12, "captured only");
        // Fresh tokens: the token-worth form discounts synthetic ones (D·k), the pool does not.
        assert!(tw.loss(1e5, 1e6, 1e7, 0.5) > pool.loss(1e5, 1e6, 1e7, 0.5));
        // Many epochs of a half-synthetic pool: both saturate, at U·k·(1 + R*) effective tokens.
        let d_inf: f64 = 1e7 * (0.5 + 0.5 * 0.35) * 7.0;
        let at = 1.2 + 60.0 / 1e5f64.powf(0.35) + 400.0 / d_inf.powf(0.3);
        assert!((pool.loss(1e5, 1e12, 1e7, 0.5) / at - 1.0).abs() < 1e-6);
        assert!((tw.loss(1e5, 1e12, 1e7, 0.5) / at - 1.0).abs() < 1e-6);
    }
}
