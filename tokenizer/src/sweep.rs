//! The codebook-size sweep (our ScaMo Fig. 6): every (quantizer, codebook) pair trained with
//! the same steps and evaluated on one split, as a table.
//!
//! ```text
//! OUT/<quantizer>-<codebook>/     each run's tokenizer checkpoint (resumable) and eval-<split>.json
//! OUT/sweep.csv, sweep.parquet    one row per run (columns: SweepRow's fields)
//! OUT/utilization.{svg,png}       utilisation, entropy and MPJPE against codebook size,
//! OUT/entropy.{svg,png}           one line per quantizer
//! OUT/mpjpe.{svg,png}
//! ```
//!
//! Re-running the same command resumes unfinished runs and reuses finished evaluations.

use crate::checkpoint::{read_json, write_json};
use crate::error::TokenizerError;
use crate::evaluate::{evaluate, EvalReport};
use crate::model::{MotionTokenizer, TokenizerConfig};
use crate::train::{train, StepReport, TrainConfig};
use crate::{Bound, ConvConfig};
use arrow_array::{ArrayRef, Float64Array, RecordBatch, StringArray, UInt64Array};
use candle_core::Device;
use ingest::corpus::Corpus;
use parquet::arrow::ArrowWriter;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;

/// One run of the sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepRow {
    /// `fsq` or `vq`.
    pub quantizer: String,
    /// Requested (nominal) codebook size.
    pub codebook: u64,
    /// Real number of codes.
    pub codebook_size: u64,
    /// Fraction of codes used on the split.
    pub utilization: f64,
    /// exp(entropy) of code usage.
    pub perplexity: f64,
    /// Entropy of code usage in nats.
    pub entropy: f64,
    /// Mean |reconstruction − input| of normalised features.
    pub recon_l1: f64,
    /// Mean per-joint position error, millimetres.
    pub mpjpe_mm: f64,
    /// Training steps.
    pub steps: u64,
    /// Training wall time, seconds.
    pub train_s: f64,
    /// Tokens evaluated.
    pub tokens: u64,
}

impl SweepRow {
    fn new(report: &EvalReport, steps: u64, train_s: f64) -> Self {
        Self {
            quantizer: report.quantizer.clone(),
            codebook: report.nominal_codebook as u64,
            codebook_size: report.codebook_size as u64,
            utilization: report.utilization,
            perplexity: report.perplexity,
            entropy: report.entropy,
            recon_l1: report.recon_l1,
            mpjpe_mm: report.mpjpe_mm,
            steps,
            train_s,
            tokens: report.tokens,
        }
    }
}

/// What the sweep tells its caller as it goes.
pub enum SweepEvent<'a> {
    /// A training step of run `name`.
    Step(&'a str, StepReport),
    /// Evaluation progress of run `name`: (clips done, clips).
    Eval(&'a str, usize, usize),
    /// Run `name` finished with this row.
    Done(&'a str, &'a SweepRow),
}

/// The grid to run.
#[derive(Debug, Clone)]
pub struct SweepPlan {
    /// Quantizers (`fsq`, `vq`).
    pub quantizers: Vec<String>,
    /// Nominal codebook sizes.
    pub codebooks: Vec<usize>,
    /// Encoder/decoder sizes shared by every run.
    pub conv: ConvConfig,
    /// FSQ bound.
    pub bound: Bound,
    /// Training settings shared by every run.
    pub train: TrainConfig,
    /// Split the metrics are computed on.
    pub split: String,
}

/// Run (or resume) every pair of `plan` on `corpus_dir` into `out`; writes the tables and
/// returns the rows in plan order.
pub fn sweep(
    corpus_dir: &Path,
    out: &Path,
    plan: &SweepPlan,
    device: &Device,
    mut on_event: impl FnMut(SweepEvent),
) -> Result<Vec<SweepRow>, TokenizerError> {
    let corpus = Corpus::open(corpus_dir).map_err(|message| TokenizerError::File {
        path: corpus_dir.to_path_buf(),
        message,
    })?;
    let mut rows = Vec::new();
    for quantizer in &plan.quantizers {
        for &codebook in &plan.codebooks {
            let name = format!("{quantizer}-{codebook}");
            let config = TokenizerConfig::new(quantizer, codebook, plan.bound, plan.conv.clone())?;
            let dir = out.join(&name);
            let state = train(corpus_dir, &dir, config, plan.train.clone(), device, |r| {
                on_event(SweepEvent::Step(&name, r))
            })?;
            let eval_path = dir.join(format!("eval-{}.json", plan.split));
            let id = MotionTokenizer::content_id(&dir)?;
            let cached = read_json::<EvalReport>(&eval_path)
                .ok()
                .filter(|r| r.tokenizer_id == id);
            let report = match cached {
                Some(report) => report,
                None => {
                    let tokenizer = MotionTokenizer::load(&dir, device)?;
                    let report =
                        evaluate(&tokenizer, dir.clone(), &corpus, &plan.split, |d, t| {
                            on_event(SweepEvent::Eval(&name, d, t))
                        })?;
                    write_json(&eval_path, &report)?;
                    report
                }
            };
            let row = SweepRow::new(&report, state.step, state.wall_s);
            on_event(SweepEvent::Done(&name, &row));
            rows.push(row);
        }
    }
    write_tables(out, &rows)?;
    write_plots(out, &rows)?;
    Ok(rows)
}

fn file_error(path: &Path, e: impl std::fmt::Display) -> TokenizerError {
    TokenizerError::File {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Write `OUT/sweep.csv` and `OUT/sweep.parquet` (atomically).
pub fn write_tables(out: &Path, rows: &[SweepRow]) -> Result<(), TokenizerError> {
    let mut csv = String::from(
        "quantizer,codebook,codebook_size,utilization,perplexity,entropy,recon_l1,mpjpe_mm,steps,train_s,tokens\n",
    );
    for r in rows {
        csv.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{}\n",
            r.quantizer,
            r.codebook,
            r.codebook_size,
            r.utilization,
            r.perplexity,
            r.entropy,
            r.recon_l1,
            r.mpjpe_mm,
            r.steps,
            r.train_s,
            r.tokens
        ));
    }
    let csv_path = out.join("sweep.csv");
    ingest::npy::write_atomic(&csv_path, csv.as_bytes()).map_err(|e| file_error(&csv_path, e))?;
    let u64s = |f: &dyn Fn(&SweepRow) -> u64| {
        Arc::new(UInt64Array::from_iter_values(rows.iter().map(f))) as ArrayRef
    };
    let f64s = |f: &dyn Fn(&SweepRow) -> f64| {
        Arc::new(Float64Array::from_iter_values(rows.iter().map(f))) as ArrayRef
    };
    let batch = RecordBatch::try_from_iter([
        (
            "quantizer",
            Arc::new(StringArray::from_iter_values(
                rows.iter().map(|r| &r.quantizer),
            )) as ArrayRef,
        ),
        ("codebook", u64s(&|r| r.codebook)),
        ("codebook_size", u64s(&|r| r.codebook_size)),
        ("utilization", f64s(&|r| r.utilization)),
        ("perplexity", f64s(&|r| r.perplexity)),
        ("entropy", f64s(&|r| r.entropy)),
        ("recon_l1", f64s(&|r| r.recon_l1)),
        ("mpjpe_mm", f64s(&|r| r.mpjpe_mm)),
        ("steps", u64s(&|r| r.steps)),
        ("train_s", f64s(&|r| r.train_s)),
        ("tokens", u64s(&|r| r.tokens)),
    ])
    .map_err(|e| TokenizerError::Argument(format!("sweep table: {e}")))?;
    let parquet_path = out.join("sweep.parquet");
    let mut bytes = Vec::new();
    let mut writer = ArrowWriter::try_new(&mut bytes, batch.schema(), None)
        .map_err(|e| file_error(&parquet_path, e))?;
    writer
        .write(&batch)
        .and_then(|_| writer.close().map(|_| ()))
        .map_err(|e| file_error(&parquet_path, e))?;
    ingest::npy::write_atomic(&parquet_path, &bytes).map_err(|e| file_error(&parquet_path, e))
}

/// Utilisation, entropy and MPJPE against codebook size (log x), one line per quantizer.
pub fn write_plots(out: &Path, rows: &[SweepRow]) -> Result<(), TokenizerError> {
    let mut quantizers: Vec<&str> = rows.iter().map(|r| r.quantizer.as_str()).collect();
    quantizers.dedup();
    // Nominal sizes on x: FSQ's real sizes (240, 1000, …) sit next to VQ's and would crowd
    // the ticks; the tables keep both.
    let mut sizes: Vec<f64> = rows.iter().map(|r| r.codebook as f64).collect();
    sizes.sort_by(f64::total_cmp);
    sizes.dedup();
    type Metric<'a> = (&'a str, &'a str, &'a dyn Fn(&SweepRow) -> f64);
    let metrics: [Metric; 3] = [
        ("utilization", "codebook utilisation (%)", &|r| {
            100.0 * r.utilization
        }),
        ("entropy", "entropy of code usage (nats)", &|r| r.entropy),
        ("mpjpe", "MPJPE (mm)", &|r| r.mpjpe_mm),
    ];
    for (name, label, value) in metrics {
        let mut chart = plot::Chart::new(
            format!("{label} vs codebook size"),
            "codebook size (nominal 2^k; FSQ uses Π L_i ≤ 2^k codes)",
            label,
        );
        chart.log_x = true;
        chart.x_ticks = Some(sizes.clone());
        for (i, q) in quantizers.iter().enumerate() {
            let points = rows
                .iter()
                .filter(|r| r.quantizer == *q)
                .map(|r| (r.codebook as f64, value(r)))
                .collect();
            chart
                .series
                .push(plot::Series::line(q.to_uppercase(), points).with_color(i));
        }
        chart
            .write(&out.join(name))
            .map_err(|e| file_error(&out.join(name), e))?;
    }
    Ok(())
}
