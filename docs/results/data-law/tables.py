"""The data-ladder tables from a sweep's results.csv (standard library only).

    python3 docs/results/data-law/tables.py RUNS/results.csv

Prints, as Markdown: for each data subset and budget, the best run by validation-selected test
L_u (its final L_u, epochs, unique hours, and the per-origin test L_u at the selected step:
captured clips, synthetic clips); then, at each budget, the best L_u against the subset's
unique hours (the value of more data at fixed compute): on the whole test split, and on its
captured clips alone. Every L_u is ScaMo's Eq. 8 against the full train split's unigram.
"""

import csv
import sys
from collections import defaultdict


def fmt_c(c):
    mantissa, exponent = f"{c:.0e}".split("e")
    exponent = int(exponent)
    return f"10^{exponent}" if mantissa == "1" else f"{mantissa}·10^{exponent}"


def best_runs(rows, col):
    """The run of lowest `col` per (subset, budget)."""
    best = {}
    for r in rows:
        key = (r["data"], float(r["budget"]))
        if key not in best or float(r[col]) < float(best[key][col]):
            best[key] = r
    return best


def per_subset(rows, best):
    print("| subset | hours (synthetic share) | C | runs | best model | N_nv | epochs | L_u val-selected | L_u final | captured (val-sel.) | synthetic (val-sel.) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    counts = defaultdict(int)
    for r in rows:
        counts[(r["data"], float(r["budget"]))] += 1
    for (data, c), r in sorted(best.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        print(
            f"| `{data}` | {float(r['hours']):.2f} ({float(r['synth_share']):.0%}) | {fmt_c(c)} | "
            f"{counts[(data, c)]} | `{r['model']}` | {int(r['n_nv']):,} | {float(r['epochs']):.1f} | "
            f"{float(r['best_norm_test_loss']):.3f} | {float(r['norm_test_loss']):.3f} | "
            f"{float(r['best_real_norm_test_loss']):.3f} | {float(r['best_synth_norm_test_loss']):.3f} |"
        )


def by_hours(rows, col):
    best = best_runs(rows, col)
    subsets = sorted({d for d, _ in best}, key=lambda d: (d.split("-")[0], float(
        next(r["hours"] for (dd, _), r in best.items() if dd == d))))
    budgets = sorted({c for _, c in best})
    print("| C | " + " | ".join(f"`{d}`" for d in subsets) + " |")
    print("|---|" + "---|" * len(subsets))
    for c in budgets:
        cells = []
        for d in subsets:
            r = best.get((d, c))
            cells.append("" if r is None else f"{float(r[col]):.3f}")
        print(f"| {fmt_c(c)} | " + " | ".join(cells) + " |")


def main():
    with open(sys.argv[1]) as f:
        rows = [r for r in csv.DictReader(f) if r["seed"] == "0"]
    per_subset(rows, best_runs(rows, "best_norm_test_loss"))
    for col in ["best_norm_test_loss", "best_real_norm_test_loss", "norm_test_loss"]:
        print(f"\nBest `{col}` per budget and subset:\n")
        by_hours(rows, col)


if __name__ == "__main__":
    main()
