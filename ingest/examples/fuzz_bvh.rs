//! Structured mutation fuzzer for the whole per-input BVH path.
//!
//! `cargo run --release -p ingest --example fuzz_bvh -- --seconds N --seed S [--seeds-dir DIR]`
//!
//! Each input goes through parse → retarget → budgets → resample → segment → features
//! under `catch_unwind`; a watchdog aborts when one input runs over 5 s. A panicking or
//! hanging input is written to `fuzz-crash-<seed>-<n>.bvh` and the process exits non-zero;
//! an input that aborts the process (allocation failure) ends it with the abort's status.

use ingest::bvh_fuzzing::{check, Fuzzer, Outcome};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Longest time one input may take before it counts as a hang.
const HANG: Duration = Duration::from_secs(5);

struct Args {
    seconds: u64,
    seed: u64,
    seeds_dir: Option<PathBuf>,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        seconds: 60,
        seed: 1,
        seeds_dir: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--seconds" => {
                args.seconds = value()?.parse().map_err(|e| format!("--seconds: {e}"))?
            }
            "--seed" => args.seed = value()?.parse().map_err(|e| format!("--seed: {e}"))?,
            "--seeds-dir" => args.seeds_dir = Some(PathBuf::from(value()?)),
            other => return Err(format!("unknown argument '{other}'")),
        }
    }
    Ok(args)
}

/// `.bvh` files under `dir` (recursively), capped so the seed corpus stays in memory.
fn read_seeds(dir: &Path, out: &mut Vec<Vec<u8>>) -> std::io::Result<()> {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for path in entries {
        if out.len() >= 64 {
            break;
        }
        if path.is_dir() {
            read_seeds(&path, out)?;
        } else if path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("bvh"))
        {
            out.push(std::fs::read(&path)?);
        }
    }
    Ok(())
}

fn save(seed: u64, n: u64, input: &[u8]) -> String {
    let path = format!("fuzz-crash-{seed}-{n}.bvh");
    match std::fs::write(&path, input) {
        Ok(()) => path,
        Err(e) => format!("(could not write {path}: {e})"),
    }
}

fn main() {
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("fuzz_bvh: {e}\nusage: fuzz_bvh --seconds N --seed S [--seeds-dir DIR]");
            std::process::exit(2);
        }
    };
    let mut extra = Vec::new();
    if let Some(dir) = &args.seeds_dir {
        if let Err(e) = read_seeds(dir, &mut extra) {
            eprintln!("fuzz_bvh: reading seeds from {}: {e}", dir.display());
            std::process::exit(2);
        }
    }
    println!(
        "fuzz_bvh: seed {}, {} seed files, {} s",
        args.seed,
        extra.len(),
        args.seconds
    );
    std::panic::set_hook(Box::new(|_| {}));
    let mut fuzzer = Fuzzer::new(args.seed, 64, extra);

    // The watchdog sees the current input and when it started (ms since start, 0 = idle).
    let start = Instant::now();
    let current: Arc<Mutex<(u64, Vec<u8>)>> = Arc::new(Mutex::new((0, Vec::new())));
    let started_ms = Arc::new(AtomicU64::new(0));
    {
        let (current, started_ms, seed) = (current.clone(), started_ms.clone(), args.seed);
        std::thread::spawn(move || loop {
            std::thread::sleep(Duration::from_millis(250));
            let began = started_ms.load(Ordering::Acquire);
            let now = start.elapsed().as_millis() as u64;
            if began != 0 && now.saturating_sub(began) > HANG.as_millis() as u64 {
                let (n, input) = match current.lock() {
                    Ok(g) => g.clone(),
                    Err(p) => p.into_inner().clone(),
                };
                eprintln!(
                    "fuzz_bvh: HANG on input {n} (> {HANG:?}); saved to {}",
                    save(seed, n, &input)
                );
                std::process::exit(1);
            }
        });
    }

    // Inputs refused by the parser, by retargeting, and processed (with clips ingested).
    let (mut total, mut unparsed, mut unmapped, mut processed, mut ingested) =
        (0u64, 0u64, 0u64, 0u64, 0u64);
    let deadline = Duration::from_secs(args.seconds);
    while start.elapsed() < deadline {
        let input = fuzzer.next_input();
        if let Ok(mut g) = current.lock() {
            *g = (total, input.clone());
        }
        started_ms.store(start.elapsed().as_millis().max(1) as u64, Ordering::Release);
        let outcome = check(&input);
        started_ms.store(0, Ordering::Release);
        match outcome {
            Ok(Outcome::Unparsed) => unparsed += 1,
            Ok(Outcome::NotRetargeted) => unmapped += 1,
            Ok(Outcome::Processed { clips, .. }) => {
                processed += 1;
                ingested += u64::from(clips > 0);
            }
            Err(msg) => {
                eprintln!(
                    "fuzz_bvh: PANIC on input {total}: {msg}; saved to {}",
                    save(args.seed, total, &input)
                );
                std::process::exit(1);
            }
        }
        total += 1;
    }
    let secs = start.elapsed().as_secs_f64();
    println!(
        "fuzz_bvh: {total} inputs in {secs:.1} s ({:.0} inputs/s): {unparsed} refused by the parser, \
         {unmapped} by retargeting, {processed} processed to the end ({ingested} with clips \
         ingested); 0 panics, 0 hangs, 0 aborts",
        total as f64 / secs
    );
}
