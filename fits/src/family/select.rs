//! Choosing a family by its error where it will be used: each applicable family is fitted
//! without some runs and scored on them — the most expensive runs (leave-top-out: the
//! extrapolation a scaling law is for), or each budget group in turn (leave-one-budget-out)
//! — or each data subset in turn (leave-one-ladder-out) — and the lowest error is adopted. Scores on a held-out table use ScaleBench's R²
//! (arXiv 2604.22753, `benchmark/metrics.py`: 1 − SS_res/SS_tot on the loss, clipped to
//! [−1, 1]; the unclipped value is kept beside it).

use super::engine::{Family, Settings, Space};
use super::Point;
use serde::{Deserialize, Serialize};

/// Which runs each family is scored on before one is adopted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Holdout {
    /// The `share` of runs with the largest compute 6·(N + N_v)·D.
    TopCost {
        /// Share of the runs held out (at least one run).
        share: f64,
    },
    /// Each group (budget) in turn; `groups[i]` is run i's group.
    Groups {
        /// Group index of every run.
        groups: Vec<usize>,
    },
    /// Each data subset (a ladder of nested fractions) in turn; `groups[i]` is run i's.
    Subsets {
        /// Subset index of every run.
        groups: Vec<usize>,
    },
}

/// How well a law predicts some runs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Score {
    /// Runs scored.
    pub rows: usize,
    /// RMS residual in the fit's residual space.
    pub rms_residual: f64,
    /// R² of the loss (may be below −1).
    pub r2: f64,
    /// R² clipped to [−1, 1], as ScaleBench reports it.
    pub r2_clipped: f64,
    /// Mean |L̂ − L|/|L|.
    pub mean_abs_rel_error: f64,
}

/// Scores `theta` of `family` on `rows`.
pub fn score(
    family: &dyn Family,
    theta: &[f64],
    rows: &[Point],
    loss: &[f64],
    space: Space,
) -> Score {
    let pred: Vec<f64> = rows.iter().map(|x| family.predict(theta, x)).collect();
    score_predictions(&pred, loss, space)
}

/// Scores predictions `pred` of the losses `loss`.
pub fn score_predictions(pred: &[f64], loss: &[f64], space: Space) -> Score {
    let n = loss.len() as f64;
    let mean = loss.iter().sum::<f64>() / n;
    let ss_tot: f64 = loss.iter().map(|l| (l - mean).powi(2)).sum();
    let ss_res: f64 = pred.iter().zip(loss).map(|(p, l)| (p - l).powi(2)).sum();
    let r2 = if ss_tot > 1e-30 {
        1.0 - ss_res / ss_tot
    } else {
        f64::NAN
    };
    let sq: f64 = pred
        .iter()
        .zip(loss)
        .map(|(p, l)| space.residual(*p, *l).powi(2))
        .sum();
    let rel: f64 = pred
        .iter()
        .zip(loss)
        .map(|(p, l)| ((p - l) / l).abs())
        .sum();
    Score {
        rows: loss.len(),
        rms_residual: (sq / n).sqrt(),
        r2,
        r2_clipped: r2.clamp(-1.0, 1.0),
        mean_abs_rel_error: rel / n,
    }
}

/// One family's standing in the ranking.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ranked {
    /// Family name.
    pub law: String,
    /// Its error on the held-out runs (`None` when it was not fitted).
    pub holdout: Option<Score>,
    /// Why it was not fitted.
    pub refusal: Option<String>,
}

/// Every family scored on held-out runs, best first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ranking {
    /// How runs were held out.
    pub holdout: Holdout,
    /// Families, lowest held-out RMS residual first; refused ones last.
    pub ranked: Vec<Ranked>,
}

impl Ranking {
    /// The adopted family: the best scored one.
    pub fn adopted(&self) -> Option<&str> {
        self.ranked
            .iter()
            .find(|r| r.holdout.is_some())
            .map(|r| r.law.as_str())
    }
}

/// The (train, held) run indices of each fold.
fn folds(rows: &[Point], holdout: &Holdout) -> Vec<(Vec<usize>, Vec<usize>)> {
    match holdout {
        Holdout::TopCost { share } => {
            let mut order: Vec<usize> = (0..rows.len()).collect();
            order.sort_by(|&a, &b| rows[a].compute().total_cmp(&rows[b].compute()));
            let held = ((share * rows.len() as f64).ceil() as usize).clamp(1, rows.len() - 1);
            let (train, top) = order.split_at(rows.len() - held);
            vec![(train.to_vec(), top.to_vec())]
        }
        Holdout::Groups { groups } | Holdout::Subsets { groups } => {
            let k = groups.iter().max().map_or(0, |m| m + 1);
            (0..k)
                .map(|g| (0..rows.len()).partition(|&i| groups[i] != g))
                .filter(|(_, held): &(Vec<usize>, Vec<usize>)| !held.is_empty())
                .collect()
        }
    }
}

fn pick<T: Copy>(v: &[T], idx: &[usize]) -> Vec<T> {
    idx.iter().map(|&i| v[i]).collect()
}

/// Fits every family on each fold's training runs (no bootstrap) and scores it on the held
/// runs, pooled over folds.
pub fn rank(
    families: &[Box<dyn Family>],
    rows: &[Point],
    loss: &[f64],
    holdout: Holdout,
    s: &Settings,
) -> Ranking {
    let quick = Settings {
        bootstrap: 0,
        ..s.clone()
    };
    let space = Space::for_losses(loss);
    let folds = folds(rows, &holdout);
    let mut ranked: Vec<Ranked> = families
        .iter()
        .map(|f| {
            let (mut pred, mut held_loss) = (Vec::new(), Vec::new());
            for (train, held) in &folds {
                let (tr, tl) = (pick(rows, train), pick(loss, train));
                let fitted = match f.refusal(&tr, &tl) {
                    Some(why) => Err(why),
                    None => f.fit(&tr, &tl, None, &quick).map_err(|e| e.to_string()),
                };
                match fitted {
                    Ok(fit) => {
                        pred.extend(held.iter().map(|&i| f.predict(&fit.theta, &rows[i])));
                        held_loss.extend(held.iter().map(|&i| loss[i]));
                    }
                    Err(why) => {
                        return Ranked {
                            law: f.name().into(),
                            holdout: None,
                            refusal: Some(why),
                        };
                    }
                }
            }
            // One score pooled over folds: each held run predicted by its own fold's fit.
            let pooled = score_predictions(&pred, &held_loss, space);
            Ranked {
                law: f.name().into(),
                holdout: Some(pooled),
                refusal: None,
            }
        })
        .collect();
    ranked.sort_by(|a, b| match (&a.holdout, &b.holdout) {
        (Some(x), Some(y)) => x.rms_residual.total_cmp(&y.rms_residual),
        (Some(_), None) => std::cmp::Ordering::Less,
        (None, Some(_)) => std::cmp::Ordering::Greater,
        (None, None) => std::cmp::Ordering::Equal,
    });
    Ranking { holdout, ranked }
}
