//! Helpers shared by the ingest crate's integration tests.

#[path = "../../../tests/common/skip.rs"]
mod skip;

pub use skip::not_run;
use std::path::PathBuf;

/// `../shared/data` beside the repository, or `None` (a recorded skip) when it is missing;
/// fails the test instead when `CI` or `MOTIONSCALE_STRICT_TESTS` is set.
pub fn data_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data"));
    if dir.is_dir() {
        return Some(dir);
    }
    not_run(&format!("the shared data {} is missing", dir.display()));
    None
}
