"""A third ingredient tried on the two-part law: the selected checkpoint of a long schedule is not
annealed, so ln L gains ln(1 + κ·(1 − a)), a = the share of the cosine decay done at the selected
step (5% warm-up, cosine to 10%). python3 anneal.py RESULTS CUT: fitted on the budgets <= CUT."""
import csv, os, sys, warnings, numpy as np
from scipy.optimize import least_squares
warnings.filterwarnings('ignore')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from law import load, predict, nv_line, starts
path = sys.argv[1]; cut = float(sys.argv[2])
rows = list(csv.DictReader(open(path))); g = lambda k: np.array([float(r[k]) for r in rows])
d = load(path); NV = nv_line(path)
share = g('best_step') / g('steps'); ep = g('epochs')
def annealed(sh, warm=0.05):
    x = np.clip((sh - warm) / (1 - warm), 0, 1)
    lr = 0.1 + 0.9 * (1 + np.cos(np.pi * x)) / 2
    return (1 - lr) / 0.9
def model(t, N, D, U, s, sh):
    return predict('M', t[:7], N, D, U, s) + np.log1p(np.exp(t[7]) * (1 - annealed(sh)))
train = np.where(d['C'] <= cut * 1.01)[0]
lnL = np.log(d['L'][train])
args = [d['N'][train], d['D'][train] * share[train], d['U'][train], d['s'][train], share[train]]
best = None
rng = np.random.default_rng(0)
for t0 in starts('M', rng, 40):
    t0 = np.append(t0, np.log(0.05))
    r = least_squares(lambda t: model(t, *args) - lnL, t0, loss='huber', f_scale=1e-3, max_nfev=4000, x_scale='jac')
    if best is None or r.cost < best.cost: best = r
t = best.x
print('law', np.round(t, 3), 'kappa', np.exp(t[7]), 'objective', best.cost)
stop = train[share[train] < 0.98]
X = np.column_stack([np.ones(len(stop)), np.log(d['N'][stop]), np.log(d['U'][stop])])
c = np.linalg.lstsq(X, np.log(ep[stop] * share[stop]), rcond=None)[0]
def run_loss(N, D, U, s):
    es = np.exp(c[0] + c[1] * np.log(N) + c[2] * np.log(U))
    used = np.minimum(D, es * U); sh = used / D
    return np.exp(model(t, N, used, U, s, sh))
def n_opt(C, U, s):
    N = np.logspace(3.5, 9, 2000); D = C / (6 * (N + NV(N)))
    L = run_loss(N, D, np.full_like(N, U), np.full_like(N, s)); i = np.argmin(L); return N[i], L[i]
errs = []
for cc in sorted(set(d['C'])):
    if cc <= cut * 1.01: continue
    for sub in sorted(set(d['data'][d['C'] == cc])):
        m = np.where((d['C'] == cc) & (d['data'] == sub))[0]; j = m[np.argmin(d['L'][m])]
        n_p, l_p = n_opt(cc, d['U'][j], d['s'][j]); errs.append(l_p - d['L'][j])
        print(f'  {cc:.3g} {sub:8s}: best {d["L"][j]:.3f} | law {l_p:.3f} ({l_p-d["L"][j]:+.3f}) at N {n_p:.3g}')
print(f'  mean |miss| {np.mean(np.abs(errs)):.3f}')
# in-sample bias per subset at its top budget (rule tokens)
full = train
pl = np.log(run_loss(d['N'][full], d['D'][full], d['U'][full], d['s'][full])) - np.log(d['L'][full])
for sub in sorted(set(d['data'])):
    top = max(d['C'][(d['data'] == sub) & (d['C'] <= cut * 1.01)])
    m = (d['data'][full] == sub) & (d['C'][full] == top)
    print(f'  in-sample {sub} at {top:.3g}: mean log residual {np.mean(pl[m]):+.3f}')
