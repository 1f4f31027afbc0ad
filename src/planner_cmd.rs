//! `motionscale sweep replay` and `sweep plan --next`: the active sweep planner
//! (`fits::planner`), judged on finished tables and used to choose a study's next runs.

use crate::plan_args::PlanArgs;
use anyhow::{bail, Context, Result};
use experiments::next::{self, listed};
use experiments::plan;
use experiments::IsoFlopPlan;
use fits::isoflop::parabola_minimum;
use fits::loss_shape::Form;
use fits::planner::{budget_groups, Candidate, Settings, Target, GROUP_TOL_DEX};
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

/// Parses `--loss-form`.
fn parse_form(name: &str) -> Result<Form, String> {
    Form::parse(name).ok_or_else(|| format!("{name:?}: expected log, curved or floor"))
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
        .filter(|&i| (runs[i].budget.log10() - c_star.log10()).abs() <= GROUP_TOL_DEX)
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
        .filter(|b| b.log10() < args.target_budget.log10() - GROUP_TOL_DEX)
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
    let top = below[below.len() - 1].log10() + GROUP_TOL_DEX;
    let first = below[args.start_budgets - 1].log10() + GROUP_TOL_DEX;
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
            .map(|f| format!("loss{}: ", args.target.by_law(f)))
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

/// `sweep plan --next K`: the base plan (--extend) extended by the K proposals
/// (`experiments::next`), printed with what each costs and buys.
pub fn next_plan(args: &PlanArgs, k: usize) -> Result<IsoFlopPlan> {
    let (Some(c_star), Some(fits_path), Some(base_path)) =
        (args.target_budget, &args.fits, &args.extend)
    else {
        bail!("--next needs --target-budget, --fits and --extend");
    };
    let fit = next::read_fit(fits_path, args.target)?;
    let base = IsoFlopPlan::read(base_path)?;
    let mut request = args.request()?;
    request.extend = None;
    let grid = plan::plan(&request)?;
    let req = next::Request {
        fits: fits_path,
        goal: args.target,
        target_budget: c_star,
        k,
        max_compute: args.max_compute.unwrap_or(f64::INFINITY),
        results: args.results.as_deref(),
        hours: args.hours,
    };
    let runs = next::next_runs(&req, &fit, &grid, &base)?;
    println!("{}", runs.state);
    for (i, p) in runs.proposals.iter().enumerate() {
        println!(
            "next {}: {} ({:.3e} FLOPs): {}",
            i + 1,
            p.runs.join(", "),
            p.cost,
            p.why
        );
    }
    request.only = runs.proposals.into_iter().flat_map(|p| p.runs).collect();
    request.extend = Some(base);
    Ok(plan::plan(&request)?)
}
