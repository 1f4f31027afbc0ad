//! `motionscale fit --law`: the law families of `fits::family` on any table.

use crate::fit::{BootstrapBlock, FitArgs, LawSelection};
use anyhow::{Context, Result};
use fits::family::engine::Family;
use fits::family::engine::Settings;
use fits::family::run::{
    families, fit_laws as fit_table_laws, replay_summary, replays, LawColumns,
};
use fits::family::select::Holdout;
use fits::fitted::FitOptions;
use fits::isoflop::group_rows;
use fits::Table;
use std::process::ExitCode;
use std::time::Instant;

/// `motionscale fit --law`: runs the law families named and writes OUT/laws.json.
pub fn fit_laws(args: &FitArgs) -> Result<ExitCode> {
    let t0 = Instant::now();
    let opts = args.options()?;
    let pool = crate::commands::thread_pool(args.workers)?;
    pool.install(|| fit_laws_in_pool(args, &opts, t0))
}

/// The fit inside the worker pool.
fn fit_laws_in_pool(args: &FitArgs, opts: &FitOptions, t0: Instant) -> Result<ExitCode> {
    let table = Table::read(&args.results)?;
    let c = &opts.columns;
    let loss = args
        .param_loss_col
        .clone()
        .or_else(|| args.loss_col.clone())
        .unwrap_or_else(|| c.param_loss.name.clone());
    let cols = LawColumns {
        n: c.n.name.clone(),
        d: c.d.name.clone(),
        loss,
        u: Some(args.u_col.clone().unwrap_or_else(|| "unique_tokens".into())),
        epochs: Some(c.epochs.name.clone()),
        nv: Some(c.nv.name.clone()),
        vocab: Some(c.v.name.clone()),
        synth_share: Some(c.synth_share.name.clone()),
    };
    let holdout = match args.select {
        LawSelection::Top => Holdout::TopCost {
            share: args.top_share,
        },
        LawSelection::Budget => Holdout::Groups {
            groups: budget_groups(&table, &cols, opts)?,
        },
        LawSelection::Ladder => Holdout::Subsets {
            groups: ladder_groups(&table)?,
        },
    };
    let clusters = match args.block_bootstrap {
        None => None,
        Some(BootstrapBlock::Budget) => Some(budget_groups(&table, &cols, opts)?),
        Some(BootstrapBlock::Ladder) => Some(ladder_groups(&table)?),
    };
    let settings = Settings {
        delta: args.huber_delta,
        bootstrap: args.bootstrap,
        bootstrap_starts: match args.bootstrap_starts {
            Some(_) => opts.bootstrap_starts.unwrap_or(Settings::default().starts),
            None => Settings::default().bootstrap_starts,
        },
        bootstrap_all: args.bootstrap_all,
        seed: args.seed,
        ..Settings::default()
    };
    let chosen = families(&args.law)?;
    if !args.replay.is_empty() {
        return replay(args, &table, &cols, &chosen, &settings, t0);
    }
    let report = fit_table_laws(
        &table,
        &cols,
        &chosen,
        holdout,
        clusters.as_deref(),
        args.test.as_deref(),
        &settings,
    )?;
    let path = args.out.join("laws.json");
    motionscale_core::files::write_atomic(&path, serde_json::to_string_pretty(&report)?.as_bytes())
        .with_context(|| path.display().to_string())?;
    print!("{}", report.summary());
    println!(
        "wrote {} in {:.2} s on {} threads",
        path.display(),
        t0.elapsed().as_secs_f64(),
        rayon::current_num_threads()
    );
    Ok(ExitCode::SUCCESS)
}

/// Each run's budget group: the group column where the table has it, else its compute
/// (the budget column, or 6·N·D) within --group-tol dex.
fn budget_groups(table: &Table, cols: &LawColumns, opts: &FitOptions) -> Result<Vec<usize>> {
    let c = &opts.columns;
    let compute = if table.has(&c.c.name) {
        table.numbers(&c.c.name, "--c-col")?
    } else {
        let n = table.numbers(&cols.n, "--n-col")?;
        let d = table.numbers(&cols.d, "--d-col")?;
        n.iter().zip(&d).map(|(n, d)| 6.0 * n * d).collect()
    };
    let group = if table.has(&c.group.name) {
        Some(table.numbers(&c.group.name, "--group-col")?)
    } else {
        None
    };
    let mut of_row = vec![0; compute.len()];
    for (g, rows) in group_rows(&compute, group.as_deref(), opts.group_tol_dex)
        .into_iter()
        .enumerate()
    {
        rows.into_iter().for_each(|i| of_row[i] = g);
    }
    Ok(of_row)
}

/// The data subset (ladder) of every run: one group per distinct value of the `data` column
/// (a sweep's subset name; empty for the whole train split).
fn ladder_groups(table: &Table) -> Result<Vec<usize>> {
    let Some(labels) = table.labels("data") else {
        anyhow::bail!(
            "{}: --select ladder needs a `data` column (a sweep's data subset of each run)",
            table.path().display()
        );
    };
    let mut names: Vec<&String> = labels.iter().collect();
    names.sort();
    names.dedup();
    if names.len() < 2 {
        anyhow::bail!(
            "{}: --select ladder needs runs on two data subsets or more",
            table.path().display()
        );
    }
    Ok(labels
        .iter()
        .map(|l| names.binary_search(&l).expect("listed"))
        .collect())
}

/// `fit --law NAME --test FILE --replay CAPS`: the design replays of one family.
fn replay(
    args: &FitArgs,
    table: &Table,
    cols: &LawColumns,
    chosen: &[Box<dyn Family>],
    settings: &Settings,
    t0: Instant,
) -> Result<ExitCode> {
    let [family] = chosen else {
        anyhow::bail!("--replay takes one --law (got {})", args.law.join(","));
    };
    if let Some(bad) = args.replay.iter().find(|c| !(**c > 0.0 && **c <= 1.0)) {
        anyhow::bail!("--replay {bad}: a cap is a share of the pool's cost in (0, 1]");
    }
    let test = args
        .test
        .as_deref()
        .expect("clap requires --test with --replay");
    let done = replays(
        table,
        test,
        cols,
        family.as_ref(),
        &args.replay,
        args.replay_seeds,
        settings,
    )?;
    let path = args.out.join("replays.json");
    motionscale_core::files::write_atomic(&path, serde_json::to_string_pretty(&done)?.as_bytes())
        .with_context(|| path.display().to_string())?;
    print!("{}", replay_summary(family.name(), &done));
    println!(
        "wrote {} in {:.2} s",
        path.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}
