//! Checkpoint files: safetensors and JSON, written atomically, read with errors naming the file.

use crate::error::TokenizerError;
use candle_core::Tensor;
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::collections::HashMap;
use std::path::Path;

/// Write `tensors` as safetensors to `path` atomically (temporary file in the same folder,
/// then rename), so a crash never leaves a half-written checkpoint.
pub fn save_safetensors(
    tensors: &HashMap<String, Tensor>,
    path: &Path,
) -> Result<(), TokenizerError> {
    let file_error = |e: &dyn std::fmt::Display| TokenizerError::File {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let dir = path.parent().unwrap_or_else(|| Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| file_error(&e))?;
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("out");
    let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
    candle_core::safetensors::save(tensors, &tmp).map_err(|e| file_error(&e))?;
    std::fs::rename(&tmp, path).map_err(|e| file_error(&e))
}

fn file_error(path: &Path, e: impl std::fmt::Display) -> TokenizerError {
    TokenizerError::File {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Write `value` as pretty JSON to `path`, atomically.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), TokenizerError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| file_error(path, e))?;
    ingest::npy::write_atomic(path, text.as_bytes()).map_err(|e| file_error(path, e))
}

/// Parse the JSON file at `path`.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T, TokenizerError> {
    let text = std::fs::read_to_string(path).map_err(|e| file_error(path, e))?;
    serde_json::from_str(&text).map_err(|e| file_error(path, e))
}
