"""PyTorch + transformers CPU reference: caption embedding with all-MiniLM-L6-v2, for
`motionscale bench embed --reference`.

What a user of the field runs to get per-token caption embeddings (`embed-text`'s output):
the Hugging Face tokenizer and `AutoModel` loaded from the same folder (`config.json`,
`tokenizer.json`, `model.safetensors`), in eval mode under `torch.inference_mode()`; captions
sorted by length and embedded `--batch` at a time, each batch padded to its longest caption
with the attention mask; the last hidden state of every real token ([CLS] and [SEP] included)
copied out per caption. The timed call embeds every caption of the input file once.

usage: pytorch_embed_text.py --encoder DIR --captions FILE [--batch 64] [--threads 2]
                             [--warmup 1] [--reps 3] [--out FILE]
FILE holds one caption per line. Prints JSON: captions/s, tokens/s, median seconds per pass.
"""
import argparse
import statistics
import time

import torch
from transformers import AutoModel, AutoTokenizer

from reference_output import emit


def embed_all(model, tokenizer, captions, batch):
    order = sorted(range(len(captions)), key=lambda i: len(captions[i]))
    out = [None] * len(captions)
    tokens = 0
    with torch.inference_mode():
        for start in range(0, len(order), batch):
            chunk = order[start:start + batch]
            enc = tokenizer([captions[i] for i in chunk], padding=True, return_tensors="pt")
            hidden = model(**enc).last_hidden_state
            lengths = enc["attention_mask"].sum(dim=1).tolist()
            for row, (i, n) in enumerate(zip(chunk, lengths)):
                out[i] = hidden[row, :n].numpy().copy()
                tokens += n
    return out, tokens


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--encoder", required=True)
    ap.add_argument("--captions", required=True)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with open(args.captions, encoding="utf-8") as f:
        captions = [line.rstrip("\n") for line in f if line.strip()]
    tokenizer = AutoTokenizer.from_pretrained(args.encoder)
    model = AutoModel.from_pretrained(args.encoder).eval()
    for _ in range(args.warmup):
        embed_all(model, tokenizer, captions, args.batch)
    samples = []
    for _ in range(args.reps):
        t0 = time.perf_counter()
        _, tokens = embed_all(model, tokenizer, captions, args.batch)
        samples.append(time.perf_counter() - t0)
    median = statistics.median(samples)
    out = {
        "captions": len(captions),
        "tokens": tokens,
        "batch": args.batch,
        "threads": torch.get_num_threads(),
        "median_s": median,
        "captions_per_s": len(captions) / median,
        "tokens_per_s": tokens / median,
        "samples_s": samples,
        "torch": torch.__version__,
    }
    emit(out, args.out)


if __name__ == "__main__":
    main()
