#!/usr/bin/env bash
# The data-law pilot's fits from its results.csv:
#   bash docs/results/data-law/fits.sh MOTIONSCALE RESULTS_CSV OUT_DIR
# 1. per data subset: the IsoFLOP fit on the validation-selected test L_u (N_opt per budget);
# 2. every run: the data-constrained L(N, D') with R* and the exchange rate of synthetic data,
#    on the validation-selected test cross-entropy of the captured clips (fits.json);
# 3. the same with early stopping: the law on the selected checkpoints' tokens beside a
#    stopping rule (fits-early-stopping.json; early-stopping/README.md says why).
set -euo pipefail
B=$1 RESULTS=$2 OUT=$3
mkdir -p "$OUT/subsets"
python3 - "$RESULTS" "$OUT/subsets" <<'PY'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
by = {}
for r in rows:
    by.setdefault(r["data"], []).append(r)
for name, rs in by.items():
    with open(f"{sys.argv[2]}/{name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rs)
PY
for csv in "$OUT"/subsets/*.csv; do
  name=$(basename "$csv" .csv)
  "$B" fit --results "$csv" --out "$OUT/subsets/$name" --loss-col best_norm_test_loss \
    --param-loss-col best_real_test_loss --bootstrap 200 > "$OUT/subsets/$name.txt"
done
"$B" fit --results "$RESULTS" --out "$OUT/all" --loss-col best_norm_test_loss \
  --param-loss-col best_real_test_loss --repeated-data --bootstrap 200 > "$OUT/all.txt"
cp "$OUT/all/fits.json" "$OUT/fits.json"
"$B" fit --results "$RESULTS" --out "$OUT/all-early-stopping" --loss-col best_norm_test_loss \
  --param-loss-col best_real_test_loss --repeated-data --early-stopping --bootstrap 200 \
  > "$OUT/all-early-stopping.txt"
cp "$OUT/all-early-stopping/fits.json" "$OUT/fits-early-stopping.json"
