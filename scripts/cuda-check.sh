#!/usr/bin/env bash
# Checks a motionscale binary built with `--features cuda` on a machine with an NVIDIA GPU:
#  1. finds the CUDA libraries the binary links (the driver's libcuda.so.1; cuBLAS, cuRAND and
#     the runtime, e.g. from a PyTorch install) and sets LD_LIBRARY_PATH;
#  2. `evaluator train` STEPS steps with `--device cuda`, then the same command with
#     `--device cpu`, same seed, a validation every step;
#  3. `evaluator embed` of the test split with the GPU-trained weights on both devices;
#  4. prints both loss logs side by side and the largest embedding difference; all in $OUT.
#
#   BIN=path/to/motionscale[.gz] CORPUS=corpus OUT=out bash scripts/cuda-check.sh
#
# CORPUS: any small corpus with caption embeddings (e.g. `motionscale synth --clips 120` and
# `motionscale embed-text --fallback`). Env: STEPS=20 BATCH=64 SEED=0 RUN_TIMEOUT=150.
# docs/results/cuda.md has the run on an H100.
set -uo pipefail
OUT=${OUT:-$PWD/cuda-check-out}
STEPS=${STEPS:-20}
BATCH=${BATCH:-64}
SEED=${SEED:-0}
RUN_TIMEOUT=${RUN_TIMEOUT:-150}
mkdir -p "$OUT"
main() {
WORK=$(mktemp -d -t cuda-check.XXXXXX)
echo "== work dir $WORK, out $OUT, steps $STEPS, batch $BATCH, seed $SEED"

# ---- 1. binary and CUDA libraries (scripts/cuda-env.sh)
source "$(dirname "${BASH_SOURCE[0]}")/cuda-env.sh"
cuda_env || return $?

# ---- 2. GPU
echo "== nvidia-smi -L"; nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.used,memory.total --format=csv

# ---- corpus (copied: the runs write nothing into the given one)
cp -r "${CORPUS:?set CORPUS to a corpus with caption embeddings}" "$WORK/corpus"
CORPUS=$WORK/corpus

device_of() { [ "$1" = gpu ] && echo cuda || echo cpu; }

run_train() { # $1 = gpu|cpu
  local tag=$1
  echo "== evaluator train on $tag"
  local t0=$(date +%s.%N)
  RUST_BACKTRACE=1 timeout "$RUN_TIMEOUT" "$BIN" evaluator train --corpus "$CORPUS" --out "$WORK/ev-$tag" \
      --steps "$STEPS" --eval-every 1 --batch "$BATCH" --seed "$SEED" --device "$(device_of "$tag")" \
      > "$OUT/train-$tag.out" 2>&1
  local rc=$?
  local t1=$(date +%s.%N)
  cat "$OUT/train-$tag.out"
  echo "train-$tag rc=$rc wall=$(python3 -c "print(round($t1-$t0,1))")s"
  mkdir -p "$OUT/ev-$tag"
  cp "$WORK/ev-$tag"/{log.jsonl,config.json} "$OUT/ev-$tag/" 2>/dev/null
  return $rc
}

# ---- 3a. GPU run, with a memory/utilisation monitor (evidence the GPU was really used)
nvidia-smi --query-gpu=timestamp,memory.used,utilization.gpu --format=csv -lms 500 > "$OUT/gpu-monitor.csv" 2>&1 &
MON=$!
( while sleep 1; do nvidia-smi --query-compute-apps=pid,process_name,used_memory --format=csv,noheader; done ) \
  > "$OUT/gpu-apps.txt" 2>&1 &
APPS=$!
run_train gpu
GPU_RC=$?
kill "$MON" "$APPS" 2>/dev/null; wait "$MON" "$APPS" 2>/dev/null
echo "peak GPU memory.used during the GPU run (MiB): $(awk -F', ' 'NR>1{gsub(/ MiB/,"",$2); if($2+0>m)m=$2+0} END{print m+0}' "$OUT/gpu-monitor.csv")"
echo "compute apps seen: $(sort -u "$OUT/gpu-apps.txt" | grep -c motionscale) motionscale line(s)"; sort -u "$OUT/gpu-apps.txt" | head -5

# ---- 3b. CPU run (same binary)
run_train cpu
CPU_RC=$?

# ---- 4. forward pass of the GPU-trained weights on both devices
if [ $GPU_RC -eq 0 ]; then
  for tag in gpu cpu; do
    echo "== evaluator embed (GPU-trained weights) on $tag"
    RUST_BACKTRACE=1 timeout "$RUN_TIMEOUT" "$BIN" evaluator embed --evaluator "$WORK/ev-gpu" --motions "$CORPUS" \
        --split test --device "$(device_of "$tag")" --out "$OUT/embed-$tag" > "$OUT/embed-$tag.out" 2>&1
    echo "embed-$tag rc=$?"; tail -5 "$OUT/embed-$tag.out"
  done
fi

# ---- 5. comparison
echo "== loss logs (log.jsonl: one validation per step; train_loss = that step's loss)"
python3 - "$OUT" <<'EOF'
import ast, json, os, struct, sys
out = sys.argv[1]
def log(tag):
    p = os.path.join(out, f"ev-{tag}", "log.jsonl")
    return [json.loads(l) for l in open(p)] if os.path.exists(p) else []
g, c = log("gpu"), log("cpu")
keys = ["train_loss", "r_precision_top1", "emotion_accuracy", "action_accuracy"]
print(f"{'step':>4} {'gpu train_loss':>15} {'cpu train_loss':>15} {'|diff|':>10}   gpu/cpu R@1")
worst = 0.0
for i in range(max(len(g), len(c))):
    a = g[i] if i < len(g) else {}
    b = c[i] if i < len(c) else {}
    la, lb = a.get("train_loss"), b.get("train_loss")
    d = abs(la - lb) if la is not None and lb is not None else float("nan")
    if d == d: worst = max(worst, d)
    fmt = lambda v: f"{v:15.6f}" if isinstance(v, (int, float)) else f"{'-':>15}"
    print(f"{a.get('step', b.get('step', i+1)):>4} {fmt(la)} {fmt(lb)} {d:10.2e}   {a.get('r_precision_top1','-')}/{b.get('r_precision_top1','-')}")
print(f"steps logged: gpu {len(g)}, cpu {len(c)}; max |train_loss diff| {worst:.3e}")
if g and c and all(x.get("train_loss") == y.get("train_loss") for x, y in zip(g, c)):
    print("NOTE: bit-identical losses: the 'GPU' run probably fell back to the CPU (check gpu-monitor.csv)")
def npy(p):
    with open(p, "rb") as f:
        assert f.read(6) == b"\x93NUMPY"
        major = f.read(2)[0]
        n = struct.unpack("<H" if major == 1 else "<I", f.read(2 if major == 1 else 4))[0]
        h = ast.literal_eval(f.read(n).decode())
        assert h["descr"] == "<f4", h
        data = f.read()
        return h["shape"], struct.unpack(f"<{len(data)//4}f", data)
for name in ["motion_embeddings.npy", "text_embeddings.npy"]:
    pg, pc = (os.path.join(out, f"embed-{t}", name) for t in ("gpu", "cpu"))
    if os.path.exists(pg) and os.path.exists(pc):
        (sg, vg), (sc, vc) = npy(pg), npy(pc)
        m = max((abs(x - y) for x, y in zip(vg, vc)), default=float("nan"))
        print(f"embed {name}: shape gpu {sg} cpu {sc}; max |gpu-cpu| {m:.3e} (same weights)")
EOF
echo "== rc: train gpu=$GPU_RC cpu=$CPU_RC"
rm -rf "$WORK"
[ "$GPU_RC" -eq 0 ] && [ "$CPU_RC" -eq 0 ]
}
main 2>&1 | tee "$OUT/check.log"
