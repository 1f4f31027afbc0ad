"""Retrodiction: fit each form on the budgets <= CUT (every data subset), predict above.
   python3 retro.py RESULTS FORMS CUT   (FORMS: M,MN,G,P; see law.py)"""
import os, numpy as np, sys, warnings
warnings.filterwarnings('ignore')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from law import *
PATH = sys.argv[1]
d = load(PATH)
NV = nv_line(PATH)
forms = sys.argv[2].split(',')
cut = float(sys.argv[3])
train = np.where(d['C'] <= cut * 1.01)[0]
targets = [(c, sub) for c in sorted(set(d['C'])) if c > cut * 1.01 for sub in sorted(set(d['data'][d['C'] == c]))]
def obs(c, sub):
    m = np.where((d['C'] == c) & (d['data'] == sub))[0]
    j = m[np.argmin(d['L'][m])]
    return d['N'][j], d['L'][j], d['U'][j], d['s'][j], len(set(d['N'][m]))
for form in forms:
    t, cost = fit(form, d, train, nstart=40)
    print(f'== {form} fitted on C <= {cut:.3g}: {len(train)} runs, objective {cost:.5f}, theta {np.round(t,3)}')
    errs = []
    for c, sub in targets:
        n_b, l_b, u, s, k = obs(c, sub)
        m = np.where((d['C'] == c) & (d['data'] == sub))[0]
        lp = predict(form, t, d['N'][m], d['D'][m], d['U'][m], d['s'][m])
        rms = np.sqrt(np.mean((lp - np.log(d['L'][m]))**2))
        n_p, l_p = n_opt(form, t, c, u, s, NV)
        errs.append(l_p - l_b)
        print(f'  {c:.3g} {sub:8s} sizes {k}: best run N {n_b:.3g} CE {l_b:.3f} | law N_opt {n_p:.3g} ({n_p/n_b:.2f}x) CE {l_p:.3f} (miss {l_p-l_b:+.3f}); rows rms log {rms:.3f}')
    print(f'  mean |CE miss| {np.mean(np.abs(errs)):.3f}')
