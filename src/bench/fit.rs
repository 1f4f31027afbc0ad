//! `motionscale bench fit`: the timing of a whole `fit` command on a Chinchilla-like stand-in
//! or on a given table (e.g. ScaleBench's data-constrained runs), beside SciPy's.

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

/// Arguments of `motionscale bench fit`.
#[derive(clap::Args, Debug)]
pub struct BenchFitArgs {
    /// Seed of the synthetic Chinchilla stand-in (252 runs on 9 IsoFLOP budgets, 1% noise).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Bootstrap resamples passed to `fit`.
    #[arg(long, default_value_t = 500)]
    pub bootstrap: usize,
    /// Start grid passed to `fit`.
    #[arg(long, default_value = "epoch")]
    pub starts_grid: String,
    /// Worker threads passed to `fit` (default: all cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Keep the CSV timed (DIR/chinchilla_standin.csv, or DIR/table.csv with --table) and the
    /// fit (DIR/fits/) here instead of a temporary folder.
    #[arg(long, value_name = "DIR")]
    pub keep: Option<PathBuf>,
    /// Also time the multi-start parametric fit alone, ours in this process and SciPy's
    /// (scripts/scipy_fit.py: L-BFGS-B from every start, as Epoch's replication), and print the ratio.
    #[arg(long)]
    pub reference: bool,
    /// Both fit every K-th start of the grid only (SciPy needs ~10 min for all 4,500 here).
    #[arg(long, default_value_t = 10)]
    pub reference_stride: usize,
    /// The SciPy reference script.
    #[arg(long, default_value = "scripts/scipy_fit.py")]
    pub reference_script: PathBuf,
    /// A table (CSV or Parquet) to time instead of the stand-in, e.g. ScaleBench's
    /// `data_constrained_scaling_law-train.parquet`; it is rewritten with Epoch's column names
    /// (C = 6·N·D) so that `fit` and SciPy read the same file.
    #[arg(long, value_name = "FILE")]
    pub table: Option<PathBuf>,
    /// With --table: its N column.
    #[arg(long, default_value = "params", requires = "table")]
    pub n_col: String,
    /// With --table: its D column.
    #[arg(long, default_value = "tokens", requires = "table")]
    pub d_col: String,
    /// With --table: its loss column.
    #[arg(long, default_value = "loss", requires = "table")]
    pub loss_col: String,
    /// Also write the figures as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// The figures of `bench fit` (its `--json`).
#[derive(Debug, Serialize, Deserialize)]
pub struct FitFigures {
    /// What was timed: "fit command".
    pub what: String,
    /// Runs in the table fitted.
    pub runs: usize,
    /// `--table`, or none for the Chinchilla stand-in.
    pub table: Option<PathBuf>,
    /// The start grid passed to `fit`.
    pub grid: String,
    /// Bootstrap resamples passed to `fit`.
    pub bootstrap: usize,
    /// Worker threads of `fit`.
    pub threads: usize,
    /// Wall seconds of the whole `fit` command.
    pub command_s: f64,
    /// With `--reference`: the multi-start parametric fit alone, ours beside SciPy's.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub parametric: Option<ParametricFigures>,
}

/// The multi-start parametric fit of L(N, D), ours in this process beside SciPy's.
#[derive(Debug, Serialize, Deserialize)]
pub struct ParametricFigures {
    /// Starts of Epoch's grid both fitted from (every `--reference-stride`-th).
    pub starts: usize,
    /// Our wall seconds.
    pub ours_s: f64,
    /// Our best fit.
    pub ours: LawFit,
    /// SciPy's run, as `scripts/scipy_fit.py` wrote it.
    pub reference: ScipyFit,
    /// SciPy's seconds over ours.
    pub ratio: f64,
}

/// The fitted L(N, D) = E + A/N^α + B/D^β and its objective.
#[derive(Debug, Serialize, Deserialize)]
pub struct LawFit {
    /// Irreducible loss E.
    #[serde(rename = "E")]
    pub e: f64,
    /// Coefficient A of the parameter term.
    #[serde(rename = "A")]
    pub a: f64,
    /// Coefficient B of the data term.
    #[serde(rename = "B")]
    pub b: f64,
    /// Parameter exponent.
    pub alpha: f64,
    /// Data exponent.
    pub beta: f64,
    /// The best start's objective (Huber loss of the log residuals).
    pub objective: f64,
}

/// The output of `scripts/scipy_fit.py`: L-BFGS-B from every start, its best fit and time.
#[derive(Debug, Serialize, Deserialize)]
pub struct ScipyFit {
    /// Runs it read.
    pub runs: usize,
    /// Starts it fitted from.
    pub starts: usize,
    /// Its gradient: "analytic" or "finite differences".
    pub jac: String,
    /// Wall seconds of all its starts.
    pub seconds: f64,
    /// Its best fit (the same keys as ours).
    #[serde(flatten)]
    pub fit: LawFit,
}

/// The runs timed: `--table`'s, or the seeded Chinchilla stand-in.
fn runs_of(args: &BenchFitArgs) -> Result<Vec<fits::synth::Run>> {
    let Some(path) = &args.table else {
        return Ok(fits::synth::chinchilla_standin(args.seed));
    };
    let t = fits::Table::read(path)?;
    let n = t.numbers(&args.n_col, "--n-col")?;
    let d = t.numbers(&args.d_col, "--d-col")?;
    let loss = t.numbers(&args.loss_col, "--loss-col")?;
    Ok((0..n.len())
        .map(|i| fits::synth::Run {
            n: n[i],
            d: d[i],
            c: 6.0 * n[i] * d[i],
            loss: loss[i],
        })
        .collect())
}

/// Target wall time of a full 4,500-start fit of ~250 runs on 2 cores.
const TARGET_SECONDS: f64 = 10.0;

/// `motionscale bench fit`: writes a Chinchilla-like stand-in CSV with Epoch's column names and
/// times the whole `motionscale fit` command on it (a child process: parse, fit, bootstrap,
/// plots, fits.json).
pub fn bench(args: BenchFitArgs) -> Result<ExitCode> {
    let tmp = tempfile::tempdir().context("creating a temporary folder")?;
    let dir = match &args.keep {
        Some(d) => {
            std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
            d.clone()
        }
        None => tmp.path().to_path_buf(),
    };
    let csv = dir.join(match args.table {
        Some(_) => "table.csv",
        None => "chinchilla_standin.csv",
    });
    let runs = runs_of(&args)?;
    fits::synth::write_epoch_csv(&csv, &runs)
        .with_context(|| format!("writing {}", csv.display()))?;
    let out = dir.join("fits");
    let exe = std::env::current_exe().context("locating the motionscale binary")?;
    let mut cmd = std::process::Command::new(exe);
    cmd.arg("fit")
        .arg("--results")
        .arg(&csv)
        .args(["--n-col", "Model Size", "--d-col", "Training Tokens"])
        .args(["--c-col", "Training FLOP", "--loss-col", "loss"])
        .args(["--starts-grid", &args.starts_grid])
        .args(["--bootstrap", &args.bootstrap.to_string()])
        .arg("--out")
        .arg(&out);
    if let Some(w) = args.workers {
        cmd.args(["--workers", &w.to_string()]);
    }
    let t0 = Instant::now();
    let output = cmd.output().context("running motionscale fit")?;
    let secs = t0.elapsed().as_secs_f64();
    print!("{}", String::from_utf8_lossy(&output.stdout));
    if !output.status.success() {
        bail!(
            "motionscale fit failed: {}",
            String::from_utf8_lossy(&output.stderr)
        );
    }
    let threads = args
        .workers
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    println!(
        "bench fit: {} runs of {}, grid {:?}, {} bootstrap resamples, {threads} threads: whole command {secs:.2} s (target < {TARGET_SECONDS} s on 2 cores: {})",
        runs.len(),
        args.table.as_ref().map_or("the Chinchilla stand-in".into(), |p| p.display().to_string()),
        args.starts_grid,
        args.bootstrap,
        if secs < TARGET_SECONDS { "met" } else { "MISSED" }
    );
    let parametric = match args.reference {
        true => Some(parametric_beside_scipy(&args, &csv, &runs)?),
        false => None,
    };
    let figures = FitFigures {
        what: "fit command".into(),
        runs: runs.len(),
        table: args.table.clone(),
        grid: args.starts_grid.clone(),
        bootstrap: args.bootstrap,
        threads,
        command_s: secs,
        parametric,
    };
    super::write_json(args.json.as_ref(), &figures)?;
    Ok(ExitCode::SUCCESS)
}

/// Our multi-start fit of L(N, D) on `runs` (in this process, all threads) and SciPy's on the
/// same CSV, one after the other; prints both, their fitted exponents and the ratio.
fn parametric_beside_scipy(
    args: &BenchFitArgs,
    csv: &std::path::Path,
    runs: &[fits::synth::Run],
) -> Result<ParametricFigures> {
    use fits::parametric::{multi_start, natural, LogRuns, StartGrid};
    let column = |f: fn(&fits::synth::Run) -> f64| runs.iter().map(f).collect::<Vec<_>>();
    let log_runs = LogRuns::new(&column(|r| r.n), &column(|r| r.d), &column(|r| r.loss));
    let starts: Vec<[f64; 5]> = StartGrid::epoch()
        .points()
        .into_iter()
        .step_by(args.reference_stride.max(1))
        .collect();
    let t0 = Instant::now();
    let fit = multi_start(&log_runs, 1e-3, &starts, &Default::default())?;
    let ours = t0.elapsed().as_secs_f64();
    let [e, a, b, alpha, beta] = natural(&fit.best().x);
    let csv_arg = csv.to_string_lossy();
    let stride = args.reference_stride.max(1).to_string();
    let flags = ["--results", &csv_arg, "--stride", &stride];
    let theirs: ScipyFit = super::run_reference(&args.reference_script, &flags)?;
    let scipy_s = theirs.seconds;
    println!(
        "parametric fit, {} starts of Epoch's grid: ours {ours:.2} s (α {alpha:.4}, β {beta:.4}, E {e:.4}); SciPy L-BFGS-B {scipy_s:.1} s (α {:.4}, β {:.4}, E {:.4}) → ratio {:.0}×",
        starts.len(),
        theirs.fit.alpha,
        theirs.fit.beta,
        theirs.fit.e,
        scipy_s / ours
    );
    Ok(ParametricFigures {
        starts: starts.len(),
        ours_s: ours,
        ours: LawFit {
            e,
            a,
            b,
            alpha,
            beta,
            objective: fit.best().f,
        },
        reference: theirs,
        ratio: scipy_s / ours,
    })
}
