"""Data-constrained law variants, fitted as `fit --repeated-data` does (Huber δ = 1e-3 on log residuals,
many starts), to compare forms before one is built into `fit`:
  M  Muennighoff et al. 2023 with the exchange rate (what `fit` fits: L = E + A/N^α + B/D'^β);
  MN M with effective parameters past κ·U (R*_N);  G  L = E + (A/N^α + B/D'^β)^γ;
  P  M plus an overfitting term G·(D/U)^ψ·(N/U)^μ;
  S  M with the effective data saturating at S = κ·U'^γ instead: D' = S·(1 − e^(−D/S))."""
import csv, sys, numpy as np
from scipy.optimize import least_squares, minimize

def load(path):
    rows = list(csv.DictReader(open(path)))
    f = lambda k: np.array([float(r[k]) for r in rows])
    return dict(C=f('budget'), N=f('n_nv'), D=f('tokens'), U=f('unique_tokens'), s=f('synth_share'),
                L=f('best_real_test_loss'), data=np.array([r['data'] for r in rows]))

def eff(x, u, r):
    """Muennighoff: x' = x up to u, else u + u r (1 - exp(-(x/u - 1)/r))."""
    z = np.maximum(x / u - 1.0, 0.0)
    return np.where(x <= u, x, u + u * r * (1 - np.exp(-z / r)))

# theta: a, b, e, alpha, beta, ln r_d, ln rho, [extra...]
def predict(form, t, N, D, U, s):
    a, b, e, al, be, lrd, lrho = t[:7]
    k = 1 - s + np.exp(lrho) * s
    Dp = eff(D, U, np.exp(lrd)) * k
    if form == 'M':
        Np = N
        X, Y = a - al * np.log(Np), b - be * np.log(Dp)
        return np.logaddexp(np.logaddexp(X, Y), e)
    if form == 'MN':   # parameters past kappa * U' decay with R*_N
        lkap, lrn = t[7], t[8]
        Np = eff(N, np.exp(lkap) * U * k, np.exp(lrn))
        X, Y = a - al * np.log(Np), b - be * np.log(Dp)
        return np.logaddexp(np.logaddexp(X, Y), e)
    if form == 'G':    # L = E + (A/N^a + B/D'^b)^gamma
        g = t[7]
        X, Y = a - al * np.log(N), b - be * np.log(Dp)
        return np.logaddexp(g * np.logaddexp(X, Y), e)
    if form == 'S':    # effective data saturates at S = kappa * U'^gamma: D' = S (1 - exp(-D/S))
        S = np.exp(t[5] + t[7] * np.log(U * k))
        Dp = S * -np.expm1(-(D * k) / S)
        X, Y = a - al * np.log(N), b - be * np.log(Dp)
        return np.logaddexp(np.logaddexp(X, Y), e)
    if form == 'P':    # overfitting penalty: + G * (D/U)^psi * (N/U)^mu  (grows with epochs and size per datum)
        lg, psi, mu = t[7], t[8], t[9]
        X, Y = a - al * np.log(N), b - be * np.log(Dp)
        P = lg + psi * np.log(D / U) + mu * np.log(N / (U * k))
        return np.logaddexp(np.logaddexp(np.logaddexp(X, Y), e), P)
    raise ValueError(form)

NPAR = dict(M=7, MN=9, G=8, P=10)

def starts(form, rng, n=40):
    out = []
    for _ in range(n):
        t = [rng.uniform(0, 15), rng.uniform(0, 20), rng.uniform(-1, 1.5), rng.uniform(0.1, 1.2),
             rng.uniform(0.1, 1.5), np.log(rng.uniform(1, 50)), np.log(rng.uniform(0.1, 1.5))]
        if form == 'MN': t += [np.log(rng.uniform(0.3, 300)), np.log(rng.uniform(1, 100))]
        if form == 'G': t += [rng.uniform(0.3, 1.5)]
        if form == 'P': t += [rng.uniform(-15, -2), rng.uniform(0.1, 2), rng.uniform(0.0, 1.5)]
        if form == 'S': t[5] = rng.uniform(0, 8); t += [rng.uniform(0.3, 1.2)]
        out.append(np.array(t))
    return out

def fit(form, d, idx, seed=0, nstart=40):
    rng = np.random.default_rng(seed)
    lnL = np.log(d['L'][idx])
    args = [d[k][idx] for k in 'NDUs']
    def res(t):
        return predict(form, t, *args) - lnL
    best = None
    for t0 in starts(form, rng, nstart):
        try:
            r = least_squares(res, t0, loss='huber', f_scale=1e-3, max_nfev=4000, x_scale='jac')
        except Exception:
            continue
        if np.all(np.isfinite(r.x)) and (best is None or r.cost < best.cost):
            best = r
    return best.x, best.cost

def n_opt(form, t, C, U, s, nv):
    N = np.logspace(3.5, 9, 2000)
    D = C / (6 * (N + nv(N)))
    lp = predict(form, t, N, D, np.full_like(N, U), np.full_like(N, s))
    i = np.argmin(lp)
    return N[i], np.exp(lp[i])

def nv_line(path):
    """log10 N_v = c0 + c1 log10 N over the runs (the sweep spends C = 6 (N + N_v) D)."""
    rows = list(csv.DictReader(open(path)))
    x = np.log10([float(r['n_nv']) for r in rows]); y = np.log10([float(r['n_v']) for r in rows])
    c1, c0 = np.polyfit(x, y, 1)
    return lambda n: 10 ** (c0 + c1 * np.log10(n))
