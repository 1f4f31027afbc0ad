"""Load a motionscale prefix LM into the PyTorch reference `PrefixLM` and compare logits.

Usage: python3 scripts/torch-check-lm.py RUN_DIR LOGITS_DIR [REFERENCE_DIR]

RUN_DIR is a `motionscale train --out` folder; LOGITS_DIR holds what
`motionscale model logits --model RUN_DIR --out LOGITS_DIR` wrote for a few clips (the text
embeddings fed as the prefix, the motion inputs [BOS, m0, …] and our logits). The script builds
`PrefixLM` from `../shared/bench/pytorch_prefix_lm.py` (REFERENCE_DIR overrides the folder)
with the run's width, layers, heads, SwiGLU width and vocabulary, loads `model.safetensors`
with `load_state_dict(strict=True)` (every key and shape must match), runs each clip through it
and prints the largest absolute logit difference and the share of equal arg-max tokens. It
exits 1 when a difference exceeds 1e-3. Needs torch, numpy and safetensors.
"""
import importlib.util
import json
import os
import sys

import numpy as np
import torch
from safetensors.torch import load_file

TOLERANCE = 1e-3


def reference_module(folder):
    path = os.path.join(folder, "pytorch_prefix_lm.py")
    sys.path.insert(0, folder)  # it imports its neighbour `common`
    spec = importlib.util.spec_from_file_location("pytorch_prefix_lm", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def configure(ref, model, prefix_len, motion_len):
    """Point the reference's module-level sequence constants and buffers at one clip's shape."""
    ref.N_PREFIX, ref.N_MOTION = prefix_len, motion_len
    cos, sin = ref.rope_tables(prefix_len + motion_len, model.d // model.n_heads)
    model.cos, model.sin = cos, sin
    model.mask = ref.prefix_lm_mask(prefix_len, motion_len)


def main():
    run_dir, logits_dir = sys.argv[1:3]
    here = os.path.dirname(os.path.abspath(__file__))
    folder = sys.argv[3] if len(sys.argv) > 3 else os.path.join(here, "..", "..", "shared", "bench")
    ref = reference_module(folder)
    c = json.load(open(os.path.join(run_dir, "config.json")))["model"]
    vocab = c["codebook_size"] + 3
    ref.PREFIX_DIM = c["text_dim"]
    torch.manual_seed(0)
    model = ref.PrefixLM(d=c["d_model"], n_layers=c["n_layers"], n_heads=c["n_heads"],
                         ffn_hidden=c["ffn_hidden"], vocab=vocab)
    for norm in [model.norm] + [m for b in model.blocks for m in (b.n1, b.n2)]:
        norm.eps = c["norm_eps"]
    model.load_state_dict(load_file(os.path.join(run_dir, "model.safetensors")), strict=True)
    model.eval()
    clips = [json.loads(line) for line in open(os.path.join(logits_dir, "clips.jsonl"))]
    largest, same, positions = 0.0, 0, 0
    with torch.no_grad():
        for k, clip in enumerate(clips):
            text = np.load(os.path.join(logits_dir, f"clip-{k}-text.npy"))
            ours = np.load(os.path.join(logits_dir, f"clip-{k}-logits.npy"))
            inputs = torch.tensor([clip["inputs"]], dtype=torch.long)
            configure(ref, model, clip["prefix_len"], inputs.shape[1])
            theirs = model(torch.from_numpy(text)[None], inputs)[0].numpy()
            largest = max(largest, float(np.abs(theirs - ours).max()))
            same += int((theirs.argmax(-1) == ours.argmax(-1)).sum())
            positions += ours.shape[0]
    print(f"{len(clips)} clips, {positions} motion positions, vocabulary {vocab}: largest logit "
          f"difference {largest:.2e}; same arg-max at {same}/{positions}")
    if largest > TOLERANCE:
        print(f"FAIL: logits differ by more than {TOLERANCE}")
        sys.exit(1)


if __name__ == "__main__":
    main()
