#!/usr/bin/env bash
# Where a GPU training step of the prefix LM spends its time: `bench train --device cuda` at
# ScaMo's 44M and 343M shapes under Nsight Systems (`nsys`, when the machine has it), and the
# GPU kernels summed by name (time, calls), the top ones printed. For a binary built with
# `scripts/build-cuda.sh`, on the GPU machine:
#
#   BIN=target-cuda/release/motionscale OUT=$OUT bash scripts/gpu-profile.sh
#
# Writes $OUT/profile-<shape>.csv (nsys's cuda_gpu_kern_sum) and $OUT/profile.md; exits 2
# when no nsys is found (nothing else is needed from it).
set -uo pipefail
OUT=${OUT:-$PWD/gpu-profile-out}
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
mkdir -p "$OUT"
WORK=$(mktemp -d -t gpu-profile.XXXXXX)
source "$REPO/scripts/cuda-env.sh"
cuda_env || exit $?
NSYS=$(command -v nsys || ls /usr/local/cuda*/bin/nsys /opt/nvidia/nsight-systems*/bin/nsys 2>/dev/null | head -1)
[ -n "$NSYS" ] || { echo "no nsys on this machine"; exit 2; }
echo "nsys: $NSYS ($("$NSYS" --version))"
for shape in 512x8@256 1024x24@128; do
  "$NSYS" profile -t cuda --force-overwrite true -o "$WORK/prof-$shape" \
    "$BIN" bench train --device cuda:0 --sizes "$shape" --min-time 3 > "$WORK/bench-$shape.txt" 2>&1
  grep '^train' "$WORK/bench-$shape.txt"
  "$NSYS" stats --report cuda_gpu_kern_sum --format csv --output "$WORK/sum-$shape" \
    "$WORK/prof-$shape.nsys-rep" > /dev/null 2>&1
  cp "$WORK/sum-$shape"*.csv "$OUT/profile-$shape.csv" 2>/dev/null
done
python3 - "$OUT" <<'PY'
import csv, glob, os, sys
out, lines = sys.argv[1], []
for f in sorted(glob.glob(f"{out}/profile-*.csv")):
    rows = list(csv.DictReader(open(f)))
    total = sum(float(r["Total Time (ns)"]) for r in rows)
    calls = sum(int(r["Instances"]) for r in rows)
    lines += [f"### {os.path.basename(f)[8:-4]}: {total/1e6:.0f} ms of GPU kernels, {calls} launches",
              "", "| kernel | share | ms | launches |", "|---|---|---|---|"]
    for r in rows[:25]:
        t = float(r["Total Time (ns)"])
        lines.append(f"| `{r['Name'][:70]}` | {100*t/total:.1f}% | {t/1e6:.1f} | {r['Instances']} |")
    lines.append("")
text = "\n".join(lines)
print(text)
open(f"{out}/profile.md", "w").write(text + "\n")
PY
rm -rf "$WORK"
