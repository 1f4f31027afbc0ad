//! `sweep plan --next`: the runs a live study trains next. The fit named by `--fits` decides
//! how they are chosen: an IsoFLOP fit (`fits.json`) narrows N_opt or the loss at C* by the
//! planner's bootstrap (`fits::planner`), or the value of an hour by the data-constrained
//! fit's Laplace posterior (`fits::hour_design`); a law family's fit (`laws.json`) buys the
//! greedy V-optimal runs for its loss at C* (`fits::family::design`). The caller prints.

use crate::error::SweepError;
use crate::plan::{IsoFlopPlan, PlanPoint};
use fits::data_value::{predict_data, Hours};
use fits::family::design;
use fits::family::run::{read_points, LawReport};
use fits::family::Point;
use fits::fit_file::FitFile;
use fits::hour_design::{self, DataCandidate};
use fits::loss_shape::Form;
use fits::planner::{self, budget_groups, Candidate, Goal, Observation, Settings, Target};
use fits::replay;
use fits::{Fits, Table};
use std::path::{Path, PathBuf};

/// What `--next` is asked.
#[derive(Debug, Clone)]
pub struct Request<'a> {
    /// The fit that chooses (`fits.json` or `laws.json`).
    pub fits: &'a Path,
    /// What an IsoFLOP fit narrows.
    pub goal: Goal,
    /// C*, above every trained budget.
    pub target_budget: f64,
    /// Runs (or proposals) wanted.
    pub k: usize,
    /// The most FLOPs the proposals may cost together.
    pub max_compute: f64,
    /// The trained runs' table (default: the one the fit read).
    pub results: Option<&'a Path>,
    /// With `hour_value`: the corpus's hours (default: the plan's full-data subset).
    pub hours: Option<Hours>,
}

/// Runs proposed together, what they cost and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Proposal {
    /// Their run ids.
    pub runs: Vec<String>,
    /// FLOPs.
    pub cost: f64,
    /// What they buy.
    pub why: String,
}

/// The planner's view now and its proposals, best first.
#[derive(Debug, Clone, PartialEq)]
pub struct NextRuns {
    /// One line on the target now (trained runs, its interval, the candidates).
    pub state: String,
    /// The proposals.
    pub proposals: Vec<Proposal>,
}

/// The budgets listed for an error message.
pub fn listed(budgets: &[f64]) -> String {
    let list: Vec<String> = budgets.iter().map(|b| format!("{b:.3e}")).collect();
    list.join(", ")
}

/// Reads the fit and checks, before any plan is read, that it has what `goal` narrows.
pub fn read_fit(path: &Path, goal: Goal) -> Result<FitFile, SweepError> {
    let file = FitFile::read(path)?;
    let FitFile::IsoFlop(fits) = &file else {
        return Ok(file);
    };
    let (has, law) = match goal {
        Goal::IsoFlop(Target::NOpt) => (
            fits.power_laws.contains_key("n_opt_vs_c"),
            "N_opt ∝ C^b law (n_opt_vs_c)",
        ),
        Goal::IsoFlop(Target::Loss) => (fits.log_law.is_some(), "law of the loss at N_opt"),
        Goal::HourValue => (
            fits.repeated_data.is_some(),
            "data-constrained fit (`fit --repeated-data`)",
        ),
    };
    if !has {
        let message = format!(
            "no {law} to narrow for --target {} (skipped: {})",
            goal.name(),
            fits.skipped.join("; ")
        );
        return Err(SweepError::invalid(path, message));
    }
    Ok(file)
}

/// The proposals for `req` from the `grid` (every point the study could run) that the plan
/// trained so far, `base`, does not have.
pub fn next_runs(
    req: &Request,
    fit: &FitFile,
    grid: &IsoFlopPlan,
    base: &IsoFlopPlan,
) -> Result<NextRuns, SweepError> {
    let out = match (fit, req.goal) {
        (FitFile::Families(report), _) => by_design(req, report, grid, base)?,
        (FitFile::IsoFlop(fits), Goal::IsoFlop(t)) => isoflop(req, fits, grid, base, t)?,
        (FitFile::IsoFlop(fits), Goal::HourValue) => hours(req, fits, grid, base)?,
    };
    if out.proposals.is_empty() {
        return Err(SweepError::Argument(
            "no candidate fits --max-compute, is predictable from the trained runs, or is expected to narrow the interval".into(),
        ));
    }
    Ok(out)
}

/// The trained runs of `base` on the grid's data subset, as the planner sees them; the error
/// says why they cannot support a law at C*.
fn trained_runs(
    req: &Request,
    fit: &Fits,
    base: &IsoFlopPlan,
    subset: Option<&String>,
) -> Result<Vec<Observation>, SweepError> {
    let results = req
        .results
        .map_or_else(|| PathBuf::from(&fit.input.file), Path::to_path_buf);
    let loss_col = fit
        .input
        .columns
        .get("loss")
        .cloned()
        .flatten()
        .unwrap_or_else(|| "norm_test_loss".into());
    let (rows, losses) = replay::read_runs(&Table::read(&results)?, &loss_col)?;
    let obs: Vec<Observation> = (0..rows.len())
        .filter(|&i| {
            base.points
                .iter()
                .any(|p| p.run_id == rows[i].id && p.data.as_ref() == subset)
        })
        .map(|i| planner::observed(&rows[i], losses[i]))
        .collect();
    let trained = budget_groups(&obs.iter().map(|o| o.budget).collect::<Vec<_>>());
    if trained.len() < 3 {
        let message = format!(
            "{} budget(s) trained in the plan's subset ({}); the planner needs three for a law",
            trained.len(),
            listed(&trained)
        );
        return Err(SweepError::invalid(&results, message));
    }
    let c_star = req.target_budget;
    if c_star.log10() <= trained[trained.len() - 1].log10() + planner::GROUP_TOL_DEX {
        return Err(SweepError::Argument(format!(
            "--target-budget {c_star:.3e} is not above the budgets trained ({})",
            listed(&trained)
        )));
    }
    Ok(obs)
}

/// The grid's runnable points below C* that `base` does not have.
fn open_points<'a>(
    grid: &'a IsoFlopPlan,
    base: &'a IsoFlopPlan,
    c_star: f64,
) -> impl Iterator<Item = &'a PlanPoint> {
    grid.points.iter().filter(move |p| {
        p.runnable() && p.budget < c_star && !base.points.iter().any(|b| b.run_id == p.run_id)
    })
}

/// The grid's runnable points below C* that `base` does not have, as candidates.
fn candidates(grid: &IsoFlopPlan, base: &IsoFlopPlan, c_star: f64) -> Vec<Candidate> {
    open_points(grid, base, c_star)
        .map(|p| Candidate {
            id: p.run_id.clone(),
            budget: p.budget,
            n: p.n_nv as f64,
            vocab: grid.vocabulary(p.codebook).map(|v| v.codebook_size as f64),
            cost: p.budget,
        })
        .collect()
}

/// The planner's proposals as run ids.
fn with_ids(proposals: Vec<planner::Proposal>, ids: &[&str]) -> Vec<Proposal> {
    proposals
        .into_iter()
        .map(|p| Proposal {
            runs: p.runs.iter().map(|&j| ids[j].to_string()).collect(),
            cost: p.cost,
            why: p.why,
        })
        .collect()
}

/// N_opt or the loss at N_opt: the IsoFLOP bootstrap (`fits::planner`).
fn isoflop(
    req: &Request,
    fit: &Fits,
    grid: &IsoFlopPlan,
    base: &IsoFlopPlan,
    target: Target,
) -> Result<NextRuns, SweepError> {
    // The study's subset: the data of the grid's points (trained rows of other subsets differ).
    let subset = grid.points.first().and_then(|p| p.data.clone());
    let obs = trained_runs(req, fit, base, subset.as_ref())?;
    let c_star = req.target_budget;
    let pool = candidates(grid, base, c_star);
    // The loss extrapolates by the form `fit` chose for it (leave-one-budget-out error).
    let loss_form = fit
        .loss_shape
        .as_ref()
        .and_then(|shape| shape.chosen.as_deref())
        .and_then(Form::parse)
        .unwrap_or_default();
    let settings = Settings {
        loss_form,
        ..Settings::default()
    };
    let now = planner::posterior(&obs, target, c_star, &settings);
    let state = format!(
        "planner: {} trained runs of the plan; {}{} at {c_star:.3e} now: median {:.4}, 95% [{:.4}, {:.4}], width {:.4} {}, {} of {} draws with a law, spread {:.3} ({} candidates)",
        obs.len(), target.name(), target.by_law(loss_form), now.median, now.low, now.high, now.width, target.unit(), now.valid, now.draws, now.spread(), pool.len()
    );
    let proposals = planner::propose(
        &obs,
        &pool,
        target,
        c_star,
        req.k,
        req.max_compute,
        &settings,
    );
    let ids: Vec<&str> = pool.iter().map(|c| c.id.as_str()).collect();
    Ok(NextRuns {
        state,
        proposals: with_ids(proposals, &ids),
    })
}

/// `hour_value`: the data-constrained fit's Laplace posterior (`fits::hour_design`) over the
/// grid's points of every data subset.
fn hours(
    req: &Request,
    fit: &Fits,
    grid: &IsoFlopPlan,
    base: &IsoFlopPlan,
) -> Result<NextRuns, SweepError> {
    let rd = fit.repeated_data.as_ref().ok_or_else(|| {
        SweepError::invalid(req.fits, "no data-constrained fit (`fit --repeated-data`)")
    })?;
    let n_col = fit.input.columns.get("N").cloned().flatten();
    if n_col.as_deref() != Some("n_nv") {
        let message = format!(
            "the fit's N column is {n_col:?}; --target hour_value reads the plan's N as n_nv"
        );
        return Err(SweepError::invalid(req.fits, message));
    }
    let hours = match req.hours {
        Some(h) => h,
        None => corpus_hours(grid).ok_or_else(|| {
            SweepError::Argument(
                "--target hour_value: the plan has no full-data subset; pass --hours real=H,synth=H".into(),
            )
        })?,
    };
    let c_star = req.target_budget;
    let pool = data_candidates(grid, base, c_star);
    if pool.is_empty() {
        return Err(SweepError::Argument(format!(
            "--target hour_value: no point of the grid below {c_star:.3e} has a data subset (plan with --data-fractions)"
        )));
    }
    let (now, proposals) =
        hour_design::propose_hours(rd, &pool, c_star, hours, req.k, req.max_compute)
            .map_err(SweepError::Argument)?;
    let refits = predict_data(rd, c_star, hours).map_err(SweepError::Argument)?;
    let by_refits = &refits.hour_values[0].loss_change;
    let state = format!(
        "planner: +1 h of captured motion at {c_star:.3e} with {:.2} h captured, {:.2} h synthetic: {:.4e} nats, Laplace 95% [{:.4e}, {:.4e}], width {:.3e} (the fit's refits: [{:.4e}, {:.4e}]); {} candidates",
        hours.real, hours.synth, now.value, now.low, now.high, now.width,
        by_refits.ci_low.unwrap_or(f64::NAN), by_refits.ci_high.unwrap_or(f64::NAN), pool.len()
    );
    let ids: Vec<&str> = pool.iter().map(|c| c.id.as_str()).collect();
    Ok(NextRuns {
        state,
        proposals: with_ids(proposals, &ids),
    })
}

/// The hours per source of the plan's full data (`all` at fraction 1).
fn corpus_hours(grid: &IsoFlopPlan) -> Option<Hours> {
    grid.data
        .iter()
        .filter(|d| d.fraction == 1.0)
        .max_by(|a, b| a.hours.total_cmp(&b.hours))
        .map(|d| Hours {
            real: d.hours - d.synth_hours,
            synth: d.synth_hours,
        })
}

/// The grid's runnable points below C* with a data subset that `base` does not have.
fn data_candidates(grid: &IsoFlopPlan, base: &IsoFlopPlan, c_star: f64) -> Vec<DataCandidate> {
    open_points(grid, base, c_star)
        .filter_map(|p| {
            let subset = grid
                .data
                .iter()
                .find(|d| Some(&d.name) == p.data.as_ref())?;
            Some(DataCandidate {
                id: p.run_id.clone(),
                budget: p.budget,
                n: p.n_nv as f64,
                d: p.tokens as f64,
                u: p.unique_tokens? as f64,
                synth: subset.synth_hours / subset.hours,
                cost: p.budget,
            })
        })
        .collect()
}

/// A plan point as a law family reads it: N = N_nv, D its tokens, N_v, U (its data
/// subset's unique tokens, else its vocabulary's train tokens) and its data subset's
/// synthetic share, where it has a subset.
fn as_point(grid: &IsoFlopPlan, p: &PlanPoint, d: f64) -> Point {
    let u = p
        .unique_tokens
        .or_else(|| grid.vocabulary(p.codebook).map(|v| v.train_tokens))
        .map(|u| u as f64);
    let subset = grid.data.iter().find(|s| Some(&s.name) == p.data.as_ref());
    Point {
        n: p.n_nv as f64,
        d,
        u,
        nv: Some(p.n_v as f64),
        s: subset.map(|s| s.synth_hours / s.hours),
    }
}

/// A laws.json: greedy V-optimal runs for the adopted family's loss at C* over the grid's
/// model sizes (`fits::family::design::next_runs`), at the fit's θ, one run a proposal.
fn by_design(
    req: &Request,
    report: &LawReport,
    grid: &IsoFlopPlan,
    base: &IsoFlopPlan,
) -> Result<NextRuns, SweepError> {
    let bad = |message: String| SweepError::invalid(req.fits, message);
    let fit = report
        .fits
        .iter()
        .find(|f| f.law == report.adopted)
        .ok_or_else(|| bad(format!("no fit of its adopted law {}", report.adopted)))?;
    let family =
        fits::family::family(&fit.law).ok_or_else(|| bad(format!("unknown law {:?}", fit.law)))?;
    let results = req.results.unwrap_or(&report.table);
    let (trained, _) = read_points(&Table::read(results)?, &report.columns)?;
    let c_star = req.target_budget;
    let open: Vec<&PlanPoint> = open_points(grid, base, c_star).collect();
    let candidates: Vec<Point> = open
        .iter()
        .map(|p| as_point(grid, p, p.tokens as f64))
        .collect();
    let cost: Vec<f64> = open.iter().map(|p| p.budget).collect();
    let mut target: Vec<Point> = grid
        .points
        .iter()
        .map(|p| as_point(grid, p, c_star / (6.0 * (p.n_nv + p.n_v) as f64)))
        .collect();
    target.dedup_by(|a, b| a.n == b.n && a.nv == b.nv && a.u == b.u);
    let picks = design::next_runs(
        family.as_ref(),
        (&fit.theta, fit.space),
        &trained,
        &candidates,
        &cost,
        &target,
        (req.k, req.max_compute),
    );
    let state = format!(
        "planner: {} law ({} trained runs of {}), {} candidates; loss at {c_star:.3e} over {} model sizes, V-optimal:",
        fit.law,
        trained.len(),
        results.display(),
        candidates.len(),
        target.len()
    );
    let proposals = picks
        .iter()
        .map(|&(j, variance)| Proposal {
            runs: vec![open[j].run_id.clone()],
            cost: cost[j],
            why: format!("mean prediction variance at C* {variance:.4} (noise units)"),
        })
        .collect();
    Ok(NextRuns { state, proposals })
}

#[cfg(test)]
mod tests {
    use super::*;
    use fits::family::engine::Settings as LawSettings;
    use fits::family::run::{fit_laws, LawColumns};
    use fits::family::select::Holdout;
    use std::fmt::Write;

    /// The data-law study's first plan (5 budgets × 4 data fractions) as the grid; its points
    /// up to 10¹² as the base, "trained" on a Chinchilla law (Hoffmann et al.'s fit).
    fn study() -> (IsoFlopPlan, IsoFlopPlan, String) {
        let grid: IsoFlopPlan =
            toml::from_str(include_str!("../../docs/results/data-law/plan-a.toml")).unwrap();
        let mut base = grid.clone();
        base.points.retain(|p| p.budget <= 1e12);
        let mut csv = String::from("run_id,n_nv,tokens,loss\n");
        for p in &base.points {
            let (n, d) = (p.n_nv as f64, p.tokens as f64);
            let loss = 1.69 + 406.4 / n.powf(0.34) + 410.7 / d.powf(0.28);
            let _ = writeln!(csv, "{},{n},{d},{loss}", p.run_id);
        }
        (grid, base, csv)
    }

    #[test]
    fn a_law_family_fit_proposes_open_runs_below_the_target_budget() {
        let (grid, base, csv) = study();
        let tmp = tempfile::tempdir().unwrap();
        let results = tmp.path().join("results.csv");
        std::fs::write(&results, csv).unwrap();
        let cols = LawColumns {
            n: "n_nv".into(),
            d: "tokens".into(),
            loss: "loss".into(),
            u: None,
            epochs: None,
            nv: None,
            vocab: None,
            synth_share: None,
        };
        let settings = LawSettings {
            bootstrap: 0,
            starts: 16,
            ..LawSettings::default()
        };
        let families = fits::family::run::families(&["chinchilla".into()]).unwrap();
        let table = Table::read(&results).unwrap();
        let holdout = Holdout::TopCost { share: 0.1 };
        let report = fit_laws(&table, &cols, &families, holdout, None, None, &settings).unwrap();
        let laws = tmp.path().join("laws.json");
        std::fs::write(&laws, serde_json::to_string(&report).unwrap()).unwrap();
        let fit = read_fit(&laws, Goal::IsoFlop(Target::NOpt)).unwrap();
        let mut req = Request {
            fits: &laws,
            goal: Goal::IsoFlop(Target::NOpt),
            target_budget: 3e13,
            k: 3,
            max_compute: f64::INFINITY,
            results: None,
            hours: None,
        };
        let runs = next_runs(&req, &fit, &grid, &base).unwrap();
        assert!(
            runs.state.starts_with("planner: chinchilla law"),
            "{}",
            runs.state
        );
        assert_eq!(runs.proposals.len(), 3, "{runs:?}");
        for p in &runs.proposals {
            let point = grid.points.iter().find(|q| q.run_id == p.runs[0]).unwrap();
            assert!(base.points.iter().all(|b| b.run_id != point.run_id));
            assert!(point.budget > 1e12 && point.budget < 3e13 && p.cost == point.budget);
        }
        // A cap below every open run's cost leaves nothing to propose.
        req.max_compute = 1e11;
        let err = next_runs(&req, &fit, &grid, &base).unwrap_err();
        assert!(
            err.to_string().contains("no candidate fits --max-compute"),
            "{err}"
        );
    }

    #[test]
    fn a_fit_without_the_targets_law_is_refused_naming_it() {
        let (_, base, csv) = study();
        let tmp = tempfile::tempdir().unwrap();
        let results = tmp.path().join("results.csv");
        let mut with_budget = String::from("budget,run_id,n_nv,tokens,norm_test_loss\n");
        for (p, line) in base.points.iter().zip(csv.lines().skip(1)) {
            let _ = writeln!(with_budget, "{},{line}", p.budget);
        }
        std::fs::write(&results, with_budget).unwrap();
        let opts = fits::FitOptions {
            bootstrap: 0,
            ..fits::FitOptions::default()
        };
        let fitted = fits::fit_table(&Table::read(&results).unwrap(), &opts).unwrap();
        let path = tmp.path().join("fits.json");
        std::fs::write(&path, serde_json::to_string(&fitted).unwrap()).unwrap();
        // Chinchilla's N_opt lies outside these sizes (sized for the motion law): no vertex.
        let err = read_fit(&path, Goal::IsoFlop(Target::NOpt))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("no N_opt ∝ C^b law (n_opt_vs_c) to narrow for --target n_opt"),
            "{err}"
        );
        assert!(read_fit(&path, Goal::IsoFlop(Target::Loss)).is_err());
        let err = read_fit(&path, Goal::HourValue).unwrap_err().to_string();
        assert!(
            err.contains("no data-constrained fit (`fit --repeated-data`) to narrow"),
            "{err}"
        );
        std::fs::write(&path, "{\"unrelated\": 1}").unwrap();
        let err = read_fit(&path, Goal::HourValue).unwrap_err().to_string();
        assert!(err.contains("neither a fits.json"), "{err}");
    }
}
