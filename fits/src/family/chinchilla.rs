//! Chinchilla's L(N, D) = E + A/N^α + B/D^β (Hoffmann et al. 2022, approach 3), in the
//! log parametrisation θ = (a, b, e, α, β) with A = eᵃ, B = eᵇ, E = eᵉ.

use super::{Allocation, Axis, Law, Point};

/// The Chinchilla family.
pub struct Chinchilla;

/// The start values of today's `epoch` grid (4,500 points; scripts/scipy_fit.py uses them).
pub(super) fn epoch_starts() -> [Vec<f64>; 5] {
    let steps = |lo: f64, step: f64, n: usize| (0..n).map(|i| lo + step * i as f64).collect();
    [
        steps(0.0, 5.0, 6),
        steps(0.0, 5.0, 6),
        steps(-1.0, 0.5, 5),
        steps(0.0, 0.5, 5),
        steps(0.0, 0.5, 5),
    ]
}

/// Chinchilla's compute-optimal N at budget C = 6·N·D, from ln A, ln B and the exponents:
/// G·(C/6)^(β/(α+β)) with G = (αA/(βB))^(1/(α+β)).
pub(super) fn n_opt(ln_a: f64, ln_b: f64, alpha: f64, beta: f64, c: f64) -> f64 {
    let ln_g = ((alpha / beta).ln() + ln_a - ln_b) / (alpha + beta);
    (ln_g + beta / (alpha + beta) * (c / 6.0).ln()).exp()
}

impl Law<5> for Chinchilla {
    fn name(&self) -> &'static str {
        "chinchilla"
    }

    fn equation(&self) -> &'static str {
        "L = E + A/N^alpha + B/D^beta"
    }

    fn needs(&self) -> &'static [Axis] {
        &[Axis::N, Axis::D]
    }

    fn positive(&self) -> bool {
        true
    }

    fn param_names(&self) -> [&'static str; 5] {
        ["a", "b", "e", "alpha", "beta"]
    }

    fn start_values(&self, _loss: &[f64]) -> [Vec<f64>; 5] {
        epoch_starts()
    }

    fn predict(&self, t: &[f64; 5], x: &Point, g: &mut [f64; 5]) -> f64 {
        let (ln_n, ln_d) = (x.n.ln(), x.d.ln());
        let t1 = (t[0] - t[3] * ln_n).exp();
        let t2 = (t[1] - t[4] * ln_d).exp();
        let e = t[2].exp();
        *g = [t1, t2, e, -t1 * ln_n, -t2 * ln_d];
        e + t1 + t2
    }

    fn natural(&self, t: &[f64; 5]) -> Vec<(&'static str, f64)> {
        vec![
            ("E", t[2].exp()),
            ("A", t[0].exp()),
            ("B", t[1].exp()),
            ("alpha", t[3]),
            ("beta", t[4]),
        ]
    }

    fn theta_from_natural(&self, p: &[f64; 5]) -> [f64; 5] {
        [p[1].ln(), p[2].ln(), p[0].ln(), p[3], p[4]]
    }

    fn allocation(&self, t: &[f64; 5], c: f64) -> Option<Allocation> {
        let (alpha, beta) = (t[3], t[4]);
        if !(alpha > 0.0 && beta > 0.0) {
            return None;
        }
        let n = n_opt(t[0], t[1], alpha, beta, c);
        let d = c / (6.0 * n);
        let x = Point {
            n,
            d,
            ..Point::default()
        };
        let mut g = [0.0; 5];
        let loss = self.predict(t, &x, &mut g);
        Some(Allocation {
            compute: c,
            n,
            d,
            loss,
        })
    }
}
