"""Scores the committed forward predictions (fwd-two-part.json, fwd-all-tokens.json) on the runs
of plan-t16.toml (indices 334-341), read from a results table; with PREFIX and LO-HI, those of
PREFIX{two-part,all-tokens}.json on the indices LO-HI instead:
   python3 score.py RESULTS [PREFIX LO-HI]"""
import csv, json, math, os, sys
here = os.path.dirname(os.path.abspath(__file__))
prefix, (lo, hi) = 'fwd-', (334, 341)
if len(sys.argv) > 3:
    prefix, (lo, hi) = sys.argv[2], map(int, sys.argv[3].split('-'))
rows = [r for r in csv.DictReader(open(sys.argv[1])) if lo <= int(r['index']) <= hi]
laws = {k: json.load(open(os.path.join(here, f'{prefix}{k}.json')))['predictions'] for k in ('two-part', 'all-tokens')}
# the previous budget's best; the best at any budget trained before
NO_GROWTH = {'real-1': (2.4749, 2.4142), 'all-1_8': (3.7890, 3.7380), 'all-1_2': (2.7060, 2.7060)}
for sub in sorted({r['data'] for r in rows}, reverse=True):
    rs = sorted((r for r in rows if r['data'] == sub), key=lambda r: int(r['n_nv']))
    print(f"== {sub} at {float(rs[0]['budget']):.3g}: {len(rs)} runs")
    sq = {k: 0.0 for k in laws}
    for r in rs:
        ce = float(r['best_real_test_loss']); sel = float(r['best_step']) / float(r['steps'])
        line = f"  {r['model']:6s} CE {ce:.3f} (selected at {int(r['best_step'])} of {int(r['steps'])}, {float(r['epochs']) * sel:.1f} epochs)"
        for k, p in laws.items():
            v, lo, hi = p[sub]['runs'][r['model']]
            sq[k] += math.log(v / ce) ** 2
            line += f" | {k} {v:.3f} [{lo:.3f}, {hi:.3f}] {'in' if lo <= ce <= hi else 'out'} ({v - ce:+.3f})"
        print(line)
    best = min(rs, key=lambda r: float(r['best_real_test_loss'])) if rs else None
    if best:
        b = float(best['best_real_test_loss'])
        print(f"  best run {best['model']} CE {b:.3f}")
        for k, p in laws.items():
            v, lo, hi = p[sub]['ce']
            print(f"    {k}: best {v:.3f} [{lo:.3f}, {hi:.3f}] {'in' if lo <= b <= hi else 'out'} ({v - b:+.3f}); RMS log error over the runs {math.sqrt(sq[k] / len(rs)):.3f}")
        g, a = NO_GROWTH[sub]
        print(f"    no growth: the previous budget's best {g:.3f} ({g - b:+.3f}); any earlier budget's best {a:.3f} ({a - b:+.3f})")
