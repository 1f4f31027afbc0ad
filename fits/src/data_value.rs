//! What another hour of motion is worth at a budget: the data-constrained law (Muennighoff et
//! al. 2023, with the exchange rate of synthetic data, `repeated`) turned into the
//! compute-optimal model for C FLOPs and H hours per source, the loss it reaches, and the
//! marginal value of +1 h and +10 h of each source — in loss, and in the compute that would buy
//! the same loss at today's hours. Every quantity is recomputed for each bootstrap refit, and
//! its 95% interval is the percentile interval over them.

use crate::fitted::RepeatedData;
use crate::fitted::{CellMiss, ExchangeForm, InSampleCoverage};
use crate::laws::Estimate;
use crate::parametric::{percentile_of_sorted, with_draws};
use crate::repeated::NaturalLaw;
use crate::search::{bisect, grid_golden_min};
use crate::stopping::{stop_epochs, tokens_used};
use serde::{Deserialize, Serialize};
use statrs::distribution::{ContinuousCDF, Normal};
use std::f64::consts::LN_10;

/// Hours of each source in the corpus.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Hours {
    /// Captured (real) motion.
    pub real: f64,
    /// Synthetic motion.
    pub synth: f64,
}

/// One law: (E, A, B, α, β, R*_D, ρ, R*_N), with the conversions the fit recorded and, with
/// early stopping, the stopping rule's coefficients.
#[derive(Debug, Clone, Copy)]
struct Law {
    theta: [f64; 8],
    form: ExchangeForm,
    tokens_per_hour: f64,
    nv_line: Option<[f64; 2]>,
    stopping: Option<[f64; 3]>,
}

/// The compute-optimal point of one law at (C, hours).
#[derive(Debug, Clone, Copy)]
struct Optimum {
    n: f64,
    n_v: f64,
    d: f64,
    loss: f64,
}

impl Law {
    /// N_v of a model of N parameters (0 without the fit's line).
    fn n_v(&self, n: f64) -> f64 {
        self.nv_line
            .map_or(0.0, |[c0, c1]| 10f64.powf(c0 + c1 * n.log10()))
    }

    /// The loss of N trained on D tokens of the corpus `h` (with early stopping, on the
    /// tokens it trains before it stops improving).
    fn loss(&self, n: f64, d: f64, h: Hours) -> f64 {
        let u = self.unique_tokens(h);
        let d = self.stopping.map_or(d, |c| tokens_used(&c, n, d, u));
        let law = NaturalLaw {
            theta: self.theta,
            form: self.form,
        };
        law.loss(n, d, u, h.synth / (h.real + h.synth))
    }

    /// U: the corpus's unique tokens.
    fn unique_tokens(&self, h: Hours) -> f64 {
        (h.real + h.synth) * self.tokens_per_hour
    }

    /// The loss of N at budget C (D = C / (6·(N + N_v))).
    fn at(&self, c: f64, n: f64, h: Hours) -> Optimum {
        let n_v = self.n_v(n);
        let d = c / (6.0 * (n + n_v));
        Optimum {
            n,
            n_v,
            d,
            loss: self.loss(n, d, h),
        }
    }

    /// The best N at C: a scan over log N, then golden-section refinement.
    fn optimum(&self, c: f64, h: Hours) -> Optimum {
        let (lo, hi) = (1.0, (c / 6.0).sqrt().log10() + 3.0);
        let f = |x: f64| self.at(c, 10f64.powf(x), h).loss;
        let best = grid_golden_min(f, (lo, hi), 200, 80).unwrap_or(lo);
        self.at(c, 10f64.powf(best), h)
    }

    /// C_sat, the budget past which all further compute lowers the loss by less than `noise`,
    /// and the loss unlimited compute reaches on `h` (at 10¹⁰·C).
    fn saturation(&self, c: f64, h: Hours, noise: f64) -> (f64, f64) {
        let floor = self.optimum(c * 1e10, h).loss;
        let excess = |ln_c: f64| self.optimum(ln_c.exp(), h).loss - floor - noise;
        let (lo, hi) = (c.ln() - 8.0 * LN_10, c.ln() + 10.0 * LN_10);
        if excess(lo) <= 0.0 {
            return (lo.exp(), floor);
        }
        (bisect(|x| excess(x) > 0.0, (lo, hi), 50).exp(), floor)
    }

    /// The budget C' at which today's hours reach `loss` (∞ when no budget does).
    fn compute_for(&self, loss: f64, c: f64, h: Hours) -> f64 {
        let (lo, hi) = (c.ln() - 3.0 * LN_10, c.ln() + 12.0 * LN_10);
        let above = |ln_c: f64| self.optimum(ln_c.exp(), h).loss > loss;
        if above(hi) {
            return f64::INFINITY;
        }
        bisect(above, (lo, hi), 60).exp()
    }
}

/// The value of more hours of one source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HourValue {
    /// `real` or `synth`.
    pub source: String,
    /// Hours added.
    pub hours: f64,
    /// Loss change at the budget, the model re-optimised (negative: better).
    pub loss_change: Estimate,
    /// C'/C: the compute that reaches the same loss at today's hours, as a multiple of C
    /// (∞ when no budget does: the data, not the compute, limits the loss; `null` in JSON). An
    /// interval end that falls among the refits at ∞ is unbounded (absent).
    pub compute_equivalent: Estimate,
    /// The share of the bootstrap refits at which no budget reaches that loss.
    #[serde(default)]
    pub unbuyable: f64,
}

impl HourValue {
    /// Whether the compute equivalent can be acted on: every refit reaches the loss at some
    /// budget, both interval ends are finite, and the loss change's interval excludes 0.
    pub fn resolved(&self) -> bool {
        let finite = |e: &Estimate| {
            e.value.is_finite()
                && e.ci_low.is_some_and(f64::is_finite)
                && e.ci_high.is_some_and(f64::is_finite)
        };
        let signed = matches!(
            (self.loss_change.ci_low, self.loss_change.ci_high),
            (Some(lo), Some(hi)) if lo > 0.0 || hi < 0.0
        );
        self.unbuyable == 0.0 && finite(&self.compute_equivalent) && signed
    }
}

/// Where more compute stops paying on a corpus's hours.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataBound {
    /// The seed SD of the loss that sets the threshold.
    pub noise: f64,
    /// C_sat: the budget past which all further compute lowers the loss by less than `noise`.
    pub saturation: Estimate,
    /// The loss unlimited compute reaches on these hours.
    pub floor: Estimate,
    /// The loss change of doubling the captured hours at the budget, the model re-optimised.
    pub doubling: Estimate,
    /// Whether the budget is past C_sat (point law).
    pub bound: bool,
}

/// Whether `budget` is past the point where compute stops paying on `hours` (by more than
/// `noise`, the seed SD of the loss), and what doubling the captured hours buys there.
pub fn data_bound(
    rd: &RepeatedData,
    budget: f64,
    hours: Hours,
    noise: f64,
) -> Result<DataBound, String> {
    if !(noise.is_finite() && noise > 0.0) {
        return Err(format!("--noise {noise}: the seed SD must be positive"));
    }
    let laws = laws(rd)?;
    let (sat, floor): (Vec<f64>, Vec<f64>) = laws
        .iter()
        .map(|l| l.saturation(budget, hours, noise))
        .unzip();
    let doubled = Hours {
        real: 2.0 * hours.real,
        ..hours
    };
    let doubling: Vec<f64> = laws
        .iter()
        .map(|l| l.optimum(budget, doubled).loss - l.optimum(budget, hours).loss)
        .collect();
    Ok(DataBound {
        noise,
        saturation: estimate(&sat),
        floor: estimate(&floor),
        doubling: estimate(&doubling),
        bound: budget >= sat[0],
    })
}

/// `predict --hours`: the optimum at (C, hours) and what more hours are worth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DataPrediction {
    /// The budget C.
    pub budget: f64,
    /// The corpus's hours per source.
    pub hours: Hours,
    /// Unique loss positions U of the corpus (hours × the fit's tokens per hour).
    pub unique_tokens: f64,
    /// The vocabulary every run of the fit shared (the law is for it).
    pub vocab: Option<f64>,
    /// Compute-optimal N (the fit's N column).
    pub n_opt: Estimate,
    /// N_v at N_opt.
    pub n_v: f64,
    /// D = C / (6·(N_opt + N_v)).
    pub d: Estimate,
    /// D / U.
    pub epochs: Estimate,
    /// With early stopping: e*, the epochs after which N_opt stops improving on validation
    /// (compute spent past them buys nothing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_epochs: Option<Estimate>,
    /// The loss there (the fit's parametric loss column): 95% interval of the law's refits.
    pub loss: Estimate,
    /// The 95% prediction interval of one run's loss there: the refits spread by the runs'
    /// scatter about the law (absent without the fit's Laplace information).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_prediction: Option<Estimate>,
    /// 6·(N_opt + N_v)·D / C.
    pub spends: f64,
    /// +1 h and +10 h of each source.
    pub hour_values: Vec<HourValue>,
    /// What the intervals allow one to act on.
    pub verdicts: Vec<String>,
}

/// The fitted law of `rd`, natural parameters (E, A, B, α, β, R*_D, ρ, R*_N): ρ = 1 where it
/// was not fitted, R*_N = ∞.
pub fn fitted_law(rd: &RepeatedData) -> [f64; 8] {
    let l = &rd.law;
    [
        l.e.value,
        l.a.value,
        l.b.value,
        l.alpha.value,
        l.beta.value,
        rd.r_star.value,
        rd.exchange.as_ref().map_or(1.0, |e| e.value),
        rd.r_star_n.as_ref().map_or(f64::INFINITY, |r| r.value),
    ]
}

/// The law `theta` with the fit's conversions (hours to tokens, N to N_v) and its point
/// stopping rule.
fn law(rd: &RepeatedData, theta: [f64; 8]) -> Result<Law, String> {
    let tokens_per_hour = rd
        .tokens_per_hour
        .ok_or("the data-constrained fit has no tokens per hour (refit a table with the sweep's `hours` column)")?;
    Ok(Law {
        theta,
        form: rd.exchange_form,
        tokens_per_hour,
        nv_line: rd.nv_line,
        stopping: rd.stopping.as_ref().map(|s| s.coef),
    })
}

/// The laws of `rd`: its point estimate, then its bootstrap refits (each with the stopping
/// rule refitted on the same resample).
fn laws(rd: &RepeatedData) -> Result<Vec<Law>, String> {
    let exchange_fitted = rd.exchange.is_some();
    let point = law(rd, fitted_law(rd))?;
    let mut out = vec![point];
    for (i, d) in rd.draws.iter().enumerate() {
        let mut t = *d;
        if !exchange_fitted {
            t[6] = 1.0;
        }
        let stopping = match &rd.stopping {
            Some(s) => Some(*s.draws.get(i).ok_or(
                "the stopping rule has fewer bootstrap refits than the law (a damaged fits.json)",
            )?),
            None => None,
        };
        out.push(Law {
            theta: t,
            stopping,
            ..point
        });
    }
    Ok(out)
}

/// The compute-optimal N at C with `hours` under the law `theta` (natural parameters) of `rd`.
pub fn optimal_size(
    rd: &RepeatedData,
    theta: [f64; 8],
    budget: f64,
    hours: Hours,
) -> Result<f64, String> {
    Ok(law(rd, theta)?.optimum(budget, hours).n)
}

/// The loss change (negative: better) that `more` hours buy at C with `hours` today, the
/// model re-optimised, under the law `theta` (natural parameters) of `rd`.
pub fn hour_loss_change(
    rd: &RepeatedData,
    theta: [f64; 8],
    budget: f64,
    hours: Hours,
    more: Hours,
) -> Result<f64, String> {
    let law = law(rd, theta)?;
    let after = Hours {
        real: hours.real + more.real,
        synth: hours.synth + more.synth,
    };
    Ok(law.optimum(budget, after).loss - law.optimum(budget, hours).loss)
}

/// An estimate from the point law's value (first) and the refits'.
fn estimate(values: &[f64]) -> Estimate {
    with_draws(values[0], &values[1..])
}

/// As `estimate`, for values that may be +∞: the refits at ∞ rank above every finite one, so
/// that an interval end among them is unbounded (`None`), and the share of refits at ∞.
fn unbounded_estimate(values: &[f64]) -> (Estimate, f64) {
    let mut refits = values[1..].to_vec();
    refits.sort_by(f64::total_cmp);
    let end = |q: f64| percentile_of_sorted(&refits, q).filter(|v| v.is_finite());
    let infinite = refits.iter().filter(|v| v.is_infinite()).count();
    let estimate = Estimate {
        value: values[0],
        se: None,
        ci_low: end(0.025),
        ci_high: end(0.975),
    };
    (estimate, infinite as f64 / refits.len().max(1) as f64)
}

/// The optimum at `budget` and `hours`, and the value of +1 h and +10 h per source.
pub fn predict_data(
    rd: &RepeatedData,
    budget: f64,
    hours: Hours,
) -> Result<DataPrediction, String> {
    if !(budget.is_finite() && budget > 0.0) {
        return Err(format!(
            "--budget {budget}: must be a positive number of FLOPs"
        ));
    }
    if !(hours.real >= 0.0 && hours.synth >= 0.0 && hours.real + hours.synth > 0.0) {
        return Err(format!(
            "--hours real={},synth={}: need some hours, none negative",
            hours.real, hours.synth
        ));
    }
    let laws = laws(rd)?;
    let optima: Vec<Optimum> = laws.iter().map(|l| l.optimum(budget, hours)).collect();
    let u = laws[0].unique_tokens(hours);
    let of = |f: fn(&Optimum) -> f64| estimate(&optima.iter().map(f).collect::<Vec<_>>());
    let mut hour_values = Vec::new();
    for (source, add) in [
        (
            "real",
            Hours {
                real: 1.0,
                synth: 0.0,
            },
        ),
        (
            "synth",
            Hours {
                real: 0.0,
                synth: 1.0,
            },
        ),
    ] {
        for more in [1.0, 10.0] {
            let h = Hours {
                real: hours.real + more * add.real,
                synth: hours.synth + more * add.synth,
            };
            let (mut dl, mut ratio) = (Vec::new(), Vec::new());
            for (law, base) in laws.iter().zip(&optima) {
                let better = law.optimum(budget, h).loss;
                dl.push(better - base.loss);
                ratio.push(law.compute_for(better, budget, hours) / budget);
            }
            let (compute_equivalent, unbuyable) = unbounded_estimate(&ratio);
            hour_values.push(HourValue {
                source: source.into(),
                hours: more,
                loss_change: estimate(&dl),
                compute_equivalent,
                unbuyable,
            });
        }
    }
    let p = &optima[0];
    let n_opt = of(|o| o.n);
    let stops: Option<Vec<f64>> = laws
        .iter()
        .zip(&optima)
        .map(|(l, o)| l.stopping.map(|c| stop_epochs(&c, o.n, u)))
        .collect();
    let stop_epochs = stops.map(|v| estimate(&v));
    let mut verdicts = verdicts(&n_opt, &hour_values, rd.draws.len());
    if rd.exchange.is_none() && hours.synth > 0.0 {
        verdicts.push(
            "ρ was not fitted (every run had the same synthetic share): a synthetic hour counts as a captured one here, an assumption the runs do not test".into(),
        );
    }
    if let Some(e) = stop_epochs.as_ref().filter(|e| e.value * u < p.d) {
        verdicts.push(format!(
            "N_opt stops improving after {:.1} of the {:.1} epochs C buys: the last {:.0}% of the compute buys nothing on these hours",
            e.value,
            p.d / u,
            100.0 * (1.0 - e.value * u / p.d)
        ));
    }
    Ok(DataPrediction {
        budget,
        hours,
        unique_tokens: u,
        vocab: rd.vocab,
        verdicts,
        n_opt,
        n_v: p.n_v,
        d: of(|o| o.d),
        epochs: estimate(&optima.iter().map(|o| o.d / u).collect::<Vec<_>>()),
        stop_epochs,
        loss: of(|o| o.loss),
        loss_prediction: scatter(rd).map(|sd| predictive(&loss_values(&optima), sd)),
        spends: 6.0 * (p.n + p.n_v) * p.d / budget,
        hour_values,
    })
}

/// One model size at (C, hours): the loss the law gives it, trained on C's tokens (with early
/// stopping, up to e*).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SizeLoss {
    /// N (the fit's N column).
    pub n: f64,
    /// D / U: the epochs C buys this size.
    pub epochs: f64,
    /// With early stopping: e*, the epochs after which this size stops improving (point law).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_epochs: Option<f64>,
    /// The law's loss: 95% interval of the refits.
    pub loss: Estimate,
    /// The 95% prediction interval of one run's loss (absent without the fit's scatter).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub loss_prediction: Option<Estimate>,
}

/// `predict --sizes`: the sizes one can train at (C, hours), and the best of them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SizeLosses {
    /// Each size asked about, in the order given.
    pub sizes: Vec<SizeLoss>,
    /// The best of them: the point law's lowest, its loss the lowest of the sizes at each
    /// refit (what a ladder scores a cell by: its best run).
    pub best: SizeLoss,
}

/// The loss of each of `sizes` at `budget` and `hours`, and of the best of them.
pub fn size_losses(
    rd: &RepeatedData,
    budget: f64,
    hours: Hours,
    sizes: &[f64],
) -> Result<SizeLosses, String> {
    if let Some(bad) = sizes.iter().find(|n| !(n.is_finite() && **n > 0.0)) {
        return Err(format!(
            "--sizes {bad}: a model size must be a positive number of parameters"
        ));
    }
    if sizes.is_empty() {
        return Err("--sizes: give at least one model size".into());
    }
    let laws = laws(rd)?;
    let sd = scatter(rd);
    let u = laws[0].unique_tokens(hours);
    let at: Vec<Vec<Optimum>> = sizes
        .iter()
        .map(|&n| laws.iter().map(|l| l.at(budget, n, hours)).collect())
        .collect();
    let size_loss = |n: f64, d: f64, losses: Vec<f64>| SizeLoss {
        n,
        epochs: d / u,
        stop_epochs: laws[0].stopping.map(|c| stop_epochs(&c, n, u)),
        loss: estimate(&losses),
        loss_prediction: sd.map(|sd| predictive(&losses, sd)),
    };
    let each: Vec<SizeLoss> = at
        .iter()
        .map(|o| size_loss(o[0].n, o[0].d, loss_values(o)))
        .collect();
    let lowest: Vec<f64> = (0..laws.len())
        .map(|k| at.iter().map(|o| o[k].loss).fold(f64::INFINITY, f64::min))
        .collect();
    let point = (0..sizes.len())
        .min_by(|&a, &b| at[a][0].loss.total_cmp(&at[b][0].loss))
        .unwrap_or(0);
    let best = size_loss(at[point][0].n, at[point][0].d, lowest);
    Ok(SizeLosses { sizes: each, best })
}

/// Each law's loss at its optimum.
fn loss_values(optima: &[Optimum]) -> Vec<f64> {
    optima.iter().map(|o| o.loss).collect()
}

/// The log-space SD of one run about the law: √(σ² + τ²), the within-budget scatter and the
/// budgets' shared misfit of the fit's residuals.
fn scatter(rd: &RepeatedData) -> Option<f64> {
    rd.information
        .as_ref()
        .map(|i| (i.sigma2 + i.tau2).sqrt())
        .filter(|s| s.is_finite())
}

/// A 95% prediction interval for one run: each refit's value (`values[1..]`; the point law's
/// where there are none) spread in log space by `sd` at 101 normal quantiles, and the point
/// law's value.
fn predictive(values: &[f64], sd: f64) -> Estimate {
    let normal = Normal::standard();
    let z: Vec<f64> = (0..101)
        .map(|j| normal.inverse_cdf((j as f64 + 0.5) / 101.0))
        .collect();
    let refits = if values.len() > 1 {
        &values[1..]
    } else {
        values
    };
    let spread: Vec<f64> = refits
        .iter()
        .flat_map(|v| z.iter().map(move |z| v * (sd * z).exp()))
        .collect();
    with_draws(values[0], &spread)
}

/// The law's 95% prediction interval against the best loss of every (budget, data subset)
/// cell of its frontier: how often the runs it was fitted on fall inside. `None` without
/// the Laplace information (the scatter) or tokens per hour.
pub fn in_sample_coverage(rd: &RepeatedData) -> Option<InSampleCoverage> {
    let sd = scatter(rd)?;
    let laws = laws(rd).ok()?;
    let misses: Vec<CellMiss> = rd
        .frontier
        .iter()
        .filter_map(|cell| {
            let u = cell.unique_tokens / laws[0].tokens_per_hour;
            let hours = Hours {
                real: u * (1.0 - cell.synth_share),
                synth: u * cell.synth_share,
            };
            let losses: Vec<f64> = laws
                .iter()
                .map(|l| l.optimum(cell.budget, hours).loss)
                .collect();
            let predicted = predictive(&losses, sd);
            let inside = matches!(
                (predicted.ci_low, predicted.ci_high),
                (Some(lo), Some(hi)) if (lo..=hi).contains(&cell.loss)
            );
            (!inside).then_some(CellMiss {
                budget: cell.budget,
                unique_tokens: cell.unique_tokens,
                synth_share: cell.synth_share,
                loss: cell.loss,
                predicted,
            })
        })
        .collect();
    Some(InSampleCoverage {
        cells: rd.frontier.len(),
        covered: rd.frontier.len() - misses.len(),
        scatter: sd,
        misses,
    })
}

/// Plain sentences on what the intervals allow.
fn verdicts(n_opt: &Estimate, values: &[HourValue], draws: usize) -> Vec<String> {
    if draws == 0 {
        return vec![
            "the fit kept no bootstrap refits: no intervals, nothing here is pinned".into(),
        ];
    }
    let mut out = Vec::new();
    if let (Some(lo), Some(hi)) = (n_opt.ci_low, n_opt.ci_high) {
        let decades = (hi / lo).log10();
        out.push(match decades > 1.0 {
            true => format!("N_opt's 95% interval spans {decades:.1} decades: too wide to act on"),
            false => format!("N_opt's 95% interval spans {decades:.2} decades"),
        });
    }
    for v in values.iter().filter(|v| v.hours == 1.0) {
        let (Some(lo), Some(hi)) = (v.loss_change.ci_low, v.loss_change.ci_high) else {
            continue;
        };
        out.push(match lo < 0.0 && hi > 0.0 {
            true => format!("+1 h of {} motion: the sign of its value is not resolved (its interval contains 0)", v.source),
            false => format!("+1 h of {} motion: its value is resolved (interval [{lo:.4}, {hi:.4}])", v.source),
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fitted::{LawEstimates, StoppingRule};
    use crate::lbfgs::Termination;

    /// A fit with known parameters (E, A, B, α, β, R*_D, ρ, R*_N) and three refits around
    /// them.
    fn fit(theta: [f64; 8]) -> RepeatedData {
        let jitter = |f: f64| {
            let mut t = theta;
            t[3] *= f;
            t[4] *= f;
            t
        };
        RepeatedData {
            block_intervals: Vec::new(),
            law: LawEstimates::from_fn(|k| Estimate::exact(theta[k])),
            r_star: Estimate::exact(theta[5]),
            r_star_n: Some(Estimate::exact(theta[7])),
            past_base_size: 0,
            note_n: None,
            exchange: Some(Estimate::exact(theta[6])),
            exchange_form: ExchangeForm::TokenWorth,
            exchange_forms: Vec::new(),
            in_sample: None,
            n_runs: 0,
            repeated_runs: 0,
            max_epochs: 0.0,
            objective: 0.0,
            termination: Termination::Gradient,
            bootstrap: [3, 3],
            held_out: None,
            note: None,
            draws: vec![jitter(0.98), theta, jitter(1.02)],
            frontier: Vec::new(),
            tokens_per_hour: Some(36_000.0),
            nv_line: Some([1.0, 0.5]),
            vocab: Some(1000.0),
            information: None,
            stopping: None,
        }
    }

    // A = βB/α: the law allocates U_N = U^(β/α) = U^0.82 parameters to U unique tokens
    // (8.9e4 for 10^6), so that R*_N = 5 bites above 5e5.
    const THETA: [f64; 8] = [1.2, 330.0, 400.0, 0.34, 0.28, 15.0, 0.4, 5.0];

    #[test]
    fn compute_stops_paying_past_the_saturation_budget() {
        let rd = fit(THETA);
        let h = Hours {
            real: 2.0,
            synth: 0.0,
        };
        let small = data_bound(&rd, 1e10, h, 0.01).unwrap();
        assert!(!small.bound, "{small:?}");
        let c_sat = small.saturation.value;
        let law = laws(&rd).unwrap()[0];
        let gain = law.optimum(c_sat, h).loss - law.optimum(1e6 * c_sat, h).loss;
        assert!(
            (gain - 0.01).abs() < 1e-3,
            "past C_sat compute buys the seed SD: {gain}"
        );
        let big = data_bound(&rd, 10.0 * c_sat, h, 0.01).unwrap();
        assert!(big.bound && big.doubling.value < 0.0, "{big:?}");
        assert!(data_bound(&rd, 1e15, h, 0.0)
            .unwrap_err()
            .contains("--noise"));
    }

    /// With ρ not fitted (every run one synthetic share) the prediction says that a
    /// synthetic hour was counted as a captured one, and only where synthetic hours are given.
    #[test]
    fn an_unfitted_exchange_rate_is_named_as_an_assumption() {
        let mut theta = THETA;
        theta[6] = 1.0;
        let mut rd = fit(theta);
        rd.exchange = None;
        let flagged = |synth: f64| {
            let p = predict_data(&rd, 1e15, Hours { real: 20.0, synth }).unwrap();
            p.verdicts.iter().any(|v| v.contains("ρ was not fitted"))
        };
        assert!(flagged(10.0));
        assert!(!flagged(0.0));
    }

    #[test]
    fn the_optimum_spends_the_budget_and_beats_its_neighbours() {
        let rd = fit(THETA);
        let h = Hours {
            real: 20.0,
            synth: 10.0,
        };
        let p = predict_data(&rd, 1e15, h).unwrap();
        assert!((p.spends - 1.0).abs() < 0.05, "{}", p.spends);
        let law = laws(&rd).unwrap()[0];
        for f in [0.8, 1.25] {
            assert!(law.at(1e15, p.n_opt.value * f, h).loss > p.loss.value);
        }
        assert!((p.unique_tokens - 30.0 * 36_000.0).abs() < 1e-6);
        assert!((p.epochs.value - p.d.value / p.unique_tokens).abs() < 1e-9);
        let (lo, hi) = (p.n_opt.ci_low.unwrap(), p.n_opt.ci_high.unwrap());
        assert!(lo <= p.n_opt.value && p.n_opt.value <= hi);
    }

    #[test]
    fn each_size_gets_its_loss_and_the_best_is_the_lowest_at_every_refit() {
        // e* falls with N: past saturation a size too large for the data stops early, on fewer
        // tokens, and the law gives it a higher loss than N_opt's.
        let mut rd = fit(THETA);
        let coef = [8.0, -0.3, 0.0];
        rd.stopping = Some(StoppingRule {
            coef,
            se: [0.0; 3],
            runs: 10,
            residual_sd: 0.1,
            draws: vec![coef; 3],
        });
        let h = Hours {
            real: 2.0,
            synth: 1.0,
        };
        let c = 1e18;
        let n_opt = predict_data(&rd, c, h).unwrap().n_opt.value;
        let sizes = [n_opt, 30.0 * n_opt, n_opt / 30.0];
        let got = size_losses(&rd, c, h, &sizes).unwrap();
        let law = laws(&rd).unwrap()[0];
        for (s, &n) in got.sizes.iter().zip(&sizes) {
            assert_eq!(s.n, n);
            assert!((s.loss.value - law.at(c, n, h).loss).abs() < 1e-12);
            assert_eq!(
                s.stop_epochs,
                Some(stop_epochs(&coef, n, law.unique_tokens(h)))
            );
            assert!(
                s.epochs > s.stop_epochs.unwrap(),
                "past saturation every size stops early"
            );
            assert!(s.loss.ci_low.unwrap() <= s.loss.ci_high.unwrap());
        }
        assert!(
            got.sizes[1].loss.value > got.sizes[0].loss.value,
            "too large for the data"
        );
        assert!(
            got.sizes[2].loss.value > got.sizes[0].loss.value,
            "too small"
        );
        assert_eq!(got.best.n, n_opt);
        assert_eq!(got.best.loss.value, got.sizes[0].loss.value);
        for s in &got.sizes {
            assert!(got.best.loss.ci_high.unwrap() <= s.loss.ci_high.unwrap());
        }
        for bad in [vec![], vec![1e6, 0.0], vec![f64::NAN]] {
            assert!(size_losses(&rd, c, h, &bad)
                .unwrap_err()
                .contains("--sizes"));
        }
    }

    #[test]
    fn an_hour_of_real_motion_is_worth_more_than_one_of_synthetic_at_rho_below_one() {
        // Below the budgets where N' and D' saturate and compute stops buying loss.
        const C: f64 = 1e14;
        let p = predict_data(
            &fit(THETA),
            C,
            Hours {
                real: 20.0,
                synth: 10.0,
            },
        )
        .unwrap();
        let value = |source: &str, hours: f64| {
            p.hour_values
                .iter()
                .find(|v| v.source == source && v.hours == hours)
                .unwrap()
                .clone()
        };
        let (real, synth) = (value("real", 1.0), value("synth", 1.0));
        assert!(real.loss_change.value < synth.loss_change.value && synth.loss_change.value < 0.0);
        assert!(value("real", 10.0).loss_change.value < real.loss_change.value);
        // More data is worth more than 1× compute, and the real hour more than the synthetic.
        assert!(
            real.compute_equivalent.value > synth.compute_equivalent.value,
            "{real:?} {synth:?}"
        );
        assert!(synth.compute_equivalent.value > 1.0);
        // The equivalent compute at today's hours reaches the same loss.
        let law = laws(&fit(THETA)).unwrap()[0];
        let h = Hours {
            real: 20.0,
            synth: 10.0,
        };
        let target = law
            .optimum(
                C,
                Hours {
                    real: 21.0,
                    synth: 10.0,
                },
            )
            .loss;
        let c = real.compute_equivalent.value * C;
        assert!((law.optimum(c, h).loss - target).abs() < 1e-6);
    }

    #[test]
    fn refits_that_no_budget_serves_rank_above_the_rest_and_are_counted() {
        let inf = f64::INFINITY;
        let (e, share) = unbounded_estimate(&[2.0, 1.0, inf, 3.0, inf]);
        assert_eq!((e.value, share), (2.0, 0.5));
        assert!((e.ci_low.unwrap() - 1.15).abs() < 1e-12, "{e:?}");
        assert_eq!(e.ci_high, None, "the upper end lies among the refits at ∞");
        let (e, share) = unbounded_estimate(&[2.0, 1.0, 3.0]);
        assert_eq!((e.ci_high, share), (Some(2.95), 0.0));
    }

    #[test]
    fn bad_budgets_and_hours_and_fits_without_hours_say_so() {
        let rd = fit(THETA);
        let h = Hours {
            real: 1.0,
            synth: 0.0,
        };
        assert!(predict_data(&rd, -1.0, h).unwrap_err().contains("--budget"));
        let none = Hours {
            real: 0.0,
            synth: 0.0,
        };
        assert!(predict_data(&rd, 1e15, none)
            .unwrap_err()
            .contains("need some hours"));
        let no_rate = RepeatedData {
            tokens_per_hour: None,
            ..rd
        };
        assert!(predict_data(&no_rate, 1e15, h)
            .unwrap_err()
            .contains("tokens per hour"));
    }
}
