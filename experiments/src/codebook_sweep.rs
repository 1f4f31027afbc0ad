//! The codebook-size sweep (our ScaMo Fig. 6): every (quantizer, codebook) pair trained with
//! the same steps, its codebook use read on the train split (tokens ≫ codes) and its
//! reconstruction on the chosen split (with that split's N, utilisation and the uniform
//! tokenizer's coverage 1 − e^(−N/K) beside it), as a table.
//!
//! ```text
//! OUT/<quantizer>-<codebook>/     each run's tokenizer checkpoint (resumable),
//!                                 eval-train.json and eval-<split>.json
//! OUT/sweep.csv, sweep.parquet    one row per run (columns: SweepRow's fields)
//! OUT/utilization.{svg,png}       utilisation, entropy and MPJPE (global and root-aligned)
//! OUT/entropy.{svg,png}           against codebook size, one line per quantizer
//! OUT/mpjpe.{svg,png}, OUT/mpjpe_root.{svg,png}
//! ```
//!
//! Re-running the same command resumes unfinished runs and reuses finished evaluations.

use arrow_array::{ArrayRef, Float64Array, RecordBatch, StringArray, UInt64Array};
use candle_core::Device;
use ingest::corpus::Corpus;
use motionscale_core::{read_json, write_json};
use parquet::arrow::ArrowWriter;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use tokenizer::error::TokenizerError;
use tokenizer::evaluate::{evaluate, EvalReport};
use tokenizer::model::{MotionTokenizer, TokenizerConfig};
use tokenizer::train::{train, StepReport, TrainConfig};
use tokenizer::{Bound, ConvConfig};

/// One run of the sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepRow {
    /// `fsq` or `vq`.
    pub quantizer: String,
    /// Requested (nominal) codebook size.
    pub codebook: u64,
    /// Real number of codes.
    pub codebook_size: u64,
    /// Fraction of codes used on the train split (the headline: tokens ≫ codes there).
    pub utilization: f64,
    /// exp(entropy) of code usage on the train split.
    pub perplexity: f64,
    /// Entropy of code usage on the train split, nats.
    pub entropy: f64,
    /// Mean |reconstruction − input| of normalised features on the evaluated split.
    pub recon_l1: f64,
    /// Mean per-joint position error on global joints, millimetres, evaluated split.
    pub mpjpe_mm: f64,
    /// Mean per-joint position error on root-aligned joints (MoMask's convention),
    /// millimetres, evaluated split.
    pub mpjpe_root_mm: f64,
    /// Training steps.
    pub steps: u64,
    /// Training wall time, seconds.
    pub train_s: f64,
    /// Tokens of the train split.
    pub tokens: u64,
    /// The split reconstruction is measured on (`--split`).
    pub split: String,
    /// Tokens of that split, N.
    pub split_tokens: u64,
    /// Fraction of codes used on that split.
    pub split_utilization: f64,
    /// What a uniform tokenizer would use with that split's tokens, 1 − e^(−N/K).
    pub split_uniform_coverage: f64,
}

impl SweepRow {
    fn new(train: &EvalReport, split: &EvalReport, steps: u64, train_s: f64) -> Self {
        Self {
            quantizer: train.quantizer.clone(),
            codebook: train.nominal_codebook as u64,
            codebook_size: train.codebook_size as u64,
            utilization: train.utilization,
            perplexity: train.perplexity,
            entropy: train.entropy,
            recon_l1: split.recon_l1,
            mpjpe_mm: split.mpjpe_mm,
            mpjpe_root_mm: split.mpjpe_root_mm,
            steps,
            train_s,
            tokens: train.tokens,
            split: split.split.clone(),
            split_tokens: split.tokens,
            split_utilization: split.utilization,
            split_uniform_coverage: split.uniform_coverage,
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
    let corpus = Corpus::open(corpus_dir).map_err(|e| TokenizerError::File {
        path: corpus_dir.to_path_buf(),
        message: e.to_string(),
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
            let id = MotionTokenizer::content_id(&dir)?;
            let mut reports = Vec::new();
            for split in ["train", plan.split.as_str()] {
                let eval_path = dir.join(format!("eval-{split}.json"));
                let cached = read_json::<EvalReport>(&eval_path)
                    .ok()
                    .filter(|r| r.tokenizer_id == id && r.mpjpe_root_mm > 0.0);
                let report = match cached {
                    Some(report) => report,
                    None => {
                        let tokenizer = MotionTokenizer::load(&dir, device)?;
                        let report = evaluate(&tokenizer, dir.clone(), &corpus, split, |d, t| {
                            on_event(SweepEvent::Eval(&name, d, t))
                        })?;
                        write_json(&eval_path, &report)?;
                        report
                    }
                };
                reports.push(report);
            }
            let row = SweepRow::new(&reports[0], &reports[1], state.step, state.wall_s);
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
        "quantizer,codebook,codebook_size,utilization,perplexity,entropy,recon_l1,mpjpe_mm,\
         mpjpe_root_mm,steps,train_s,tokens,split,split_tokens,split_utilization,\
         split_uniform_coverage\n",
    );
    for r in rows {
        csv.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            r.quantizer,
            r.codebook,
            r.codebook_size,
            r.utilization,
            r.perplexity,
            r.entropy,
            r.recon_l1,
            r.mpjpe_mm,
            r.mpjpe_root_mm,
            r.steps,
            r.train_s,
            r.tokens,
            r.split,
            r.split_tokens,
            r.split_utilization,
            r.split_uniform_coverage
        ));
    }
    let csv_path = out.join("sweep.csv");
    motionscale_core::write_atomic(&csv_path, csv.as_bytes())
        .map_err(|e| file_error(&csv_path, e))?;
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
        ("mpjpe_root_mm", f64s(&|r| r.mpjpe_root_mm)),
        ("steps", u64s(&|r| r.steps)),
        ("train_s", f64s(&|r| r.train_s)),
        ("tokens", u64s(&|r| r.tokens)),
        (
            "split",
            Arc::new(StringArray::from_iter_values(rows.iter().map(|r| &r.split))) as ArrayRef,
        ),
        ("split_tokens", u64s(&|r| r.split_tokens)),
        ("split_utilization", f64s(&|r| r.split_utilization)),
        (
            "split_uniform_coverage",
            f64s(&|r| r.split_uniform_coverage),
        ),
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
    motionscale_core::write_atomic(&parquet_path, &bytes).map_err(|e| file_error(&parquet_path, e))
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
    // Usage is read on the train split, reconstruction on the split the sweep evaluated.
    let split = rows.first().map_or("evaluated", |r| r.split.as_str());
    type Metric<'a> = (&'a str, String, &'a dyn Fn(&SweepRow) -> f64);
    let metrics: [Metric; 4] = [
        (
            "utilization",
            "codebook utilisation, train split (%)".into(),
            &|r| 100.0 * r.utilization,
        ),
        (
            "entropy",
            "entropy of code usage, train split (nats)".into(),
            &|r| r.entropy,
        ),
        (
            "mpjpe",
            format!("MPJPE, global joints, {split} split (mm)"),
            &|r| r.mpjpe_mm,
        ),
        (
            "mpjpe_root",
            format!("MPJPE, root-aligned joints, {split} split (mm)"),
            &|r| r.mpjpe_root_mm,
        ),
    ];
    for (name, label, value) in metrics {
        let mut chart = plot::Chart::new(
            format!("{label} vs codebook size"),
            "codebook size (nominal 2^k; FSQ uses Π L_i ≤ 2^k codes)",
            label.as_str(),
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
