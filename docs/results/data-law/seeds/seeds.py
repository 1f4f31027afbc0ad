"""Seeds at one budget of the full-data ladder: mean ± SD over seeds per size, and the Welch 95%
interval of the difference between two sizes (validation-selected L_u and captured CE).

    python3 docs/results/data-law/seeds/seeds.py 1e14 512x4,384x4 \
        docs/results/data-law/results.csv docs/results/data-law/seeds/results-1e14.csv

Needs numpy and scipy.
"""
import csv
import sys

from scipy import stats
import numpy as np
budget = float(sys.argv[1]); sizes = sys.argv[2].split(',')
rows = [r for f in sys.argv[3:] for r in csv.DictReader(open(f))]
rows = [r for r in rows if float(r['budget']) == budget and r['data'] == 'all-1']
for col in ['best_norm_test_loss', 'best_real_test_loss']:
    v = {m: np.array([float(r[col]) for r in rows if r['model'] == m]) for m in sizes}
    for m in sizes:
        print(f"{col} {m}: n={len(v[m])} mean {v[m].mean():.4f} sd {v[m].std(ddof=1):.4f} values {np.round(v[m],4).tolist()}")
    a, b = v[sizes[0]], v[sizes[1]]
    d = a.mean() - b.mean()
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    dof = (va + vb) ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    h = stats.t.ppf(0.975, dof) * np.sqrt(va + vb)
    print(f"{col} {sizes[0]} - {sizes[1]}: {d:+.4f} [{d-h:+.4f}, {d+h:+.4f}] (Welch, dof {dof:.1f})")
