//! Power laws y = k·x^p (OLS of log10 y on log10 x) and the log law L = α·log10 C + β, with
//! standard errors, 95% intervals, R², residuals, and interval-carrying evaluation.

use crate::ols::{t95, Line};
use serde::{Deserialize, Serialize};

/// A coefficient with its standard error and 95% interval (each `None` when not available).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// Point estimate (∞ where it diverged: JSON writes `null`, read back as ∞).
    #[serde(deserialize_with = "crate::planner::infinite_if_null")]
    pub value: f64,
    /// Standard error (OLS) where one exists.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub se: Option<f64>,
    /// Lower end of the 95% interval.
    pub ci_low: Option<f64>,
    /// Upper end of the 95% interval.
    pub ci_high: Option<f64>,
}

impl Estimate {
    /// A value without uncertainty (published coefficients).
    pub fn exact(value: f64) -> Self {
        Self {
            value,
            se: None,
            ci_low: None,
            ci_high: None,
        }
    }

    /// value ± t₀.₉₇₅(dof)·se.
    pub fn with_se(value: f64, se: Option<f64>, dof: usize) -> Self {
        let half = se.filter(|_| dof > 0).map(|s| t95(dof) * s);
        Self {
            value,
            se,
            ci_low: half.map(|h| value - h),
            ci_high: half.map(|h| value + h),
        }
    }
}

/// A straight-line fit y = intercept + slope·x (x, y possibly log10 of the quantities) with
/// what is needed for intervals at a new x.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LineFit {
    /// Intercept (log10 k for a power law, β for the log law).
    pub intercept: Estimate,
    /// Slope (the exponent for a power law, α for the log law).
    pub slope: Estimate,
    /// cov(intercept, slope).
    pub cov: Option<f64>,
    /// Points fitted.
    pub n_points: usize,
    /// Residual degrees of freedom (points − 2).
    pub dof: usize,
    /// R² of the line.
    pub r2: Option<f64>,
    /// Fitted points (x, y) in the line's space.
    pub points: Vec<[f64; 2]>,
    /// y − fitted, in the line's space.
    pub residuals: Vec<f64>,
}

impl LineFit {
    /// RMS of the residuals: the scatter of the points around the line, in the line's space
    /// (decades for a power law); `None` without points.
    pub fn scatter(&self) -> Option<f64> {
        let n = self.residuals.len();
        (n > 0).then(|| (self.residuals.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt())
    }

    /// OLS on (x, y); `None` with fewer than two distinct x.
    pub fn fit(x: &[f64], y: &[f64]) -> Option<Self> {
        let line = Line::fit(x, y)?;
        let dof = line.ols.dof;
        Some(Self {
            intercept: Estimate::with_se(line.intercept, line.ols.se(0), dof),
            slope: Estimate::with_se(line.slope, line.ols.se(1), dof),
            cov: line.ols.cov.as_ref().map(|c| c[0][1]),
            n_points: x.len(),
            dof,
            r2: line.ols.r2.is_finite().then_some(line.ols.r2),
            points: x.iter().zip(y).map(|(&a, &b)| [a, b]).collect(),
            residuals: line.ols.residuals.clone(),
        })
    }

    /// Published coefficients without uncertainty.
    pub fn exact(intercept: f64, slope: f64) -> Self {
        Self {
            intercept: Estimate::exact(intercept),
            slope: Estimate::exact(slope),
            cov: None,
            n_points: 0,
            dof: 0,
            r2: None,
            points: Vec::new(),
            residuals: Vec::new(),
        }
    }

    /// The fitted mean at `x` with its 95% confidence interval (when the fit carries SEs).
    pub fn at(&self, x: f64) -> Estimate {
        let value = self.intercept.value + self.slope.value * x;
        let se = match (self.intercept.se, self.slope.se, self.cov) {
            (Some(si), Some(ss), Some(c)) => {
                Some((si * si + x * x * ss * ss + 2.0 * x * c).max(0.0).sqrt())
            }
            _ => None,
        };
        Estimate::with_se(value, se, self.dof)
    }

    /// A new observation at `x` with its 95% prediction interval: the fitted mean's variance
    /// plus the residual variance (None without residual degrees of freedom).
    pub fn predict_at(&self, x: f64) -> Estimate {
        let mean = self.at(x);
        let residual_var = (self.dof > 0)
            .then(|| self.residuals.iter().map(|r| r * r).sum::<f64>() / self.dof as f64);
        let se = match (mean.se, residual_var) {
            (Some(s), Some(v)) => Some((s * s + v).sqrt()),
            _ => None,
        };
        Estimate::with_se(mean.value, se, self.dof)
    }
}

/// y = k·x^p, fitted as log10 y = log10 k + p·log10 x.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PowerLaw {
    /// What x is (e.g. `C`).
    pub x: String,
    /// What y is (e.g. `N_opt`).
    pub y: String,
    /// The line in log10–log10 space: intercept = log10 k, slope = p.
    pub fit: LineFit,
}

impl PowerLaw {
    /// Fits y = k·x^p to positive (x, y); `None` with fewer than two distinct x.
    pub fn fit(x_name: &str, y_name: &str, x: &[f64], y: &[f64]) -> Option<Self> {
        let lx: Vec<f64> = x.iter().map(|v| v.log10()).collect();
        let ly: Vec<f64> = y.iter().map(|v| v.log10()).collect();
        Some(Self {
            x: x_name.into(),
            y: y_name.into(),
            fit: LineFit::fit(&lx, &ly)?,
        })
    }

    /// Published y = 10^log10_k · x^exponent.
    pub fn exact(x_name: &str, y_name: &str, log10_k: f64, exponent: f64) -> Self {
        Self {
            x: x_name.into(),
            y: y_name.into(),
            fit: LineFit::exact(log10_k, exponent),
        }
    }

    /// The exponent p.
    pub fn exponent(&self) -> f64 {
        self.fit.slope.value
    }

    /// y at `x` with a 95% interval (from the log-space interval), in y's units.
    pub fn at(&self, x: f64) -> Estimate {
        unlog(self.fit.at(x.log10()))
    }

    /// A new y observed at `x`, with its 95% prediction interval, in y's units.
    pub fn predict_at(&self, x: f64) -> Estimate {
        unlog(self.fit.predict_at(x.log10()))
    }

    /// The law as text, e.g. `N_opt = 10^-0.520 · C^0.570`.
    pub fn equation(&self) -> String {
        format!(
            "{} = 10^{:.3} · {}^{:.3}",
            self.y, self.fit.intercept.value, self.x, self.fit.slope.value
        )
    }
}

/// An estimate of log10 y as one of y (the interval's ends mapped; no SE).
fn unlog(e: Estimate) -> Estimate {
    Estimate {
        value: 10f64.powf(e.value),
        se: None,
        ci_low: e.ci_low.map(|v| 10f64.powf(v)),
        ci_high: e.ci_high.map(|v| 10f64.powf(v)),
    }
}

/// L = α·log10 C + β (α = slope, β = intercept).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogLaw {
    /// The line in (log10 C, L) space.
    pub fit: LineFit,
}

impl LogLaw {
    /// Fits the log law to (C, L); `None` with fewer than two distinct C.
    pub fn fit(c: &[f64], loss: &[f64]) -> Option<Self> {
        let lc: Vec<f64> = c.iter().map(|v| v.log10()).collect();
        Some(Self {
            fit: LineFit::fit(&lc, loss)?,
        })
    }

    /// Published L = slope·log10 C + intercept.
    pub fn exact(slope: f64, intercept: f64) -> Self {
        Self {
            fit: LineFit::exact(intercept, slope),
        }
    }

    /// L at budget `c` with a 95% interval.
    pub fn at(&self, c: f64) -> Estimate {
        self.fit.at(c.log10())
    }

    /// A new minimum's L at budget `c`, with its 95% prediction interval.
    pub fn predict_at(&self, c: f64) -> Estimate {
        self.fit.predict_at(c.log10())
    }

    /// The law as text.
    pub fn equation(&self) -> String {
        format!(
            "L = {:.4} · log10 C + {:.4}",
            self.fit.slope.value, self.fit.intercept.value
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn power_law_is_exact_on_exact_data_and_interval_widens_away_from_data() {
        let c = [1e15, 1e16, 1e17, 1e18];
        let n: Vec<f64> = c
            .iter()
            .map(|v: &f64| 10f64.powf(-0.52) * v.powf(0.57))
            .collect();
        let law = PowerLaw::fit("C", "N_opt", &c, &n).unwrap();
        assert!((law.exponent() - 0.57).abs() < 1e-12);
        assert!((law.fit.intercept.value + 0.52).abs() < 1e-9);
        let at = law.at(1e18);
        assert!((at.value / (10f64.powf(-0.52) * 1e18f64.powf(0.57)) - 1.0).abs() < 1e-9);

        // Noisy points: the interval at the data's centre is narrower than far outside it.
        let noisy = [1.0, 1.9, 3.2, 3.9, 5.1];
        let fit = LineFit::fit(&[0.0, 1.0, 2.0, 3.0, 4.0], &noisy).unwrap();
        let width = |x: f64| {
            let e = fit.at(x);
            e.ci_high.unwrap() - e.ci_low.unwrap()
        };
        assert!(width(2.0) < width(10.0));
        // At the centre the SE of the mean is σ/√n.
        let s2: f64 = fit.residuals.iter().map(|r| r * r).sum::<f64>() / 3.0;
        assert!((fit.at(2.0).se.unwrap() - (s2 / 5.0).sqrt()).abs() < 1e-12);
        // A new observation adds the residual variance: at the centre σ·√(1 + 1/n).
        let new = fit.predict_at(2.0);
        assert!((new.se.unwrap() - (s2 * (1.0 + 1.0 / 5.0)).sqrt()).abs() < 1e-12);
        assert!(new.ci_high.unwrap() - new.ci_low.unwrap() > width(2.0));
    }

    #[test]
    fn published_law_has_no_interval() {
        let law = LogLaw::exact(-1.062, 13.839);
        let l = law.at(1e18);
        assert!((l.value - (-1.062 * 18.0 + 13.839)).abs() < 1e-12);
        assert_eq!(l.ci_low, None);
    }
}
