//! IsoFLOP minima (Chinchilla approach 2): per budget, a parabola of loss in log10 N whose
//! vertex is the compute-optimal N — used only when it is a real interior minimum (convex, and
//! inside the sampled range); likewise over log10 V at a fixed N.

use crate::laws::Estimate;
use crate::ols::{distinct, Line, Parabola};
use serde::{Deserialize, Serialize};

/// A parabola minimum over one variable (N at a budget, or V at a budget and fixed N).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IsoMinimum {
    /// The budget C of the group.
    pub budget: f64,
    /// The variable minimised over: `N` or `V`.
    pub over: String,
    /// The fixed N for minima over V.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fixed_n: Option<f64>,
    /// (x, loss) for each distinct x, the lowest loss at that x, sorted by x.
    pub points: Vec<[f64; 2]>,
    /// True only for a convex parabola whose vertex lies inside the sampled x range.
    pub interior: bool,
    /// Why the minimum is not interior (or could not be fitted).
    pub reason: Option<String>,
    /// log10 of the vertex with its delta-method SE and t interval (present whenever a parabola was fitted).
    pub log10_opt: Option<Estimate>,
    /// The vertex x* = 10^log10_opt.
    pub opt: Option<f64>,
    /// The parabola's loss at the vertex.
    pub loss_opt: Option<f64>,
    /// c2 of loss = c0 + c1·u + c2·u², u = log10 x − centre (positive: convex).
    pub curvature: Option<f64>,
    /// R² of the parabola.
    pub r2: Option<f64>,
    /// loss − parabola at each point.
    pub residuals: Vec<f64>,
    /// [centre, c0, c1, c2] to redraw the parabola.
    pub parabola: Option<[f64; 4]>,
    /// For interior minima over V: N_v = V_opt·width at this N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nv_opt: Option<f64>,
}

/// The minimum over N at one budget, with D and N_v read off at N_opt.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BudgetMinimum {
    /// The parabola minimum over N.
    #[serde(flatten)]
    pub min: IsoMinimum,
    /// Runs in this budget group.
    pub runs: usize,
    /// D at N_opt (log10 D linear in log10 N across the budget's points).
    pub d_opt: Option<f64>,
    /// N_v at N_opt (log10 of the fixed-N vocabulary optima linear in log10 N, inside their N range).
    pub nv_opt: Option<f64>,
    /// Why `nv_opt` is missing, when a vocabulary column exists.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nv_reason: Option<String>,
    /// V at N_opt (log10 of the fixed-N vocabulary optima linear in log10 N, as `nv_opt`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v_opt: Option<f64>,
}

/// Fits a parabola of `loss` in log10 `x` (lowest loss per distinct x) and judges its vertex.
pub fn parabola_minimum(
    budget: f64,
    over: &str,
    fixed_n: Option<f64>,
    x: &[f64],
    loss: &[f64],
) -> IsoMinimum {
    let points = envelope(x, loss);
    let mut out = IsoMinimum {
        budget,
        over: over.into(),
        fixed_n,
        points: points.clone(),
        interior: false,
        reason: None,
        log10_opt: None,
        opt: None,
        loss_opt: None,
        curvature: None,
        r2: None,
        residuals: Vec::new(),
        parabola: None,
        nv_opt: None,
    };
    let lx: Vec<f64> = points.iter().map(|p| p[0].log10()).collect();
    let ly: Vec<f64> = points.iter().map(|p| p[1]).collect();
    if distinct(&lx) < 3 {
        out.reason = Some(format!(
            "only {} distinct {over} value(s); a parabola needs 3",
            distinct(&lx)
        ));
        return out;
    }
    let Some(p) = Parabola::fit(&lx, &ly) else {
        out.reason = Some("parabola fit is singular".into());
        return out;
    };
    let (lo, hi) = (lx[0], lx[lx.len() - 1]);
    out.curvature = Some(p.curvature());
    out.r2 = p.ols.r2.is_finite().then_some(p.ols.r2);
    out.residuals = p.ols.residuals.clone();
    out.parabola = Some([p.centre, p.coef[0], p.coef[1], p.coef[2]]);
    if p.curvature() <= 0.0 {
        out.reason = Some(format!(
            "not convex in log10 {over} (curvature {:.3e} ≤ 0): no minimum",
            p.curvature()
        ));
        return out;
    }
    let v = p.vertex();
    out.log10_opt = Some(Estimate::with_se(v, p.vertex_se(), p.ols.dof));
    out.opt = Some(10f64.powf(v));
    out.loss_opt = Some(p.at(v));
    if v < lo || v > hi {
        out.reason = Some(format!(
            "vertex at {over} = {:.3e} lies outside the sampled range [{:.3e}, {:.3e}]",
            10f64.powf(v),
            10f64.powf(lo),
            10f64.powf(hi)
        ));
        return out;
    }
    out.interior = true;
    out
}

/// The lowest loss at each distinct x, sorted by x.
pub(crate) fn envelope(x: &[f64], loss: &[f64]) -> Vec<[f64; 2]> {
    envelope_rows(x, loss)
        .into_iter()
        .map(|i| [x[i], loss[i]])
        .collect()
}

/// The rows of [`envelope`]: the row with the lowest loss at each distinct x (the first such
/// row on a tie), sorted by x.
pub(crate) fn envelope_rows(x: &[f64], loss: &[f64]) -> Vec<usize> {
    let mut rows: Vec<usize> = (0..x.len()).collect();
    rows.sort_by(|&i, &j| x[i].total_cmp(&x[j]).then(loss[i].total_cmp(&loss[j])));
    rows.dedup_by(|later, first| x[*later] == x[*first]);
    rows
}

/// Groups of row indices sharing a budget: equal values of `group` when given, otherwise runs
/// of `c` whose log10 gaps are at most `tol_dex` (single linkage). Sorted by budget.
pub fn group_rows(c: &[f64], group: Option<&[f64]>, tol_dex: f64) -> Vec<Vec<usize>> {
    let key: Vec<f64> = match group {
        Some(g) => g.to_vec(),
        None => c.iter().map(|v| v.log10()).collect(),
    };
    let mut order: Vec<usize> = (0..key.len()).collect();
    order.sort_by(|&i, &j| key[i].total_cmp(&key[j]));
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut last = f64::NAN;
    for i in order {
        let same = match group {
            Some(_) => key[i] == last,
            None => key[i] - last <= tol_dex,
        };
        match groups.last_mut() {
            Some(g) if same => g.push(i),
            _ => groups.push(vec![i]),
        }
        last = key[i];
    }
    groups
}

/// Geometric mean of `c` over `rows`: a budget group's C.
pub fn group_budget(c: &[f64], rows: &[usize]) -> f64 {
    10f64.powf(rows.iter().map(|&i| c[i].log10()).sum::<f64>() / rows.len() as f64)
}

/// Columns the minima read, row-aligned.
#[derive(Debug, Clone, Copy)]
pub struct Columns<'a> {
    /// Compute per run.
    pub c: &'a [f64],
    /// Model size (non-vocabulary parameters in our sweeps).
    pub n: &'a [f64],
    /// Loss.
    pub loss: &'a [f64],
    /// Training tokens.
    pub d: Option<&'a [f64]>,
    /// Vocabulary (codebook) size.
    pub v: Option<&'a [f64]>,
    /// Model width d (N_v = V·width).
    pub width: Option<&'a [f64]>,
}

/// Minima over V at each (budget, N) that has at least one run.
pub fn vocab_minima(cols: &Columns, groups: &[Vec<usize>]) -> Vec<IsoMinimum> {
    let Some(v) = cols.v else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for rows in groups {
        let budget = group_budget(cols.c, rows);
        let mut sizes: Vec<f64> = rows.iter().map(|&i| cols.n[i]).collect();
        sizes.sort_by(f64::total_cmp);
        sizes.dedup();
        for n in sizes {
            let at: Vec<usize> = rows.iter().copied().filter(|&i| cols.n[i] == n).collect();
            let x: Vec<f64> = at.iter().map(|&i| v[i]).collect();
            let l: Vec<f64> = at.iter().map(|&i| cols.loss[i]).collect();
            if distinct(&x) < 2 {
                continue;
            }
            let mut m = parabola_minimum(budget, "V", Some(n), &x, &l);
            if let (Some(w), Some(v_opt), true) = (cols.width, m.opt, m.interior) {
                let width = at.iter().map(|&i| w[i]).sum::<f64>() / at.len() as f64;
                m.nv_opt = Some(v_opt * width);
            }
            out.push(m);
        }
    }
    out
}

/// Minima over N per budget group, with D_opt and N_v_opt read off at N_opt (`vocab` are the
/// minima from [`vocab_minima`]).
pub fn budget_minima(
    cols: &Columns,
    groups: &[Vec<usize>],
    vocab: &[IsoMinimum],
) -> Vec<BudgetMinimum> {
    groups
        .iter()
        .map(|rows| {
            let budget = group_budget(cols.c, rows);
            let x: Vec<f64> = rows.iter().map(|&i| cols.n[i]).collect();
            let l: Vec<f64> = rows.iter().map(|&i| cols.loss[i]).collect();
            let min = parabola_minimum(budget, "N", None, &x, &l);
            let at_opt = |line: &Line| {
                let lx = min.log10_opt?.value;
                min.interior.then(|| 10f64.powf(line.at(lx)))
            };
            // D along the budget's best-per-N runs.
            let d_opt = cols.d.and_then(|d| {
                let best = best_rows(cols, rows);
                let lx: Vec<f64> = best.iter().map(|&i| cols.n[i].log10()).collect();
                let ly: Vec<f64> = best.iter().map(|&i| d[i].log10()).collect();
                Line::fit(&lx, &ly).and_then(|line| at_opt(&line))
            });
            let v_opt = cols
                .v
                .and_then(|_| at_optimum(&min, budget, vocab, |m| m.opt).0);
            let (nv_opt, nv_reason) = match (cols.v, cols.width) {
                (None, _) => (None, None),
                (Some(_), None) => (
                    None,
                    Some("no width column: N_v = V·d cannot be formed".to_string()),
                ),
                (Some(_), Some(_)) => at_optimum(&min, budget, vocab, |m| m.nv_opt),
            };
            BudgetMinimum {
                min,
                runs: rows.len(),
                d_opt,
                nv_opt,
                nv_reason,
                v_opt,
            }
        })
        .collect()
}

/// The lowest-loss run at each distinct N within `rows`.
fn best_rows(cols: &Columns, rows: &[usize]) -> Vec<usize> {
    let mut best: Vec<usize> = Vec::new();
    let mut sorted = rows.to_vec();
    sorted.sort_by(|&i, &j| {
        cols.n[i]
            .total_cmp(&cols.n[j])
            .then(cols.loss[i].total_cmp(&cols.loss[j]))
    });
    for i in sorted {
        if best.last().is_none_or(|&j| cols.n[j] != cols.n[i]) {
            best.push(i);
        }
    }
    best
}

/// A vocabulary optimum read off at N_opt: log10 of `value` (V_opt or N_v_opt) of the budget's
/// interior fixed-N vocabulary minima, linear in log10 N, evaluated at N_opt when N_opt lies
/// inside their N range.
fn at_optimum(
    min: &IsoMinimum,
    budget: f64,
    vocab: &[IsoMinimum],
    value: fn(&IsoMinimum) -> Option<f64>,
) -> (Option<f64>, Option<String>) {
    let Some(n_opt) = min.opt.filter(|_| min.interior) else {
        return (None, Some("no interior N minimum at this budget".into()));
    };
    let (lx, ly): (Vec<f64>, Vec<f64>) = vocab
        .iter()
        .filter(|m| m.budget == budget && m.interior)
        .filter_map(|m| Some((m.fixed_n?.log10(), value(m)?.log10())))
        .unzip();
    if distinct(&lx) < 2 {
        return (
            None,
            Some(format!(
                "{} interior vocabulary minima at fixed N; need 2 to read N_v at N_opt",
                lx.len()
            )),
        );
    }
    let (lo, hi) = lx
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let at = n_opt.log10();
    if at < lo || at > hi {
        return (
            None,
            Some(format!(
                "N_opt = {n_opt:.3e} outside the N range [{:.3e}, {:.3e}] of the vocabulary minima",
                10f64.powf(lo),
                10f64.powf(hi)
            )),
        );
    }
    let line = Line::fit(&lx, &ly).expect("two distinct x");
    (Some(10f64.powf(line.at(at))), None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interior_vertex_is_found_and_edge_or_concave_ones_are_rejected() {
        let x: Vec<f64> = (0..7).map(|i| 10f64.powf(7.0 + 0.25 * i as f64)).collect();
        let bowl = |c: f64| move |v: &f64| 2.0 + 0.3 * (v.log10() - c).powi(2);
        let l: Vec<f64> = x.iter().map(bowl(7.8)).collect();
        let m = parabola_minimum(1e18, "N", None, &x, &l);
        assert!(m.interior, "{m:?}");
        assert!((m.log10_opt.unwrap().value - 7.8).abs() < 1e-9);
        assert!((m.loss_opt.unwrap() - 2.0).abs() < 1e-9);

        let edge: Vec<f64> = x.iter().map(bowl(9.0)).collect();
        let m = parabola_minimum(1e18, "N", None, &x, &edge);
        assert!(
            !m.interior && m.reason.as_ref().unwrap().contains("outside"),
            "{m:?}"
        );
        assert!(
            (m.log10_opt.unwrap().value - 9.0).abs() < 1e-9,
            "the vertex is still reported"
        );

        let cap: Vec<f64> = x
            .iter()
            .map(|v| 3.0 - 0.1 * (v.log10() - 7.7).powi(2))
            .collect();
        let m = parabola_minimum(1e18, "N", None, &x, &cap);
        assert!(
            !m.interior && m.reason.as_ref().unwrap().contains("not convex"),
            "{m:?}"
        );

        let m = parabola_minimum(1e18, "N", None, &x[..2], &l[..2]);
        assert!(!m.interior && m.reason.as_ref().unwrap().contains("needs 3"));
    }

    #[test]
    fn envelope_keeps_the_lowest_loss_per_x() {
        let e = envelope(&[2.0, 1.0, 2.0, 1.0], &[5.0, 4.0, 3.0, 6.0]);
        assert_eq!(e, vec![[1.0, 4.0], [2.0, 3.0]]);
    }

    #[test]
    fn grouping_by_column_or_by_closeness() {
        let c = [1e18, 1.05e18, 3e18, 2.9e18, 1e19];
        let g = group_rows(&c, None, 0.05);
        assert_eq!(g, vec![vec![0, 1], vec![3, 2], vec![4]]);
        let budget = [1.0, 1.0, 2.0, 2.0, 2.0];
        assert_eq!(
            group_rows(&c, Some(&budget), 0.05),
            vec![vec![0, 1], vec![2, 3, 4]]
        );
        assert!((group_budget(&c, &[0, 1]) - (1e18f64 * 1.05e18).sqrt()).abs() < 1e3);
    }
}
