//! The Farseer law (Li et al. 2025, "Farseer: A Refined Scaling Law in Large Language
//! Models"): L = exp(s·n^q + S) + exp(B·n^b + Q)·D^(−exp(A·n^a + E)), with n = N/10⁹ (a
//! fixed unit, so that s, B and A are of order one). The paper's signs are kept as bounds:
//! q ∈ (0, 1), b ∈ (−1, 0), a ∈ (0, 1).

use super::{Axis, Law, Point};

/// The Farseer family.
pub struct Farseer;

/// The unit of N in the law.
const N_UNIT: f64 = 1e9;

impl Law<9> for Farseer {
    fn name(&self) -> &'static str {
        "farseer"
    }

    fn equation(&self) -> &'static str {
        "L = exp(s*n^q + S) + exp(B*n^b + Q) * D^(-exp(A*n^a + E)), n = N/1e9"
    }

    fn needs(&self) -> &'static [Axis] {
        &[Axis::N, Axis::D]
    }

    fn positive(&self) -> bool {
        true
    }

    fn param_names(&self) -> [&'static str; 9] {
        ["E", "s", "q", "S", "B", "b", "Q", "A", "a"]
    }

    fn start_values(&self, _loss: &[f64]) -> [Vec<f64>; 9] {
        [
            vec![0.0, 2.0, 4.0],
            vec![-1.0, -0.3, 0.3],
            vec![0.05, 0.2, 0.5],
            vec![-1.0, -0.3, 0.3],
            vec![1.0, 5.0, 20.0],
            vec![-0.5, -0.2, -0.05],
            vec![-3.0, -1.0, 1.0],
            vec![-5.0, -2.0, 0.0],
            vec![0.02, 0.1, 0.3],
        ]
    }

    fn bounds(&self) -> [Option<(f64, f64)>; 9] {
        let mut b = [None; 9];
        b[2] = Some((0.0, 1.0));
        b[5] = Some((-1.0, 0.0));
        b[8] = Some((0.0, 1.0));
        b
    }

    fn predict(&self, t: &[f64; 9], x: &Point, g: &mut [f64; 9]) -> f64 {
        let [e, s, q, big_s, big_b, b, big_q, big_a, a] = *t;
        let n = x.n / N_UNIT;
        let (ln_n, ln_d) = (n.ln(), x.d.ln());
        let (nq, nb, na) = (n.powf(q), n.powf(b), n.powf(a));
        let t1 = (s * nq + big_s).exp();
        let k = (big_a * na + e).exp();
        let t2 = (big_b * nb + big_q - k * ln_d).exp();
        let dk = -t2 * ln_d * k;
        *g = [
            dk,
            t1 * nq,
            t1 * s * nq * ln_n,
            t1,
            t2 * nb,
            t2 * big_b * nb * ln_n,
            t2,
            dk * na,
            dk * big_a * na * ln_n,
        ];
        t1 + t2
    }

    fn natural(&self, t: &[f64; 9]) -> Vec<(&'static str, f64)> {
        self.param_names().into_iter().zip(*t).collect()
    }

    fn theta_from_natural(&self, p: &[f64; 9]) -> [f64; 9] {
        *p
    }
}
