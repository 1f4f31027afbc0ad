"""The tokenizer's training step in PyTorch on a GPU: the T2M-GPT-shape VQ-VAE / FSQ-VAE of
pytorch_vqvae.py in --bench-dir (../shared/bench; imported, not copied), its loss and AdamW,
on CUDA, each step timed between synchronisations. `motionscale bench tokenizer --device cuda
--reference` runs it in the same invocation and prints the ratio.

    python3 scripts/pytorch_vqvae_gpu.py --bench-dir ../shared/bench --quant fsq --batch 256 --out fig.json
"""
import argparse
import json
import os
import statistics
import sys
import time

import torch
import torch.nn.functional as F


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--quant", choices=["vq", "fsq"], default="fsq")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--out", required=True)
    ap.add_argument("--bench-dir", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                        "..", "..", "shared", "bench"))
    args = ap.parse_args()
    sys.path.insert(0, os.path.abspath(args.bench_dir))
    from pytorch_vqvae import MotionVQVAE, count_macs
    if not torch.cuda.is_available():
        raise SystemExit("CUDA is not available")
    dev = torch.device("cuda")
    torch.manual_seed(0)
    model = MotionVQVAE(args.quant).to(dev)
    model.train()
    x = torch.randn(args.batch, args.frames, 263, device=dev)
    macs, _ = count_macs(model, x)
    if args.quant == "vq":
        model.quant.initted = False
    opt = torch.optim.AdamW(model.parameters(), lr=2e-4, betas=(0.9, 0.99), weight_decay=0.0)

    def step():
        opt.zero_grad(set_to_none=True)
        pred, commit, _ = model(x)
        vp = pred[:, 1:, 4:67] - pred[:, :-1, 4:67]
        vg = x[:, 1:, 4:67] - x[:, :-1, 4:67]
        loss = F.smooth_l1_loss(pred, x) + 0.02 * commit + 0.5 * F.smooth_l1_loss(vp, vg)
        loss.backward()
        opt.step()

    for _ in range(args.warmup):
        step()
    torch.cuda.synchronize()
    times = []
    for _ in range(args.reps):
        t0 = time.perf_counter()
        step()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    median = statistics.median(times)
    flops = 6 * (macs["conv"] + macs["linear"])
    out = {
        "impl": "pytorch", "device": torch.cuda.get_device_name(0), "torch_version": torch.__version__,
        "quant": args.quant, "batch": args.batch, "frames": args.frames,
        "step_time": {"median_s": median, "min_s": min(times), "max_s": max(times), "n": len(times)},
        "steps_per_s": 1.0 / median, "frames_per_s": args.batch * args.frames / median,
        "model_flops_per_step": flops, "achieved_tflops": flops / median / 1e12,
        "peak_mem_allocated_gib": torch.cuda.max_memory_allocated() / 2**30,
    }
    with open(args.out, "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
