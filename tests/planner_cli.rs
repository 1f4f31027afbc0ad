//! End-to-end: `motionscale sweep replay` on a synthetic IsoFLOP table with known truth, its
//! report section, `sweep plan --next` extending a plan whose runs are "trained" by that law,
//! and the planner's bad inputs (`sweep replay`, `sweep plan --next`).

mod common;

use common::*;
use experiments::IsoFlopPlan;
use fits::synth::{isoflop_runs, CHINCHILLA};
use std::fmt::Write as _;
use std::path::Path;

/// A sweep-style results table: seven sizes at each of `budgets` from a Chinchilla-form law with
/// 1% noise and a ripple in log N the parabolas cannot follow.
fn write_table(path: &Path, budgets: &[f64]) {
    let runs = isoflop_runs(&CHINCHILLA, budgets, 7, 0.01, 0.0, 11);
    let mut csv = String::from("run_id,index,budget,n_nv,tokens,flops,norm_test_loss,test_loss\n");
    for (i, r) in runs.iter().enumerate() {
        let loss = r.loss + ripple(r.n, r.c);
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
    let stdout = replay_ok(&csv, &out, &["--seeds", "5", "--draws", "64"]);
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
    // The planner's predictive check where active stopped: one row per run it left.
    let check = summary
        .active_predictive_check
        .expect("active was replayed");
    let rows = std::fs::read_to_string(out.join("predictive-check.csv")).unwrap();
    assert!(rows.starts_with("id,budget,n,vocab,predicted,sd,loss,z,on_envelope\n"));
    assert_eq!(rows.lines().count(), check.runs + 1);
    assert!(
        stdout.contains("active's model where it stopped"),
        "{stdout}"
    );
    for f in [
        "replay-width.svg",
        "replay-width.png",
        "replay-error.svg",
        "replay-error.png",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    // The loss target extrapolates by the law given (`fit`'s choice), and says which.
    let loss_out = tmp.path().join("replay-loss");
    let loss_args = [
        "--target",
        "loss",
        "--loss-form",
        "floor",
        "--policy",
        "active",
    ];
    let stdout = replay_ok(
        &csv,
        &loss_out,
        &[&loss_args[..], &["--draws", "64"]].concat(),
    );
    assert!(stdout.contains("loss (the floor law): truth"), "{stdout}");
    let summary: fits::replay::ReplaySummary = read_json(&loss_out.join("summary.json"));
    assert_eq!(summary.loss_form.as_deref(), Some("floor"));
    assert!(
        summary.full_table.width.is_finite(),
        "{:?}",
        summary.full_table
    );

    let page = tmp.path().join("report.html");
    motionscale_ok(&["report", arg(&out), "--out", arg(&page)]);
    let html = std::fs::read_to_string(&page).unwrap();
    assert!(html.contains("share to the full table"), "planner section");
    assert!(
        html.contains("Active's model where it stopped"),
        "its predictive check"
    );
}

/// The ripple in log N and log C that [`write_table`] adds to the law.
fn ripple(n: f64, c: f64) -> f64 {
    0.02 * (4.0 * n.log10() + c.log10()).sin()
}

/// `sweep replay` of `csv` at C* = 10^21 into `out`, plus `extra`; returns its output.
fn replay_ok(csv: &Path, out: &Path, extra: &[&str]) -> String {
    let mut args = vec![
        "sweep",
        "replay",
        "--results",
        arg(csv),
        "--target-budget",
        "1e21",
        "--out",
        arg(out),
    ];
    args.extend_from_slice(extra);
    motionscale_ok(&args)
}

#[test]
fn next_extends_the_plan_with_runs_that_enter_the_next_budget_around_the_law() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    tiny_lm_corpus(&corpus);
    let models = "8x1,12x1,16x1,24x1,32x1,48x1,64x1,96x1,128x2";
    let base_path = tmp.path().join("base.toml");
    sweep_plan(&corpus, "1e10,3e10,1e11", models, "256", &[], &base_path);
    let base = IsoFlopPlan::read(&base_path).unwrap();

    // "Train" every point of the base plan: the Chinchilla law at its (N, D), with the ripple.
    let mut csv = String::from("run_id,index,budget,n_nv,tokens,flops,norm_test_loss\n");
    for (i, p) in base.points.iter().enumerate() {
        let n = p.n_nv as f64;
        let loss = CHINCHILLA.loss(n, p.budget / (6.0 * n)) + ripple(n, p.budget);
        let (c, id) = (p.budget, &p.run_id);
        let _ = writeln!(csv, "{id},{i},{c},{n},{},{c},{loss}", p.tokens);
    }
    let results = tmp.path().join("results.csv");
    std::fs::write(&results, csv).unwrap();
    let fit = tmp.path().join("fit");
    motionscale_ok(&[
        "fit",
        "--results",
        arg(&results),
        "--bootstrap",
        "0",
        "--out",
        arg(&fit),
    ]);

    let next_path = tmp.path().join("next.toml");
    let fits_json = fit.join("fits.json");
    let stdout = sweep_plan(
        &corpus,
        "3e11",
        models,
        "256",
        &[
            "--extend",
            arg(&base_path),
            "--next",
            "2",
            "--fits",
            arg(&fits_json),
            "--target-budget",
            "1e12",
        ],
        &next_path,
    );
    let n_base = base.points.len();
    assert!(
        stdout.contains(&format!("planner: {n_base} trained runs of the plan")),
        "{stdout}"
    );
    assert!(stdout.contains("next 1: "), "{stdout}");
    let next = IsoFlopPlan::read(&next_path).unwrap();
    assert_eq!(
        next.points[..n_base],
        base.points[..],
        "the base comes first, unchanged"
    );
    let new = &next.points[n_base..];
    // No parabola at 3e11 yet: the first proposal enters it with sizes that straddle the
    // law's vertex there, near the truth.
    assert!(new.len() >= 3, "{stdout}");
    assert!(new.iter().all(|p| p.budget == 3e11), "{new:?}");
    let sizes: Vec<f64> = new.iter().map(|p| (p.n_nv as f64).log10()).collect();
    let truth = CHINCHILLA.n_opt(3e11).log10();
    let (low, high) = sizes
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &x| {
            (l.min(x), h.max(x))
        });
    assert!(low < truth && truth < high, "{sizes:?} around {truth}");
    for p in new {
        assert!(stdout.contains(&p.run_id), "{} printed: {stdout}", p.run_id);
    }
    next_from_a_law_family(&corpus, models, (&base_path, &results));
}

/// `--next` on the laws.json of `fit --law chinchilla` over the same runs: the V-optimal
/// design's runs for the loss at C*, appended to the base plan.
fn next_from_a_law_family(corpus: &Path, models: &str, (base_path, results): (&Path, &Path)) {
    let tmp = tempfile::tempdir().unwrap();
    let fit = tmp.path().join("laws");
    motionscale_ok(&[
        "fit",
        "--law",
        "chinchilla",
        "--results",
        arg(results),
        "--loss-col",
        "norm_test_loss",
        "--bootstrap",
        "0",
        "--out",
        arg(&fit),
    ]);
    let next_path = tmp.path().join("next.toml");
    let laws = fit.join("laws.json");
    let stdout = sweep_plan(
        corpus,
        "3e11",
        models,
        "256",
        &[
            "--extend",
            arg(base_path),
            "--next",
            "2",
            "--fits",
            arg(&laws),
            "--target-budget",
            "1e12",
        ],
        &next_path,
    );
    assert!(stdout.contains("planner: chinchilla law"), "{stdout}");
    let (base, next) = (
        IsoFlopPlan::read(base_path).unwrap(),
        IsoFlopPlan::read(&next_path).unwrap(),
    );
    let new = &next.points[base.points.len()..];
    assert_eq!(new.len(), 2, "{stdout}");
    for p in new {
        assert!(
            p.budget == 3e11 && stdout.contains(&p.run_id),
            "{p:?}: {stdout}"
        );
    }
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
    let cubic = motionscale(&[
        "sweep",
        "replay",
        "--results",
        arg(&csv),
        "--target-budget",
        "3e20",
        "--loss-form",
        "cubic",
        "--out",
        arg(&out),
    ]);
    fails_with(&cubic, "expected log, curved or floor");

    let one = tmp.path().join("one.csv");
    write_table(&one, &[1e18]);
    fails_with(&replay("1e21", &one), "1 budget(s) below");

    // Two rows of one run id: a replay names its choices by id.
    let twice = tmp.path().join("twice.csv");
    let text = std::fs::read_to_string(&csv).unwrap();
    std::fs::write(&twice, text.replacen("\nr1,", "\nr0,", 1)).unwrap();
    fails_with(
        &replay("1e20", &twice),
        "column \"run_id\", row 2 (data row, 1-based): \"r0\" is row 1's id too",
    );

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
