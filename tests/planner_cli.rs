//! End-to-end: `motionscale sweep replay` on a synthetic IsoFLOP table with known truth, its
//! report section, and the planner's bad inputs (`sweep replay`, `sweep plan --next`).

mod common;

use common::*;
use fits::synth::{isoflop_runs, CHINCHILLA};
use std::fmt::Write as _;
use std::path::Path;

/// A sweep-style results table: seven sizes at each of `budgets` from a Chinchilla-form law with
/// 1% noise and a ripple in log N the parabolas cannot follow.
fn write_table(path: &Path, budgets: &[f64]) {
    let runs = isoflop_runs(&CHINCHILLA, budgets, 7, 0.01, 0.0, 11);
    let mut csv = String::from("run_id,index,budget,n_nv,tokens,flops,norm_test_loss,test_loss\n");
    for (i, r) in runs.iter().enumerate() {
        let loss = r.loss + 0.02 * (4.0 * r.n.log10() + r.c.log10()).sin();
        let _ = writeln!(
            csv,
            "r{i},{i},{},{},{},{},{loss},{loss}",
            r.c, r.n, r.d, r.c
        );
    }
    std::fs::write(path, csv).unwrap();
}

#[test]
fn replay_scores_every_policy_against_the_runs_at_the_target_and_reports_it() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("results.csv");
    write_table(&csv, &[1e18, 3e18, 1e19, 3e19, 1e20, 3e20, 1e21]);
    let out = tmp.path().join("replay");
    let stdout = motionscale_ok(&[
        "sweep",
        "replay",
        "--results",
        arg(&csv),
        "--target-budget",
        "1e21",
        "--seeds",
        "5",
        "--draws",
        "64",
        "--out",
        arg(&out),
    ]);
    assert!(stdout.contains("42 runs below 1.000e21"), "{stdout}");
    let summary: fits::replay::ReplaySummary = read_json(&out.join("summary.json"));
    let names: Vec<&str> = summary.policies.iter().map(|p| p.policy.as_str()).collect();
    assert_eq!(names, ["active", "grid", "random"]);
    assert_eq!(summary.policies[2].orders, 5);
    assert_eq!(summary.start_runs, 21);
    // The truth is the vertex of the runs at 10^21, near the law's own optimum.
    assert!(
        (summary.truth - CHINCHILLA.n_opt(1e21).log10()).abs() < 0.3,
        "{}",
        summary.truth
    );
    for p in &summary.policies {
        assert!(p.final_share <= 0.3 + 1e-12, "{p:?}");
    }
    let steps = std::fs::read_to_string(out.join("replay.csv")).unwrap();
    assert!(steps.starts_with("policy,order,step,runs,compute,"));
    for f in [
        "replay-width.svg",
        "replay-width.png",
        "replay-error.svg",
        "replay-error.png",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    let page = tmp.path().join("report.html");
    motionscale_ok(&["report", arg(&out), "--out", arg(&page)]);
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains("share to the full table"), "planner section");
}

#[test]
fn planner_bad_inputs_name_what_is_missing() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("results.csv");
    write_table(&csv, &[1e18, 3e18, 1e19, 3e19, 1e20]);
    let out = tmp.path().join("replay");
    let replay = |budget: &str, table: &Path| {
        motionscale(&[
            "sweep",
            "replay",
            "--results",
            arg(table),
            "--target-budget",
            budget,
            "--out",
            arg(&out),
        ])
    };
    fails_with(&replay("1e17", &csv), "is not above the table's budgets");
    fails_with(&replay("1e21", &csv), "pass --truth");

    let one = tmp.path().join("one.csv");
    write_table(&one, &[1e18]);
    fails_with(&replay("1e21", &one), "1 budget(s) below");

    // A fit of two budgets has no N_opt law for `--next` to narrow.
    let two = tmp.path().join("two.csv");
    write_table(&two, &[1e18, 3e18]);
    let fit = tmp.path().join("fit");
    motionscale_ok(&[
        "fit",
        "--results",
        arg(&two),
        "--bootstrap",
        "0",
        "--out",
        arg(&fit),
    ]);
    let (corpus, plan) = (arg(tmp.path()), tmp.path().join("plan.toml"));
    let (fits, next) = (fit.join("fits.json"), tmp.path().join("next.toml"));
    let next_for = |target: &str| {
        motionscale(&[
            "sweep",
            "plan",
            "--corpus",
            corpus,
            "--extend",
            arg(&plan),
            "--next",
            "2",
            "--target",
            target,
            "--fits",
            arg(&fits),
            "--target-budget",
            "1e21",
            "--out",
            arg(&next),
        ])
    };
    fails_with(&next_for("n_opt"), "no N_opt ∝ C^b law (n_opt_vs_c)");
    // Nor a data-constrained law for the value of an hour.
    fails_with(
        &next_for("hour_value"),
        "no data-constrained fit (`fit --repeated-data`)",
    );
}
