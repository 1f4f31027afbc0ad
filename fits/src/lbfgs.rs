//! L-BFGS with a strong-Wolfe line search (Nocedal & Wright, Algorithms 7.4, 3.5 and 3.6),
//! for small fixed-size problems: state lives in `[f64; N]` arrays.

/// Stopping and line-search settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LbfgsOptions {
    /// Correction pairs kept.
    pub memory: usize,
    /// Iteration cap.
    pub max_iter: usize,
    /// Converged when the largest gradient component is at most this (absolute).
    pub gtol: f64,
    /// Sufficient-decrease (Armijo) constant.
    pub c1: f64,
    /// Curvature constant of the strong Wolfe condition.
    pub c2: f64,
    /// Stalled when 10 steps in a row lower f by at most this much, relative.
    pub ftol: f64,
}

impl Default for LbfgsOptions {
    fn default() -> Self {
        Self {
            memory: 10,
            max_iter: 2000,
            gtol: 1e-10,
            c1: 1e-4,
            c2: 0.9,
            ftol: 1e-15,
        }
    }
}

/// Why the minimiser stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Termination {
    /// The gradient is below `gtol`.
    Gradient,
    /// No decrease is possible at floating-point precision (line search fails from a
    /// steepest-descent direction, or 10 steps in a row change f by at most `ftol` relative).
    Stalled,
    /// `max_iter` reached.
    MaxIter,
    /// The objective is not finite at the start.
    NonFinite,
}

/// The end point of a minimisation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Minimum<const N: usize> {
    /// Minimiser.
    pub x: [f64; N],
    /// Objective at `x`.
    pub f: f64,
    /// Largest absolute gradient component at `x`.
    pub grad_inf: f64,
    /// Iterations taken.
    pub iterations: usize,
    /// Objective/gradient evaluations.
    pub evaluations: usize,
    /// Why it stopped.
    pub termination: Termination,
}

fn dot<const N: usize>(a: &[f64; N], b: &[f64; N]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn inf_norm<const N: usize>(a: &[f64; N]) -> f64 {
    a.iter().fold(0.0, |m, v| m.max(v.abs()))
}

/// A point on the search line: step, objective, directional derivative, position, gradient.
#[derive(Clone, Copy)]
struct Probe<const N: usize> {
    a: f64,
    f: f64,
    d: f64,
    x: [f64; N],
    g: [f64; N],
}

/// Minimises `f` (which returns the objective and writes the gradient into its second argument)
/// from `x0`.
pub fn minimize<const N: usize, F>(mut f: F, x0: [f64; N], opts: &LbfgsOptions) -> Minimum<N>
where
    F: FnMut(&[f64; N], &mut [f64; N]) -> f64,
{
    let mut x = x0;
    let mut g = [0.0; N];
    let mut fx = f(&x, &mut g);
    let mut evals = 1;
    let done = |x, f, g: &[f64; N], it, ev, t| Minimum {
        x,
        f,
        grad_inf: inf_norm(g),
        iterations: it,
        evaluations: ev,
        termination: t,
    };
    if !fx.is_finite() || g.iter().any(|v| !v.is_finite()) {
        return done(x, fx, &g, 0, evals, Termination::NonFinite);
    }
    let m = opts.memory.max(1);
    let mut s_hist: Vec<[f64; N]> = Vec::with_capacity(m);
    let mut y_hist: Vec<[f64; N]> = Vec::with_capacity(m);
    let mut rho_hist: Vec<f64> = Vec::with_capacity(m);
    let mut alpha = vec![0.0; m];
    let mut flat = 0;
    for it in 0..opts.max_iter {
        if inf_norm(&g) <= opts.gtol {
            return done(x, fx, &g, it, evals, Termination::Gradient);
        }
        // Two-loop recursion: d = −H·g.
        let mut q = g;
        for i in (0..s_hist.len()).rev() {
            alpha[i] = rho_hist[i] * dot(&s_hist[i], &q);
            for (qj, yj) in q.iter_mut().zip(&y_hist[i]) {
                *qj -= alpha[i] * yj;
            }
        }
        let gamma = match (s_hist.last(), y_hist.last()) {
            (Some(s), Some(y)) => dot(s, y) / dot(y, y),
            _ => 1.0,
        };
        for v in q.iter_mut() {
            *v *= gamma;
        }
        for i in 0..s_hist.len() {
            let beta = rho_hist[i] * dot(&y_hist[i], &q);
            for (qj, sj) in q.iter_mut().zip(&s_hist[i]) {
                *qj += (alpha[i] - beta) * sj;
            }
        }
        let mut d = q.map(|v| -v);
        let steepest = s_hist.is_empty() || dot(&g, &d) >= 0.0;
        if steepest {
            d = g.map(|v| -v);
            s_hist.clear();
            y_hist.clear();
            rho_hist.clear();
        }
        let a0 = if steepest {
            (1.0 / dot(&g, &g).sqrt()).min(1.0)
        } else {
            1.0
        };
        let start = Probe {
            a: 0.0,
            f: fx,
            d: dot(&g, &d),
            x,
            g,
        };
        match line_search(&mut f, &start, &d, a0, opts, &mut evals) {
            Some(p) => {
                let s: [f64; N] = std::array::from_fn(|j| p.x[j] - x[j]);
                let y: [f64; N] = std::array::from_fn(|j| p.g[j] - g[j]);
                let sy = dot(&s, &y);
                if sy > 1e-300 && dot(&y, &y) > 0.0 {
                    if s_hist.len() == m {
                        s_hist.remove(0);
                        y_hist.remove(0);
                        rho_hist.remove(0);
                    }
                    s_hist.push(s);
                    y_hist.push(y);
                    rho_hist.push(1.0 / sy);
                }
                flat = if fx - p.f <= opts.ftol * fx.abs() {
                    flat + 1
                } else {
                    0
                };
                x = p.x;
                g = p.g;
                fx = p.f;
                if flat >= 10 {
                    return done(x, fx, &g, it + 1, evals, Termination::Stalled);
                }
            }
            None if steepest => return done(x, fx, &g, it, evals, Termination::Stalled),
            None => {
                // Drop the curvature memory and retry from steepest descent.
                s_hist.clear();
                y_hist.clear();
                rho_hist.clear();
            }
        }
    }
    done(x, fx, &g, opts.max_iter, evals, Termination::MaxIter)
}

/// Evaluates the objective at step `a` along `d` from `start`.
fn probe<const N: usize, F>(
    f: &mut F,
    start: &Probe<N>,
    d: &[f64; N],
    a: f64,
    evals: &mut usize,
) -> Probe<N>
where
    F: FnMut(&[f64; N], &mut [f64; N]) -> f64,
{
    let x: [f64; N] = std::array::from_fn(|j| start.x[j] + a * d[j]);
    let mut g = [0.0; N];
    let fa = f(&x, &mut g);
    *evals += 1;
    let finite = fa.is_finite() && g.iter().all(|v| v.is_finite());
    Probe {
        a,
        f: if finite { fa } else { f64::INFINITY },
        d: if finite { dot(&g, d) } else { f64::NAN },
        x,
        g,
    }
}

/// Strong-Wolfe line search (N&W Algorithm 3.5). `None` when no step decreases f.
fn line_search<const N: usize, F>(
    f: &mut F,
    start: &Probe<N>,
    d: &[f64; N],
    a0: f64,
    opts: &LbfgsOptions,
    evals: &mut usize,
) -> Option<Probe<N>>
where
    F: FnMut(&[f64; N], &mut [f64; N]) -> f64,
{
    let armijo = |p: &Probe<N>| p.f <= start.f + opts.c1 * p.a * start.d;
    let curvature = |p: &Probe<N>| p.d.abs() <= -opts.c2 * start.d;
    let mut prev = *start;
    let mut a = a0;
    for i in 0..40 {
        let p = probe(f, start, d, a, evals);
        if !armijo(&p) || (i > 0 && p.f >= prev.f) {
            return zoom(f, start, d, prev, p, opts, evals);
        }
        if curvature(&p) {
            return Some(p);
        }
        if p.d >= 0.0 {
            return zoom(f, start, d, p, prev, opts, evals);
        }
        prev = p;
        a *= 2.0;
    }
    (prev.a > 0.0).then_some(prev)
}

/// N&W Algorithm 3.6 with safeguarded cubic interpolation. `lo` satisfies Armijo with the
/// lowest f so far; the minimiser lies between `lo` and `hi`.
fn zoom<const N: usize, F>(
    f: &mut F,
    start: &Probe<N>,
    d: &[f64; N],
    mut lo: Probe<N>,
    mut hi: Probe<N>,
    opts: &LbfgsOptions,
    evals: &mut usize,
) -> Option<Probe<N>>
where
    F: FnMut(&[f64; N], &mut [f64; N]) -> f64,
{
    // Steps that move x by less than its floating-point resolution cannot change f.
    let d_inf = inf_norm(d);
    let x_res = 4.0 * f64::EPSILON * (inf_norm(&start.x) + 1.0);
    for _ in 0..60 {
        let width = hi.a - lo.a;
        if width.abs() * d_inf <= x_res {
            break;
        }
        let a = cubic_min(&lo, &hi)
            .filter(|&c| {
                let (l, h) = (lo.a.min(hi.a), lo.a.max(hi.a));
                c > l + 0.1 * (h - l) && c < h - 0.1 * (h - l)
            })
            .unwrap_or(lo.a + 0.5 * width);
        let p = probe(f, start, d, a, evals);
        if p.f > start.f + opts.c1 * a * start.d || p.f >= lo.f {
            hi = p;
        } else {
            if p.d.abs() <= -opts.c2 * start.d {
                return Some(p);
            }
            if p.d * (hi.a - lo.a) >= 0.0 {
                hi = lo;
            }
            lo = p;
        }
    }
    (lo.a > 0.0 && lo.f < start.f).then_some(lo)
}

/// Minimiser of the cubic matching f and f' at both ends (N&W eq. 3.59); `None` if undefined.
fn cubic_min<const N: usize>(lo: &Probe<N>, hi: &Probe<N>) -> Option<f64> {
    if !(hi.f.is_finite() && hi.d.is_finite()) {
        return None;
    }
    let d1 = lo.d + hi.d - 3.0 * (lo.f - hi.f) / (lo.a - hi.a);
    let disc = d1 * d1 - lo.d * hi.d;
    if disc < 0.0 {
        return None;
    }
    let d2 = (hi.a - lo.a).signum() * disc.sqrt();
    let a = hi.a - (hi.a - lo.a) * (hi.d + d2 - d1) / (hi.d - lo.d + 2.0 * d2);
    a.is_finite().then_some(a)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rosenbrock(x: &[f64; 2], g: &mut [f64; 2]) -> f64 {
        let (a, b) = (1.0 - x[0], x[1] - x[0] * x[0]);
        g[0] = -2.0 * a - 400.0 * x[0] * b;
        g[1] = 200.0 * b;
        a * a + 100.0 * b * b
    }

    #[test]
    fn rosenbrock_from_the_classic_start() {
        let m = minimize(rosenbrock, [-1.2, 1.0], &LbfgsOptions::default());
        assert_eq!(m.termination, Termination::Gradient, "{m:?}");
        assert!(
            (m.x[0] - 1.0).abs() < 1e-8 && (m.x[1] - 1.0).abs() < 1e-8,
            "{m:?}"
        );
        assert!(m.f < 1e-18, "{m:?}");
        assert!(m.iterations < 100, "{m:?}");
    }

    #[test]
    fn rosenbrock_from_far_away_and_high_dimensions() {
        // Chained Rosenbrock in 6-D from a distant start.
        let f = |x: &[f64; 6], g: &mut [f64; 6]| {
            g.fill(0.0);
            let mut v = 0.0;
            for i in 0..5 {
                let (a, b) = (1.0 - x[i], x[i + 1] - x[i] * x[i]);
                v += a * a + 100.0 * b * b;
                g[i] += -2.0 * a - 400.0 * x[i] * b;
                g[i + 1] += 200.0 * b;
            }
            v
        };
        let m = minimize(
            f,
            [-3.0, 4.0, -2.0, 0.5, 3.0, -1.0],
            &LbfgsOptions::default(),
        );
        assert_eq!(m.termination, Termination::Gradient, "{m:?}");
        assert!(m.x.iter().all(|v| (v - 1.0).abs() < 1e-7), "{m:?}");
    }

    #[test]
    fn line_search_meets_strong_wolfe() {
        // A convex quadratic with a badly scaled first step: the accepted step satisfies both conditions.
        let mut f = |x: &[f64; 2], g: &mut [f64; 2]| {
            g[0] = 2.0 * x[0];
            g[1] = 20.0 * x[1];
            x[0] * x[0] + 10.0 * x[1] * x[1]
        };
        let mut g = [0.0; 2];
        let x = [3.0, 1.0];
        let fx = f(&x, &mut g);
        let d = g.map(|v| -v);
        let start = Probe {
            a: 0.0,
            f: fx,
            d: dot(&g, &d),
            x,
            g,
        };
        let opts = LbfgsOptions::default();
        let mut evals = 0;
        for a0 in [1e-4, 1.0, 100.0] {
            let p = line_search(&mut f, &start, &d, a0, &opts, &mut evals).unwrap();
            assert!(p.f <= fx + opts.c1 * p.a * start.d, "Armijo at a0 = {a0}");
            assert!(p.d.abs() <= -opts.c2 * start.d, "curvature at a0 = {a0}");
        }
    }

    #[test]
    fn non_finite_regions_are_backed_out_of() {
        // f = x − ln(x) is finite only for x > 0; minimum at x = 1.
        let f = |x: &[f64; 1], g: &mut [f64; 1]| {
            g[0] = 1.0 - 1.0 / x[0];
            if x[0] > 0.0 {
                x[0] - x[0].ln()
            } else {
                f64::NAN
            }
        };
        let m = minimize(f, [20.0], &LbfgsOptions::default());
        assert!((m.x[0] - 1.0).abs() < 1e-9, "{m:?}");
        let bad = minimize(f, [-1.0], &LbfgsOptions::default());
        assert_eq!(bad.termination, Termination::NonFinite);
    }
}
