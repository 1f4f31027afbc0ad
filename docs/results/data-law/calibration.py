"""Coverage of the forward 95% intervals in calibration.csv (standard library only).

    python3 docs/results/data-law/calibration.py [CSV]

Recomputes each row's `covered` from low <= observed <= high, exits 1 if that disagrees with
the CSV's column, and prints the share of intervals that held the truth: over all rows, per
interval kind, for the headline quantities alone (N_opt, D_opt, the loss at the optimum or the
best run) and for the per-run rows alone (ids with a `run-` field), per law (the id's last
field), and per kind within the headline rows.
"""
import csv
import os
import sys
from collections import defaultdict

path = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(os.path.abspath(__file__)), "calibration.csv")
rows = list(csv.DictReader(open(path, newline="")))
bad = []
for r in rows:
    inside = float(r["low"]) <= float(r["observed"]) <= float(r["high"])
    if ("yes" if inside else "no") != r["covered"]:
        bad.append(r["id"])
    r["inside"] = inside
    r["scope"] = "per-run" if any(f.startswith("run-") for f in r["id"].split(".")) else "headline"
    r["law"] = r["id"].split(".")[-1]


def share(label, group):
    k, n = sum(r["inside"] for r in group), len(group)
    print(f"{label:44s} {k:3d} of {n:3d}  ({100 * k / n:.0f}%)")


share("all rows", rows)
for key in ("interval_kind", "scope", "law"):
    groups = defaultdict(list)
    for r in rows:
        groups[r[key]].append(r)
    for name in sorted(groups):
        share(f"{key} = {name}", groups[name])
head = [r for r in rows if r["scope"] == "headline"]
groups = defaultdict(list)
for r in head:
    groups[r["interval_kind"]].append(r)
for name in sorted(groups):
    share(f"headline, interval_kind = {name}", groups[name])
if bad:
    print("covered column disagrees with low <= observed <= high:", ", ".join(bad))
    sys.exit(1)
