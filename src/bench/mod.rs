//! `motionscale bench …`: each stage's speed, printed beside the target or the PyTorch
//! reference (`../shared/bench/`) measured in the same run.

mod embed;
mod fit;
mod gru;
mod ingest;
mod lm;
mod lm_gpu;
mod lm_step;
mod machine;
mod tokenizer;

use anyhow::{bail, Context, Result};
use clap::Subcommand;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

/// The stages `bench` times.
#[derive(Subcommand)]
pub enum BenchCommand {
    /// Ingest both Bandai Namco archives and time joints → 263 features on fixture (a).
    Ingest(ingest::BenchIngestArgs),
    /// Time synthetic corpus building: generation + features, and the whole ingest.
    Synth(ingest::BenchSynthArgs),
    /// Prefix-LM training step and generation: tokens/s, GFLOP/s, MFU, PyTorch ratio.
    Train(lm_step::BenchTrainArgs),
    /// Time tokenizer training steps (FSQ, VQ) at the T2M-GPT shape; --reference runs PyTorch too.
    Tokenizer(tokenizer::BenchTokenizerArgs),
    /// Time caption embedding (MiniLM) over a corpus's captions; --reference runs PyTorch too.
    Embed(embed::BenchEmbedArgs),
    /// Time the whole `fit` command (4,500 starts + bootstrap) on a Chinchilla-like stand-in.
    Fit(fit::BenchFitArgs),
    /// Time the evaluator's training step (batch 64, hidden 256); --reference runs PyTorch too.
    Evaluator(gru::BenchEvaluatorArgs),
    /// Time BI-CTVAE training steps at cl2gen's shapes; --reference runs PyTorch too.
    Ctvae(gru::BenchCtvaeArgs),
}

/// Run one `bench` command.
pub fn run(command: BenchCommand) -> Result<ExitCode> {
    match command {
        BenchCommand::Ingest(args) => ingest::ingest(args),
        BenchCommand::Synth(args) => ingest::synth(args),
        BenchCommand::Train(args) => lm::train(args),
        BenchCommand::Tokenizer(args) => tokenizer::bench_tokenizer(args),
        BenchCommand::Embed(args) => embed::bench_embed(args),
        BenchCommand::Fit(args) => fit::bench(args),
        BenchCommand::Evaluator(args) => gru::evaluator(args),
        BenchCommand::Ctvae(args) => gru::ctvae(args),
    }
}

/// CPU jiffies so far: (idle of all cores, total of all cores, this process).
fn cpu_snapshot() -> Option<(u64, u64, u64)> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let all: Vec<u64> = stat
        .lines()
        .next()?
        .split_whitespace()
        .skip(1)
        .filter_map(|v| v.parse().ok())
        .collect();
    let own = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name: state is field 3, utime 14, stime 15.
    let fields: Vec<&str> = own.rsplit_once(')')?.1.split_whitespace().collect();
    let utime: u64 = fields.get(11)?.parse().ok()?;
    let stime: u64 = fields.get(12)?.parse().ok()?;
    Some((all.get(3)? + all.get(4)?, all.iter().sum(), utime + stime))
}

/// Share of all cores' time between two snapshots that other processes used (0: a quiet
/// machine; 0.5 on 2 cores: one whole core was busy elsewhere), as `pytorch_prefix_lm.py`'s
/// `foreign_cpu_fraction`.
fn foreign_load(a: Option<(u64, u64, u64)>, b: Option<(u64, u64, u64)>) -> Option<f64> {
    let ((idle0, total0, own0), (idle1, total1, own1)) = (a?, b?);
    let total = total1.checked_sub(total0).filter(|&t| t > 0)? as f64;
    let busy = total - (idle1 - idle0) as f64;
    Some(((busy - (own1 - own0) as f64) / total).max(0.0))
}

/// Tell `perf record --control` (`scripts/profile-cpu.sh`, through the FIFOs named by
/// `MOTIONSCALE_PERF_CTL` and `MOTIONSCALE_PERF_ACK`) to `enable` or `disable` sampling, and
/// wait for its acknowledgement, so that a profile holds the timed calls only. Without the
/// variables, nothing; with them, perf must hold the other ends (it blocks until it answers).
fn profiler(command: &str) {
    use std::io::{Read, Write};
    let (Ok(ctl), Ok(ack)) = (
        std::env::var("MOTIONSCALE_PERF_CTL"),
        std::env::var("MOTIONSCALE_PERF_ACK"),
    ) else {
        return;
    };
    let done = std::fs::OpenOptions::new()
        .write(true)
        .open(&ctl)
        .and_then(|mut f| f.write_all(format!("{command}\n").as_bytes()))
        .and_then(|()| std::fs::File::open(&ack)?.read_exact(&mut [0u8; 4]));
    if let Err(e) = done {
        eprintln!("warning: profiler control through {ctl} and {ack}: {e}");
    }
}

/// Median, min and max of `f`'s wall time after `warmup` calls, over at least `reps` calls
/// and `min_time` seconds, with the foreign CPU load meanwhile.
pub fn time<F: FnMut() -> Result<()>>(
    warmup: usize,
    reps: usize,
    min_time: f64,
    mut f: F,
) -> Result<Value> {
    for _ in 0..warmup {
        f()?;
    }
    profiler("enable");
    let before = cpu_snapshot();
    let mut samples = Vec::new();
    let mut total = 0.0;
    while samples.len() < reps || total < min_time {
        let t = Instant::now();
        f()?;
        samples.push(t.elapsed().as_secs_f64());
        total += samples.last().expect("pushed");
        if samples.len() >= 200 {
            break;
        }
    }
    let after = cpu_snapshot();
    profiler("disable");
    let foreign = foreign_load(before, after);
    // /proc reports jiffies of 1/100 s.
    let own_cpu = before.zip(after).map(|(a, b)| (b.2 - a.2) as f64 / 100.0);
    let calls = samples.len() as f64;
    samples.sort_by(f64::total_cmp);
    Ok(
        json!({"median_s": samples[samples.len() / 2], "min_s": samples[0],
              "max_s": samples[samples.len() - 1], "n": samples.len(),
              "foreign_cpu_fraction": foreign,
              "own_cpu_s_per_call": own_cpu.map(|c| c / calls)}),
    )
}

/// A number of a reference script's JSON output.
pub fn number(json: &serde_json::Value, key: &str) -> Result<f64> {
    json[key]
        .as_f64()
        .with_context(|| format!("the reference's output has no number {key:?}"))
}

/// Run the PyTorch reference `script` with `args` plus `--out FILE` and read the JSON it wrote.
pub fn run_reference(script: &Path, args: &[&str]) -> Result<serde_json::Value> {
    let out = tempfile::NamedTempFile::new()?;
    let status = std::process::Command::new("python3")
        .arg(script)
        .args(args)
        .arg("--out")
        .arg(out.path())
        .stdout(std::process::Stdio::null())
        .status()
        .with_context(|| format!("running python3 {}", script.display()))?;
    if !status.success() {
        bail!(
            "{} failed ({status}); is torch installed?",
            script.display()
        );
    }
    serde_json::from_slice(&std::fs::read(out.path())?)
        .with_context(|| format!("reading the output of {}", script.display()))
}

/// Write `figures` as pretty JSON to `path` (atomically), when a path is given, with the
/// machine they were measured on (`machine`; a list of figures goes under `figures`).
pub fn write_json(path: Option<&PathBuf>, figures: &Value) -> Result<()> {
    if let Some(path) = path {
        let mut figures = match figures {
            Value::Object(_) => figures.clone(),
            _ => json!({ "figures": figures }),
        };
        figures["machine"] = machine::machine();
        let text = serde_json::to_string_pretty(&figures)?;
        motionscale_core::write_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
