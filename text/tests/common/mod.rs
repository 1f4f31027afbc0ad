//! Helpers shared by the integration tests.

#[path = "../../../tests/common/skip.rs"]
mod skip;

use std::path::PathBuf;

/// The fetched MiniLM encoder: `MOTIONSCALE_TEXT_ENCODER` or the default folder. Missing
/// fails when `CI` or `MOTIONSCALE_STRICT_TESTS` is set and is a recorded skip otherwise.
pub fn minilm_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("MOTIONSCALE_TEXT_ENCODER")
        .map(PathBuf::from)
        .unwrap_or_else(text::default_encoder_dir);
    if dir.join("model.safetensors").is_file() {
        return Some(dir);
    }
    let note = format!(
        "{}: no MiniLM encoder; run scripts/fetch-text-encoder.sh",
        dir.display()
    );
    skip::not_run(&note);
    None
}
