"""The data-ladder tables from a sweep's results.csv (standard library only).

    python3 docs/results/data-law/tables.py RUNS/results.csv

Prints, as Markdown: for each data subset and budget, the best run by final test L_u (and its
validation-selected L_u, epochs, unique hours), and the per-origin test L_u of that run
(captured clips, synthetic clips); then, at each budget, the best L_u against the subset's
unique hours (the value of more data at fixed compute).
"""

import csv
import sys
from collections import defaultdict


def fmt_c(c):
    mantissa, exponent = f"{c:.0e}".split("e")
    exponent = int(exponent)
    return f"10^{exponent}" if mantissa == "1" else f"{mantissa}·10^{exponent}"


def best_runs(rows):
    """The run of lowest final L_u per (subset, budget)."""
    best = {}
    for r in rows:
        key = (r["data"], float(r["budget"]))
        if key not in best or float(r["norm_test_loss"]) < float(best[key]["norm_test_loss"]):
            best[key] = r
    return best


def per_subset(rows, best):
    print("| subset | hours (synthetic share) | C | runs | best model | N_nv | epochs | L_u final | L_u val-selected | L_u captured | L_u synthetic |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    counts = defaultdict(int)
    for r in rows:
        counts[(r["data"], float(r["budget"]))] += 1
    for (data, c), r in sorted(best.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        print(
            f"| `{data}` | {float(r['hours']):.2f} ({float(r['synth_share']):.0%}) | {fmt_c(c)} | "
            f"{counts[(data, c)]} | `{r['model']}` | {int(r['n_nv']):,} | {float(r['epochs']):.1f} | "
            f"{float(r['norm_test_loss']):.3f} | {float(r['best_norm_test_loss']):.3f} | "
            f"{float(r['real_norm_test_loss']):.3f} | {float(r['synth_norm_test_loss']):.3f} |"
        )


def by_hours(best):
    subsets = sorted({d for d, _ in best}, key=lambda d: (d.split("-")[0], float(
        next(r["hours"] for (dd, _), r in best.items() if dd == d))))
    budgets = sorted({c for _, c in best})
    print("| C | " + " | ".join(f"`{d}`" for d in subsets) + " |")
    print("|---|" + "---|" * len(subsets))
    for c in budgets:
        cells = []
        for d in subsets:
            r = best.get((d, c))
            cells.append("" if r is None else f"{float(r['norm_test_loss']):.3f}")
        print(f"| {fmt_c(c)} | " + " | ".join(cells) + " |")


def main():
    with open(sys.argv[1]) as f:
        rows = [r for r in csv.DictReader(f) if r["seed"] == "0"]
    best = best_runs(rows)
    per_subset(rows, best)
    print()
    by_hours(best)


if __name__ == "__main__":
    main()
