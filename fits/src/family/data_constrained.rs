//! Muennighoff et al. (2023)'s data-constrained law: L = E + A/N^α + B/D'^β with the
//! effective data D' = U + U·R*_D·(1 − e^(−R/R*_D)), R = D/U − 1 the repetitions past the
//! first epoch, U capped at D; θ = (a, b, e, α, β, r) with A = eᵃ, B = eᵇ, E = eᵉ, R*_D = eʳ.

use super::chinchilla::{epoch_starts, Chinchilla};
use super::{Axis, Law, Point};

/// The data-constrained family (effective data; parameters counted as they are).
pub struct DataConstrained;

impl DataConstrained {
    /// The loss at `x` with ∂L/∂θ written into `g`, and ∂L/∂ln U: the slope in the size of
    /// the unique pool (0 where the pool is not repeated), which the exchange-rate forms need.
    pub(super) fn predict_with_pool_slope(
        &self,
        t: &[f64; 6],
        x: &Point,
        g: &mut [f64; 6],
    ) -> (f64, f64) {
        // U_D = min(U, D): a run shorter than its pool sees D unique tokens (D' = D).
        let u = x.u.unwrap_or(x.d).min(x.d);
        let r_star = t[5].exp();
        let reps = (x.d / u - 1.0).max(0.0);
        let decay = (-reps / r_star).exp();
        let d_eff = u * (1.0 + r_star * (1.0 - decay));
        // Chinchilla at the effective data; then ∂D'/∂r = R*·∂D'/∂R*
        // = R*·U·((1 − e^(−R/R*)) − (R/R*)·e^(−R/R*)).
        let mut g5 = [0.0; 5];
        let core = [t[0], t[1], t[2], t[3], t[4]];
        let loss = Chinchilla.predict(&core, &Point { d: d_eff, ..*x }, &mut g5);
        let dd_dr = r_star * u * ((1.0 - decay) - reps / r_star * decay);
        g[..5].copy_from_slice(&g5);
        g[5] = -t[4] * g5[1] * dd_dr / d_eff;
        // ∂D'/∂ln U_D = D' − D·e^(−R/R*) while the pool repeats (U < D).
        let pool_slope = if x.u.is_some_and(|pool| pool < x.d) {
            -t[4] * g5[1] * (d_eff - x.d * decay) / d_eff
        } else {
            0.0
        };
        (loss, pool_slope)
    }
}

impl Law<6> for DataConstrained {
    fn name(&self) -> &'static str {
        "data-constrained"
    }

    fn equation(&self) -> &'static str {
        "L = E + A/N^alpha + B/D'^beta, D' = U_D + U_D*R_D*(1 - exp(-(D/U_D - 1)/R_D)), U_D = min(U, D)"
    }

    fn needs(&self) -> &'static [Axis] {
        &[Axis::N, Axis::D, Axis::U]
    }

    fn positive(&self) -> bool {
        true
    }

    fn param_names(&self) -> [&'static str; 6] {
        ["a", "b", "e", "alpha", "beta", "r"]
    }

    fn start_values(&self, _loss: &[f64]) -> [Vec<f64>; 6] {
        let [a, b, e, alpha, beta] = epoch_starts();
        [a, b, e, alpha, beta, vec![0.0, 1.5, 3.0, 4.5]]
    }

    fn predict(&self, t: &[f64; 6], x: &Point, g: &mut [f64; 6]) -> f64 {
        self.predict_with_pool_slope(t, x, g).0
    }

    fn natural(&self, t: &[f64; 6]) -> Vec<(&'static str, f64)> {
        vec![
            ("E", t[2].exp()),
            ("A", t[0].exp()),
            ("B", t[1].exp()),
            ("alpha", t[3]),
            ("beta", t[4]),
            ("R*_D", t[5].exp()),
        ]
    }

    fn theta_from_natural(&self, p: &[f64; 6]) -> [f64; 6] {
        [p[1].ln(), p[2].ln(), p[0].ln(), p[3], p[4], p[5].ln()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run shorter than its pool is Chinchilla's at D (D' = D, not U); one repeating its
    /// pool sees less than D.
    #[test]
    fn effective_data_is_the_tokens_seen_until_the_pool_repeats() {
        let t = [5.0, 6.0, 0.5, 0.34, 0.28, 2.0];
        let core = [t[0], t[1], t[2], t[3], t[4]];
        let mut g = [0.0; 6];
        let at = |d: f64, u: f64| Point {
            n: 1e8,
            d,
            u: Some(u),
            ..Point::default()
        };
        let plain = |d: f64| Chinchilla.predict(&core, &at(d, d), &mut [0.0; 5]);
        let short = DataConstrained.predict(&t, &at(1e9, 1e11), &mut g);
        let (p9, p11) = (plain(1e9), plain(1e11));
        assert!((short - p9).abs() < 1e-12, "{short} vs {p9}");
        let repeated = DataConstrained.predict(&t, &at(1e11, 1e9), &mut g);
        assert!(repeated > p11, "{repeated} vs {p11}");
    }
}
