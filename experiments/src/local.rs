//! The local executor: a sweep folder adopts its plan, the vocabularies are prepared, then
//! every missing point runs, one at a time in this process or `jobs` at a time in worker
//! processes. Each worker gets `cores / jobs` threads (`RAYON_NUM_THREADS`, which both rayon
//! and candle's CPU kernels read) so that the workers do not oversubscribe the machine, and
//! dies with its parent (`PR_SET_PDEATHSIG`), so killing `sweep run` stops the whole sweep.
//!
//! With GPUs ([`LocalOptions::devices`]) the workers are `jobs_per_device` per GPU: small
//! runs leave most of a GPU idle and share one, while a large run (at least
//! `exclusive_params` parameters) only starts on an idle GPU and keeps it to itself.

use crate::plan::{adopt_plan, read_adopted_plan, IsoFlopPlan, PlanPoint};
use crate::prepare::prepare_vocabulary;
use crate::results::{self, read_row, run_dir};
use crate::run::{run_point, Outcome, RunError};
use crate::SweepError;
use candle_core::Device;
use nn::device::DeviceSpec;
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command};
use std::time::Duration;

/// How [`run_local`] runs the points.
pub struct LocalOptions<'a> {
    /// Points trained at once on the CPU (1: in this process).
    pub jobs: usize,
    /// Only these plan rows (all when `None`).
    pub only: Option<Vec<usize>>,
    /// The command that runs one plan row in a worker process, on a GPU when given (used
    /// when `jobs > 1` or with `devices`).
    pub worker: &'a dyn Fn(usize, Option<DeviceSpec>) -> Command,
    /// GPUs the worker processes share (none: workers on the CPU).
    pub devices: Vec<DeviceSpec>,
    /// Worker processes per GPU.
    pub jobs_per_device: usize,
    /// Points of at least this many parameters (N_nv + N_v) take a GPU alone.
    pub exclusive_params: u64,
    /// Where vocabularies are prepared and, without `devices`, points run in this process.
    pub device: &'a Device,
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

/// Prepare the token sets of every vocabulary that `points` use, on `device`.
pub fn prepare_all(
    plan: &IsoFlopPlan,
    runs: &Path,
    points: &[&PlanPoint],
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<(), SweepError> {
    for vocab in &plan.vocabularies {
        if points
            .iter()
            .any(|p| p.codebook == vocab.codebook && p.runnable())
        {
            prepare_vocabulary(plan, vocab, runs, device, log)?;
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
    prepare_all(plan, &runs, &todo, options.device, log)?;
    if options.devices.is_empty() && (options.jobs <= 1 || todo.len() <= 1) {
        for point in todo {
            match run_point(plan, &runs, point, options.device, log) {
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
    // From the folder's own plan: `plan` may be an older one that it extends.
    summary.rows = results::rebuild_tables(&runs, &read_adopted_plan(&runs)?)?.len();
    Ok(summary)
}

/// What one device (or the CPU) is running: how many workers, and whether one is large.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Load {
    /// Workers running there.
    pub running: usize,
    /// Whether one of them is a large run.
    pub large: bool,
}

/// The slot a point may start on now, given each slot's load and the workers a slot takes:
/// the least loaded slot with room, where a large point needs an idle slot and a slot
/// running a large point takes nothing else; `None` when the point must wait.
pub fn pick_slot(large: bool, loads: &[Load], per_slot: usize) -> Option<usize> {
    loads
        .iter()
        .enumerate()
        .filter(|(_, l)| !l.large && l.running < per_slot && (!large || l.running == 0))
        .min_by_key(|(_, l)| l.running)
        .map(|(i, _)| i)
}

/// Run `todo` in worker processes: `options.jobs` at once on the CPU, or `jobs_per_device`
/// per GPU of `options.devices` (large points alone on theirs).
fn run_workers(
    runs: &Path,
    todo: Vec<&PlanPoint>,
    options: &LocalOptions,
    summary: &mut Summary,
    log: &dyn Fn(&str),
) -> Result<(), SweepError> {
    let gpus = !options.devices.is_empty();
    let (slots, per_slot) = if gpus {
        (options.devices.len(), options.jobs_per_device.max(1))
    } else {
        (1, options.jobs.max(1))
    };
    let threads = (available_threads() / (slots * per_slot)).max(1);
    log(&format!(
        "{} points in up to {} worker processes ({per_slot} on each of {}) of {threads} thread(s) each",
        todo.len(),
        slots * per_slot,
        if gpus {
            let names: Vec<String> = options.devices.iter().map(|d| d.to_string()).collect();
            names.join(", ")
        } else {
            "the CPU".into()
        }
    ));
    let large = |p: &PlanPoint| gpus && p.n_nv + p.n_v >= options.exclusive_params;
    let mut queue: Vec<&PlanPoint> = todo;
    let mut loads = vec![Load::default(); slots];
    let mut running: Vec<(&PlanPoint, usize, Child)> = Vec::new();
    loop {
        // Start, in plan order, every waiting point that has a slot now.
        let mut k = 0;
        while k < queue.len() {
            let Some(slot) = pick_slot(large(queue[k]), &loads, per_slot) else {
                k += 1;
                continue;
            };
            let point = queue.remove(k);
            let device = gpus.then(|| options.devices[slot]);
            let mut command = (options.worker)(point.index, device);
            command.env("RAYON_NUM_THREADS", threads.to_string());
            die_with_parent(&mut command);
            let child = command.spawn().map_err(|e| SweepError::Command {
                command: format!("{command:?}"),
                message: e.to_string(),
            })?;
            loads[slot].running += 1;
            loads[slot].large |= large(point);
            running.push((point, slot, child));
        }
        if running.is_empty() {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(100));
        let mut still = Vec::with_capacity(running.len());
        for (point, slot, mut child) in running {
            let status = child.try_wait().map_err(|e| SweepError::Command {
                command: format!("worker for {}", point.run_id),
                message: e.to_string(),
            })?;
            let Some(s) = status else {
                still.push((point, slot, child));
                continue;
            };
            loads[slot].running -= 1;
            if large(point) {
                loads[slot].large = false;
            }
            if s.success() {
                summary.trained += 1;
            } else {
                let error = worker_error(runs, &point.run_id)
                    .unwrap_or_else(|| format!("worker exited with {s}"));
                log(&format!("{}: failed: {error}", point.run_id));
                summary.failed.push((point.run_id.clone(), error));
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_runs_share_a_gpu_and_a_large_one_takes_an_idle_gpu_alone() {
        let idle = Load::default();
        let one = Load {
            running: 1,
            large: false,
        };
        let big = Load {
            running: 1,
            large: true,
        };
        // Small points go to the least loaded GPU with room.
        assert_eq!(pick_slot(false, &[one, idle], 4), Some(1));
        assert_eq!(pick_slot(false, &[one, one], 2), Some(0));
        let full = Load {
            running: 2,
            large: false,
        };
        assert_eq!(pick_slot(false, &[full, full], 2), None);
        // A large point waits for an idle GPU; nothing joins a GPU running a large point.
        assert_eq!(pick_slot(true, &[one, one], 4), None);
        assert_eq!(pick_slot(true, &[one, idle], 4), Some(1));
        assert_eq!(pick_slot(false, &[big], 4), None);
        assert_eq!(pick_slot(true, &[big, idle], 4), Some(1));
    }
}
