//! Placing a budget's model sizes around the N_opt an earlier fit predicts: the window of
//! the candidate ladder centred on it in log N, and a warning whenever the sampled sizes do
//! not bracket it (a minimum at the edge of a sweep is not a minimum).

use fits::isoflop::BudgetMinimum;
use fits::laws::PowerLaw;
use serde::{Deserialize, Serialize};

/// Where a budget's predicted N_opt comes from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Centre {
    /// The budget C.
    pub budget: f64,
    /// The predicted N_opt (non-vocabulary parameters, as the fit's N column).
    pub n_opt: f64,
    /// The fit's own parabola at this budget, or its N_opt ∝ C^b law.
    pub source: String,
}

/// [`centre`] of an IsoFLOP fit at `budget`, from its parabolas, its N_opt ∝ C^b law and
/// its parametric law.
pub fn of_fit(fits: &fits::Fits, budget: f64) -> Result<Centre, String> {
    let parametric = fits
        .parametric
        .as_ref()
        .map(|p| fits::predict::parametric_at(p, budget).n_opt.value);
    let law = fits.power_laws.get("n_opt_vs_c");
    centre(&fits.budgets, law, parametric, budget)
}

/// Predicted N_opt at `budget` from an earlier fit: the vertex of its parabola at the same
/// budget (within 0.05 dex) when it is convex, even outside the sizes it sampled (the best guess
/// after a pilot whose minimum sat at an edge); else its N_opt ∝ C^b law; else
/// `parametric_n_opt`, the compute-optimal N of its parametric L(N, D) at `budget` (a pilot with
/// fewer than three interior minima has no law).
pub fn centre(
    budgets: &[BudgetMinimum],
    law: Option<&PowerLaw>,
    parametric_n_opt: Option<f64>,
    budget: f64,
) -> Result<Centre, String> {
    let same = budgets
        .iter()
        .find(|b| (b.min.budget.log10() - budget.log10()).abs() <= 0.05);
    if let Some(b) = same {
        if let (Some(n), Some(k)) = (b.min.opt, b.min.curvature.filter(|k| *k > 0.0)) {
            let source = if b.min.interior {
                format!("the fit's parabola at this budget (curvature {k:.3e})")
            } else {
                format!(
                    "the fit's parabola at this budget, whose vertex lies outside its sizes ({})",
                    b.min.reason.as_deref().unwrap_or("not interior")
                )
            };
            return Ok(Centre {
                budget,
                n_opt: n,
                source,
            });
        }
    }
    match (law, parametric_n_opt) {
        (Some(law), _) => Ok(Centre {
            budget,
            n_opt: law.at(budget).value,
            source: format!("the fit's law {}", law.equation()),
        }),
        (None, Some(n_opt)) => Ok(Centre {
            budget,
            n_opt,
            source: "the compute-optimal N of the fit's parametric L(N, D)".into(),
        }),
        (None, None) => Err(format!(
            "budget {budget:.3e}: the fit has no convex parabola at this budget, no N_opt ∝ C^b law and no parametric L(N, D)"
        )),
    }
}

/// The `k` consecutive sizes of the sorted `sizes` centred on `n_opt` in log10, as a range of
/// indices ([`bracket_warning`] says whether they bracket it).
pub fn window(sizes: &[f64], n_opt: f64, k: usize) -> std::ops::Range<usize> {
    let k = k.clamp(1, sizes.len().max(1));
    let nearest = (0..sizes.len())
        .min_by(|&i, &j| {
            let d = |x: f64| (x.log10() - n_opt.log10()).abs();
            d(sizes[i]).total_cmp(&d(sizes[j]))
        })
        .unwrap_or(0);
    let start = nearest
        .saturating_sub(k / 2)
        .min(sizes.len().saturating_sub(k));
    start..(start + k).min(sizes.len())
}

/// A warning when `sampled` has fewer than two sizes below or above `n_opt`.
pub fn bracket_warning(sampled: &[f64], n_opt: f64, budget: f64) -> Option<String> {
    let below = sampled.iter().filter(|&&n| n < n_opt).count();
    let above = sampled.iter().filter(|&&n| n > n_opt).count();
    if below >= 2 && above >= 2 {
        return None;
    }
    let (lo, hi) = sampled
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &n| (a.min(n), b.max(n)));
    let side = if below < 2 { "smaller" } else { "larger" };
    Some(format!(
        "budget {budget:.3e}: the sizes sampled ({lo:.3e} .. {hi:.3e}) have {below} below and {above} above the predicted N_opt = {n_opt:.3e}; a minimum at the edge is not a minimum: add {side} models"
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ladder() -> Vec<f64> {
        (0..9).map(|i| 1e5 * 2f64.powi(i)).collect()
    }

    #[test]
    fn the_window_is_centred_on_n_opt_and_brackets_it() {
        let sizes = ladder();
        let r = window(&sizes, 1.6e6, 6);
        assert_eq!(
            r,
            1..7,
            "1.6e6 is ladder[4]: three sizes below it, two above"
        );
        assert_eq!(bracket_warning(&sizes[r], 1.6e6, 1e12), None);
    }

    #[test]
    fn a_prediction_at_or_past_the_ladder_end_warns() {
        let sizes = ladder();
        let r = window(&sizes, 5e7, 6);
        assert_eq!(r, 3..9, "clamped to the largest sizes");
        let w = bracket_warning(&sizes[r], 5e7, 3e13).expect("the optimum is above every size");
        assert!(
            w.contains("6 below and 0 above") && w.contains("add larger models"),
            "{w}"
        );
        let r = window(&sizes, 1.5e5, 6);
        let w = bracket_warning(&sizes[r], 1.5e5, 1e11).unwrap();
        assert!(w.contains("add smaller models"), "{w}");
    }

    #[test]
    fn a_pilot_whose_minimum_sits_at_the_edge_centres_on_its_vertex_and_warns() {
        use fits::isoflop::parabola_minimum;
        // A pilot at 1e12 sampled 1e5..8e5, but the loss falls all the way: the vertex is
        // beyond the largest size.
        let n: Vec<f64> = (0..4).map(|i| 1e5 * 2f64.powi(i)).collect();
        let loss: Vec<f64> = n
            .iter()
            .map(|v| 2.0 + 0.3 * (v.log10() - 6.3).powi(2))
            .collect();
        let min = parabola_minimum(1e12, "N", None, &n, &loss);
        assert!(!min.interior);
        let budgets = [BudgetMinimum {
            min,
            runs: 4,
            d_opt: None,
            nv_opt: None,
            nv_reason: None,
            v_opt: None,
        }];
        let c = centre(&budgets, None, Some(1e9), 1e12).unwrap();
        assert!((c.n_opt.log10() - 6.3).abs() < 1e-9, "{c:?}");
        assert!(c.source.contains("outside its sizes"), "{}", c.source);
        // Re-planned on the same small ladder the optimum is still past the edge: warned.
        let r = window(&n, c.n_opt, 4);
        let w = bracket_warning(&n[r], c.n_opt, 1e12).unwrap();
        assert!(w.contains("add larger models"), "{w}");
        // No parabola at another budget, no law and no parametric fit: the error says why.
        let err = centre(&budgets, None, None, 1e13).unwrap_err();
        assert!(err.contains("no convex parabola"), "{err}");
        // Without a law, the parametric fit's optimum centres it.
        let c = centre(&budgets, None, Some(2.5e6), 1e13).unwrap();
        assert_eq!(c.n_opt, 2.5e6);
        assert!(c.source.contains("parametric"), "{}", c.source);
        // With a law, another budget is centred on it (before the parametric fit).
        let law = PowerLaw::exact("C", "N_opt", -0.52, 0.57);
        let c = centre(&budgets, Some(&law), Some(2.5e6), 1e13).unwrap();
        assert!((c.n_opt / 10f64.powf(-0.52 + 0.57 * 13.0) - 1.0).abs() < 1e-12);
    }
}
