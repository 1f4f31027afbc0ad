//! `fit --law`: the named families (or every one the columns allow) fitted to a table,
//! ranked by held-out error, the best adopted, and optionally scored on a held-out table.

use super::design::{replay, Policy, Replay};
use super::engine::{Family, FamilyFit, Settings, Space};
use super::select::{rank, score, Holdout, Ranking, Score};
use super::vocab_choice::{vocab_lobo, VocabLoboPoint};
use super::vpnls::{lobo, LoboPoint};
use super::Axis;
use super::{family, registry, Point};
use crate::table::Table;
use crate::FitError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The columns a law fit reads.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LawColumns {
    /// Model parameters N.
    pub n: String,
    /// Training tokens D.
    pub d: String,
    /// The loss.
    pub loss: String,
    /// Unique tokens U (`None`: no data-constrained law unless `epochs` gives U = D/epochs).
    pub u: Option<String>,
    /// Epochs over the unique tokens, for U = D/epochs where no U column is named.
    pub epochs: Option<String>,
    /// Vocabulary parameters N_v (or the vocabulary size).
    pub nv: Option<String>,
    /// The vocabulary size, for the choice of vocabulary at a left-out budget.
    #[serde(default)]
    pub vocab: Option<String>,
    /// The synthetic share of the unique data, for the exchange-rate laws.
    #[serde(default)]
    pub synth_share: Option<String>,
}

/// A held-out table's scores.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TestScores {
    /// The table.
    pub path: PathBuf,
    /// (family, score) for every fitted family, the adopted one first.
    pub scores: Vec<(String, Score)>,
}

/// What `fit --law` writes to laws.json.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LawReport {
    /// The table fitted.
    pub table: PathBuf,
    /// Its columns.
    pub columns: LawColumns,
    /// Runs fitted.
    pub rows: usize,
    /// Residual space (log unless a loss is ≤ 0).
    pub space: Space,
    /// The fitter's settings.
    pub settings: Settings,
    /// The families scored on held-out runs.
    pub ranking: Ranking,
    /// The adopted family.
    pub adopted: String,
    /// Every scored family fitted to all runs, adopted first; bootstrap intervals for the
    /// adopted one (every one with `Settings::bootstrap_all`).
    pub fits: Vec<FamilyFit>,
    /// Scores on a held-out table, where one was given.
    pub test: Option<TestScores>,
    /// With budget groups: N_opt at each budget left out, by the parabola vertices of the
    /// others and by variable projection, beside its own vertex.
    pub n_opt_lobo: Option<Vec<LoboPoint>>,
    /// With budget groups and a vocabulary column: each vocabulary law's choice of vocabulary
    /// at each budget left out, beside the per-vocabulary parabolas' (law name, points).
    #[serde(default)]
    pub vocab_lobo: Vec<(String, Vec<VocabLoboPoint>)>,
}

/// Reads the runs of `table` on `cols`.
pub fn read_points(table: &Table, cols: &LawColumns) -> Result<(Vec<Point>, Vec<f64>), FitError> {
    let n = table.numbers(&cols.n, "--n-col")?;
    let d = table.numbers(&cols.d, "--d-col")?;
    let loss = table.numbers(&cols.loss, "--loss-col")?;
    let optional = |c: &Option<String>, flag: &str| -> Result<Option<Vec<f64>>, FitError> {
        c.as_deref()
            .filter(|c| table.has(c))
            .map(|c| table.numbers(c, flag))
            .transpose()
    };
    let u = match optional(&cols.u, "--u-col")? {
        Some(u) => Some(u),
        None => optional(&cols.epochs, "--epochs-col")?
            .map(|e| d.iter().zip(e).map(|(d, e)| d / e).collect()),
    };
    let nv = optional(&cols.nv, "--nv-col")?;
    let share = optional(&cols.synth_share, "--synth-share-col")?;
    let points = (0..n.len())
        .map(|i| Point {
            n: n[i],
            d: d[i],
            u: u.as_ref().map(|u| u[i]),
            nv: nv.as_ref().map(|v| v[i]),
            s: share.as_ref().map(|s| s[i]),
        })
        .collect();
    Ok((points, loss))
}

/// The families named (`all`: every one), or an error naming the unknown one.
pub fn families(names: &[String]) -> Result<Vec<Box<dyn Family>>, FitError> {
    if names.iter().any(|n| n == "all") {
        return Ok(registry());
    }
    names
        .iter()
        .map(|name| {
            family(name).ok_or_else(|| {
                let known = super::names().join(", ");
                FitError::Invalid(format!("--law {name:?}: the laws are {known} (or all)"))
            })
        })
        .collect()
}

/// Fits `families` to `table`, ranks them by `holdout`, adopts the best and scores every fit
/// on `test` (a table with the same columns) where given. `clusters[i]` is run i's block for
/// the bootstrap (`None`: runs are resampled one by one).
pub fn fit_laws(
    table: &Table,
    cols: &LawColumns,
    families: &[Box<dyn Family>],
    holdout: Holdout,
    clusters: Option<&[usize]>,
    test: Option<&Path>,
    s: &Settings,
) -> Result<LawReport, FitError> {
    let (rows, loss) = read_points(table, cols)?;
    let n_opt_lobo = match &holdout {
        Holdout::Groups { groups } => Some(lobo(&rows, &loss, groups)),
        Holdout::TopCost { .. } | Holdout::Subsets { .. } => None,
    };
    let ranking = rank(families, &rows, &loss, holdout, s);
    let adopted = ranking
        .adopted()
        .map(str::to_string)
        .ok_or_else(|| FitError::TooFew {
            path: table.path().to_path_buf(),
            fit: "any law".into(),
            message: ranking
                .ranked
                .iter()
                .map(|r| format!("{}: {}", r.law, r.refusal.as_deref().unwrap_or("?")))
                .collect::<Vec<_>>()
                .join("; "),
        })?;
    let fits: Vec<FamilyFit> = ranking
        .ranked
        .iter()
        .filter(|r| r.holdout.is_some())
        .map(|r| {
            let f = families
                .iter()
                .find(|f| f.name() == r.law)
                .expect("ranked family");
            let boot = s.bootstrap_all || r.law == adopted;
            f.fit(
                &rows,
                &loss,
                clusters,
                &Settings {
                    bootstrap: if boot { s.bootstrap } else { 0 },
                    ..s.clone()
                },
            )
        })
        .collect::<Result<_, _>>()?;
    let test = test
        .map(|path| test_scores(path, cols, families, &fits))
        .transpose()?;
    let vocab_lobo = vocab_choices(table, cols, families, (&rows, &loss), &ranking, s)?;
    Ok(LawReport {
        table: table.path().to_path_buf(),
        columns: cols.clone(),
        rows: rows.len(),
        space: Space::for_losses(&loss),
        settings: s.clone(),
        ranking,
        adopted,
        fits,
        test,
        n_opt_lobo,
        vocab_lobo,
    })
}

/// With budget groups and a vocabulary column, every fitted family with a vocabulary axis
/// chooses the vocabulary at each budget left out.
fn vocab_choices(
    table: &Table,
    cols: &LawColumns,
    families: &[Box<dyn Family>],
    (rows, loss): (&[Point], &[f64]),
    ranking: &Ranking,
    s: &Settings,
) -> Result<Vec<(String, Vec<VocabLoboPoint>)>, FitError> {
    let (Holdout::Groups { groups }, Some(col)) = (&ranking.holdout, &cols.vocab) else {
        return Ok(Vec::new());
    };
    if !table.has(col) {
        return Ok(Vec::new());
    }
    let vocab = table.numbers(col, "--v-col")?;
    if vocab.iter().all(|&v| v == vocab[0]) {
        return Ok(Vec::new());
    }
    let quick = Settings {
        bootstrap: 0,
        ..s.clone()
    };
    Ok(families
        .iter()
        .filter(|f| f.needs().contains(&Axis::Nv))
        .filter(|f| {
            ranking
                .ranked
                .iter()
                .any(|r| r.law == f.name() && r.holdout.is_some())
        })
        .map(|f| {
            let points = vocab_lobo(f.as_ref(), (rows, loss, &vocab), groups, &quick);
            (f.name().to_string(), points)
        })
        .collect())
}

/// Every fit scored on the held-out table at `path`.
fn test_scores(
    path: &Path,
    cols: &LawColumns,
    families: &[Box<dyn Family>],
    fits: &[FamilyFit],
) -> Result<TestScores, FitError> {
    let (rows, loss) = read_points(&Table::read(path)?, cols)?;
    let scores = fits
        .iter()
        .map(|fit| {
            let f = families
                .iter()
                .find(|f| f.name() == fit.law)
                .expect("fitted family");
            let sc = score(f.as_ref(), &fit.theta, &rows, &loss, fit.space);
            (fit.law.clone(), sc)
        })
        .collect();
    Ok(TestScores {
        path: path.to_path_buf(),
        scores,
    })
}

impl LawReport {
    /// The ranking, the adopted law's parameters and the held-out table's scores, as text.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        self.ranking_lines(&mut s);
        if let Some(fit) = self.fits.first() {
            fit_lines(fit, &mut s);
        }
        if let Some(points) = &self.n_opt_lobo {
            n_opt_lobo_lines(points, &mut s);
        }
        for (law, points) in &self.vocab_lobo {
            vocab_lobo_lines(law, points, &mut s);
        }
        if let Some(t) = &self.test {
            test_lines(t, &mut s);
        }
        s
    }

    /// How the families were held out, and each one's error or why it was not fitted.
    fn ranking_lines(&self, s: &mut String) {
        use crate::report::sig;
        use std::fmt::Write;
        let held = match &self.ranking.holdout {
            Holdout::TopCost { share } => {
                format!("the {:.0}% most expensive runs held out", 100.0 * share)
            }
            Holdout::Groups { groups } => format!(
                "each of {} budget groups held out in turn",
                groups.iter().max().map_or(0, |m| m + 1)
            ),
            Holdout::Subsets { groups } => format!(
                "each of {} data subsets held out in turn",
                groups.iter().max().map_or(0, |m| m + 1)
            ),
        };
        let space = match self.space {
            Space::Log => "log",
            Space::Loss => "loss",
        };
        let _ = writeln!(
            s,
            "{} runs; laws ranked by RMS {space} residual, {held}:",
            self.rows
        );
        for r in &self.ranking.ranked {
            let _ = match (&r.holdout, &r.refusal) {
                (Some(h), _) => writeln!(
                    s,
                    "  {:<17} held-out RMS {}  R² {:.3}  mean |rel. error| {:.2}%{}",
                    r.law,
                    sig(h.rms_residual),
                    h.r2,
                    100.0 * h.mean_abs_rel_error,
                    if r.law == self.adopted {
                        "  ← adopted"
                    } else {
                        ""
                    }
                ),
                (None, why) => writeln!(
                    s,
                    "  {:<17} not fitted: {}",
                    r.law,
                    why.as_deref().unwrap_or("?")
                ),
            };
        }
    }
}

/// A fit's equation, convergence and natural parameters with their intervals.
fn fit_lines(fit: &FamilyFit, s: &mut String) {
    use crate::report::sig;
    use std::fmt::Write;
    let _ = writeln!(
        s,
        "{}: {} ({} runs, {} of {} starts at the optimum, {} of {} bootstrap refits{})",
        fit.law,
        fit.equation,
        fit.rows,
        fit.at_optimum,
        fit.starts,
        fit.bootstrap_converged,
        fit.bootstrap_resamples,
        fit.bootstrap_clusters
            .map(|k| format!(" resampling {k} blocks"))
            .unwrap_or_default()
    );
    for p in &fit.natural {
        let ci = match (p.ci_low, p.ci_high) {
            (Some(lo), Some(hi)) => format!(" [{}, {}]", sig(lo), sig(hi)),
            _ => String::new(),
        };
        let _ = writeln!(s, "  {:<8} {}{ci}", p.name, sig(p.value));
    }
}

/// Every fit's score on the held-out table.
fn test_lines(t: &TestScores, s: &mut String) {
    use std::fmt::Write;
    let rows = t.scores.first().map_or(0, |x| x.1.rows);
    let _ = writeln!(s, "held-out table {} ({rows} runs):", t.path.display());
    for (law, sc) in &t.scores {
        let _ = writeln!(
            s,
            "  {law:<17} R² {:.4} (clipped {:.4})  mean |rel. error| {:.2}%",
            sc.r2,
            sc.r2_clipped,
            100.0 * sc.mean_abs_rel_error
        );
    }
}

/// The leave-one-budget-out N_opt errors of both approaches, a line each and their means.
fn n_opt_lobo_lines(points: &[LoboPoint], s: &mut String) {
    use crate::report::sig;
    use std::fmt::Write;
    let _ = writeln!(
        s,
        "N_opt with each budget left out (log10 error against its own vertex, decades):"
    );
    let (mut par, mut vp, mut covered) = (Vec::new(), Vec::new(), [0, 0]);
    for p in points {
        let err = |x: Option<f64>| x.map(|x| x - p.vertex);
        let text = |e: Option<f64>| e.map_or("—".into(), |e| format!("{e:+.3}"));
        let (ep, ev) = (err(p.parabola), err(p.vpnls));
        par.extend(ep);
        vp.extend(ev);
        let interval = p.vpnls_interval.map_or(String::new(), |[lo, hi]| {
            covered[0] += usize::from(lo <= p.vertex && p.vertex <= hi);
            covered[1] += 1;
            format!(" [{:+.3}, {:+.3}]", lo - p.vertex, hi - p.vertex)
        });
        let _ = writeln!(
            s,
            "  C {:<10} vertex {:<10} parabola vertices {:<7} VPNLS {}{interval}",
            sig(p.budget),
            sig(10f64.powf(p.vertex)),
            text(ep),
            text(ev)
        );
    }
    let mean_abs = |v: &[f64]| v.iter().map(|e| e.abs()).sum::<f64>() / v.len().max(1) as f64;
    let _ = writeln!(
        s,
        "  mean |error|: parabola vertices {:.3} ({} budgets), VPNLS {:.3} ({} budgets)",
        mean_abs(&par),
        par.len(),
        mean_abs(&vp),
        vp.len()
    );
    let _ = writeln!(
        s,
        "  the budget's own vertex inside VPNLS's 95% interval (other budgets resampled whole): {}/{}",
        covered[0], covered[1]
    );
}

/// The vocabulary each way picks at each budget left out, its hits and mean |log2 error|.
fn vocab_lobo_lines(law: &str, points: &[VocabLoboPoint], s: &mut String) {
    use crate::report::sig;
    use std::fmt::Write;
    let _ = writeln!(
        s,
        "Vocabulary with each budget left out: {law} law against the per-vocabulary parabolas (V picked; the budget's own best):"
    );
    let show = |v: Option<f64>| v.map_or("—".into(), |v| format!("{v:.0}"));
    let log2_err = |v: Option<f64>, t: f64| v.map(|v| (v / t).log2().abs());
    let (mut law_err, mut par_err, mut hits) = (Vec::new(), Vec::new(), [0, 0]);
    for p in points {
        law_err.extend(log2_err(p.law, p.truth));
        par_err.extend(log2_err(p.parabola, p.truth));
        hits[0] += usize::from(p.law == Some(p.truth));
        hits[1] += usize::from(p.parabola_nearest == Some(p.truth));
        let _ = writeln!(
            s,
            "  C {:<10} best V {:<6} law {:<6} parabolas {:<6} (nearest {})",
            sig(p.budget),
            show(Some(p.truth)),
            show(p.law),
            show(p.parabola),
            show(p.parabola_nearest)
        );
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let _ = writeln!(
        s,
        "  right vocabulary: law {}/{n}, parabolas {}/{n}; mean |log2 error|: law {:.2}, parabolas {:.2}",
        hits[0],
        hits[1],
        mean(&law_err),
        mean(&par_err),
        n = points.len()
    );
}

/// Replays of [`super::design::replay`] at every cap and seed, with the pool's losses read from
/// `table` and the target region from `test`.
pub fn replays(
    table: &Table,
    test: &Path,
    cols: &LawColumns,
    family: &dyn Family,
    caps: &[f64],
    seeds: u64,
    s: &Settings,
) -> Result<Vec<Replay>, FitError> {
    use rayon::prelude::*;
    let (pool, loss) = read_points(table, cols)?;
    let (t_rows, t_loss) = read_points(&Table::read(test)?, cols)?;
    let cost: Vec<f64> = pool.iter().map(Point::compute).collect();
    let quick = Settings {
        bootstrap: 0,
        starts: 16,
        ..s.clone()
    };
    let jobs: Vec<(Policy, f64, u64)> = [Policy::VOptimal, Policy::Random]
        .into_iter()
        .flat_map(|p| {
            caps.iter()
                .flat_map(move |&c| (0..seeds).map(move |k| (p, c, k)))
        })
        .collect();
    Ok(jobs
        .par_iter()
        .map(|&job| replay(family, &pool, &loss, &cost, (&t_rows, &t_loss), job, &quick))
        .collect())
}

/// Mean ± SD of the target R² (clipped) per policy and cap, a line each.
pub fn replay_summary(family: &str, replays: &[Replay]) -> String {
    use std::fmt::Write;
    let mut caps: Vec<f64> = replays.iter().map(|r| r.cap).collect();
    caps.sort_by(f64::total_cmp);
    caps.dedup();
    let mut s = format!(
        "{family}: replays, target-region R² (clipped; a failed fit counts −1) over seeds:\n"
    );
    for (policy, name) in [(Policy::VOptimal, "V-optimal"), (Policy::Random, "random")] {
        for &cap in &caps {
            let these: Vec<&Replay> = replays
                .iter()
                .filter(|r| r.cap == cap && r.policy == policy)
                .collect();
            let r2: Vec<f64> = these
                .iter()
                .map(|r| r.target.map_or(-1.0, |t| t.r2_clipped))
                .collect();
            let n = r2.len() as f64;
            let mean = r2.iter().sum::<f64>() / n;
            let sd =
                (r2.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
            let runs = these.iter().map(|r| r.chosen.len()).sum::<usize>() as f64 / n;
            let _ = writeln!(
                s,
                "  {name:<9} cap {:>5.1}%: R² {mean:.3} ± {sd:.3} ({} seeds, {runs:.0} runs bought on average)",
                100.0 * cap,
                r2.len()
            );
        }
    }
    s
}
