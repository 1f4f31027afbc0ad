//! N_opt by variable projection (VPNLS; Marin's scaling-law analysis, Open-Athena/
//! scaling-law-analysis): in Chinchilla's L = E + A/N^α + B/D^β the coefficients (E, A, B)
//! are, for fixed exponents, a linear least-squares solve, so only (α, β) are searched — a
//! grid, then a finer grid around its best — and N_opt = G·(C/6)^(β/(α+β)) follows in closed
//! form. Beside it, the parabola vertices of Chinchilla's approach 2; `lobo` scores both by
//! leaving each budget out in turn against that budget's own vertex, VPNLS with a 95%
//! interval from the other budgets resampled whole (runs of one budget share its noise).

use super::engine::resample_weights;
use super::Point;
use crate::isoflop::parabola_minimum;
use crate::ols::{Line, Ols};
use crate::parametric::percentile;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Chinchilla's law fitted by variable projection (least squares on the loss).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Vpnls {
    /// E.
    pub e: f64,
    /// A.
    pub a: f64,
    /// B.
    pub b: f64,
    /// α.
    pub alpha: f64,
    /// β.
    pub beta: f64,
    /// Residual sum of squares.
    pub rss: f64,
}

/// The linear solve at fixed exponents: (E, A, B, RSS), `None` unless A, B > 0.
fn project(rows: &[Point], loss: &[f64], alpha: f64, beta: f64) -> Option<[f64; 4]> {
    let x: Vec<Vec<f64>> = rows
        .iter()
        .map(|p| vec![1.0, p.n.powf(-alpha), p.d.powf(-beta)])
        .collect();
    let ols = Ols::fit(&x, loss)?;
    let rss = ols.residuals.iter().map(|r| r * r).sum();
    (ols.coef[1] > 0.0 && ols.coef[2] > 0.0).then_some([ols.coef[0], ols.coef[1], ols.coef[2], rss])
}

/// The best (α, β) on a square grid of half-width `half` and step `step` around `centre`.
fn search(rows: &[Point], loss: &[f64], centre: [f64; 2], half: f64, step: f64) -> Option<Vpnls> {
    let k = (half / step).round() as i64;
    let mut best: Option<Vpnls> = None;
    for i in -k..=k {
        for j in -k..=k {
            let (alpha, beta) = (centre[0] + i as f64 * step, centre[1] + j as f64 * step);
            if alpha <= 0.0 || beta <= 0.0 {
                continue;
            }
            if let Some([e, a, b, rss]) = project(rows, loss, alpha, beta) {
                if best.is_none_or(|v| rss < v.rss) {
                    best = Some(Vpnls {
                        e,
                        a,
                        b,
                        alpha,
                        beta,
                        rss,
                    });
                }
            }
        }
    }
    best
}

impl Vpnls {
    /// Fits the runs: exponents in (0, 1.5] by 0.025, then ±0.025 by 0.001.
    pub fn fit(rows: &[Point], loss: &[f64]) -> Option<Self> {
        let coarse = search(rows, loss, [0.75, 0.75], 0.75, 0.025)?;
        search(rows, loss, [coarse.alpha, coarse.beta], 0.025, 0.001)
    }

    /// The compute-optimal N at budget C (C = 6·N·D).
    pub fn n_opt(&self, c: f64) -> f64 {
        super::chinchilla::n_opt(self.a.ln(), self.b.ln(), self.alpha, self.beta, c)
    }
}

/// One budget left out: its own vertex and the two predictions of it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LoboPoint {
    /// The budget left out (geometric mean of its runs' 6·N·D).
    pub budget: f64,
    /// log10 of its runs' parabola vertex.
    pub vertex: f64,
    /// log10 N_opt from the other budgets' vertices (a line in log–log).
    pub parabola: Option<f64>,
    /// log10 N_opt from VPNLS on the other budgets' runs.
    pub vpnls: Option<f64>,
    /// Its 95% interval: VPNLS refitted to the other budgets resampled whole.
    #[serde(default)]
    pub vpnls_interval: Option<[f64; 2]>,
}

/// Resamples in VPNLS's interval of N_opt.
const VPNLS_RESAMPLES: usize = 100;

/// The 95% interval of log10 N_opt at `c` of VPNLS refitted to `rows` resampled by
/// `clusters` (each cluster drawn whole; `clusters[i]` in 0..k), seeded.
fn n_opt_interval(rows: &[Point], loss: &[f64], clusters: &[usize], c: f64) -> Option<[f64; 2]> {
    let draws: Vec<f64> = (0..VPNLS_RESAMPLES)
        .into_par_iter()
        .filter_map(|b| {
            let w = resample_weights(rows.len(), Some(clusters), 0x7695, b);
            let (r, l): (Vec<Point>, Vec<f64>) = (0..rows.len())
                .flat_map(|i| std::iter::repeat_n((rows[i], loss[i]), w[i] as usize))
                .unzip();
            Vpnls::fit(&r, &l).map(|v| v.n_opt(c).log10())
        })
        .collect();
    if draws.len() * 10 < VPNLS_RESAMPLES * 9 {
        return None;
    }
    Some([percentile(&draws, 0.025)?, percentile(&draws, 0.975)?])
}

/// Each budget group with an interior vertex left out in turn (`groups[i]`: run i's group).
pub fn lobo(rows: &[Point], loss: &[f64], groups: &[usize]) -> Vec<LoboPoint> {
    let k = groups.iter().max().map_or(0, |m| m + 1);
    let members: Vec<Vec<usize>> = (0..k)
        .map(|g| (0..rows.len()).filter(|&i| groups[i] == g).collect())
        .collect();
    let budget = |m: &[usize]| {
        (m.iter()
            .map(|&i| (6.0 * rows[i].n * rows[i].d).ln())
            .sum::<f64>()
            / m.len() as f64)
            .exp()
    };
    let vertex = |m: &[usize]| {
        let n: Vec<f64> = m.iter().map(|&i| rows[i].n).collect();
        let l: Vec<f64> = m.iter().map(|&i| loss[i]).collect();
        let v = parabola_minimum(budget(m), "N", None, &n, &l);
        (v.interior)
            .then_some(v.log10_opt.map(|e| e.value))
            .flatten()
    };
    let vertices: Vec<Option<f64>> = members.iter().map(|m| vertex(m)).collect();
    (0..k)
        .filter_map(|h| {
            let truth = vertices[h]?;
            let c = budget(&members[h]);
            let (lc, lv): (Vec<f64>, Vec<f64>) = (0..k)
                .filter(|&g| g != h)
                .filter_map(|g| vertices[g].map(|v| (budget(&members[g]).log10(), v)))
                .unzip();
            let parabola = Line::fit(&lc, &lv).map(|l| l.at(c.log10()));
            let train: Vec<usize> = (0..rows.len()).filter(|&i| groups[i] != h).collect();
            let tr: Vec<Point> = train.iter().map(|&i| rows[i]).collect();
            let tl: Vec<f64> = train.iter().map(|&i| loss[i]).collect();
            let vpnls = Vpnls::fit(&tr, &tl).map(|v| v.n_opt(c).log10());
            // The other budgets, numbered 0..k−1 for the cluster resample.
            let clusters: Vec<usize> = train
                .iter()
                .map(|&i| groups[i] - usize::from(groups[i] > h))
                .collect();
            Some(LoboPoint {
                budget: c,
                vertex: truth,
                parabola,
                vpnls,
                vpnls_interval: vpnls.and_then(|_| n_opt_interval(&tr, &tl, &clusters, c)),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_the_exponents_and_n_opt_of_an_exact_table() {
        let (e, a, b, alpha, beta) = (1.69, 406.4, 410.7, 0.34, 0.28);
        let rows: Vec<Point> = (0..8)
            .flat_map(|i| (0..8).map(move |j| (i, j)))
            .map(|(i, j)| Point {
                n: 10f64.powf(7.0 + 0.4 * i as f64),
                d: 10f64.powf(8.0 + 0.4 * j as f64),
                ..Point::default()
            })
            .collect();
        let loss: Vec<f64> = rows
            .iter()
            .map(|p| e + a * p.n.powf(-alpha) + b * p.d.powf(-beta))
            .collect();
        let v = Vpnls::fit(&rows, &loss).unwrap();
        assert!(
            (v.alpha - alpha).abs() < 2e-3 && (v.beta - beta).abs() < 2e-3,
            "{v:?}"
        );
        let truth = Vpnls {
            e,
            a,
            b,
            alpha,
            beta,
            rss: 0.0,
        };
        let c = 1e21;
        assert!((v.n_opt(c) / truth.n_opt(c)).log10().abs() < 0.02, "{v:?}");
    }
}
