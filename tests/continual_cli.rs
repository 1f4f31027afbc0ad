//! Continual expert training through the binary on a synthetic corpus: scenario datasets,
//! a tiny backbone and evaluator, `continual` with seq-lora and mtl (matrix shapes, summary
//! metrics, an identical summary when re-run), the replay buffer's lists, the O-LoRA and
//! LwF-LoRA steps' settings, ES-MoE's experts and gate across steps and its single-LoRA
//! ablation, `compare` (seeds in one row, one evaluator per table), the refusal of a
//! backbone that trained on held-out clips, and scenario lists that keep the corpus split.

mod common;

use common::*;
use serde_json::Value;
use std::collections::HashMap;
use std::path::Path;

/// The arguments of a small `continual` run of `method` over `orders` orders on the test setup.
fn continual_args(setup: &Path, method: &str, orders: &str, out: &Path) -> Vec<String> {
    let p = |name: &str| arg(&setup.join(name)).to_string();
    let mut args: Vec<String> = ["continual", "--scenarios"].map(String::from).to_vec();
    args.push(p("scenarios"));
    args.extend(["--method".into(), method.into(), "--base".into(), p("run")]);
    args.extend([
        "--tokens".into(),
        p("tokens"),
        "--evaluator".into(),
        p("evaluator"),
    ]);
    for (flag, value) in [
        ("--orders", orders),
        ("--tokens-budget", "600"),
        ("--batch", "8"),
        ("--repeats", "2"),
        ("--pool", "8"),
        ("--mm-texts", "2"),
        ("--eval-split", "train"),
    ] {
        args.extend([flag.to_string(), value.to_string()]);
    }
    args.extend(["--out".into(), arg(out).to_string()]);
    args
}

fn continual(setup: &Path, method: &str, out: &Path) -> Value {
    let args = continual_args(setup, method, "2", out);
    motionscale_ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    read_json(&out.join("summary.json"))
}

#[test]
fn continual_methods_fill_the_matrices_and_resume_to_the_same_summary() {
    let tmp = tempfile::tempdir().unwrap();
    let setup = tmp.path();
    let corpus = setup.join("corpus");
    synth_corpus(&corpus, 300);
    tiny_lm_run(&corpus, setup);
    train_evaluator(&corpus, &setup.join("evaluator"), &[]);
    motionscale_ok(&[
        "scenarios",
        "--corpus",
        arg(&corpus),
        "--split",
        "unseen",
        "--out",
        arg(&setup.join("scenarios")),
    ]);

    let seq = setup.join("seq");
    let report = continual(setup, "seq-lora", &seq);
    let orders = report["orders"].as_array().unwrap();
    assert_eq!(orders.len(), 2);
    for order in orders {
        let r = order["r"].as_array().unwrap();
        assert_eq!(r.len(), 6, "one row per step");
        assert!(r.iter().all(|row| row.as_array().unwrap().len() == 6));
        assert!(order["summary"]["fr"].is_number());
        let last: Vec<f64> = r[5]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let ar = last.iter().sum::<f64>() / 6.0;
        assert!((order["summary"]["ar"].as_f64().unwrap() - ar).abs() < 1e-12);
    }
    assert_ne!(
        orders[0]["datasets"], orders[1]["datasets"],
        "order 1 is shuffled"
    );
    for o in 0..2 {
        for stem in ["fid", "r_precision"] {
            let svg = std::fs::read_to_string(seq.join(format!("order-{o}/{stem}.svg"))).unwrap();
            assert!(svg.contains("after "), "{stem}: rows labelled by step");
            assert!(seq.join(format!("order-{o}/{stem}.png")).is_file());
        }
    }
    let csv = std::fs::read_to_string(seq.join("summary.csv")).unwrap();
    assert_eq!(csv.lines().count(), 4, "header, two orders, mean: {csv}");
    assert!(
        !seq.join("order-0/step-1/gen-D01_daily").exists(),
        "generated motions are removed once scored"
    );
    // Re-running finds every step done and writes the same summary.
    let first = std::fs::read(seq.join("summary.json")).unwrap();
    continual(setup, "seq-lora", &seq);
    assert_eq!(std::fs::read(seq.join("summary.json")).unwrap(), first);

    // Replay: step 2 trains on its dataset plus 5% of the first one's train clips.
    let replay = setup.join("replay");
    continual(setup, "replay", &replay);
    let order: Vec<String> = read_json(&replay.join("order-0/order.json"));
    let lines = |p: &Path| std::fs::read_to_string(p).unwrap().lines().count();
    let scenarios = setup.join("scenarios");
    let (first_train, second_train) = (
        lines(&scenarios.join(&order[0]).join("train.txt")),
        lines(&scenarios.join(&order[1]).join("train.txt")),
    );
    assert_eq!(
        lines(&replay.join("order-0/step-2/lists/train.txt")),
        second_train + (first_train as f64 * 0.05).ceil() as usize
    );

    // O-LoRA: step 2 trains a new expert on the model with step 1's merged in, kept
    // orthogonal to step 1's adapter.
    let olora = setup.join("o-lora");
    let report = continual(setup, "o-lora", &olora);
    assert!(report["mean"]["fr"].is_number());
    let step2: Value = read_json(&olora.join("order-0/step-2/train/config.json"));
    let shape = &step2["train"]["model"]["lora"];
    assert_eq!(shape["expert"], "o-lora-2");
    assert_eq!(shape["base"], arg(&olora.join("order-0/step-1/train")));
    assert_eq!(
        shape["orthogonal_to"][0],
        arg(&olora.join("order-0/step-1/train/adapter.safetensors"))
    );
    assert_eq!(shape["orthogonality"], 0.5);

    // LwF-LoRA: from step 2 on, distilled towards the previous step's model.
    let lwf = setup.join("lwf-lora");
    continual(setup, "lwf-lora", &lwf);
    let lwf_shape = |k: usize| -> Value {
        read_json::<Value>(&lwf.join(format!("order-0/step-{k}/train/config.json")))["train"]
            ["model"]["lora"]
            .clone()
    };
    assert!(lwf_shape(1)["distill_from"].is_null());
    assert_eq!(
        lwf_shape(2)["distill_from"],
        arg(&lwf.join("order-0/step-1/train"))
    );
    assert_eq!(lwf_shape(2)["distillation"], 1.0);

    // MTL: one step on every dataset, no forgetting rate.
    let mtl = setup.join("mtl");
    let report = continual(setup, "mtl", &mtl);
    let r = report["orders"][0]["r"].as_array().unwrap();
    assert_eq!(r.len(), 1);
    assert!(report["mean"]["fr"].is_null());

    let table = motionscale_ok(&["continual", "compare", arg(&seq), arg(&mtl)]);
    assert_eq!(table.lines().count(), 4, "{table}");
    assert!(
        table.contains("| seq-lora | 2 | 1 |") && table.contains("| mtl | 2 | 1 |"),
        "{table}"
    );
    let evaluator_id = report["evaluator_id"].as_str().unwrap();
    assert_eq!(
        evaluator_id.len(),
        12,
        "the evaluator's content id: {report}"
    );
    assert!(table.contains(&format!("| {evaluator_id} |")), "{table}");
    compare_groups_seeds_and_refuses_mixed_evaluators(setup, &mtl);
    // ES-MoE: one expert per dataset; step 2 loads step 1's experts and gate and adds its own.
    let moe = setup.join("es-moe");
    // One order each (per-caption generation runs one sequence at a time).
    let mut args = continual_args(setup, "es-moe", "1", &moe);
    motionscale_ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let report: Value = read_json(&moe.join("summary.json"));
    assert_eq!(report["orders"][0]["r"].as_array().unwrap().len(), 6);
    assert!(report["mean"]["fr"].is_number());
    let order: Vec<String> = read_json(&moe.join("order-0/order.json"));
    let step2 = moe.join("order-0/step-2/train");
    let shape: Value =
        read_json::<Value>(&step2.join("config.json"))["train"]["model"]["es_moe"].clone();
    assert_eq!(shape["previous"], arg(&moe.join("order-0/step-1/train")));
    assert_eq!(shape["expert"], order[1].as_str());
    let manifest: Value = read_json(&step2.join("moe.json"));
    assert_eq!(manifest["experts"], serde_json::json!([order[0], order[1]]));
    let weights: Vec<f64> = read_json::<Value>(&step2.join("eval.json"))["expert_weights"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(weights.len(), 2);
    assert!(
        (weights.iter().sum::<f64>() - 1.0).abs() < 1e-5,
        "{weights:?}"
    );
    assert_eq!(report["orders"][0]["gate"][1], serde_json::json!(weights));
    assert_eq!(report["orders"][0]["gate"].as_array().unwrap().len(), 6);
    assert!(
        !step2.join("model.safetensors").exists(),
        "no single model file"
    );
    // An ES-MoE run generates from a caption like any other run.
    let json = setup.join("moe-gen.json");
    motionscale_ok(&[
        "generate",
        "--model",
        arg(&step2),
        "--text",
        "a person walks forward",
        "--out",
        arg(&json),
    ]);
    assert!(!read_json::<Value>(&json)["tokens"]
        .as_array()
        .unwrap()
        .is_empty());

    // The single-LoRA ablation fine-tunes one shared expert through the steps.
    let single = setup.join("es-moe-single");
    args = continual_args(setup, "es-moe", "1", &single);
    args.extend(["--ablation", "single-lora"].map(String::from));
    motionscale_ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let manifest: Value = read_json(&single.join("order-0/step-3/train/moe.json"));
    assert_eq!(manifest["experts"], serde_json::json!(["shared"]));
    let table = motionscale_ok(&["continual", "compare", arg(&moe), arg(&single)]);
    assert!(
        table.contains("| es-moe | 1 |") && table.contains("| es-moe w/o MoE (single LoRA) | 1 |"),
        "{table}"
    );
    // The new expert's weight: the gate's last entry after steps 2..6, averaged.
    let gate = read_json::<Value>(&moe.join("summary.json"))["orders"][0]["gate"].clone();
    let newest: Vec<f64> = gate.as_array().unwrap()[1..]
        .iter()
        .map(|w| w.as_array().unwrap().last().unwrap().as_f64().unwrap())
        .collect();
    let mean = newest.iter().sum::<f64>() / newest.len() as f64;
    let moe_row = table
        .lines()
        .find(|l| l.contains("| es-moe | 1 |"))
        .unwrap();
    assert!(moe_row.contains(&format!("| {mean:.3} |")), "{table}");

    refuses_a_backbone_that_trained_on_held_out_clips(setup);
    a_law_sizes_the_backbone(setup);

    let mut args = continual_args(setup, "seq-lora", "1", &setup.join("no"));
    args.extend(["--ablation", "no-cged"].map(String::from));
    let out = motionscale(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(code(&out), 1);
    assert!(
        text(&out).contains("--ablation applies to --method es-moe"),
        "{}",
        text(&out)
    );
    // --expert-epochs: `backbone` needs a law-sized one; a number must be positive.
    for (epochs, why) in [
        ("backbone", "needs a law-sized backbone"),
        ("0", "need a positive number"),
        ("many", "a number or `backbone`"),
    ] {
        let mut args = continual_args(setup, "seq-lora", "1", &setup.join("no-epochs"));
        let at = args.iter().position(|a| a == "--tokens-budget").unwrap();
        args.drain(at..at + 2);
        args.extend(["--expert-epochs", epochs].map(String::from));
        let out = motionscale(&args.iter().map(String::as_str).collect::<Vec<_>>());
        assert_eq!(code(&out), 1, "{epochs}: {}", text(&out));
        assert!(text(&out).contains(why), "{epochs}: {}", text(&out));
    }
}

/// `continual --fits laws.json --budget C`: a Chinchilla law whose N_opt at C = 6·10¹⁰ is
/// 10⁵ (α = β = 0.3, A = B) picks the ladder model nearest it, trains it for C, records the
/// choice in the summary; a second run reuses it from that folder given as --sweep; a law
/// that reads the vocabulary is refused, naming the file.
fn a_law_sizes_the_backbone(setup: &Path) {
    let csv = setup.join("law.csv");
    let mut table = String::from("N,D,loss\n");
    for i in 0..6 {
        for j in 0..6 {
            let (n, d) = (
                10f64.powf(4.0 + 0.4 * i as f64),
                10f64.powf(5.0 + 0.4 * j as f64),
            );
            let loss = 1.5 + 50.0 * n.powf(-0.3) + 50.0 * d.powf(-0.3);
            table.push_str(&format!("{n},{d},{loss}\n"));
        }
    }
    std::fs::write(&csv, table).unwrap();
    let fit = setup.join("law-fit");
    motionscale_ok(&[
        "fit",
        "--results",
        arg(&csv),
        "--n-col",
        "N",
        "--d-col",
        "D",
        "--loss-col",
        "loss",
        "--law",
        "chinchilla",
        "--bootstrap",
        "10",
        "--out",
        arg(&fit),
    ]);
    let laws = fit.join("laws.json");
    let by_law = |out: &Path, extra: &[&str]| {
        let mut args = continual_args(setup, "seq-lora", "1", out);
        let at = args.iter().position(|a| a == "--base").unwrap();
        args.drain(at..at + 2);
        args.extend(["--fits", arg(&laws), "--budget", "6e10"].map(String::from));
        args.extend(["--models", "cpu-50K,cpu-100K,cpu-400K"].map(String::from));
        if extra.contains(&"--expert-epochs") {
            let at = args.iter().position(|a| a == "--tokens-budget").unwrap();
            args.drain(at..at + 2);
        }
        args.extend(extra.iter().map(|s| s.to_string()));
        motionscale(&args.iter().map(String::as_str).collect::<Vec<_>>())
    };
    let first = setup.join("law-seq");
    let out = by_law(&first, &[]);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let summary: Value = read_json(&first.join("summary.json"));
    let choice = &summary["config"]["backbone"];
    let n_opt = choice["n_opt"].as_f64().unwrap();
    assert!((n_opt / 1e5).ln().abs() < 0.1, "N_opt {n_opt}: {choice}");
    assert!(
        choice["law"].as_str().unwrap().contains("chinchilla"),
        "{choice}"
    );
    assert_eq!(choice["reused"], false);
    let run = std::path::PathBuf::from(choice["run"].as_str().unwrap());
    assert!(run.join("model.safetensors").is_file(), "{choice}");
    assert_eq!(summary["config"]["base"], choice["run"]);
    let n_nv = choice["n_nv"].as_f64().unwrap();
    assert!(
        (n_nv / n_opt).ln().abs() < (4f64).ln(),
        "{choice}: a ladder model near N_opt"
    );
    // Given the first run's backbone folder as a sweep, the second run reuses its backbone;
    // --expert-epochs backbone trains each step as many epochs of its clips as the backbone
    // trained of its own.
    let sweep = first.join("backbone");
    let second = [
        "--sweep",
        arg(&sweep),
        "--expert-epochs",
        "backbone",
        "--eval-learned-only",
    ];
    let out = by_law(&setup.join("law-seq-2"), &second);
    assert_eq!(code(&out), 0, "{}", text(&out));
    let again: Value = read_json(&setup.join("law-seq-2/summary.json"));
    assert_eq!(again["config"]["backbone"]["reused"], true);
    assert_eq!(again["config"]["backbone"]["run"], choice["run"]);
    let epochs = choice["epochs"].as_f64().unwrap();
    assert!(epochs > 0.0, "{choice}");
    assert_eq!(again["config"]["expert_epochs"].as_f64(), Some(epochs));
    let step: Value = read_json(&setup.join("law-seq-2/order-0/step-1/train/config.json"));
    let budget = step["train"]["tokens_budget"].as_f64().unwrap();
    assert!(
        budget > epochs && budget != 600.0,
        "epochs × the step's loss positions, not --tokens-budget: {budget}"
    );
    // --eval-learned-only: after step k only the first k datasets are scored.
    for order in again["orders"].as_array().unwrap() {
        let f = order["f"].as_array().unwrap();
        for (k, row) in f.iter().enumerate() {
            for (j, cell) in row.as_array().unwrap().iter().enumerate() {
                assert_eq!(cell.is_number(), j <= k, "step {k}, dataset {j}: {order}");
            }
        }
    }
    // A laws.json whose adopted law reads the vocabulary does not size a backbone.
    let mut report: Value = read_json(&laws);
    report["adopted"] = "vocab".into();
    std::fs::write(&laws, report.to_string()).unwrap();
    let out = by_law(&setup.join("law-vocab"), &[]);
    assert_eq!(code(&out), 1);
    assert!(
        text(&out).contains("laws.json") && text(&out).contains("reads the vocabulary"),
        "{}",
        text(&out)
    );
}

/// A second MTL seed shares the first one's row (mean ± interval over 2 seeds); a run whose
/// summary names another evaluator is refused unless `--mixed-evaluators`.
fn compare_groups_seeds_and_refuses_mixed_evaluators(setup: &Path, mtl: &Path) {
    let seed1 = setup.join("mtl-seed1");
    let mut args = continual_args(setup, "mtl", "2", &seed1);
    args.extend(["--seed", "1"].map(String::from));
    motionscale_ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let table = motionscale_ok(&["continual", "compare", arg(mtl), arg(&seed1)]);
    assert_eq!(table.lines().count(), 3, "one row for both seeds: {table}");
    assert!(table.contains("(+1 seeds) | mtl | 2 | 2 |"), "{table}");
    assert!(table.contains(" ± "), "an interval over the seeds: {table}");

    let other = setup.join("mtl-other-evaluator");
    std::fs::create_dir_all(&other).unwrap();
    let mut summary: Value = read_json(&seed1.join("summary.json"));
    summary["evaluator_id"] = Value::from("000000000000");
    std::fs::write(other.join("summary.json"), summary.to_string()).unwrap();
    let out = motionscale(&["continual", "compare", arg(mtl), arg(&other)]);
    assert_eq!(code(&out), 1);
    assert!(
        text(&out).contains("scored by different evaluators")
            && text(&out).contains("000000000000"),
        "{}",
        text(&out)
    );
    motionscale_ok(&[
        "continual",
        "compare",
        "--mixed-evaluators",
        arg(mtl),
        arg(&other),
    ]);
}

/// A dataset whose test list holds a clip the backbone trained on is refused, naming the list.
fn refuses_a_backbone_that_trained_on_held_out_clips(setup: &Path) {
    let leaky = setup.join("scenarios-leaky");
    std::fs::create_dir_all(&leaky).unwrap();
    let scenarios = setup.join("scenarios");
    for entry in std::fs::read_dir(&scenarios).unwrap() {
        let path = entry.unwrap().path();
        let target = leaky.join(path.file_name().unwrap());
        if path.is_dir() {
            std::fs::create_dir_all(&target).unwrap();
            for file in std::fs::read_dir(&path).unwrap() {
                let file = file.unwrap().path();
                std::fs::copy(&file, target.join(file.file_name().unwrap())).unwrap();
            }
        } else {
            std::fs::copy(&path, &target).unwrap();
        }
    }
    let sets: Value = read_json(&scenarios.join("datasets.json"));
    let first = sets["datasets"][0]["name"].as_str().unwrap();
    let train = std::fs::read_to_string(leaky.join(first).join("train.txt")).unwrap();
    let test = leaky.join(first).join("test.txt");
    let mut held_out = std::fs::read_to_string(&test).unwrap();
    held_out.push_str(train.lines().next().unwrap());
    held_out.push('\n');
    std::fs::write(&test, held_out).unwrap();
    let mut args = continual_args(setup, "seq-lora", "1", &setup.join("leaky"));
    args[2] = arg(&leaky).to_string();
    let out = motionscale(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(code(&out), 1, "{}", text(&out));
    assert!(
        text(&out).contains("test.txt") && text(&out).contains("train clips of the backbone"),
        "{}",
        text(&out)
    );
}

/// Scenario datasets keep the corpus split, for Unseen and Mixed: no val/test list holds a
/// clip the corpus puts in train (the per-dataset re-split did: 9 of the 15 D01_daily test
/// clips of this corpus were corpus train clips), and every labelled clip is listed once.
#[test]
fn scenario_lists_keep_the_corpus_split() {
    let tmp = tempfile::tempdir().unwrap();
    let corpus = tmp.path().join("corpus");
    motionscale_ok(&[
        "ingest",
        "--source",
        "synth:600:11",
        "--out",
        arg(&corpus),
        "--mirror",
    ]);
    let meta = ingest::corpus::Corpus::open(&corpus)
        .unwrap()
        .clip_metadata()
        .unwrap();
    let split_of: HashMap<&str, &str> = meta
        .iter()
        .map(|m| (m.motion_id.as_str(), m.split.as_str()))
        .collect();
    let labelled = meta.iter().filter(|m| m.labels.scenario.is_some()).count();
    for kind in ["unseen", "mixed"] {
        let out = tmp.path().join(kind);
        motionscale_ok(&[
            "scenarios",
            "--corpus",
            arg(&corpus),
            "--split",
            kind,
            "--out",
            arg(&out),
        ]);
        let sets: Value = read_json(&out.join("datasets.json"));
        let mut listed = 0;
        for d in sets["datasets"].as_array().unwrap() {
            for (list, ids) in d["clips"].as_object().unwrap() {
                for id in ids.as_array().unwrap().iter().map(|v| v.as_str().unwrap()) {
                    assert_eq!(split_of[id], list, "{kind} {}: {id}", d["name"]);
                    listed += 1;
                }
            }
        }
        assert_eq!(listed, labelled, "{kind}: every labelled clip listed once");
    }
}
