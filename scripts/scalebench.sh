#!/usr/bin/env bash
# ScaleBench (arXiv 2604.22753; ../shared/data/scalebench): for data_con, vocab and farseer,
# every law family fitted to the train split (the family chosen on it alone) and scored on the
# held-out split, then the design replays at 1%, 5% and 10% of the pool's cost over 10 seeds,
# printed beside the paper's Table 2; then, with each budget left out in turn, N_opt by parabola
# vertices and by VPNLS and the vocabulary by per-vocabulary parabolas and by the vocabulary
# laws, on our two studies and on ScaleBench's farseer table.
#   bash scripts/scalebench.sh [BINARY] [OUT]     # writes OUT/<task>{,-replay-<law>}.txt and JSON
set -euo pipefail
cd "$(dirname "$0")/.."
M=${1:-target/release/motionscale}; OUT=${2:-docs/results/law-benchmarks}
SB=${SCALEBENCH:-../shared/data/scalebench}
mkdir -p "$OUT"
declare -A COLS=(
  [data_constrained]="--n-col params --d-col tokens --loss-col loss"
  [vocab]="--n-col non_vocab_parameters --nv-col vocab_size --d-col num_characters --loss-col unigram_normalized_loss"
  [farseer]="--n-col N --d-col D --loss-col loss"
)
declare -A LAWS=([data_constrained]="data-constrained" [vocab]="vocab-effective vocab" [farseer]="farseer")
for task in data_constrained vocab farseer; do
  split() { echo "$SB/${task}_scaling_law-$1.parquet"; }
  # shellcheck disable=SC2086
  "$M" fit --law all --results "$(split train)" --test "$(split test)" ${COLS[$task]} \
    --out "$OUT/$task" | tee "$OUT/$task.txt"
  for law in ${LAWS[$task]}; do
    # shellcheck disable=SC2086
    "$M" fit --law "$law" --results "$(split train)" --test "$(split test)" ${COLS[$task]} \
      --replay 0.01,0.05,0.1 --replay-seeds 10 --out "$OUT/$task-replay-$law" \
      | tee "$OUT/$task-replay-$law.txt"
  done
done
# Each budget left out: the 154-run scaling-law study, the data-law study's full-data runs
# (its subsets differ in data, so they are not pooled) and ScaleBench's farseer train split.
python3 - docs/results/data-law/results.csv "$OUT/data-law-all-1.csv" <<'PY'
import csv, sys
rows = [r for r in csv.DictReader(open(sys.argv[1])) if r["data"] == "all-1"]
with open(sys.argv[2], "w", newline="") as f:
    w = csv.DictWriter(f, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
PY
lobo() { local name=$1; shift; "$M" fit --law all --select budget "$@" --out "$OUT/$name" | tee "$OUT/$name.txt"; }
lobo scaling-law --results docs/results/scaling-law/results.csv --loss-col norm_test_loss
lobo data-law-all-1 --results "$OUT/data-law-all-1.csv" --loss-col best_real_test_loss
# shellcheck disable=SC2086
lobo farseer-lobo --results "$SB/farseer_scaling_law-train.parquet" ${COLS[farseer]}
echo
echo "ScaleBench Table 2 (target-region R² at 1% / 5% / 10%):"
sed -n '/^| task | Random/,/^| farseer/p' "$SB/README.md"
