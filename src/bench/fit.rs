//! `motionscale bench fit`: the timing of a whole `fit` command on a Chinchilla-like stand-in.

use anyhow::{bail, Context, Result};
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
    /// Keep the stand-in CSV (DIR/chinchilla_standin.csv) and the fit (DIR/fits/) here
    /// instead of a temporary folder.
    #[arg(long, value_name = "DIR")]
    pub keep: Option<PathBuf>,
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
    let csv = dir.join("chinchilla_standin.csv");
    let runs = fits::synth::chinchilla_standin(args.seed);
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
        "bench fit: {} runs, grid {:?}, {} bootstrap resamples, {threads} threads: whole command {secs:.2} s (target < {TARGET_SECONDS} s on 2 cores: {})",
        runs.len(),
        args.starts_grid,
        args.bootstrap,
        if secs < TARGET_SECONDS { "met" } else { "MISSED" }
    );
    Ok(ExitCode::SUCCESS)
}
