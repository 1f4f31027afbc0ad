"""Forward prediction of the two-part law (data-constrained law on the selected checkpoint's tokens
+ stopping rule), fitted on every committed row, with a paired bootstrap over runs (the same resample refits both parts).
   python3 forward.py RESULTS BOOTSTRAP two-part|all-tokens OUT.json [PLAN INDICES]
(PLAN INDICES: predict those runs of the plan instead of the 3e13 ones below.)
"all-tokens": the current law (every token counts, no stopping rule)."""
import csv, os, sys, json, warnings, numpy as np
from scipy.optimize import least_squares
warnings.filterwarnings('ignore')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from law import load, fit, predict, nv_line
path = sys.argv[1]
B = int(sys.argv[2])
rows = list(csv.DictReader(open(path)))
g = lambda k: np.array([float(r[k]) for r in rows])
d = load(path)
NV = nv_line(path)
frac = g('best_step') / g('steps'); ep = g('epochs')
dsel = dict(d); dsel['D'] = d['D'] * frac
# the runs of plan-t16.toml: N_nv and the tokens the plan spends at 3e13
SIZES = {'64x2': (123392, 19858922), '96x2': (258624, 11081560), '128x2': (442880, 7146451), '160x2': (677120, 5009618), '160x4': (1292480, 3098969), '192x4': (1845120, 2241879)}
TARGETS = [('all-1_8', 3e13, 27076, 0.5078004004079624), ('real-1', 3e13, 112436, 0.0)]
if len(sys.argv) > 6:   # PLAN INDICES: the runs of one subset and budget, from a plan
    import tomllib
    points = tomllib.load(open(sys.argv[5], 'rb'))['points']
    pts = [points[int(i)] for i in sys.argv[6].split(',')]
    SIZES = {q['model']: (q['n_nv'], q['tokens']) for q in pts}
    share = {r['data']: float(r['synth_share']) for r in rows}
    TARGETS = sorted({(q['data'], q['budget'], q['unique_tokens'], share[q['data']]) for q in pts})
def stop_rule(idx):
    s = idx[frac[idx] < 0.98]
    X = np.column_stack([np.ones(len(s)), np.log(d['N'][s]), np.log(d['U'][s])])
    return np.linalg.lstsq(X, np.log(ep[s] * frac[s]), rcond=None)[0]
def refit(idx, t0, data):
    lnL = np.log(d['L'][idx]); a = [data[k][idx] for k in 'NDUs']
    r = least_squares(lambda t: predict('M', t, *a) - lnL, t0, loss='huber', f_scale=1e-3, max_nfev=4000, x_scale='jac')
    return r.x
def run_loss(t, c, N, C, U, s, D=None):
    """c: the stopping rule, or None for the current law (all tokens count). D: the run's
    tokens (default: C spent as 6 (N + N_v) D on the N_v line)."""
    D = C / (6 * (N + NV(N))) if D is None else D
    es = np.inf if c is None else np.exp(c[0] + c[1] * np.log(N) + c[2] * np.log(U))
    return np.exp(predict('M', t, N, np.minimum(D, es * U), U, s))
def answers(t, c):
    out = {}
    for sub, C, U, s in TARGETS:
        N = np.logspace(3.5, 9, 2000)
        L = run_loss(t, c, N, C, np.full_like(N, U), np.full_like(N, s)); i = np.argmin(L)
        out[sub] = dict(n_opt=N[i], ce=L[i], runs={m: float(run_loss(t, c, np.array([n]), C, np.array([U]), np.array([s]), np.array([dd]))[0]) for m, (n, dd) in SIZES.items()})
    return out
idx = np.arange(len(rows))
two_part = len(sys.argv) < 4 or sys.argv[3] != 'all-tokens'
data = dsel if two_part else d
rule = stop_rule if two_part else (lambda r: None)
t, cost = fit('M', data, idx, nstart=40); c = rule(idx)
print('two-part law (selected tokens + stopping rule)' if two_part else 'current law (all tokens)')
print('law', np.round(t, 4).tolist(), 'objective', round(cost, 6)); print('stopping', c if c is None else np.round(c, 4).tolist())
point = answers(t, c)
rng = np.random.default_rng(2026)
draws = []
for b in range(B):
    r = rng.integers(0, len(rows), len(rows))
    draws.append(answers(refit(r, t, data), rule(r)))
q = lambda v: (np.percentile(v, 2.5), np.percentile(v, 97.5))
res = {}
for sub, C, U, s in TARGETS:
    p = point[sub]
    lo, hi = q([x[sub]['n_opt'] for x in draws]); clo, chi = q([x[sub]['ce'] for x in draws])
    print(f'{sub} at {C:.3g}: N_opt {p["n_opt"]:.3g} [{lo:.3g}, {hi:.3g}]  best captured CE {p["ce"]:.3f} [{clo:.3f}, {chi:.3f}]')
    res[sub] = dict(budget=C, unique_tokens=U, synth_share=s, n_opt=[p['n_opt'], lo, hi], ce=[p['ce'], clo, chi], runs={})
    for m in SIZES:
        v = p['runs'][m]; rl, rh = q([x[sub]['runs'][m] for x in draws])
        res[sub]['runs'][m] = [v, rl, rh]
        print(f'   {m:6s} N {SIZES[m][0]:>8d}: captured CE {v:.3f} [{rl:.3f}, {rh:.3f}]')
json.dump(dict(law=t.tolist(), stopping=None if c is None else c.tolist(), bootstrap=B, predictions=res), open(sys.argv[4] if len(sys.argv) > 4 else 'forward.json', 'w'), indent=1)
