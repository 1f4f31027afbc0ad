"""The plateau check's table: each run of the recipe (selection.csv) beside the old run of the
same budget and size (../../results.csv, full data, seed 0), captured CE at the selected
checkpoint.

    python3 compare.py
"""
import csv
from pathlib import Path

here = Path(__file__).parent
old = {
    (float(r["budget"]), r["model"]): float(r["best_real_test_loss"])
    for r in csv.DictReader(open(here / "../../results.csv"))
    if r["data"] == "all-1" and r["seed"] == "0"
}
plan_budget = {}
for r in csv.DictReader(open(here / "results.csv")):
    plan_budget[r["run_id"]] = (float(r["budget"]), r["model"])
rows = []
for r in csv.DictReader(open(here / "selection.csv")):
    budget, model = plan_budget[r["run_id"]]
    rows.append((budget, model, float(r["lr"]), r["best_step"], r["steps"], float(r["real_test_ce"]), old[(budget, model)]))
rows.sort()
print("| budget | model | lr | selected step | recipe | old (lr 1e-3, wd 0.1) | change |")
print("|---|---|---|---|---|---|---|")
for b, m, lr, step, steps, new, was in rows:
    print(f"| {b:.3g} | {m} | {lr:.2e} | {step} of {steps} | {new:.4f} | {was:.4f} | {new - was:+.4f} |")
print()
for b in sorted({r[0] for r in rows}):
    new = min(r[5] for r in rows if r[0] == b)
    was = min(r[6] for r in rows if r[0] == b)
    print(f"best at {b:.3g}: recipe {new:.4f}, old {was:.4f} ({new - was:+.4f})")
