//! The vocabulary as a multiplier of the effective model and data: L = E + A/(N·N_v^k₁)^α +
//! B/(D·N_v^k₂)^β (ScaleBench's vocabulary form sl_6, arXiv 2604.22753): a larger vocabulary
//! acts as more parameters and, through its compression, as more data. E is free (the loss is
//! negative), A = eᵃ, B = eᵇ.

use super::{free_floor_starts, Axis, Law, Point};

/// The effective-vocabulary family.
pub struct VocabEffective;

impl Law<7> for VocabEffective {
    fn name(&self) -> &'static str {
        "vocab-effective"
    }

    fn equation(&self) -> &'static str {
        "L = E + A/(N*N_v^k1)^alpha + B/(D*N_v^k2)^beta"
    }

    fn needs(&self) -> &'static [Axis] {
        &[Axis::N, Axis::Nv, Axis::D]
    }

    fn positive(&self) -> bool {
        false
    }

    fn param_names(&self) -> [&'static str; 7] {
        ["a", "alpha", "k1", "b", "beta", "k2", "E"]
    }

    fn start_values(&self, loss: &[f64]) -> [Vec<f64>; 7] {
        [
            vec![0.0, 5.0, 10.0],
            vec![0.1, 0.3, 0.6],
            vec![-0.5, 0.0, 0.5, 1.5],
            vec![5.0, 10.0, 15.0],
            vec![0.2, 0.4],
            vec![-0.5, 0.0, 0.5],
            free_floor_starts(loss),
        ]
    }

    fn predict(&self, t: &[f64; 7], x: &Point, g: &mut [f64; 7]) -> f64 {
        let ln_v = x.nv.unwrap_or(1.0).ln();
        let n_eff = x.n.ln() + t[2] * ln_v;
        let d_eff = x.d.ln() + t[5] * ln_v;
        let t1 = (t[0] - t[1] * n_eff).exp();
        let t2 = (t[3] - t[4] * d_eff).exp();
        *g = [
            t1,
            -t1 * n_eff,
            -t1 * t[1] * ln_v,
            t2,
            -t2 * d_eff,
            -t2 * t[4] * ln_v,
            1.0,
        ];
        t[6] + t1 + t2
    }

    fn natural(&self, t: &[f64; 7]) -> Vec<(&'static str, f64)> {
        vec![
            ("E", t[6]),
            ("A", t[0].exp()),
            ("alpha", t[1]),
            ("k1", t[2]),
            ("B", t[3].exp()),
            ("beta", t[4]),
            ("k2", t[5]),
        ]
    }

    fn theta_from_natural(&self, p: &[f64; 7]) -> [f64; 7] {
        [p[1].ln(), p[2], p[3], p[4].ln(), p[5], p[6], p[0]]
    }
}
