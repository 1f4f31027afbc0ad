//! `motionscale bench train --no-train`: the generation figures alone, and the machine they
//! were measured on in the JSON (topology, caches, this machine's FMA peak, which is also the
//! MFU denominator unless `--peak-gflops` is given).

mod common;

use common::*;
use serde_json::Value;

#[test]
fn generation_alone_writes_its_figures_and_the_machine_it_ran_on() {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("bench.json");
    let printed = motionscale_ok(&[
        "bench",
        "train",
        "--no-train",
        "--min-time",
        "0.05",
        "--json",
        arg(&json),
    ]);
    let report: Value = read_json(&json);
    assert_eq!(report["train"], serde_json::json!([]), "{printed}");
    for run in [
        "batch1_cached",
        "batch1_uncached",
        "batch32_cached",
        "batch32_uncached",
    ] {
        let tokens_per_s = report["generate"][run]["tokens_per_s"].as_f64();
        assert!(tokens_per_s.is_some_and(|t| t > 0.0), "{run}: {report}");
    }
    let machine = &report["machine"];
    let topology = &machine["topology"];
    assert!(
        topology["physical_cores"].as_u64().is_some_and(|c| c >= 1),
        "{machine}"
    );
    let peak = machine["fma_peak_gflops"].as_f64().expect("an FMA peak");
    assert!(peak > 0.0, "{machine}");
    let row_kernels = machine["row_kernels"].as_str();
    assert!(
        matches!(row_kernels, Some("avx512" | "avx2" | "baseline")),
        "{machine}"
    );
    let transposed_lhs = machine["transposed_lhs"].as_str();
    assert!(
        matches!(transposed_lhs, Some("in-place" | "copied")),
        "{machine}"
    );
    assert_eq!(report["peak_gflops"].as_f64(), Some(peak), "{report}");
    assert!(printed.contains("FMA peak measured now"), "{printed}");
}
