"""Where in its schedule a run was selected, and what that cost: every (size, data subset) trained
at two or more budgets (seed 0), with each run's planned epochs, the epoch of its
validation-selected checkpoint and the learning-rate factor there (the recipe's schedule: 5%
linear warm-up, then cosine to 0.1 of the peak), and its best captured test CE.

    python3 schedule.py          # prints the pairs, then the loss change of each pair whose
                                 # selected checkpoint moved from a low rate (<= 0.5) to a high one
                                 # (>= 0.8) while the size and the data stayed the same
"""
import csv, math, pathlib, statistics

HERE = pathlib.Path(__file__).resolve().parent
WARMUP, FINAL = 0.05, 0.1


def rate(share):
    """The learning-rate factor at `share` of a run's steps."""
    if share < WARMUP:
        return share / WARMUP
    progress = (share - WARMUP) / (1 - WARMUP)
    return FINAL + (1 - FINAL) * 0.5 * (1 + math.cos(math.pi * progress))


def runs():
    rows = list(csv.DictReader(open(HERE / "results.csv")))
    for r in csv.DictReader(open(HERE.parent / "plateau" / "results.csv")):
        if float(r["budget"]) > 3.1e13:  # the plateau check's 3e13 runs are the ladder's own
            rows.append({**r, "data": r["data"] or "all-1"})
    return [r for r in rows if r["seed"] == "0"]


def main():
    groups = {}
    for r in runs():
        share = float(r["best_step"]) / float(r["steps"])
        groups.setdefault((r["model"], r["data"]), []).append(
            (float(r["budget"]), float(r["epochs"]), float(r["epochs"]) * share, rate(share),
             float(r["best_real_test_loss"])))
    changes = []
    for (model, data), v in sorted(groups.items()):
        if len(v) < 2:
            continue
        v.sort()
        print(f"{model:>6} {data:<8} " + " | ".join(
            f"{c:.0e}: {e:.0f} ep, selected at {s:.1f} (rate {lr:.2f}) {loss:.3f}"
            for c, e, s, lr, loss in v))
        for a, b in zip(v, v[1:]):
            if a[3] <= 0.5 and b[3] >= 0.8:
                changes.append((model, data, b[4] - a[4]))
    print("selected at a high rate instead of a low one, same size and data:")
    for model, data, d in changes:
        print(f"  {model} {data}: {d:+.3f}")
    values = [d for *_, d in changes]
    print(f"  median {statistics.median(values):+.3f} over {len(values)} pairs "
          f"(range {min(values):+.3f} to {max(values):+.3f})")


if __name__ == "__main__":
    main()
