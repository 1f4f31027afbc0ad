//! End-to-end: `motionscale fit` on a Chinchilla-like stand-in with Epoch's column names,
//! `motionscale predict` from its fits.json and from the scamo preset, and bad inputs.

mod common;

use common::*;
use fits::synth;

#[test]
fn fit_standin_through_the_cli_then_predict_from_its_fits() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("chinchilla.csv");
    synth::write_epoch_csv(&csv, &synth::chinchilla_standin(21)).unwrap();
    let out = tmp.path().join("fits");
    let run = motionscale(&[
        "fit",
        "--results",
        csv.to_str().unwrap(),
        "--n-col",
        "Model Size",
        "--d-col",
        "Training Tokens",
        "--c-col",
        "Training FLOP",
        "--loss-col",
        "loss",
        "--bootstrap",
        "40",
        "--seed",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code(&run), 0, "{}", text(&run));
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        stdout.contains("IsoFLOP minima over N: 9 of 9 interior"),
        "{stdout}"
    );
    assert!(stdout.contains("parametric L(N, D)"), "{stdout}");

    let fits: serde_json::Value = read_json(&out.join("fits.json"));
    assert_eq!(fits["settings"]["starts"], 4500);
    assert_eq!(fits["settings"]["seed"], 3);
    assert_eq!(fits["settings"]["huber_delta"], 1e-3);
    assert_eq!(fits["settings"]["bootstrap"], 40);
    assert_eq!(fits["input"]["columns"]["N"], "Model Size");
    assert_eq!(fits["input"]["columns"]["C"], "Training FLOP");
    assert_eq!(fits["parametric"]["n_runs"], 252);
    for key in ["E", "A", "B", "alpha", "beta"] {
        let p = &fits["parametric"][key];
        let (v, lo, hi) = (
            p["value"].as_f64().unwrap(),
            p["ci_low"].as_f64().unwrap(),
            p["ci_high"].as_f64().unwrap(),
        );
        assert!(lo <= v && v <= hi, "{key}: {p}");
    }
    let alpha = fits["parametric"]["alpha"]["value"].as_f64().unwrap();
    assert!((alpha - 0.34).abs() < 0.05, "alpha {alpha}");
    for stem in ["isoflop_n", "law_n_opt_vs_c", "law_d_opt_vs_c", "log_law"] {
        let png = std::fs::read(out.join(format!("{stem}.png"))).unwrap();
        assert!(png.starts_with(b"\x89PNG"), "{stem}.png");
        let svg = std::fs::read_to_string(out.join(format!("{stem}.svg"))).unwrap();
        assert!(svg.contains("<svg"), "{stem}.svg");
    }

    let fits_path = out.join("fits.json");
    let pred = motionscale(&[
        "predict",
        "--fits",
        fits_path.to_str().unwrap(),
        "--budget",
        "1e22",
        "--json",
    ]);
    assert_eq!(code(&pred), 0, "{}", text(&pred));
    let p: serde_json::Value = serde_json::from_slice(&pred.stdout).unwrap();
    let n = p["n_nv"]["value"].as_f64().unwrap();
    let truth = synth::CHINCHILLA.n_opt(1e22);
    assert!((n / truth).log10().abs() < 0.1, "N_opt {n:e} vs {truth:e}");
    assert!(
        p["n_nv"]["ci_low"].as_f64().unwrap() < n && n < p["n_nv"]["ci_high"].as_f64().unwrap()
    );
    let par = p["parametric"]["n_opt"]["value"].as_f64().unwrap();
    assert!(
        (par / truth).log10().abs() < 0.1,
        "parametric N_opt {par:e} vs {truth:e}"
    );
}

#[test]
fn predict_scamo_preset_states_the_inconsistencies() {
    let out = motionscale(&["predict", "--preset", "scamo", "--budget", "1e18", "--json"]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let p: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let n_nv = p["n_nv"]["value"].as_f64().unwrap();
    assert!((n_nv / 10f64.powf(-0.52 + 0.57 * 18.0) - 1.0).abs() < 1e-9);
    assert!((n_nv / 5.5e9 - 1.0).abs() < 0.01, "{n_nv:e}");
    assert_eq!(p["vocab"]["nominal"], 65536);
    assert_eq!(p["vocab"]["real"], 64000);
    let checks = p["consistency"].as_array().unwrap();
    let failed: Vec<&str> = checks
        .iter()
        .filter(|c| c["ok"] == false)
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    for name in [
        "compute",
        "N_v: C-law vs N_nv-law",
        "paper at 1e18: N_nv",
        "paper at 1e18: D",
    ] {
        assert!(
            failed.iter().any(|f| f.starts_with(name)),
            "{name} not flagged: {failed:?}"
        );
    }
    let warnings = p["warnings"].as_array().unwrap();
    assert!(warnings.len() >= failed.len());

    let human = motionscale(&["predict", "--preset", "scamo", "--budget", "1e18"]);
    assert_eq!(code(&human), 0);
    assert!(String::from_utf8_lossy(&human.stdout).contains("warning: inconsistent: compute"));
}

/// A committed fit whose parametric law diverged (B = ∞: the stage-2 ladder's `dc-stopping`
/// fit, docs/results/data-law/recipe/ladder): `predict` says it has no compute-optimal
/// allocation instead of printing an N_opt of 0 and a NaN loss.
#[test]
fn predict_refuses_the_allocation_of_a_diverged_parametric_law() {
    let fits = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("docs/results/data-law/recipe/ladder/stage2/dc-stopping/fits.json");
    let printed = motionscale_ok(&["predict", "--fits", arg(&fits), "--budget", "1e15"]);
    assert!(
        printed.contains("the parametric law has no compute-optimal allocation (A "),
        "{printed}"
    );
    for absent in ["NaN", "parametric N_opt"] {
        assert!(!printed.contains(absent), "{absent:?} in {printed}");
    }
}

/// `predict --sizes` on the committed stage-3 fit of the data-law ladder (`dc-stopping` on 94
/// runs): at 2·10¹⁴ FLOPs on half the data, the law gives `1024x4` (5.1·10⁷ parameters) a
/// higher loss than the small sizes it asks for — it stops after fewer epochs — and the best of
/// the sizes is the lowest; a size that is not positive names the file, and --sizes needs
/// --hours.
#[test]
fn predict_sizes_gives_each_size_its_loss_and_the_best_of_them() {
    let fits = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("docs/results/data-law/recipe/ladder/stage3/dc-stopping/fits.json");
    let args = [
        "predict",
        "--fits",
        arg(&fits),
        "--budget",
        "2e14",
        "--hours",
        "real=3.036889,synth=2.844333",
    ];
    let sizes = ["--sizes", "1845120,3247616,50739200"];
    let text = motionscale_ok(&[&args[..], &sizes].concat());
    for needle in [
        "the sizes asked about (--sizes):",
        "N 5.074e7",
        "best, N 3.248e6",
    ] {
        assert!(text.contains(needle), "{needle:?} in {text}");
    }
    let json = motionscale_ok(&[&args[..], &sizes, &["--json"]].concat());
    let raw: serde_json::Value = serde_json::from_str(&json).unwrap();
    let s: fits::data_value::SizeLosses = serde_json::from_value(raw["sizes"].clone()).unwrap();
    let loss: Vec<f64> = s.sizes.iter().map(|z| z.loss.value).collect();
    assert!(
        loss[2] > loss[0] + 0.05 && loss[2] > loss[1] + 0.05,
        "{loss:?}"
    );
    assert!(s.sizes[2].stop_epochs < s.sizes[0].stop_epochs, "{s:?}");
    assert_eq!(s.best.loss.value, loss[0].min(loss[1]));
    assert!(s.best.loss_prediction.is_some(), "{s:?}");

    let bad = motionscale(&[&args[..], &["--sizes", "3e6,0"]].concat());
    fails_with(
        &bad,
        "fits.json: --sizes 0: a model size must be a positive number",
    );
    let no_hours = motionscale(&[
        "predict",
        "--fits",
        arg(&fits),
        "--budget",
        "2e14",
        "--sizes",
        "3e6",
    ]);
    fails_with(&no_hours, "--hours");
}

#[test]
fn fit_errors_name_the_file_and_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("runs.csv");
    std::fs::write(
        &csv,
        "n_nv,budget,norm_test_loss\n1e6,1e15,2.0\n2e6,1e15,x\n",
    )
    .unwrap();
    let out_dir = tmp.path().join("out");
    let args = |extra: &[&str]| {
        let mut a = vec![
            "fit",
            "--results",
            csv.to_str().unwrap(),
            "--out",
            out_dir.to_str().unwrap(),
        ];
        a.extend_from_slice(extra);
        motionscale(&a)
    };
    let out = args(&[]);
    assert_eq!(code(&out), 1);
    let msg = text(&out);
    assert!(
        msg.contains("runs.csv") && msg.contains("row 2") && msg.contains("\"x\" is not a number"),
        "{msg}"
    );

    let out = args(&["--loss-col", "L"]);
    assert_eq!(code(&out), 1);
    assert!(text(&out).contains("no column \"L\""), "{}", text(&out));

    let out = motionscale(&["predict", "--budget", "1e18"]);
    assert_ne!(code(&out), 0, "needs --fits or --preset");
}

#[test]
fn fit_holds_out_a_budget_fits_both_conventions_and_says_what_it_cannot_fit() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("sweep.csv");
    synth::write_sweep_csv(&csv, &synth::vocab_sweep(2)).unwrap();
    let out = tmp.path().join("fits");
    let fit = |results: &std::path::Path, extra: &[&str]| {
        let mut args = vec![
            "fit",
            "--results",
            arg(results),
            "--out",
            arg(&out),
            "--starts-grid",
            "coarse",
            "--bootstrap",
            "10",
        ];
        args.extend_from_slice(extra);
        motionscale(&args)
    };
    let run = fit(&csv, &["--holdout-budget", "1e18", "--repeated-data"]);
    assert_eq!(code(&run), 0, "{}", text(&run));
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        stdout.contains("held-out budget 1.000e18 (42 runs"),
        "{stdout}"
    );
    assert!(
        stdout.contains("N_opt exponent: IsoFLOP (approach 2)"),
        "{stdout}"
    );
    assert!(
        stdout.contains("total parameters (N = n_nv + n_v)"),
        "{stdout}"
    );
    assert!(
        stdout.contains(
            "skipped: data-constrained L(N, D'): needs a tokens column and an epochs column"
        ),
        "{stdout}"
    );
    let fits: serde_json::Value = read_json(&out.join("fits.json"));
    assert_eq!(
        fits["budgets"].as_array().unwrap().len(),
        6,
        "1e18 not fitted"
    );
    let checks = fits["holdout"]["checks"].as_array().unwrap();
    assert_eq!(checks[0]["quantity"], "N_opt (IsoFLOP law)");
    assert!(
        checks[0]["ratio"].as_f64().unwrap() > 0.5 && checks[0]["ratio"].as_f64().unwrap() < 2.0
    );
    assert_eq!(fits["total_n"]["input"]["columns"]["N"], "n_nv + n_v");
    assert!(fits["power_laws"]["v_opt_vs_c"]["fit"]["slope"]["value"].is_number());

    let pred = motionscale(&[
        "predict",
        "--fits",
        arg(&out.join("fits.json")),
        "--budget",
        "1e19",
    ]);
    assert_eq!(code(&pred), 0, "{}", text(&pred));
    let p = String::from_utf8_lossy(&pred.stdout);
    assert!(p.contains("V (its own C-law)"), "{p}");
    assert!(
        p.contains("N_opt: IsoFLOP law (approach 2) vs parametric (approach 3)"),
        "{p}"
    );

    // One budget and one vocabulary: what cannot be fitted is named, the rest is fitted, exit 0.
    let one = tmp.path().join("one.csv");
    let text_all = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text_all.lines();
    let mut kept = vec![lines.next().unwrap().to_string()];
    kept.extend(
        lines
            .filter(|l| l.contains("c1e15-") && l.contains("-v1024,"))
            .map(String::from),
    );
    std::fs::write(&one, kept.join("\n") + "\n").unwrap();
    let run = fit(&one, &[]);
    assert_eq!(code(&run), 0, "{}", text(&run));
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        stdout.contains("1 vocabulary size(s) in the table (1024); a minimum over V needs 3"),
        "{stdout}"
    );
    assert!(
        stdout.contains("in 1 budget group(s), need 3 budgets"),
        "{stdout}"
    );
    assert!(stdout.contains("parametric L(N, D)"), "{stdout}");
}

#[test]
fn predict_hours_needs_a_data_constrained_law() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("chinchilla.csv");
    synth::write_epoch_csv(&csv, &synth::chinchilla_standin(5)).unwrap();
    let out = tmp.path().join("fits");
    motionscale_ok(&[
        "fit",
        "--results",
        arg(&csv),
        "--n-col",
        "Model Size",
        "--d-col",
        "Training Tokens",
        "--c-col",
        "Training FLOP",
        "--loss-col",
        "loss",
        "--bootstrap",
        "0",
        "--out",
        arg(&out),
    ]);
    let fits = out.join("fits.json");
    let predict = |hours: &str| {
        motionscale(&[
            "predict",
            "--fits",
            arg(&fits),
            "--budget",
            "1e22",
            "--hours",
            hours,
        ])
    };
    fails_with(&predict("real=20,synth=10"), "no data-constrained law");
    fails_with(&predict("mocap=3"), "the sources are real and synth");
}

/// A captured-only ladder drawn from a known data-constrained law whose runs stop improving
/// after e* = 100·N^−0.35·U^0.05 epochs, with the sweep's columns (`best_step` of 100,000
/// steps, `hours` at 10⁶ unique tokens an hour), written to `path`.
fn stopping_ladder(path: &std::path::Path) {
    let truth = fits::repeated::NaturalLaw {
        theta: [1.2, 60.0, 400.0, 0.35, 0.3, 6.0, 1.0, f64::INFINITY],
        form: fits::fitted::ExchangeForm::TokenWorth,
    };
    let rule = [100f64.ln(), -0.35, 0.05];
    let mut csv = String::from(
        "budget,n_nv,tokens,test_loss,norm_test_loss,epochs,synth_share,best_step,steps,hours\n",
    );
    for unique in [5e6, 2e7] {
        for c in [1e13, 1e14, 1e15] {
            for k in 0..5 {
                let n = 10f64.powf(4.0 + 0.5 * k as f64);
                let d = c / (6.0 * n);
                let stop = fits::stopping::stop_epochs(&rule, n, unique) * unique;
                let step = (1e5 * (stop / d).min(1.0)).round().max(1.0);
                let l = truth.loss(n, d * step / 1e5, unique, 0.0);
                csv.push_str(&format!(
                    "{c},{n},{d},{l},{l},{},0,{step},100000,{}\n",
                    d / unique,
                    unique / 1e6
                ));
            }
        }
    }
    std::fs::write(path, csv).unwrap();
}

#[test]
fn predict_hours_from_an_early_stopping_fit_says_what_compute_cannot_buy() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("ladder.csv");
    stopping_ladder(&csv);
    let out = tmp.path().join("fits");
    let fitted = motionscale_ok(&[
        "fit",
        "--results",
        arg(&csv),
        "--repeated-data",
        "--early-stopping",
        "--starts-grid",
        "coarse",
        "--bootstrap",
        "20",
        "--out",
        arg(&out),
    ]);
    assert!(fitted.contains("early stopping: ln e* = 4.6"), "{fitted}");
    assert!(
        fitted.contains("in sample: the 95% prediction interval (refits + a run's scatter"),
        "{fitted}"
    );
    let fits = out.join("fits.json");
    let args = ["predict", "--fits", arg(&fits), "--budget", "1e18"];
    let text = motionscale_ok(&[&args[..], &["--hours", "real=5"]].concat());
    for needle in [
        "  a run    ",
        "a run: the 95% prediction interval of one run's loss",
        "stops at",
        "buys nothing on these hours",
        "+1 h real : loss -",
        "worth more than any compute: no budget reaches that loss with today's hours",
    ] {
        assert!(text.contains(needle), "{needle:?} in {text}");
    }
    let json = motionscale_ok(&[&args[..], &["--hours", "real=5", "--json"]].concat());
    let raw: serde_json::Value = serde_json::from_str(&json).unwrap();
    let real = &raw["prediction"]["hour_values"][0];
    assert!(
        real["compute_equivalent"]["value"].is_null(),
        "∞ is null in JSON: {real}"
    );
    // … and reads back as ∞.
    let p: fits::data_value::DataPrediction =
        serde_json::from_value(raw["prediction"].clone()).unwrap();
    let stop = p.stop_epochs.expect("the stopping rule's epochs at N_opt");
    assert!(p.epochs.value > 10.0 * stop.value, "{p:?}");
    let real = &p.hour_values[0];
    assert_eq!((real.source.as_str(), real.unbuyable), ("real", 1.0));
    assert!(real.compute_equivalent.value.is_infinite(), "{real:?}");
    data_bound_verdict(&fits);
}

/// `fit --exchange-form` takes both forms, scores each on held-out runs and prints them, the
/// adopted first; a form it does not know is refused by name.
#[test]
fn fit_scores_both_exchange_forms_on_the_data_subsets() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("ladder.csv");
    stopping_ladder(&csv);
    let out = tmp.path().join("fits");
    let fit = |form: &'static str| {
        let args = [
            "fit",
            "--results",
            arg(&csv),
            "--repeated-data",
            "--exchange-form",
        ];
        let rest = [
            "--starts-grid",
            "coarse",
            "--bootstrap",
            "0",
            "--out",
            arg(&out),
        ];
        [&args[..], &[form], &rest[..]].concat()
    };
    // One source: ρ is not fitted; two data subsets are too few, so each form is scored on
    // the 3 budgets left out in turn.
    let printed = motionscale_ok(&fit("effective-pool,token-worth"));
    for needle in [
        "form effective-pool (adopted): rho -, RMS log error",
        "form token-worth: rho -, RMS log error",
        "over 3 budgets left out",
    ] {
        assert!(printed.contains(needle), "{needle:?} in {printed}");
    }
    let refused = motionscale(&fit("pool"));
    fails_with(&refused, "invalid value 'pool' for '--exchange-form");
}

/// On the same fit, at 10¹⁸ FLOPs and 2.5 h distinct captured hours mirrored (5 h in the
/// fit's units), with a seed SD of 0.005 nats: the budget is data-bound, the verdict says
/// where compute stops paying, when to stop and what doubling the captured hours buys, the
/// two naive baselines are printed and no hour is given a compute price.
fn data_bound_verdict(fits: &std::path::Path) {
    let args = [
        "predict",
        "--fits",
        arg(fits),
        "--budget",
        "1e18",
        "--hours",
        "real=2.5",
        "--mirrored",
        "--noise",
        "0.005",
    ];
    let text = motionscale_ok(&args);
    for needle in [
        "2.5 h distinct = 5 h with mirrors",
        "data-bound above ",
        "with the schedule ending there",
        "buy data — doubling the captured hours changes the loss by -",
        "baselines from the best run at C = 1.000e15",
        "no growth N",
        "N ∝ C N",
    ] {
        assert!(text.contains(needle), "{needle:?} in {text}");
    }
    assert!(!text.contains("× compute"), "no compute price: {text}");
    let json = motionscale_ok(&[&args[..], &["--json"]].concat());
    let raw: serde_json::Value = serde_json::from_str(&json).unwrap();
    let b: fits::data_value::DataBound = serde_json::from_value(raw["data_bound"].clone()).unwrap();
    assert!(b.bound && b.saturation.value < 1e18, "{b:?}");
    assert!(
        b.doubling.value < 0.0 && b.doubling.ci_high.unwrap() < 0.0,
        "{b:?}"
    );
    report_leads_with_the_verdict(fits, &text);
}

/// `report FITS --hours …` opens its first section with the verdict `predict` printed, before
/// the first budget's table; without --hours it says how to get it.
fn report_leads_with_the_verdict(fits: &std::path::Path, predicted: &str) {
    let dir = fits.parent().unwrap();
    let page = |extra: &[&str]| {
        let html = dir.join("report.html");
        let args = [
            "report",
            arg(fits),
            "--budgets",
            "1e18",
            "--out",
            arg(&html),
        ];
        motionscale_ok(&[&args[..], extra].concat());
        std::fs::read_to_string(&html).unwrap()
    };
    let html = page(&["--hours", "real=2.5", "--mirrored", "--noise", "0.005"]);
    let first = html.find("<section id=\"predictions\">").unwrap();
    let answer = &html[first..html[first..].find("<h3>").unwrap() + first];
    let sentence = predicted
        .lines()
        .find(|l| l.contains("data-bound above "))
        .unwrap()
        .trim()
        .replace('<', "&lt;");
    assert!(
        answer.contains("C = 1.000e18 FLOPs on 2.5 h distinct = 5 h with mirrors captured"),
        "{answer}"
    );
    assert!(answer.contains(&sentence), "{sentence:?} in {answer}");
    let n_opt = predicted
        .lines()
        .find_map(|l| l.trim().strip_prefix("N_opt"))
        .unwrap()
        .trim();
    assert!(
        answer.contains(&format!("The data-constrained optimum: N_opt {n_opt}, ")),
        "{n_opt:?} in {answer}"
    );
    // Past C_sat the IsoFLOP table that follows is marked as not applying.
    let table = &html[first + answer.len()..];
    assert!(
        table.contains("Past C_sat on 2.5 h distinct") && table.contains("do not apply here"),
        "{table}"
    );
    let without = page(&[]);
    assert!(without.contains("give --hours real=H,synth=H for its data-bound verdict"));
}

/// ScaleBench's tasks (arXiv 2604.22753) through `fit --law all`: each task's family chosen
/// on its train split alone, then scored on its held-out high-compute split; the paper's
/// "All Data" R² is 0.79 (data_con), 0.93 (vocab) and 0.91 (farseer).
#[test]
fn fit_law_all_on_scalebench_beats_the_all_data_rows() {
    let Some(data) = shared_data() else { return };
    let sb = data.join("scalebench");
    let tmp = tempfile::tempdir().unwrap();
    let tasks: [(&str, &[&str], &str, f64); 3] = [
        (
            "data_constrained",
            &[
                "--n-col",
                "params",
                "--d-col",
                "tokens",
                "--loss-col",
                "loss",
            ],
            "data-constrained",
            0.79,
        ),
        (
            "vocab",
            &[
                "--n-col",
                "non_vocab_parameters",
                "--nv-col",
                "vocab_size",
                "--d-col",
                "num_characters",
                "--loss-col",
                "unigram_normalized_loss",
            ],
            "vocab-effective",
            0.93,
        ),
        (
            "farseer",
            &["--n-col", "N", "--d-col", "D", "--loss-col", "loss"],
            "farseer",
            0.91,
        ),
    ];
    for (task, cols, family, all_data) in tasks {
        let train = sb.join(format!("{task}_scaling_law-train.parquet"));
        let test = sb.join(format!("{task}_scaling_law-test.parquet"));
        let out = tmp.path().join(task);
        let mut args = vec![
            "fit",
            "--law",
            "all",
            "--results",
            arg(&train),
            "--test",
            arg(&test),
        ];
        args.extend_from_slice(cols);
        args.extend_from_slice(&["--bootstrap", "20", "--out", arg(&out)]);
        let stdout = motionscale_ok(&args);
        let report: serde_json::Value = read_json(&out.join("laws.json"));
        assert_eq!(report["adopted"], family, "{task}: {stdout}");
        let (law, score) = (
            &report["test"]["scores"][0][0],
            &report["test"]["scores"][0][1],
        );
        assert_eq!(law, family);
        let r2 = score["r2_clipped"].as_f64().unwrap();
        assert!(r2 >= all_data, "{task}: R² {r2} < {all_data}\n{stdout}");
        assert!(stdout.contains("← adopted"), "{stdout}");
    }
}

#[test]
fn fit_law_names_an_unknown_family_and_a_missing_axis() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = tmp.path().join("runs.csv");
    synth::write_epoch_csv(&csv, &synth::chinchilla_standin(21)).unwrap();
    let mut base = epoch_table_fit(arg(&csv), "0");
    base.push("--out");
    let out = tmp.path().join("laws");
    let mut args = base.to_vec();
    args.extend_from_slice(&[arg(&out), "--law", "chinchila"]);
    fails_with(
        &motionscale(&args),
        "--law \"chinchila\": the laws are chinchilla, data-constrained, data-constrained-token-worth, data-constrained-effective-pool, unique-floor, vocab, vocab-effective, farseer (or all)",
    );
    let mut args = base.to_vec();
    args.extend_from_slice(&[arg(&out), "--law", "data-constrained"]);
    fails_with(
        &motionscale(&args),
        "data-constrained: needs a positive U for every run",
    );
    let mut args = base.to_vec();
    args.extend_from_slice(&[arg(&out), "--law", "all"]);
    let stdout = motionscale_ok(&args);
    assert!(
        stdout.contains("chinchilla") && stdout.contains("← adopted"),
        "{stdout}"
    );
    let report: serde_json::Value = read_json(&out.join("laws.json"));
    assert_eq!(report["adopted"], "chinchilla", "{stdout}");
    predict_reads_a_laws_json(&out.join("laws.json"));
}

/// `predict` on the laws.json of the Chinchilla stand-in: the adopted law's N_opt at a budget
/// 3× past the table near the truth's, and `--hours` refused for want of the IsoFLOP fit.
fn predict_reads_a_laws_json(laws: &std::path::Path) {
    let c = 1e22;
    let stdout = motionscale_ok(&["predict", "--fits", arg(laws), "--budget", "1e22", "--json"]);
    let p: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(p["law"], "chinchilla", "{stdout}");
    let n = p["n"]["value"].as_f64().unwrap();
    let truth = synth::CHINCHILLA.n_opt(c);
    assert!(
        (n / truth).log10().abs() < 0.1,
        "N_opt {n} vs truth {truth}"
    );
    let d = p["d"]["value"].as_f64().unwrap();
    assert!((6.0 * n * d / c - 1.0).abs() < 1e-9, "{stdout}");
    fails_with(
        &motionscale(&[
            "predict",
            "--fits",
            arg(laws),
            "--budget",
            "1e22",
            "--hours",
            "real=1",
        ]),
        "a laws.json of `fit --law`; this needs the IsoFLOP fit",
    );
}

/// `fit --law … --select ladder`: each data subset held out in turn; on runs drawn from the
/// unique-data floor law (three pools, small seeded noise) that law is adopted over the
/// data-constrained one, and a table without a `data` column is refused.
#[test]
fn fit_law_select_ladder_holds_each_data_subset_out() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = unique_floor_ladders(tmp.path());
    let out = tmp.path().join("laws");
    let mut args = epoch_table_fit(arg(&csv), "0");
    args.extend_from_slice(&[
        "--law",
        "data-constrained,unique-floor",
        "--select",
        "ladder",
        "--out",
        arg(&out),
    ]);
    let stdout = motionscale_ok(&args);
    assert!(
        stdout.contains("each of 3 data subsets held out in turn"),
        "{stdout}"
    );
    let report: serde_json::Value = read_json(&out.join("laws.json"));
    assert_eq!(report["adopted"], "unique-floor", "{stdout}");
    let plain = tmp.path().join("plain.csv");
    let without: String = std::fs::read_to_string(&csv)
        .unwrap()
        .lines()
        .map(|l| l.rsplit_once(',').unwrap().0.to_string() + "\n")
        .collect();
    std::fs::write(&plain, without).unwrap();
    args[2] = arg(&plain);
    fails_with(&motionscale(&args), "--select ladder needs a `data` column");
}

/// `fit --law … --block-bootstrap ladder` resamples whole data subsets: the fit records 3
/// blocks and its intervals are at least as wide as the run-by-run bootstrap's for the
/// floor's exponent, which only the comparison between subsets informs.
#[test]
fn fit_law_block_bootstrap_resamples_whole_subsets() {
    let tmp = tempfile::tempdir().unwrap();
    let csv = unique_floor_ladders(tmp.path());
    let gamma_width = |block: Option<&str>| {
        let out = tmp.path().join(format!("laws-{}", block.unwrap_or("rows")));
        let mut args = epoch_table_fit(arg(&csv), "40");
        args.extend_from_slice(&["--law", "unique-floor", "--out", arg(&out)]);
        if let Some(b) = block {
            args.extend_from_slice(&["--block-bootstrap", b]);
        }
        let stdout = motionscale_ok(&args);
        let report: serde_json::Value = read_json(&out.join("laws.json"));
        let fit = &report["fits"][0];
        let gamma = fit["natural"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["name"] == "gamma")
            .unwrap();
        let width = gamma["ci_high"].as_f64().unwrap() - gamma["ci_low"].as_f64().unwrap();
        (stdout, fit["bootstrap_clusters"].clone(), width)
    };
    let (rows_out, rows_blocks, rows_width) = gamma_width(None);
    let (out, blocks, width) = gamma_width(Some("ladder"));
    assert!(rows_blocks.is_null(), "{rows_out}");
    assert_eq!(blocks, 3, "{out}");
    assert!(out.contains("resampling 3 blocks"), "{out}");
    assert!(width >= rows_width, "blocks {width} vs rows {rows_width}");
}

/// `fit` on a table with Epoch AI's column names and `bootstrap` resamples.
fn epoch_table_fit<'a>(csv: &'a str, bootstrap: &'a str) -> Vec<&'a str> {
    vec![
        "fit",
        "--results",
        csv,
        "--n-col",
        "Model Size",
        "--d-col",
        "Training Tokens",
        "--loss-col",
        "loss",
        "--bootstrap",
        bootstrap,
    ]
}

/// Runs drawn from the unique-data floor law on three pools (small seeded noise), each pool a
/// data subset (`data` column); returns the table's path in `dir`.
fn unique_floor_ladders(dir: &std::path::Path) -> std::path::PathBuf {
    let csv = dir.join("runs.csv");
    let mut text = String::from("Model Size,Training Tokens,loss,unique_tokens,data\n");
    let mut rng = motionscale_core::rng::SplitMix64(5);
    for (name, u) in [("u1", 1e7f64), ("u2", 3e7), ("u3", 1e8)] {
        for i in 0..5 {
            for j in 0..6 {
                let n = 10f64.powf(6.5 + 0.5 * i as f64);
                let d = 10f64.powf(7.0 + 0.5 * j as f64);
                let law =
                    1.8 + 300.0 * n.powf(-0.33) + 2000.0 * d.powf(-0.35) + 40.0 * u.powf(-0.2);
                let loss = law * (1.0 + 0.002 * rng.range(-1.0, 1.0));
                text.push_str(&format!("{n},{d},{loss},{u},{name}\n"));
            }
        }
    }
    std::fs::write(&csv, text).unwrap();
    csv
}
