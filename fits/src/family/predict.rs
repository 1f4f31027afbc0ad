//! `predict` on a `laws.json`: the adopted family's compute-optimal N and D at a budget and
//! the loss there, each with a 95% interval over the bootstrap refits. The loss's interval is
//! a prediction interval: each refit's loss is offset by a residual of the fit drawn at
//! random, so it holds the runs' own scatter as well as the law's uncertainty.

use super::engine::Space;
use super::run::LawReport;
use super::{family, Axis, Point};
use crate::laws::Estimate;
use crate::parametric::percentile;
use crate::FitError;
use motionscale_core::rng::SplitMix64;
use serde::Serialize;

/// The adopted family's answer at one budget.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FamilyPrediction {
    /// The family.
    pub law: String,
    /// Budget C in FLOPs (C = 6·(N + N_v)·D).
    pub compute: f64,
    /// Unique tokens held, where the law reads them.
    pub unique_tokens: Option<f64>,
    /// Vocabulary parameters held, where the law reads them.
    pub vocab_params: Option<f64>,
    /// Compute-optimal N.
    pub n: Estimate,
    /// Its D.
    pub d: Estimate,
    /// The loss there (a prediction interval).
    pub loss: Estimate,
    /// Bootstrap refits with an allocation, of those in the fit.
    pub draws: usize,
}

/// The adopted family of `report` at budget `c`, with the U and N_v of `at` where it reads them.
pub fn predict_at(report: &LawReport, c: f64, at: Point) -> Result<FamilyPrediction, FitError> {
    let fit = report
        .fits
        .iter()
        .find(|f| f.law == report.adopted)
        .ok_or_else(|| {
            FitError::Invalid(format!("no fit of the adopted law {}", report.adopted))
        })?;
    let fam =
        family(&fit.law).ok_or_else(|| FitError::Invalid(format!("unknown law {:?}", fit.law)))?;
    let cannot = |needs: &str| FitError::CannotFit {
        fit: "predict with a law family",
        needs: format!("the adopted law ({}) reads {needs}", fit.law),
    };
    if fam.needs().contains(&Axis::U) && at.u.is_none() {
        return Err(cannot("unique tokens U: give --unique-tokens"));
    }
    if fam.needs().contains(&Axis::Nv) && at.nv.is_none() {
        return Err(cannot("vocabulary parameters N_v: give --vocab-params"));
    }
    if fam.needs().contains(&Axis::S) && at.s.is_none() {
        return Err(cannot("the synthetic share s: give --synth-share"));
    }
    if !(c.is_finite() && c > 0.0) {
        return Err(FitError::BadOption {
            flag: "--budget".into(),
            problem: format!("{c}: must be a positive number of FLOPs"),
        });
    }
    let best = fam
        .allocation(&fit.theta, c, &at)
        .ok_or_else(|| cannot("an N at which the loss is finite"))?;
    let mut rng = SplitMix64::stream(0x9ed, c.to_bits());
    let (mut n, mut d, mut loss) = (Vec::new(), Vec::new(), Vec::new());
    for theta in &fit.draws {
        let Some(a) = fam.allocation(theta, c, &at) else {
            continue;
        };
        let r = fit.residuals[rng.index(fit.residuals.len())];
        n.push(a.n);
        d.push(a.d);
        loss.push(match fit.space {
            Space::Log => a.loss * (-r).exp(),
            Space::Loss => a.loss - r,
        });
    }
    let estimate = |value: f64, v: &[f64]| Estimate {
        value,
        se: None,
        ci_low: percentile(v, 0.025),
        ci_high: percentile(v, 0.975),
    };
    Ok(FamilyPrediction {
        law: fit.law.clone(),
        compute: c,
        unique_tokens: at.u.filter(|_| fam.needs().contains(&Axis::U)),
        vocab_params: at.nv.filter(|_| fam.needs().contains(&Axis::Nv)),
        n: estimate(best.n, &n),
        d: estimate(best.d, &d),
        loss: estimate(best.loss, &loss),
        draws: n.len(),
    })
}
