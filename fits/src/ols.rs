//! Ordinary least squares: coefficients, their covariance and standard errors, R², residuals;
//! straight lines and parabolas (with the vertex and its delta-method standard error).

use nalgebra::{DMatrix, DVector};
use statrs::distribution::{ContinuousCDF, StudentsT};

/// An OLS fit of y = X·c.
#[derive(Debug, Clone, PartialEq)]
pub struct Ols {
    /// Coefficients c.
    pub coef: Vec<f64>,
    /// Covariance of c: σ²·(XᵀX)⁻¹ with σ² = RSS / (n − p); `None` when n ≤ p.
    pub cov: Option<Vec<Vec<f64>>>,
    /// Coefficient of determination, 1 − RSS/TSS.
    pub r2: f64,
    /// y − X·c, in input order.
    pub residuals: Vec<f64>,
    /// Degrees of freedom n − p.
    pub dof: usize,
}

impl Ols {
    /// Fits `y` on the rows of `x` (each row has the same length p ≤ n). `None` when XᵀX is singular.
    pub fn fit(x: &[Vec<f64>], y: &[f64]) -> Option<Self> {
        let n = y.len();
        let p = x.first()?.len();
        if n < p || x.len() != n {
            return None;
        }
        let xm = DMatrix::from_fn(n, p, |i, j| x[i][j]);
        let yv = DVector::from_column_slice(y);
        let xtx = xm.transpose() * &xm;
        let inv = xtx.try_inverse()?;
        let coef = &inv * (xm.transpose() * &yv);
        let fitted = &xm * &coef;
        let residuals: Vec<f64> = (0..n).map(|i| y[i] - fitted[i]).collect();
        let rss: f64 = residuals.iter().map(|r| r * r).sum();
        let mean = y.iter().sum::<f64>() / n as f64;
        let tss: f64 = y.iter().map(|v| (v - mean).powi(2)).sum();
        let dof = n - p;
        let cov = (dof > 0).then(|| {
            let s2 = rss / dof as f64;
            (0..p)
                .map(|i| (0..p).map(|j| s2 * inv[(i, j)]).collect())
                .collect()
        });
        Some(Self {
            coef: coef.iter().copied().collect(),
            cov,
            r2: if tss > 0.0 { 1.0 - rss / tss } else { f64::NAN },
            residuals,
            dof,
        })
    }

    /// Standard error of coefficient `i`.
    pub fn se(&self, i: usize) -> Option<f64> {
        self.cov.as_ref().map(|c| c[i][i].max(0.0).sqrt())
    }
}

/// Number of distinct values in `x`.
pub fn distinct(x: &[f64]) -> usize {
    let mut v = x.to_vec();
    v.sort_by(f64::total_cmp);
    v.dedup();
    v.len()
}

/// The 97.5% normal quantile (the normal's two-sided 95% critical value).
pub const Z95: f64 = 1.959_963_984_540_054;

/// Two-sided 95% Student-t critical value for `dof` degrees of freedom.
pub fn t95(dof: usize) -> f64 {
    StudentsT::new(0.0, 1.0, dof.max(1) as f64)
        .expect("valid Student t parameters")
        .inverse_cdf(0.975)
}

/// Mean of `values` and the half-width of its two-sided 95% Student-t interval (n − 1
/// degrees of freedom; 0 for a single value): the interval over a handful of training seeds.
pub fn mean_interval(values: &[f64]) -> (f64, f64) {
    let n = values.len();
    let mean = values.iter().sum::<f64>() / n as f64;
    if n < 2 {
        return (mean, 0.0);
    }
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    (mean, t95(n - 1) * (var / n as f64).sqrt())
}

/// y = intercept + slope·x by OLS.
#[derive(Debug, Clone, PartialEq)]
pub struct Line {
    /// Intercept.
    pub intercept: f64,
    /// Slope.
    pub slope: f64,
    /// The underlying fit (coefficient order: intercept, slope).
    pub ols: Ols,
}

impl Line {
    /// Fits a straight line; `None` with fewer than two distinct x.
    pub fn fit(x: &[f64], y: &[f64]) -> Option<Self> {
        if distinct(x) < 2 {
            return None;
        }
        let rows: Vec<Vec<f64>> = x.iter().map(|&v| vec![1.0, v]).collect();
        let ols = Ols::fit(&rows, y)?;
        Some(Self {
            intercept: ols.coef[0],
            slope: ols.coef[1],
            ols,
        })
    }

    /// The fitted value at `x`.
    pub fn at(&self, x: f64) -> f64 {
        self.intercept + self.slope * x
    }
}

/// y = c0 + c1·u + c2·u² with u = x − centre (centred for conditioning).
#[derive(Debug, Clone, PartialEq)]
pub struct Parabola {
    /// The x the fit is centred on (mean of the sampled x).
    pub centre: f64,
    /// c0, c1, c2 in the centred variable.
    pub coef: [f64; 3],
    /// The underlying fit.
    pub ols: Ols,
}

impl Parabola {
    /// Fits a parabola; `None` with fewer than three distinct x.
    pub fn fit(x: &[f64], y: &[f64]) -> Option<Self> {
        if distinct(x) < 3 {
            return None;
        }
        let centre = x.iter().sum::<f64>() / x.len().max(1) as f64;
        let rows: Vec<Vec<f64>> = x
            .iter()
            .map(|&v| {
                let u = v - centre;
                vec![1.0, u, u * u]
            })
            .collect();
        let ols = Ols::fit(&rows, y)?;
        Some(Self {
            centre,
            coef: [ols.coef[0], ols.coef[1], ols.coef[2]],
            ols,
        })
    }

    /// The fitted value at `x`.
    pub fn at(&self, x: f64) -> f64 {
        let u = x - self.centre;
        self.coef[0] + self.coef[1] * u + self.coef[2] * u * u
    }

    /// Curvature y'' / 2 (positive: convex, a minimum exists).
    pub fn curvature(&self) -> f64 {
        self.coef[2]
    }

    /// The stationary point x* = centre − c1 / (2·c2).
    pub fn vertex(&self) -> f64 {
        self.centre - self.coef[1] / (2.0 * self.coef[2])
    }

    /// Delta-method standard error of the vertex from cov(c1, c2).
    pub fn vertex_se(&self) -> Option<f64> {
        let cov = self.ols.cov.as_ref()?;
        let (c1, c2) = (self.coef[1], self.coef[2]);
        let g1 = -1.0 / (2.0 * c2);
        let g2 = c1 / (2.0 * c2 * c2);
        let var = g1 * g1 * cov[1][1] + 2.0 * g1 * g2 * cov[1][2] + g2 * g2 * cov[2][2];
        Some(var.max(0.0).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_matches_hand_computation() {
        // x = 0..4, y = 1, 3, 2, 5, 4: x̄ = 2, ȳ = 3, Sxx = 10, Sxy = 4 + 0 + 0 + 2 + 2 = 8.
        let x = [0.0, 1.0, 2.0, 3.0, 4.0];
        let y = [1.0, 3.0, 2.0, 5.0, 4.0];
        let line = Line::fit(&x, &y).unwrap();
        assert!((line.slope - 0.8).abs() < 1e-12);
        assert!((line.intercept - 1.4).abs() < 1e-12);
        // Residuals -0.4, 0.8, -1.0, 1.2, -0.6: RSS = 3.6, σ² = 1.2.
        let rss: f64 = line.ols.residuals.iter().map(|r| r * r).sum();
        assert!((rss - 3.6).abs() < 1e-12);
        // SE(slope) = sqrt(σ²/Sxx) = sqrt(0.12); SE(intercept) = sqrt(σ²(1/n + x̄²/Sxx)) = sqrt(0.72).
        assert!((line.ols.se(1).unwrap() - 0.12f64.sqrt()).abs() < 1e-12);
        assert!((line.ols.se(0).unwrap() - 0.72f64.sqrt()).abs() < 1e-12);
        // R² = 1 − 3.6/TSS, TSS = 4+0+1+4+1 = 10.
        assert!((line.ols.r2 - 0.64).abs() < 1e-12);
        assert_eq!(line.ols.dof, 3);
    }

    #[test]
    fn exact_fit_has_zero_se_and_two_points_have_none() {
        let line = Line::fit(&[1.0, 2.0, 3.0], &[2.0, 4.0, 6.0]).unwrap();
        assert!((line.slope - 2.0).abs() < 1e-12 && line.intercept.abs() < 1e-12);
        assert!(line.ols.se(1).unwrap() < 1e-7);
        assert_eq!(Line::fit(&[1.0, 2.0], &[0.0, 1.0]).unwrap().ols.se(1), None);
        assert!(Line::fit(&[1.0, 1.0, 1.0], &[0.0, 1.0, 2.0]).is_none());
    }

    #[test]
    fn parabola_vertex_is_exact_on_a_parabola() {
        // y = 3 (x − 8.5)² + 2 sampled at 7..10.
        let x: Vec<f64> = (0..7).map(|i| 7.0 + 0.5 * i as f64).collect();
        let y: Vec<f64> = x
            .iter()
            .map(|v| 3.0 * (v - 8.5) * (v - 8.5) + 2.0)
            .collect();
        let p = Parabola::fit(&x, &y).unwrap();
        assert!((p.vertex() - 8.5).abs() < 1e-10);
        assert!((p.curvature() - 3.0).abs() < 1e-10);
        assert!((p.at(p.vertex()) - 2.0).abs() < 1e-10);
        assert!(p.vertex_se().unwrap() < 1e-6);
    }

    #[test]
    fn vertex_se_matches_the_delta_method_by_hand() {
        // Three points determine the parabola, four leave one dof.
        let x = [-1.0, 0.0, 1.0, 2.0];
        let y = [2.1, 0.9, 2.0, 5.2];
        let p = Parabola::fit(&x, &y).unwrap();
        let cov = p.ols.cov.clone().unwrap();
        let (c1, c2) = (p.coef[1], p.coef[2]);
        let var = cov[1][1] / (4.0 * c2 * c2) - 2.0 * c1 * cov[1][2] / (4.0 * c2.powi(3))
            + c1 * c1 * cov[2][2] / (4.0 * c2.powi(4));
        assert!((p.vertex_se().unwrap() - var.sqrt()).abs() < 1e-12);
        assert!(Parabola::fit(&[1.0, 1.0, 2.0, 2.0], &[1.0, 2.0, 3.0, 4.0]).is_none());
    }

    #[test]
    fn t_quantiles_match_tables() {
        assert!((t95(1) - 12.706).abs() < 1e-3);
        assert!((t95(5) - 2.571).abs() < 1e-3);
        assert!((t95(1000) - 1.962).abs() < 1e-3);
    }

    #[test]
    fn seed_interval_matches_a_hand_case() {
        // 1, 2, 3: mean 2, sample sd 1, half-width t(2) · 1/√3 = 4.303 / 1.732 = 2.484.
        let (mean, half) = mean_interval(&[1.0, 2.0, 3.0]);
        assert!((mean - 2.0).abs() < 1e-12);
        assert!((half - 2.484).abs() < 1e-3, "{half}");
        assert_eq!(mean_interval(&[0.5]), (0.5, 0.0));
    }
}
