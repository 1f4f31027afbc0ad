#!/usr/bin/env bash
# The main job on the built-in default data: write the demo BVH clips, ingest them into a
# corpus, verify it and export the HumanML3D layout. Outputs land in runs/quickstart/.
set -euo pipefail
cd "$(dirname "$0")/.."
out=runs/quickstart
cargo build --release --quiet
bin=target/release/motionscale
"$bin" demo --out "$out/inputs"
"$bin" ingest --source "bvh:$out/inputs" --out "$out/corpus" --mirror
"$bin" corpus verify "$out/corpus"
"$bin" corpus stats "$out/corpus"
"$bin" export hml3d "$out/corpus" "$out/humanml3d"
"$bin" export bvh "$out/corpus" demo_walk "$out/demo_walk.bvh"
echo "quickstart done: corpus in $out/corpus, HumanML3D layout in $out/humanml3d"
