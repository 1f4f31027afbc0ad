//! Helpers shared by the ingest crate's integration tests.

use std::path::PathBuf;

/// `../shared/data` beside the repository, or `None` (with a note) when it is missing outside
/// CI. With `CI` set a missing folder fails the test instead of skipping it.
pub fn data_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data"));
    if dir.is_dir() {
        return Some(dir);
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "shared data missing at {} (CI is set)",
        dir.display()
    );
    eprintln!("note: {} missing, test not run", dir.display());
    None
}
