//! docs/guide.md is the binary's help: `scripts/guide.sh` run with this test's binary writes the
//! same text byte for byte (one generator: the test runs the script rather than repeating its
//! traversal of the commands).

mod common;

use common::*;
use std::path::Path;
use std::process::Command;

#[test]
fn guide_matches_the_help_of_every_command() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let tmp = tempfile::tempdir().unwrap();
    let fresh = tmp.path().join("guide.md");
    let run = Command::new("bash")
        .arg(root.join("scripts/guide.sh"))
        .arg(env!("CARGO_BIN_EXE_motionscale"))
        .arg(&fresh)
        .output()
        .expect("bash runs");
    assert_eq!(code(&run), 0, "scripts/guide.sh failed: {}", text(&run));
    let fresh = std::fs::read_to_string(&fresh).unwrap();
    let committed = std::fs::read_to_string(root.join("docs/guide.md")).unwrap_or_default();
    // Every command, subcommands included, has its section.
    for section in [
        "## motionscale\n",
        "## motionscale fit\n",
        "## motionscale sweep plan\n",
    ] {
        assert!(fresh.contains(section), "no {section:?} in:\n{fresh}");
    }
    if fresh != committed {
        let line = fresh
            .lines()
            .zip(committed.lines())
            .position(|(a, b)| a != b)
            .map_or(fresh.lines().count().min(committed.lines().count()), |i| i)
            + 1;
        panic!(
            "docs/guide.md differs from the binary's help (first at line {line}): \
             run `bash scripts/guide.sh` after `cargo build --release` and commit docs/guide.md"
        );
    }
}
