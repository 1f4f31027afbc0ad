//! `motionscale sweep plan|run|status|submit|collect`: IsoFLOP sweeps of the prefix LM
//! (the `sweeps` crate), locally or on Slurm.

use crate::plan_args::PlanArgs;
use anyhow::{Context, Result};
use experiments::local::{self, LocalOptions};
use experiments::plan;
use experiments::slurm::{self, SlurmOptions};
use experiments::status::PointState;
use experiments::IsoFlopPlan;
use std::path::PathBuf;
use std::process::{Command, ExitCode};
use std::time::Duration;

/// `motionscale sweep plan`.
pub fn plan_cmd(args: PlanArgs) -> Result<ExitCode> {
    let plan = match args.next {
        Some(k) => crate::planner_cmd::next_plan(&args, k)?,
        None => plan::plan(&args.request()?)?,
    };
    plan.write(&args.out)?;
    println!(
        "{:>4}  {:<36} {:>9} {:>10} {:>6} {:>10} {:>9} {:>12} {:>7}  flags",
        "row", "run", "C", "model", "V", "N_nv", "N_v", "D", "epochs"
    );
    for p in &plan.points {
        let flags: Vec<&str> = p.flags.iter().map(|f| f.as_str()).collect();
        println!(
            "{:>4}  {:<36} {:>9.2e} {:>10} {:>6} {:>10} {:>9} {:>12} {:>7.2}  {}",
            p.index,
            p.run_id,
            p.budget,
            p.model,
            p.codebook,
            p.n_nv,
            p.n_v,
            p.tokens,
            p.epochs,
            flags.join(",")
        );
    }
    for v in &plan.vocabularies {
        println!(
            "vocabulary {} ({} codes): {} train clips, {} train tokens per epoch",
            v.codebook, v.codebook_size, v.train_clips, v.train_tokens
        );
    }
    for d in &plan.data {
        println!(
            "data {}: {} train clips, {:.2} h ({:.0}% synthetic), seed {}",
            d.name,
            d.train_clips,
            d.hours,
            100.0 * d.synth_hours / d.hours,
            d.seed
        );
    }
    for c in &plan.centres {
        println!(
            "budget {:.3e}: centred on N_opt = {:.3e} from {}",
            c.budget, c.n_opt, c.source
        );
    }
    for w in &plan.warnings {
        println!("warning: {w}");
    }
    let skipped = plan.points.iter().filter(|p| !p.runnable()).count();
    println!(
        "{} points ({} below one step, not run) → {}",
        plan.points.len(),
        skipped,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale sweep run`.
#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Plan file (`sweep plan`).
    #[arg(long)]
    pub plan: PathBuf,
    /// Sweep folder: one folder per run, results.csv / results.parquet.
    #[arg(long)]
    pub out: PathBuf,
    /// Points trained at once, each in a worker process with cores / N threads.
    #[arg(long, default_value_t = 1)]
    pub jobs: usize,
    /// Run only this plan row (the Slurm array task id).
    #[arg(long)]
    pub only_index: Option<usize>,
    /// Only train / tokenize the vocabularies, then stop.
    #[arg(long, conflicts_with = "only_index")]
    pub prepare_only: bool,
    /// Where this process prepares vocabularies and trains (without --devices).
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// GPUs the points are spread over, worker processes sharing each (e.g. cuda:0,cuda:1).
    #[arg(long, value_delimiter = ',', conflicts_with_all = ["only_index", "jobs"])]
    pub devices: Vec<nn::device::DeviceSpec>,
    /// Worker processes per GPU of --devices (small runs leave a GPU mostly idle).
    #[arg(long, default_value_t = 1)]
    pub jobs_per_device: usize,
    /// Points of at least this many parameters (N_nv + N_v) take a GPU alone.
    #[arg(long, default_value_t = 50_000_000)]
    pub exclusive_params: u64,
}

fn log_line(line: &str) {
    eprintln!("sweep: {line}");
}

/// `motionscale sweep run`.
pub fn run_cmd(args: RunArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let plan = IsoFlopPlan::read(&args.plan)?;
    if args.prepare_only {
        let runs = plan::adopt_plan(&plan, &args.out)?;
        let points = local::select(&plan, None)?;
        local::prepare_all(&plan, &runs, &points, &args.device.open()?, &log_line)?;
        println!("vocabularies ready in {}", runs.display());
        return Ok(ExitCode::SUCCESS);
    }
    let exe = std::env::current_exe().context("locating the motionscale executable")?;
    let runs = std::path::absolute(&args.out)?;
    let plan_file = runs.join(plan::PLAN_FILE);
    let device = args.device.open()?;
    let worker = |index: usize, gpu: Option<nn::device::DeviceSpec>| {
        let mut c = Command::new(&exe);
        c.arg("sweep")
            .arg("run")
            .arg("--plan")
            .arg(&plan_file)
            .arg("--out")
            .arg(&runs)
            .arg("--only-index")
            .arg(index.to_string())
            .arg("--device")
            .arg(gpu.unwrap_or_else(|| args.device.spec()).to_string());
        c
    };
    let options = LocalOptions {
        jobs: args.jobs.max(1),
        only: args.only_index.map(|i| vec![i]),
        worker: &worker,
        devices: args.devices.clone(),
        jobs_per_device: args.jobs_per_device,
        exclusive_params: args.exclusive_params,
        device: &device,
    };
    let started = std::time::Instant::now();
    let summary = local::run_local(&plan, &runs, &options, &log_line)?;
    println!(
        "{} trained, {} already done, {} failed, {} not runnable; results.csv has {} rows ({:.1} s) → {}",
        summary.trained,
        summary.already_done,
        summary.failed.len(),
        summary.not_runnable.len(),
        summary.rows,
        started.elapsed().as_secs_f64(),
        runs.display()
    );
    for (id, error) in &summary.failed {
        eprintln!("failed: {id}: {error}");
    }
    Ok(if summary.failed.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// Arguments of `motionscale sweep status`.
#[derive(clap::Args, Debug)]
pub struct StatusArgs {
    /// Sweep folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// `motionscale sweep status`.
pub fn status_cmd(args: StatusArgs) -> Result<ExitCode> {
    let plan = plan::read_adopted_plan(&args.out)?;
    let points = experiments::status::status(&plan, &args.out)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&points)?);
        return Ok(ExitCode::SUCCESS);
    }
    for p in &points {
        println!(
            "{:>4}  {:<26} {:<12} {:>10}  {}",
            p.index,
            p.run_id,
            p.state.as_str(),
            p.step.map(|s| format!("step {s}")).unwrap_or_default(),
            p.detail.as_deref().unwrap_or("")
        );
    }
    let count = |s: PointState| points.iter().filter(|p| p.state == s).count();
    println!(
        "{} points: {} done, {} running, {} failed, {} pending, {} not runnable",
        points.len(),
        count(PointState::Done),
        count(PointState::Running),
        count(PointState::Failed),
        count(PointState::Pending),
        count(PointState::NotRunnable)
    );
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale sweep submit`.
#[derive(clap::Args, Debug)]
pub struct SubmitArgs {
    /// Plan file (`sweep plan`).
    #[arg(long)]
    pub plan: PathBuf,
    /// Sweep folder (must be visible to the compute nodes).
    #[arg(long)]
    pub out: PathBuf,
    /// Scheduler.
    #[arg(long, value_parser = ["slurm"])]
    pub backend: String,
    /// At most this many array tasks at once.
    #[arg(long)]
    pub array_throttle: Option<usize>,
    /// Partition.
    #[arg(long)]
    pub partition: Option<String>,
    /// CPUs per task (RAYON_NUM_THREADS in the task).
    #[arg(long, default_value_t = 1)]
    pub cpus_per_task: usize,
    /// GPUs per training task (`#SBATCH --gpus-per-task`; the task trains on it). 0: CPU.
    #[arg(long, default_value_t = 0)]
    pub gpus_per_task: usize,
    /// Time limit per job, e.g. 2:00:00.
    #[arg(long)]
    pub time: Option<String>,
    /// Extra argument of the fit job's `motionscale fit` (repeat for several).
    #[arg(long = "fit-arg", allow_hyphen_values = true)]
    pub fit_args: Vec<String>,
    /// Wait for every job to finish and fail unless all COMPLETED.
    #[arg(long)]
    pub wait: bool,
    /// Longest wait in seconds.
    #[arg(long, default_value_t = 86_400)]
    pub timeout: u64,
}

/// `motionscale sweep submit`.
pub fn submit_cmd(args: SubmitArgs) -> Result<ExitCode> {
    let plan = IsoFlopPlan::read(&args.plan)?;
    let options = SlurmOptions {
        exe: std::env::current_exe().context("locating the motionscale executable")?,
        array_throttle: args.array_throttle,
        partition: args.partition.clone(),
        cpus_per_task: args.cpus_per_task.max(1),
        gpus_per_task: args.gpus_per_task,
        time: args.time.clone(),
        fit_args: args.fit_args.clone(),
    };
    let submission = slurm::submit(&plan, &args.out, &options)?;
    if let Some(job) = &submission.prepare {
        println!("prepare job {job}");
    }
    if let Some(job) = &submission.array {
        println!(
            "array job {job}: plan rows {} ({} tasks)",
            slurm::array_spec(&submission.rows),
            submission.rows.len()
        );
    }
    println!(
        "fit job {} (afterok) → {}",
        submission.fit,
        args.out.join(slurm::FITS_DIR).display()
    );
    if args.wait {
        let started = std::time::Instant::now();
        slurm::wait(&submission, Duration::from_secs(args.timeout))?;
        println!(
            "all {} jobs COMPLETED in {:.1} s",
            submission.jobs().len(),
            started.elapsed().as_secs_f64()
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale sweep collect`.
#[derive(clap::Args, Debug)]
pub struct CollectArgs {
    /// Sweep folder.
    #[arg(long)]
    pub out: PathBuf,
    /// First select each finished run's checkpoint again from its train/evals.jsonl by
    /// today's rule (a run on one data source on that source's validation clips) and rewrite
    /// the result.json files it changes (rows of runs finished before the rule).
    #[arg(long)]
    pub reselect: bool,
}

/// `motionscale sweep collect`: rebuild results.csv / results.parquet from every run's
/// result.json; exit 2 when some runnable points have none.
pub fn collect_cmd(args: CollectArgs) -> Result<ExitCode> {
    if args.reselect {
        let plan = plan::read_adopted_plan(&args.out)?;
        let changed = experiments::run::reselect(&plan, &args.out)?;
        for c in &changed {
            println!(
                "{}: best step {} → {}, test CE {:.4} → {:.4} (captured {:.4} → {:.4})",
                c.after.run_id,
                c.before.best_step,
                c.after.best_step,
                c.before.best_test_loss,
                c.after.best_test_loss,
                c.before.best_real_test_loss,
                c.after.best_real_test_loss
            );
        }
        println!("{} runs re-selected", changed.len());
    }
    let (rows, missing) = local::collect(&args.out)?;
    println!(
        "{} rows → {}, {}",
        rows.len(),
        args.out.join("results.csv").display(),
        args.out.join("results.parquet").display()
    );
    if missing.is_empty() {
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!(
        "{} points have no result: {}",
        missing.len(),
        missing.join(", ")
    );
    Ok(ExitCode::from(2))
}
