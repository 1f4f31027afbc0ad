"""The learning-rate rule of the data-bound recipe (issue #55, Build 1), from a rate sweep.

    python3 lr_rule.py lr-*/ > lr-rule.txt

Each folder is one rate of the sweep, holding `selection.csv`: per run, the validation
cross-entropy at the validation-selected checkpoint (the test split is never used to choose)
and the test cross-entropy there. Per size: a parabola in log10(lr) through the three rates
around the lowest loss gives lr*; then log10(lr*) = a + b·log10(N_nv) by least squares over the
sizes. Prints the table and the rule as the TOML lines of a recipe.
"""
import csv, math, sys
from pathlib import Path


def rows(dirs):
    for d in map(Path, dirs):
        for r in csv.DictReader(open(d / "selection.csv")):
            yield r["model"], int(r["n_nv"]), float(r["lr"]), float(r["val_ce"]), float(r["test_ce"])


def vertex(points):
    """lr at the minimum of a parabola in log10 lr through the best point and its neighbours."""
    points = sorted(points)
    i = min(range(len(points)), key=lambda k: points[k][1])
    if i in (0, len(points) - 1):
        return points[i][0], "at the edge of the grid"
    (x0, y0), (x1, y1), (x2, y2) = [(math.log10(l), v) for l, v in points[i - 1 : i + 2]]
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
    return 10 ** (-b / (2 * a)), "parabola"


def main(dirs):
    by_size = {}
    for model, n_nv, lr, val, test in rows(dirs):
        by_size.setdefault((n_nv, model), []).append((lr, val, test))
    print("| model | N_nv | lr | val CE (selected) | test CE (selected) |")
    print("|---|---|---|---|---|")
    best = []
    for (n_nv, model), runs in sorted(by_size.items()):
        for lr, val, test in sorted(runs):
            print(f"| {model} | {n_nv:,} | {lr:g} | {val:.4f} | {test:.4f} |")
        lr_star, how = vertex([(lr, val) for lr, val, _ in runs])
        best.append((n_nv, model, lr_star, how, len(runs)))
    print()
    for n_nv, model, lr_star, how, n in best:
        print(f"{model} (N_nv {n_nv:,}): lr* {lr_star:.3g} ({how}, {n} rates)")
    fit = [(math.log10(n), math.log10(l)) for n, _, l, how, _ in best if how == "parabola"]
    if len(fit) < 2:
        print("fewer than two sizes with an interior optimum: no rule")
        return
    mx = sum(x for x, _ in fit) / len(fit)
    my = sum(y for _, y in fit) / len(fit)
    b = sum((x - mx) * (y - my) for x, y in fit) / sum((x - mx) ** 2 for x, _ in fit)
    ref = 10 ** mx
    print(f"\nrule over {len(fit)} sizes: lr* = {10 ** my:.3g} · (N_nv / {ref:.4g})^{b:.3f}")
    print(f"\nlr_at_reference = {10 ** my:.4g}\nreference_params = {ref:.6g}\nlr_exponent = {b:.4f}")


if __name__ == "__main__":
    main(sys.argv[1:])
