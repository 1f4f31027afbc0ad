//! Tao et al. (2024), "Scaling Laws with Vocabulary" (approach 3): the unigram-normalised
//! loss L = E + A₁/N^α₁ + A₂/N_v^α₂ + B/D^β over non-vocabulary parameters N, vocabulary
//! parameters N_v (V·d; the vocabulary size where the table has no width) and training
//! characters D. E is free (the loss is negative), A₁ = e^a₁, A₂ = e^a₂, B = eᵇ; α₂ may take
//! either sign, so the vocabulary term can rise or fall with N_v.

use super::{free_floor_starts, Axis, Law, Point};

/// The vocabulary family.
pub struct Vocabulary;

impl Law<7> for Vocabulary {
    fn name(&self) -> &'static str {
        "vocab"
    }

    fn equation(&self) -> &'static str {
        "L = E + A1/N^alpha1 + A2/N_v^alpha2 + B/D^beta"
    }

    fn needs(&self) -> &'static [Axis] {
        &[Axis::N, Axis::Nv, Axis::D]
    }

    fn positive(&self) -> bool {
        false
    }

    fn param_names(&self) -> [&'static str; 7] {
        ["E", "a1", "alpha1", "a2", "alpha2", "b", "beta"]
    }

    fn start_values(&self, loss: &[f64]) -> [Vec<f64>; 7] {
        let coef = vec![0.0, 5.0, 10.0, 20.0];
        let exponent = vec![0.2, 0.5, 1.0];
        [
            free_floor_starts(loss),
            coef.clone(),
            exponent.clone(),
            coef.clone(),
            vec![-0.5, 0.2, 0.5],
            coef,
            exponent,
        ]
    }

    fn predict(&self, t: &[f64; 7], x: &Point, g: &mut [f64; 7]) -> f64 {
        let nv = x.nv.unwrap_or(1.0);
        let (ln_n, ln_v, ln_d) = (x.n.ln(), nv.ln(), x.d.ln());
        let t1 = (t[1] - t[2] * ln_n).exp();
        let t2 = (t[3] - t[4] * ln_v).exp();
        let t3 = (t[5] - t[6] * ln_d).exp();
        *g = [1.0, t1, -t1 * ln_n, t2, -t2 * ln_v, t3, -t3 * ln_d];
        t[0] + t1 + t2 + t3
    }

    fn natural(&self, t: &[f64; 7]) -> Vec<(&'static str, f64)> {
        vec![
            ("E", t[0]),
            ("A1", t[1].exp()),
            ("alpha1", t[2]),
            ("A2", t[3].exp()),
            ("alpha2", t[4]),
            ("B", t[5].exp()),
            ("beta", t[6]),
        ]
    }

    fn theta_from_natural(&self, p: &[f64; 7]) -> [f64; 7] {
        [p[0], p[1].ln(), p[2], p[3].ln(), p[4], p[5].ln(), p[6]]
    }
}
