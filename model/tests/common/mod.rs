//! Helpers shared by the integration tests.

use std::path::PathBuf;

/// The fetched MiniLM encoder: `MOTIONSCALE_TEXT_ENCODER` or the default folder. Missing
/// fails under CI and skips (with a note) otherwise.
pub fn minilm_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("MOTIONSCALE_TEXT_ENCODER")
        .map(PathBuf::from)
        .unwrap_or_else(model::default_encoder_dir);
    if dir.join("model.safetensors").is_file() {
        return Some(dir);
    }
    let note = format!(
        "{}: no MiniLM encoder; run scripts/fetch-text-encoder.sh",
        dir.display()
    );
    assert!(std::env::var_os("CI").is_none(), "{note}");
    eprintln!("skipping: {note}");
    None
}
