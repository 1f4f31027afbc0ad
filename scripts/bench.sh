#!/usr/bin/env bash
# Every stage's speed beside its reference, measured in one run on this machine, as JSON in
# OUT (docs/results/bench/ for docs/results/bench.md):
#
#   scripts/bench.sh OUT CORPUS HUMANML3D_DIR
#
# CORPUS: a corpus whose captions the caption-embedding bench embeds;
# HUMANML3D_DIR: a checkout of EricGuo5513/HumanML3D (the ingest bench's reference).
# Needs torch, transformers and scipy (pip) and the MiniLM encoder
# (scripts/fetch-text-encoder.sh). Run it on a quiet machine: each figure records the CPU
# share other processes took meanwhile (foreign_cpu_fraction). Where perf is installed, it
# ends with scripts/profile-cpu.sh on four stages (OUT/profile-*; about 4 minutes more).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/bench.sh OUT CORPUS HUMANML3D_DIR}
corpus=${2:?usage: scripts/bench.sh OUT CORPUS HUMANML3D_DIR}
humanml3d=${3:?usage: scripts/bench.sh OUT CORPUS HUMANML3D_DIR}
mkdir -p "$out"
cargo build --release --quiet -p motionscale
b=target/release/motionscale
{
  echo "revision $(git describe --always --dirty --abbrev=12)"
  echo "date $(date -u +%Y-%m-%dT%H:%MZ)"
  lscpu | grep -E '^(Model name|CPU\(s\)):'
  python3 -c 'import torch, transformers, scipy; print("torch", torch.__version__, "transformers", transformers.__version__, "scipy", scipy.__version__)'
} | tee "$out/machine.txt"
$b bench ingest --reference "$humanml3d" --json "$out/ingest.json"
$b bench tokenizer --reference --json "$out/tokenizer.json"
$b bench train --reference --json "$out/train.json"
$b bench embed --corpus "$corpus" --reference --json "$out/embed.json"
$b bench fit --reference --json "$out/fit.json"
$b bench evaluator --reference --json "$out/evaluator.json"
$b bench ctvae --reference --json "$out/ctvae.json"
if command -v perf >/dev/null; then
  scripts/profile-cpu.sh "$out/profile-train-d256" > /dev/null
  scripts/profile-cpu.sh "$out/profile-train-d512" train --sizes 512x8 --no-generate --min-time 10 > /dev/null
  scripts/profile-cpu.sh "$out/profile-tokenizer-fsq64" tokenizer --quantizers fsq --batches 64 --reps 20 > /dev/null
  scripts/profile-cpu.sh "$out/profile-evaluator" evaluator --reps 60 > /dev/null
  rm -f "$out"/profile-*/perf.data
else
  echo "perf not found: no profiles (Debian: apt-get install linux-perf)" >&2
fi
