//! `motionscale report`: gather what the stages wrote (a corpus, tokenizer evaluations, an
//! IsoFLOP sweep folder, a fit) and write one self-contained HTML page of it
//! ([`crate::report_page`] draws the page).

use crate::commands::corpus_stats;
use crate::report_page::{DataVerdict, Study, Sweep};
use anyhow::{bail, Context, Result};
use fits::report::estimate_text;
use fits::{Fits, Laws, PredictOptions, Prediction};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tokenizer::evaluate::EvalReport;

/// Arguments of `motionscale report`.
#[derive(clap::Args, Debug)]
#[command(
    long_about = "Write one self-contained HTML page (inline SVG charts, no scripts, \
    nothing fetched) of a study: corpus statistics, tokenizer metrics, the sweep's status, \
    IsoFLOP curves, the fitted laws with their 95% intervals, and predictions at compute \
    budgets with the consistency checks between the laws.\n\n\
    Each input is one of: a corpus folder (manifest.json); an IsoFLOP sweep folder (plan.toml, \
    with its results.csv, fits/fits.json or fits.json, and tokenizer evaluations *.json under \
    tokenizers/); a fits.json (or the folder holding it); a tokenizer evaluation JSON \
    (`tokenizer eval --out`). Sections without an input say so."
)]
pub struct ReportArgs {
    /// Corpus folders, sweep folders, fits.json files or tokenizer evaluation JSONs.
    #[arg(required = true, value_name = "RUNS|FITS|CORPUS")]
    pub inputs: Vec<PathBuf>,
    /// The HTML file to write.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Compute budgets in FLOPs to predict at, comma-separated [default: 10× and 100× the
    /// largest budget of the fit].
    #[arg(long, value_delimiter = ',', value_name = "C,…")]
    pub budgets: Vec<f64>,
    /// With a fit of the data-constrained law (`fit --repeated-data`): the corpus's hours,
    /// and the page leads with predict's data-bound verdict at each budget.
    #[command(flatten)]
    pub data: crate::fit::HoursArgs,
}

/// `motionscale report`.
pub fn report(args: ReportArgs) -> Result<ExitCode> {
    let mut study = Study {
        inputs: args.inputs.clone(),
        corpus: None,
        tokenizers: Vec::new(),
        sweep: None,
        fits: None,
        predictions: Vec::new(),
        data_verdicts: Vec::new(),
        replay: None,
    };
    for input in &args.inputs {
        add_input(&mut study, input)?;
    }
    let budgets = study
        .fits
        .as_ref()
        .map_or_else(Vec::new, |(_, f)| budgets(f, &args.budgets));
    study.predictions = predictions(study.fits.as_ref(), &budgets);
    study.data_verdicts = data_verdicts(study.fits.as_ref(), &budgets, &args.data)?;
    let html = crate::report_page::page(&study)?;
    motionscale_core::write_atomic(&args.out, html.as_bytes())
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "wrote {} ({} KiB): {}",
        args.out.display(),
        html.len() / 1024,
        crate::report_page::contents(&study).join(", ")
    );
    Ok(ExitCode::SUCCESS)
}

/// Add what `input` holds to `study`; an input of a kind already given is an error.
fn add_input(study: &mut Study, input: &Path) -> Result<()> {
    if input.is_file() {
        return add_json(study, input);
    }
    if !input.is_dir() {
        bail!("{}: no such file or folder", input.display());
    }
    if input.join("manifest.json").is_file() {
        let stats = corpus_stats(input)
            .with_context(|| format!("reading the corpus {}", input.display()))?;
        return set_once(&mut study.corpus, (input.to_path_buf(), stats), input);
    }
    if input.join("plan.toml").is_file() {
        return add_sweep(study, input);
    }
    if input.join("fits.json").is_file() {
        return add_json(study, &input.join("fits.json"));
    }
    if input.join("replay.csv").is_file() {
        return add_replay(study, input);
    }
    bail!(
        "{}: neither a corpus (manifest.json), a sweep folder (plan.toml), a fit (fits.json) nor a planner replay (replay.csv)",
        input.display()
    )
}

/// A `sweep replay` folder: its summary and charts.
fn add_replay(study: &mut Study, dir: &Path) -> Result<()> {
    let path = dir.join("summary.json");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let summary = parse(
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?,
        &path,
        "a `sweep replay` summary",
    )?;
    let charts = ["replay-width.svg", "replay-error.svg"]
        .iter()
        .map(|f| {
            std::fs::read_to_string(dir.join(f))
                .with_context(|| format!("reading {}", dir.join(f).display()))
        })
        .collect::<Result<_>>()?;
    let replay = crate::report_page::Replay {
        dir: dir.to_path_buf(),
        summary,
        charts,
    };
    set_once(&mut study.replay, replay, dir)
}

/// Put `value` in `slot`, or fail when an earlier input already filled it.
fn set_once<T>(slot: &mut Option<T>, value: T, input: &Path) -> Result<()> {
    if slot.is_some() {
        bail!(
            "{}: a report takes one input of each kind (corpus, sweep, fit, replay)",
            input.display()
        );
    }
    *slot = Some(value);
    Ok(())
}

/// A JSON input: a `fits.json` or a tokenizer evaluation.
fn add_json(study: &mut Study, path: &Path) -> Result<()> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let value: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    if value.get("power_laws").is_some() {
        let fits: Fits = parse(value, path, "a fits.json written by `motionscale fit`")?;
        return set_once(&mut study.fits, (path.to_path_buf(), fits), path);
    }
    if value.get("tokenizer_id").is_some() {
        let eval: EvalReport = parse(value, path, "a `tokenizer eval` report")?;
        study.tokenizers.push((path.to_path_buf(), eval));
        return Ok(());
    }
    bail!(
        "{}: neither a fits.json (`motionscale fit`) nor a tokenizer evaluation (`tokenizer eval --out`)",
        path.display()
    )
}

/// `value` (read from `path`) as a `T`, or an error naming the file and what it should be.
fn parse<T: serde::de::DeserializeOwned>(
    value: serde_json::Value,
    path: &Path,
    what: &str,
) -> Result<T> {
    serde_json::from_value(value).with_context(|| format!("{}: not {what}", path.display()))
}

/// A sweep folder: its plan, point states and results table, its fit and its tokenizer
/// evaluations when it has them.
fn add_sweep(study: &mut Study, dir: &Path) -> Result<()> {
    let plan = experiments::plan::read_adopted_plan(dir)?;
    let points = experiments::status::status(&plan, dir)?;
    let csv = dir.join("results.csv");
    let rows = if csv.is_file() {
        experiments::results::read_csv(&csv)?
    } else {
        Vec::new()
    };
    let sweep = Sweep {
        dir: dir.to_path_buf(),
        plan,
        points,
        rows,
    };
    set_once(&mut study.sweep, sweep, dir)?;
    for fits in [dir.join("fits").join("fits.json"), dir.join("fits.json")] {
        if fits.is_file() {
            add_json(study, &fits)?;
            break;
        }
    }
    for eval in tokenizer_evaluations(&dir.join("tokenizers"))? {
        add_json(study, &eval)?;
    }
    Ok(())
}

/// The tokenizer evaluation JSONs in `dir` and its subfolders (`*eval*.json`), sorted.
fn tokenizer_evaluations(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut found = Vec::new();
    if !dir.is_dir() {
        return Ok(found);
    }
    for entry in std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
        let path = entry
            .with_context(|| format!("listing {}", dir.display()))?
            .path();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
        if path.is_dir() {
            found.extend(tokenizer_evaluations(&path)?);
        } else if name.is_some_and(|n| n.contains("eval") && n.ends_with(".json")) {
            found.push(path);
        }
    }
    found.sort();
    Ok(found)
}

/// The budgets to predict at: those given, else 10× and 100× the fit's largest budget.
fn budgets(fits: &Fits, given: &[f64]) -> Vec<f64> {
    let largest = fits
        .budgets
        .iter()
        .map(|b| b.min.budget)
        .fold(0.0, f64::max);
    if given.is_empty() && largest > 0.0 {
        vec![10.0 * largest, 100.0 * largest]
    } else {
        given.to_vec()
    }
}

/// Predictions at `budgets`.
fn predictions(
    fits: Option<&(PathBuf, Fits)>,
    budgets: &[f64],
) -> Vec<(f64, Result<Prediction, String>)> {
    let Some((path, fits)) = fits else {
        return Vec::new();
    };
    let laws = Laws::from_fits(fits, &path.display().to_string());
    budgets
        .iter()
        .map(|&budget| {
            let opts = PredictOptions {
                budget,
                width: None,
                vocab: None,
            };
            (
                budget,
                fits::predict(&laws, &opts).map_err(|e| e.to_string()),
            )
        })
        .collect()
}

/// The data-constrained optimum in one line: N_opt, its epochs (and e*), the loss and a run's.
fn optimum_text(p: &fits::data_value::DataPrediction) -> String {
    let stops = p.stop_epochs.as_ref().map_or(String::new(), |e| {
        format!(", stops at {}", estimate_text(e))
    });
    let run = crate::fit::run_text(p.loss_prediction.as_ref());
    format!(
        "N_opt {}, {} epochs{stops}; loss {}{run}",
        estimate_text(&p.n_opt),
        estimate_text(&p.epochs),
        estimate_text(&p.loss)
    )
}

/// predict's data-bound verdict at each budget on the hours given (none without --hours; a
/// fit without the data-constrained law is an error naming the file).
fn data_verdicts(
    fits: Option<&(PathBuf, Fits)>,
    budgets: &[f64],
    data: &crate::fit::HoursArgs,
) -> Result<Vec<DataVerdict>> {
    let (Some((path, fits)), Some(hours)) = (fits, data.hours) else {
        if data.hours.is_some() {
            bail!("--hours needs a fit of the data-constrained law among the inputs");
        }
        return Ok(Vec::new());
    };
    let on = format!(
        "{} captured + {} synthetic",
        data.hours_text(hours.real),
        data.hours_text(hours.synth)
    );
    let mut verdicts = Vec::new();
    for &budget in budgets {
        if let Some(answer) = data.answer(fits, path, budget)? {
            verdicts.push(DataVerdict {
                budget,
                hours: on.clone(),
                sentence: data.verdict_text(&answer),
                optimum: optimum_text(&answer.prediction),
                bound: answer.bound.as_ref().is_some_and(|b| b.bound),
            });
        }
    }
    Ok(verdicts)
}
