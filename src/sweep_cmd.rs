//! `motionscale sweep plan|run|status|submit|collect`: IsoFLOP sweeps of the prefix LM
//! (the `sweeps` crate), locally or on Slurm.

use crate::tokenizer_cmd::TrainFlags;
use anyhow::{bail, Context, Result};
use clap::Parser;
use experiments::data_ladder::{self, DataSource};
use experiments::local::{self, LocalOptions};
use experiments::plan::{self, PlanRequest, TrainSettings, VocabSource};
use experiments::slurm::{self, SlurmOptions};
use experiments::status::PointState;
use experiments::IsoFlopPlan;
use lm::train::Hyperparams;
use std::path::PathBuf;
use std::process::{Command, ExitCode};
use std::time::Duration;

/// Arguments of `motionscale sweep plan`.
#[derive(clap::Args, Debug)]
pub struct PlanArgs {
    /// Corpus with caption embeddings (`embed-text`); tokenizers the plan trains learn on it.
    #[arg(long)]
    pub corpus: PathBuf,
    /// Compute budgets C in FLOPs (6·N·D convention), comma-separated.
    #[arg(long, value_delimiter = ',', required_unless_present = "extend")]
    pub budgets: Vec<f64>,
    /// Models, comma-separated: presets, `cpu` (the CPU ladder), `scamo` (ScaMo's six sizes)
    /// or WIDTHxLAYERS[xHEADS] shapes (heads of width 64 by default).
    #[arg(long, value_delimiter = ',', required_unless_present = "extend")]
    pub models: Vec<String>,
    /// Nominal codebook sizes, comma-separated.
    #[arg(long, value_delimiter = ',', required_unless_present = "extend")]
    pub vocabs: Vec<usize>,
    /// Trained tokenizers to use: `V=DIR,…` (tokenized into RUNS/tokens/V).
    #[arg(long, value_delimiter = ',')]
    pub tokenizers: Vec<String>,
    /// Token sets to use as they are: `V=DIR,…`.
    #[arg(long, value_delimiter = ',')]
    pub token_sets: Vec<String>,
    /// Quantizer of the tokenizers the plan trains (vocabularies given neither way).
    #[arg(long, default_value = "fsq", value_parser = ["fsq", "vq"])]
    pub quantizer: String,
    /// `tokenizer train` flags of the tokenizers the plan trains, e.g.
    /// "--width 64 --batch 64 --steps 1200 --lr 5e-4 --grad-clip 1".
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    pub tokenizer_flags: String,
    /// Text encoder id of the caption embeddings (default: the corpus's only one).
    #[arg(long)]
    pub text_emb: Option<String>,
    /// Optimisation settings of every point.
    #[command(flatten)]
    pub hyper: Hyperparams,
    /// Checkpoint and evaluate the test split every N steps (and at the end).
    #[arg(long, default_value_t = TrainSettings::default().checkpoint_every)]
    pub checkpoint_every: u64,
    /// Arithmetic of every point: f32, or bf16 products from f32 masters (on a GPU).
    #[arg(long, default_value = "f32", value_name = "f32|bf16")]
    pub precision: nn::device::Precision,
    /// An earlier fit (`fit`'s fits.json, e.g. of a pilot sweep): each budget then gets the
    /// --sizes-per-budget models of --models nearest its predicted N_opt (the fit's parabola at
    /// that budget, else its N_opt ∝ C^b law, else its parametric L(N, D)), with a warning where
    /// they do not bracket it.
    #[arg(long, value_name = "FITS_JSON")]
    pub fits: Option<PathBuf>,
    /// Models per budget when centring on --fits.
    #[arg(long, default_value_t = 6, requires = "fits")]
    pub sizes_per_budget: usize,
    /// Flag points that take more than E epochs of the train split (`above-max-epochs`).
    #[arg(long, value_name = "E")]
    pub max_epochs: Option<f64>,
    /// Drop the points above --max-epochs instead of flagging them (listed as warnings).
    #[arg(long, requires = "max_epochs")]
    pub drop_above_max_epochs: bool,
    /// An earlier plan to extend: its points come first, unchanged, and a sweep folder that
    /// ran it adopts the new plan (give the same corpus, settings and vocabulary folders).
    #[arg(long, value_name = "PLAN")]
    pub extend: Option<PathBuf>,
    /// Run ids to repeat with each of --seeds (new points `<run_id>-s<seed>`), e.g. each
    /// budget's best point, for the run-to-run noise.
    #[arg(long, value_delimiter = ',', requires = "seeds")]
    pub repeat: Vec<String>,
    /// Training seeds of the --repeat points, comma-separated.
    #[arg(long, value_delimiter = ',', requires = "repeat")]
    pub seeds: Vec<u64>,
    /// The unique-data axis: every point at each fraction of the train hours, e.g.
    /// `1/8,1/4,1/2,1` (nested subsets drawn by source clip, mirrors and segments together;
    /// val and test stay whole; run ids end in `-d<source>-<fraction>`).
    #[arg(long, value_delimiter = ',', value_parser = data_ladder::parse_fraction)]
    pub data_fractions: Vec<f64>,
    /// The clips the --data-fractions draw from: real (captured), synth or all.
    #[arg(long, default_value = "all", requires = "data_fractions")]
    pub data_source: DataSource,
    /// Seed of the clip order of the --data-fractions (recorded in the plan).
    #[arg(long, default_value_t = 0, requires = "data_fractions")]
    pub data_seed: u64,
    /// Propose the K runs (from --budgets × --models × --vocabs) that most narrow the
    /// --target's interval at --target-budget per FLOP, given the runs of the --extend plan
    /// trained so far (`sweep replay` judges the policy); the output extends that plan.
    #[arg(long, value_name = "K", requires_all = ["target_budget", "fits", "extend"])]
    pub next: Option<usize>,
    /// With --next: the budget C* whose target is narrowed (above every trained budget).
    #[arg(long, requires = "next")]
    pub target_budget: Option<f64>,
    /// With --next: n_opt (log10 N_opt), loss (at N_opt), or hour_value (the loss change of
    /// +1 h of captured motion at --target-budget; needs a `fit --repeated-data` fit).
    #[arg(long, default_value = "n_opt", value_parser = fits::planner::Goal::parse)]
    pub target: fits::planner::Goal,
    /// With --next --target hour_value: the corpus's hours per source (default: the plan's
    /// full-data subset).
    #[arg(long, value_name = "real=H,synth=H", value_parser = crate::fit::parse_hours, requires = "next")]
    pub hours: Option<fits::data_value::Hours>,
    /// With --next: the most FLOPs the proposed runs may cost together.
    #[arg(long, requires = "next")]
    pub max_compute: Option<f64>,
    /// With --next: the results table of the trained runs (default: the table --fits read).
    #[arg(long, requires = "next")]
    pub results: Option<PathBuf>,
    /// Output plan file (.toml).
    #[arg(long)]
    pub out: PathBuf,
}

/// `tokenizer train` flags given as one string.
#[derive(Parser, Debug)]
#[command(no_binary_name = true)]
struct TokenizerFlagsLine {
    #[command(flatten)]
    flags: TrainFlags,
}

/// `V=DIR` pairs.
fn vocab_dirs(pairs: &[String], flag: &str) -> Result<Vec<(usize, PathBuf)>> {
    pairs
        .iter()
        .map(|p| {
            let (v, dir) = p
                .split_once('=')
                .with_context(|| format!("--{flag} {p:?}: want V=DIR"))?;
            let v = v
                .parse()
                .with_context(|| format!("--{flag} {p:?}: {v:?} is not a codebook size"))?;
            Ok((v, PathBuf::from(dir)))
        })
        .collect()
}

impl PlanArgs {
    fn settings(&self) -> TrainSettings {
        TrainSettings {
            hyper: self.hyper.clone(),
            checkpoint_every: self.checkpoint_every,
            precision: self.precision,
        }
    }

    pub(crate) fn request(&self) -> Result<PlanRequest> {
        let flags = TokenizerFlagsLine::try_parse_from(self.tokenizer_flags.split_whitespace())
            .with_context(|| format!("--tokenizer-flags {:?}", self.tokenizer_flags))?
            .flags;
        let tokenizers = vocab_dirs(&self.tokenizers, "tokenizers")?;
        let token_sets = vocab_dirs(&self.token_sets, "token-sets")?;
        for (v, _) in tokenizers.iter().chain(&token_sets) {
            if !self.vocabs.contains(v) {
                bail!("vocabulary {v} is given a folder but is not in --vocabs");
            }
        }
        let mut vocabularies = Vec::new();
        for &v in &self.vocabs {
            let given = |list: &[(usize, PathBuf)]| {
                list.iter().find(|(k, _)| *k == v).map(|(_, d)| d.clone())
            };
            let source = match (given(&token_sets), given(&tokenizers)) {
                (Some(_), Some(_)) => {
                    bail!("vocabulary {v}: give a token set or a tokenizer, not both")
                }
                (Some(dir), None) => VocabSource::TokenSet { dir },
                (None, Some(dir)) => VocabSource::Tokenizer { dir },
                (None, None) => VocabSource::Train {
                    tokenizer: Box::new(flags.tokenizer_config(&self.quantizer, v)?),
                    train: Box::new(flags.train_config()),
                },
            };
            vocabularies.push((v, source));
        }
        Ok(PlanRequest {
            corpus: self.corpus.clone(),
            text_encoder: self.text_emb.clone(),
            budgets: self.budgets.clone(),
            models: self.models.clone(),
            vocabularies,
            train: self.settings(),
            centring: match &self.fits {
                None => None,
                Some(path) => Some(plan::Centring {
                    fits: serde_json::from_slice(
                        &std::fs::read(path).with_context(|| path.display().to_string())?,
                    )
                    .with_context(|| {
                        format!("{}: not a fits.json of `motionscale fit`", path.display())
                    })?,
                    sizes: self.sizes_per_budget,
                }),
            },
            max_epochs: self.max_epochs.map(|epochs| plan::EpochLimit {
                epochs,
                drop: self.drop_above_max_epochs,
            }),
            extend: self.extend.as_deref().map(IsoFlopPlan::read).transpose()?,
            repeat: self.repeat.clone(),
            repeat_seeds: self.seeds.clone(),
            data_fractions: self.data_fractions.clone(),
            data_source: self.data_source,
            data_seed: self.data_seed,
            only: Vec::new(),
        })
    }
}

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
