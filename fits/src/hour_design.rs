//! The planner's `hour_value` target: what one more hour of captured motion is worth at a
//! budget C* (the loss change with the model re-optimised, `data_value`), and the runs that
//! narrow its interval most per FLOP.
//!
//! The posterior is a Laplace (Gauss–Newton) approximation of the data-constrained fit
//! (`repeated`) at its optimum θ̂: Cov θ ≈ (JᵀV⁻¹J)⁻¹, J the fitted runs' gradients of ln L̂.
//! V models the log residuals, the law's misfit included and not only seed noise: each budget's
//! runs share a misfit of variance τ² beside their own σ² (the residuals of our sweeps are offset
//! by ±0.03–0.05 per budget), so a budget's runs inform less than independent runs would. The
//! target q(θ) has gradient g (central differences), and its 95% interval is
//! q̂ ± 1.96·√(gᵀ(JᵀV⁻¹J)⁻¹g); a misfit shared at C* cancels in q, a difference of two losses
//! there. A run adds its row j to J whatever loss it reaches: in the
//! linearised model the width after a set of runs does not depend on their outcomes, so it is
//! computed, not averaged over predicted outcomes as the IsoFLOP target's bootstrap must be.
//! Runs are chosen greedily by the width they remove per FLOP (c-optimal design, Chaloner &
//! Verdinelli 1995), among sizes near the law's own optimum for their budget and data: far from
//! it the linearised law would value runs (a large model trained for a few steps) whose loss it
//! does not describe.

use crate::data_value::{fitted_law, hour_loss_change, optimal_size, Hours};
use crate::fitted::ExchangeForm;
use crate::fitted::RepeatedData;
use crate::ols::Z95;
use crate::planner::{Proposal, GROUP_TOL_DEX, SIZE_WINDOW_DEX};
use crate::repeated::{coordinates, natural, NaturalLaw};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Central-difference step in θ (logs and exponents, all of order one).
const STEP: f64 = 1e-4;

/// A run the planner may propose, as the data-constrained law sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct DataCandidate {
    /// Run id.
    pub id: String,
    /// Budget C.
    pub budget: f64,
    /// Model size N (the fit's N column).
    pub n: f64,
    /// Tokens it trains on, D.
    pub d: f64,
    /// Unique tokens of its data, U.
    pub u: f64,
    /// Synthetic share of its unique data.
    pub synth: f64,
    /// FLOPs it costs.
    pub cost: f64,
}

/// The target's Laplace posterior: the fitted law's value and its 95% interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HourPosterior {
    /// q(θ̂): the loss change of +1 h of captured motion (negative: better).
    pub value: f64,
    /// 2.5% quantile.
    pub low: f64,
    /// 97.5% quantile.
    pub high: f64,
    /// high − low, nats.
    pub width: f64,
}

/// One budget group's runs in the linearised fit.
#[derive(Debug, Clone)]
struct Group {
    log_c: f64,
    runs: f64,
    jtj: DMatrix<f64>,
    sum: DVector<f64>,
}

/// The linearised fit: the target's gradient and the information, by budget group.
struct Design {
    law: [f64; 8],
    form: ExchangeForm,
    free: Vec<usize>,
    groups: Vec<Group>,
    sigma2: f64,
    tau2: f64,
    value: f64,
    gradient: DVector<f64>,
}

impl Design {
    fn new(rd: &RepeatedData, budget: f64, hours: Hours) -> Result<Self, String> {
        let info = rd.information.as_ref().ok_or(
            "the data-constrained fit has no Laplace information (refit with this version of `fit --repeated-data`)",
        )?;
        let law = fitted_law(rd);
        let more = Hours {
            real: 1.0,
            synth: 0.0,
        };
        let q = |nat: [f64; 8]| hour_loss_change(rd, nat, budget, hours, more);
        let t = coordinates(&law);
        let p = info.free.len();
        let mut gradient = DVector::zeros(p);
        for (a, &k) in info.free.iter().enumerate() {
            let (mut up, mut down) = (t, t);
            up[k] += STEP;
            down[k] -= STEP;
            gradient[a] = (q(natural(&up, true))? - q(natural(&down, true))?) / (2.0 * STEP);
        }
        let groups = info
            .budgets
            .iter()
            .map(|b| Group {
                log_c: b.budget.log10(),
                runs: b.runs as f64,
                jtj: DMatrix::from_fn(p, p, |i, j| b.jtj[i][j]),
                sum: DVector::from_column_slice(&b.sum),
            })
            .collect();
        Ok(Self {
            law,
            form: rd.exchange_form,
            free: info.free.clone(),
            groups,
            sigma2: info.sigma2.max(f64::MIN_POSITIVE),
            tau2: info.tau2,
            value: q(law)?,
            gradient,
        })
    }

    /// Jᵀ V⁻¹ J with V block-diagonal by budget, each block σ²·I + τ²·11ᵀ.
    fn information(&self, groups: &[Group]) -> DMatrix<f64> {
        let p = self.free.len();
        groups.iter().fold(DMatrix::zeros(p, p), |acc, g| {
            let shared = self.tau2 / (self.sigma2 + g.runs * self.tau2);
            acc + (&g.jtj - &g.sum * g.sum.transpose() * shared) / self.sigma2
        })
    }

    /// The 95% width with the runs of `groups`; `None` where the information is singular.
    fn width(&self, groups: &[Group]) -> Option<f64> {
        let x = self.information(groups).cholesky()?.solve(&self.gradient);
        Some(2.0 * Z95 * self.gradient.dot(&x).max(0.0).sqrt())
    }

    /// `groups` with a candidate's run added to its budget's group (or a new one).
    fn with_run(&self, groups: &[Group], c: &DataCandidate) -> Vec<Group> {
        let law = NaturalLaw {
            theta: self.law,
            form: self.form,
        };
        let g = law.log_loss_gradient(c.n, c.d, c.u, c.synth);
        let row = DVector::from_iterator(self.free.len(), self.free.iter().map(|&k| g[k]));
        let mut out = groups.to_vec();
        let x = c.budget.log10();
        let at = match out
            .iter()
            .position(|g| (g.log_c - x).abs() <= GROUP_TOL_DEX)
        {
            Some(i) => i,
            None => {
                let p = self.free.len();
                out.push(Group {
                    log_c: x,
                    runs: 0.0,
                    jtj: DMatrix::zeros(p, p),
                    sum: DVector::zeros(p),
                });
                out.len() - 1
            }
        };
        let g = &mut out[at];
        g.runs += 1.0;
        g.jtj += &row * row.transpose();
        g.sum += &row;
        out
    }

    /// Whether the candidate's N is within [`SIZE_WINDOW_DEX`] of the law's optimum for its
    /// budget and data.
    fn near_optimum(&self, rd: &RepeatedData, c: &DataCandidate) -> Result<bool, String> {
        let tokens_per_hour = rd.tokens_per_hour.unwrap_or(1.0);
        let h = c.u / tokens_per_hour;
        let own = Hours {
            real: h * (1.0 - c.synth),
            synth: h * c.synth,
        };
        let best = optimal_size(rd, self.law, c.budget, own)?;
        Ok((c.n / best).log10().abs() <= SIZE_WINDOW_DEX)
    }

    fn posterior(&self) -> Result<HourPosterior, String> {
        let width = self
            .width(&self.groups)
            .ok_or("the fit's information matrix is singular: a coordinate is not identified")?;
        Ok(HourPosterior {
            value: self.value,
            low: self.value - width / 2.0,
            high: self.value + width / 2.0,
            width,
        })
    }
}

/// The Laplace posterior of +1 h of captured motion at `budget` with `hours` today.
pub fn hour_posterior(
    rd: &RepeatedData,
    budget: f64,
    hours: Hours,
) -> Result<HourPosterior, String> {
    Design::new(rd, budget, hours)?.posterior()
}

/// Up to `k` runs of `candidates`, within `max_compute` FLOPs, that narrow the hour value's
/// interval most per FLOP, each chosen with the earlier ones added; with the posterior now.
pub fn propose_hours(
    rd: &RepeatedData,
    candidates: &[DataCandidate],
    budget: f64,
    hours: Hours,
    k: usize,
    max_compute: f64,
) -> Result<(HourPosterior, Vec<Proposal>), String> {
    let design = Design::new(rd, budget, hours)?;
    let now = design.posterior()?;
    let (mut groups, mut before, mut room) = (design.groups.clone(), now.width, max_compute);
    let mut open = Vec::new();
    for (i, c) in candidates.iter().enumerate() {
        if design.near_optimum(rd, c)? {
            open.push(i);
        }
    }
    let mut out = Vec::new();
    while out.len() < k {
        let scored = open
            .iter()
            .filter(|&&i| candidates[i].cost <= room)
            .filter_map(|&i| {
                let with = design.with_run(&groups, &candidates[i]);
                let after = design.width(&with)?;
                Some((i, with, after, (before - after) / candidates[i].cost))
            })
            .filter(|s| s.3 > 0.0)
            .max_by(|a, b| a.3.total_cmp(&b.3));
        let Some((i, with, after, rate)) = scored else {
            break;
        };
        let c = &candidates[i];
        out.push(Proposal {
            runs: vec![i],
            cost: c.cost,
            width_before: before,
            expected_width: after,
            why: format!(
                "N {:.3e}, {:.1} epochs of {:.3e} unique tokens ({:.0}% synthetic): width {before:.3e} → {after:.3e} nats ({:+.2e} per 10^12 FLOPs)",
                c.n,
                c.d / c.u,
                c.u,
                100.0 * c.synth,
                -rate * 1e12
            ),
        });
        (groups, before, room) = (with, after, room - c.cost);
        open.retain(|&j| j != i);
    }
    Ok((now, out))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data_value::predict_data;
    use crate::fitted::FitOptions;
    use crate::parametric::StartGrid;
    use crate::repeated::NaturalLaw;
    use crate::{fit_table, Table};
    use motionscale_core::rng::SplitMix64;
    use std::fmt::Write;

    /// (E, A, B, α, β, R*_D, ρ, R*_N) of the synthetic runs.
    const TRUTH: [f64; 8] = [1.2, 60.0, 400.0, 0.35, 0.3, 6.0, 0.3, f64::INFINITY];
    const TOKENS_PER_HOUR: f64 = 36_000.0;
    const NOISE: f64 = 0.01;

    /// A run of the ladders: (C, N, U, synthetic share).
    type Run = (f64, f64, f64, f64);

    /// A captured-only and a half-synthetic ladder at two corpus sizes each, 5 sizes per budget.
    fn ladders(budgets: &[f64]) -> Vec<Run> {
        let mut out = Vec::new();
        for (u, share) in [(5e6, 0.0), (2e7, 0.0), (1e7, 0.5), (4e7, 0.5)] {
            for &c in budgets {
                out.extend((0..5).map(|k| (c, 10f64.powf(4.0 + 0.5 * k as f64), u, share)));
            }
        }
        out
    }

    /// The runs' losses under TRUTH with log-normal misfit (run i draws stream i), fitted.
    fn fitted(dir: &std::path::Path, runs: &[Run]) -> RepeatedData {
        let mut csv =
            String::from("budget,n_nv,tokens,test_loss,norm_test_loss,epochs,synth_share,hours\n");
        for (i, &(c, n, u, share)) in runs.iter().enumerate() {
            let d = c / (6.0 * n);
            let noise = NOISE * SplitMix64::stream(7, i as u64).normal();
            let truth = NaturalLaw {
                theta: TRUTH,
                form: ExchangeForm::TokenWorth,
            };
            let l = truth.loss(n, d, u, share) * noise.exp();
            let h = u / TOKENS_PER_HOUR;
            let _ = writeln!(csv, "{c},{n},{d},{l},{l},{},{share},{h}", d / u);
        }
        let path = dir.join("results.csv");
        std::fs::write(&path, csv).unwrap();
        let opts = FitOptions {
            grid: StartGrid::coarse(),
            grid_name: "coarse".into(),
            bootstrap: 60,
            repeated_data: true,
            ..FitOptions::default()
        };
        let fits = fit_table(&Table::read(&path).unwrap(), &opts).unwrap();
        fits.repeated_data.expect("fitted")
    }

    fn candidate((c, n, u, share): Run, id: usize) -> DataCandidate {
        DataCandidate {
            id: format!("r{id}"),
            budget: c,
            n,
            d: c / (6.0 * n),
            u,
            synth: share,
            cost: c,
        }
    }

    const BUDGET: f64 = 1e16;
    const HOURS: Hours = Hours {
        real: 300.0,
        synth: 300.0,
    };

    /// The refits' 95% interval width of +1 h captured (`predict --hours`).
    fn refit_width(rd: &RepeatedData) -> f64 {
        let p = predict_data(rd, BUDGET, HOURS).unwrap();
        let v = &p.hour_values[0];
        assert_eq!((v.source.as_str(), v.hours), ("real", 1.0));
        let e = &v.loss_change;
        e.ci_high.expect("refits give an interval") - e.ci_low.expect("and a low end")
    }

    #[test]
    fn the_laplace_interval_of_an_hour_agrees_with_the_refits_and_covers_the_truth() {
        let dir = tempfile::tempdir().unwrap();
        let rd = fitted(dir.path(), &ladders(&[1e13, 1e14, 1e15]));
        let laplace = hour_posterior(&rd, BUDGET, HOURS).unwrap();
        let truth = hour_loss_change(
            &rd,
            TRUTH,
            BUDGET,
            HOURS,
            Hours {
                real: 1.0,
                synth: 0.0,
            },
        )
        .unwrap();
        assert!(truth < 0.0, "an hour helps: {truth}");
        assert!(
            laplace.low < truth && truth < laplace.high,
            "{laplace:?} vs {truth}"
        );
        let ratio = laplace.width / refit_width(&rd);
        assert!(
            (0.5..2.0).contains(&ratio),
            "Laplace / refits width {ratio}"
        );
    }

    #[test]
    fn runs_chosen_for_the_hour_value_narrow_the_refits_more_than_random_ones() {
        let all = ladders(&[1e13, 1e14, 1e15]);
        // Trained: every ladder below 1e15; open: the 1e15 runs.
        let (trained, open): (Vec<Run>, Vec<Run>) = all.iter().partition(|r| r.0 < 1e15);
        let dir = tempfile::tempdir().unwrap();
        let rd = fitted(dir.path(), &trained);
        let pool: Vec<DataCandidate> = open
            .iter()
            .enumerate()
            .map(|(i, &r)| candidate(r, i))
            .collect();
        let (now, chosen) = propose_hours(&rd, &pool, BUDGET, HOURS, 3, f64::INFINITY).unwrap();
        assert_eq!(chosen.len(), 3, "{chosen:?}");
        let widths: Vec<f64> = chosen.iter().map(|p| p.expected_width).collect();
        assert!(
            now.width > widths[0] && widths[0] > widths[1] && widths[1] > widths[2],
            "{now:?} {widths:?}"
        );
        let width_with = |picks: &[usize]| {
            let mut runs = trained.clone();
            runs.extend(picks.iter().map(|&i| open[i]));
            refit_width(&fitted(dir.path(), &runs))
        };
        let planned = width_with(&chosen.iter().map(|p| p.runs[0]).collect::<Vec<_>>());
        let mut random: Vec<f64> = (0..3)
            .map(|s| {
                let mut rng = SplitMix64::stream(11, s);
                let mut picks: Vec<usize> = Vec::new();
                while picks.len() < 3 {
                    let i = rng.index(open.len());
                    if !picks.contains(&i) {
                        picks.push(i);
                    }
                }
                width_with(&picks)
            })
            .collect();
        random.sort_by(f64::total_cmp);
        assert!(
            planned < random[1],
            "planned {planned} vs random {random:?}"
        );
    }
}
