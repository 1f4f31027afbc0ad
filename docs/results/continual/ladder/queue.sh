#!/usr/bin/env bash
# The forgetting ladder of issue #59, resumable: `bash queue.sh MOTIONSCALE PHASE` from the folder
# holding bandai-synth/, cl/ (evaluator, scen-synth, fits.json) and recipe/ladder/runs (the
# data-law ladder's sweep, which holds the backbones). Start it once per core; each lane claims
# the next job not yet finished (cl/claims/<job>, cleared with `rm -r cl/claims` before a
# restart) and runs it at one thread. PHASE: ladder (1e11, 1e12, 3e12, 1e13 × 4 methods × 3
# seeds, rank 8), ranks (1e12, ranks 2 and 32, ES-MoE and SeqLoRA × 3 seeds) or forward (2e13 × 4
# methods × 3 seeds, forecast in forecast-2e13.json before it runs).
# Protocol: the backbone learns the captured (Bandai) clips only, sized by the data-law fit at
# their hours; its experts learn the six synthetic datasets, each step as many epochs of its
# clips as the backbone trained of its own; LoRA lr 1e-2 (chosen on validation CE), α = 2·rank.
set -u
motionscale=$1 phase=$2
models=16x1,24x1,32x1,48x1,64x1,96x1,64x2,96x2,128x2,160x2,128x4,160x4,192x4,256x4,320x4,384x4,512x4
jobs() {
  local budgets=$1 ranks=$2 methods=${3:-es-moe seq-lora replay mtl}
  for budget in $budgets; do for rank in $ranks; do for seed in 0 1 2; do
    for method in $methods; do
      echo "c$budget-r$rank-$method-s$seed $budget $rank $method $seed"
    done
  done; done; done
}
case $phase in
  ladder) list=$(jobs "1e11 1e12 3e12 1e13" 8) ;;
  ranks) list=$(jobs 1e12 "2 32" "es-moe seq-lora") ;;
  forward) list=$(jobs 2e13 8) ;;
  *) echo "PHASE: ladder, ranks or forward" >&2; exit 2 ;;
esac
mkdir -p cl/claims cl/runs cl/logs
while read -r name budget rank method seed; do
  [ -f "cl/runs/$name/summary.json" ] && continue
  mkdir "cl/claims/$name" 2>/dev/null || continue
  start=$(date +%s)
  RAYON_NUM_THREADS=1 "$motionscale" continual --scenarios cl/scen-synth --method "$method" \
    --fits cl/fits.json --budget "$budget" --models $models --backbone-data real \
    --sweep recipe/ladder/runs --tokens recipe/ladder/runs/tokens/1024 --evaluator cl/evaluator \
    --orders 3 --repeats 5 --mm-texts 0 --eval-learned-only --expert-epochs backbone --lr 1e-2 \
    --lora-rank "$rank" --lora-alpha $((2 * rank)) --seed "$seed" \
    --out "cl/runs/$name" >> "cl/logs/$name.log" 2>&1
  echo "$name rc $? $(( $(date +%s) - start )) s" >> cl/queue.log
done <<< "$list"
