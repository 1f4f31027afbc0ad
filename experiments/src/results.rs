//! The results table: one [`RunRow`] per finished point. Each run's row is written alone to
//! `RUNS/<run_id>/result.json` (temp + rename: the source of truth); `RUNS/results.csv` and
//! `RUNS/results.parquet` are rebuilt from all of them, in plan order, under a lock and
//! again by temp + rename. A kill at any moment therefore leaves every table whole, and a
//! rebuild can never hold a row twice or half a row.
//!
//! Columns ([`COLUMNS`], the declared Arrow schema of [`schema`]): the spec's `run_id, budget,
//! n_nv, n_v, vocab, d_model, layers, heads, tokens, train_loss, test_loss, norm_test_loss,
//! wall_s, flops` (the names `motionscale fit` reads by default), then `seed, git_revision,
//! hostname, device, precision` and `index, model, vocab_nominal, tokens_planned, steps,
//! flops_6n, epochs, flags`, then the validation-selected evaluation's `best_step,
//! best_test_loss, best_norm_test_loss` (0 / NaN without validation clips).

use crate::plan::{IsoFlopPlan, PlanPoint};
use crate::SweepError;
use arrow_array::{ArrayRef, Float64Array, RecordBatch, StringArray, UInt64Array};
use arrow_schema::{DataType, Field, Schema};
use motionscale_core::lock::FileLock;
use parquet::arrow::ArrowWriter;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// File name of a run's row inside its folder.
pub const RESULT_FILE: &str = "result.json";

/// The result of one finished point.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunRow {
    /// Run folder name.
    pub run_id: String,
    /// Planned compute budget C (the IsoFLOP group).
    pub budget: f64,
    /// Non-vocabulary parameters.
    pub n_nv: u64,
    /// Vocabulary parameters (2·V·d: untied embedding and head).
    pub n_v: u64,
    /// Motion codes K the model saw (FSQ 2^8 → 240).
    pub vocab: u64,
    /// Width d.
    pub d_model: u64,
    /// Blocks.
    pub layers: u64,
    /// Heads.
    pub heads: u64,
    /// Motion tokens trained on, D (the budget rounded up to whole batches).
    pub tokens: u64,
    /// Mean training loss over the last evaluation interval.
    pub train_loss: f64,
    /// Test cross-entropy over motion codes (nats).
    pub test_loss: f64,
    /// Normalised test loss L_u (ScaMo Eq. 8).
    pub norm_test_loss: f64,
    /// Training wall time in seconds, summed over resumed attempts.
    pub wall_s: f64,
    /// Exact FLOPs executed (matmuls incl. attention and padding).
    pub flops: f64,
    /// Seed of weights and batch order.
    pub seed: u64,
    /// `git describe --always --dirty` of the source tree, or `unknown`.
    pub git_revision: String,
    /// Host that finished the run.
    pub hostname: String,
    /// Device that finished the run (`cpu`, `cuda:N`; rows from before devices: `cpu`).
    #[serde(default = "cpu")]
    pub device: String,
    /// Arithmetic of the run (`f32`, `bf16`).
    #[serde(default = "f32")]
    pub precision: String,
    /// Plan row.
    pub index: u64,
    /// Model preset.
    pub model: String,
    /// Nominal codebook size.
    pub vocab_nominal: u64,
    /// Planned D.
    pub tokens_planned: u64,
    /// Optimiser steps.
    pub steps: u64,
    /// 6·(N_nv + N_v)·D of the tokens trained on.
    pub flops_6n: f64,
    /// D over one epoch of the train split.
    pub epochs: f64,
    /// The plan's flags, `;`-separated.
    pub flags: String,
    /// Step of the evaluation with the lowest validation cross-entropy (0: no validation).
    #[serde(default)]
    pub best_step: u64,
    /// Test cross-entropy at that step (NaN: no validation).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub best_test_loss: f64,
    /// Test L_u at that step (NaN: no validation).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub best_norm_test_loss: f64,
    /// The train subset (`sweep plan --data-fractions`; empty: the whole train split).
    #[serde(default)]
    pub data: String,
    /// The clips the subset draws from (`real`, `synth`, `all`).
    #[serde(default = "all")]
    pub data_source: String,
    /// Its share of the source's train hours.
    #[serde(default = "one")]
    pub data_fraction: f64,
    /// Loss positions of one epoch of the data trained on, U (D / U = epochs; 0: not recorded).
    #[serde(default)]
    pub unique_tokens: u64,
    /// Train hours of the subset, mirrored copies included (NaN: not recorded).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub hours: f64,
    /// Synthetic share of those hours (NaN: not recorded).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub synth_share: f64,
    /// Test cross-entropy on the captured clips (NaN: the test split has one origin).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub real_test_loss: f64,
    /// Test L_u on the captured clips.
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub real_norm_test_loss: f64,
    /// Test cross-entropy on the synthetic clips.
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub synth_test_loss: f64,
    /// Test L_u on the synthetic clips.
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub synth_norm_test_loss: f64,
    /// Captured clips' test cross-entropy at the validation-selected step.
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub best_real_test_loss: f64,
    /// Captured clips' test L_u at the validation-selected step.
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub best_real_norm_test_loss: f64,
    /// Synthetic clips' test cross-entropy at the validation-selected step.
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub best_synth_test_loss: f64,
    /// Synthetic clips' test L_u at the validation-selected step.
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub best_synth_norm_test_loss: f64,
    /// Peak learning rate it trained with (NaN: not recorded).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub lr: f64,
    /// AdamW weight decay it trained with (NaN: not recorded).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub weight_decay: f64,
    /// Residual dropout it trained with (NaN: not recorded).
    #[serde(default = "nan", deserialize_with = "nan_if_null")]
    pub dropout: f64,
    /// The plan's recipe by name (empty: none, or not recorded).
    #[serde(default)]
    pub recipe: String,
}

fn all() -> String {
    "all".into()
}

fn one() -> f64 {
    1.0
}

fn nan() -> f64 {
    f64::NAN
}

/// A float that JSON wrote as `null` (serde_json's NaN) reads back as NaN.
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

fn cpu() -> String {
    "cpu".into()
}

fn f32() -> String {
    "f32".into()
}

/// One cell of a row.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Cell<'a> {
    /// Unsigned integer.
    U64(u64),
    /// Float.
    F64(f64),
    /// Text.
    Str(&'a str),
}

/// A column: name, Arrow type and how to read it from a row.
pub type Column = (&'static str, DataType, fn(&RunRow) -> Cell<'_>);

/// Every column of the table, in order.
pub const COLUMNS: [Column; 48] = [
    ("run_id", DataType::Utf8, |r| Cell::Str(&r.run_id)),
    ("budget", DataType::Float64, |r| Cell::F64(r.budget)),
    ("n_nv", DataType::UInt64, |r| Cell::U64(r.n_nv)),
    ("n_v", DataType::UInt64, |r| Cell::U64(r.n_v)),
    ("vocab", DataType::UInt64, |r| Cell::U64(r.vocab)),
    ("d_model", DataType::UInt64, |r| Cell::U64(r.d_model)),
    ("layers", DataType::UInt64, |r| Cell::U64(r.layers)),
    ("heads", DataType::UInt64, |r| Cell::U64(r.heads)),
    ("tokens", DataType::UInt64, |r| Cell::U64(r.tokens)),
    ("train_loss", DataType::Float64, |r| Cell::F64(r.train_loss)),
    ("test_loss", DataType::Float64, |r| Cell::F64(r.test_loss)),
    ("norm_test_loss", DataType::Float64, |r| {
        Cell::F64(r.norm_test_loss)
    }),
    ("wall_s", DataType::Float64, |r| Cell::F64(r.wall_s)),
    ("flops", DataType::Float64, |r| Cell::F64(r.flops)),
    ("seed", DataType::UInt64, |r| Cell::U64(r.seed)),
    ("git_revision", DataType::Utf8, |r| {
        Cell::Str(&r.git_revision)
    }),
    ("hostname", DataType::Utf8, |r| Cell::Str(&r.hostname)),
    ("device", DataType::Utf8, |r| Cell::Str(&r.device)),
    ("precision", DataType::Utf8, |r| Cell::Str(&r.precision)),
    ("index", DataType::UInt64, |r| Cell::U64(r.index)),
    ("model", DataType::Utf8, |r| Cell::Str(&r.model)),
    ("vocab_nominal", DataType::UInt64, |r| {
        Cell::U64(r.vocab_nominal)
    }),
    ("tokens_planned", DataType::UInt64, |r| {
        Cell::U64(r.tokens_planned)
    }),
    ("steps", DataType::UInt64, |r| Cell::U64(r.steps)),
    ("flops_6n", DataType::Float64, |r| Cell::F64(r.flops_6n)),
    ("epochs", DataType::Float64, |r| Cell::F64(r.epochs)),
    ("flags", DataType::Utf8, |r| Cell::Str(&r.flags)),
    ("best_step", DataType::UInt64, |r| Cell::U64(r.best_step)),
    ("best_test_loss", DataType::Float64, |r| {
        Cell::F64(r.best_test_loss)
    }),
    ("best_norm_test_loss", DataType::Float64, |r| {
        Cell::F64(r.best_norm_test_loss)
    }),
    ("data", DataType::Utf8, |r| Cell::Str(&r.data)),
    ("data_source", DataType::Utf8, |r| Cell::Str(&r.data_source)),
    ("data_fraction", DataType::Float64, |r| {
        Cell::F64(r.data_fraction)
    }),
    ("unique_tokens", DataType::UInt64, |r| {
        Cell::U64(r.unique_tokens)
    }),
    ("hours", DataType::Float64, |r| Cell::F64(r.hours)),
    ("synth_share", DataType::Float64, |r| {
        Cell::F64(r.synth_share)
    }),
    ("real_test_loss", DataType::Float64, |r| {
        Cell::F64(r.real_test_loss)
    }),
    ("real_norm_test_loss", DataType::Float64, |r| {
        Cell::F64(r.real_norm_test_loss)
    }),
    ("synth_test_loss", DataType::Float64, |r| {
        Cell::F64(r.synth_test_loss)
    }),
    ("synth_norm_test_loss", DataType::Float64, |r| {
        Cell::F64(r.synth_norm_test_loss)
    }),
    ("best_real_test_loss", DataType::Float64, |r| {
        Cell::F64(r.best_real_test_loss)
    }),
    ("best_real_norm_test_loss", DataType::Float64, |r| {
        Cell::F64(r.best_real_norm_test_loss)
    }),
    ("best_synth_test_loss", DataType::Float64, |r| {
        Cell::F64(r.best_synth_test_loss)
    }),
    ("best_synth_norm_test_loss", DataType::Float64, |r| {
        Cell::F64(r.best_synth_norm_test_loss)
    }),
    ("lr", DataType::Float64, |r| Cell::F64(r.lr)),
    ("weight_decay", DataType::Float64, |r| {
        Cell::F64(r.weight_decay)
    }),
    ("dropout", DataType::Float64, |r| Cell::F64(r.dropout)),
    ("recipe", DataType::Utf8, |r| Cell::Str(&r.recipe)),
];

impl PartialEq for RunRow {
    /// Column by column; a float the run did not record (NaN) equals another such.
    fn eq(&self, other: &Self) -> bool {
        COLUMNS
            .iter()
            .all(|(_, _, get)| match (get(self), get(other)) {
                (Cell::F64(a), Cell::F64(b)) => a == b || (a.is_nan() && b.is_nan()),
                (a, b) => a == b,
            })
    }
}

/// The Arrow schema of `results.parquet` (no nulls).
pub fn schema() -> Arc<Schema> {
    Arc::new(Schema::new(
        COLUMNS
            .iter()
            .map(|(name, ty, _)| Field::new(*name, ty.clone(), false))
            .collect::<Vec<_>>(),
    ))
}

/// `rows` as CSV text: a header row of [`COLUMNS`], then one line per row.
pub fn to_csv(rows: &[RunRow]) -> Result<Vec<u8>, SweepError> {
    let mut w = csv::Writer::from_writer(Vec::new());
    let csv_error = |e: csv::Error| SweepError::Argument(format!("results CSV: {e}"));
    w.write_record(COLUMNS.iter().map(|c| c.0))
        .map_err(csv_error)?;
    for row in rows {
        w.write_record(COLUMNS.iter().map(|(_, _, get)| match get(row) {
            Cell::U64(v) => v.to_string(),
            Cell::F64(v) => v.to_string(),
            Cell::Str(s) => s.to_string(),
        }))
        .map_err(csv_error)?;
    }
    w.into_inner()
        .map_err(|e| SweepError::Argument(format!("results CSV: {e}")))
}

/// Read a `results.csv` written by [`to_csv`] (its header names every [`RunRow`] field).
pub fn read_csv(path: &Path) -> Result<Vec<RunRow>, SweepError> {
    let mut reader = csv::Reader::from_path(path).map_err(|e| SweepError::invalid(path, e))?;
    reader
        .deserialize()
        .enumerate()
        .map(|(i, row)| {
            row.map_err(|e| SweepError::invalid(path, format!("data row {}: {e}", i + 1)))
        })
        .collect()
}

/// `rows` as a Parquet file (one record batch, [`schema`]).
pub fn to_parquet(rows: &[RunRow]) -> Result<Vec<u8>, SweepError> {
    let columns: Vec<ArrayRef> = COLUMNS
        .iter()
        .map(|(_, ty, get)| -> ArrayRef {
            let cells = rows.iter().map(get);
            match ty {
                DataType::UInt64 => {
                    Arc::new(UInt64Array::from_iter_values(cells.map(|c| match c {
                        Cell::U64(v) => v,
                        other => unreachable!("{other:?} in a UInt64 column"),
                    })))
                }
                DataType::Float64 => {
                    Arc::new(Float64Array::from_iter_values(cells.map(|c| match c {
                        Cell::F64(v) => v,
                        other => unreachable!("{other:?} in a Float64 column"),
                    })))
                }
                _ => Arc::new(StringArray::from_iter_values(cells.map(|c| match c {
                    Cell::Str(s) => s,
                    other => unreachable!("{other:?} in a Utf8 column"),
                }))),
            }
        })
        .collect();
    let parquet_error =
        |e: &dyn std::fmt::Display| SweepError::Argument(format!("results Parquet: {e}"));
    let batch = RecordBatch::try_new(schema(), columns).map_err(|e| parquet_error(&e))?;
    let mut bytes = Vec::new();
    let mut writer =
        ArrowWriter::try_new(&mut bytes, schema(), None).map_err(|e| parquet_error(&e))?;
    writer
        .write(&batch)
        .and_then(|_| writer.close().map(|_| ()))
        .map_err(|e| parquet_error(&e))?;
    Ok(bytes)
}

/// `RUNS/<run_id>/`.
pub fn run_dir(runs: &Path, run_id: &str) -> PathBuf {
    runs.join(run_id)
}

/// Read a run's `result.json`, if it exists.
pub fn read_row(runs: &Path, run_id: &str) -> Result<Option<RunRow>, SweepError> {
    let path = run_dir(runs, run_id).join(RESULT_FILE);
    match std::fs::read_to_string(&path) {
        Ok(text) => serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| SweepError::invalid(&path, e)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(SweepError::io(&path, e)),
    }
}

/// Write a run's `result.json` atomically.
pub fn write_row(runs: &Path, row: &RunRow) -> Result<(), SweepError> {
    let path = run_dir(runs, &row.run_id).join(RESULT_FILE);
    let text = serde_json::to_string_pretty(row).map_err(|e| SweepError::invalid(&path, e))?;
    motionscale_core::write_atomic(&path, text.as_bytes()).map_err(|e| SweepError::io(&path, e))
}

/// The rows of every finished point of `plan`, in plan order; a row that does not belong to
/// its point (another plan's run) is an error.
pub fn finished_rows(runs: &Path, plan: &IsoFlopPlan) -> Result<Vec<RunRow>, SweepError> {
    let mut rows = Vec::new();
    for point in &plan.points {
        if let Some(row) = read_row(runs, &point.run_id)? {
            if row.index != point.index as u64 || row.budget != point.budget {
                let path = run_dir(runs, &point.run_id).join(RESULT_FILE);
                return Err(SweepError::invalid(
                    &path,
                    format!(
                        "belongs to plan row {} (budget {}), not to this plan's row {}",
                        row.index, row.budget, point.index
                    ),
                ));
            }
            rows.push(with_settings(row, plan, point));
        }
    }
    Ok(rows)
}

/// `row` with the settings its plan gave it where the row predates their columns.
fn with_settings(mut row: RunRow, plan: &IsoFlopPlan, point: &PlanPoint) -> RunRow {
    if row.lr.is_nan() {
        let hyper = plan.hyper(point);
        (row.lr, row.weight_decay, row.dropout) = (hyper.lr, hyper.weight_decay, hyper.dropout);
        row.recipe = plan.recipe_name();
    }
    row
}

/// Rebuild `RUNS/results.csv` and `RUNS/results.parquet` from every `result.json` of `plan`
/// (under `RUNS/.results.lock`, each file by temp + rename); returns the rows.
pub fn rebuild_tables(runs: &Path, plan: &IsoFlopPlan) -> Result<Vec<RunRow>, SweepError> {
    let _lock = FileLock::acquire(&runs.join(".results.lock"))?;
    let rows = finished_rows(runs, plan)?;
    for (name, bytes) in [
        ("results.csv", to_csv(&rows)?),
        ("results.parquet", to_parquet(&rows)?),
    ] {
        let path = runs.join(name);
        motionscale_core::write_atomic(&path, &bytes).map_err(|e| SweepError::io(&path, e))?;
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(i: u64) -> RunRow {
        RunRow {
            run_id: format!("c1e12-cpu-50K-v{i}"),
            budget: 1e12,
            n_nv: 74_048,
            n_v: 31_104,
            vocab: 240,
            d_model: 64,
            layers: 1,
            heads: 1,
            tokens: 1000 + i,
            train_loss: 5.25,
            test_loss: 5.5,
            norm_test_loss: 0.125,
            wall_s: 1.5,
            flops: 1.25e12,
            seed: 0,
            git_revision: "abc, \"quoted\"".into(),
            hostname: "host".into(),
            device: "cuda:1".into(),
            precision: "bf16".into(),
            index: i,
            model: "cpu-50K".into(),
            vocab_nominal: 256,
            tokens_planned: 999,
            steps: 3,
            flops_6n: 1.1e12,
            epochs: 0.5,
            flags: "exceeds-data".into(),
            best_step: 3 + i,
            best_test_loss: 1.25,
            best_norm_test_loss: -0.5,
            data: "real-1_4".into(),
            data_source: "real".into(),
            data_fraction: 0.25,
            unique_tokens: 2000,
            hours: 0.75,
            synth_share: 0.0,
            real_test_loss: 5.0,
            real_norm_test_loss: 0.25,
            synth_test_loss: 6.0,
            synth_norm_test_loss: -0.25,
            best_real_test_loss: 4.75,
            best_real_norm_test_loss: 0.0,
            best_synth_test_loss: 5.75,
            best_synth_norm_test_loss: -0.75,
            lr: 1e-3,
            weight_decay: 0.1,
            dropout: f64::NAN,
            recipe: "r, \"q\"".into(),
        }
    }

    #[test]
    fn a_table_from_before_devices_and_validation_reads_with_the_defaults() {
        let path =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/results/scaling-law/results.csv");
        let rows = read_csv(&path).unwrap();
        assert_eq!(rows.len(), 154);
        for r in &rows {
            assert_eq!((r.device.as_str(), r.precision.as_str()), ("cpu", "f32"));
            assert_eq!(r.best_step, 0);
            assert!(r.best_test_loss.is_nan() && r.best_norm_test_loss.is_nan());
            assert_eq!((r.data.as_str(), r.data_source.as_str()), ("", "all"));
            assert_eq!((r.data_fraction, r.unique_tokens), (1.0, 0));
            assert!(r.hours.is_nan() && r.real_norm_test_loss.is_nan());
        }
    }

    #[test]
    fn csv_reads_back_the_rows_written() {
        let rows = vec![row(0), row(1)];
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("results.csv");
        std::fs::write(&path, to_csv(&rows).unwrap()).unwrap();
        assert_eq!(read_csv(&path).unwrap(), rows);
        std::fs::write(&path, "run_id,budget\nx,not-a-number\n").unwrap();
        let err = read_csv(&path).unwrap_err().to_string();
        assert!(
            err.contains("results.csv") && err.contains("data row 1"),
            "{err}"
        );
    }

    #[test]
    fn csv_and_parquet_hold_every_column_in_order() {
        let rows = [row(0), row(1)];
        let csv = String::from_utf8(to_csv(&rows).unwrap()).unwrap();
        let mut lines = csv.lines();
        let header: Vec<&str> = lines.next().unwrap().split(',').collect();
        assert_eq!(header, COLUMNS.map(|c| c.0));
        // The spec's columns first, named as `motionscale fit` reads them by default.
        assert_eq!(header[..14], fits::synth::SWEEP_COLUMNS);
        let mut reader = csv::Reader::from_reader(csv.as_bytes());
        let records: Vec<csv::StringRecord> = reader.records().map(Result::unwrap).collect();
        assert_eq!(records.len(), 2);
        assert_eq!(
            &records[1][15], "abc, \"quoted\"",
            "text with commas and quotes survives"
        );
        assert_eq!(records[1][8].parse::<u64>().unwrap(), 1001);
        assert_eq!(records[0][13].parse::<f64>().unwrap(), 1.25e12);

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.parquet");
        std::fs::write(&path, to_parquet(&rows).unwrap()).unwrap();
        let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(
            std::fs::File::open(&path).unwrap(),
        )
        .unwrap();
        assert_eq!(reader.schema().as_ref(), schema().as_ref());
        let batch = reader.build().unwrap().next().unwrap().unwrap();
        assert_eq!(batch.num_rows(), 2);
    }

    #[test]
    fn result_files_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(read_row(dir.path(), "c1e12-cpu-50K-v3").unwrap(), None);
        write_row(dir.path(), &row(3)).unwrap();
        assert_eq!(
            read_row(dir.path(), "c1e12-cpu-50K-v3").unwrap(),
            Some(row(3))
        );
        // NaN (no validation clips, one origin) is JSON's null and reads back as NaN.
        let unrecorded = RunRow {
            hours: f64::NAN,
            best_test_loss: f64::NAN,
            ..row(4)
        };
        write_row(dir.path(), &unrecorded).unwrap();
        let back = read_row(dir.path(), "c1e12-cpu-50K-v4").unwrap().unwrap();
        assert!(back.hours.is_nan() && back.best_test_loss.is_nan());
        assert_eq!(back, unrecorded, "not recorded equals not recorded");
        assert_ne!(back, row(4));
        let csv_path = dir.path().join("results.csv");
        std::fs::write(&csv_path, to_csv(&[unrecorded]).unwrap()).unwrap();
        assert!(read_csv(&csv_path).unwrap()[0].hours.is_nan());
    }
}
