"""Scores stage 2's pre-registered predictions (stage2/predictions.csv, committed before the
runs) on the cells trained since: a cell's loss is the best captured test CE
(`best_real_test_loss`) over the sizes declared for it in plan-2.toml (seed 0).

    python3 score2.py            # prints the table, writes stage2/scored.csv
"""
import csv, pathlib, tomllib

HERE = pathlib.Path(__file__).resolve().parent
STAGE2 = HERE / "stage2"
WITHIN = 0.05


def adopted():
    for line in (STAGE2 / "summary.txt").read_text().splitlines():
        if "<- adopted" in line:
            return line.split()[0]
    raise SystemExit("stage2/summary.txt names no adopted law")


def declared_cells():
    """(budget, data) -> run ids of the stage-2 points declared for that cell (seed 0)."""
    plan = tomllib.load(open(HERE / "plan-2.toml", "rb"))
    first = len(tomllib.load(open(HERE / "plan-1.toml", "rb"))["points"])
    cells = {}
    for p in plan["points"][first:]:
        if p.get("seed", 0) == 0 and "-s" not in p["run_id"].rsplit("-d", 1)[-1]:
            cells.setdefault((float(p["budget"]), p["data"]), []).append(p["run_id"])
    return cells


def main():
    law = adopted()
    rows = {r["run_id"]: r for r in csv.DictReader(open(HERE / "results.csv"))}
    every = list(csv.DictReader(open(STAGE2 / "predictions.csv")))
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
    with open(STAGE2 / "scored.csv", "w", newline="") as f:
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
    second_scoring(rows, measured)


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


if __name__ == "__main__":
    main()
