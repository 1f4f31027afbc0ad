//! The results table: a CSV or Parquet file read into named columns.

use crate::FitError;
use arrow_array::cast::AsArray;
use arrow_array::types::{
    Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type, UInt16Type, UInt32Type,
    UInt64Type, UInt8Type,
};
use arrow_array::{Array, ArrayRef};
use arrow_schema::DataType;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use std::path::{Path, PathBuf};

/// One column's cells: numbers (Parquet numeric columns) or text (CSV, Parquet strings).
#[derive(Debug, Clone)]
enum Cells {
    Numbers(Vec<Option<f64>>),
    Text(Vec<Option<String>>),
    /// A Parquet column of a type that is neither numeric nor text (its type's name).
    Other(String),
}

/// Column names, columns and row count of a parsed file.
type Parsed = (Vec<String>, Vec<Cells>, usize);

/// Builds the format error about the file being read.
type FormatError<'a> = dyn Fn(String) -> FitError + 'a;

/// A results table read from a file, with its columns in file order.
#[derive(Debug, Clone)]
pub struct Table {
    path: PathBuf,
    names: Vec<String>,
    columns: Vec<Cells>,
    rows: usize,
}

impl Table {
    /// Reads `path`: `.csv` (header row, comma-separated) or `.parquet`.
    pub fn read(path: &Path) -> Result<Self, FitError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let format = |message: String| FitError::Format {
            path: path.to_path_buf(),
            message,
        };
        let parse = match ext.as_deref() {
            Some("csv") => Self::parse_csv,
            Some("parquet") | Some("pq") => Self::parse_parquet,
            _ => {
                return Err(format(
                    "unsupported extension: expected .csv or .parquet".into(),
                ))
            }
        };
        let file = std::fs::File::open(path).map_err(|source| FitError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let (names, columns, rows) = parse(file, &format)?;
        Ok(Self {
            path: path.to_path_buf(),
            names,
            columns,
            rows,
        })
    }

    fn parse_csv(file: std::fs::File, format: &FormatError) -> Result<Parsed, FitError> {
        let mut reader = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            .from_reader(file);
        let names: Vec<String> = reader
            .headers()
            .map_err(|e| format(format!("header: {e}")))?
            .iter()
            .map(str::to_string)
            .collect();
        let mut text: Vec<Vec<Option<String>>> = vec![Vec::new(); names.len()];
        for (i, record) in reader.records().enumerate() {
            let record = record.map_err(|e| format(format!("data row {}: {e}", i + 1)))?;
            for (col, cell) in text.iter_mut().zip(record.iter()) {
                col.push((!cell.is_empty()).then(|| cell.to_string()));
            }
        }
        let rows = text.first().map_or(0, Vec::len);
        Ok((names, text.into_iter().map(Cells::Text).collect(), rows))
    }

    fn parse_parquet(file: std::fs::File, format: &FormatError) -> Result<Parsed, FitError> {
        let builder =
            ParquetRecordBatchReaderBuilder::try_new(file).map_err(|e| format(e.to_string()))?;
        let schema = builder.schema().clone();
        let reader = builder.build().map_err(|e| format(e.to_string()))?;
        let names: Vec<String> = schema.fields().iter().map(|f| f.name().clone()).collect();
        let mut columns: Vec<Cells> = schema
            .fields()
            .iter()
            .map(|f| match f.data_type() {
                DataType::Utf8 | DataType::LargeUtf8 | DataType::Utf8View => {
                    Cells::Text(Vec::new())
                }
                t if is_plain_number(t) => Cells::Numbers(Vec::new()),
                t => Cells::Other(t.to_string()),
            })
            .collect();
        let mut rows = 0;
        for batch in reader {
            let batch = batch.map_err(|e| format(e.to_string()))?;
            rows += batch.num_rows();
            for (i, cells) in columns.iter_mut().enumerate() {
                append(cells, batch.column(i))
                    .map_err(|m| format(format!("column {:?}: {m}", names[i])))?;
            }
        }
        Ok((names, columns, rows))
    }

    /// The file this table was read from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Number of data rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Column names in file order.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// True when the table has a column called `name`.
    pub fn has(&self, name: &str) -> bool {
        self.names.iter().any(|n| n == name)
    }

    /// Column `name` as finite numbers; the error names the row of the first bad cell.
    /// `flag` is the command-line flag that picks this column (for the error message).
    pub fn numbers(&self, name: &str, flag: &str) -> Result<Vec<f64>, FitError> {
        self.parse_numbers(name, flag, false)
    }

    /// Column `name` as numbers, NaN allowed (a value the sweep did not record).
    pub fn numbers_or_nan(&self, name: &str, flag: &str) -> Result<Vec<f64>, FitError> {
        self.parse_numbers(name, flag, true)
    }

    /// Column `name` as text (numbers as written), `None` when the table has no such column.
    pub fn labels(&self, name: &str) -> Option<Vec<String>> {
        let idx = self.names.iter().position(|n| n == name)?;
        Some(match &self.columns[idx] {
            Cells::Numbers(v) => v
                .iter()
                .map(|c| c.map_or_else(String::new, |x| x.to_string()))
                .collect(),
            Cells::Text(v) => v.iter().map(|c| c.clone().unwrap_or_default()).collect(),
            Cells::Other(_) => vec![String::new(); self.rows],
        })
    }

    fn parse_numbers(&self, name: &str, flag: &str, nan: bool) -> Result<Vec<f64>, FitError> {
        let idx =
            self.names
                .iter()
                .position(|n| n == name)
                .ok_or_else(|| FitError::MissingColumn {
                    path: self.path.clone(),
                    column: name.to_string(),
                    available: self.names.join(", "),
                    hint: format!("pick another with {flag}"),
                })?;
        let bad = |row: usize, problem: String| FitError::BadCell {
            path: self.path.clone(),
            column: name.to_string(),
            row: row + 1,
            problem,
        };
        let parse = |row: usize, cell: Option<f64>, text: Option<&str>| -> Result<f64, FitError> {
            let v = match (cell, text) {
                (Some(v), _) => v,
                (None, Some(t)) => t
                    .parse::<f64>()
                    .map_err(|_| bad(row, format!("{t:?} is not a number")))?,
                (None, None) => return Err(bad(row, "empty cell".into())),
            };
            if v.is_finite() || (nan && v.is_nan()) {
                Ok(v)
            } else {
                Err(bad(row, format!("{v} is not finite")))
            }
        };
        match &self.columns[idx] {
            Cells::Numbers(v) => v
                .iter()
                .enumerate()
                .map(|(row, &c)| parse(row, c, None))
                .collect(),
            Cells::Text(v) => v
                .iter()
                .enumerate()
                .map(|(row, c)| parse(row, None, c.as_deref()))
                .collect(),
            Cells::Other(t) => Err(FitError::Format {
                path: self.path.clone(),
                message: format!("column {name:?} has type {t}, not numbers"),
            }),
        }
    }
}

/// Integer and float types read as f64 (decimals and half floats are not).
fn is_plain_number(t: &DataType) -> bool {
    use DataType::*;
    matches!(
        t,
        Float64 | Float32 | Int64 | Int32 | Int16 | Int8 | UInt64 | UInt32 | UInt16 | UInt8
    )
}

/// Appends one Arrow column chunk to `cells` (numeric types become f64; nulls stay `None`).
fn append(cells: &mut Cells, array: &ArrayRef) -> Result<(), String> {
    macro_rules! prim {
        ($t:ty) => {
            array
                .as_primitive::<$t>()
                .iter()
                .map(|v| v.map(|x| x as f64))
                .collect::<Vec<Option<f64>>>()
        };
    }
    match cells {
        Cells::Numbers(out) => {
            let values = match array.data_type() {
                DataType::Float64 => prim!(Float64Type),
                DataType::Float32 => prim!(Float32Type),
                DataType::Int64 => prim!(Int64Type),
                DataType::Int32 => prim!(Int32Type),
                DataType::Int16 => prim!(Int16Type),
                DataType::Int8 => prim!(Int8Type),
                DataType::UInt64 => prim!(UInt64Type),
                DataType::UInt32 => prim!(UInt32Type),
                DataType::UInt16 => prim!(UInt16Type),
                DataType::UInt8 => prim!(UInt8Type),
                other => return Err(format!("unsupported numeric type {other}")),
            };
            out.extend(values);
        }
        Cells::Text(out) => {
            let strings: Vec<Option<String>> = match array.data_type() {
                DataType::Utf8 => array
                    .as_string::<i32>()
                    .iter()
                    .map(|s| s.map(str::to_string))
                    .collect(),
                DataType::LargeUtf8 => array
                    .as_string::<i64>()
                    .iter()
                    .map(|s| s.map(str::to_string))
                    .collect(),
                DataType::Utf8View => array
                    .as_string_view()
                    .iter()
                    .map(|s| s.map(str::to_string))
                    .collect(),
                other => return Err(format!("unexpected type {other}")),
            };
            out.extend(strings);
        }
        Cells::Other(_) => {}
    }
    Ok(())
}
