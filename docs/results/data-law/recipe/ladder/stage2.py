"""Stage 2 of the re-run ladders (issue #55): the laws fitted on stage 1 alone, chosen by their
error on the cells of each data subset left out in turn, and their predictions for the cells
stage 2 trains. A cell is a (budget, data fraction); its loss is the best captured test CE
(`best_real_test_loss`, the validation-selected checkpoint) over the sizes trained there.

    python3 stage2.py MOTIONSCALE [RESULTS_CSV]    # writes stage2/ beside this file

The leave-one-ladder-out scores are kept in stage2/ and reused when present (delete the file
to refit them).

Laws (each fitted by `motionscale fit`, predicted by `motionscale predict`):
- `dc-stopping`: Muennighoff et al.'s data-constrained law on the selected checkpoints' tokens
  with the stopping rule e* (`fit --repeated-data --early-stopping`, both exchange forms);
  a cell's prediction is `predict --hours` at the cell's captured and synthetic hours.
- `dc`, `unique-floor`, `chinchilla`: `fit --law` on the runs' planned tokens (the loss of a
  run's selected checkpoint as a function of what the run was given); a cell's prediction is
  `predict --unique-tokens U --vocab-params N_v` (N_v of the ladder's model nearest N_opt).
The exchange-rate forms (`data-constrained-token-worth`, `-effective-pool`) are tried too; with
one synthetic share in every run they are refused (ρ is not identified), and the refusal is kept.
"""
import csv, json, math, os, pathlib, subprocess, sys, tempfile

HERE = pathlib.Path(__file__).resolve().parent
# The binary and a table given are resolved from the caller's folder; everything runs from
# HERE with relative paths, so the files written name no machine's folders.
BIN = str(pathlib.Path(sys.argv[1]).resolve()) if os.sep in sys.argv[1] else sys.argv[1]
RESULTS = pathlib.Path(sys.argv[2]).resolve() if len(sys.argv) > 2 else pathlib.Path("results.csv")
OUT = pathlib.Path("stage2")
LOSS = "best_real_test_loss"
FRACTIONS = {"all-1_4": 0.25, "all-1_2": 0.5, "all-1": 1.0}
TARGETS = [1e14, 3e14]
LAWS = ["dc-stopping", "dc", "unique-floor", "chinchilla"]
# Non-vocabulary and vocabulary parameters of the ladder's shapes (WIDTHx4 beyond stage 1).
SHAPES = {"256x4": (3247616, 513536), "320x4": (5040000, 641920), "384x4": (7229184, 770304),
          "448x4": (9812096, 898688), "512x4": (12782592, 1027072), "640x4": (19915520, 1283840),
          "768x4": (28614144, 1540608)}


def run(*args):
    return subprocess.run([BIN, *map(str, args)], check=True, capture_output=True, text=True).stdout


def cells(rows):
    """(budget, data) -> (best loss, its model, hours, synth hours, unique tokens)."""
    out = {}
    for r in rows:
        key = (float(r["budget"]), r["data"])
        if key not in out or float(r[LOSS]) < out[key][0]:
            out[key] = (float(r[LOSS]), r["model"], float(r["hours"]),
                        float(r["hours"]) * float(r["synth_share"]), float(r["unique_tokens"]))
    return out


def fit(law, table, out, bootstrap, block=None):
    """Fits `law` to `table` in folder `out`; returns the fits file and the fit's text."""
    common = ["--results", table, "--out", out, "--bootstrap", bootstrap, "--loss-col"]
    if law == "dc-stopping":
        text = run("fit", *common, "best_norm_test_loss", "--param-loss-col", LOSS, "--repeated-data",
                   "--early-stopping", "--exchange-form", "token-worth,effective-pool")
        return pathlib.Path(out) / "fits.json", text
    name = {"dc": "data-constrained"}.get(law, law)
    extra = ["--block-bootstrap", block] if block else []
    text = run("fit", *common, LOSS, "--law", name, "--u-col", "unique_tokens", *extra)
    return pathlib.Path(out) / "laws.json", text


def predict(law, fits, budget, cell, shapes):
    """(loss, low, high, N_opt) of the law's 95% prediction interval at a cell."""
    _, _, hours, synth, unique = cell
    if law == "dc-stopping":
        p = json.loads(run("predict", "--fits", fits, "--budget", budget, "--json",
                           "--hours", f"real={hours - synth},synth={synth}"))["prediction"]
        lp = p["loss_prediction"]
        return lp["value"], lp["ci_low"], lp["ci_high"], p["n_opt"]["value"]
    nv = 0.0
    for _ in range(2):  # N_v of the shape nearest the optimum, then the optimum again
        p = json.loads(run("predict", "--fits", fits, "--budget", budget, "--json",
                           "--unique-tokens", unique, "--vocab-params", nv))
        nv = min(shapes.values(), key=lambda s: abs(math.log(s[0] / p["n"]["value"])))[1]
    return p["loss"]["value"], p["loss"]["ci_low"], p["loss"]["ci_high"], p["n"]["value"]


def write(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def main():
    os.chdir(HERE)
    rows = list(csv.DictReader(open(RESULTS)))
    shapes = dict(SHAPES)
    shapes.update({r["model"]: (float(r["n_nv"]), float(r["n_v"])) for r in rows})
    measured = cells(rows)
    OUT.mkdir(exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp())
    loo_csv = OUT / "leave-one-ladder-out.csv"
    loo = list(csv.DictReader(open(loo_csv))) if loo_csv.exists() else []
    for held in FRACTIONS if not loo else []:
        table = tmp / f"without-{held}.csv"
        write(table, [r for r in rows if r["data"] != held])
        for law in LAWS:
            fits, _ = fit(law, table, tmp / f"{law}-without-{held}", 0)
            for (c, d), cell in sorted(measured.items()):
                if d == held:
                    p = predict(law, fits, c, cell, shapes)
                    loo.append({"law": law, "held_out": held, "budget": f"{c:.3g}",
                                "best": f"{cell[0]:.4f}", "predicted": f"{p[0]:.4f}",
                                "error": f"{p[0] - cell[0]:+.4f}"})
    write(loo_csv, loo)
    rms = {law: math.sqrt(sum(float(r["error"]) ** 2 for r in loo if r["law"] == law)
                          / sum(r["law"] == law for r in loo)) for law in LAWS}
    adopted = min(rms, key=rms.get)
    lines = ["leave-one-ladder-out RMS error of the cells' best captured CE (12 cells per law):"]
    lines += [f"  {law:<13} {rms[law]:.4f}" + ("  <- adopted" if law == adopted else "")
              for law in sorted(LAWS, key=rms.get)]
    try:
        run("fit", "--results", RESULTS, "--out", tmp / "exchange", "--bootstrap", 0, "--loss-col",
            LOSS, "--law", "data-constrained-token-worth,data-constrained-effective-pool")
        lines.append("exchange-rate forms: fitted (see exchange/)")
    except subprocess.CalledProcessError as e:
        lines.append("exchange-rate forms: " + e.stderr.strip().splitlines()[-1])
    preds, inside = [], {}
    for law in LAWS:
        fits, text = fit(law, RESULTS, OUT / law, 100 if law == "dc-stopping" else 200, "budget")
        (OUT / f"{law}.txt").write_text(text)
        for (c, d), cell in sorted(measured.items()):
            lo, hi = predict(law, fits, c, cell, shapes)[1:3]
            inside.setdefault(law, []).append(lo <= cell[0] <= hi)
        last = {d: measured[(3e13, d)] for d in FRACTIONS}
        prev = {d: measured[(1e13, d)] for d in FRACTIONS}
        for c in TARGETS:
            for d in FRACTIONS:
                v, lo, hi, n = predict(law, fits, c, last[d], shapes)
                slope = (last[d][0] - prev[d][0]) / math.log10(3)
                preds.append({"law": law, "budget": f"{c:.3g}", "data": d, "loss": f"{v:.4f}",
                              "pi_low": f"{lo:.4f}", "pi_high": f"{hi:.4f}", "n_opt": f"{n:.4g}",
                              "no_growth": f"{last[d][0]:.4f}",
                              "trend": f"{last[d][0] + slope * math.log10(c / 3e13):.4f}"})
    write(OUT / "predictions.csv", preds)
    lines.append("in sample (fitted on all 60 runs, budget-block bootstrap): cells whose best lies "
                 "inside the 95% prediction interval")
    lines += [f"  {law:<13} {sum(v)} of {len(v)}" for law, v in inside.items()]
    lines.append("predictions (95% prediction intervals; baselines: no growth from 3e13, and the "
                 "1e13 -> 3e13 trend per decade carried on):")
    for p in preds:
        lines.append("  " + "  ".join(f"{k} {v}" for k, v in p.items()))
    (OUT / "summary.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
