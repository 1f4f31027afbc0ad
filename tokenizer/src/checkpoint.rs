//! Checkpoint files: safetensors written atomically.

use crate::error::TokenizerError;
use candle_core::Tensor;
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
