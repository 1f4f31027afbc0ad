"""Load a motionscale evaluator into PyTorch modules and compare embeddings with ours.

Usage: python3 scripts/torch-check-evaluator.py EVALUATOR_DIR CORPUS EMBED_DIR [N]

Builds the evaluator from `nn.Conv1d`, `nn.GRU(bidirectional=True)` and `nn.Linear` with the
key names of `model.safetensors` (`load_state_dict(strict=True)`: every key and shape must
match), then, for the first N (default 64) motions listed in EMBED_DIR/motions.jsonl (from
`motionscale evaluator embed --motions CORPUS --out EMBED_DIR`), reads their features and
first caption's token embeddings from the corpus's Parquet files with pyarrow, embeds them in
PyTorch and prints the largest difference from EMBED_DIR/{motion,text}_embeddings.npy and the
share of equal emotion/action predictions. Needs torch, numpy, pyarrow and safetensors.
"""
import glob
import json
import os
import sys

import numpy as np
import pyarrow.parquet as pq
import torch
from safetensors.torch import load_file
from torch import nn

UNIT = 4


class Head(nn.Sequential):
    def __init__(self, inp, hidden, out):
        super().__init__(nn.Linear(inp, hidden), nn.LeakyReLU(0.2), nn.Linear(hidden, out))


def last_states(gru, x, lengths):
    packed = nn.utils.rnn.pack_padded_sequence(x, lengths, batch_first=True, enforce_sorted=False)
    _, h = gru(packed)  # (2, batch, hidden): forward, backward
    return torch.cat([h[0], h[1]], dim=-1)


class Evaluator(nn.Module):
    def __init__(self, c):
        super().__init__()
        h = c["hidden"]
        self.motion = nn.Module()
        self.motion.conv = nn.Sequential(
            nn.Conv1d(c["feature_dim"], h, 4, 2, 1), nn.LeakyReLU(0.2), nn.Conv1d(h, h, 4, 2, 1))
        self.motion.gru = nn.GRU(h, h, batch_first=True, bidirectional=True)
        self.motion.head = Head(2 * h, h, c["embed_dim"])
        self.emotion = nn.Linear(2 * h, max(1, len(c["emotions"])))
        self.action = nn.Linear(2 * h, max(1, len(c["actions"])))
        self.text = nn.Module()
        self.text.input = nn.Linear(c["text_dim"], h)
        self.text.gru = nn.GRU(h, h, batch_first=True, bidirectional=True)
        self.text.head = Head(2 * h, h, c["embed_dim"])

    def encode_motion(self, x):  # one clip: (frames, 263), frames a multiple of UNIT
        y = self.motion.conv(x.T[None])  # (1, hidden, frames / 4)
        y = nn.functional.leaky_relu(y, 0.2).transpose(1, 2)
        pooled = last_states(self.motion.gru, y, [y.shape[1]])
        e = self.motion.head(pooled)
        return e / e.norm(dim=-1, keepdim=True), self.emotion(pooled), self.action(pooled)

    def encode_text(self, t):  # one caption: (tokens, text_dim)
        pooled = last_states(self.text.gru, self.text.input(t[None]), [t.shape[0]])
        e = self.text.head(pooled)
        return e / e.norm(dim=-1, keepdim=True)


def main():
    evaluator_dir, corpus, embed_dir = sys.argv[1:4]
    n = int(sys.argv[4]) if len(sys.argv) > 4 else 64
    file = json.load(open(os.path.join(evaluator_dir, "config.json")))
    c = file["config"]
    model = Evaluator(c)
    model.load_state_dict(load_file(os.path.join(evaluator_dir, "model.safetensors")), strict=True)
    model.eval()
    mean = np.load(os.path.join(evaluator_dir, "mean.npy"))
    std = np.load(os.path.join(evaluator_dir, "std.npy"))
    motions = [json.loads(l) for l in open(os.path.join(embed_dir, "motions.jsonl"))][:n]
    ours_m = np.load(os.path.join(embed_dir, "motion_embeddings.npy"))[:n]
    ours_t = np.load(os.path.join(embed_dir, "text_embeddings.npy"))[:n]
    wanted = {m["id"] for m in motions}
    features = {}
    for shard in sorted(glob.glob(os.path.join(corpus, "shards", "*.parquet"))):
        t = pq.read_table(shard, columns=["motion_id", "num_frames", "features"])
        for mid, frames, f in zip(t.column("motion_id").to_pylist(), t.column("num_frames").to_pylist(),
                                  t.column("features").to_pylist()):
            if mid in wanted:
                features[mid] = np.asarray(f, dtype=np.float32).reshape(frames, -1)
    captions = {m["caption"] for m in motions}
    tokens = {}
    text_dir = os.path.join(corpus, "text", file["text_encoder"])
    for shard in sorted(glob.glob(os.path.join(text_dir, "*.parquet"))):
        t = pq.read_table(shard, columns=["caption", "num_tokens", "embeddings"])
        for cap, k, e in zip(t.column("caption").to_pylist(), t.column("num_tokens").to_pylist(),
                             t.column("embeddings").to_pylist()):
            if cap in captions:
                tokens[cap] = np.asarray(e, dtype=np.float32).reshape(k, -1)[: c["max_text_tokens"]]
    diff_m = diff_t = 0.0
    same_emotion = same_action = 0
    with torch.no_grad():
        for i, m in enumerate(motions):
            x = (features[m["id"]] - mean) / std
            frames = max(min(len(x), c["max_frames"]) // UNIT * UNIT, UNIT)
            e, emo, act = model.encode_motion(torch.from_numpy(x[:frames].astype(np.float32)))
            diff_m = max(diff_m, float(np.abs(e[0].numpy() - ours_m[i]).max()))
            same_emotion += c["emotions"][int(emo.argmax())] == m["emotion"]
            same_action += c["actions"][int(act.argmax())] == m["action"]
            t = model.encode_text(torch.from_numpy(tokens[m["caption"]]))
            diff_t = max(diff_t, float(np.abs(t[0].numpy() - ours_t[i]).max()))
    print(f"{len(motions)} motions: largest motion-embedding difference {diff_m:.2e}, "
          f"text-embedding difference {diff_t:.2e}; same emotion {same_emotion}/{len(motions)}, "
          f"same action {same_action}/{len(motions)}")


if __name__ == "__main__":
    main()
