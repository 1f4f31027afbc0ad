//! The Slurm backend: a job array whose task `SLURM_ARRAY_TASK_ID` runs plan row
//! `SLURM_ARRAY_TASK_ID` (`sweep run --only-index`), preceded by a job that prepares the
//! vocabularies when the sweep trains or tokenizes any, and followed by a job that collects
//! the results and fits them, each chained with `--dependency=afterok:<previous>`.
//!
//! ```text
//! RUNS/slurm/prepare.sbatch   sweep run --prepare-only           (only when needed)
//! RUNS/slurm/array.sbatch     #SBATCH --array=<missing rows>%<throttle>
//! RUNS/slurm/fit.sbatch       sweep collect, then motionscale fit → RUNS/fits/
//! RUNS/slurm/jobs.json        the submitted job ids
//! RUNS/slurm/logs/            one log per job / array task
//! ```
//!
//! Only the points not yet done go into the array, so submitting again after a failure
//! finishes the sweep. Every task exports `RAYON_NUM_THREADS=$SLURM_CPUS_PER_TASK`.

use crate::plan::{adopt_plan, IsoFlopPlan, PLAN_FILE};
use crate::results::read_row;
use crate::SweepError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// Folder of the fit job's output inside the sweep folder.
pub const FITS_DIR: &str = "fits";

/// What to submit and how.
#[derive(Debug, Clone)]
pub struct SlurmOptions {
    /// The `motionscale` executable the jobs run (absolute).
    pub exe: PathBuf,
    /// At most this many array tasks at once (`%N`).
    pub array_throttle: Option<usize>,
    /// Partition (default: the cluster's default).
    pub partition: Option<String>,
    /// CPUs per task.
    pub cpus_per_task: usize,
    /// GPUs per training task (0: the tasks run on the CPU); the tasks then train on the
    /// GPU Slurm hands them (`--device cuda`: Slurm's `CUDA_VISIBLE_DEVICES` makes it
    /// `cuda:0`).
    pub gpus_per_task: usize,
    /// Time limit per job (`--time`), e.g. `1:00:00`.
    pub time: Option<String>,
    /// Extra arguments of `motionscale fit`.
    pub fit_args: Vec<String>,
}

/// The submitted jobs (`RUNS/slurm/jobs.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Submission {
    /// Vocabulary preparation job, when one was needed.
    pub prepare: Option<String>,
    /// Array job, when any point was missing.
    pub array: Option<String>,
    /// Plan rows in the array.
    pub rows: Vec<usize>,
    /// Collect-and-fit job.
    pub fit: String,
}

impl Submission {
    /// Every job id, in submission order.
    pub fn jobs(&self) -> Vec<&str> {
        self.prepare
            .iter()
            .chain(&self.array)
            .chain(std::iter::once(&self.fit))
            .map(String::as_str)
            .collect()
    }
}

/// `rows` as a Slurm array range list: `0-3,5,7-9`.
pub fn array_spec(rows: &[usize]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < rows.len() {
        let start = rows[i];
        while i + 1 < rows.len() && rows[i + 1] == rows[i] + 1 {
            i += 1;
        }
        parts.push(if rows[i] == start {
            start.to_string()
        } else {
            format!("{start}-{}", rows[i])
        });
        i += 1;
    }
    parts.join(",")
}

/// `s` quoted for a POSIX shell.
pub fn shell_quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

fn path_arg(p: &Path) -> String {
    shell_quote(&p.to_string_lossy())
}

/// An sbatch script: `#SBATCH` lines, the thread cap, then `body`.
fn script(name: &str, log: &str, options: &SlurmOptions, extra: &[String], body: &str) -> String {
    let mut lines = vec![
        "#!/bin/bash".to_string(),
        format!("#SBATCH --job-name={name}"),
        format!("#SBATCH --output={log}"),
        format!("#SBATCH --cpus-per-task={}", options.cpus_per_task),
    ];
    lines.extend(
        options
            .partition
            .iter()
            .map(|p| format!("#SBATCH --partition={p}")),
    );
    lines.extend(options.time.iter().map(|t| format!("#SBATCH --time={t}")));
    lines.extend(extra.iter().cloned());
    lines.push("# Written by `motionscale sweep submit`.".into());
    lines.push("set -euo pipefail".into());
    lines.push(
        "# One worker per task: cap rayon and candle's CPU threads at the allocation.".into(),
    );
    lines.push("export RAYON_NUM_THREADS=\"${SLURM_CPUS_PER_TASK:-1}\"".into());
    lines.push(body.to_string());
    lines.join("\n") + "\n"
}

/// The `#SBATCH` lines and the `sweep run` device flag of a task with `gpus` GPUs (none: the
/// CPU, the binary's default device).
fn gpu_request(gpus: usize) -> (Vec<String>, &'static str) {
    match gpus {
        0 => (Vec::new(), ""),
        n => (
            vec![format!("#SBATCH --gpus-per-task={n}")],
            " --device cuda",
        ),
    }
}

/// The scripts of a submission, written into `RUNS/slurm/`.
#[derive(Debug, Clone, PartialEq)]
pub struct Scripts {
    /// `prepare.sbatch`, when a vocabulary must be trained or tokenized.
    pub prepare: Option<PathBuf>,
    /// `array.sbatch` and its rows, when any point is missing.
    pub array: Option<(PathBuf, Vec<usize>)>,
    /// `fit.sbatch`.
    pub fit: PathBuf,
}

/// Write the sbatch scripts for the points of `plan` not yet done in `runs` (absolute).
pub fn write_scripts(
    plan: &IsoFlopPlan,
    runs: &Path,
    options: &SlurmOptions,
) -> Result<Scripts, SweepError> {
    let dir = runs.join("slurm");
    let logs = dir.join("logs");
    std::fs::create_dir_all(&logs).map_err(|e| SweepError::io(&logs, e))?;
    let exe = path_arg(&options.exe);
    let plan_arg = path_arg(&runs.join(PLAN_FILE));
    let runs_arg = path_arg(runs);
    let write = |name: &str, text: String| -> Result<PathBuf, SweepError> {
        let path = dir.join(name);
        motionscale_core::write_atomic(&path, text.as_bytes())
            .map_err(|e| SweepError::io(&path, e))?;
        Ok(path)
    };
    let mut rows = Vec::new();
    for point in plan.points.iter().filter(|p| p.runnable()) {
        if read_row(runs, &point.run_id)?.is_none() {
            rows.push(point.index);
        }
    }
    let needs_prepare = plan.vocabularies.iter().any(|v| {
        rows.iter().any(|&r| plan.points[r].codebook == v.codebook)
            && !v
                .tokens_dir(runs)
                .join(tokenizer::tokens::MANIFEST)
                .is_file()
    });
    let (gpu_lines, device) = gpu_request(options.gpus_per_task);
    let prepare = needs_prepare
        .then(|| {
            let body = format!(
                "exec {exe} sweep run --plan {plan_arg} --out {runs_arg} --prepare-only{device}"
            );
            let log = logs.join("prepare-%j.log");
            write(
                "prepare.sbatch",
                script(
                    "sweep-prepare",
                    &log.to_string_lossy(),
                    options,
                    &gpu_lines,
                    &body,
                ),
            )
        })
        .transpose()?;
    let array = (!rows.is_empty())
        .then(|| {
            let throttle = options.array_throttle.map(|t| format!("%{t}")).unwrap_or_default();
            let mut extra = vec![
                "# Array task ids are plan rows (the points not done at submission).".to_string(),
                format!("#SBATCH --array={}{throttle}", array_spec(&rows)),
            ];
            extra.extend(gpu_lines.iter().cloned());
            let body = format!(
                "exec {exe} sweep run --plan {plan_arg} --out {runs_arg} --only-index \"$SLURM_ARRAY_TASK_ID\"{device}"
            );
            let log = logs.join("run-%A_%a.log");
            let path = write("array.sbatch", script("sweep-runs", &log.to_string_lossy(), options, &extra, &body))?;
            Ok::<_, SweepError>((path, rows.clone()))
        })
        .transpose()?;
    let fit_args: Vec<String> = options.fit_args.iter().map(|a| shell_quote(a)).collect();
    let body = format!(
        "{exe} sweep collect --out {runs_arg}\nexec {exe} fit --results {} --out {} {}",
        path_arg(&runs.join("results.parquet")),
        path_arg(&runs.join(FITS_DIR)),
        fit_args.join(" ")
    );
    let fit = write(
        "fit.sbatch",
        script(
            "sweep-fit",
            &logs.join("fit-%j.log").to_string_lossy(),
            options,
            &[],
            body.trim_end(),
        ),
    )?;
    Ok(Scripts {
        prepare,
        array,
        fit,
    })
}

/// Run `program args…` and return its trimmed stdout, or its stderr as the error.
fn command_output(program: &str, args: &[String]) -> Result<String, SweepError> {
    let line = format!("{program} {}", args.join(" "));
    let out = Command::new(program)
        .args(args)
        .output()
        .map_err(|e| SweepError::Command {
            command: line.clone(),
            message: e.to_string(),
        })?;
    if !out.status.success() {
        return Err(SweepError::Command {
            command: line,
            message: format!(
                "{}: {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// `sbatch --parsable [--dependency=afterok:<after>] script`: the job id.
fn sbatch(script: &Path, after: Option<&str>) -> Result<String, SweepError> {
    let mut args = vec!["--parsable".to_string()];
    if let Some(job) = after {
        args.push(format!("--dependency=afterok:{job}"));
    }
    args.push(script.to_string_lossy().into_owned());
    let out = command_output("sbatch", &args)?;
    // --parsable prints `jobid` or `jobid;cluster`.
    Ok(out.split(';').next().unwrap_or_default().to_string())
}

/// Adopt `plan` into `runs`, write the scripts and submit them, chained with afterok;
/// records the job ids in `RUNS/slurm/jobs.json`.
pub fn submit(
    plan: &IsoFlopPlan,
    runs: &Path,
    options: &SlurmOptions,
) -> Result<Submission, SweepError> {
    let runs = adopt_plan(plan, runs)?;
    let scripts = write_scripts(plan, &runs, options)?;
    let prepare = scripts
        .prepare
        .as_deref()
        .map(|s| sbatch(s, None))
        .transpose()?;
    let array = scripts
        .array
        .as_ref()
        .map(|(s, _)| sbatch(s, prepare.as_deref()))
        .transpose()?;
    let fit = sbatch(&scripts.fit, array.as_deref().or(prepare.as_deref()))?;
    let submission = Submission {
        prepare,
        array,
        rows: scripts.array.map(|(_, rows)| rows).unwrap_or_default(),
        fit,
    };
    let path = runs.join("slurm").join("jobs.json");
    let text =
        serde_json::to_string_pretty(&submission).map_err(|e| SweepError::invalid(&path, e))?;
    motionscale_core::write_atomic(&path, text.as_bytes()).map_err(|e| SweepError::io(&path, e))?;
    Ok(submission)
}

/// Final states of a job's tasks from `scontrol -o show job` (e.g. `["COMPLETED"; 4]`).
pub fn job_states(job: &str) -> Result<Vec<String>, SweepError> {
    let out = command_output(
        "scontrol",
        &["-o".into(), "show".into(), "job".into(), job.into()],
    )?;
    Ok(out
        .lines()
        .filter_map(|l| {
            l.split_whitespace()
                .find_map(|f| f.strip_prefix("JobState="))
        })
        .map(String::from)
        .collect())
}

/// Wait until every job of `submission` has left the queue (squeue; there is no sacct
/// without slurmdbd), then check that all of them COMPLETED. Fails early when a job waits on
/// a dependency that can never be satisfied (an earlier job failed), and after `timeout`.
pub fn wait(submission: &Submission, timeout: Duration) -> Result<(), SweepError> {
    let jobs = submission.jobs().join(",");
    let started = Instant::now();
    loop {
        let queued = command_output(
            "squeue",
            &[
                "-h".into(),
                "-j".into(),
                jobs.clone(),
                "-o".into(),
                "%i %r".into(),
            ],
        )?;
        if queued.is_empty() {
            break;
        }
        if queued.contains("DependencyNeverSatisfied") {
            return Err(SweepError::Command {
                command: format!("squeue -j {jobs}"),
                message: format!("a job failed, its dependants can never start:\n{queued}"),
            });
        }
        if started.elapsed() > timeout {
            return Err(SweepError::Command {
                command: format!("squeue -j {jobs}"),
                message: format!("still queued after {} s:\n{queued}", timeout.as_secs()),
            });
        }
        std::thread::sleep(Duration::from_secs(1));
    }
    for job in submission.jobs() {
        let states = job_states(job)?;
        if states.is_empty() || states.iter().any(|s| s != "COMPLETED") {
            return Err(SweepError::Command {
                command: format!("scontrol show job {job}"),
                message: format!("job {job} ended in states {states:?}"),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_ranges_compress_consecutive_rows() {
        assert_eq!(array_spec(&[0, 1, 2, 3]), "0-3");
        assert_eq!(array_spec(&[0, 1, 2, 3, 5, 7, 8, 9]), "0-3,5,7-9");
        assert_eq!(array_spec(&[4]), "4");
        assert_eq!(array_spec(&[]), "");
    }

    #[test]
    fn a_gpu_task_asks_slurm_for_its_gpus_and_trains_on_them() {
        assert_eq!(gpu_request(0), (Vec::new(), ""));
        assert_eq!(
            gpu_request(2),
            (
                vec!["#SBATCH --gpus-per-task=2".to_string()],
                " --device cuda"
            )
        );
    }

    #[test]
    fn shell_quoting_survives_quotes_and_spaces() {
        assert_eq!(shell_quote("a b"), "'a b'");
        assert_eq!(shell_quote("it's"), r"'it'\''s'");
    }
}
