#!/usr/bin/env bash
# The forgetting ladder of issue #59, resumable: `bash queue.sh MOTIONSCALE PHASE` from the folder
# holding bandai-synth/, cl/ (evaluator, scenarios, fits.json) and recipe/ladder/runs (the
# data-law ladder, the backbones). Start it once per core; each lane claims the next job not yet
# finished (cl/claims/<job>, cleared with `rm -r cl/claims` before a restart) and runs it at one
# thread. PHASE: ladder (3e11, 3e12, 3e13 × 4 methods × 3 seeds, rank 8), ranks (3e12, ranks 4
# and 16) or forward (4e13, declared in predictions.md before it runs).
set -u
motionscale=$1 phase=$2
models=16x1,24x1,32x1,48x1,64x1,96x1,64x2,96x2,128x2,160x2,128x4,160x4,192x4,256x4,320x4,384x4,512x4
jobs() {
  local budgets=$1 ranks=$2
  for budget in $budgets; do for rank in $ranks; do for seed in 0 1 2; do
    for method in es-moe seq-lora replay mtl; do
      echo "c$budget-r$rank-$method-s$seed $budget $rank $method $seed"
    done
  done; done; done
}
case $phase in
  ladder) list=$(jobs "3e11 3e12 3e13" 8) ;;
  ranks) list=$(jobs 3e12 "4 16") ;;
  forward) list=$(jobs 4e13 8) ;;
  *) echo "PHASE: ladder, ranks or forward" >&2; exit 2 ;;
esac
mkdir -p cl/claims cl/runs cl/logs
while read -r name budget rank method seed; do
  [ -f "cl/runs/$name/summary.json" ] && continue
  mkdir "cl/claims/$name" 2>/dev/null || continue
  start=$(date +%s)
  RAYON_NUM_THREADS=1 "$motionscale" continual --scenarios cl/scen-unseen --method "$method" \
    --fits cl/fits.json --budget "$budget" --models $models --sweep recipe/ladder/runs \
    --tokens recipe/ladder/runs/tokens/1024 --evaluator cl/evaluator --orders 3 --repeats 5 --mm-texts 0 --eval-learned-only \
    --tokens-share 0.025 --lora-rank "$rank" --lora-alpha $((2 * rank)) --seed "$seed" \
    --out "cl/runs/$name" >> "cl/logs/$name.log" 2>&1
  echo "$name rc $? $(( $(date +%s) - start )) s" >> cl/queue.log
done <<< "$list"
