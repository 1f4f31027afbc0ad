//! Files written atomically (a temporary file beside the target, then a rename, so a reader
//! never sees half a file), JSON read and written with the file named in every error, and the
//! check that a run folder holds the run asked for before a trainer resumes it.

use serde::de::DeserializeOwned;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};

/// A file that could not be read, written or understood, named.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// Reading or writing the file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The file is present but unusable (bad JSON, another run's configuration…).
    #[error("{}: {message}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
}

impl FileError {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// `path` holds something unusable.
    pub fn invalid(path: &Path, message: impl std::fmt::Display) -> Self {
        Self::Invalid {
            path: path.to_path_buf(),
            message: message.to_string(),
        }
    }

    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            Self::Io { path, .. } | Self::Invalid { path, .. } => path,
        }
    }
}

/// Write bytes to `path` atomically: a temporary file in the same folder, then rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir)?;
    let tmp = dir.join(format!(
        ".{}.tmp{}",
        path.file_name().and_then(|n| n.to_str()).unwrap_or("out"),
        std::process::id()
    ));
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, path)
}

/// Write `value` as pretty JSON to `path`, atomically.
pub fn write_json(path: &Path, value: &impl Serialize) -> Result<(), FileError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| FileError::invalid(path, e))?;
    write_atomic(path, text.as_bytes()).map_err(|e| FileError::io(path, e))
}

/// Parse the JSON file at `path`.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T, FileError> {
    let text = std::fs::read_to_string(path).map_err(|e| FileError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| FileError::invalid(path, e))
}

/// Append `value` as one JSON line to `path` (created if missing).
pub fn append_json_line(path: &Path, value: &impl Serialize) -> Result<(), FileError> {
    let line = serde_json::to_string(value).map_err(|e| FileError::invalid(path, e))?;
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| FileError::io(path, e))?;
    writeln!(file, "{line}").map_err(|e| FileError::io(path, e))
}

/// Every line of the JSON-lines file `path` (as [`append_json_line`] writes it), parsed;
/// blank lines are skipped and a bad line is an error naming its number.
pub fn read_json_lines<T: DeserializeOwned>(path: &Path) -> Result<Vec<T>, FileError> {
    let text = std::fs::read_to_string(path).map_err(|e| FileError::io(path, e))?;
    text.lines()
        .enumerate()
        .filter(|(_, line)| !line.trim().is_empty())
        .map(|(i, line)| {
            serde_json::from_str(line)
                .map_err(|e| FileError::invalid(path, format!("line {}: {e}", i + 1)))
        })
        .collect()
}

/// Refuse to resume a run folder whose configuration file (`config_path`, if present) holds
/// another run: `same` says whether the stored configuration is the one asked for, and `what`
/// names the run in the error ("a continual run").
pub fn check_same_run<T: DeserializeOwned>(
    config_path: &Path,
    what: &str,
    same: impl FnOnce(T) -> bool,
) -> Result<(), FileError> {
    if config_path.is_file() && !same(read_json(config_path)?) {
        return Err(FileError::invalid(
            config_path,
            format!("this folder holds {what} with another configuration; use another --out"),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_round_trips_atomically_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a/b.json");
        write_json(&path, &vec![1.5, 2.0]).unwrap();
        assert_eq!(read_json::<Vec<f64>>(&path).unwrap(), vec![1.5, 2.0]);
        let names: Vec<_> = std::fs::read_dir(path.parent().unwrap()).unwrap().collect();
        assert_eq!(names.len(), 1, "no temporary file is left behind");
        let err = read_json::<String>(&path).unwrap_err();
        assert_eq!(err.path(), path);
        assert!(err.to_string().starts_with(&path.display().to_string()));
    }

    #[test]
    fn json_lines_read_back_what_was_appended_and_a_bad_line_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("log.jsonl");
        append_json_line(&path, &1u32).unwrap();
        append_json_line(&path, &2u32).unwrap();
        assert_eq!(read_json_lines::<u32>(&path).unwrap(), [1, 2]);
        std::fs::write(&path, "1\n\nx\n").unwrap();
        let err = read_json_lines::<u32>(&path).unwrap_err();
        assert!(err.to_string().contains("line 3"), "{err}");
    }

    #[test]
    fn a_folder_holding_another_run_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("config.json");
        check_same_run(&path, "a run", |_: u32| false).unwrap();
        write_json(&path, &3u32).unwrap();
        check_same_run(&path, "a run", |c: u32| c == 3).unwrap();
        let err = check_same_run(&path, "a CL2Gen run", |c: u32| c == 4).unwrap_err();
        assert!(err
            .to_string()
            .contains("holds a CL2Gen run with another configuration"));
    }
}
