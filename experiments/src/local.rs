//! The local executor: a sweep folder adopts its plan, the vocabularies are prepared, then
//! every missing point runs, one at a time in this process or `jobs` at a time in worker
//! processes. Each worker gets `cores / jobs` threads (`RAYON_NUM_THREADS`, which both rayon
//! and candle's CPU kernels read) so that the workers do not oversubscribe the machine, and
//! dies with its parent (`PR_SET_PDEATHSIG`), so killing `sweep run` stops the whole sweep.

use crate::plan::{IsoFlopPlan, PlanPoint};
use crate::prepare::prepare_vocabulary;
use crate::results::{self, read_row, run_dir};
use crate::run::{run_point, Outcome, RunError};
use crate::SweepError;
use std::collections::VecDeque;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::Duration;

/// File name of the plan copy inside a sweep folder.
pub const PLAN_FILE: &str = "plan.toml";

/// How [`run_local`] runs the points.
pub struct LocalOptions<'a> {
    /// Points trained at once (1: in this process).
    pub jobs: usize,
    /// Only these plan rows (all when `None`).
    pub only: Option<Vec<usize>>,
    /// The command that runs one plan row in a worker process (used when `jobs > 1`).
    pub worker: &'a dyn Fn(usize) -> Command,
}

/// What [`run_local`] did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Summary {
    /// Selected points already done before this call.
    pub already_done: usize,
    /// Points trained by this call.
    pub trained: usize,
    /// Points that failed: run id and error.
    pub failed: Vec<(String, String)>,
    /// Points not run because the plan flags them below one step.
    pub not_runnable: Vec<String>,
    /// Rows in the rebuilt results table.
    pub rows: usize,
}

/// Create the sweep folder `runs` (made absolute) and give it `plan`: write `runs/plan.toml`,
/// or check that the one there is the same plan, or one that `plan` extends (then `plan`
/// replaces it: its first points are the ones already run).
pub fn adopt_plan(plan: &IsoFlopPlan, runs: &Path) -> Result<PathBuf, SweepError> {
    std::fs::create_dir_all(runs).map_err(|e| SweepError::io(runs, e))?;
    let runs = std::fs::canonicalize(runs).map_err(|e| SweepError::io(runs, e))?;
    let path = runs.join(PLAN_FILE);
    if path.exists() {
        let adopted = IsoFlopPlan::read(&path)?;
        if adopted != *plan {
            if !plan.extends(&adopted) {
                return Err(SweepError::invalid(
                    &path,
                    "this sweep folder holds a different plan (not one this plan extends); use another --out",
                ));
            }
            plan.write(&path)?;
        }
    } else {
        plan.write(&path)?;
    }
    Ok(runs)
}

/// The sweep folder's own plan (`runs/plan.toml`).
pub fn read_adopted_plan(runs: &Path) -> Result<IsoFlopPlan, SweepError> {
    IsoFlopPlan::read(&runs.join(PLAN_FILE))
}

/// The points of `plan` in `only` (all when `None`); an index outside the plan is an error.
pub fn select<'p>(
    plan: &'p IsoFlopPlan,
    only: Option<&[usize]>,
) -> Result<Vec<&'p PlanPoint>, SweepError> {
    match only {
        None => Ok(plan.points.iter().collect()),
        Some(indices) => indices
            .iter()
            .map(|&i| {
                plan.points.get(i).ok_or_else(|| {
                    SweepError::Argument(format!(
                        "plan row {i} does not exist (the plan has {} points)",
                        plan.points.len()
                    ))
                })
            })
            .collect(),
    }
}

/// Prepare the token sets of every vocabulary that `points` use.
pub fn prepare_all(
    plan: &IsoFlopPlan,
    runs: &Path,
    points: &[&PlanPoint],
    log: &dyn Fn(&str),
) -> Result<(), SweepError> {
    for vocab in &plan.vocabularies {
        if points
            .iter()
            .any(|p| p.codebook == vocab.codebook && p.runnable())
        {
            prepare_vocabulary(plan, vocab, runs, log)?;
        }
    }
    Ok(())
}

/// Threads available to the sweep: `RAYON_NUM_THREADS` when set, else the cores.
pub fn available_threads() -> usize {
    std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, usize::from))
}

/// Run every selected point of `plan` that is not done into `runs`, then rebuild the tables.
pub fn run_local(
    plan: &IsoFlopPlan,
    runs: &Path,
    options: &LocalOptions,
    log: &dyn Fn(&str),
) -> Result<Summary, SweepError> {
    let runs = adopt_plan(plan, runs)?;
    let selected = select(plan, options.only.as_deref())?;
    let mut summary = Summary::default();
    let mut todo = Vec::new();
    for point in selected {
        if !point.runnable() {
            summary.not_runnable.push(point.run_id.clone());
        } else if read_row(&runs, &point.run_id)?.is_some() {
            summary.already_done += 1;
        } else {
            todo.push(point);
        }
    }
    prepare_all(plan, &runs, &todo, log)?;
    if options.jobs <= 1 || todo.len() <= 1 {
        for point in todo {
            match run_point(plan, &runs, point, log) {
                Ok(Outcome::Trained(row)) => {
                    summary.trained += 1;
                    log(&format!(
                        "{}: done: test CE {:.4}, L_u {:.4}, D {}, {:.1} s",
                        row.run_id, row.test_loss, row.norm_test_loss, row.tokens, row.wall_s
                    ));
                }
                Ok(Outcome::AlreadyDone(_)) => summary.already_done += 1,
                Err(e) => {
                    log(&format!("{}: failed: {e}", point.run_id));
                    summary.failed.push((point.run_id.clone(), e.to_string()));
                }
            }
        }
    } else {
        run_workers(&runs, todo, options, &mut summary, log)?;
    }
    summary.rows = results::rebuild_tables(&runs, plan)?.len();
    Ok(summary)
}

/// Run `todo` in up to `options.jobs` worker processes at once.
fn run_workers(
    runs: &Path,
    todo: Vec<&PlanPoint>,
    options: &LocalOptions,
    summary: &mut Summary,
    log: &dyn Fn(&str),
) -> Result<(), SweepError> {
    let threads = (available_threads() / options.jobs).max(1);
    log(&format!(
        "{} points in {} worker processes of {threads} thread(s) each",
        todo.len(),
        options.jobs
    ));
    let mut queue: VecDeque<&PlanPoint> = todo.into();
    let mut running: Vec<(&PlanPoint, Child)> = Vec::new();
    loop {
        while running.len() < options.jobs {
            let Some(point) = queue.pop_front() else {
                break;
            };
            let mut command = (options.worker)(point.index);
            command.env("RAYON_NUM_THREADS", threads.to_string());
            die_with_parent(&mut command);
            let child = command.spawn().map_err(|e| SweepError::Command {
                command: format!("{command:?}"),
                message: e.to_string(),
            })?;
            running.push((point, child));
        }
        if running.is_empty() {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(100));
        let mut still = Vec::with_capacity(running.len());
        for (point, mut child) in running {
            let status = child.try_wait().map_err(|e| SweepError::Command {
                command: format!("worker for {}", point.run_id),
                message: e.to_string(),
            })?;
            match status {
                None => still.push((point, child)),
                Some(s) if s.success() => summary.trained += 1,
                Some(s) => {
                    let error = worker_error(runs, &point.run_id)
                        .unwrap_or_else(|| format!("worker exited with {s}"));
                    log(&format!("{}: failed: {error}", point.run_id));
                    summary.failed.push((point.run_id.clone(), error));
                }
            }
        }
        running = still;
    }
}

/// The error a failed worker recorded for its point, if any.
fn worker_error(runs: &Path, run_id: &str) -> Option<String> {
    let text = std::fs::read_to_string(run_dir(runs, run_id).join("error.json")).ok()?;
    serde_json::from_str::<RunError>(&text)
        .ok()
        .map(|e| e.error)
}

/// Make the process `command` starts receive SIGKILL when this process dies.
fn die_with_parent(command: &mut Command) {
    // SAFETY: getpid before the fork; in the child only async-signal-safe calls
    // (prctl, getppid, _exit) run before exec.
    let parent = unsafe { libc::getpid() };
    unsafe {
        command.pre_exec(move || {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            // The parent may have died between fork and prctl: then nobody would kill us.
            if libc::getppid() != parent {
                libc::_exit(1);
            }
            Ok(())
        });
    }
}

/// Rebuild the tables of the sweep folder `runs` from its own plan: the rows, and the run
/// ids of runnable points without one.
pub fn collect(runs: &Path) -> Result<(Vec<results::RunRow>, Vec<String>), SweepError> {
    let plan = read_adopted_plan(runs)?;
    let rows = results::rebuild_tables(runs, &plan)?;
    let missing = plan
        .points
        .iter()
        .filter(|p| p.runnable() && !rows.iter().any(|r| r.run_id == p.run_id))
        .map(|p| p.run_id.clone())
        .collect();
    Ok((rows, missing))
}
