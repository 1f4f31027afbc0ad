"""Stage 3 of the re-run ladders (issue #55): the law chosen by its forward error on stage 2's
four scored cells, refitted on every run so far, its predictions for new cells at 2·10¹⁴ FLOPs,
and the sizes that will score them (plan-5.toml), written before any of those runs.

    python3 stage3.py MOTIONSCALE          # writes stage3/ and plan-5.toml beside this file

A cell's loss is the best captured test CE (`best_real_test_loss`, the validation-selected
checkpoint) over the sizes declared for it. The sizes: the two ladder shapes whose N bracket
the adopted law's N_opt at the cell. The table: results.csv (stages 1 and 2, seeds, the anneal
test) and the plateau check's runs above 3·10¹³ (../plateau/results.csv; its data column is
empty and is filled with `all-1`, the only subset it trained).
"""
import csv, math, os, pathlib, tomllib

import stage2
from stage2 import FRACTIONS, LAWS, cells, fit, predict, write

HERE = stage2.HERE
OUT = pathlib.Path("stage3")
TARGET = 2e14
BASE, PREV = 1e14, 3e13  # the baselines: no growth from BASE, the PREV -> BASE trend carried on


def table():
    rows = list(csv.DictReader(open(HERE / "results.csv")))
    for r in csv.DictReader(open(HERE.parent / "plateau" / "results.csv")):
        if float(r["budget"]) > 3.1e13:
            rows.append({**r, "data": r["data"] or "all-1"})
    return rows


def forward_rms():
    """Each law's RMS error over stage 2's forward cells (scored.csv lists them)."""
    scored = {(float(s["budget"]), s["data"]): float(s["best"])
              for s in csv.DictReader(open(HERE / "stage2" / "scored.csv"))}
    errors = {}
    for p in csv.DictReader(open(HERE / "stage2" / "predictions.csv")):
        key = (float(p["budget"]), p["data"])
        if key in scored:
            errors.setdefault(p["law"], []).append(float(p["loss"]) - scored[key])
    return {law: math.sqrt(sum(e * e for e in v) / len(v)) for law, v in errors.items()}, len(scored)


def bracket(n_opt, shapes):
    """The two shapes (by non-vocabulary N) around n_opt: the largest below, the smallest above."""
    below = max((m for m in shapes if shapes[m][0] <= n_opt), key=lambda m: shapes[m][0])
    above = min((m for m in shapes if shapes[m][0] > n_opt), key=lambda m: shapes[m][0])
    return [below, above]


def plan(declared, rows):
    """plan-4.toml with the stage-3 points appended (the same runs, indices from 89)."""
    text = (HERE / "plan-4.toml").read_text()
    index = len(tomllib.loads(text)["points"])
    shape = {r["model"]: r for r in rows}
    unique = {r["data"]: float(r["unique_tokens"]) for r in rows}
    extra = []
    for d, models in declared.items():
        for m in models:
            s = shape[m]
            n_nv, n_v = int(s["n_nv"]), int(s["n_v"])
            tokens = round(TARGET / (6 * (n_nv + n_v)))
            extra.append(f"""
[[points]]
index = {index}
run_id = "c2e14-{m}-v1024-d{d}"
budget = {TARGET:.1f}
model = "{m}"
codebook = 1024
d_model = {s['d_model']}
n_layers = {s['layers']}
n_heads = {s['heads']}
n_nv = {n_nv}
n_v = {n_v}
tokens = {tokens}
epochs = {tokens / unique[d]!r}
flags = ["exceeds-data"]
seed = 0
data = "{d}"
unique_tokens = {int(unique[d])}
""")
            index += 1
    head, centres = text.split("\n[[centres]]", 1)
    (HERE / "plan-5.toml").write_text(head.rstrip("\n") + "\n" + "".join(extra) + "\n[[centres]]" + centres)


def main():
    os.chdir(HERE)
    rows = table()
    all_rows = OUT / "rows.csv"
    OUT.mkdir(exist_ok=True)
    write(all_rows, rows)
    shapes = dict(stage2.SHAPES)
    shapes.update({r["model"]: (float(r["n_nv"]), float(r["n_v"])) for r in rows})
    measured = cells(rows)
    rms, n_cells = forward_rms()
    adopted = min(rms, key=rms.get)
    lines = [f"forward RMS error of stage 2's predictions over its {n_cells} scored cells:"]
    lines += [f"  {law:<13} {rms[law]:.4f}" + ("  <- adopted" if law == adopted else "")
              for law in sorted(rms, key=rms.get)]
    preds, declared = [], {}
    for law in LAWS:
        fits, text = fit(law, all_rows, OUT / law, 100 if law == "dc-stopping" else 200, "budget")
        (OUT / f"{law}.txt").write_text(text)
        for d in FRACTIONS:
            base, prev = measured[(BASE, d)], measured[(PREV, d)]
            v, lo, hi, n = predict(law, fits, TARGET, base, shapes)
            slope = (base[0] - prev[0]) / math.log10(BASE / PREV)
            if law == adopted:
                declared[d] = bracket(n, shapes)
            preds.append({"law": law, "budget": f"{TARGET:.3g}", "data": d, "loss": f"{v:.4f}",
                          "pi_low": f"{lo:.4f}", "pi_high": f"{hi:.4f}", "n_opt": f"{n:.4g}",
                          "no_growth": f"{base[0]:.4f}",
                          "trend": f"{base[0] + slope * math.log10(TARGET / BASE):.4f}"})
    write(OUT / "predictions.csv", preds)
    plan(declared, rows)
    lines.append(f"fitted on {len(rows)} runs (stage2/ refits: stage2.py); predictions at "
                 f"{TARGET:.3g} (95% prediction intervals; baselines: no growth from {BASE:.3g}, "
                 f"the {PREV:.3g} -> {BASE:.3g} trend per decade carried on):")
    lines += ["  " + "  ".join(f"{k} {v}" for k, v in p.items()) for p in preds]
    mine = {p["data"]: float(p["loss"]) for p in preds if p["law"] == adopted}
    lines.append(f"doubling 1/2 -> 1 at {TARGET:.3g} ({adopted}): {mine['all-1'] - mine['all-1_2']:+.4f}")
    lines.append("declared sizes (plan-5.toml): " + "; ".join(f"{d} {', '.join(m)}" for d, m in declared.items()))
    (OUT / "summary.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
