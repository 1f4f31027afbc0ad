"""SciPy reference: the parametric L(N, D) fit (Approach 3) as Besiroglu et al. (Epoch, 2024)
replicate Chinchilla, for `motionscale bench fit --reference`.

Written from the method's description (the same one `fits/src/parametric.rs` implements):
θ = (a, b, e, α, β), residual r = LSE(a − α ln N, b − β ln D, e) − ln L, objective
Σ Huber_δ(r) with δ = 1e-3 (scipy.special.huber), minimised by scipy.optimize.minimize
(L-BFGS-B, gradient by finite differences, as the replication's code leaves `jac` unset) from
every start of Epoch's grid: α, β ∈ {0, 0.5, …, 2}, e ∈ {−1, −0.5, …, 1}, a, b ∈ {0, 5, …, 25}
(4,500 starts; `--stride K` keeps every K-th, in the order α, β, e, a, b, as `motionscale`'s
grid); the lowest objective wins. `--jac` passes the analytic gradient instead.

usage: scipy_fit.py --results CSV [--n-col "Model Size"] [--d-col "Training Tokens"]
                    [--loss-col loss] [--stride 1] [--jac] [--out FILE]
Prints JSON: the fitted E, A, B, α, β, the objective, starts, and the wall seconds.
"""
import argparse
import csv
import itertools
import time

import numpy as np
from scipy.optimize import minimize
from scipy.special import huber, logsumexp

from reference_output import emit

DELTA = 1e-3


def objective(theta, ln_n, ln_d, ln_l):
    a, b, e, alpha, beta = theta
    terms = np.stack([a - alpha * ln_n, b - beta * ln_d, np.full_like(ln_n, e)])
    return huber(DELTA, logsumexp(terms, axis=0) - ln_l).sum()


def gradient(theta, ln_n, ln_d, ln_l):
    a, b, e, alpha, beta = theta
    terms = np.stack([a - alpha * ln_n, b - beta * ln_d, np.full_like(ln_n, e)])
    lse = logsumexp(terms, axis=0)
    r = lse - ln_l
    dh = np.clip(r, -DELTA, DELTA)
    w = np.exp(terms - lse) * dh
    return np.array([w[0].sum(), w[1].sum(), w[2].sum(), -(w[0] * ln_n).sum(), -(w[1] * ln_d).sum()])


def epoch_grid():
    alphas = betas = np.arange(0.0, 2.01, 0.5)
    es = np.arange(-1.0, 1.01, 0.5)
    as_ = bs = np.arange(0.0, 25.01, 5.0)
    return [np.array([a, b, e, al, be]) for al, be, e, a, b in itertools.product(alphas, betas, es, as_, bs)]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--results", required=True)
    ap.add_argument("--n-col", default="Model Size")
    ap.add_argument("--d-col", default="Training Tokens")
    ap.add_argument("--loss-col", default="loss")
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--jac", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    with open(args.results, newline="") as f:
        rows = list(csv.DictReader(f))
    ln_n = np.log([float(r[args.n_col]) for r in rows])
    ln_d = np.log([float(r[args.d_col]) for r in rows])
    ln_l = np.log([float(r[args.loss_col]) for r in rows])
    starts = epoch_grid()[::args.stride]
    jac = gradient if args.jac else None
    t0 = time.perf_counter()
    best = None
    for start in starts:
        res = minimize(objective, start, args=(ln_n, ln_d, ln_l), jac=jac, method="L-BFGS-B")
        if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
            best = res
    seconds = time.perf_counter() - t0
    a, b, e, alpha, beta = best.x
    out = {
        "runs": len(rows),
        "starts": len(starts),
        "jac": "analytic" if args.jac else "finite differences",
        "seconds": seconds,
        "objective": float(best.fun),
        "E": float(np.exp(e)),
        "A": float(np.exp(a)),
        "B": float(np.exp(b)),
        "alpha": float(alpha),
        "beta": float(beta),
    }
    emit(out, args.out)


if __name__ == "__main__":
    main()
