"""Load a motionscale tokenizer checkpoint into the PyTorch reference model and compare.

Usage: python3 scripts/torch-check-tokenizer.py TOKENIZER_DIR FEATURES.npy [OURS.npy]

Builds `shared/bench/pytorch_vqvae.py`'s Encoder / FSQ or QuantizeEMAReset / Decoder with the
checkpoint's config.json, loads `model.safetensors` with `safetensors.torch.load_file` and
`load_state_dict(strict=True)` (so every key and shape must match), reconstructs the clip in
FEATURES.npy (n × 263 raw HumanML3D features, e.g. from `motionscale export hml3d`), and — when
OURS.npy (from `motionscale tokenizer decode`) is given — prints the largest difference
between the two reconstructions. Needs torch, numpy and safetensors.
"""
import json
import os
import sys

import numpy as np
import torch
from safetensors.torch import load_file

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "bench"))
import pytorch_vqvae as ref  # noqa: E402


def build(config):
    conv = config["conv"]
    quant = config["quantizer"]
    model = torch.nn.Module()
    model.encoder = ref.Encoder(conv["input_dim"], conv["width"], conv["code_dim"], conv["down_t"],
                                conv["depth"], conv["dilation_growth"])
    model.decoder = ref.Decoder(conv["input_dim"], conv["width"], conv["code_dim"], conv["down_t"],
                                conv["depth"], conv["dilation_growth"])
    if quant["kind"] == "fsq":
        if quant["bound"] != "tanh":
            sys.exit("the reference FSQ has the tanh bound only")
        model.quant = ref.FSQ(tuple(quant["levels"]), conv["code_dim"])
    else:
        model.quant = ref.QuantizeEMAReset(quant["codebook_size"], quant["dim"])
        model.quant.initted = True
    return model


def main():
    tok_dir, features_path = sys.argv[1], sys.argv[2]
    config = json.load(open(os.path.join(tok_dir, "config.json")))
    model = build(config)
    state = load_file(os.path.join(tok_dir, "model.safetensors"))
    model.load_state_dict(state, strict=True)
    model.eval()
    print(f"loaded {len(state)} tensors strictly into the reference {config['quantizer']['kind']} model")
    mean = np.load(os.path.join(tok_dir, "mean.npy"))
    std = np.load(os.path.join(tok_dir, "std.npy"))
    feats = np.load(features_path).astype(np.float32)
    factor = 2 ** config["conv"]["down_t"]
    n = feats.shape[0] // factor * factor
    x = torch.from_numpy((feats[:n] - mean) / std)[None]
    with torch.no_grad():
        h = model.encoder(x.permute(0, 2, 1))
        hq, _, _ = model.quant(h)
        out = model.decoder(hq).permute(0, 2, 1)[0].numpy() * std + mean
    print(f"reconstructed {n} frames")
    if len(sys.argv) > 3:
        ours = np.load(sys.argv[3])
        diff = np.abs(ours - out).max()
        scale = np.abs(out).max()
        print(f"max |ours - torch| = {diff:.3g} (max |value| {scale:.3g})")
        if diff > 1e-3 * max(scale, 1.0):
            sys.exit("reconstructions differ")


if __name__ == "__main__":
    main()
