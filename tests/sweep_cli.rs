//! IsoFLOP sweeps through the binary on a tiny corpus: the plan (D from C, flags, one
//! tokenizer per vocabulary), then a sweep killed with SIGKILL at random moments five times
//! and run again to completion. The tables must be whole after every kill, and the final
//! table must hold exactly one row per runnable point, equal to an uninterrupted sweep's in
//! every deterministic column.

mod common;

use common::*;
use experiments::plan::{PointFlag, VocabSource};
use experiments::{IsoFlopPlan, RunRow};
use motionscale_core::rng::SplitMix64;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// `sweep plan` on `corpus` with budgets `budgets`: one model, two trained vocabularies.
fn make_plan(corpus: &Path, budgets: &str, out: &Path) -> IsoFlopPlan {
    tiny_plan(corpus, budgets, "256,1024", &[], out)
}

/// `sweep plan` of cpu-50K on `corpus` at `budgets` and trained vocabularies `vocabs`, with
/// `extra` flags.
fn tiny_plan(
    corpus: &Path,
    budgets: &str,
    vocabs: &str,
    extra: &[&str],
    out: &Path,
) -> IsoFlopPlan {
    let settings = ["--batch", "8", "--checkpoint-every", "10"];
    sweep_plan(
        corpus,
        budgets,
        "cpu-50K",
        vocabs,
        &[&settings[..], extra].concat(),
        out,
    );
    IsoFlopPlan::read(out).expect("the plan reads back")
}

/// Python: both tables of a sweep folder as JSON rows, after checking they agree.
const TABLES: &str = r#"
import csv, json, math, sys, pyarrow.parquet as pq
runs = sys.argv[1]
rows = pq.read_table(f"{runs}/results.parquet").to_pylist()
with open(f"{runs}/results.csv") as f:
    text = list(csv.DictReader(f))
assert len(text) == len(rows), (len(text), len(rows))
same = lambda a, b: a == b or (math.isnan(a) and math.isnan(b))
for t, r in zip(text, rows):
    for k, v in r.items():
        assert (t[k] == v) if isinstance(v, str) else same(float(t[k]), float(v)), (k, t[k], v)
# NaN (not recorded) as JSON's null, as serde_json writes it.
nulled = [{k: None if isinstance(v, float) and math.isnan(v) else v for k, v in r.items()} for r in rows]
print(json.dumps(nulled))
"#;

/// The rows of both tables (which must agree), or none before the first rebuild.
fn table_rows(runs: &Path) -> Vec<RunRow> {
    if !runs.join("results.parquet").exists() {
        return Vec::new();
    }
    serde_json::from_str(&python(TABLES, &[arg(runs)])).expect("rows parse")
}

/// Every column a re-run reproduces exactly (all but wall time, host and revision).
fn deterministic(row: &RunRow) -> RunRow {
    RunRow {
        wall_s: 0.0,
        hostname: String::new(),
        git_revision: String::new(),
        ..row.clone()
    }
}

fn run_sweep(plan: &Path, runs: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_motionscale"));
    c.args([
        "sweep",
        "run",
        "--plan",
        arg(plan),
        "--out",
        arg(runs),
        "--jobs",
        "2",
    ]);
    c
}

/// Waits until `runs` holds the result of one of `ids`, or `limit` has passed: how long it took.
fn until_first_result(runs: &Path, ids: &[&str], limit: Duration) -> Duration {
    let started = Instant::now();
    let finished = || {
        ids.iter()
            .any(|id| matches!(experiments::results::read_row(runs, id), Ok(Some(_))))
    };
    while !finished() && started.elapsed() < limit {
        std::thread::sleep(Duration::from_millis(10));
    }
    started.elapsed()
}

/// `sweep run` of `plan` into `runs`, which must succeed; its output.
fn sweep_run_ok(plan: &Path, runs: &Path) -> String {
    motionscale_ok(&["sweep", "run", "--plan", arg(plan), "--out", arg(runs)])
}

#[test]
fn a_sweep_killed_five_times_ends_with_one_row_per_point() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    tiny_lm_corpus(&corpus);
    let plan_path = tmp.path().join("plan.toml");
    let plan = make_plan(&corpus, "1e6,1.5e10,3e10", &plan_path);

    // The plan: 3 budgets × 1 model × 2 vocabularies, D from lm::accounting.
    assert_eq!(plan.points.len(), 6);
    assert_eq!(plan.vocabularies.len(), 2);
    for (v, codes) in plan.vocabularies.iter().zip([240, 1000]) {
        assert_eq!(v.codebook_size, codes, "FSQ level sets 2^8 and 2^10");
        assert!(matches!(v.source, VocabSource::Train { .. }));
        assert!(v.train_tokens > 0 && v.train_clips > 0);
    }
    for p in &plan.points {
        let n6 = 6.0 * (p.n_nv + p.n_v) as f64;
        assert!(
            (n6 * p.tokens as f64 - p.budget).abs() <= n6,
            "C = 6(N_nv+N_v)·D: {p:?}"
        );
        let vocab = plan.vocabulary(p.codebook).unwrap();
        assert_eq!(
            p.n_v,
            2 * (vocab.codebook_size as u64 + 3) * 64,
            "untied 2·V·d"
        );
        assert_eq!(
            p.flags.contains(&PointFlag::ExceedsData),
            p.tokens > vocab.train_tokens
        );
        assert_eq!(
            p.flags.contains(&PointFlag::BelowOneStep),
            p.budget == 1e6,
            "{p:?}"
        );
    }
    let runnable: Vec<&str> = plan
        .points
        .iter()
        .filter(|p| p.runnable())
        .map(|p| p.run_id.as_str())
        .collect();
    assert_eq!(runnable.len(), 4);
    assert!(plan
        .points
        .iter()
        .any(|p| p.flags.contains(&PointFlag::ExceedsData)));

    // The uninterrupted sweep.
    let reference = tmp.path().join("reference");
    let started = Instant::now();
    let out = run_sweep(&plan_path, &reference).output().unwrap();
    let full = started.elapsed();
    assert_eq!(code(&out), 0, "{}", text(&out));
    eprintln!("uninterrupted sweep: {:.2} s", full.as_secs_f64());
    let expected = table_rows(&reference);
    assert_eq!(
        expected
            .iter()
            .map(|r| r.run_id.as_str())
            .collect::<Vec<_>>(),
        runnable
    );

    // Five SIGKILLs at random moments, then a run to completion.
    let killed = tmp.path().join("killed");
    let mut rng = SplitMix64::stream(0x5EED, 5);
    for kill in 0..5 {
        let mut child = run_sweep(&plan_path, &killed)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        // The first kill lands mid-sweep under any load (the reference's time does not tell
        // how fast this run goes): right after the first point finishes.
        let delay = match kill {
            0 => until_first_result(&killed, &runnable, full * 4),
            _ => {
                let delay = full.mul_f64(rng.range(0.1, 0.9));
                std::thread::sleep(delay);
                delay
            }
        };
        let _ = child.kill(); // SIGKILL; the child may have finished already
        child.wait().unwrap();
        // Worker processes die with their parent (PR_SET_PDEATHSIG): wait for their locks.
        std::thread::sleep(Duration::from_millis(300));
        let rows = table_rows(&killed);
        let ids: std::collections::HashSet<&str> = rows.iter().map(|r| r.run_id.as_str()).collect();
        assert_eq!(ids.len(), rows.len(), "a duplicate row after kill {kill}");
        for row in &rows {
            let done = experiments::results::read_row(&killed, &row.run_id).unwrap();
            assert_eq!(
                done.as_ref(),
                Some(row),
                "table row without its result.json"
            );
        }
        let status = motionscale_ok(&["sweep", "status", "--out", arg(&killed)]);
        eprintln!(
            "kill {} after {:.2} s: {} of {} rows\n{status}",
            kill + 1,
            delay.as_secs_f64(),
            rows.len(),
            runnable.len()
        );
        if kill == 0 {
            assert!(
                rows.len() < runnable.len(),
                "the first kill came after the whole sweep"
            );
        }
        assert!(
            status.contains(" 0 running"),
            "no process is left: {status}"
        );
    }
    motionscale_ok(&[
        "sweep",
        "run",
        "--plan",
        arg(&plan_path),
        "--out",
        arg(&killed),
        "--jobs",
        "2",
    ]);
    let rows = table_rows(&killed);
    assert_eq!(rows.len(), expected.len(), "one row per point");
    for (got, want) in rows.iter().zip(&expected) {
        assert_eq!(deterministic(got), deterministic(want));
    }
    let status = motionscale_ok(&["sweep", "status", "--out", arg(&killed)]);
    assert!(
        status.contains("6 points: 4 done, 0 running, 0 failed, 0 pending, 2 not runnable"),
        "{status}"
    );
    let collected = motionscale_ok(&["sweep", "collect", "--out", arg(&killed)]);
    assert!(collected.starts_with("4 rows"), "{collected}");
    assert_eq!(table_rows(&killed), rows, "collect rebuilds the same table");

    // A sweep folder belongs to one plan.
    let other = tmp.path().join("other.toml");
    make_plan(&corpus, "2e10", &other);
    let out = motionscale(&["sweep", "run", "--plan", arg(&other), "--out", arg(&killed)]);
    assert_eq!(code(&out), 1);
    assert!(text(&out).contains("different plan"), "{}", text(&out));
}

/// A results CSV whose IsoFLOP minima follow N_opt = 10^-0.52 · C^0.57 at 1e9, 1e10 and 1e11.
fn pilot_results(path: &Path) {
    let mut csv = String::from("budget,n_nv,norm_test_loss\n");
    for c in [1e9f64, 1e10, 1e11] {
        let centre = -0.52 + 0.57 * c.log10();
        for k in 0..7 {
            let ln = centre - 0.6 + 0.2 * k as f64;
            let loss = 2.0 + 0.3 * (ln - centre).powi(2);
            csv.push_str(&format!("{c},{},{loss}\n", 10f64.powf(ln)));
        }
    }
    std::fs::write(path, csv).unwrap();
}

#[test]
fn a_plan_centred_on_an_earlier_fit_brackets_n_opt_warns_past_the_ladder_and_limits_epochs() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    tiny_lm_corpus(&corpus);
    let results = tmp.path().join("pilot.csv");
    pilot_results(&results);
    let fits_dir = tmp.path().join("fits");
    motionscale_ok(&[
        "fit",
        "--results",
        arg(&results),
        "--out",
        arg(&fits_dir),
        "--starts-grid",
        "coarse",
        "--bootstrap",
        "0",
    ]);
    let plan_path = tmp.path().join("plan.toml");
    let fits_json = fits_dir.join("fits.json");
    let plan_args = |extra: &[&str]| {
        let mut a = vec![
            "sweep",
            "plan",
            "--corpus",
            arg(&corpus),
            "--budgets",
            "1e11,1e15",
            "--models",
            "cpu",
            "--vocabs",
            "256",
            "--tokenizer-flags=--width 32 --batch 8 --steps 30",
            "--batch",
            "8",
            "--fits",
            arg(&fits_json),
            "--sizes-per-budget",
            "4",
            "--out",
            arg(&plan_path),
        ];
        a.extend_from_slice(extra);
        a.into_iter().map(String::from).collect::<Vec<String>>()
    };
    let owned = plan_args(&["--max-epochs", "1000"]);
    let out = motionscale_ok(&owned.iter().map(String::as_str).collect::<Vec<_>>());
    let plan = IsoFlopPlan::read(&plan_path).unwrap();

    // 1e11 sits inside the CPU ladder: four sizes, two on each side of N_opt, no warning.
    let n_opt = 10f64.powf(-0.52 + 0.57 * 11.0);
    assert_eq!(plan.centres.len(), 2);
    assert!(
        (plan.centres[0].n_opt / n_opt - 1.0).abs() < 1e-6,
        "{:?}",
        plan.centres[0]
    );
    let at = |c: f64| -> Vec<f64> {
        plan.points
            .iter()
            .filter(|p| p.budget == c)
            .map(|p| p.n_nv as f64)
            .collect()
    };
    let sizes = at(1e11);
    assert_eq!(sizes.len(), 4, "{sizes:?}");
    assert_eq!(sizes.iter().filter(|&&n| n < n_opt).count(), 2, "{sizes:?}");
    assert!(
        plan.warnings.iter().all(|w| !w.contains("budget 1.000e11")),
        "{:?}",
        plan.warnings
    );
    // 1e15 predicts ~1e8 parameters, past the largest CPU model: the four largest, and a warning.
    assert_eq!(at(1e15).len(), 4);
    let w = plan
        .warnings
        .iter()
        .find(|w| w.contains("budget 1.000e15"))
        .expect("warned");
    assert!(
        w.contains("4 below and 0 above") && w.contains("add larger models"),
        "{w}"
    );
    assert!(out.contains("warning: budget 1.000e15"), "{out}");
    // Above --max-epochs: flagged.
    for p in &plan.points {
        assert_eq!(
            p.flags.contains(&PointFlag::AboveMaxEpochs),
            p.epochs > 1000.0,
            "{p:?}"
        );
    }
    assert!(
        plan.points.iter().any(|p| p.epochs > 1000.0),
        "the tiny corpus repeats a lot"
    );

    // Dropped instead: every point left is within the limit, every dropped one is listed.
    let owned = plan_args(&["--max-epochs", "1000", "--drop-above-max-epochs"]);
    motionscale_ok(&owned.iter().map(String::as_str).collect::<Vec<_>>());
    let dropped = IsoFlopPlan::read(&plan_path).unwrap();
    assert!(dropped.points.iter().all(|p| p.epochs <= 1000.0));
    let listed = dropped
        .warnings
        .iter()
        .filter(|w| w.starts_with("dropped "))
        .count();
    assert_eq!(dropped.points.len() + listed, plan.points.len());
    assert!(listed > 0);
}

/// The demo's captured clips (each file under `copies` names) and 40 synthetic ones,
/// mirrored, with fallback caption embeddings: both origins in train and test (and, with 4
/// copies, in validation).
fn mixed_corpus(tmp: &Path, copies: usize) -> std::path::PathBuf {
    let (inputs, corpus) = (tmp.join("inputs"), tmp.join("corpus"));
    demo_inputs(&inputs);
    for entry in std::fs::read_dir(&inputs).unwrap() {
        let path = entry.unwrap().path();
        let (stem, ext) = (path.file_stem().unwrap(), path.extension().unwrap());
        for k in 2..=copies {
            let name = format!("{}_{k}.{}", stem.to_string_lossy(), ext.to_string_lossy());
            std::fs::copy(&path, inputs.join(name)).unwrap();
        }
    }
    let bvh = format!("bvh:{}", inputs.display());
    motionscale_ok(&[
        "ingest",
        "--source",
        &bvh,
        "--source",
        "synth:40:2",
        "--mirror",
        "--out",
        arg(&corpus),
    ]);
    motionscale_ok(&[
        "embed-text",
        "--corpus",
        arg(&corpus),
        "--fallback",
        "--fallback-dim",
        "32",
    ]);
    corpus
}

/// `sweep plan` of cpu-50K at 3e10 on one trained vocabulary at `fractions` of `source`.
fn data_plan(corpus: &Path, fractions: &str, source: &str, out: &Path) -> IsoFlopPlan {
    let data = ["--data-fractions", fractions, "--data-source", source];
    tiny_plan(corpus, "3e10", "256", &data, out)
}

#[test]
fn a_data_ladder_trains_nested_subsets_and_reports_test_losses_per_origin() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = mixed_corpus(tmp.path(), 1);
    let plan_path = tmp.path().join("plan.toml");
    let plan = data_plan(&corpus, "1/2,1", "all", &plan_path);
    let names: Vec<&str> = plan.data.iter().map(|d| d.name.as_str()).collect();
    assert_eq!(names, ["all-1_2", "all-1"]);
    let ids: Vec<&str> = plan.points.iter().map(|p| p.run_id.as_str()).collect();
    assert_eq!(
        ids,
        ["c3e10-cpu-50K-v256-dall-1_2", "c3e10-cpu-50K-v256-dall-1"]
    );
    let (half, whole) = (&plan.points[0], &plan.points[1]);
    let (u_half, u_whole) = (half.unique_tokens(&plan), whole.unique_tokens(&plan));
    assert_eq!(
        u_whole, plan.vocabularies[0].train_tokens,
        "1 is the whole split"
    );
    assert!(
        u_half < u_whole && 2 * u_half > u_whole * 4 / 5,
        "{u_half} of {u_whole}"
    );
    assert!((half.epochs - half.tokens as f64 / u_half as f64).abs() < 1e-12);
    let (h_half, h_whole) = (plan.data[0].hours, plan.data[1].hours);
    assert!(
        h_half >= h_whole / 2.0 && h_half < h_whole,
        "{h_half} h of {h_whole} h"
    );

    let runs = tmp.path().join("runs");
    sweep_run_ok(&plan_path, &runs);
    let list = |name: &str, split: &str| -> Vec<String> {
        let path = runs.join("data").join(name).join(format!("{split}.txt"));
        std::fs::read_to_string(path)
            .unwrap()
            .lines()
            .map(String::from)
            .collect()
    };
    let (train_half, train_whole) = (list("all-1_2", "train"), list("all-1", "train"));
    assert!(
        train_half.iter().all(|id| train_whole.contains(id)),
        "nested"
    );
    for id in &train_half {
        let mirror = id.strip_prefix('M').map_or(format!("M{id}"), String::from);
        assert!(train_half.contains(&mirror), "{id} without its mirror");
    }
    assert_eq!(
        list("all-1_2", "test"),
        list("all-1", "test"),
        "test stays whole"
    );

    let rows = table_rows(&runs);
    assert_eq!(rows.len(), 2);
    for (row, point) in rows.iter().zip(&plan.points) {
        assert_eq!(row.data, point.data.clone().unwrap());
        assert_eq!(
            (row.data_source.as_str(), row.unique_tokens),
            ("all", point.unique_tokens(&plan))
        );
        assert!(
            row.synth_share > 0.5 && row.synth_share < 1.0,
            "{}",
            row.synth_share
        );
        let eval: serde_json::Value =
            read_json(&runs.join(&row.run_id).join("train").join("eval.json"));
        let test = &eval["test"];
        let part = |o: &str, k: &str| test["by_origin"][o][k].as_f64().unwrap();
        assert_eq!(
            (row.real_test_loss, row.synth_test_loss),
            (
                part("real", "cross_entropy"),
                part("synth", "cross_entropy")
            )
        );
        assert_eq!(row.real_norm_test_loss, part("real", "normalized_loss"));
        // Per origin, weighted by their code targets, the mix.
        let (tr, ts) = (part("real", "code_targets"), part("synth", "code_targets"));
        assert_eq!(tr + ts, test["code_targets"].as_f64().unwrap());
        for k in ["cross_entropy", "normalized_loss"] {
            let mix = (part("real", k) * tr + part("synth", k) * ts) / (tr + ts);
            assert!(
                (mix - test[k].as_f64().unwrap()).abs() < 1e-9,
                "{k}: {mix} vs {}",
                test[k]
            );
        }
        assert!(row.best_real_norm_test_loss.is_finite() && row.best_synth_test_loss.is_finite());
    }
    // The whole-split point equals a plain (no --data-fractions) point's training, and the
    // plain point records the whole split's hours.
    let plain = tmp.path().join("plain.toml");
    make_plan(&corpus, "3e10", &plain);
    let r = tmp.path().join("plain-runs");
    let plain_plan = IsoFlopPlan::read(&plain).unwrap();
    assert_eq!(plain_plan.points[0].tokens, plan.points[1].tokens);
    assert_eq!(plain_plan.train_split.as_ref(), Some(&plan.data[1]));
    sweep_run_ok(&plain, &r);
    let plain_row = table_rows(&r).remove(0);
    assert_eq!(
        rows[1].test_loss, plain_row.test_loss,
        "the lists of fraction 1 select the same clips as the corpus's splits"
    );
    assert_eq!(
        (plain_row.hours, plain_row.synth_share),
        (rows[1].hours, rows[1].synth_share)
    );

    let real_plan = data_plan(&corpus, "1", "real", &tmp.path().join("real.toml"));
    assert_eq!(real_plan.data[0].name, "real-1");
    assert_eq!(real_plan.data[0].synth_hours, 0.0);
    assert!(real_plan.points[0].unique_tokens(&real_plan) < u_whole);
    let out = motionscale(&[
        "sweep",
        "plan",
        "--corpus",
        arg(&corpus),
        "--budgets",
        "3e10",
        "--models",
        "cpu-50K",
        "--vocabs",
        "256",
        "--data-fractions",
        "3/2",
        "--out",
        arg(&tmp.path().join("bad.toml")),
    ]);
    assert_eq!(code(&out), 1, "{}", text(&out));
    assert!(text(&out).contains("(0, 1]"), "{}", text(&out));
}

#[test]
fn a_captured_only_run_selects_on_captured_validation_clips_and_collect_reselects_old_rows() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = mixed_corpus(tmp.path(), 4);
    let plan_path = tmp.path().join("real.toml");
    let plan = data_plan(&corpus, "1", "real", &plan_path);
    let runs = tmp.path().join("runs");
    sweep_run_ok(&plan_path, &runs);
    let dir = runs.join(&plan.points[0].run_id);
    let evals: Vec<serde_json::Value> =
        std::fs::read_to_string(dir.join("train").join("evals.jsonl"))
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
    assert!(evals.len() > 2, "{} evaluations", evals.len());
    let captured_val = |e: &serde_json::Value| {
        let v = &e["val"]["by_origin"];
        assert!(v["synth"].is_object(), "validation holds both origins");
        v["real"]["cross_entropy"].as_f64().unwrap()
    };
    // The first of the lowest, as the trainer selects.
    let on_captured = evals
        .iter()
        .min_by(|a, b| captured_val(a).total_cmp(&captured_val(b)))
        .unwrap();
    let captured_test =
        |e: &serde_json::Value| e["test"]["by_origin"]["real"]["cross_entropy"].as_f64();
    let row = table_rows(&runs).remove(0);
    assert_eq!(Some(row.best_step), on_captured["step"].as_u64());
    assert_eq!(Some(row.best_real_test_loss), captured_test(on_captured));
    let eval: serde_json::Value = read_json(&dir.join("train").join("eval.json"));
    assert_eq!(eval["best"]["selected_on"], "real");
    assert_eq!(
        eval["best"]["val_cross_entropy"].as_f64(),
        Some(captured_val(on_captured))
    );

    // A row finished under another selection (here: the worst evaluation) is corrected.
    let result = dir.join("result.json");
    let today = std::fs::read_to_string(&result).unwrap();
    let first = evals
        .iter()
        .max_by(|a, b| captured_val(a).total_cmp(&captured_val(b)))
        .unwrap();
    let stale = RunRow {
        best_step: first["step"].as_u64().unwrap(),
        best_test_loss: first["test"]["cross_entropy"].as_f64().unwrap(),
        best_real_test_loss: captured_test(first).unwrap(),
        ..row.clone()
    };
    assert_ne!(stale.best_step, row.best_step);
    std::fs::write(&result, serde_json::to_string_pretty(&stale).unwrap()).unwrap();
    let collect = ["sweep", "collect", "--out", arg(&runs), "--reselect"];
    let out = motionscale_ok(&collect);
    assert!(out.contains("1 runs re-selected"), "{out}");
    assert_eq!(std::fs::read_to_string(&result).unwrap(), today);
    assert_eq!(deterministic(&table_rows(&runs)[0]), deterministic(&row));
    let again = motionscale_ok(&collect);
    assert!(again.contains("0 runs re-selected"), "{again}");
}

#[test]
fn a_recipe_sets_each_points_rate_by_its_size_and_every_row_names_it() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    tiny_lm_corpus(&corpus);
    let recipe = tmp.path().join("recipe.toml");
    std::fs::write(
        &recipe,
        "name = \"test-recipe\"\nlr_at_reference = 2e-3\nreference_params = 1e5\n\
         lr_exponent = -0.5\nwarmup = 0.1\nweight_decay = 0.3\ndropout = 0.1\n",
    )
    .unwrap();
    let plan_path = tmp.path().join("plan.toml");
    let settings = [
        "--batch",
        "8",
        "--checkpoint-every",
        "10",
        "--recipe",
        arg(&recipe),
    ];
    sweep_plan(
        &corpus,
        "2e10",
        "cpu-50K,cpu-100K",
        "256",
        &settings,
        &plan_path,
    );
    let plan = IsoFlopPlan::read(&plan_path).unwrap();
    assert_eq!(plan.train.recipe.as_ref().unwrap().name, "test-recipe");
    let runs = tmp.path().join("runs");
    sweep_run_ok(&plan_path, &runs);
    let rows = table_rows(&runs);
    assert_eq!(rows.len(), 2);
    for row in &rows {
        let rule = 2e-3 * (row.n_nv as f64 / 1e5).powf(-0.5);
        assert!(
            (row.lr - rule).abs() <= 1e-12 * rule,
            "{} lr {} vs {rule}",
            row.run_id,
            row.lr
        );
        assert_eq!((row.weight_decay, row.dropout), (0.3, 0.1));
        assert_eq!(row.recipe, "test-recipe");
        let config: serde_json::Value =
            read_json(&runs.join(&row.run_id).join("train/config.json"));
        assert_eq!(config["train"]["lr"].as_f64(), Some(row.lr), "{config}");
    }
    assert!(rows[0].lr != rows[1].lr, "two sizes, one rate");
    // A row from before the settings' columns gets them from its plan when collected.
    let result = runs.join(&rows[0].run_id).join("result.json");
    let mut old: serde_json::Value = read_json(&result);
    for key in ["lr", "weight_decay", "dropout", "recipe"] {
        old.as_object_mut().unwrap().remove(key).unwrap();
    }
    std::fs::write(&result, old.to_string()).unwrap();
    motionscale_ok(&["sweep", "collect", "--out", arg(&runs)]);
    assert_eq!(table_rows(&runs), rows);
    // A bad recipe is refused, naming its file.
    std::fs::write(&recipe, "name = \"x\"\n").unwrap();
    let out = motionscale(&[
        "sweep",
        "plan",
        "--corpus",
        arg(&corpus),
        "--budgets",
        "2e10",
        "--models",
        "cpu-50K",
        "--vocabs",
        "256",
        "--recipe",
        arg(&recipe),
        "--out",
        arg(&tmp.path().join("bad.toml")),
    ]);
    fails_with(&out, "recipe.toml");
}
