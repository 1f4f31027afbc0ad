//! A saturating law for repeated data: Chinchilla's L(N, D) plus a floor set by the unique
//! data with its own exponent, L = E + A/N^α + B/D^β + C/U^γ. Past the point where the
//! N and D terms are spent, the loss stays at E + C/U^γ however much is trained: the plateau
//! that the data-constrained law reaches only through its effective data (and with D's
//! exponent β). θ = (a, b, c, e, α, β, γ) with A = eᵃ, B = eᵇ, C = eᶜ, E = eᵉ.

use super::chinchilla::epoch_starts;
use super::{Axis, Law, Point};

/// The unique-data floor family.
pub struct UniqueFloor;

impl Law<7> for UniqueFloor {
    fn name(&self) -> &'static str {
        "unique-floor"
    }

    fn equation(&self) -> &'static str {
        "L = E + A/N^alpha + B/D^beta + C/U^gamma"
    }

    fn needs(&self) -> &'static [Axis] {
        &[Axis::N, Axis::D, Axis::U]
    }

    fn positive(&self) -> bool {
        true
    }

    fn param_names(&self) -> [&'static str; 7] {
        ["a", "b", "c", "e", "alpha", "beta", "gamma"]
    }

    fn start_values(&self, _loss: &[f64]) -> [Vec<f64>; 7] {
        let [a, b, e, alpha, beta] = epoch_starts();
        [a, b, vec![0.0, 5.0], e, alpha, beta, vec![0.25, 0.75]]
    }

    fn predict(&self, t: &[f64; 7], x: &Point, g: &mut [f64; 7]) -> f64 {
        let ln_u = x.u.unwrap_or(x.d).ln();
        let (ln_n, ln_d) = (x.n.ln(), x.d.ln());
        let t1 = (t[0] - t[4] * ln_n).exp();
        let t2 = (t[1] - t[5] * ln_d).exp();
        let t3 = (t[2] - t[6] * ln_u).exp();
        let e = t[3].exp();
        *g = [t1, t2, t3, e, -t1 * ln_n, -t2 * ln_d, -t3 * ln_u];
        e + t1 + t2 + t3
    }

    fn natural(&self, t: &[f64; 7]) -> Vec<(&'static str, f64)> {
        vec![
            ("E", t[3].exp()),
            ("A", t[0].exp()),
            ("B", t[1].exp()),
            ("C", t[2].exp()),
            ("alpha", t[4]),
            ("beta", t[5]),
            ("gamma", t[6]),
        ]
    }

    fn theta_from_natural(&self, p: &[f64; 7]) -> [f64; 7] {
        [p[1].ln(), p[2].ln(), p[3].ln(), p[0].ln(), p[4], p[5], p[6]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// However long a run trains on a fixed pool, its loss stays above E + C/U^γ; a larger
    /// pool lowers that floor.
    #[test]
    fn the_floor_follows_the_unique_data() {
        let t = UniqueFloor.theta_from_natural(&[1.8, 400.0, 400.0, 30.0, 0.34, 0.28, 0.2]);
        let at = |n: f64, d: f64, u: f64| {
            UniqueFloor.predict(
                &t,
                &Point {
                    n,
                    d,
                    u: Some(u),
                    ..Point::default()
                },
                &mut [0.0; 7],
            )
        };
        let floor = |u: f64| 1.8 + 30.0 * u.powf(-0.2);
        assert!(at(1e20, 1e24, 1e8) > floor(1e8));
        assert!((at(1e20, 1e24, 1e8) - floor(1e8)).abs() < 1e-3);
        assert!(floor(1e9) < floor(1e8));
    }
}
