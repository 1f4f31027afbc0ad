//! `motionscale sweep replay` and `sweep plan --next`: the active sweep planner
//! (`fits::planner`), judged on finished tables and used to choose a study's next runs.

use crate::plan_args::PlanArgs;
use anyhow::{bail, Context, Result};
use experiments::plan;
use experiments::IsoFlopPlan;
use fits::data_value::{predict_data, Hours};
use fits::family::design::next_runs;
use fits::family::run::{read_points, LawReport};
use fits::family::Point;
use fits::fitted::FitFile;
use fits::hour_design::{self, DataCandidate};
use fits::isoflop::{self, parabola_minimum};
use fits::loss_shape::Form;
use fits::planner::{self, Candidate, Goal, Observation, Settings, Target};
use fits::replay::{self, Policy, ReplayStep, ReplayTable};
use fits::Table;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Arguments of `motionscale sweep replay`.
#[derive(clap::Args, Debug)]
pub struct ReplayArgs {
    /// A finished results table (`results.csv` or `.parquet` of `sweep run`/`collect`).
    #[arg(long)]
    pub results: PathBuf,
    /// The budget C* whose target is extrapolated from the budgets below it; its own runs,
    /// if any, give the truth the policies are scored against.
    #[arg(long)]
    pub target_budget: f64,
    /// What is extrapolated: n_opt (log10 N_opt, decades) or loss (at N_opt).
    #[arg(long, default_value = "n_opt", value_parser = Target::parse)]
    pub target: Target,
    /// With --target loss: the loss law it extrapolates by, log, curved or floor (pass the one
    /// `fit` chose for the table, its fits.json's `loss_shape.chosen`; `sweep plan --next`
    /// reads it from there).
    #[arg(long, default_value = "log", value_parser = parse_form)]
    pub loss_form: Form,
    /// Policies to replay, comma-separated: active, grid, random, oracle (knows every loss:
    /// the full table's envelope runs, cheapest budget first; what reproducing it costs).
    #[arg(long, value_delimiter = ',', default_value = "active,grid,random", value_parser = Policy::parse)]
    pub policy: Vec<Policy>,
    /// Random orders to replay (their median is the random policy's curve).
    #[arg(long, default_value_t = 20)]
    pub seeds: usize,
    /// Stop each policy before its compute passes this share of the table's (below C*).
    #[arg(long, default_value_t = 0.3)]
    pub max_compute_share: f64,
    /// Every policy starts from the whole grid of this many cheapest budgets (a law needs three).
    #[arg(long, default_value_t = 3)]
    pub start_budgets: usize,
    /// Bootstrap draws of each posterior.
    #[arg(long, default_value_t = 200)]
    pub draws: usize,
    /// Seed of the draws and the random orders.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The loss column.
    #[arg(long, default_value = "norm_test_loss")]
    pub loss_col: String,
    /// The target's true value (log10 N_opt or the loss), when the table has no runs at C*.
    #[arg(long)]
    pub truth: Option<f64>,
    /// Output folder: replay.csv, summary.json, replay-width and replay-error charts, and
    /// predictive-check.csv (the runs active left, against what its model expected of them).
    #[arg(long)]
    pub out: PathBuf,
}

/// " (the … law)" after a `loss` target's name, naming the form it extrapolates by.
fn by_law(target: Target, form: Form) -> String {
    match target {
        Target::Loss => format!(" (the {} law)", form.name()),
        Target::NOpt => String::new(),
    }
}

/// Parses `--loss-form`.
fn parse_form(name: &str) -> Result<Form, String> {
    Form::parse(name).ok_or_else(|| format!("{name:?}: expected log, curved or floor"))
}

/// log10 distance under which two budgets are one group (as `fit`).
const TOL_DEX: f64 = 0.05;

/// The budget groups of `c`, ascending.
fn budget_groups(c: &[f64]) -> Vec<f64> {
    isoflop::group_rows(c, None, TOL_DEX)
        .iter()
        .map(|g| isoflop::group_budget(c, g))
        .collect()
}

/// The budgets listed for an error message.
fn listed(budgets: &[f64]) -> String {
    let list: Vec<String> = budgets.iter().map(|b| format!("{b:.3e}")).collect();
    list.join(", ")
}

/// The target's value in the runs at C* (their envelope parabola's interior vertex).
fn truth_at(
    path: &Path,
    runs: &[Candidate],
    losses: &[f64],
    target: Target,
    c_star: f64,
) -> Result<f64> {
    let at: Vec<usize> = (0..runs.len())
        .filter(|&i| (runs[i].budget.log10() - c_star.log10()).abs() <= TOL_DEX)
        .collect();
    if at.is_empty() {
        bail!(
            "{}: no runs at --target-budget {c_star:.3e} to score the policies against; pass --truth",
            path.display()
        );
    }
    let n: Vec<f64> = at.iter().map(|&i| runs[i].n).collect();
    let l: Vec<f64> = at.iter().map(|&i| losses[i]).collect();
    let m = parabola_minimum(c_star, "N", None, &n, &l);
    match (m.interior, m.log10_opt, m.loss_opt) {
        (true, Some(v), Some(loss)) => Ok(match target {
            Target::NOpt => v.value,
            Target::Loss => loss,
        }),
        _ => bail!(
            "{}: the {} runs at {c_star:.3e} have no interior minimum ({}); pass --truth",
            path.display(),
            at.len(),
            m.reason.unwrap_or_default()
        ),
    }
}

/// The replay table of `args`: the pool below C*, its start, the truth and the cap.
fn replay_table(args: &ReplayArgs) -> Result<ReplayTable> {
    let t = Table::read(&args.results)?;
    let (runs, losses) = replay::read_runs(&t, &args.loss_col)?;
    let all = budget_groups(&runs.iter().map(|r| r.budget).collect::<Vec<_>>());
    let below: Vec<f64> = all
        .iter()
        .copied()
        .filter(|b| b.log10() < args.target_budget.log10() - TOL_DEX)
        .collect();
    if below.is_empty() {
        bail!(
            "{}: --target-budget {:.3e} is not above the table's budgets ({}): nothing to extrapolate from",
            args.results.display(),
            args.target_budget,
            listed(&all)
        );
    }
    if below.len() < args.start_budgets.max(3) + 1 {
        bail!(
            "{}: {} budget(s) below {:.3e} ({}); a replay needs the {} start budgets (--start-budgets, at least 3 for a law) and one more to choose from",
            args.results.display(),
            below.len(),
            args.target_budget,
            listed(&below),
            args.start_budgets.max(3)
        );
    }
    let truth = match args.truth {
        Some(v) => v,
        None => truth_at(
            &args.results,
            &runs,
            &losses,
            args.target,
            args.target_budget,
        )?,
    };
    let top = below[below.len() - 1].log10() + TOL_DEX;
    let first = below[args.start_budgets - 1].log10() + TOL_DEX;
    let keep: Vec<usize> = (0..runs.len())
        .filter(|&i| runs[i].budget.log10() <= top)
        .collect();
    let pool: Vec<Candidate> = keep.iter().map(|&i| runs[i].clone()).collect();
    let total: f64 = pool.iter().map(|r| r.cost).sum();
    Ok(ReplayTable {
        start: (0..pool.len())
            .filter(|&i| pool[i].budget.log10() <= first)
            .collect(),
        losses: keep.iter().map(|&i| losses[i]).collect(),
        pool,
        target: args.target,
        c_star: args.target_budget,
        truth,
        max_compute: args.max_compute_share * total,
        settings: Settings {
            draws: args.draws,
            seed: args.seed,
            loss_form: args.loss_form,
            ..Settings::default()
        },
    })
}

/// `motionscale sweep replay`.
pub fn replay_cmd(args: ReplayArgs) -> Result<ExitCode> {
    let table = replay_table(&args)?;
    let pool_compute: f64 = table.pool.iter().map(|r| r.cost).sum();
    let full = table.full();
    let unit = args.target.unit();
    // The loss law matters, and is named, for the loss target only.
    let loss_form = (args.target == Target::Loss).then_some(args.loss_form);
    println!(
        "replay: {} runs below {:.3e} ({:.3e} FLOPs), {} in the start; {}truth {:.4}; full table: median {:.4}, 95% [{:.4}, {:.4}], width {:.4} {unit}",
        table.pool.len(),
        table.c_star,
        pool_compute,
        table.start.len(),
        loss_form
            .map(|f| format!("loss{}: ", by_law(args.target, f)))
            .unwrap_or_default(),
        table.truth,
        full.median,
        full.low,
        full.high,
        full.width
    );
    let curves = run_policies(&table, &args);
    let start: f64 = table.start.iter().map(|&i| table.pool[i].cost).sum();
    let levels: Vec<f64> = (0..100)
        .map(|k| start + (table.max_compute - start) * k as f64 / 99.0)
        .collect();
    let summaries: Vec<replay::PolicySummary> = curves
        .iter()
        .map(|(name, c)| replay::summarise(name, c, pool_compute, &levels, full.width))
        .collect();
    std::fs::create_dir_all(&args.out).with_context(|| args.out.display().to_string())?;
    let every: Vec<Vec<ReplayStep>> = curves.iter().flat_map(|(_, c)| c.clone()).collect();
    replay::write_csv(&args.out.join("replay.csv"), &every)?;
    let active = curves.iter().find(|(name, _)| *name == "active");
    let check = active.map(|(_, c)| table.predictive_check(&c[0]));
    if let Some(checks) = &check {
        replay::write_check_csv(&args.out.join("predictive-check.csv"), checks)?;
    }
    let summary = replay::ReplaySummary {
        results: args.results.display().to_string(),
        target: args.target.name().into(),
        loss_form: loss_form.map(|f| f.name().into()),
        target_budget: args.target_budget,
        truth: table.truth,
        loss_col: args.loss_col.clone(),
        pool_runs: table.pool.len(),
        pool_compute,
        start_runs: table.start.len(),
        start_share: start / pool_compute,
        max_compute_share: args.max_compute_share,
        draws: args.draws,
        seed: args.seed,
        full_table: full,
        policies: summaries,
        active_at_or_below: replay::at_or_below(&curves, &levels),
        active_predictive_check: check.as_deref().map(replay::summarise_check),
    };
    motionscale_core::files::write_json(&args.out.join("summary.json"), &summary)?;
    for (chart, stem) in replay::charts(&curves, pool_compute, &levels, &full, unit)
        .iter()
        .zip(["replay-width", "replay-error"])
    {
        chart.write(&args.out.join(stem))?;
    }
    print_summary(&summary);
    println!("→ {}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

/// Each policy's curves (one per random order for `random`).
fn run_policies<'a>(
    table: &ReplayTable,
    args: &'a ReplayArgs,
) -> Vec<(&'a str, Vec<Vec<ReplayStep>>)> {
    args.policy
        .iter()
        .map(|&policy| {
            let orders = match policy {
                Policy::Random => args.seeds,
                _ => 1,
            };
            let c: Vec<Vec<ReplayStep>> = (0..orders).map(|o| table.replay(policy, o)).collect();
            eprintln!("replay: {} done ({} curve(s))", policy.name(), c.len());
            (policy.name(), c)
        })
        .collect()
}

/// The summary table `sweep replay` prints.
fn print_summary(summary: &replay::ReplaySummary) {
    println!(
        "{:<8} {:>6} {:>11} {:>11} {:>11} {:>16} {:>11} {:>11}",
        "policy",
        "orders",
        "end share",
        "end width",
        "end error",
        "share to full w.",
        "mean width",
        "mean error"
    );
    for s in &summary.policies {
        let reach = s.share_to_full_width.map_or("never".into(), |v| {
            format!("{v:.3} ({}/{})", s.orders_reaching_full_width, s.orders)
        });
        println!(
            "{:<8} {:>6} {:>11.3} {:>11.4} {:>11.4} {:>16} {:>11.4} {:>11.4}",
            s.policy,
            s.orders,
            s.final_share,
            s.final_width,
            s.final_error,
            reach,
            s.mean_width,
            s.mean_error
        );
    }
    if let Some(c) = &summary.active_predictive_check {
        println!(
            "active's model where it stopped, against the {} runs it left: RMS z {:.2}, |z| > 1.96 at {:.0}% (1 and 5% if its predictive SD is right); the {} on the full table's envelopes: RMS z {:.2}, mean z {:+.2}",
            c.runs,
            c.rms_z,
            100.0 * c.beyond_95,
            c.envelope_runs,
            c.envelope_rms_z,
            c.envelope_mean_z
        );
    }
    for b in &summary.active_at_or_below {
        println!(
            "active at or below {}: width at {:.0}% of the compute levels, error at {:.0}%",
            b.policy,
            100.0 * b.width,
            100.0 * b.error
        );
    }
}

/// The fit `--next` narrows, checked to have the target's law.
fn fit_with_law(path: &Path, goal: Goal) -> Result<fits::Fits> {
    let fits = fits::Fits::read(path)?;
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
        bail!(
            "{}: no {law} to narrow for --target {} (skipped: {})",
            path.display(),
            goal.name(),
            fits.skipped.join("; ")
        );
    }
    Ok(fits)
}

/// The trained runs of `base` on the grid's data subset, as the planner sees them; the error
/// says why they cannot support a law at C*.
fn trained_runs(
    args: &PlanArgs,
    fit: &fits::Fits,
    base: &IsoFlopPlan,
    subset: Option<&String>,
    c_star: f64,
) -> Result<Vec<Observation>> {
    let results = args
        .results
        .clone()
        .unwrap_or_else(|| PathBuf::from(&fit.input.file));
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
        bail!(
            "{}: {} budget(s) trained in the plan's subset ({}); the planner needs three for a law",
            results.display(),
            trained.len(),
            listed(&trained)
        );
    }
    if c_star.log10() <= trained[trained.len() - 1].log10() + TOL_DEX {
        bail!(
            "--target-budget {c_star:.3e} is not above the budgets trained ({})",
            listed(&trained)
        );
    }
    Ok(obs)
}

/// The grid's runnable points below C* that `base` does not have.
fn open_points<'a>(
    grid: &'a IsoFlopPlan,
    base: &'a IsoFlopPlan,
    c_star: f64,
) -> impl Iterator<Item = &'a experiments::plan::PlanPoint> {
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

/// `sweep plan --next K`: the base plan (--extend) extended by the K proposals.
pub fn next_plan(args: &PlanArgs, k: usize) -> Result<IsoFlopPlan> {
    let (Some(c_star), Some(fits_path), Some(base_path)) =
        (args.target_budget, &args.fits, &args.extend)
    else {
        bail!("--next needs --target-budget, --fits and --extend");
    };
    let base = IsoFlopPlan::read(base_path)?;
    let mut request = args.request()?;
    request.extend = None;
    let grid = plan::plan(&request)?;
    let room = args.max_compute.unwrap_or(f64::INFINITY);
    let chosen = match FitFile::read(fits_path)? {
        FitFile::Families(report) => {
            next_by_design(args, &report, &grid, &base, (c_star, k, room))?
        }
        FitFile::IsoFlop(_) => {
            let fit = fit_with_law(fits_path, args.target)?;
            match args.target {
                Goal::IsoFlop(t) => next_isoflop(args, &fit, &grid, &base, t, (c_star, k, room))?,
                Goal::HourValue => {
                    next_hours(args, &fit, fits_path, &grid, &base, (c_star, k, room))?
                }
            }
        }
    };
    request.only = chosen;
    request.extend = Some(base);
    Ok(plan::plan(&request)?)
}

/// A plan point as a law family reads it: N = N_nv, D its tokens, N_v, and U (its data
/// subset's unique tokens, else its vocabulary's train tokens).
fn as_point(grid: &IsoFlopPlan, p: &experiments::plan::PlanPoint, d: f64) -> Point {
    let u = p
        .unique_tokens
        .or_else(|| grid.vocabulary(p.codebook).map(|v| v.train_tokens))
        .map(|u| u as f64);
    Point {
        n: p.n_nv as f64,
        d,
        u,
        nv: Some(p.n_v as f64),
    }
}

/// `--next` on a laws.json: greedy V-optimal runs for the adopted family's loss at C* over
/// the grid's model sizes (`fits::family::design::next_runs`), at the fit's θ.
fn next_by_design(
    args: &PlanArgs,
    report: &LawReport,
    grid: &IsoFlopPlan,
    base: &IsoFlopPlan,
    (c_star, k, room): (f64, usize, f64),
) -> Result<Vec<String>> {
    let fit = report
        .fits
        .iter()
        .find(|f| f.law == report.adopted)
        .context("the laws.json has no fit of its adopted law")?;
    let family = fits::family::family(&fit.law).context("unknown law in the laws.json")?;
    let results = args.results.clone().unwrap_or_else(|| report.table.clone());
    let (trained, _) = read_points(&Table::read(&results)?, &report.columns)?;
    let open: Vec<_> = open_points(grid, base, c_star).collect();
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
    let picks = next_runs(
        family.as_ref(),
        (&fit.theta, fit.space),
        &trained,
        &candidates,
        &cost,
        &target,
        (k, room),
    );
    if picks.is_empty() {
        bail!("no candidate below --target-budget fits --max-compute or is informative for the {} law", fit.law);
    }
    println!(
        "planner: {} law ({} trained runs of {}), {} candidates; loss at {c_star:.3e} over {} model sizes, V-optimal:",
        fit.law,
        trained.len(),
        results.display(),
        candidates.len(),
        target.len()
    );
    for (i, (j, variance)) in picks.iter().enumerate() {
        println!(
            "next {}: {} ({:.3e} FLOPs): mean prediction variance at C* {:.4} (noise units)",
            i + 1,
            open[*j].run_id,
            cost[*j],
            variance
        );
    }
    Ok(picks.iter().map(|(j, _)| open[*j].run_id.clone()).collect())
}

/// The proposals' run ids, printed with what each costs and buys.
fn chosen_ids(proposals: &[planner::Proposal], ids: &[&str]) -> Result<Vec<String>> {
    if proposals.is_empty() {
        bail!("no candidate fits --max-compute, is predictable from the trained runs, or is expected to narrow the interval");
    }
    for (i, p) in proposals.iter().enumerate() {
        let these: Vec<&str> = p.runs.iter().map(|&j| ids[j]).collect();
        println!(
            "next {}: {} ({:.3e} FLOPs): {}",
            i + 1,
            these.join(", "),
            p.cost,
            p.why
        );
    }
    Ok(proposals
        .iter()
        .flat_map(|p| p.runs.iter().map(|&j| ids[j].to_string()))
        .collect())
}

/// `--next` on N_opt or the loss at N_opt: the IsoFLOP bootstrap (`fits::planner`).
fn next_isoflop(
    args: &PlanArgs,
    fit: &fits::Fits,
    grid: &IsoFlopPlan,
    base: &IsoFlopPlan,
    target: Target,
    (c_star, k, room): (f64, usize, f64),
) -> Result<Vec<String>> {
    // The study's subset: the data of the grid's points (trained rows of other subsets differ).
    let subset = grid.points.first().and_then(|p| p.data.clone());
    let obs = trained_runs(args, fit, base, subset.as_ref(), c_star)?;
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
    println!(
        "planner: {} trained runs of the plan; {}{} at {c_star:.3e} now: median {:.4}, 95% [{:.4}, {:.4}], width {:.4} {}, {} of {} draws with a law, spread {:.3} ({} candidates)",
        obs.len(), target.name(), by_law(target, loss_form), now.median, now.low, now.high, now.width, target.unit(), now.valid, now.draws, now.spread(), pool.len()
    );
    let proposals = planner::propose(&obs, &pool, target, c_star, k, room, &settings);
    let ids: Vec<&str> = pool.iter().map(|c| c.id.as_str()).collect();
    chosen_ids(&proposals, &ids)
}

/// `--next --target hour_value`: the data-constrained fit's Laplace posterior
/// (`fits::hour_design`) over the grid's points of every data subset.
fn next_hours(
    args: &PlanArgs,
    fit: &fits::Fits,
    fits_path: &Path,
    grid: &IsoFlopPlan,
    base: &IsoFlopPlan,
    (c_star, k, room): (f64, usize, f64),
) -> Result<Vec<String>> {
    let rd = fit
        .repeated_data
        .as_ref()
        .context("checked by fit_with_law")?;
    let n_col = fit.input.columns.get("N").cloned().flatten();
    if n_col.as_deref() != Some("n_nv") {
        bail!(
            "{}: the fit's N column is {n_col:?}; --target hour_value reads the plan's N as n_nv",
            fits_path.display()
        );
    }
    let hours = match args.hours {
        Some(h) => h,
        None => corpus_hours(grid).context(
            "--target hour_value: the plan has no full-data subset; pass --hours real=H,synth=H",
        )?,
    };
    let pool = data_candidates(grid, base, c_star);
    if pool.is_empty() {
        bail!("--target hour_value: no point of the grid below {c_star:.3e} has a data subset (plan with --data-fractions)");
    }
    let (now, proposals) = hour_design::propose_hours(rd, &pool, c_star, hours, k, room)
        .map_err(anyhow::Error::msg)?;
    let refits = predict_data(rd, c_star, hours).map_err(anyhow::Error::msg)?;
    let by_refits = &refits.hour_values[0].loss_change;
    println!(
        "planner: +1 h of captured motion at {c_star:.3e} with {:.2} h captured, {:.2} h synthetic: {:.4e} nats, Laplace 95% [{:.4e}, {:.4e}], width {:.3e} (the fit's refits: [{:.4e}, {:.4e}]); {} candidates",
        hours.real, hours.synth, now.value, now.low, now.high, now.width,
        by_refits.ci_low.unwrap_or(f64::NAN), by_refits.ci_high.unwrap_or(f64::NAN), pool.len()
    );
    let ids: Vec<&str> = pool.iter().map(|c| c.id.as_str()).collect();
    chosen_ids(&proposals, &ids)
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
