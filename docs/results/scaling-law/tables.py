"""The scaling-law study's tables from a sweep's results.csv (standard library only).

    python3 docs/results/scaling-law/tables.py $L/runs/results.csv

Prints, as Markdown: the IsoFLOP grid (L_u of every run, best vocabulary marked), the seed
repeats (each seed's L_u, mean, standard deviation, range, and wall time with the binary
that trained it), and worker throughput per
model size and binary (the plan's budget FLOPs C per wall second of the run, with the
number of runs).
"""

import csv
import statistics
import sys
from collections import defaultdict


def fmt_c(c):
    mantissa, exponent = f"{c:.0e}".split("e")
    exponent = int(exponent)
    return f"10^{exponent}" if mantissa == "1" else f"{mantissa}·10^{exponent}"


def grid(rows):
    base = [r for r in rows if r["seed"] == "0"]
    vocabs = sorted({int(r["vocab"]) for r in base})
    print("| C | model | N_nv | " + " | ".join(f"K = {v}" for v in vocabs) + " |")
    print("|---|---|---|" + "---|" * len(vocabs))
    by = defaultdict(dict)
    for r in base:
        by[(float(r["budget"]), int(r["n_nv"]), r["model"])][int(r["vocab"])] = float(
            r["norm_test_loss"]
        )
    for (c, n, model), losses in sorted(by.items()):
        best = min(losses.values())
        cells = []
        for v in vocabs:
            if v not in losses:
                cells.append("")
            elif losses[v] == best:
                cells.append(f"**{losses[v]:.3f}**")
            else:
                cells.append(f"{losses[v]:.3f}")
        print(f"| {fmt_c(c)} | {model} | {n:,} | " + " | ".join(cells) + " |")


def seeds(rows):
    groups = defaultdict(list)
    for r in rows:
        base = r["run_id"].rsplit("-s", 1)[0] if r["seed"] != "0" else r["run_id"]
        groups[base].append(r)
    print("| point | seeds | L_u per seed | mean | sd | range | wall s per seed (binary) |")
    print("|---|---|---|---|---|---|---|")
    for run_id, runs in sorted(groups.items()):
        if len(runs) < 2:
            continue
        runs.sort(key=lambda r: int(r["seed"]))
        losses = [float(r["norm_test_loss"]) for r in runs]
        walls = ", ".join(f"{float(r['wall_s']):.0f} ({r['git_revision'][:7]})" for r in runs)
        values = ", ".join(f"{v:.4f}" for v in losses)
        print(
            f"| `{run_id}` | {len(runs)} | {values} | {statistics.mean(losses):.4f} "
            f"| {statistics.stdev(losses):.4f} | {max(losses) - min(losses):.4f} | {walls} |"
        )


def throughput(rows):
    by = defaultdict(list)
    for r in rows:
        by[(r["model"], int(r["n_nv"]), r["git_revision"][:7])].append(
            float(r["budget"]) / float(r["wall_s"]) / 1e9
        )
    revs = sorted({rev for _, _, rev in by})
    models = sorted({(n, m) for m, n, _ in by})
    print("Median C / wall over runs (GFLOP/s of the plan's 6·(N_nv + N_v)·D), per binary:\n")
    print("| model | N_nv | " + " | ".join(f"`{r}`" for r in revs) + " |")
    print("|---|---|" + "---|" * len(revs))
    for n, model in models:
        cells = []
        for rev in revs:
            xs = by.get((model, n, rev))
            cells.append(f"{statistics.median(xs):.1f} ({len(xs)})" if xs else "")
        print(f"| {model} | {n:,} | " + " | ".join(cells) + " |")


def main():
    rows = list(csv.DictReader(open(sys.argv[1])))
    for title, table in [("IsoFLOP grid (L_u)", grid), ("Seed repeats", seeds),
                         ("Throughput", throughput)]:
        print(f"\n### {title}\n")
        table(rows)


if __name__ == "__main__":
    main()
