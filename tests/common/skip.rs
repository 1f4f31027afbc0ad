//! When a test whose prerequisite (the shared data, the MiniLM encoder, spaCy) is missing
//! fails and when it skips: one rule for every crate's tests, which include this file
//! with `#[path]`. Skips are never silent: each is printed and appended to the file named by
//! `MOTIONSCALE_SKIPPED`, which `scripts/test.sh` lists at the end of the run.

// Each test binary uses a subset of these helpers.
#![allow(dead_code)]

use std::io::Write;
use std::path::Path;

/// Whether a missing prerequisite fails the test: `CI` is set, or `MOTIONSCALE_STRICT_TESTS`
/// is (`scripts/test.sh` sets it whenever `../shared/data` exists).
pub fn strict() -> bool {
    std::env::var_os("CI").is_some() || std::env::var_os("MOTIONSCALE_STRICT_TESTS").is_some()
}

/// The current test cannot run because of `reason`: fails it when [`strict`], else records
/// the skip with [`record_not_run`].
pub fn not_run(reason: &str) {
    assert!(
        !strict(),
        "{reason} (CI or MOTIONSCALE_STRICT_TESTS is set, so this test must run)"
    );
    record_not_run(reason);
}

/// Print that the current test did not run and why, and append `test: reason` to the file
/// named by `MOTIONSCALE_SKIPPED` when that is set.
pub fn record_not_run(reason: &str) {
    let test = current_test();
    eprintln!("note: {test} not run: {reason}");
    let Some(log) = std::env::var_os("MOTIONSCALE_SKIPPED") else {
        return;
    };
    // One write per line on an append-mode file: lines from parallel tests do not interleave.
    let line = format!("{test}: {reason}\n");
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log)
        .and_then(|mut f| f.write_all(line.as_bytes()))
        .unwrap_or_else(|e| panic!("{}: {e}", Path::new(&log).display()));
}

/// `package/test-binary::test`: libtest names each test's thread after the test; a test
/// without the harness runs on `main` and is named by its binary alone.
fn current_test() -> String {
    let exe = std::env::args().next().unwrap_or_default();
    let stem = Path::new(&exe)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    // Cargo names test binaries `NAME-HASH`.
    let binary = stem
        .rsplit_once('-')
        .map_or(stem.as_str(), |(name, _)| name);
    let prefix = format!("{}/{binary}", env!("CARGO_PKG_NAME"));
    match std::thread::current().name() {
        Some(name) if name != "main" => format!("{prefix}::{name}"),
        _ => prefix,
    }
}
