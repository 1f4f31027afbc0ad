#!/bin/bash
# The outputs of a fixed set of small commands, hashed: a refactor that claims byte-identical
# outputs runs this with the binary before and after and compares the two lists.
#
#   bash scripts/output-hashes.sh BINARY BANDAI_SET_1_DIR OUT_DIR   # writes OUT_DIR/sha256.txt
#
# One thread, fixed seeds, the fallback text embedding (no download). Files that record a wall
# time or a revision are hashed with those fields removed (`timing-free`), so the list compares
# what the commands computed.
set -euo pipefail
M=$(realpath "$1"); BANDAI=$(realpath "$2"); OUT=$3
REPO=$(cd "$(dirname "$0")/.." && pwd)
rm -rf "$OUT"; mkdir -p "$OUT"; cd "$OUT"
export RAYON_NUM_THREADS=1
run() { echo "+ motionscale $*" >&2; "$M" "$@"; }

# Exit status 2: some inputs were rejected (listed in corpus/rejects.jsonl, hashed below).
run ingest --source "bvh:$BANDAI" --source synth:300:3 --mirror --out corpus || [ $? -eq 2 ]
run embed-text --corpus corpus --fallback --fallback-dim 32
run tokenizer train --corpus corpus --quantizer fsq --codebook 256 --width 32 --batch 16 \
    --steps 200 --out tok
run tokenize --tokenizer tok --corpus corpus --out tokens
run train --tokens tokens --preset cpu-50K --vocab 240 --tokens-budget 60000 --batch 8 --out lm
run generate --model lm --tokenizer tok --text "a person walks forward" --seed 1 --out gen.npy
run generate --model lm --tokenizer tok --text "a person walks forward" --seed 1 --out gen.bvh
run evaluator train --corpus corpus --out evaluator --hidden 16 --embed-dim 16 --max-frames 64 \
    --batch 16 --steps 200 --eval-every 100
run generate --model lm --tokenizer tok --captions-from corpus --split test --out gen-test
run eval --evaluator evaluator --motions gen-test --corpus corpus --repeats 2 --out eval.json
run fit --results "$REPO/docs/results/scaling-sweep/results.csv" --bootstrap 20 \
    --workers 1 --out fit
run predict --fits fit/fits.json --budget 1e15 --json > predict-fits.json
run predict --preset scamo --budget 1e18 --json > predict-scamo.json
run scenarios --corpus corpus --split unseen --source synth --out scenarios
run continual --scenarios scenarios --method seq-lora --base lm --tokens tokens \
    --evaluator evaluator --orders 1 --tokens-budget 400 --batch 8 --repeats 1 --pool 8 \
    --mm-texts 2 --eval-split train --out continual
run cl2gen --corpus corpus --evaluator evaluator --source synth --min-clips 10 --layers 1 \
    --hidden 8 --latent 4 --steps-per-task 20 --batch 4 --samples-per-class 4 --min-frames 12 \
    --max-frames 20 --repeats 1 --out cl2gen
run cl2gen --corpus corpus --evaluator evaluator --source synth --min-clips 10 --layers 1 \
    --hidden 8 --latent 4 --steps-per-task 20 --batch 4 --samples-per-class 4 --min-frames 12 \
    --max-frames 20 --repeats 1 --replay 1/2 --out cl2gen-gen-replay
run cl2gen --corpus corpus --evaluator evaluator --source synth --min-clips 10 --layers 1 \
    --hidden 8 --latent 4 --steps-per-task 20 --batch 4 --samples-per-class 4 --min-frames 12 \
    --max-frames 20 --repeats 1 --replay 1/2 --replay-source real --out cl2gen-real-replay

# Fields that differ between two runs of the same binary on the same inputs.
strip='walk(if type == "object" then del(.wall_s, .train_s, .elapsed_s, .seconds, .revision,
       .created, .started, .finished, .tokens_per_s, .steps_per_s) else . end)'
find . -type f ! -name sha256.txt ! -name '*.log' ! -name '*.lock' | sort | while read -r f; do
  if [[ $f == *.json ]] && jq -e . "$f" > /dev/null 2>&1; then
    echo "$(jq -cS "$strip" "$f" | sha256sum | cut -c1-64)  $f (timing-free)"
  elif [[ $f == *.jsonl ]]; then
    echo "$(jq -cS "$strip" "$f" | sha256sum | cut -c1-64)  $f (timing-free)"
  else
    sha256sum "$f"
  fi
done > sha256.txt
wc -l < sha256.txt
