//! Single-thread throughput of `hml263::process` on fixture (a) (170 frames), in input
//! frames per second. Run: `cargo run --release -p ingest --example hml263_speed`.

use ingest::hml263::{process, Hml263Extractor, Hml263Options};
use ingest::skeleton::{Pose, NUM_JOINTS};
use std::time::Instant;

fn main() -> Result<(), String> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/humanml3d-fixtures/a_asis_joints.npy"
    );
    let arr = ingest::npy::read(std::path::Path::new(path))?;
    let poses: Vec<Pose> = arr
        .data
        .chunks_exact(NUM_JOINTS * 3)
        .map(|f| std::array::from_fn(|j| [f[3 * j], f[3 * j + 1], f[3 * j + 2]]))
        .collect();
    let opts = Hml263Options::default();
    let fresh = best_seconds(|| process(&poses, &opts).map(|o| o.features[0]))?;
    report("process (fresh buffers)", fresh, poses.len());
    let mut ex = Hml263Extractor::default();
    let mut out = process(&poses, &opts)?;
    let reused = best_seconds(|| {
        ex.process_into(&poses, &opts, &mut out)?;
        Ok(out.features[0])
    })?;
    report(
        "Hml263Extractor::process_into (reused buffers)",
        reused,
        poses.len(),
    );
    Ok(())
}

const CALLS: usize = 1_000;

/// Seconds per call of the fastest of many short rounds: the machine is shared, so the
/// minimum is the least disturbed estimate.
fn best_seconds(mut call: impl FnMut() -> Result<f32, String>) -> Result<f64, String> {
    let mut best = f64::INFINITY;
    let mut checksum = 0.0f32;
    for _ in 0..60 {
        let start = Instant::now();
        for _ in 0..CALLS {
            checksum += std::hint::black_box(call()?);
        }
        best = best.min(start.elapsed().as_secs_f64() / CALLS as f64);
    }
    println!("(checksum {checksum})");
    Ok(best)
}

fn report(label: &str, secs: f64, frames: usize) {
    let fps = frames as f64 / secs;
    println!(
        "{label}: {:.2} µs per {frames}-frame call, {fps:.0} input frames/s on one thread ({:.0}× the reference's 19,600)",
        secs * 1e6,
        fps / 19_600.0
    );
}
