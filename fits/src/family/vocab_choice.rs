//! Which vocabulary at a budget, answered two ways with each budget left out in turn, and
//! scored against that budget's own runs:
//! - the vocabulary law (Tao et al. 2024) fitted to the other budgets' runs: of the held-out
//!   budget's (N, N_v, D) designs, the vocabulary whose runs it predicts lowest;
//! - the per-vocabulary parabolas of approach 2: at each other budget the vocabulary whose
//!   parabola vertex in N is lowest, and a line of log V on log C through those.
//!
//! The truth is the held-out budget's vocabulary with the lowest vertex (its lowest run where
//! a vocabulary's runs have no interior vertex).

use super::engine::{Family, Settings};
use super::Point;
use crate::isoflop::parabola_minimum;
use crate::ols::Line;
use serde::{Deserialize, Serialize};

/// One budget left out: its best vocabulary and the two predictions of it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VocabLoboPoint {
    /// The budget left out (geometric mean of its runs' compute).
    pub budget: f64,
    /// The vocabulary with the lowest vertex among its own runs.
    pub truth: f64,
    /// The vocabulary the law fitted to the other budgets predicts lowest there.
    pub law: Option<f64>,
    /// V from the line through the other budgets' best vocabularies (continuous).
    pub parabola: Option<f64>,
    /// The table's vocabulary nearest that V in log.
    pub parabola_nearest: Option<f64>,
}

/// The vocabulary of `members` whose runs reach the lowest `loss`: each vocabulary's
/// parabola vertex in N, or its lowest run where the vertex is not interior.
fn best_vocab(rows: &[Point], loss: &[f64], vocab: &[f64], members: &[usize]) -> Option<f64> {
    let mut sizes: Vec<f64> = members.iter().map(|&i| vocab[i]).collect();
    sizes.sort_by(f64::total_cmp);
    sizes.dedup();
    sizes
        .into_iter()
        .filter_map(|v| {
            let of_v: Vec<usize> = members.iter().copied().filter(|&i| vocab[i] == v).collect();
            let n: Vec<f64> = of_v.iter().map(|&i| rows[i].n).collect();
            let l: Vec<f64> = of_v.iter().map(|&i| loss[i]).collect();
            let lowest = l.iter().copied().fold(f64::INFINITY, f64::min);
            let m = parabola_minimum(0.0, "N", None, &n, &l);
            let at = m.loss_opt.filter(|_| m.interior).unwrap_or(lowest);
            at.is_finite().then_some((at, v))
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, v)| v)
}

/// Each budget group left out in turn (`groups[i]`: run i's group; `vocab[i]`: its
/// vocabulary size); `family` is fitted with `s` to the other groups' runs.
pub fn vocab_lobo(
    family: &dyn Family,
    (rows, loss, vocab): (&[Point], &[f64], &[f64]),
    groups: &[usize],
    s: &Settings,
) -> Vec<VocabLoboPoint> {
    let k = groups.iter().max().map_or(0, |m| m + 1);
    let members: Vec<Vec<usize>> = (0..k)
        .map(|g| (0..rows.len()).filter(|&i| groups[i] == g).collect())
        .collect();
    let budget = |m: &[usize]| {
        (m.iter().map(|&i| rows[i].compute().ln()).sum::<f64>() / m.len() as f64).exp()
    };
    let best: Vec<Option<f64>> = members
        .iter()
        .map(|m| best_vocab(rows, loss, vocab, m))
        .collect();
    let mut sizes: Vec<f64> = vocab.to_vec();
    sizes.sort_by(f64::total_cmp);
    sizes.dedup();
    let nearest = |v: f64| {
        sizes
            .iter()
            .copied()
            .min_by(|a, b| (a / v).ln().abs().total_cmp(&(b / v).ln().abs()))
    };
    (0..k)
        .filter_map(|h| {
            let truth = best[h]?;
            let c = budget(&members[h]);
            let (lc, lv): (Vec<f64>, Vec<f64>) = (0..k)
                .filter(|&g| g != h)
                .filter_map(|g| best[g].map(|v| (budget(&members[g]).log10(), v.log10())))
                .unzip();
            let parabola = Line::fit(&lc, &lv).map(|l| 10f64.powf(l.at(c.log10())));
            let train: Vec<usize> = (0..rows.len()).filter(|&i| groups[i] != h).collect();
            let tr: Vec<Point> = train.iter().map(|&i| rows[i]).collect();
            let tl: Vec<f64> = train.iter().map(|&i| loss[i]).collect();
            let law = family.fit(&tr, &tl, None, s).ok().and_then(|f| {
                let pred: Vec<f64> = rows.iter().map(|x| family.predict(&f.theta, x)).collect();
                best_vocab(rows, &pred, vocab, &members[h])
            });
            Some(VocabLoboPoint {
                budget: c,
                truth,
                law,
                parabola,
                parabola_nearest: parabola.and_then(nearest),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A table made by the vocabulary law itself, where the best vocabulary moves from the
    /// smallest to the largest across five budgets: the law fitted without a budget names
    /// that budget's best vocabulary.
    #[test]
    fn the_law_names_each_budgets_best_vocabulary_on_an_exact_table() {
        let family = crate::family::family("vocab").unwrap();
        let theta = family.theta_from_natural(&[-2.0, 50.0, 0.3, 200.0, 0.5, 300.0, 0.3]);
        let (mut rows, mut vocab, mut groups) = (Vec::new(), Vec::new(), Vec::new());
        for (g, c) in [1e12, 1e13, 1e14, 1e15, 1e16].into_iter().enumerate() {
            for v in [256.0, 1024.0, 4096.0, 16384.0] {
                for i in 0..7 {
                    let n = 10f64.powf(4.0 + 0.5 * g as f64 + 0.3 * i as f64);
                    let nv = v * 64.0;
                    rows.push(Point {
                        n,
                        d: c / (6.0 * (n + nv)),
                        nv: Some(nv),
                        ..Point::default()
                    });
                    vocab.push(v);
                    groups.push(g);
                }
            }
        }
        let loss: Vec<f64> = rows.iter().map(|x| family.predict(&theta, x)).collect();
        let s = Settings {
            bootstrap: 0,
            starts: 16,
            ..Settings::default()
        };
        let points = vocab_lobo(family.as_ref(), (&rows, &loss, &vocab), &groups, &s);
        assert_eq!(points.len(), 5);
        let truths: Vec<f64> = points.iter().map(|p| p.truth).collect();
        assert!(
            truths.first() < truths.last(),
            "best V should grow: {truths:?}"
        );
        for p in &points {
            assert_eq!(p.law, Some(p.truth), "{p:?}");
        }
    }
}
