//! Errors of the fits crate; each names the file, column or fit it is about.

use std::path::PathBuf;

/// Why reading a table, fitting or predicting failed.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// The results file could not be opened or read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The results file is not valid CSV/Parquet, or has an unsupported extension.
    #[error("{}: {message}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A requested column is absent.
    #[error("{}: no column {column:?} (columns: {available}); {hint}", path.display())]
    MissingColumn {
        /// The file.
        path: PathBuf,
        /// The column asked for.
        column: String,
        /// The file's columns, comma-separated.
        available: String,
        /// Which flag sets it.
        hint: String,
    },
    /// A cell that must be a number is not.
    #[error("{}: column {column:?}, row {row} (data row, 1-based): {problem}", path.display())]
    BadCell {
        /// The file.
        path: PathBuf,
        /// The column.
        column: String,
        /// 1-based data row (the CSV header is not counted).
        row: usize,
        /// What is wrong with the cell.
        problem: String,
    },
    /// Not enough data for a required fit.
    #[error("{}: too few runs for {fit}: {message}", path.display())]
    TooFew {
        /// The results file.
        path: PathBuf,
        /// The fit.
        fit: String,
        /// Counts and what is needed.
        message: String,
    },
    /// A fits file or option is inconsistent.
    #[error("{0}")]
    Invalid(String),
    /// A flag's value is not one of the names it takes.
    #[error("{flag} {given:?}: expected {expected}")]
    UnknownChoice {
        /// The flag.
        flag: &'static str,
        /// The value given.
        given: String,
        /// The names it takes.
        expected: &'static str,
    },
    /// A flag's value does not fit the table.
    #[error("{flag}: {problem}")]
    BadOption {
        /// The flag.
        flag: String,
        /// What is wrong, with what the table offers.
        problem: String,
    },
    /// A fit these runs cannot support: which column or which spread is missing.
    #[error("{fit}: {needs}")]
    CannotFit {
        /// The fit.
        fit: &'static str,
        /// What it needs that the runs lack.
        needs: String,
    },
    /// An error about one file's contents.
    #[error("{}: {source}", path.display())]
    InFile {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        source: Box<FitError>,
    },
    /// A plot could not be written.
    #[error(transparent)]
    Plot(#[from] plot::PlotError),
}
