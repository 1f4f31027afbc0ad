"""Two-part law: the data-constrained law on the selected checkpoint's tokens, and a stopping rule
e*(N, U) for when a run's validation loss stops improving. A run of N on C/6N tokens is predicted
at min(D, e* U) tokens, D = C / 6(N + N_v).
   python3 stopped.py RESULTS CUT [FORM]: fitted on the budgets <= CUT, predicted above."""
import csv, os, sys, warnings, numpy as np
warnings.filterwarnings('ignore')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from law import load, fit, predict, nv_line
rows = list(csv.DictReader(open(sys.argv[1])))
g = lambda k: np.array([float(r[k]) for r in rows])
PATH = sys.argv[1]
d = load(PATH)
NV = nv_line(PATH)
frac = g('best_step') / g('steps')
ep = g('epochs')
dsel = dict(d); dsel['D'] = d['D'] * frac
cut = float(sys.argv[2])
form = sys.argv[3] if len(sys.argv) > 3 else 'M'
train = np.where(d['C'] <= cut * 1.01)[0]
t, cost = fit(form, dsel, train, nstart=40)
print(f'law {form} on selected tokens, C <= {cut:.3g}: {len(train)} runs, theta {np.round(t,3)}')
# stopping rule from the runs (of the fitted budgets) that stopped before their end
stop = train[frac[train] < 0.98]
X = np.column_stack([np.ones(len(stop)), np.log(d['N'][stop]), np.log(d['U'][stop])])
c, *_ = np.linalg.lstsq(X, np.log(ep[stop] * frac[stop]), rcond=None)
print(f'stopping rule: ln e* = {c[0]:.3f} + {c[1]:.3f} ln N + {c[2]:.3f} ln U  ({len(stop)} runs stopped early)')
def run_loss(N, C, U, s):
    D = C / (6 * (N + NV(N)))
    estar = np.exp(c[0] + c[1] * np.log(N) + c[2] * np.log(U))
    return np.exp(predict(form, t, N, np.minimum(D, estar * U), U, s))
def n_opt(C, U, s):
    N = np.logspace(3.5, 9, 2000)
    L = run_loss(N, C, np.full_like(N, U), np.full_like(N, s))
    i = np.argmin(L); return N[i], L[i]
errs = []
for cc in sorted(set(d['C'])):
    if cc <= cut * 1.01: continue
    for sub in sorted(set(d['data'][d['C'] == cc])):
        m = np.where((d['C'] == cc) & (d['data'] == sub))[0]
        j = m[np.argmin(d['L'][m])]
        lp = run_loss(d['N'][m], cc, d['U'][m], d['s'][m])
        rms = np.sqrt(np.mean((np.log(lp) - np.log(d['L'][m]))**2))
        n_p, l_p = n_opt(cc, d['U'][j], d['s'][j])
        errs.append(l_p - d['L'][j])
        print(f'  {cc:.3g} {sub:8s}: best run N {d["N"][j]:.3g} CE {d["L"][j]:.3f} | N_opt {n_p:.3g} ({n_p/d["N"][j]:.2f}x) CE {l_p:.3f} (miss {l_p-d["L"][j]:+.3f}); rows rms log {rms:.3f}')
print(f'  mean |CE miss| {np.mean(np.abs(errs)):.3f}')
