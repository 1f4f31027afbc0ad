//! The shape of the loss law over the IsoFLOP minima: the straight log law L = a + b·log10 C
//! against a curved one (+ c·log10² C) and one with a floor (L = E + A·10^(−k·(log10 C − x̄)),
//! A > 0, k > 0), each scored by leave-one-budget-out error — the form that extrapolates, not
//! the one that fits best in sample, is the one to predict with.

use crate::ols::{Line, Ols};
use serde::{Deserialize, Serialize};

/// One form of the law, fitted on every minimum and scored on each left out.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShapeFit {
    /// `log`, `curved` or `floor`.
    pub form: String,
    /// The parameters: [a, b] (log), [a, b, c] (curved, in x − x̄), [E, A, k] (floor).
    pub params: Vec<f64>,
    /// x̄, the mean log10 C the curved and floor forms are centred on.
    pub centre: f64,
    /// RMS residual on the minima it was fitted on.
    pub rms: f64,
    /// RMS error on each minimum left out in turn (`None` with too few minima).
    pub lobo_rms: Option<f64>,
    /// (log10 C, loss predicted without it) for each minimum left out.
    pub lobo: Vec<[f64; 2]>,
}

/// The three forms and the one chosen by leave-one-budget-out error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LossShape {
    /// (log10 C, loss at the minimum) of the interior minima.
    pub points: Vec<[f64; 2]>,
    /// The forms, in the order log, curved, floor.
    pub forms: Vec<ShapeFit>,
    /// The form with the lowest leave-one-budget-out RMS.
    pub chosen: Option<String>,
}

impl ShapeFit {
    /// The loss this form predicts at log10 C = `x`.
    pub fn at(&self, x: f64) -> f64 {
        Form::parse(&self.form).map_or(f64::NAN, |f| f.at(&self.params, self.centre, x))
    }
}

impl LossShape {
    /// The form chosen by leave-one-budget-out error, if any was scored.
    pub fn chosen_fit(&self) -> Option<&ShapeFit> {
        let chosen = self.chosen.as_deref()?;
        self.forms.iter().find(|f| f.form == chosen)
    }
}

/// A form of the loss law in log10 C.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Form {
    /// L = a + b·x.
    #[default]
    Log,
    /// L = a + b·u + c·u², u = x − x̄.
    Curved,
    /// L = E + A·10^(−k·u), A > 0, k > 0.
    Floor,
}

impl Form {
    /// The three forms, in the order `compare` reports them.
    pub const ALL: [Form; 3] = [Form::Log, Form::Curved, Form::Floor];

    /// `log`, `curved` or `floor`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Log => "log",
            Self::Curved => "curved",
            Self::Floor => "floor",
        }
    }

    /// The form `name` names.
    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Its number of parameters.
    pub fn params(self) -> usize {
        match self {
            Self::Log => 2,
            Self::Curved | Self::Floor => 3,
        }
    }

    /// The loss with parameters `p` (centred on `centre`) at log10 C = `x`.
    pub fn at(self, p: &[f64], centre: f64, x: f64) -> f64 {
        let u = x - centre;
        match self {
            Self::Log => p[0] + p[1] * x,
            Self::Curved => p[0] + p[1] * u + p[2] * u * u,
            Self::Floor => p[0] + p[1] * 10f64.powf(-p[2] * u),
        }
    }

    /// ∂L/∂p at `x` (the rows of the Jacobian a delta-method interval needs).
    pub fn gradient(self, p: &[f64], centre: f64, x: f64) -> Vec<f64> {
        let u = x - centre;
        match self {
            Self::Log => vec![1.0, x],
            Self::Curved => vec![1.0, u, u * u],
            Self::Floor => {
                let decay = 10f64.powf(-p[2] * u);
                vec![1.0, decay, -p[1] * std::f64::consts::LN_10 * u * decay]
            }
        }
    }

    /// Fits the form to (x, y): its parameters and centre; `None` when the points cannot
    /// determine it.
    pub fn fit(self, x: &[f64], y: &[f64]) -> Option<(Vec<f64>, f64)> {
        let centre = x.iter().sum::<f64>() / x.len() as f64;
        match self {
            Self::Log => {
                let l = Line::fit(x, y)?;
                Some((vec![l.intercept, l.slope], centre))
            }
            Self::Curved => {
                let rows: Vec<Vec<f64>> = x
                    .iter()
                    .map(|v| {
                        let u = v - centre;
                        vec![1.0, u, u * u]
                    })
                    .collect();
                Some((Ols::fit(&rows, y)?.coef[..3].to_vec(), centre))
            }
            Self::Floor => {
                // For a fixed decay k the floor form is linear in (E, A): scan k, keep the best.
                let fit_k = |k: f64| {
                    let rows: Vec<Vec<f64>> = x
                        .iter()
                        .map(|v| vec![1.0, 10f64.powf(-k * (v - centre))])
                        .collect();
                    let ols = Ols::fit(&rows, y)?;
                    let rss: f64 = ols.residuals.iter().map(|r| r * r).sum();
                    (ols.coef[1] > 0.0).then_some((rss, ols.coef[0], ols.coef[1], k))
                };
                let (_, e, a, k) = (1..=400)
                    .filter_map(|i| fit_k(i as f64 * 0.01))
                    .min_by(|p, q| p.0.total_cmp(&q.0))?;
                Some((vec![e, a, k], centre))
            }
        }
    }
}

/// Fits and scores the three forms on the minima `points` ((log10 C, loss), ascending C).
pub fn compare(points: &[[f64; 2]]) -> LossShape {
    let forms: Vec<ShapeFit> = Form::ALL
        .into_iter()
        .filter_map(|form| {
            let params = form.params();
            let (x, y): (Vec<f64>, Vec<f64>) = points.iter().map(|p| (p[0], p[1])).unzip();
            let (p, centre) = form.fit(&x, &y)?;
            let at = |v: f64| form.at(&p, centre, v);
            let rms = (x
                .iter()
                .zip(&y)
                .map(|(v, w)| (at(*v) - w).powi(2))
                .sum::<f64>()
                / x.len() as f64)
                .sqrt();
            // Each minimum predicted from the others (needs a spare point beyond the parameters).
            let lobo: Vec<[f64; 2]> = (0..x.len())
                .filter(|_| x.len() > params + 1)
                .filter_map(|i| {
                    let keep = |v: &[f64]| -> Vec<f64> {
                        v.iter()
                            .enumerate()
                            .filter(|(j, _)| *j != i)
                            .map(|(_, w)| *w)
                            .collect()
                    };
                    let (q, c) = form.fit(&keep(&x), &keep(&y))?;
                    Some([x[i], form.at(&q, c, x[i])])
                })
                .collect();
            let lobo_rms = (lobo.len() == x.len() && !lobo.is_empty()).then(|| {
                (lobo
                    .iter()
                    .zip(&y)
                    .map(|(p, w)| (p[1] - w).powi(2))
                    .sum::<f64>()
                    / lobo.len() as f64)
                    .sqrt()
            });
            Some(ShapeFit {
                form: form.name().into(),
                params: p,
                centre,
                rms,
                lobo_rms,
                lobo,
            })
        })
        .collect();
    let chosen = forms
        .iter()
        .filter_map(|f| Some((f.lobo_rms?, f.form.clone())))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, f)| f);
    LossShape {
        points: points.to_vec(),
        forms,
        chosen,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points(f: impl Fn(f64) -> f64) -> Vec<[f64; 2]> {
        (0..7)
            .map(|i| {
                let x = 11.0 + 0.5 * i as f64;
                [x, f(x)]
            })
            .collect()
    }

    #[test]
    fn each_form_is_recovered_and_chosen_on_its_own_law() {
        let floor = compare(&points(|x| -5.0 + 3.0 * 10f64.powf(-0.6 * (x - 12.5))));
        assert_eq!(floor.chosen.as_deref(), Some("floor"), "{floor:?}");
        let chosen = floor.chosen_fit().unwrap();
        assert!((chosen.at(12.5) + 2.0).abs() < 1e-3 && (chosen.at(14.0) + 4.6223).abs() < 1e-3);
        let p = &floor.forms[2].params;
        assert!(
            (p[0] + 5.0).abs() < 1e-3 && (p[1] - 3.0).abs() < 1e-3 && (p[2] - 0.6).abs() < 1e-9,
            "{p:?}"
        );
        let line = compare(&points(|x| 10.0 - 1.2 * x));
        assert!(line.forms[0].lobo_rms.unwrap() < 1e-9);
        let curved = compare(&points(|x| 10.0 - 1.2 * x + 0.3 * (x - 12.0).powi(2)));
        assert_eq!(curved.chosen.as_deref(), Some("curved"), "{curved:?}");
        assert!(curved.forms[0].lobo_rms.unwrap() > 10.0 * curved.forms[1].lobo_rms.unwrap());
    }

    #[test]
    fn too_few_minima_are_fitted_but_not_scored() {
        let s = compare(&points(|x| 10.0 - x)[..4]);
        assert!(s.forms[0].lobo_rms.is_some());
        assert!(s.forms[1].lobo_rms.is_none() && s.chosen.as_deref() == Some("log"));
    }
}
