#!/usr/bin/env bash
# The GPU acceptance check of the prefix LM's graph executor (docs/results/gpu.md records its
# table), for a binary built with `scripts/build-cuda.sh` and carried to a machine with one
# H100/H200. At most about 5 minutes:
#  1. `model executors`: the graph and GPU executors on the GPU (f32) against the cpu
#     executor on the CPU, same seeded weights and batch: loss, every gradient, logits,
#     KV-cached decoding;
#     and each fused op's kernels (nn/kernels/fused_ops.cu, AdamW's included) against its
#     CPU side;
#  2. a small corpus, tokenizer and token set made on the GPU, then 300 training steps of
#     d256/4L in f32 and in bf16 on it: the train and test losses side by side (within 1%);
#  3. `bench train --device cuda --reference`: ScaMo-44M and ScaMo-343M shapes beside
#     PyTorch eager bf16 and torch.compile on the same GPU (both ratios, MFU, PyTorch memory),
#     with the default (gpu) executor, then the graph executor's figures beside them;
#     `bench tokenizer --device cuda --reference` beside scripts/pytorch_vqvae_gpu.py;
#  4. sharing: 1 and 8 concurrent d256/4L batch-32 training processes on the GPU, aggregate
#     motion tokens/s;
#  5. `sweep run --devices cuda:0 --jobs-per-device 3` over a 6-point micro plan; every row
#     must say it ran on cuda:0.
#
#   BIN=target-cuda/release/motionscale SHARED=shared-copy OUT=$OUT bash scripts/gpu-check.sh
#
# SHARED: a copy of ../shared/bench (the PyTorch references) where the device machine can read
# it (`../shared` does not travel there: copy it into a git-excluded folder and carry it).
# Env: SKIP_BENCH=1 skips step 3 (the slowest, torch.compile included), SKIP_TOKENIZER_BENCH=1
# its tokenizer part, SKIP_SWEEP=1 step 5. Everything lands in
# $OUT (gpu-check.log, gpu-check.md, the JSON of every step).
set -uo pipefail
OUT=${OUT:-$PWD/gpu-check-out}
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
SHARED=$(realpath "${SHARED:-$REPO/../shared}")
mkdir -p "$OUT"
main() {
WORK=$(mktemp -d -t gpu-check.XXXXXX)
BIN=${BIN:?set BIN to the cuda-built motionscale}
source "$REPO/scripts/cuda-env.sh"
cuda_env || return $?
nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"
python3 -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda)' | tee "$OUT/torch.txt"
echo "binary: $("$BIN" --version)" | tee "$OUT/binary.txt"
M() { echo "+ motionscale $*" >&2; "$BIN" "$@"; }
D=cuda:0
FAIL=0

echo "== 1. executors"
M model executors --device $D --json > "$OUT/executors-d256.json" || FAIL=1
M model executors --device $D --width 512 --layers 8 --heads 8 --batch 16 --json \
  > "$OUT/executors-d512.json" || FAIL=1
cat "$OUT"/executors-*.json

echo "== 2. corpus, tokenizer, token set, 300 steps f32 vs bf16"
cd "$WORK"
M synth --clips 600 --seed 0 --mirror --out corpus > /dev/null
M embed-text --corpus corpus --fallback > /dev/null
M tokenizer train --corpus corpus --quantizer fsq --codebook 256 --width 64 --batch 64 --steps 300 \
  --device $D --out tok > /dev/null || FAIL=1
M tokenize --tokenizer tok --corpus corpus --device $D --out tokens > /dev/null || FAIL=1
for p in f32 bf16; do
  M train --tokens tokens --width 256 --layers 4 --heads 4 --tokens-budget 400000 --stop-after 300 \
    --eval-every 100 --device $D --precision $p --out lm-$p --json > "$OUT/train-$p.json" || FAIL=1
  cp lm-$p/evals.jsonl "$OUT/evals-$p.jsonl" 2>/dev/null
done

echo "== 3. benches beside PyTorch"
if [ -z "${SKIP_BENCH-}" ]; then
  (cd "$REPO" && M bench train --device $D --reference --json "$OUT/bench-train.json" \
    --gpu-reference-script "$SHARED/bench/gpu/pytorch_prefix_lm_gpu.py") || FAIL=1
  (cd "$REPO" && M bench train --device $D --executor graph --json "$OUT/bench-train-graph.json") || FAIL=1
  if [ -z "${SKIP_TOKENIZER_BENCH-}" ]; then
    (cd "$REPO" && M bench tokenizer --device $D --reference --json "$OUT/bench-tokenizer.json" \
      --bench-dir "$SHARED/bench") || FAIL=1
  fi
fi

echo "== 4. sharing one GPU"
share() { # $1 = processes
  local pids=()
  for i in $(seq 1 "$1"); do
    "$BIN" bench train --device $D --sizes 256x4@32 --min-time 8 --json "$OUT/share-$1-$i.json" \
      > /dev/null 2>&1 & pids+=($!)
  done
  wait "${pids[@]}"
}
share 1; share 8

echo "== 5. sweep over the GPU"
[ -n "${SKIP_SWEEP-}" ] || {
M sweep plan --corpus corpus --token-sets 256=tokens --vocabs 256 --budgets 3e10,1e11 \
  --models 32x1,64x1,64x2 --batch 16 --out plan.toml > /dev/null || FAIL=1
M sweep run --plan plan.toml --out sweep --devices $D --jobs-per-device 3 || FAIL=1
cp sweep/results.csv "$OUT/sweep-results.csv" 2>/dev/null
}

python3 - "$OUT" <<'EOF' || FAIL=1
import csv, glob, json, os, sys
out = sys.argv[1]
rows, ok = [], True
def row(*cells): rows.append("| " + " | ".join(str(c) for c in cells) + " |")
def check(name, passed, detail):
    global ok
    ok &= passed
    row(name, "pass" if passed else "**FAIL**", detail)
rows += ["| check | result | figures |", "|---|---|---|"]
for f in sorted(glob.glob(f"{out}/executors-*.json")):
    a = json.load(open(f))
    fused = a.get("fused_ops", [])
    worst = max(fused, key=lambda o: o[1]) if fused else ["none", 0.0]
    step = a.get("gpu_step", [0.0, 0.0, "none"])
    check(f"executors {os.path.basename(f)[10:-5]} (graph and gpu executors on {a['device']} vs cpu)",
          max(a["loss_relative"], a["gradient_relative"], a["logits_relative"], worst[1], step[0], step[1]) <= 1e-5,
          f"graph: loss {a['loss_relative']:.1e}, gradients {a['gradient_relative']:.1e} ({a['worst_weight']}), "
          f"logits {a['logits_relative']:.1e}, KV-cached max abs {a['cached_logits_max_abs']:.1e}; "
          f"gpu executor: loss {step[0]:.1e}, gradients {step[1]:.1e} ({step[2]}); "
          f"fused ops on the GPU vs CPU: worst {worst[1]:.1e} ({worst[0]}) over {len(fused)} outputs")
ev = {p: [json.loads(l) for l in open(f"{out}/evals-{p}.jsonl")] for p in ("f32", "bf16")
      if os.path.exists(f"{out}/evals-{p}.jsonl")}
if len(ev) == 2 and ev["f32"] and ev["bf16"]:
    a, b = ev["f32"][-1], ev["bf16"][-1]
    rel = lambda k: abs(b[k] - a[k]) / a[k] if k in a else abs(b["test"][k] - a["test"][k]) / a["test"][k]
    check(f"bf16 vs f32 after {a['step']} steps", rel("train_loss") <= 0.01 and rel("cross_entropy") <= 0.01,
          f"train {a['train_loss']:.4f} / {b['train_loss']:.4f}, test CE {a['test']['cross_entropy']:.4f} / "
          f"{b['test']['cross_entropy']:.4f}")
else:
    check("bf16 vs f32", False, "a training run did not finish")
if os.path.exists(f"{out}/bench-train-graph.json"):
    for t in json.load(open(f"{out}/bench-train-graph.json"))["train"]:
        row(f"bench d{t['d_model']}/{t['n_layers']}L B{t['batch']} {t['precision']}, graph executor", "",
            f"{t['motion_tokens_per_s']:.0f} tok/s (MFU {100*(t['mfu'] or float('nan')):.1f}%, fwd+bwd "
            f"{1e3*t['phase_median_s']['fwd_bwd']:.0f} ms, forward alone {1e3*t['phase_median_s'].get('fwd', float('nan')):.0f} ms, "
            f"AdamW {1e3*t['phase_median_s']['opt']:.0f} ms)")
if os.path.exists(f"{out}/bench-train.json"):
    for t in json.load(open(f"{out}/bench-train.json"))["train"]:
        r = t.get("reference", {})
        e, c = r.get("eager", {}), r.get("compiled", {})
        mem = e.get("result", {}).get("peak_mem_allocated_gib", float("nan"))
        row(f"bench d{t['d_model']}/{t['n_layers']}L B{t['batch']} {t['precision']}",
            f"{e.get('ratio', float('nan')):.2f}× eager, {c.get('ratio', float('nan')):.2f}× compiled",
            f"ours {t['motion_tokens_per_s']:.0f} tok/s (MFU {100*(t['mfu'] or float('nan')):.1f}%, fwd+bwd "
            f"{1e3*t['phase_median_s']['fwd_bwd']:.0f} ms, AdamW {1e3*t['phase_median_s']['opt']:.0f} ms); "
            f"PyTorch eager {e.get('result', {}).get('motion_tokens_per_s', float('nan')):.0f}, compiled "
            f"{c.get('result', {}).get('motion_tokens_per_s', float('nan')):.0f} tok/s; peak memory allocated: ours "
            f"{t.get('peak_gpu_memory_allocated_gib') or float('nan'):.2f} GiB, PyTorch eager {mem:.2f} GiB")
if os.path.exists(f"{out}/bench-tokenizer.json"):
    for t in json.load(open(f"{out}/bench-tokenizer.json"))["figures"]:
        row(f"bench tokenizer {t['quantizer']} B{t['batch']}", f"{t.get('ratio', float('nan')):.2f}× PyTorch eager",
            f"ours {t['steps_per_s']:.1f} steps/s, PyTorch {t.get('reference', {}).get('steps_per_s', float('nan')):.1f}")
share = {n: sum(json.load(open(f))["train"][0]["motion_tokens_per_s"] for f in glob.glob(f"{out}/share-{n}-*.json"))
         for n in (1, 8)}
if share[1] and share[8]:
    row("8 runs d256/4L B32 sharing the GPU", f"{share[8]/share[1]:.1f}× one run",
        f"aggregate {share[8]:.0f} vs {share[1]:.0f} motion tok/s (PyTorch eager 8.5×, candle composed 1.7× in ../shared/bench/gpu)")
if os.environ.get("SKIP_SWEEP"):
    pass
elif os.path.exists(f"{out}/sweep-results.csv"):
    res = list(csv.DictReader(open(f"{out}/sweep-results.csv")))
    check("sweep run --devices cuda:0", len(res) >= 6 and all(r["device"] == "cuda:0" for r in res),
          f"{len(res)} rows, devices {sorted({r['device'] for r in res})}")
else:
    check("sweep run --devices cuda:0", False, "no results.csv")
text = "\n".join(rows)
print(text)
open(f"{out}/gpu-check.md", "w").write(text + "\n")
sys.exit(0 if ok else 1)
EOF
cd "$REPO"; rm -rf "$WORK"
echo "== gpu-check: $([ $FAIL -eq 0 ] && echo PASS || echo FAIL)"
return $FAIL
}
main 2>&1 | tee "$OUT/gpu-check.log"
exit "${PIPESTATUS[0]}"
