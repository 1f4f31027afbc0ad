"""Scores a stage's pre-registered predictions (stageN/predictions.csv, committed before the
runs) on the cells trained since: a cell's loss is the best captured test CE
(`best_real_test_loss`) over the sizes declared for it (seed 0) in the stage's plan — stage 2's
in plan-2.toml (after plan-1.toml's points), stage 3's in plan-5.toml (after plan-4.toml's).
With stage 3, each declared size is scored too, against stage3/sizes.txt (`predict --sizes`).

    python3 score.py 2           # prints the table, writes stage2/scored.csv
    python3 score.py 3           # the same for stage 3
"""
import csv, pathlib, re, sys, tomllib

HERE = pathlib.Path(__file__).resolve().parent
STAGE_NUMBER = sys.argv[1] if len(sys.argv) > 1 else "2"
STAGE = HERE / f"stage{STAGE_NUMBER}"
PLANS = {"2": ("plan-1.toml", "plan-2.toml"), "3": ("plan-4.toml", "plan-5.toml")}
WITHIN = 0.05


def adopted():
    for line in (STAGE / "summary.txt").read_text().splitlines():
        if "<- adopted" in line:
            return line.split()[0]
    raise SystemExit("stage2/summary.txt names no adopted law")


def declared_cells():
    """(budget, data) -> run ids of the stage's points declared for that cell (seed 0)."""
    before, declared = PLANS[STAGE_NUMBER]
    plan = tomllib.load(open(HERE / declared, "rb"))
    first = len(tomllib.load(open(HERE / before, "rb"))["points"])
    cells = {}
    for p in plan["points"][first:]:
        if p.get("seed", 0) == 0 and "-s" not in p["run_id"].rsplit("-d", 1)[-1]:
            cells.setdefault((float(p["budget"]), p["data"]), []).append(p["run_id"])
    return cells


def main():
    law = adopted()
    rows = {r["run_id"]: r for r in csv.DictReader(open(HERE / "results.csv"))}
    every = list(csv.DictReader(open(STAGE / "predictions.csv")))
    preds = {(float(p["budget"]), p["data"]): p for p in every if p["law"] == law}
    out, measured = [], {}
    for (c, d), ids in sorted(declared_cells().items()):
        done = [rows[i] for i in ids if i in rows]
        if len(done) < len(ids):
            so_far = ", ".join(f"{r['model']} {float(r['best_real_test_loss']):.4f}" for r in done)
            print(f"{c:.3g} {d}: {len(done)} of {len(ids)} declared runs trained; not scored yet"
                  + (f" (so far: {so_far})" if done else ""))
            continue
        best = min(done, key=lambda r: float(r["best_real_test_loss"]))
        loss = float(best["best_real_test_loss"])
        measured[(c, d)] = loss
        p = preds[(c, d)]
        err = {k: float(p[k]) - loss for k in ("loss", "no_growth", "trend")}
        out.append({"budget": f"{c:.3g}", "data": d, "best": f"{loss:.4f}", "model": best["model"],
                    "law": law, "predicted": p["loss"], "pi_low": p["pi_low"], "pi_high": p["pi_high"],
                    "error": f"{err['loss']:+.4f}",
                    "inside_pi": float(p["pi_low"]) <= loss <= float(p["pi_high"]),
                    "within_0.05": abs(err["loss"]) <= WITHIN,
                    "no_growth_error": f"{err['no_growth']:+.4f}", "trend_error": f"{err['trend']:+.4f}",
                    "beats_both_baselines": abs(err["loss"]) < min(abs(err["no_growth"]), abs(err["trend"]))})
    if not out:
        return
    with open(STAGE / "scored.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(out[0]))
        w.writeheader()
        w.writerows(out)
    print(" | ".join(out[0]))
    for r in out:
        print(" | ".join(str(v) for v in r.values()))
    print("every law's error (predicted − measured) at the scored cells:")
    for p in every:
        key = (float(p["budget"]), p["data"])
        if key in measured:
            inside = float(p["pi_low"]) <= measured[key] <= float(p["pi_high"])
            print(f"  {p['law']:<13} {key[0]:.3g} {key[1]:<8} {float(p['loss']) - measured[key]:+.4f}"
                  f"  {'inside' if inside else 'outside'} [{p['pi_low']}, {p['pi_high']}]")
    for c in sorted({c for c, _ in measured}):
        if (c, "all-1") in measured and (c, "all-1_2") in measured:
            want = float(preds[(c, "all-1")]["loss"]) - float(preds[(c, "all-1_2")]["loss"])
            got = measured[(c, "all-1")] - measured[(c, "all-1_2")]
            print(f"doubling 1/2 -> 1 at {c:.3g}: predicted {want:+.4f}, measured {got:+.4f}, "
                  f"error {want - got:+.4f}")
    if STAGE_NUMBER == "2":
        second_scoring(rows, measured)
    else:
        size_scoring(rows)


def second_scoring(rows, scored):
    """Sizes added after the first scoring (plan-3.toml): each run's loss beside its cell's."""
    later_plan = HERE / "plan-3.toml"
    if not later_plan.exists():
        return
    first = len(tomllib.load(open(HERE / "plan-2.toml", "rb"))["points"])
    for p in tomllib.load(open(later_plan, "rb"))["points"][first:]:
        r = rows.get(p["run_id"])
        cell = (float(p["budget"]), p["data"])
        if r is None:
            print(f"second scoring: {p['run_id']} not trained yet")
            continue
        loss = float(r["best_real_test_loss"])
        was = scored.get(cell)
        print(f"second scoring: {p['run_id']} {loss:.4f} at step {r['best_step']} of {r['steps']}"
              + (f"; the cell's first scoring {was:.4f}" if was is not None else ""))


def size_scoring(rows):
    """Each declared size's loss against `predict --sizes` in sizes.txt (its 'a run' interval)."""
    text = (STAGE / "sizes.txt").read_text()
    cell = None
    print("each declared size (predict --sizes; a run's 95% prediction interval):")
    for line in text.splitlines():
        head = re.match(r"## (\S+):", line)
        if head:
            cell = {"1/4": "all-1_4", "1/2": "all-1_2", "all": "all-1"}[head.group(1)]
        size = re.match(r"\s+N (\S+)\s.*loss (\S+) .*a run \S+ \[(\S+), (\S+)\]", line)
        if not size:
            continue
        n, loss, lo, hi = (float(v) for v in size.groups())
        run = next((r for r in rows.values() if r["data"] == cell and float(r["budget"]) == 2e14
                    and abs(float(r["n_nv"]) / n - 1) < 1e-3 and r["seed"] == "0"), None)
        if run is None:
            print(f"  {cell} N {n:.4g}: not trained yet (predicted {loss:.4f})")
            continue
        got = float(run["best_real_test_loss"])
        print(f"  {cell} {run['model']}: {got:.4f} at step {run['best_step']} of {run['steps']}; "
              f"predicted {loss:.4f} [{lo:.4f}, {hi:.4f}], error {loss - got:+.4f}"
              f"{'' if lo <= got <= hi else ' (outside)'}")


if __name__ == "__main__":
    main()
