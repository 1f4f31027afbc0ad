"""The learning-rate check: L_u per size and peak rate at 3e12, and each rate's parabola vertex.

python3 docs/results/data-law/lr/lr_table.py  (reads the rows committed beside it; 1e-3 is the
data-law sweep's own rate, in ../results.csv)."""
import csv, math, os
here = os.path.dirname(os.path.abspath(__file__))
tables = {"1e-3": os.path.join(here, "..", "results.csv")}
tables.update({lr: os.path.join(here, f"results-lr{lr}.csv") for lr in ["3e-4", "3e-3", "1e-2"]})
sizes = ["64x2", "96x2", "128x2", "96x1"]
rows = {}
for lr, path in tables.items():
    try:
        for r in csv.DictReader(open(path)):
            if r["seed"] == "0" and r["data"] == "all-1" and float(r["budget"]) == 3e12 and r["model"] in sizes:
                rows[(lr, r["model"])] = r
    except FileNotFoundError:
        pass
print("| peak rate | " + " | ".join(f"`{m}` (N_nv {rows[('1e-3', m)]['n_nv']})" for m in sizes) + " | best | vertex of the two-layer sizes (parabola in log10 N_nv) |")
print("|---|" + "---|" * (len(sizes) + 2))
for lr in ["3e-4", "1e-3", "3e-3", "1e-2"]:
    # The vertex from the two-layer family only: 96x1 differs in depth, not just in size.
    pts = [(math.log10(float(rows[(lr, m)]["n_nv"])), float(rows[(lr, m)]["best_norm_test_loss"]), 0) for m in sizes[:3] if (lr, m) in rows]
    if len(pts) < 3 or any((lr, m) not in rows for m in sizes):
        print(f"| {lr} | (incomplete: {len(pts)} of the two-layer sizes) |"); continue
    (x1, y1, _), (x2, y2, _), (x3, y3, _) = sorted(pts)
    den = (x1 - x2) * (x1 - x3) * (x2 - x3)
    a = (x3 * (y2 - y1) + x2 * (y1 - y3) + x1 * (y3 - y2)) / den
    b = (x3 * x3 * (y1 - y2) + x2 * x2 * (y3 - y1) + x1 * x1 * (y2 - y3)) / den
    vertex = f"10^{-b / (2 * a):.2f}" if a > 0 else "none (concave)"
    best = min(sizes, key=lambda m: float(rows[(lr, m)]["best_norm_test_loss"]))
    cells = [f"{float(rows[(lr, m)]['best_norm_test_loss']):.3f} / {float(rows[(lr, m)]['best_real_test_loss']):.3f}" for m in sizes]
    print(f"| {lr} | " + " | ".join(cells) + f" | `{best}` | {vertex} |")
