//! Real data: both Bandai Namco archives through `motionscale ingest`; every input is
//! accounted for, pyarrow reads every shard, `corpus verify` passes.

mod common;

use common::*;
use ingest::bvh_fuzzing::Fuzzer;
use ingest::corpus::Corpus;
use std::collections::HashSet;
use std::path::PathBuf;

#[test]
fn both_bandai_archives_ingest_with_every_input_accounted_for() {
    let Some(data) = shared_data() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let mut sources = Vec::new();
    for archive in ["bandai-namco-1.tar.zst", "bandai-namco-2.tar.zst"] {
        let status = std::process::Command::new("tar")
            .arg("--zstd")
            .arg("-xf")
            .arg(data.join("bandai-namco").join(archive))
            .arg("-C")
            .arg(tmp.path())
            .status()
            .unwrap();
        assert!(status.success(), "extracting {archive}");
    }
    for dir in std::fs::read_dir(tmp.path()).unwrap() {
        sources.push(format!("bvh:{}", dir.unwrap().path().display()));
    }
    sources.sort();
    let corpus = tmp.path().join("corpus");
    let mut args = vec!["ingest".to_string()];
    for s in &sources {
        args.extend(["--source".to_string(), s.clone()]);
    }
    args.extend([
        "--out".into(),
        corpus.display().to_string(),
        "--json".into(),
    ]);
    let out = motionscale(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let exit = code(&out);
    assert!(exit == 0 || exit == 2, "{}", text(&out));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["inputs"], 3076);
    assert!(
        report["source_frames"].as_u64().unwrap() >= 416_845,
        "{report}"
    );

    let manifest: serde_json::Value = read_json(&corpus.join("manifest.json"));
    let ingested: u64 = manifest["sources"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["ingested_files"].as_u64().unwrap())
        .sum();
    assert!(
        ingested as f64 >= 0.99 * 3076.0,
        "only {ingested} of 3076 files ingested"
    );

    // Every input file is in a shard or in the rejects, with a reason.
    let rejects = rejects(&corpus);
    assert!(rejects
        .iter()
        .all(|r| !r["reason"].as_str().unwrap().is_empty()));
    let listing = python(
        r#"
import json, sys, pyarrow.parquet as pq
c = sys.argv[1]
for s in json.load(open(f"{c}/manifest.json"))["shards"]:
    for p in set(pq.read_table(f"{c}/{s['file']}", columns=["source_path"]).column("source_path").to_pylist()):
        print(p)
"#,
        &[corpus.to_str().unwrap()],
    );
    let mut seen: HashSet<String> = listing.lines().map(str::to_string).collect();
    seen.extend(
        rejects
            .iter()
            .map(|r| r["path"].as_str().unwrap().to_string()),
    );
    let mut missing = 0;
    for s in &sources {
        let root = s.trim_start_matches("bvh:");
        for entry in walk(std::path::Path::new(root)) {
            if entry.extension().is_some_and(|e| e == "bvh")
                && !seen.contains(&entry.display().to_string())
            {
                missing += 1;
            }
        }
    }
    assert_eq!(missing, 0, "inputs neither ingested nor rejected");

    // Labels from the sidecars made it into the rows.
    let stats = motionscale(&["corpus", "stats", corpus.to_str().unwrap(), "--json"]);
    let stats: serde_json::Value = serde_json::from_slice(&stats.stdout).unwrap();
    for scenario in ["locomotion", "greeting", "gesture", "fighting", "dance"] {
        assert!(
            stats["by"]["scenario"][scenario]["clips"].as_u64().unwrap() > 0,
            "{scenario}"
        );
    }
    assert!(stats["by"]["emotion"]["anxious"]["clips"].as_u64().unwrap() > 0);

    let rows = python(PYARROW_CHECK, &[corpus.to_str().unwrap()]);
    let n: u64 = rows.split_whitespace().next().unwrap().parse().unwrap();
    assert_eq!(n, report["clips"].as_u64().unwrap());
    let verify = motionscale(&["corpus", "verify", corpus.to_str().unwrap()]);
    assert_eq!(code(&verify), 0, "{}", text(&verify));

    // L²-EMG scenario datasets: one per scenario (unseen) or equal chunks (mixed).
    for split in ["unseen", "mixed"] {
        let out = tmp.path().join(split);
        let run = motionscale(&[
            "scenarios",
            "--corpus",
            corpus.to_str().unwrap(),
            "--split",
            split,
            "--out",
            out.to_str().unwrap(),
            "--seed",
            "3",
        ]);
        assert_eq!(code(&run), 0, "{}", text(&run));
        let sets: serde_json::Value = read_json(&out.join("datasets.json"));
        let datasets = sets["datasets"].as_array().unwrap();
        assert_eq!(datasets.len(), 5, "{split}");
        let mut total = 0;
        for d in datasets {
            let n = |s: &str| d["clips"][s].as_array().unwrap().len();
            // Clips keep their corpus split, so a scenario of a few long source clips (Bandai
            // dance) can have no train or no test clip; the command says so.
            for list in ["train", "test"] {
                if n(list) == 0 {
                    let warning = format!("{} has no {list} clip", d["name"].as_str().unwrap());
                    assert!(text(&run).contains(&warning), "{split}: {}", text(&run));
                }
            }
            total += n("train") + n("val") + n("test");
            let listed =
                std::fs::read_to_string(out.join(d["name"].as_str().unwrap()).join("test.txt"))
                    .unwrap();
            assert_eq!(listed.lines().count(), n("test"));
        }
        assert_eq!(
            total as u64,
            report["clips"].as_u64().unwrap(),
            "{split}: every labelled clip is in one dataset"
        );
        assert!(text(&run).contains("Total"), "prints the table");
    }
}

fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// Damaged inputs per folder in [`damaged_files_beside_good_ones_are_all_accounted_for`]
/// (the issue's batches: 50 damaged files beside 2 good ones).
const DAMAGED_PER_FOLDER: usize = 50;

/// Folders of damaged Bandai files (mutated by the structured fuzzer: flipped bits, nasty
/// tokens, huge values, absurd frame times and counts, cut and spliced lines) beside two good
/// files each, one ingest per folder: every input lands in a shard or in the rejects, every
/// good file is ingested, no ingest crashes, and every corpus verifies.
/// `MOTIONSCALE_DAMAGED_FOLDERS` (default 4) sets the number of folders.
#[test]
fn damaged_files_beside_good_ones_are_all_accounted_for() {
    let Some(data) = shared_data() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let status = std::process::Command::new("tar")
        .args(["--zstd", "-xf"])
        .arg(data.join("bandai-namco/bandai-namco-1.tar.zst"))
        .arg("-C")
        .arg(tmp.path())
        .args([
            "--wildcards",
            "*_bow_*.bvh",
            "*_walk_*.bvh",
            "*_punch_*.bvh",
        ])
        .status()
        .unwrap();
    assert!(status.success(), "extracting Bandai set 1");
    let mut originals = walk(tmp.path());
    originals.sort();
    let good: Vec<PathBuf> = [
        "dataset-1_bow_active_001.bvh",
        "dataset-1_punch_normal_002.bvh",
    ]
    .iter()
    .map(|n| originals.iter().find(|p| p.ends_with(n)).expect(n).clone())
    .collect();
    let seeds: Vec<Vec<u8>> = originals
        .iter()
        .map(|p| std::fs::read(p).unwrap())
        .collect();
    let mut fuzzer = Fuzzer::new(23, 0, seeds);
    let folders: usize = std::env::var("MOTIONSCALE_DAMAGED_FOLDERS")
        .map_or(4, |v| v.parse().expect("a number of folders"));
    let (mut damaged, mut rejected) = (0, 0);
    for f in 0..folders {
        let dir = tmp.path().join(format!("batch-{f:03}"));
        std::fs::create_dir(&dir).unwrap();
        for g in &good {
            std::fs::copy(g, dir.join(g.file_name().unwrap())).unwrap();
        }
        for k in 0..DAMAGED_PER_FOLDER {
            std::fs::write(dir.join(format!("damaged_{k:02}.bvh")), fuzzer.next_input()).unwrap();
        }
        let corpus = tmp.path().join(format!("corpus-{f:03}"));
        let src = format!("bvh:{}", dir.display());
        let out = motionscale(&["ingest", "--source", &src, "--out", arg(&corpus), "--json"]);
        let exit = code(&out);
        assert!(exit == 0 || exit == 2, "folder {f}: {}", text(&out));
        let clips = Corpus::open(&corpus).unwrap();
        let ingested: HashSet<String> = (0..clips.manifest().shards.len())
            .flat_map(|s| clips.shard_records(s).unwrap())
            .map(|r| r.source_path)
            .collect();
        let rejects: HashSet<String> = rejects(&corpus)
            .iter()
            .map(|r| r["path"].as_str().unwrap().to_string())
            .collect();
        for input in walk(&dir) {
            let input = input.display().to_string();
            assert!(
                ingested.contains(&input) || rejects.contains(&input),
                "folder {f}: {input} is neither ingested nor rejected"
            );
        }
        for g in &good {
            let copy = dir.join(g.file_name().unwrap()).display().to_string();
            assert!(
                ingested.contains(&copy),
                "folder {f}: good file {copy} not ingested"
            );
        }
        let verify = motionscale(&["corpus", "verify", arg(&corpus)]);
        assert_eq!(code(&verify), 0, "folder {f}: {}", text(&verify));
        damaged += DAMAGED_PER_FOLDER;
        rejected += rejects.len();
    }
    eprintln!("{damaged} damaged inputs in {folders} folders: 0 lost, {rejected} rejected");
}
