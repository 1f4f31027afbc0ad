//! `motionscale quickstart`: the whole study on built-in data, small enough for a laptop —
//! synthetic corpus (+ Bandai Namco set 1 when the shared data has it) → MiniLM caption
//! embeddings → a small FSQ tokenizer → tokens → a micro IsoFLOP sweep → fit → predict →
//! a BVH generated from a caption (and ingested back) → evaluator and `eval` → the HTML report.
//!
//! Each step runs this binary's own subcommand as a child process and prints the command
//! first, so the quickstart doubles as a worked example of the command line.

use anyhow::{bail, Context, Result};
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Instant;

/// Arguments of `motionscale quickstart`.
#[derive(clap::Args, Debug)]
pub struct QuickstartArgs {
    /// Output folder (corpus/, tokenizer/, tokens/, sweep/, generated/, evaluator/, report.html).
    #[arg(long)]
    pub out: PathBuf,
    /// Synthetic clips (before mirroring).
    #[arg(long, default_value_t = 1000)]
    pub clips: usize,
    /// Seed of the synthetic stream, the tokenizer, the sweep and the sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Shared data folder: Bandai Namco set 1 (`bandai-namco/bandai-namco-1.tar.zst`) joins
    /// the corpus when it is there.
    #[arg(long, default_value = "../shared/data")]
    pub data: PathBuf,
    /// Compute budget (FLOPs) of the named prediction.
    #[arg(long, default_value_t = 1e15)]
    pub budget: f64,
    /// Caption of the generated BVH.
    #[arg(long, default_value = "a person walks forward, looking happy")]
    pub caption: String,
    /// Embed captions with the untrained fallback table instead of MiniLM (everything learned
    /// from the text is then meaningless; only for machines that cannot fetch the encoder).
    #[arg(long)]
    pub fallback: bool,
}

/// The micro sweep: budgets (FLOPs) and model sizes, 3 × 3 runs of one vocabulary. The
/// sizes bracket the loss minimum at each budget on the quickstart corpus (at 1e11 it falls
/// below the smallest), and the largest budget keeps the sweep to a few minutes on 2 cores.
const BUDGETS: &str = "3e11,6e11,1e12";
const MODELS: &str = "32x1,cpu-50K,cpu-400K";
/// Nominal codebook of the tokenizer (FSQ [8,6,5]: 240 codes).
const CODEBOOK: &str = "256";
const STEPS: usize = 12;

/// Numbered steps, each a child `motionscale` command.
struct Steps {
    exe: PathBuf,
    done: usize,
    started: Instant,
}

impl Steps {
    /// Announce step `what` with the elapsed time.
    fn step(&mut self, what: &str) {
        self.done += 1;
        let secs = self.started.elapsed().as_secs();
        println!(
            "\n[{}/{STEPS}] {what}  ({}:{:02} elapsed)",
            self.done,
            secs / 60,
            secs % 60
        );
    }

    /// Run `motionscale ARGS` with its output shown, and return its exit code; fails when
    /// the command does not exit with one of `ok`.
    fn run(&self, args: &[OsString], ok: &[i32]) -> Result<i32> {
        // Quoted where needed, so the printed line can be pasted into a shell.
        let shown: Vec<String> = args
            .iter()
            .map(|a| a.to_string_lossy())
            .map(|a| {
                if a.contains(' ') {
                    format!("{a:?}")
                } else {
                    a.into()
                }
            })
            .collect();
        println!("      $ motionscale {}", shown.join(" "));
        let status = Command::new(&self.exe)
            .args(args)
            .status()
            .with_context(|| format!("running motionscale {}", shown.join(" ")))?;
        match status.code() {
            Some(code) if ok.contains(&code) => Ok(code),
            _ => bail!("`motionscale {}` failed ({status})", shown.join(" ")),
        }
    }
}

/// Command-line arguments from strings and paths.
macro_rules! args {
    ($($a:expr),* $(,)?) => { [$(OsString::from($a)),*] };
}

/// Run the quickstart.
pub fn quickstart(args: QuickstartArgs) -> Result<ExitCode> {
    let mut steps = Steps {
        exe: std::env::current_exe().context("locating the motionscale binary")?,
        done: 0,
        started: Instant::now(),
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let out = std::fs::canonicalize(&args.out)?;
    let corpus = out.join("corpus");
    corpus_steps(&mut steps, &args, &out, &corpus)?;
    let (tokenizer, eval_json) = tokenizer_steps(&mut steps, &args, &out, &corpus)?;
    let sweep = sweep_steps(&mut steps, &args, &out, &corpus)?;
    let model = best_run(&sweep)?;
    let bvh = generate_steps(&mut steps, &args, &out, &model, &tokenizer)?;
    eval_steps(&mut steps, &args, &out, &corpus, &model, &tokenizer)?;
    let report = report_step(&mut steps, &args, &out, &corpus, &sweep, &eval_json)?;

    let secs = steps.started.elapsed().as_secs();
    println!("\nquickstart done in {}:{:02}", secs / 60, secs % 60);
    println!("report:          {}", report.display());
    println!("generated BVH:   {} (\"{}\")", bvh.display(), args.caption);
    print_prediction(&sweep, args.budget)?;
    Ok(ExitCode::SUCCESS)
}

/// Step 12: the HTML report of the corpus, the sweep and the tokenizer's test metrics.
fn report_step(
    steps: &mut Steps,
    args: &QuickstartArgs,
    out: &Path,
    corpus: &Path,
    sweep: &Path,
    eval_json: &Path,
) -> Result<PathBuf> {
    steps.step("the HTML report");
    let report = out.join("report.html");
    let budget = args.budget.to_string();
    steps.run(
        &args![
            "report",
            sweep,
            corpus,
            eval_json,
            "--budgets",
            &budget,
            "--out",
            &report
        ],
        &[0],
    )?;
    Ok(report)
}

/// The closing summary's last lines: the sweep's prediction at `budget` and under the numbers
/// predict's verdict on them (its warnings), so that the output ends on the answer with its
/// caveats, not on numbers whose warnings scrolled past with the predict step.
fn print_prediction(sweep: &Path, budget: f64) -> Result<()> {
    let laws = fits::Laws::read(&sweep.join("fits").join("fits.json"))?;
    let opts = fits::PredictOptions {
        budget,
        width: None,
        vocab: None,
    };
    let prediction = fits::predict(&laws, &opts)?;
    println!("predicted optimum at C = {budget:.1e} FLOPs:");
    for (name, value) in crate::fit::prediction_rows(&prediction) {
        println!("  {name:<22} {value}");
    }
    if prediction.warnings.is_empty() {
        println!("  verdict: no warnings from predict");
    }
    for warning in &prediction.warnings {
        println!("  verdict: {warning}");
    }
    Ok(())
}

/// Steps 1–3: the corpus (synthetic + Bandai set 1), verified, its captions embedded.
fn corpus_steps(steps: &mut Steps, args: &QuickstartArgs, out: &Path, corpus: &Path) -> Result<()> {
    let mut sources = args![
        "ingest",
        "--source",
        format!("synth:{}:{}", args.clips, args.seed),
    ]
    .to_vec();
    let bandai = args
        .data
        .join("bandai-namco")
        .join("bandai-namco-1.tar.zst");
    let what = if bandai.is_file() {
        let dir = out.join("bandai-namco-1");
        if dir.exists() {
            std::fs::remove_dir_all(&dir).with_context(|| format!("removing {}", dir.display()))?;
        }
        std::fs::create_dir_all(&dir)?;
        crate::commands::extract(&bandai, &dir)?;
        // One source per folder of the archive, as `bench ingest` does, in name order.
        let mut folders = Vec::new();
        for entry in std::fs::read_dir(&dir)? {
            let path = entry?.path();
            if path.is_dir() {
                folders.push(path);
            }
        }
        folders.sort();
        for folder in folders {
            sources.extend(args!["--source", format!("bvh:{}", folder.display())]);
        }
        format!("{} synthetic clips + Bandai Namco set 1", args.clips)
    } else {
        format!(
            "{} synthetic clips ({} not found)",
            args.clips,
            bandai.display()
        )
    };
    steps.step(&format!("corpus: {what}, mirrored"));
    sources.extend(args!["--mirror", "--out", corpus]);
    // Exit 2: some inputs rejected (listed in rejects.jsonl); the corpus is still whole.
    steps.run(&sources, &[0, 2])?;

    steps.step("verify the corpus");
    steps.run(&args!["corpus", "verify", corpus], &[0])?;

    steps.step("caption embeddings (frozen MiniLM text encoder)");
    let mut embed = args!["embed-text", "--corpus", corpus].to_vec();
    if args.fallback {
        embed.push("--fallback".into());
    }
    steps.run(&embed, &[0])?;
    Ok(())
}

/// Steps 4–5: a small FSQ tokenizer, its test metrics, and the corpus's tokens.
fn tokenizer_steps(
    steps: &mut Steps,
    args: &QuickstartArgs,
    out: &Path,
    corpus: &Path,
) -> Result<(PathBuf, PathBuf)> {
    let tokenizer = out.join("tokenizer");
    let seed = args.seed.to_string();
    steps.step("a small FSQ tokenizer (2^8 codes, width 32)");
    steps.run(
        &args![
            "tokenizer",
            "train",
            "--corpus",
            corpus,
            "--quantizer",
            "fsq",
            "--codebook",
            CODEBOOK,
            "--width",
            "32",
            "--batch",
            "32",
            "--steps",
            "300",
            "--lr",
            "5e-4",
            "--grad-clip",
            "1",
            "--seed",
            &seed,
            "--out",
            &tokenizer,
        ],
        &[0],
    )?;
    let eval_json = tokenizer.join("eval-test.json");
    steps.run(
        &args![
            "tokenizer",
            "eval",
            "--tokenizer",
            &tokenizer,
            "--corpus",
            corpus,
            "--split",
            "test",
            "--out",
            &eval_json,
        ],
        &[0],
    )?;

    steps.step("tokens of every clip");
    let tokens = out.join("tokens");
    steps.run(
        &args![
            "tokenize",
            "--tokenizer",
            &tokenizer,
            "--corpus",
            corpus,
            "--out",
            &tokens
        ],
        &[0],
    )?;
    Ok((tokenizer, eval_json))
}

/// Steps 6–8: plan and run the micro IsoFLOP sweep, fit the laws, predict at the budget.
fn sweep_steps(
    steps: &mut Steps,
    args: &QuickstartArgs,
    out: &Path,
    corpus: &Path,
) -> Result<PathBuf> {
    let (plan, sweep) = (out.join("plan.toml"), out.join("sweep"));
    let token_set = format!("{CODEBOOK}={}", out.join("tokens").display());
    let seed = args.seed.to_string();
    steps.step(&format!(
        "micro IsoFLOP sweep: budgets {BUDGETS} × models {MODELS}"
    ));
    steps.run(
        &args![
            "sweep",
            "plan",
            "--corpus",
            corpus,
            "--budgets",
            BUDGETS,
            "--models",
            MODELS,
            "--vocabs",
            CODEBOOK,
            "--token-sets",
            &token_set,
            "--seed",
            &seed,
            "--checkpoint-every",
            "1000",
            "--out",
            &plan,
        ],
        &[0],
    )?;
    steps.run(
        &args!["sweep", "run", "--plan", &plan, "--out", &sweep, "--jobs", "2"],
        &[0],
    )?;

    steps.step("fit the scaling laws");
    let fits = sweep.join("fits");
    steps.run(
        &args![
            "fit",
            "--results",
            sweep.join("results.parquet"),
            "--out",
            &fits
        ],
        &[0],
    )?;

    steps.step(&format!("predict at C = {:.1e} FLOPs", args.budget));
    let budget = args.budget.to_string();
    steps.run(
        &args![
            "predict",
            "--fits",
            fits.join("fits.json"),
            "--budget",
            &budget
        ],
        &[0],
    )?;
    Ok(sweep)
}

/// The trained model of the sweep's best run at its largest budget (lowest L_u).
fn best_run(sweep: &Path) -> Result<PathBuf> {
    let rows = experiments::results::read_csv(&sweep.join("results.csv"))?;
    let largest = rows.iter().map(|r| r.budget).fold(0.0, f64::max);
    let best = rows
        .iter()
        .filter(|r| r.budget == largest)
        .min_by(|a, b| a.norm_test_loss.total_cmp(&b.norm_test_loss))
        .with_context(|| format!("{}: no finished run", sweep.join("results.csv").display()))?;
    println!(
        "      best run at C = {:.1e}: {} (L_u {:.4})",
        largest, best.run_id, best.norm_test_loss
    );
    Ok(sweep.join(&best.run_id).join("train"))
}

/// Step 9: a BVH from the caption, ingested back as a check that other tools can read it.
fn generate_steps(
    steps: &mut Steps,
    args: &QuickstartArgs,
    out: &Path,
    model: &Path,
    tokenizer: &Path,
) -> Result<PathBuf> {
    steps.step(&format!("generate a BVH for \"{}\"", args.caption));
    let dir = out.join("generated");
    std::fs::create_dir_all(&dir)?;
    let bvh = dir.join("caption.bvh");
    let seed = args.seed.to_string();
    steps.run(
        &generate(
            model,
            tokenizer,
            &args![
                "--text",
                &args.caption,
                "--seed",
                &seed,
                "--min-tokens",
                "16",
                "--out",
                &bvh,
            ],
        ),
        &[0],
    )?;
    let reingest = out.join("generated-reingested");
    // Exit 0 only: a rejected BVH fails the quickstart.
    steps.run(
        &args![
            "ingest",
            "--source",
            format!("bvh:{}", dir.display()),
            "--out",
            &reingest
        ],
        &[0],
    )?;
    Ok(bvh)
}

/// `generate` with `model` and the quickstart's tokenizer, then `rest`.
fn generate(model: &Path, tokenizer: &Path, rest: &[OsString]) -> Vec<OsString> {
    let mut args = args!["generate", "--model", model, "--tokenizer", tokenizer].to_vec();
    args.extend_from_slice(rest);
    args
}

/// Steps 10–11: a small evaluator, the test captions generated, and their metrics.
fn eval_steps(
    steps: &mut Steps,
    args: &QuickstartArgs,
    out: &Path,
    corpus: &Path,
    model: &Path,
    tokenizer: &Path,
) -> Result<()> {
    let evaluator = evaluator_step(steps, args, out, corpus)?;
    let seed = args.seed.to_string();
    steps.step("generate the test captions and evaluate them");
    let generated = out.join("generated-test");
    steps.run(
        &generate(
            model,
            tokenizer,
            &args![
                "--captions-from",
                corpus,
                "--split",
                "test",
                "--mm-texts",
                "10",
                "--mm-samples",
                "5",
                "--seed",
                &seed,
                "--out",
                &generated,
            ],
        ),
        // Exit 2: some captions got no motion token (counted in the output).
        &[0, 2],
    )?;
    steps.run(
        &args![
            "eval",
            "--evaluator",
            &evaluator,
            "--motions",
            &generated,
            "--corpus",
            corpus,
            "--repeats",
            "5",
            "--seed",
            &seed,
            "--out",
            out.join("eval.json"),
        ],
        &[0],
    )?;
    Ok(())
}

/// Step 10: a small text–motion evaluator trained on the corpus.
fn evaluator_step(
    steps: &mut Steps,
    args: &QuickstartArgs,
    out: &Path,
    corpus: &Path,
) -> Result<PathBuf> {
    let seed = args.seed.to_string();
    steps.step("a small text–motion evaluator");
    let evaluator = out.join("evaluator");
    steps.run(
        &args![
            "evaluator",
            "train",
            "--corpus",
            corpus,
            "--out",
            &evaluator,
            "--hidden",
            "64",
            "--embed-dim",
            "64",
            "--max-frames",
            "128",
            "--batch",
            "32",
            "--steps",
            "300",
            "--eval-every",
            "100",
            "--seed",
            &seed,
        ],
        &[0],
    )?;
    Ok(evaluator)
}
