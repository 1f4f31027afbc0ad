"""PyTorch CPU reference: one training step of BI-CTVAE, for `motionscale bench ctvae --reference`.

Written from the spec of the project's model (experiments/src/ctvae.rs, experiments/src/ctvae_train.rs):
- encoder: nn.GRU(F + C + 1 → h, num_layers=L, batch_first) over [pose, one-hot class,
  t / max_frames], packed by length; the top layer's final state → Linear(h→z) for μ and for
  log σ²; z = μ + ε·exp(log σ² / 2);
- decoder: nn.GRU(z + C + 1 → h, L) over [z, one-hot class, t / max_frames] at every step of
  the longest sequence, then Linear(h→F), zeroed past each length;
- modes: μ_a, log σ_a² parameters (C × z).
Loss: pose MSE over real frames + joint-position MSE (feature dims 4..67 scaled by the std, here
ones, squared distance per joint) + λ_latent · KL(N(μ, σ²) ‖ N(μ_a, σ_a²)) summed over the batch.
Optimizer: AdamW (lr 1e-3, β 0.9/0.999, weight decay 0.01), gradient norm clipped at 1.
Data (the same in the Rust bench): B sequences of 60 + (7·b mod 41) frames (60–100), class
b mod C, poses N(0, 1) (seeded).

usage: pytorch_ctvae.py [--shape cpu|paper] [--batch 64] [--classes 10] [--threads 2]
                        [--warmup 2] [--reps 10] [--out FILE]
Prints JSON: steps/s, median seconds per step, the shape and the timing samples.
"""
import argparse
import statistics
import time

import torch
from torch import nn

from reference_output import emit

SHAPES = {"cpu": (2, 128, 64), "paper": (8, 256, 256)}
FEATURES, MAX_FRAMES, JOINTS = 263, 100, slice(4, 67)


def lengths_of(batch):
    return [60 + (7 * b) % 41 for b in range(batch)]


class Ctvae(nn.Module):
    def __init__(self, layers, hidden, latent, classes):
        super().__init__()
        self.classes = classes
        self.enc = nn.GRU(FEATURES + classes + 1, hidden, layers, batch_first=True)
        self.mu = nn.Linear(hidden, latent)
        self.logvar = nn.Linear(hidden, latent)
        self.dec = nn.GRU(latent + classes + 1, hidden, layers, batch_first=True)
        self.out = nn.Linear(hidden, FEATURES)
        self.mode_mu = nn.Parameter(torch.randn(classes, latent))
        self.mode_logvar = nn.Parameter(torch.zeros(classes, latent))

    def conditions(self, classes, steps):
        onehot = nn.functional.one_hot(classes, self.classes).float()
        t = torch.arange(steps, dtype=torch.float32) / MAX_FRAMES
        b = classes.shape[0]
        return torch.cat([onehot[:, None].expand(b, steps, -1), t[None, :, None].expand(b, steps, 1)], 2)

    def forward(self, x, classes, lengths, eps):
        steps = x.shape[1]
        cond = self.conditions(classes, steps)
        packed = nn.utils.rnn.pack_padded_sequence(
            torch.cat([x, cond], 2), lengths, batch_first=True, enforce_sorted=False)
        _, h = self.enc(packed)
        mu, logvar = self.mu(h[-1]), self.logvar(h[-1])
        z = mu + eps * torch.exp(logvar / 2)
        dec_in = torch.cat([z[:, None].expand(-1, steps, -1), cond], 2)
        recon, _ = self.dec(dec_in)
        return self.out(recon), mu, logvar


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--shape", default="cpu", choices=sorted(SHAPES))
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--classes", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    layers, hidden, latent = SHAPES[a.shape]
    b = a.batch
    lengths = lengths_of(b)
    steps = max(lengths)
    mask = (torch.arange(steps)[None, :] < torch.tensor(lengths)[:, None]).float()[..., None]
    x = torch.randn(b, steps, FEATURES) * mask
    classes = torch.tensor([i % a.classes for i in range(b)])
    frames = sum(lengths)
    model = Ctvae(layers, hidden, latent, a.classes)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.01)

    def step():
        eps = torch.randn(b, latent)
        recon, mu, logvar = model(x, classes, lengths, eps)
        err = recon * mask - x
        pose = err.pow(2).sum() / (frames * FEATURES)
        joints = err[..., JOINTS].pow(2).sum() / (frames * 21)
        m_mu, m_lv = model.mode_mu[classes], model.mode_logvar[classes]
        kl = 0.5 * (m_lv - logvar - 1 + (logvar.exp() + (mu - m_mu).pow(2)) / m_lv.exp()).sum()
        loss = pose + joints + 1e-5 * kl
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()

    for _ in range(a.warmup):
        step()
    samples = []
    for _ in range(a.reps):
        t0 = time.perf_counter()
        step()
        samples.append(time.perf_counter() - t0)
    median = statistics.median(samples)
    out = {"what": "BI-CTVAE training step", "shape": a.shape, "layers": layers, "hidden": hidden,
           "latent": latent, "batch": b, "mean_frames": frames / b, "threads": torch.get_num_threads(),
           "median_step_s": median, "steps_per_s": 1.0 / median, "samples_s": samples,
           "torch": torch.__version__}
    emit(out, a.out)


if __name__ == "__main__":
    main()
