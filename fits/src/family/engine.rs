//! The one fitter of every law family: Σ wᵢ·Huber_δ(rᵢ) minimised by L-BFGS from the best
//! points of the family's start grid, and a bootstrap (over rows, or over clusters of rows
//! that share a budget or a data subset) refitted from the full fit's distinct optima.
//!
//! A bounded parameter is optimised through θ = lo + (hi − lo)·σ(z), so L-BFGS stays
//! unconstrained; starts are mapped in by the logit.

use super::{Allocation, Axis, Law, Point};
use crate::lbfgs::{minimize, LbfgsOptions, Minimum, Termination};
use crate::parametric::{huber, percentile};
use crate::search::grid_golden_min;
use crate::FitError;
use motionscale_core::rng::SplitMix64;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Where residuals are taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Space {
    /// r = ln L̂ − ln L (every loss positive).
    Log,
    /// r = L̂ − L (a loss that can be negative).
    Loss,
}

impl Space {
    /// Log space when every loss is positive, loss space otherwise.
    pub fn for_losses(loss: &[f64]) -> Self {
        if loss.iter().all(|&l| l > 0.0) {
            Space::Log
        } else {
            Space::Loss
        }
    }

    /// The residual of prediction `pred` against `loss`.
    pub fn residual(self, pred: f64, loss: f64) -> f64 {
        match self {
            Space::Log if pred > 0.0 => pred.ln() - loss.ln(),
            Space::Log => f64::INFINITY,
            Space::Loss => pred - loss,
        }
    }
}

/// Settings of the fitter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Settings {
    /// Huber threshold in log space (Hoffmann et al.: 1e-3); in loss space it is scaled by the
    /// median |L|.
    pub delta: f64,
    /// Grid points evaluated at most (a seeded subset of a larger product).
    pub grid_cap: usize,
    /// L-BFGS runs of the full fit: from the best grid points and as many seeded others.
    pub starts: usize,
    /// Bootstrap resamples (0: none).
    pub bootstrap: usize,
    /// Distinct optima of the full fit each resample is refitted from.
    pub bootstrap_starts: usize,
    /// Seed of the grid subset, the extra starts and the bootstrap.
    pub seed: u64,
    /// L-BFGS iteration cap.
    pub max_iter: usize,
    /// L-BFGS stops after 10 steps in a row that lower the objective by at most this share.
    pub ftol: f64,
    /// Bootstrap every scored family, not only the adopted one.
    pub bootstrap_all: bool,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            delta: 1e-3,
            grid_cap: 20_000,
            starts: 64,
            bootstrap: 500,
            bootstrap_starts: 4,
            seed: 0,
            max_iter: 1000,
            ftol: 1e-10,
            bootstrap_all: false,
        }
    }
}

impl Settings {
    fn lbfgs(&self) -> LbfgsOptions {
        LbfgsOptions {
            max_iter: self.max_iter,
            gtol: 1e-9,
            ftol: self.ftol,
            ..LbfgsOptions::default()
        }
    }
}

/// A natural parameter with its bootstrap 95% interval.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NamedEstimate {
    /// Parameter name.
    pub name: String,
    /// Full-data value (∞ where a term's scale diverged: written `null`, read back as ∞).
    #[serde(deserialize_with = "crate::planner::infinite_if_null")]
    pub value: f64,
    /// 2.5th percentile of the bootstrap draws.
    pub ci_low: Option<f64>,
    /// 97.5th percentile of the bootstrap draws.
    pub ci_high: Option<f64>,
}

/// One family fitted to one table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FamilyFit {
    /// Family name.
    pub law: String,
    /// Its equation.
    pub equation: String,
    /// Residual space.
    pub space: Space,
    /// Huber threshold used (in `space`).
    pub delta: f64,
    /// Runs fitted.
    pub rows: usize,
    /// The optimiser's parameters, by name.
    pub param_names: Vec<String>,
    /// The optimiser's θ at the optimum.
    pub theta: Vec<f64>,
    /// Natural parameters with bootstrap intervals.
    pub natural: Vec<NamedEstimate>,
    /// Σ Huber at the optimum.
    pub objective: f64,
    /// RMS residual at the optimum (in `space`).
    pub rms_residual: f64,
    /// L-BFGS runs, and how many ended within 1e-6 (relative) of the best objective.
    pub starts: usize,
    /// Runs at the optimum.
    pub at_optimum: usize,
    /// Bootstrap resamples that converged, of those drawn.
    pub bootstrap_converged: usize,
    /// Bootstrap resamples drawn.
    pub bootstrap_resamples: usize,
    /// Clusters resampled (`None`: rows).
    pub bootstrap_clusters: Option<usize>,
    /// θ of each converged resample.
    pub draws: Vec<Vec<f64>>,
    /// Residuals of the fitted rows (in `space`).
    pub residuals: Vec<f64>,
}

/// A law family behind one object-safe interface (any parameter count).
pub trait Family: Sync {
    /// Short name.
    fn name(&self) -> &'static str;
    /// The equation.
    fn equation(&self) -> &'static str;
    /// The axes it reads.
    fn needs(&self) -> &'static [Axis];
    /// Parameters fitted.
    fn param_count(&self) -> usize;
    /// Why the family cannot be fitted to these runs (`None`: it can).
    fn refusal(&self, rows: &[Point], loss: &[f64]) -> Option<String>;
    /// Fits the runs; `clusters[i]` is run i's cluster for the bootstrap (`None`: rows are
    /// resampled one by one).
    fn fit(
        &self,
        rows: &[Point],
        loss: &[f64],
        clusters: Option<&[usize]>,
        s: &Settings,
    ) -> Result<FamilyFit, FitError>;
    /// The loss θ predicts at `x`.
    fn predict(&self, theta: &[f64], x: &Point) -> f64;
    /// The loss θ predicts at `x` and ∂L̂/∂θ there.
    fn value_and_gradient(&self, theta: &[f64], x: &Point) -> (f64, Vec<f64>);
    /// The compute-optimal allocation at `c` with the other axes of `at` (U, N_v) held: the
    /// law's closed form where it has one, else the lowest predicted loss over N with
    /// D = C/(6·(N + N_v)).
    fn allocation(&self, theta: &[f64], c: f64, at: &Point) -> Option<Allocation>;
    /// The natural parameters (name, value) of the optimiser's θ.
    fn natural(&self, theta: &[f64]) -> Vec<(&'static str, f64)>;
    /// The optimiser's θ of natural parameters listed as [`Family::natural`] lists them.
    fn theta_from_natural(&self, natural: &[f64]) -> Vec<f64>;
}

/// A declared law with `P` parameters, run by the engine.
pub struct Declared<L, const P: usize>(pub L);

/// The rows of one fit with their weights (bootstrap multiplicities).
#[derive(Clone)]
struct Data<'a> {
    rows: &'a [Point],
    loss: &'a [f64],
    weights: Vec<f64>,
    space: Space,
    delta: f64,
}

impl<const P: usize, L: Law<P>> Declared<L, P> {
    fn to_theta(&self, z: &[f64; P]) -> ([f64; P], [f64; P]) {
        let bounds = self.0.bounds();
        let mut theta = *z;
        let mut jac = [1.0; P];
        for k in 0..P {
            if let Some((lo, hi)) = bounds[k] {
                let s = 1.0 / (1.0 + (-z[k]).exp());
                theta[k] = lo + (hi - lo) * s;
                jac[k] = (hi - lo) * s * (1.0 - s);
            }
        }
        (theta, jac)
    }

    fn to_z(&self, theta: &[f64; P]) -> [f64; P] {
        let bounds = self.0.bounds();
        std::array::from_fn(|k| match bounds[k] {
            Some((lo, hi)) => {
                let w = (hi - lo) * 1e-6;
                let t = theta[k].clamp(lo + w, hi - w);
                ((t - lo) / (hi - t)).ln()
            }
            None => theta[k],
        })
    }

    fn objective(&self, data: &Data, z: &[f64; P], grad: &mut [f64; P]) -> f64 {
        let (theta, jac) = self.to_theta(z);
        let mut g = [0.0; P];
        let mut sum = [0.0; P];
        let mut total = 0.0;
        for ((x, &l), &w) in data.rows.iter().zip(data.loss).zip(&data.weights) {
            if w == 0.0 {
                continue;
            }
            let pred = self.0.predict(&theta, x, &mut g);
            let r = data.space.residual(pred, l);
            if !r.is_finite() {
                return f64::INFINITY;
            }
            let scale = match data.space {
                Space::Log => 1.0 / pred,
                Space::Loss => 1.0,
            };
            let (h, dh) = huber(r, data.delta);
            total += w * h;
            for k in 0..P {
                sum[k] += w * dh * scale * g[k];
            }
        }
        for k in 0..P {
            grad[k] = sum[k] * jac[k];
        }
        total
    }

    fn value(&self, data: &Data, theta: &[f64; P]) -> f64 {
        let mut g = [0.0; P];
        self.objective(data, &self.to_z(theta), &mut g)
    }

    fn run(&self, data: &Data, z0: [f64; P], opts: &LbfgsOptions) -> Minimum<P> {
        minimize(|z, g| self.objective(data, z, g), z0, opts)
    }

    /// The grid points L-BFGS starts from: the `starts` best of (a seeded subset of) the
    /// product of start values, and `starts` seeded others.
    fn grid_starts(&self, data: &Data, s: &Settings) -> Vec<[f64; P]> {
        let values = self.0.start_values(data.loss);
        let total: usize = values.iter().map(Vec::len).product();
        let point = |mut i: usize| -> [f64; P] {
            std::array::from_fn(|k| {
                let v = &values[k];
                let x = v[i % v.len()];
                i /= v.len();
                x
            })
        };
        let mut rng = SplitMix64::stream(s.seed, 0x5eed);
        let index: Vec<usize> = if total <= s.grid_cap {
            (0..total).collect()
        } else {
            (0..s.grid_cap).map(|_| rng.index(total)).collect()
        };
        let mut scored: Vec<(f64, usize)> = index
            .par_iter()
            .map(|&i| (self.value(data, &point(i)), i))
            .filter(|(f, _)| f.is_finite())
            .collect();
        scored.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut chosen: Vec<usize> = scored.iter().take(s.starts).map(|p| p.1).collect();
        let rest = &scored[chosen.len().min(scored.len())..];
        for _ in 0..s.starts.min(rest.len()) {
            chosen.push(rest[rng.index(rest.len())].1);
        }
        chosen.into_iter().map(point).collect()
    }

    fn data<'a>(&self, rows: &'a [Point], loss: &'a [f64], s: &Settings) -> Data<'a> {
        let space = Space::for_losses(loss);
        let delta = match space {
            Space::Log => s.delta,
            Space::Loss => s.delta * median_abs(loss),
        };
        Data {
            rows,
            loss,
            weights: vec![1.0; rows.len()],
            space,
            delta,
        }
    }
}

fn median_abs(v: &[f64]) -> f64 {
    let a: Vec<f64> = v.iter().map(|x| x.abs()).collect();
    percentile(&a, 0.5).filter(|m| *m > 0.0).unwrap_or(1.0)
}

/// The best finite end point's index.
fn best<const P: usize>(ends: &[Minimum<P>]) -> Option<usize> {
    ends.iter()
        .enumerate()
        .filter(|(_, m)| m.f.is_finite() && m.termination != Termination::NonFinite)
        .min_by(|a, b| a.1.f.total_cmp(&b.1.f))
        .map(|(i, _)| i)
}

/// The `k` lowest distinct optima (objectives more than 1e-6 apart, relative), best first.
fn distinct<const P: usize>(ends: &[Minimum<P>], k: usize) -> Vec<[f64; P]> {
    let mut order: Vec<&Minimum<P>> = ends.iter().filter(|m| m.f.is_finite()).collect();
    order.sort_by(|a, b| a.f.total_cmp(&b.f));
    let mut out: Vec<[f64; P]> = Vec::new();
    let mut last: Option<f64> = None;
    for m in order {
        if last.is_none_or(|l| m.f > l + 1e-6 * l.abs()) {
            out.push(m.x);
            last = Some(m.f);
            if out.len() == k {
                break;
            }
        }
    }
    out
}

/// Bootstrap weights of resample `i`: rows (or whole clusters) drawn with replacement.
/// The allocation at `c` of the lowest `loss` over N (400 points in log N, then golden
/// section: [`grid_golden_min`]), D = C/(6·(N + N_v)), U and N_v from `at`.
fn lowest_over_n(loss: impl Fn(&Point) -> f64, c: f64, at: &Point) -> Option<Allocation> {
    let nv = at.nv.unwrap_or(0.0);
    let point = |ln_n: f64| {
        let n = ln_n.exp();
        Point {
            n,
            d: c / (6.0 * (n + nv)),
            ..*at
        }
    };
    let f = |ln_n: f64| loss(&point(ln_n));
    let (lo, hi) = (100f64.ln(), (c / 600.0).ln());
    if hi.is_nan() || hi <= lo {
        return None;
    }
    let x = point(grid_golden_min(f, (lo, hi), 399, 60)?);
    Some(Allocation {
        compute: c,
        n: x.n,
        d: x.d,
        loss: loss(&x),
    })
}

pub(super) fn resample_weights(
    n: usize,
    clusters: Option<&[usize]>,
    seed: u64,
    i: usize,
) -> Vec<f64> {
    let mut rng = SplitMix64::stream(seed, i as u64 + 1);
    let mut w = vec![0.0; n];
    match clusters {
        None => (0..n).for_each(|_| w[rng.index(n)] += 1.0),
        Some(c) => {
            let k = c.iter().max().map_or(0, |m| m + 1);
            let mut draws = vec![0.0; k];
            (0..k).for_each(|_| draws[rng.index(k)] += 1.0);
            for (wi, ci) in w.iter_mut().zip(c) {
                *wi = draws[*ci];
            }
        }
    }
    w
}

impl<const P: usize, L: Law<P>> Family for Declared<L, P> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn equation(&self) -> &'static str {
        self.0.equation()
    }

    fn needs(&self) -> &'static [Axis] {
        self.0.needs()
    }

    fn param_count(&self) -> usize {
        P
    }

    fn refusal(&self, rows: &[Point], loss: &[f64]) -> Option<String> {
        if let Some(a) = self.needs().iter().find(|a| {
            **a != Axis::S
                && rows
                    .iter()
                    .any(|r| r.get(**a).is_none_or(|v| v.is_nan() || v <= 0.0))
        }) {
            return Some(format!("needs a positive {} for every run", a.symbol()));
        }
        if self.needs().contains(&Axis::S) {
            let shares: Vec<f64> = rows.iter().filter_map(|r| r.s).collect();
            if shares.len() < rows.len() || shares.iter().any(|s| !(0.0..=1.0).contains(s)) {
                return Some("needs a synthetic share in [0, 1] for every run".into());
            }
            let ((lo, hi), identified) = crate::fitted::share_range(&shares);
            if !identified {
                return Some(format!(
                    "the synthetic share spans {lo:.3}..{hi:.3} (≤ 0.05): rho is not identified"
                ));
            }
        }
        // A vocabulary term of one N_v is a constant: not identified beside E. (One U is
        // fine: D/U still varies.)
        let nv = |r: &Point| r.nv;
        if self.needs().contains(&Axis::Nv)
            && rows.iter().all(|r| nv(r) == rows.first().and_then(nv))
        {
            return Some("N_v takes one value in every run: its terms are not identified".into());
        }
        if self.0.positive() && Space::for_losses(loss) == Space::Loss {
            return Some("predicts a positive loss and the table has a loss ≤ 0".into());
        }
        (rows.len() <= P).then(|| format!("{P} parameters need more than {} runs", rows.len()))
    }

    fn fit(
        &self,
        rows: &[Point],
        loss: &[f64],
        clusters: Option<&[usize]>,
        s: &Settings,
    ) -> Result<FamilyFit, FitError> {
        if let Some(why) = self.refusal(rows, loss) {
            return Err(FitError::Invalid(format!("law {}: {why}", self.name())));
        }
        let data = self.data(rows, loss, s);
        let opts = s.lbfgs();
        let ends: Vec<Minimum<P>> = self
            .grid_starts(&data, s)
            .par_iter()
            .map(|t| self.run(&data, self.to_z(t), &opts))
            .collect();
        let b = best(&ends).ok_or_else(|| {
            FitError::Invalid(format!(
                "law {}: the objective is not finite at any start",
                self.name()
            ))
        })?;
        let opt = ends[b];
        let at_optimum = ends
            .iter()
            .filter(|m| m.f <= opt.f + 1e-6 * opt.f.abs())
            .count();
        let boot_starts = distinct(&ends, s.bootstrap_starts.max(1));
        let draws: Vec<[f64; P]> = (0..s.bootstrap)
            .into_par_iter()
            .filter_map(|i| {
                let d = Data {
                    weights: resample_weights(rows.len(), clusters, s.seed, i),
                    ..data.clone()
                };
                let ends: Vec<Minimum<P>> = boot_starts
                    .iter()
                    .map(|z| self.run(&d, *z, &opts))
                    .collect();
                best(&ends).map(|j| self.to_theta(&ends[j].x).0)
            })
            .filter(|t| t.iter().all(|v| v.is_finite()))
            .collect();
        let theta = self.to_theta(&opt.x).0;
        Ok(self.record(
            &data,
            theta,
            &opt,
            ends.len(),
            at_optimum,
            draws,
            clusters,
            s,
        ))
    }

    fn predict(&self, theta: &[f64], x: &Point) -> f64 {
        let mut g = [0.0; P];
        self.0.predict(&as_array(theta), x, &mut g)
    }

    fn value_and_gradient(&self, theta: &[f64], x: &Point) -> (f64, Vec<f64>) {
        let mut g = [0.0; P];
        let value = self.0.predict(&as_array(theta), x, &mut g);
        (value, g.to_vec())
    }

    fn allocation(&self, theta: &[f64], c: f64, at: &Point) -> Option<Allocation> {
        let theta = as_array(theta);
        let held = |a: Axis| matches!(a, Axis::U | Axis::Nv) && at.get(a).is_some();
        match self.needs().iter().any(|&a| held(a)) {
            false => self.0.allocation(&theta, c),
            true => None,
        }
        .or_else(|| lowest_over_n(|x| self.predict(&theta, x), c, at))
    }

    fn natural(&self, theta: &[f64]) -> Vec<(&'static str, f64)> {
        self.0.natural(&as_array(theta))
    }

    fn theta_from_natural(&self, natural: &[f64]) -> Vec<f64> {
        self.0.theta_from_natural(&as_array(natural)).to_vec()
    }
}

impl<const P: usize, L: Law<P>> Declared<L, P> {
    #[allow(clippy::too_many_arguments)]
    fn record(
        &self,
        data: &Data,
        theta: [f64; P],
        opt: &Minimum<P>,
        starts: usize,
        at_optimum: usize,
        draws: Vec<[f64; P]>,
        clusters: Option<&[usize]>,
        s: &Settings,
    ) -> FamilyFit {
        let residuals: Vec<f64> = data
            .rows
            .iter()
            .zip(data.loss)
            .map(|(x, &l)| data.space.residual(self.predict(&theta, x), l))
            .collect();
        let rms = (residuals.iter().map(|r| r * r).sum::<f64>() / residuals.len() as f64).sqrt();
        let natural_draws: Vec<Vec<(&str, f64)>> =
            draws.iter().map(|t| self.0.natural(t)).collect();
        let natural = self
            .0
            .natural(&theta)
            .into_iter()
            .enumerate()
            .map(|(k, (name, value))| {
                let v: Vec<f64> = natural_draws.iter().map(|d| d[k].1).collect();
                NamedEstimate {
                    name: name.to_string(),
                    value,
                    ci_low: percentile(&v, 0.025),
                    ci_high: percentile(&v, 0.975),
                }
            })
            .collect();
        FamilyFit {
            law: self.name().to_string(),
            equation: self.equation().to_string(),
            space: data.space,
            delta: data.delta,
            rows: data.rows.len(),
            param_names: self.0.param_names().iter().map(|n| n.to_string()).collect(),
            theta: theta.to_vec(),
            natural,
            objective: opt.f,
            rms_residual: rms,
            starts,
            at_optimum,
            bootstrap_converged: draws.len(),
            bootstrap_resamples: s.bootstrap,
            bootstrap_clusters: clusters.map(|c| c.iter().max().map_or(0, |m| m + 1)),
            draws: draws.iter().map(|t| t.to_vec()).collect(),
            residuals,
        }
    }
}

fn as_array<const P: usize>(theta: &[f64]) -> [f64; P] {
    std::array::from_fn(|k| theta[k])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scale that diverged (B = e^b past f64's range) is written `null` and read back as ∞,
    /// so the laws.json stays readable.
    #[test]
    fn an_infinite_natural_parameter_reads_back() {
        let e = NamedEstimate {
            name: "B".into(),
            value: f64::INFINITY,
            ci_low: None,
            ci_high: None,
        };
        let text = serde_json::to_string(&e).unwrap();
        let back: NamedEstimate = serde_json::from_str(&text).unwrap();
        assert_eq!(back.value, f64::INFINITY, "{text}");
    }

    #[test]
    fn cluster_resamples_keep_clusters_whole() {
        let clusters = [0, 0, 1, 1, 2, 2];
        for i in 0..20 {
            let w = resample_weights(6, Some(&clusters), 3, i);
            for c in 0..3 {
                assert_eq!(w[2 * c], w[2 * c + 1], "resample {i}: cluster {c} split");
            }
            assert_eq!(w.iter().sum::<f64>(), 6.0);
        }
        let w = resample_weights(6, None, 3, 0);
        assert_eq!(w.iter().sum::<f64>(), 6.0);
    }

    #[test]
    fn loss_space_is_chosen_by_the_sign_of_the_losses() {
        assert_eq!(Space::for_losses(&[2.0, 3.0]), Space::Log);
        assert_eq!(Space::for_losses(&[-2.0, 3.0]), Space::Loss);
        assert_eq!(Space::Log.residual(-1.0, 2.0), f64::INFINITY);
        assert!((Space::Log.residual(2.0 * 1f64.exp(), 2.0) - 1.0).abs() < 1e-12);
    }
}
