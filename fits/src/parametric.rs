//! The parametric law L(N, D) = E + A/N^α + B/D^β fitted as Hoffmann et al. (approach 3) and
//! Besiroglu et al. (Epoch) do: parameters θ = (a, b, e, α, β) with A = eᵃ, B = eᵇ, E = eᵉ,
//! residuals r = LSE(a − α ln N, b − β ln D, e) − ln L, objective Σ Huber_δ(r) (summed, not
//! averaged), L-BFGS from every point of a grid of starts, best end point kept; bootstrap
//! over runs for percentile intervals.

use crate::fastmath;
use crate::lbfgs::{minimize, LbfgsOptions, Minimum, Termination};
use crate::FitError;
use motionscale_core::rng::SplitMix64;
use rayon::prelude::*;

/// Runs in log space: ln N, ln D, ln L.
#[derive(Debug, Clone, PartialEq)]
pub struct LogRuns {
    /// ln N per run.
    pub ln_n: Vec<f64>,
    /// ln D per run.
    pub ln_d: Vec<f64>,
    /// ln L per run.
    pub ln_l: Vec<f64>,
}

impl LogRuns {
    /// From positive N, D, L (the caller checks positivity).
    pub fn new(n: &[f64], d: &[f64], loss: &[f64]) -> Self {
        Self {
            ln_n: n.iter().map(|v| v.ln()).collect(),
            ln_d: d.iter().map(|v| v.ln()).collect(),
            ln_l: loss.iter().map(|v| v.ln()).collect(),
        }
    }

    /// Number of runs.
    pub fn len(&self) -> usize {
        self.ln_l.len()
    }

    /// True when there are no runs.
    pub fn is_empty(&self) -> bool {
        self.ln_l.is_empty()
    }

    /// The runs at `idx` (with repeats: a bootstrap resample).
    pub fn select(&self, idx: &[usize]) -> Self {
        Self {
            ln_n: idx.iter().map(|&i| self.ln_n[i]).collect(),
            ln_d: idx.iter().map(|&i| self.ln_d[i]).collect(),
            ln_l: idx.iter().map(|&i| self.ln_l[i]).collect(),
        }
    }

    /// Log-space residuals LSE(a − α ln N, b − β ln D, e) − ln L at θ.
    pub fn residuals(&self, theta: &[f64; 5]) -> Vec<f64> {
        (0..self.len())
            .map(|i| lse3(self.terms(theta, i)).0 - self.ln_l[i])
            .collect()
    }

    fn terms(&self, t: &[f64; 5], i: usize) -> [f64; 3] {
        [t[0] - t[3] * self.ln_n[i], t[1] - t[4] * self.ln_d[i], t[2]]
    }
}

/// log(Σ exp(tᵢ)) and the softmax weights, overflow-safe.
pub(crate) fn lse3(t: [f64; 3]) -> (f64, [f64; 3]) {
    let m = t[0].max(t[1]).max(t[2]);
    let e = t.map(|v| (v - m).exp());
    let s = e[0] + e[1] + e[2];
    (m + s.ln(), e.map(|v| v / s))
}

/// Huber loss with threshold δ and its derivative: r²/2 inside |r| ≤ δ, δ(|r| − δ/2) outside.
pub fn huber(r: f64, delta: f64) -> (f64, f64) {
    if r.abs() <= delta {
        (0.5 * r * r, r)
    } else {
        (delta * (r.abs() - 0.5 * delta), delta * r.signum())
    }
}

/// Rows evaluated together, so the exponentials and logarithms vectorise.
const CHUNK: usize = 64;

/// ln(e^t1 + e^t2 + E) and the three softmax weights, per row (|t| ≤ 700).
#[inline(always)]
fn softmax_body(t1: &[f64], t2: &[f64], exp_e: f64, lse: &mut [f64], w: &mut [[f64; CHUNK]; 3]) {
    for j in 0..t1.len() {
        let (p1, p2) = (fastmath::exp(t1[j]), fastmath::exp(t2[j]));
        let s = p1 + p2 + exp_e;
        let inv = 1.0 / s;
        lse[j] = fastmath::ln(s);
        w[0][j] = p1 * inv;
        w[1][j] = p2 * inv;
        w[2][j] = exp_e * inv;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn softmax_avx2(t1: &[f64], t2: &[f64], exp_e: f64, lse: &mut [f64], w: &mut [[f64; CHUNK]; 3]) {
    softmax_body(t1, t2, exp_e, lse, w);
}

fn softmax_terms(t1: &[f64], t2: &[f64], exp_e: f64, lse: &mut [f64], w: &mut [[f64; CHUNK]; 3]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU supports the features the function was compiled for.
            return unsafe { softmax_avx2(t1, t2, exp_e, lse, w) };
        }
    }
    softmax_body(t1, t2, exp_e, lse, w);
}

/// Σ Huber_δ(residual) at θ; writes the gradient into `grad`.
pub fn objective(runs: &LogRuns, delta: f64, theta: &[f64; 5], grad: &mut [f64; 5]) -> f64 {
    *grad = [0.0; 5];
    let [a, b, e, alpha, beta] = *theta;
    let exp_e = e.exp();
    let mut total = 0.0;
    let (mut t1, mut t2) = ([0.0; CHUNK], [0.0; CHUNK]);
    let mut w = [[0.0; CHUNK]; 3];
    let mut lse = [0.0; CHUNK];
    for start in (0..runs.len()).step_by(CHUNK) {
        let m = (runs.len() - start).min(CHUNK);
        let ln_n = &runs.ln_n[start..start + m];
        let ln_d = &runs.ln_d[start..start + m];
        let ln_l = &runs.ln_l[start..start + m];
        for j in 0..m {
            t1[j] = a - alpha * ln_n[j];
            t2[j] = b - beta * ln_d[j];
        }
        // The fast exp/ln need |t| ≤ 700 (no overflow, normal sums); otherwise the max-shifted
        // log-sum-exp per row.
        let fast = e.abs() <= 700.0
            && t1[..m]
                .iter()
                .chain(&t2[..m])
                .fold(0.0f64, |acc, t| acc.max(t.abs()))
                <= 700.0;
        if fast {
            softmax_terms(&t1[..m], &t2[..m], exp_e, &mut lse[..m], &mut w);
        } else {
            for j in 0..m {
                let (l, ws) = lse3([t1[j], t2[j], e]);
                lse[j] = l;
                for k in 0..3 {
                    w[k][j] = ws[k];
                }
            }
        }
        for j in 0..m {
            let (h, dh) = huber(lse[j] - ln_l[j], delta);
            total += h;
            grad[0] += dh * w[0][j];
            grad[1] += dh * w[1][j];
            grad[2] += dh * w[2][j];
            grad[3] -= dh * w[0][j] * ln_n[j];
            grad[4] -= dh * w[1][j] * ln_d[j];
        }
    }
    total
}

/// The grid of L-BFGS starting points: every combination of the listed values.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StartGrid {
    /// Values of a = ln A.
    pub a: Vec<f64>,
    /// Values of b = ln B.
    pub b: Vec<f64>,
    /// Values of e = ln E.
    pub e: Vec<f64>,
    /// Values of α.
    pub alpha: Vec<f64>,
    /// Values of β.
    pub beta: Vec<f64>,
}

fn steps(lo: f64, hi: f64, step: f64) -> Vec<f64> {
    let n = ((hi - lo) / step + 1e-9).floor() as usize;
    (0..=n).map(|k| lo + step * k as f64).collect()
}

impl StartGrid {
    /// Epoch's grid: α, β ∈ {0, 0.5, …, 2}, e ∈ {−1, −0.5, …, 1}, a, b ∈ {0, 5, …, 25}: 4,500 starts.
    pub fn epoch() -> Self {
        Self {
            a: steps(0.0, 25.0, 5.0),
            b: steps(0.0, 25.0, 5.0),
            e: steps(-1.0, 1.0, 0.5),
            alpha: steps(0.0, 2.0, 0.5),
            beta: steps(0.0, 2.0, 0.5),
        }
    }

    /// A 243-start grid for quick looks: α, β ∈ {0, 1, 2}, e ∈ {−1, 0, 1}, a, b ∈ {0, 10, 20}.
    pub fn coarse() -> Self {
        Self {
            a: steps(0.0, 20.0, 10.0),
            b: steps(0.0, 20.0, 10.0),
            e: steps(-1.0, 1.0, 1.0),
            alpha: steps(0.0, 2.0, 1.0),
            beta: steps(0.0, 2.0, 1.0),
        }
    }

    /// `epoch`, `coarse`, or `NAME=LO:HI:STEP` (or `NAME=V1/V2/…`) for each of a, b, e, alpha,
    /// beta, comma-separated; names not given keep Epoch's values.
    pub fn parse(spec: &str) -> Result<Self, FitError> {
        match spec {
            "epoch" => return Ok(Self::epoch()),
            "coarse" => return Ok(Self::coarse()),
            _ => {}
        }
        let bad = |m: String| FitError::Invalid(format!("--starts-grid {spec:?}: {m}"));
        let mut grid = Self::epoch();
        for part in spec.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (name, values) = part
                .split_once('=')
                .ok_or_else(|| bad(format!("{part:?} is not NAME=LO:HI:STEP")))?;
            let num = |s: &str| {
                s.trim()
                    .parse::<f64>()
                    .map_err(|_| bad(format!("{s:?} is not a number")))
            };
            let list = if values.contains(':') {
                let v: Vec<f64> = values.split(':').map(num).collect::<Result<_, _>>()?;
                match v[..] {
                    [lo, hi, step] if step > 0.0 && hi >= lo => steps(lo, hi, step),
                    _ => {
                        return Err(bad(format!(
                            "{values:?}: want LO:HI:STEP with STEP > 0, HI ≥ LO"
                        )))
                    }
                }
            } else {
                values.split('/').map(num).collect::<Result<_, _>>()?
            };
            let slot = match name.trim() {
                "a" => &mut grid.a,
                "b" => &mut grid.b,
                "e" => &mut grid.e,
                "alpha" => &mut grid.alpha,
                "beta" => &mut grid.beta,
                other => {
                    return Err(bad(format!(
                        "unknown parameter {other:?} (a, b, e, alpha, beta)"
                    )))
                }
            };
            *slot = list;
        }
        if grid.is_empty() {
            return Err(bad("the grid is empty".into()));
        }
        Ok(grid)
    }

    /// Number of starts.
    pub fn len(&self) -> usize {
        self.a.len() * self.b.len() * self.e.len() * self.alpha.len() * self.beta.len()
    }

    /// True when the grid has no starts.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every start as θ = (a, b, e, α, β).
    pub fn points(&self) -> Vec<[f64; 5]> {
        let mut out = Vec::with_capacity(self.len());
        for &alpha in &self.alpha {
            for &beta in &self.beta {
                for &e in &self.e {
                    for &a in &self.a {
                        for &b in &self.b {
                            out.push([a, b, e, alpha, beta]);
                        }
                    }
                }
            }
        }
        out
    }
}

/// Minimises Σ Huber from one start.
pub fn fit_from(runs: &LogRuns, delta: f64, start: [f64; 5], opts: &LbfgsOptions) -> Minimum<5> {
    minimize(|t, g| objective(runs, delta, t, g), start, opts)
}

/// Every start's end point (in start order) and the index of the best.
#[derive(Debug, Clone)]
pub struct MultiStart {
    /// End point of each start.
    pub ends: Vec<Minimum<5>>,
    /// Index of the lowest objective among finite end points.
    pub best: usize,
}

impl MultiStart {
    /// The best end point.
    pub fn best(&self) -> &Minimum<5> {
        &self.ends[self.best]
    }

    /// Starts whose objective is within `rel` (relative) of the best.
    pub fn at_optimum(&self, rel: f64) -> usize {
        let best = self.best().f;
        self.ends
            .iter()
            .filter(|m| m.f <= best + rel * best.abs())
            .count()
    }

    /// The `k` lowest distinct local optima, best first: end points whose objectives differ
    /// by more than 1e-6 (relative) from every lower one kept. These are the starts for the
    /// bootstrap refits: a resample moves each optimum a little but keeps the basins.
    pub fn distinct_best(&self, k: usize) -> Vec<[f64; 5]> {
        let mut order: Vec<usize> = (0..self.ends.len())
            .filter(|&i| self.ends[i].f.is_finite())
            .collect();
        order.sort_by(|&i, &j| self.ends[i].f.total_cmp(&self.ends[j].f));
        let mut out: Vec<[f64; 5]> = Vec::new();
        let mut last: Option<f64> = None;
        for i in order {
            let f = self.ends[i].f;
            if last.is_none_or(|l| f > l + 1e-6 * l.abs()) {
                out.push(self.ends[i].x);
                last = Some(f);
                if out.len() == k {
                    break;
                }
            }
        }
        out
    }
}

/// Runs L-BFGS from every start in parallel and keeps all end points.
pub fn multi_start(
    runs: &LogRuns,
    delta: f64,
    starts: &[[f64; 5]],
    opts: &LbfgsOptions,
) -> Result<MultiStart, FitError> {
    let ends: Vec<Minimum<5>> = starts
        .par_iter()
        .map(|&s| fit_from(runs, delta, s, opts))
        .collect();
    let best = best_index(&ends).ok_or_else(|| {
        FitError::Invalid("parametric fit: the objective is not finite at any start".into())
    })?;
    Ok(MultiStart { ends, best })
}

fn best_index(ends: &[Minimum<5>]) -> Option<usize> {
    ends.iter()
        .enumerate()
        .filter(|(_, m)| m.f.is_finite() && m.termination != Termination::NonFinite)
        .min_by(|a, b| a.1.f.total_cmp(&b.1.f))
        .map(|(i, _)| i)
}

/// Bootstrap over runs: resample `runs` with replacement `resamples` times (resample `i` uses
/// stream `i` of `seed`, so results do not depend on thread scheduling), refit each from
/// `starts`, and return each resample's best θ (`None` if no start gave a finite objective).
pub fn bootstrap(
    runs: &LogRuns,
    delta: f64,
    starts: &[[f64; 5]],
    resamples: usize,
    seed: u64,
    opts: &LbfgsOptions,
) -> Vec<Option<[f64; 5]>> {
    (0..resamples)
        .into_par_iter()
        .map(|i| {
            let sample = resample(runs, seed, i);
            let ends: Vec<Minimum<5>> = starts
                .iter()
                .map(|&s| fit_from(&sample, delta, s, opts))
                .collect();
            best_index(&ends).map(|b| ends[b].x)
        })
        .collect()
}

/// Bootstrap resample `i` of `runs` for `seed`: as many runs as the original, drawn with replacement.
pub fn resample(runs: &LogRuns, seed: u64, i: usize) -> LogRuns {
    let mut rng = SplitMix64::stream(seed, i as u64);
    let idx: Vec<usize> = (0..runs.len()).map(|_| rng.index(runs.len())).collect();
    runs.select(&idx)
}

/// θ = (a, b, e, α, β) → (E, A, B, α, β).
pub fn natural(theta: &[f64; 5]) -> [f64; 5] {
    [
        theta[2].exp(),
        theta[0].exp(),
        theta[1].exp(),
        theta[3],
        theta[4],
    ]
}

/// The natural parameters of the bootstrap draws that converged to finite values; a refit
/// whose log-parameter overflows (A or B = e^710…) is a failed refit, and JSON has no
/// infinity to record it with.
pub fn finite_draws(draws: &[Option<[f64; 5]>]) -> Vec<[f64; 5]> {
    draws
        .iter()
        .flatten()
        .map(natural)
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .collect()
}

/// `value` with the 95% percentile interval (2.5th to 97.5th) of its bootstrap `draws`.
pub fn with_draws(value: f64, draws: &[f64]) -> crate::laws::Estimate {
    crate::laws::Estimate {
        value,
        se: None,
        ci_low: percentile(draws, 0.025),
        ci_high: percentile(draws, 0.975),
    }
}

/// Percentile `q` ∈ [0, 1] of `values` (linear interpolation between order statistics).
pub fn percentile(values: &[f64], q: f64) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    percentile_of_sorted(&v, q)
}

/// The q-quantile of ascending `sorted` values, interpolated linearly between order
/// statistics; `None` when empty. An end at +∞ gives +∞ (or NaN between two infinities).
pub fn percentile_of_sorted(sorted: &[f64], q: f64) -> Option<f64> {
    let last = sorted.len().checked_sub(1)?;
    let pos = q.clamp(0.0, 1.0) * last as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    Some(sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_that_overflow_or_failed_are_dropped() {
        let fine = [0.5, 1.0, 2.0, 0.3, 0.4];
        let overflow = [710.0, 1.0, 2.0, 0.3, 0.4];
        let kept = finite_draws(&[Some(fine), None, Some(overflow)]);
        assert_eq!(kept, vec![natural(&fine)]);
        assert!(natural(&overflow)[1].is_infinite());
    }

    #[test]
    fn huber_by_hand() {
        assert_eq!(huber(0.0005, 1e-3), (0.5 * 0.0005 * 0.0005, 0.0005));
        let (v, d) = huber(-0.01, 1e-3);
        assert!((v - 1e-3 * (0.01 - 0.0005)).abs() < 1e-18);
        assert_eq!(d, -1e-3);
        // Continuous value and slope at the threshold.
        let (inside, din) = huber(1e-3, 1e-3);
        let (outside, dout) = huber(1e-3 + 1e-12, 1e-3);
        assert!((inside - outside).abs() < 1e-14 && (din - dout).abs() < 1e-12);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let n = [1e7, 3e8, 2e9, 5e7];
        let d = [1e9, 2e10, 5e9, 3e11];
        let l = [3.1, 2.6, 2.4, 2.9];
        let runs = LogRuns::new(&n, &d, &l);
        let theta = [6.0, 5.5, 0.4, 0.33, 0.27];
        for delta in [1e-3, 10.0] {
            let mut g = [0.0; 5];
            objective(&runs, delta, &theta, &mut g);
            for k in 0..5 {
                let h = 1e-6;
                let (mut tp, mut tm) = (theta, theta);
                tp[k] += h;
                tm[k] -= h;
                let mut scratch = [0.0; 5];
                let fd = (objective(&runs, delta, &tp, &mut scratch)
                    - objective(&runs, delta, &tm, &mut scratch))
                    / (2.0 * h);
                assert!(
                    (fd - g[k]).abs() < 1e-6 * (1.0 + g[k].abs()),
                    "δ={delta} k={k}: {fd} vs {}",
                    g[k]
                );
            }
        }
    }

    #[test]
    fn vectorised_objective_matches_the_plain_log_sum_exp() {
        let n: Vec<f64> = (0..150).map(|i| 1e6 * 1.07f64.powi(i)).collect();
        let d: Vec<f64> = (0..150).map(|i| 1e8 * 1.05f64.powi(i)).collect();
        let l: Vec<f64> = (0..150).map(|i| 2.0 + 0.01 * (i % 7) as f64).collect();
        let runs = LogRuns::new(&n, &d, &l);
        // Ordinary, and extreme enough for the overflow-safe path (t > 700).
        for theta in [
            [6.0, 5.5, 0.4, 0.33, 0.27],
            [25.0, 0.0, -1.0, 2.0, 0.0],
            [800.0, 5.0, 0.5, 0.1, 0.3],
        ] {
            let mut g = [0.0; 5];
            let got = objective(&runs, 1e-3, &theta, &mut g);
            let mut want = 0.0;
            let mut want_g = [0.0; 5];
            for i in 0..runs.len() {
                let (lse, w) = lse3(runs.terms(&theta, i));
                let (h, dh) = huber(lse - runs.ln_l[i], 1e-3);
                want += h;
                for k in 0..3 {
                    want_g[k] += dh * w[k];
                }
                want_g[3] -= dh * w[0] * runs.ln_n[i];
                want_g[4] -= dh * w[1] * runs.ln_d[i];
            }
            assert!(
                (got - want).abs() <= 1e-12 * want.abs(),
                "{theta:?}: {got} vs {want}"
            );
            for k in 0..5 {
                assert!(
                    (g[k] - want_g[k]).abs() <= 1e-10 * (1.0 + want_g[k].abs()),
                    "{theta:?} grad {k}"
                );
            }
        }
    }

    #[test]
    fn noiseless_law_is_recovered_exactly_from_the_coarse_grid() {
        let (e, a, b, alpha, beta) = (1.69f64, 406.4f64, 410.7f64, 0.34, 0.28);
        let mut n = Vec::new();
        let mut d = Vec::new();
        let mut l = Vec::new();
        for i in 0..6 {
            for j in 0..6 {
                let nn = 10f64.powf(7.0 + 0.5 * i as f64);
                let dd = 10f64.powf(9.0 + 0.5 * j as f64);
                n.push(nn);
                d.push(dd);
                l.push(e + a / nn.powf(alpha) + b / dd.powf(beta));
            }
        }
        let runs = LogRuns::new(&n, &d, &l);
        let ms = multi_start(
            &runs,
            1e-3,
            &StartGrid::coarse().points(),
            &LbfgsOptions::default(),
        )
        .unwrap();
        let got = natural(&ms.best().x);
        let want = [e, a, b, alpha, beta];
        for k in 0..5 {
            assert!((got[k] - want[k]).abs() < 1e-4 * want[k], "{k}: {got:?}");
        }
        assert!(ms.best().f < 1e-16, "{:?}", ms.best());
    }

    #[test]
    fn grids_have_the_documented_sizes() {
        assert_eq!(StartGrid::epoch().len(), 4500);
        assert_eq!(StartGrid::epoch().points().len(), 4500);
        assert_eq!(StartGrid::epoch().a, vec![0.0, 5.0, 10.0, 15.0, 20.0, 25.0]);
        assert_eq!(StartGrid::coarse().len(), 243);
        let g = StartGrid::parse("alpha=0.2/0.4, a=0:10:5").unwrap();
        assert_eq!(g.alpha, vec![0.2, 0.4]);
        assert_eq!(g.a, vec![0.0, 5.0, 10.0]);
        assert_eq!(g.len(), 2 * 5 * 5 * 3 * 6);
        assert!(StartGrid::parse("gamma=1").is_err());
        assert!(StartGrid::parse("a=5:0:1").is_err());
    }

    #[test]
    fn percentiles_interpolate() {
        let v: Vec<f64> = (0..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.025), Some(2.5));
        assert_eq!(percentile(&v, 0.975), Some(97.5));
        assert_eq!(percentile(&[], 0.5), None);
    }
}
