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
mod stage_timer;
mod tokenizer;

use anyhow::{bail, Context, Result};
use clap::Subcommand;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::Value;
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

/// Wall times of repeated calls of one function, as [`time`] measures them (the keys of
/// `../shared/bench/common.py`'s `timeit`, which the references write).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Timing {
    /// Median seconds per call.
    pub median_s: f64,
    /// Fastest call, seconds.
    pub min_s: f64,
    /// Slowest call, seconds.
    pub max_s: f64,
    /// Calls timed.
    pub n: usize,
    /// Share of all cores' time that other processes used meanwhile ([`foreign_load`]; none
    /// where `/proc` cannot be read).
    pub foreign_cpu_fraction: Option<f64>,
    /// This process's CPU seconds per call, all threads together (none where `/proc` cannot
    /// be read).
    pub own_cpu_s_per_call: Option<f64>,
}

/// Median, min and max of `f`'s wall time after `warmup` calls, over at least `reps` calls
/// and `min_time` seconds, with the foreign CPU load meanwhile.
pub fn time<F: FnMut() -> Result<()>>(
    warmup: usize,
    reps: usize,
    min_time: f64,
    mut f: F,
) -> Result<Timing> {
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
    Ok(Timing {
        median_s: samples[samples.len() / 2],
        min_s: samples[0],
        max_s: samples[samples.len() - 1],
        n: samples.len(),
        foreign_cpu_fraction: foreign,
        own_cpu_s_per_call: own_cpu.map(|c| c / calls),
    })
}

/// Read a reference script's JSON output `text` as a `T`: a missing or mistyped key is an
/// error naming the script and the key.
pub fn reference_output<T: DeserializeOwned>(script: &Path, text: &[u8]) -> Result<T> {
    serde_json::from_slice(text)
        .map_err(|e| anyhow::anyhow!("reading the output of {}: {e}", script.display()))
}

/// Run the PyTorch reference `script` with `args` plus `--out FILE` and read the JSON it wrote
/// as a `T` ([`reference_output`]).
pub fn run_reference<T: DeserializeOwned>(script: &Path, args: &[&str]) -> Result<T> {
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
    let text = std::fs::read(out.path())
        .with_context(|| format!("reading the output of {}", script.display()))?;
    reference_output(script, &text)
}

/// Write `figures` as pretty JSON to `path` (atomically), when a path is given, with the
/// machine they were measured on (`machine`; a list of figures goes under `figures`). Keys
/// come out sorted, as `serde_json`'s maps keep them.
pub fn write_json<T: Serialize + ?Sized>(path: Option<&PathBuf>, figures: &T) -> Result<()> {
    if let Some(path) = path {
        let mut figures = match serde_json::to_value(figures)? {
            Value::Object(map) => map,
            other => serde_json::Map::from_iter([("figures".to_string(), other)]),
        };
        figures.insert("machine".into(), serde_json::to_value(machine::machine())?);
        let text = serde_json::to_string_pretty(&figures)?;
        motionscale_core::write_atomic(path, text.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A committed bench figure file (`docs/results/bench/NAME`).
    fn committed(name: &str) -> Value {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("docs/results/bench")
            .join(name);
        serde_json::from_slice(&std::fs::read(&path).expect("a committed figure")).expect("JSON")
    }

    #[test]
    fn the_committed_figures_read_back_as_the_typed_structs() {
        let fit: fit::FitFigures = serde_json::from_value(committed("fit.json")).expect("fit");
        let parametric = fit.parametric.expect("the SciPy comparison");
        assert!(parametric.reference.seconds > 0.0 && parametric.reference.fit.e > 0.0);
        let embed = committed("embed.json")["reference"].clone();
        let embed: embed::EmbedReference = serde_json::from_value(embed).expect("embed");
        assert!(embed.median_s > 0.0 && embed.other.contains_key("torch"));
        let evaluator = committed("evaluator.json")["reference"].clone();
        let evaluator: gru::StepReference = serde_json::from_value(evaluator).expect("evaluator");
        assert!(evaluator.median_step_s > 0.0);
        let ctvae = committed("ctvae.json")[0]["reference"].clone();
        let ctvae: gru::StepReference = serde_json::from_value(ctvae).expect("ctvae");
        assert!(ctvae.median_step_s > 0.0);
    }

    #[test]
    fn a_missing_key_of_a_reference_names_the_script_and_the_key() {
        let text = br#"{"runs": 3, "starts": 1, "jac": "analytic", "E": 1, "A": 2, "B": 3,
            "alpha": 0.3, "beta": 0.3, "objective": 0.1}"#;
        let err = reference_output::<fit::ScipyFit>(Path::new("scripts/scipy_fit.py"), text)
            .expect_err("no seconds");
        let message = format!("{err:#}");
        assert!(message.contains("scripts/scipy_fit.py"), "{message}");
        assert!(message.contains("`seconds`"), "{message}");
    }

    #[test]
    fn a_list_of_figures_goes_under_figures_beside_the_machine() {
        let tmp = tempfile::tempdir().expect("tmp");
        let path = tmp.path().join("figures.json");
        write_json(Some(&path), &[1.0, 2.0]).expect("written");
        let written: Value = serde_json::from_slice(&std::fs::read(&path).expect("read")).unwrap();
        assert_eq!(written["figures"], serde_json::json!([1.0, 2.0]));
        assert!(written["machine"]["fma_peak_gflops"].as_f64() > Some(0.0));
    }
}
