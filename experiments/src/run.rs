//! One point of a plan, start to finish, in its own folder:
//!
//! ```text
//! RUNS/<run_id>/.lock        held (flock) by the process running the point
//! RUNS/<run_id>/train/       the lm::train run (checkpoints, config, eval.json…)
//! RUNS/<run_id>/wall.json    training seconds of earlier, interrupted attempts
//! RUNS/<run_id>/error.json   why the last attempt failed (removed when one starts)
//! RUNS/<run_id>/result.json  the row, written last by temp + rename: the point is done
//! RUNS/data/<subset>/        a data subset's split lists, shared by its points
//! ```
//!
//! A re-run resumes the training checkpoint; a checkpoint left inconsistent by a kill while
//! it was written is discarded and the point trained again from the start, which gives the
//! same weights (training is a pure function of its config).

use crate::data_ladder;
use crate::plan::{read_adopted_plan, IsoFlopPlan, PlanPoint};
use crate::prepare::prepare_vocabulary;
use crate::results::{self, read_row, run_dir, RunRow};
use crate::SweepError;
use candle_core::Device;
use ingest::corpus::{Corpus, Origin};
use lm::eval_record::BestEval;
use lm::selection;
use lm::test_loss::SplitLoss;
use lm::train::{train, TrainEvent, TrainReport};
use motionscale_core::lock::FileLock;
use motionscale_core::{write_json, FileError};
use nn::ModelError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// What [`run_point`] did.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Trained now (possibly resuming an earlier attempt).
    Trained(RunRow),
    /// Already finished before.
    AlreadyDone(RunRow),
}

impl Outcome {
    /// The point's row.
    pub fn row(&self) -> &RunRow {
        match self {
            Self::Trained(r) | Self::AlreadyDone(r) => r,
        }
    }
}

/// `RUNS/<run_id>/error.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunError {
    /// The error message.
    pub error: String,
    /// Host of the failed attempt.
    pub hostname: String,
}

/// `RUNS/<run_id>/wall.json`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
struct Wall {
    seconds: f64,
}

/// How often the wall time of a running attempt is saved.
const WALL_SAVE_EVERY: Duration = Duration::from_secs(5);

/// Train `point` of `plan` in `RUNS/<run_id>/` unless it is done, write its row and rebuild
/// the tables. A failure is recorded in `error.json` and returned.
pub fn run_point(
    plan: &IsoFlopPlan,
    runs: &Path,
    point: &PlanPoint,
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<Outcome, SweepError> {
    let dir = run_dir(runs, &point.run_id);
    let lock_path = dir.join(".lock");
    let _lock = FileLock::acquire_or_wait(&lock_path, || {
        log(&format!(
            "{}: running in another process, waiting",
            point.run_id
        ))
    })?;
    if let Some(row) = read_row(runs, &point.run_id)? {
        return Ok(Outcome::AlreadyDone(row));
    }
    let error_path = dir.join("error.json");
    if error_path.exists() {
        std::fs::remove_file(&error_path).map_err(|e| SweepError::io(&error_path, e))?;
    }
    match train_point(plan, runs, point, device, log) {
        Ok(row) => {
            results::write_row(runs, &row)?;
            // From the folder's own plan: `plan` may be an older one that it extends.
            results::rebuild_tables(runs, &read_adopted_plan(runs)?)?;
            Ok(Outcome::Trained(row))
        }
        Err(e) => {
            let record = RunError {
                error: e.to_string(),
                hostname: hostname().to_string(),
            };
            write_json(&error_path, &record)?;
            Err(e)
        }
    }
}

/// Train the point (resuming, or restarting a checkpoint a kill left inconsistent) and
/// make its row.
fn train_point(
    plan: &IsoFlopPlan,
    runs: &Path,
    point: &PlanPoint,
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<RunRow, SweepError> {
    let vocab = plan
        .vocabulary(point.codebook)
        .expect("validated plans list every point's vocabulary");
    let tokens = prepare_vocabulary(plan, vocab, runs, device, log)?;
    let splits = prepare_data(plan, point, runs)?;
    let dir = run_dir(runs, &point.run_id);
    let train_dir = dir.join("train");
    let config = plan.train_config(point, &tokens, splits.as_deref(), &train_dir)?;
    let wall_path = dir.join("wall.json");
    let before = match std::fs::read_to_string(&wall_path) {
        Ok(text) => {
            serde_json::from_str::<Wall>(&text)
                .map_err(|e| SweepError::invalid(&wall_path, e))?
                .seconds
        }
        Err(_) => 0.0,
    };
    let started = Instant::now();
    let mut saved = Instant::now();
    let mut on_event = |event: &TrainEvent| match event {
        TrainEvent::Started { from, total, .. } => log(&format!(
            "{}: {} steps{} (D {}, C {:e})",
            point.run_id,
            total,
            if *from > 0 {
                format!(", resuming at step {from}")
            } else {
                String::new()
            },
            point.tokens,
            point.budget
        )),
        TrainEvent::Step { .. } if saved.elapsed() >= WALL_SAVE_EVERY => {
            saved = Instant::now();
            let wall = Wall {
                seconds: before + started.elapsed().as_secs_f64(),
            };
            // Losing one save only under-counts the wall time of a killed attempt.
            let _ = write_json(&wall_path, &wall);
        }
        TrainEvent::Step { .. } => {}
        TrainEvent::Eval(e) => log(&format!(
            "{}: step {}: train {:.4}, test CE {:.4}, L_u {:.4}",
            point.run_id, e.step, e.train_loss, e.test.cross_entropy, e.test.normalized_loss
        )),
    };
    let report = match train(&config, device, &mut on_event) {
        Ok(report) => report,
        Err(ModelError::File(e @ FileError::Invalid { .. }))
            if e.path().starts_with(&train_dir) =>
        {
            log(&format!(
                "{}: cannot resume ({e}); training again from the start",
                point.run_id
            ));
            std::fs::remove_dir_all(&train_dir).map_err(|e| SweepError::io(&train_dir, e))?;
            train(&config, device, &mut on_event)?
        }
        Err(e) => return Err(e.into()),
    };
    let wall_s = before + started.elapsed().as_secs_f64();
    write_json(&wall_path, &Wall { seconds: wall_s })?;
    Ok(row(plan, point, &report, wall_s))
}

/// The split lists of `point`'s data subset in `RUNS/data/<name>/`, written first (none for a
/// point on the whole train split).
fn prepare_data(
    plan: &IsoFlopPlan,
    point: &PlanPoint,
    runs: &Path,
) -> Result<Option<PathBuf>, SweepError> {
    let Some(name) = &point.data else {
        return Ok(None);
    };
    let subset = plan
        .subset(name)
        .expect("validated plans list every point's subset");
    let dir = data_ladder::lists_dir(runs, name);
    if dir.is_dir() {
        return Ok(Some(dir));
    }
    let clips = Corpus::open(&plan.corpus)
        .and_then(|c| c.clip_metadata())
        .map_err(|e| SweepError::invalid(&plan.corpus, e))?;
    data_ladder::write_lists(runs, &clips, subset).map(Some)
}

/// Cross-entropy and L_u of `loss` on its clips of `origin` (NaN when it has one origin).
fn origin_losses(loss: Option<&SplitLoss>, origin: Origin) -> (f64, f64) {
    loss.and_then(|l| l.by_origin.get(&origin))
        .map_or((f64::NAN, f64::NAN), |l| {
            (l.cross_entropy, l.normalized_loss)
        })
}

/// The results row of a finished point.
fn row(plan: &IsoFlopPlan, point: &PlanPoint, report: &TrainReport, wall_s: f64) -> RunRow {
    let e = &report.eval;
    let vocab = plan.vocabulary(point.codebook).expect("validated plan");
    let subset = point.data.as_deref().and_then(|n| plan.subset(n));
    // A point on the whole train split has that split's hours (NaN in plans made before
    // the plan recorded them).
    let hours_of = match &point.data {
        Some(_) => subset,
        None => plan.train_split.as_ref(),
    };
    let (real, synth) = (
        origin_losses(Some(&e.test), Origin::Real),
        origin_losses(Some(&e.test), Origin::Synth),
    );
    let hyper = plan.hyper(point);
    let mut row = RunRow {
        run_id: point.run_id.clone(),
        budget: point.budget,
        n_nv: e.n_nv,
        n_v: e.n_v,
        vocab: vocab.codebook_size as u64,
        d_model: point.d_model as u64,
        layers: point.n_layers as u64,
        heads: point.n_heads as u64,
        tokens: e.tokens_seen,
        train_loss: e.train_loss,
        test_loss: e.test.cross_entropy,
        norm_test_loss: e.test.normalized_loss,
        wall_s,
        flops: e.flops_exact,
        seed: point.seed(plan),
        git_revision: git_revision().to_string(),
        hostname: hostname().to_string(),
        device: report.device.clone(),
        precision: plan.train.precision.to_string(),
        index: point.index as u64,
        model: point.model.clone(),
        vocab_nominal: point.codebook as u64,
        tokens_planned: point.tokens,
        steps: report.steps,
        flops_6n: e.flops_6n,
        epochs: point.epochs,
        flags: point
            .flags
            .iter()
            .map(|f| f.as_str())
            .collect::<Vec<_>>()
            .join(";"),
        best_step: 0,
        best_test_loss: f64::NAN,
        best_norm_test_loss: f64::NAN,
        data: point.data.clone().unwrap_or_default(),
        data_source: plan.data_source(point).to_string(),
        data_fraction: subset.map_or(1.0, |s| s.fraction),
        unique_tokens: point.unique_tokens(plan),
        hours: hours_of.map_or(f64::NAN, |s| s.hours),
        synth_share: hours_of.map_or(f64::NAN, |s| s.synth_hours / s.hours),
        real_test_loss: real.0,
        real_norm_test_loss: real.1,
        synth_test_loss: synth.0,
        synth_norm_test_loss: synth.1,
        best_real_test_loss: f64::NAN,
        best_real_norm_test_loss: f64::NAN,
        best_synth_test_loss: f64::NAN,
        best_synth_norm_test_loss: f64::NAN,
        lr: hyper.lr,
        weight_decay: hyper.weight_decay,
        dropout: hyper.dropout,
        recipe: plan.recipe_name(),
    };
    set_best(&mut row, e.best.as_ref());
    row
}

/// Fill `row`'s validation-selected columns from `best` (zero step and NaN losses for none).
fn set_best(row: &mut RunRow, best: Option<&BestEval>) {
    let test = best.map(|b| &b.test);
    let (real, synth) = (
        origin_losses(test, Origin::Real),
        origin_losses(test, Origin::Synth),
    );
    row.best_step = best.map_or(0, |b| b.step);
    row.best_test_loss = test.map_or(f64::NAN, |t| t.cross_entropy);
    row.best_norm_test_loss = test.map_or(f64::NAN, |t| t.normalized_loss);
    (row.best_real_test_loss, row.best_real_norm_test_loss) = real;
    (row.best_synth_test_loss, row.best_synth_norm_test_loss) = synth;
}

/// A finished point whose validation-selected checkpoint [`reselect`] changed.
#[derive(Debug, Clone, PartialEq)]
pub struct Reselected {
    /// The point's row before.
    pub before: RunRow,
    /// Its row now.
    pub after: RunRow,
}

/// Select each finished point's checkpoint again from its `evals.jsonl` by today's rule (on
/// the validation clips of the point's own data source), rewrite the rows it changes, and
/// return them. Rows finished before the rule selected on the whole split are corrected;
/// a folder already selected by it is left byte-identical.
pub fn reselect(plan: &IsoFlopPlan, runs: &Path) -> Result<Vec<Reselected>, SweepError> {
    let mut changed = Vec::new();
    for point in &plan.points {
        let Some(before) = read_row(runs, &point.run_id)? else {
            continue;
        };
        let train_dir = run_dir(runs, &point.run_id).join("train");
        let best = selection::reselect(&train_dir, plan.data_source(point).origin())?;
        let mut after = before.clone();
        set_best(&mut after, best.as_ref());
        if !same_row(&before, &after) {
            results::write_row(runs, &after)?;
            changed.push(Reselected { before, after });
        }
    }
    Ok(changed)
}

/// Equal rows, NaN equal to NaN.
fn same_row(a: &RunRow, b: &RunRow) -> bool {
    serde_json::to_value(a).ok() == serde_json::to_value(b).ok()
}

/// `git describe --always --dirty` of the source tree this binary was built from (recorded by
/// `build.rs`), or `unknown` (built without git, or not from a checkout).
pub fn git_revision() -> &'static str {
    env!("MOTIONSCALE_GIT_REVISION")
}

/// This machine's host name (`unknown` if the system does not say).
pub fn hostname() -> &'static str {
    static HOST: OnceLock<String> = OnceLock::new();
    HOST.get_or_init(|| {
        let mut buf = [0u8; 256];
        // SAFETY: gethostname writes at most buf.len() bytes into the buffer it is given.
        let ok = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) } == 0;
        let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
        ok.then(|| String::from_utf8_lossy(&buf[..end]).into_owned())
            .filter(|h| !h.is_empty())
            .unwrap_or_else(|| "unknown".into())
    })
}
