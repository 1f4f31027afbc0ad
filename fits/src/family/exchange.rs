//! The data-constrained law (Muennighoff et al. 2023; `data_constrained`) on a pool of two
//! sources: captured motion and a synthetic share s of the unique data, whose tokens are worth
//! ρ captured ones, k = 1 − s + ρ·s. Two readings of "worth" (scaling-laws.md, "Exchange
//! rate"), as `fit --repeated-data --exchange-form` fits them:
//! - token worth: U and D both scale by k, so the repetitions R = D/U − 1 are unchanged;
//! - effective pool: repetitions count against U·k = U_real + ρ·U_synth, the tokens seen in
//!   full, R = D/(U·k) − 1.
//!
//! θ = (a, b, e, α, β, r, ln ρ): the data-constrained law's six, then ln ρ.

use super::chinchilla::epoch_starts;
use super::data_constrained::DataConstrained;
use super::{Axis, Law, Point};
use crate::fitted::{exchange_factor, ExchangeForm};

/// The data-constrained law on a mixed pool, in one of the two exchange forms.
pub struct Exchange(pub ExchangeForm);

impl Law<7> for Exchange {
    fn name(&self) -> &'static str {
        match self.0 {
            ExchangeForm::TokenWorth => "data-constrained-token-worth",
            ExchangeForm::EffectivePool => "data-constrained-effective-pool",
        }
    }

    fn equation(&self) -> &'static str {
        match self.0 {
            ExchangeForm::TokenWorth => "data-constrained at k*U and k*D, k = 1 - s + rho*s",
            ExchangeForm::EffectivePool => {
                "data-constrained with U_D = min(k*U, D), k = 1 - s + rho*s"
            }
        }
    }

    fn needs(&self) -> &'static [Axis] {
        &[Axis::N, Axis::D, Axis::U, Axis::S]
    }

    fn positive(&self) -> bool {
        true
    }

    fn param_names(&self) -> [&'static str; 7] {
        ["a", "b", "e", "alpha", "beta", "r", "ln_rho"]
    }

    fn start_values(&self, _loss: &[f64]) -> [Vec<f64>; 7] {
        let [a, b, e, alpha, beta] = epoch_starts();
        let rho = vec![0.25f64.ln(), 0.0, 2f64.ln()];
        [a, b, e, alpha, beta, vec![0.0, 1.5, 3.0, 4.5], rho]
    }

    fn predict(&self, t: &[f64; 7], x: &Point, g: &mut [f64; 7]) -> f64 {
        let core = [t[0], t[1], t[2], t[3], t[4], t[5]];
        let (k, dk) = exchange_factor(x.s.unwrap_or(0.0), t[6].exp());
        let (u, d) = (x.u.unwrap_or(x.d), x.d);
        let mut g6 = [0.0; 6];
        let (loss, dl_dk) = match self.0 {
            // U and D, hence D', scale by k: ∂L/∂ln k = ∂L/∂ln D' = −β·B·D'^−β = −β·g6[1].
            ExchangeForm::TokenWorth => {
                let at = Point {
                    u: Some(k * u),
                    d: k * d,
                    ..*x
                };
                let loss = DataConstrained.predict(&core, &at, &mut g6);
                (loss, -t[4] * g6[1])
            }
            // Only the pool U·k moves: ∂L/∂ln k = ∂L/∂ln U.
            ExchangeForm::EffectivePool => {
                let at = Point {
                    u: Some(k * u),
                    ..*x
                };
                DataConstrained.predict_with_pool_slope(&core, &at, &mut g6)
            }
        };
        g[..6].copy_from_slice(&g6);
        g[6] = dl_dk * dk;
        loss
    }

    fn natural(&self, t: &[f64; 7]) -> Vec<(&'static str, f64)> {
        let mut p = DataConstrained.natural(&[t[0], t[1], t[2], t[3], t[4], t[5]]);
        p.push(("rho", t[6].exp()));
        p
    }

    fn theta_from_natural(&self, p: &[f64; 7]) -> [f64; 7] {
        let t = DataConstrained.theta_from_natural(&[p[0], p[1], p[2], p[3], p[4], p[5]]);
        [t[0], t[1], t[2], t[3], t[4], t[5], p[6].ln()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Without synthetic data both forms are the data-constrained law; with a synthetic half
    /// worth less than captured data, a short run (no repetition) is hurt only under token
    /// worth, and a long one under both.
    #[test]
    fn the_forms_agree_on_captured_data_and_differ_on_a_short_mixed_run() {
        let inner = [5.0, 6.0, 0.5, 0.34, 0.28, 2.0];
        let t = [5.0, 6.0, 0.5, 0.34, 0.28, 2.0, 0.3f64.ln()];
        let at = |d: f64, s: f64| Point {
            n: 1e8,
            d,
            u: Some(1e10),
            s: Some(s),
            ..Point::default()
        };
        let mut g = [0.0; 7];
        let plain = DataConstrained.predict(&inner, &at(1e9, 0.0), &mut [0.0; 6]);
        let (worth, pool) = (
            Exchange(ExchangeForm::TokenWorth),
            Exchange(ExchangeForm::EffectivePool),
        );
        for law in [&worth, &pool] {
            let l = law.predict(&t, &at(1e9, 0.0), &mut g);
            assert!((l - plain).abs() < 1e-12, "{}: {l} vs {plain}", law.name());
        }
        let short_worth = worth.predict(&t, &at(1e9, 0.5), &mut g);
        let short_pool = pool.predict(&t, &at(1e9, 0.5), &mut g);
        assert!(short_worth > plain + 1e-3, "{short_worth} vs {plain}");
        assert!(
            (short_pool - plain).abs() < 1e-12,
            "{short_pool} vs {plain}"
        );
        let long = |law: &Exchange, s: f64| law.predict(&t, &at(1e12, s), &mut [0.0; 7]);
        for law in [&worth, &pool] {
            assert!(long(law, 0.5) > long(law, 0.0) + 1e-3, "{}", law.name());
        }
    }

    /// A table made under the effective pool with ρ = 0.35 (three pools, each captured only
    /// and a third synthetic, 0.2% seeded noise): ranked by each data subset held out, the
    /// effective pool is adopted and recovers ρ within 10%; one share for every run is refused.
    #[test]
    fn the_effective_pool_is_adopted_on_a_table_it_made() {
        use crate::family::engine::{Family, Settings};
        use crate::family::select::{rank, Holdout};
        let truth = [1.9, 300.0, 2000.0, 0.33, 0.35, 15.4, 0.35];
        let pool = Exchange(ExchangeForm::EffectivePool);
        let theta = pool.theta_from_natural(&truth);
        let mut rng = motionscale_core::rng::SplitMix64(3);
        let (mut rows, mut loss, mut groups) = (Vec::new(), Vec::new(), Vec::new());
        for (g, (u, s)) in [1e8, 1e9, 1e10]
            .iter()
            .flat_map(|&u| [(u, 0.0), (u, 1.0 / 3.0)])
            .enumerate()
        {
            for i in 0..5 {
                for j in 0..6 {
                    let x = Point {
                        n: 10f64.powf(7.0 + 0.5 * i as f64),
                        d: 10f64.powf(8.5 + 0.5 * j as f64),
                        u: Some(u),
                        s: Some(s),
                        ..Point::default()
                    };
                    let l = pool.predict(&theta, &x, &mut [0.0; 7]);
                    loss.push(l * (1.0 + 2e-3 * rng.range(-1.0, 1.0)));
                    rows.push(x);
                    groups.push(g);
                }
            }
        }
        let families: Vec<Box<dyn Family>> = ["data-constrained-token-worth", pool.name()]
            .iter()
            .map(|n| crate::family::family(n).unwrap())
            .collect();
        let s = Settings {
            bootstrap: 0,
            ..Settings::default()
        };
        let ranking = rank(&families, &rows, &loss, Holdout::Subsets { groups }, &s);
        assert_eq!(ranking.adopted(), Some(pool.name()), "{ranking:?}");
        let fit = families[1].fit(&rows, &loss, None, &s).unwrap();
        let rho = fit.natural.iter().find(|p| p.name == "rho").unwrap().value;
        assert!((rho - 0.35).abs() < 0.035, "rho {rho}");
        let one_share: Vec<Point> = rows.iter().map(|x| Point { s: Some(0.3), ..*x }).collect();
        let refused = families[1].fit(&one_share, &loss, None, &s).unwrap_err();
        assert!(
            refused.to_string().contains("rho is not identified"),
            "{refused}"
        );
    }
}
