"""Re-select each captured-only (`dreal`) run's checkpoint on the captured validation clips.

The sweep selects every run's checkpoint on the whole validation split (captured and
synthetic clips). A run trained on captured clips only is then selected partly on synthetic
clips it never saw. This reads each run's `train/evals.jsonl` and prints, per run, the step
selected on the whole split and on its captured clips, and the captured test CE at each:
    python3 docs/results/data-law/reselect.py RUNS_DIR > selection.csv
"""
import csv
import glob
import json
import os
import sys

runs = sys.argv[1]
out = csv.writer(sys.stdout)
out.writerow(["run_id", "step_all_val", "step_real_val", "real_test_ce_all_val",
              "real_test_ce_real_val", "gain"])
for path in sorted(glob.glob(os.path.join(runs, "*-dreal-*", "train", "evals.jsonl"))):
    run_id = path.split(os.sep)[-3]
    evals = [e for e in map(json.loads, open(path)) if e.get("val")]
    on_all = min(evals, key=lambda e: e["val"]["cross_entropy"])
    on_real = min(evals, key=lambda e: e["val"]["by_origin"]["real"]["cross_entropy"])
    ce = lambda e: e["test"]["by_origin"]["real"]["cross_entropy"]
    out.writerow([run_id, on_all["step"], on_real["step"], f"{ce(on_all):.4f}",
                  f"{ce(on_real):.4f}", f"{ce(on_all) - ce(on_real):.4f}"])
