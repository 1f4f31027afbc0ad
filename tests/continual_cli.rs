//! Continual expert training through the binary on a synthetic corpus: scenario datasets,
//! a tiny backbone and evaluator, `continual` with seq-lora and mtl (matrix shapes, summary
//! metrics, an identical summary when re-run), the replay buffer's lists, the O-LoRA and
//! LwF-LoRA steps' settings, and `compare`.

mod common;

use common::*;
use serde_json::Value;
use std::path::Path;

fn continual(setup: &Path, method: &str, out: &Path) -> Value {
    let p = |name: &str| setup.join(name);
    let (scenarios, run, tokens, evaluator) =
        (p("scenarios"), p("run"), p("tokens"), p("evaluator"));
    motionscale_ok(&[
        "continual",
        "--scenarios",
        arg(&scenarios),
        "--method",
        method,
        "--base",
        arg(&run),
        "--tokens",
        arg(&tokens),
        "--evaluator",
        arg(&evaluator),
        "--orders",
        "2",
        "--tokens-budget",
        "600",
        "--batch",
        "8",
        "--repeats",
        "2",
        "--pool",
        "8",
        "--mm-texts",
        "2",
        "--eval-split",
        "train",
        "--out",
        arg(out),
    ]);
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
        table.contains("| seq-lora | 2 |") && table.contains("| mtl | 2 |"),
        "{table}"
    );
    let out = motionscale(&[
        "continual",
        "--scenarios",
        arg(&scenarios),
        "--method",
        "es-moe",
        "--base",
        "x",
        "--tokens",
        "x",
        "--evaluator",
        "x",
        "--out",
        arg(&setup.join("no")),
    ]);
    assert_eq!(code(&out), 1);
    assert!(text(&out).contains("not built yet"), "{}", text(&out));
}
