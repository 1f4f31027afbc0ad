#!/usr/bin/env bash
# The law engine on ScaleBench's tables (each task's train split → its held-out split) and
# on this project's own IsoFLOP study; writes OUT/<task>/laws.json and OUT/<task>.txt.
#   bash docs/results/law-benchmarks/run.sh [BINARY] [OUT]
set -euo pipefail
M=${1:-target/release/motionscale}; OUT=${2:-docs/results/law-benchmarks}
SB=../shared/data/scalebench
fit() { local task=$1; shift; "$M" fit --law all --out "$OUT/$task" "$@" | tee "$OUT/$task.txt"; }
fit data_con --results $SB/data_constrained_scaling_law-train.parquet \
  --test $SB/data_constrained_scaling_law-test.parquet --n-col params --d-col tokens --loss-col loss
fit vocab --results $SB/vocab_scaling_law-train.parquet --test $SB/vocab_scaling_law-test.parquet \
  --n-col non_vocab_parameters --nv-col vocab_size --d-col num_characters \
  --loss-col unigram_normalized_loss
fit farseer --results $SB/farseer_scaling_law-train.parquet \
  --test $SB/farseer_scaling_law-test.parquet --n-col N --d-col D --loss-col loss
# The 154-run motion study (docs/results/scaling-law.md): each budget left out in turn.
fit scaling-law --results docs/results/scaling-law/results.csv --select budget \
  --loss-col norm_test_loss
