//! The fitters recover known laws from synthetic, noisy IsoFLOP tables, read from CSV and
//! Parquet exactly as `motionscale fit` reads them.

use fits::fitted::{ColumnChoice, ColumnSpec, FitOptions};
use fits::lbfgs::LbfgsOptions;
use fits::parametric::{self, LogRuns, StartGrid};
use fits::synth::{self, CHINCHILLA, VOCAB_LAW};
use fits::{fit_table, Table};
use std::path::Path;
use std::sync::Arc;

fn epoch_columns() -> ColumnSpec {
    let named = |n: &str| ColumnChoice {
        name: n.into(),
        explicit: true,
    };
    ColumnSpec {
        n: named("Model Size"),
        d: named("Training Tokens"),
        c: named("Training FLOP"),
        loss: named("loss"),
        ..ColumnSpec::default()
    }
}

fn inside(name: &str, e: &fits::laws::Estimate, truth: f64) {
    let (lo, hi) = (e.ci_low.unwrap(), e.ci_high.unwrap());
    assert!(
        lo <= truth && truth <= hi,
        "{name}: truth {truth} outside [{lo}, {hi}] (estimate {})",
        e.value
    );
}

fn within_2se(name: &str, e: &fits::laws::Estimate, truth: f64) {
    let se = e.se.unwrap();
    assert!(
        (e.value - truth).abs() <= 2.0 * se,
        "{name}: {} ± {se} vs truth {truth}",
        e.value
    );
}

#[test]
fn chinchilla_standin_parameters_lie_in_their_bootstrap_intervals() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("standin.csv");
    synth::write_epoch_csv(&csv, &synth::chinchilla_standin(11)).unwrap();
    let table = Table::read(&csv).unwrap();
    let opts = FitOptions {
        columns: epoch_columns(),
        bootstrap: 200,
        seed: 5,
        ..FitOptions::default()
    };
    let f = fit_table(&table, &opts).unwrap();
    assert_eq!(f.input.groups, 9, "{}", f.input.grouping);
    assert!(f.budgets.iter().all(|b| b.min.interior), "{:?}", f.warnings);

    let p = f.parametric.as_ref().unwrap();
    assert_eq!(p.starts, 4500);
    assert_eq!(p.bootstrap.succeeded, 200);
    assert_eq!(p.loss_column, "loss");
    for (name, est, truth) in [
        ("E", &p.law.e, CHINCHILLA.e),
        ("A", &p.law.a, CHINCHILLA.a),
        ("B", &p.law.b, CHINCHILLA.b),
        ("alpha", &p.law.alpha, CHINCHILLA.alpha),
        ("beta", &p.law.beta, CHINCHILLA.beta),
    ] {
        inside(name, est, truth);
    }
    inside(
        "N_opt exponent (parametric)",
        &p.n_opt_exponent,
        CHINCHILLA.n_exponent(),
    );

    // Approach 2: N_opt ∝ C^(β/(α+β)), D_opt ∝ C^(α/(α+β)).
    let n_law = &f.power_laws["n_opt_vs_c"];
    within_2se("N_opt exponent", &n_law.fit.slope, CHINCHILLA.n_exponent());
    let d_law = &f.power_laws["d_opt_vs_c"];
    within_2se(
        "D_opt exponent",
        &d_law.fit.slope,
        1.0 - CHINCHILLA.n_exponent(),
    );
    assert!(n_law.fit.r2.unwrap() > 0.99);
    assert!(f.log_law.is_some());
    assert!(
        f.skipped
            .iter()
            .any(|s| s.starts_with("v_opt_vs_c, nv_opt_vs_c, nv_vs_n: no vocabulary column")),
        "{:?}",
        f.skipped
    );
    // Approaches 2 and 3 agree on both exponents: their 95% intervals overlap.
    assert_eq!(f.agreement.len(), 2);
    assert!(
        f.agreement.iter().all(|a| a.overlap == Some(true)),
        "{:?}",
        f.agreement
    );
}

#[test]
fn bootstrap_subset_starts_reach_the_full_grid_optimum() {
    // The bootstrap refits each resample from the best distinct local optima (up to 16) of the
    // full-data grid instead of all 4,500 starts; on resamples, that must find the same optimum.
    let runs_raw = synth::chinchilla_standin(2);
    let n: Vec<f64> = runs_raw.iter().map(|r| r.n).collect();
    let d: Vec<f64> = runs_raw.iter().map(|r| r.d).collect();
    let l: Vec<f64> = runs_raw.iter().map(|r| r.loss).collect();
    let runs = LogRuns::new(&n, &d, &l);
    let opts = LbfgsOptions::default();
    let grid = StartGrid::epoch().points();
    let full = parametric::multi_start(&runs, 1e-3, &grid, &opts).unwrap();
    let subset = full.distinct_best(16);
    assert!(subset.len() > 1);
    let draws = parametric::bootstrap(&runs, 1e-3, &subset, 4, 9, &opts);
    for (i, theta) in draws.iter().enumerate() {
        let sample = parametric::resample(&runs, 9, i);
        let best_full = parametric::multi_start(&sample, 1e-3, &grid, &opts).unwrap();
        let mut g = [0.0; 5];
        let f_sub = parametric::objective(&sample, 1e-3, &theta.unwrap(), &mut g);
        let f_full = best_full.best().f;
        assert!(
            f_sub <= f_full * (1.0 + 1e-6),
            "resample {i}: subset objective {f_sub} vs full grid {f_full}"
        );
    }
}

#[test]
fn vocabulary_sweep_with_default_columns_recovers_gamma_from_csv_and_parquet() {
    let dir = tempfile::tempdir().unwrap();
    let rows = synth::vocab_sweep(4);
    let csv = dir.path().join("results.csv");
    synth::write_sweep_csv(&csv, &rows).unwrap();
    let pq = dir.path().join("results.parquet");
    write_sweep_parquet(&pq, &rows);
    let opts = FitOptions {
        bootstrap: 20,
        grid: StartGrid::coarse(),
        grid_name: "coarse".into(),
        ..FitOptions::default()
    };
    let from_csv = fit_table(&Table::read(&csv).unwrap(), &opts).unwrap();
    let from_pq = fit_table(&Table::read(&pq).unwrap(), &opts).unwrap();
    assert_eq!(
        from_csv.power_laws, from_pq.power_laws,
        "same numbers from CSV and Parquet"
    );

    let f = from_csv;
    assert_eq!(f.input.columns["C"].as_deref(), Some("budget"));
    assert_eq!(f.input.columns["loss"].as_deref(), Some("norm_test_loss"));
    assert_eq!(f.input.columns["width"].as_deref(), Some("d_model"));
    assert_eq!(f.input.groups, 7);
    let interior_v = f.vocab_minima.iter().filter(|m| m.interior).count();
    assert!(
        interior_v * 10 >= f.vocab_minima.len() * 6,
        "{interior_v} of {}",
        f.vocab_minima.len()
    );

    let gamma = &f.power_laws["nv_vs_n"];
    within_2se("gamma", &gamma.fit.slope, VOCAB_LAW.gamma);
    within_2se("log10 k", &gamma.fit.intercept, VOCAB_LAW.log10_k);
    // Approach 2 over a discrete vocabulary grid is biased here: the best V of each (C, N) sits
    // at a varying distance from V*(N), which tilts the loss-vs-N parabolas (about -0.02 on
    // the exponent across seeds, several of its OLS standard errors). That exponent is
    // therefore checked to 0.03; γ, k and the noisier N_v,opt exponent are held to 2 SE.
    let base = VOCAB_LAW.base;
    let close = |name: &str, e: &fits::laws::Estimate, truth: f64| {
        assert!(
            (e.value - truth).abs() < 0.03,
            "{name}: {} vs truth {truth}",
            e.value
        );
    };
    close(
        "N_opt exponent",
        &f.power_laws["n_opt_vs_c"].fit.slope,
        base.n_exponent(),
    );
    within_2se(
        "N_v,opt exponent",
        &f.power_laws["nv_opt_vs_c"].fit.slope,
        VOCAB_LAW.gamma * base.n_exponent(),
    );
    // V* = N_v*/d with d ∝ N^(1/3) (N = 12·(d/32)·d²): V_opt ∝ C^((γ − 1/3)·b).
    within_2se(
        "V_opt exponent",
        &f.power_laws["v_opt_vs_c"].fit.slope,
        (VOCAB_LAW.gamma - 1.0 / 3.0) * base.n_exponent(),
    );
    // The total-parameter convention is fitted beside N_nv.
    let total = f.total_n.as_ref().unwrap();
    assert_eq!(total.input.columns["N"].as_deref(), Some("n_nv + n_v"));
    assert!(total.power_laws.contains_key("n_opt_vs_c"));
    // The normalised loss is negative for many runs: the log law uses it, the parametric fit
    // uses the positive test_loss.
    assert!(f.log_law.is_some());
    assert_eq!(f.parametric.as_ref().unwrap().loss_column, "test_loss");
}

#[test]
fn bad_inputs_name_the_file_the_column_and_the_row() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("bad.csv");
    std::fs::write(
        &csv,
        "n_nv,budget,norm_test_loss\n1e6,1e15,2.0\n2e6,1e15,oops\n",
    )
    .unwrap();
    let t = Table::read(&csv).unwrap();
    let err = fit_table(&t, &FitOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("bad.csv")
            && err.contains("norm_test_loss")
            && err.contains("row 2")
            && err.contains("oops"),
        "{err}"
    );

    std::fs::write(
        &csv,
        "n_nv,budget,norm_test_loss\n1e6,1e15,2.0\n2e6,1e15,1.9\n",
    )
    .unwrap();
    let t = Table::read(&csv).unwrap();
    let opts = FitOptions {
        columns: ColumnSpec {
            d: ColumnChoice {
                name: "toks".into(),
                explicit: true,
            },
            ..ColumnSpec::default()
        },
        ..FitOptions::default()
    };
    let err = fit_table(&t, &opts).unwrap_err().to_string();
    assert!(
        err.contains("no column \"toks\"") && err.contains("--d-col"),
        "{err}"
    );

    let err = fit_table(&t, &FitOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad.csv: too few runs"), "{err}");

    std::fs::write(&csv, "n_nv,budget,norm_test_loss\n-1,1e15,2.0\n").unwrap();
    let err = fit_table(&Table::read(&csv).unwrap(), &FitOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("row 1") && err.contains("must be > 0"),
        "{err}"
    );

    let err = Table::read(Path::new("results.xlsx"))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("results.xlsx") && err.contains(".csv or .parquet"),
        "{err}"
    );
}

fn write_sweep_parquet(path: &Path, rows: &[synth::SweepRow]) {
    use arrow_array::{ArrayRef, Float64Array, RecordBatch, StringArray, UInt32Array};
    let f = |get: fn(&synth::SweepRow) -> f64| -> ArrayRef {
        Arc::new(Float64Array::from(rows.iter().map(get).collect::<Vec<_>>()))
    };
    let u = |get: fn(&synth::SweepRow) -> u32| -> ArrayRef {
        Arc::new(UInt32Array::from(rows.iter().map(get).collect::<Vec<_>>()))
    };
    let ids: ArrayRef = Arc::new(StringArray::from(
        rows.iter().map(|r| r.run_id.clone()).collect::<Vec<_>>(),
    ));
    let columns: Vec<(&str, ArrayRef)> = vec![
        ("run_id", ids),
        ("budget", f(|r| r.budget)),
        ("n_nv", f(|r| r.n_nv)),
        ("n_v", f(|r| r.n_v)),
        ("vocab", f(|r| r.vocab)),
        ("d_model", f(|r| r.d_model)),
        ("layers", u(|r| r.layers)),
        ("heads", u(|r| r.heads)),
        ("tokens", f(|r| r.tokens)),
        ("train_loss", f(|r| r.train_loss)),
        ("test_loss", f(|r| r.test_loss)),
        ("norm_test_loss", f(|r| r.norm_test_loss)),
        ("wall_s", f(|r| r.wall_s)),
        ("flops", f(|r| r.flops)),
    ];
    let batch = RecordBatch::try_from_iter(columns).unwrap();
    let file = std::fs::File::create(path).unwrap();
    let mut w = parquet::arrow::ArrowWriter::try_new(file, batch.schema(), None).unwrap();
    w.write(&batch).unwrap();
    w.close().unwrap();
}
