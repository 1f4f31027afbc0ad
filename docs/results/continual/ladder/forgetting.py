#!/usr/bin/env python3
"""The law of forgetting (issue #59): forgetting and plasticity of continual LoRA experts
against the size of a law-sized backbone, from the forgetting ladder's runs (queue.sh).

    python3 forgetting.py RUNS                     cells, laws, ES-MoE - SeqLoRA gaps
(RUNS: the continual run folders, or a folder of their summaries as <run>.json)
    python3 forgetting.py RUNS --at C --n-nv N --model DxL --epochs E --out F.json
                                                   ... and the forecast at budget C's backbone
    python3 forgetting.py RUNS --score F.json       a forecast scored against its runs
    ... --plot F.svg                               AF, FF and PF against N_nv per method
    ... --logs DIR                                 and ES-MoE's routing of each new dataset

Per run and dataset order (the summaries of `motionscale continual`):
  AF  mean final FID (the paper's);  FR  mean over j < n of max_{j<=k<n} r[k][j] - r[n][j]
  (top-1 R-precision, the paper's);  FF  the same on FID: f[n][j] - min_{j<=k<n} f[k][j];
  PR / PF  plasticity: mean_k r[k][k] / f[k][k], dataset k scored right after learning it.
A cell (budget, rank, method) has 3 seeds x 3 orders. Intervals are bootstraps (2,000) that
resample the orders once per replicate for every cell (the orders are shared) and the seeds
of each cell. The law per method and metric: y = c + b * log10(N_nv), fitted by least squares
on the ladder's rank-8 cells, and y = c + b * log10(N_nv) + e * log10(E) with the experts'
epochs E per step; a forecast's interval adds a cell's own seed/order scatter to the line's
(the declared interval), and a second one also the law's misfit beyond that scatter.
A backtest: `--at 1e13 ...` fits the smaller sizes only, and `--score` scores it on 1e13.
"""
import argparse
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

METRICS = ["AF", "FR", "FF", "PR", "PF"]
METHODS = ["es-moe", "seq-lora", "replay", "mtl"]
DRAWS, SEED = 2000, 0


def order_metrics(order):
    f, r = order["f"], order["r"]
    n = len(r)
    out = {"AF": np.mean(f[-1])}
    if n > 1:
        out["FR"] = np.mean([max(r[k][j] for k in range(j, n - 1)) - r[-1][j] for j in range(n - 1)])
        out["FF"] = np.mean([f[-1][j] - min(f[k][j] for k in range(j, n - 1)) for j in range(n - 1)])
        out["PR"] = np.mean([r[k][k] for k in range(n)])
        out["PF"] = np.mean([f[k][k] for k in range(n)])
    return out


def expert_params(model, rank, run=None):
    """Parameters of one LoRA expert on a `DxL` backbone: every block's QKV (d -> 3d), output
    (d -> d), gate/up (d -> 2f) and down (f -> d) projections, f = round(8d/3), each r x (in +
    out); checked against the run's first adapter (safetensors header) when it is there."""
    d, layers = map(int, model.split("x"))
    f = (8 * d + 1) // 3
    params = rank * layers * (8 * d + 3 * f)
    path = Path(run or "") / "order-0" / "step-1" / "train" / "adapter.safetensors"
    if run and path.is_file():
        with open(path, "rb") as fh:
            header = json.loads(fh.read(int.from_bytes(fh.read(8), "little")))
        found = sum(math.prod(t["shape"]) for k, t in header.items() if "lora" in k)
        assert found == params, f"{path}: {found} LoRA parameters, the formula says {params}"
    return params


def load(runs):
    """cells[(budget, rank, method)] = {"n_nv", "model", "tokens_per_step", "values": metric ->
    array [seed, order]}."""
    cells = {}
    files = sorted(Path(runs).glob("*/summary.json")) or sorted(Path(runs).glob("*.json"))
    for summary in files:
        s = json.loads(summary.read_text())
        c, b = s["config"], s["config"]["backbone"]
        key = (b["budget"], c["lora"]["rank"], c["method"])
        run = summary.parent if summary.name == "summary.json" else None
        cell = cells.setdefault(key, {"n_nv": b["n_nv"], "model": b["model"],
                                      "epochs": c.get("expert_epochs"), "seeds": {},
                                      "expert_params": expert_params(b["model"], key[1], run)})
        cell["seeds"][c["seed"]] = [order_metrics(o) for o in s["orders"]]
    for cell in cells.values():
        seeds = sorted(cell["seeds"])
        cell["n_seeds"] = len(seeds)
        cell["values"] = {m: np.array([[o[m] for o in cell["seeds"][s]] for s in seeds])
                          for m in METRICS if m in cell["seeds"][seeds[0]][0]}
    return cells


def draws(cells):
    """Bootstrap replicates of every cell's mean: {key: {metric: array [DRAWS]}}."""
    rng = np.random.default_rng(SEED)
    n_orders = {v.shape[1] for c in cells.values() for v in c["values"].values()}
    assert len(n_orders) == 1, "every run has the same orders"
    n_orders = n_orders.pop()
    orders = rng.integers(0, n_orders, size=(DRAWS, n_orders))
    out = {}
    for key in sorted(cells):
        cell = cells[key]
        seeds = rng.integers(0, cell["n_seeds"], size=(DRAWS, cell["n_seeds"]))
        out[key] = {m: v[seeds[:, :, None], orders[:, None, :]].mean(axis=(1, 2))
                    for m, v in cell["values"].items()}
    return out


def ci(x):
    return np.percentile(x, 2.5), np.percentile(x, 97.5)


def fmt(value, interval, digits=4):
    return f"{value:.{digits}f} [{interval[0]:.{digits}f}, {interval[1]:.{digits}f}]"


def ladder_keys(cells, method, exclude, form="N"):
    """The cells a law of `form` is fitted to: rank 8 only, except N+P+E, which takes every
    rank (and is fitted only where the method has more than one)."""
    keys = sorted(k for k in cells if k[2] == method and k[0] not in exclude)
    if form == "N+P+E":
        return keys if len({k[1] for k in keys}) > 1 else []
    return [k for k in keys if k[1] == 8]


def fit_line(x, y):
    slope, intercept = np.polyfit(x, y, 1)
    return intercept, slope


FORMS = {"N": "c + b log10 N_nv", "N+E": "c + b log10 N_nv + e log10 E (expert epochs)",
         "N+P+E": "c + b log10 N_nv + p log10 P (expert parameters) + e log10 E"}
COEFFICIENTS = {"N": ["b"], "N+E": ["b", "e"], "N+P+E": ["b", "p", "e"]}


def features(cell, form):
    x = [1.0, math.log10(cell["n_nv"])]
    p = [math.log10(cell["expert_params"])] if form == "N+P+E" else []
    return x + p + ([math.log10(cell["epochs"])] if form != "N" else [])


def law(cells, boot, method, metric, exclude, form="N"):
    """The law `form` fitted by least squares to the ladder's cells, and refitted to every
    bootstrap replicate; `scatter` is each cell's replicate mean minus its mean, `misfit_sd`
    the cells' scatter about the law beyond their sampling noise (residual variance on n - p
    degrees of freedom less the cells' mean bootstrap variance, floored at 0)."""
    keys = [k for k in ladder_keys(cells, method, exclude, form) if metric in cells[k]["values"]]
    if len(keys) <= len(COEFFICIENTS[form]) + 1:
        return None
    X = np.array([features(cells[k], form) for k in keys])
    y = np.array([cells[k]["values"][metric].mean() for k in keys])
    solve = lambda ys: np.linalg.lstsq(X, ys, rcond=None)[0]
    ys = np.stack([boot[k][metric] for k in keys], axis=1)
    beta = solve(y)
    residual = np.sum((y - X @ beta) ** 2) / (len(keys) - X.shape[1])
    return {"keys": keys, "form": form, "beta": beta, "boot": solve(ys.T).T,
            "scatter": [boot[k][metric] - cells[k]["values"][metric].mean() for k in keys],
            "misfit_sd": math.sqrt(max(0.0, residual - ys.var(axis=0).mean()))}


def scatter_draws(fit, rng):
    pick = rng.integers(0, len(fit["scatter"]), size=DRAWS)
    return np.stack(fit["scatter"])[pick, np.arange(DRAWS)]


def forecast(fits, x, rng, sign=(1,)):
    """The forecast at features `x` of sum(sign_i * law_i): the point, the line's 95%
    interval, a cell's 95% prediction interval (the line plus a cell's scatter), and that
    interval widened by the laws' misfit (a normal draw of `misfit_sd` per law)."""
    point = sum(s * f["beta"] @ x for s, f in zip(sign, fits))
    line = sum(s * f["boot"] @ x for s, f in zip(sign, fits))
    noisy = line + sum(s * scatter_draws(f, rng) for s, f in zip(sign, fits))
    misfit = noisy + sum(rng.normal(0.0, f["misfit_sd"], DRAWS) for f in fits)
    return point, ci(line), ci(noisy), ci(misfit)


def gap(cells, boot, key_a, key_b, metric):
    a, b = cells[key_a]["values"][metric].mean(), cells[key_b]["values"][metric].mean()
    return a - b, ci(boot[key_a][metric] - boot[key_b][metric])


def report(cells, boot, exclude):
    print("## Cells (mean over seeds x orders [95% bootstrap interval])\n")
    print("| budget | model (N_nv) | rank (P) | method | seeds | epochs/step | " + " | ".join(METRICS) + " |")
    print("|---|---|---|---|---|---|" + "---|" * len(METRICS))
    for key in sorted(cells, key=lambda k: (k[0], k[1], METHODS.index(k[2]))):
        cell, b = cells[key], boot[key]
        vals = [fmt(cell["values"][m].mean(), ci(b[m]), 3) if m in b else "–" for m in METRICS]
        print(f"| {key[0]:.0e} | {cell['model']} ({cell['n_nv']:,}) | {key[1]} ({cell['expert_params']:,}) | "
              f"{key[2]} | {cell['n_seeds']} | {cell['epochs']:.2f} | " + " | ".join(vals) + " |")
    for form in FORMS:
        cells_used = "every rank" if form == "N+P+E" else "rank 8"
        print(f"\n## Law y = {FORMS[form]} ({cells_used}; coefficients [95% interval])\n")
        print("| method | " + " | ".join(METRICS) + " |")
        print("|---|" + "---|" * len(METRICS))
        for method in METHODS:
            row = []
            for m in METRICS:
                fit = law(cells, boot, method, m, exclude, form)
                coef = [] if fit is None else [
                    f"{name} {fmt(fit['beta'][i], ci(fit['boot'][:, i]))}"
                    for i, name in enumerate(COEFFICIENTS[form], start=1)]
                row.append("; ".join(coef) or "–")
            print(f"| {method} | " + " | ".join(row) + " |")
    rank_axis(cells, boot)
    print("\n## ES-MoE - SeqLoRA per size (rank 8; [95% interval])\n")
    print("| budget | N_nv | " + " | ".join(METRICS) + " |")
    print("|---|---|" + "---|" * len(METRICS))
    for budget in sorted({k[0] for k in cells}):
        a, b = (budget, 8, "es-moe"), (budget, 8, "seq-lora")
        if a in cells and b in cells:
            vals = [fmt(*gap(cells, boot, a, b, m)) for m in METRICS]
            print(f"| {budget:.0e} | {cells[a]['n_nv']:,} | " + " | ".join(vals) + " |")


def rank_axis(cells, boot):
    """At the budget with several ranks: y = c + p log10 rank per method (at a fixed backbone
    a decade of rank is a decade of expert parameters)."""
    budgets = [b for b in {k[0] for k in cells} if len({k[1] for k in cells if k[0] == b}) >= 3]
    for budget in budgets:
        ranks = sorted({k[1] for k in cells if k[0] == budget})
        params = {r: cells.get((budget, r, "seq-lora"), {}).get("expert_params") for r in ranks}
        print(f"\n## LoRA rank at {budget:.0e} (ranks {ranks}; expert parameters {params}): "
              "y = c + p log10 rank, p [95% interval]\n")
        print("| method | " + " | ".join(METRICS) + " |")
        print("|---|" + "---|" * len(METRICS))
        for method in METHODS:
            keys = [(budget, r, method) for r in ranks if (budget, r, method) in cells]
            if len(keys) < 3:
                continue
            x = np.log10([k[1] for k in keys])
            row = []
            for m in METRICS:
                if m not in cells[keys[0]]["values"]:
                    row.append("–")
                    continue
                y = [cells[k]["values"][m].mean() for k in keys]
                ys = np.stack([boot[k][m] for k in keys], axis=1)
                slopes = [fit_line(x, r)[1] for r in ys]
                row.append(fmt(fit_line(x, y)[1], ci(slopes)))
            print(f"| {method} | " + " | ".join(row) + " |")


def predict(cells, boot, budget, backbone, exclude):
    """The forecast at a larger backbone (`n_nv`, `model`, `epochs`) for every method, metric
    and law form at rank 8, and for the ES-MoE - SeqLoRA gap, beside the largest ladder
    size's value carried forward."""
    rng = np.random.default_rng(SEED + 1)
    top = max(k[0] for k in cells if k[0] not in exclude and k[1] == 8)
    at = dict(backbone, expert_params=expert_params(backbone["model"], 8))
    out = {"budget": budget, **at,
           "fitted_on": sorted({k[0] for k in cells if k[0] not in exclude}), "forecasts": []}
    for form in FORMS:
        x = np.array(features(at, form))
        for method in METHODS + ["es-moe - seq-lora"]:
            pair = method.split(" - ")
            for m in METRICS:
                fits = [law(cells, boot, p, m, exclude, form) for p in pair]
                if any(f is None for f in fits):
                    continue
                point, line, run, misfit = forecast(fits, x, rng, sign=(1, -1)[:len(fits)])
                carried = (gap(cells, boot, (top, 8, pair[0]), (top, 8, pair[1]), m)[0]
                           if len(pair) == 2 else cells[(top, 8, method)]["values"][m].mean())
                out["forecasts"].append({"what": f"{method} {m}", "law": form, "value": point,
                                         "law_95": line, "cell_95": run,
                                         "cell_misfit_95": misfit, "carried": carried})
    return out


def measured(cells, boot, budget, what):
    """The measured value and interval of a forecast quantity; None before its runs exist."""
    method, m = what.rsplit(" ", 1)
    if method == "es-moe - seq-lora":
        keys = [(budget, 8, "es-moe"), (budget, 8, "seq-lora")]
        return gap(cells, boot, *keys, m) if all(k in cells for k in keys) else None
    key = (budget, 8, method)
    return (cells[key]["values"][m].mean(), ci(boot[key][m])) if key in cells else None


PLOT_METRICS = [("AF", "final FID (AF)"), ("FF", "FID forgetting (FF)"), ("PF", "FID right after learning (PF)")]
COLORS = {"es-moe": "#d62728", "seq-lora": "#1f77b4", "replay": "#2ca02c", "mtl": "#7f7f7f"}


def plot(cells, boot, exclude, path, pred=None):
    """One SVG, a panel per metric: every rank-8 cell's mean and 95% interval against N_nv
    (log axis), each method's law y = c + b log10 N_nv (fitted without `exclude`) as a line;
    cells at excluded budgets drawn hollow, and the forecast `pred` (if any) as a square with
    its cell 95% prediction interval."""
    keys = [k for k in cells if k[1] == 8]
    at = {f["what"]: f for f in (pred or {}).get("forecasts", [])
          if f["law"] == "N" and f["what"].rsplit(" ", 1)[0] in METHODS}
    xs = [math.log10(cells[k]["n_nv"]) for k in keys] + ([math.log10(pred["n_nv"])] if pred else [])
    x0, x1 = math.floor(min(xs) * 2) / 2, math.ceil(max(xs) * 2) / 2
    w, h, pad = 330, 300, 50
    parts = []
    for p, (metric, title) in enumerate(PLOT_METRICS):
        bars = [ci(boot[k][metric]) for k in keys if metric in boot[k]]
        bars += [tuple(f["cell_95"]) for what, f in at.items() if what.endswith(" " + metric)]
        y0, y1 = min(b[0] for b in bars) - 0.05, max(b[1] for b in bars) + 0.05
        ox = p * (w + pad) + pad
        sx = lambda x: ox + (x - x0) / (x1 - x0) * w
        sy = lambda y: 20 + (1 - (y - y0) / (y1 - y0)) * h
        parts.append(f'<clipPath id="panel{p}"><rect x="{ox}" y="20" width="{w}" height="{h}"/></clipPath>')
        parts.append(f'<rect x="{ox}" y="20" width="{w}" height="{h}" fill="none" stroke="#000"/>')
        parts.append(f'<text x="{ox + w / 2}" y="14" text-anchor="middle">{title}</text>')
        for e in range(math.ceil(x0), math.floor(x1) + 1):
            parts.append(f'<text x="{sx(e)}" y="{h + 36}" text-anchor="middle">1e{e}</text>')
        for t in np.linspace(y0, y1, 5)[1:-1]:
            parts.append(f'<text x="{ox - 4}" y="{sy(t) + 4}" text-anchor="end">{t:.2f}</text>')
        parts.append(f'<text x="{ox + w / 2}" y="{h + 54}" text-anchor="middle">backbone N_nv</text>')
        parts.append(f'<g clip-path="url(#panel{p})">')
        for method in METHODS:
            color = COLORS[method]
            fit = law(cells, boot, method, metric, exclude)
            if fit is not None:
                (a, ya), (b, yb) = [(x, fit["beta"] @ [1.0, x]) for x in (x0, x1)]
                parts.append(f'<line x1="{sx(a)}" y1="{sy(ya)}" x2="{sx(b)}" y2="{sy(yb)}" '
                             f'stroke="{color}" stroke-dasharray="4 3"/>')
            for k in sorted(k for k in keys if k[2] == method and metric in boot[k]):
                x, (a, b) = math.log10(cells[k]["n_nv"]), ci(boot[k][metric])
                y = cells[k]["values"][metric].mean()
                fill = "#fff" if k[0] in exclude else color
                parts.append(f'<line x1="{sx(x)}" y1="{sy(a)}" x2="{sx(x)}" y2="{sy(b)}" stroke="{color}"/>')
                parts.append(f'<circle cx="{sx(x)}" cy="{sy(y)}" r="4" fill="{fill}" stroke="{color}"/>')
            f = at.get(f"{method} {metric}")
            if f:
                x, (a, b) = math.log10(pred["n_nv"]) + 0.04 * (METHODS.index(method) - 1.5), f["cell_95"]
                parts.append(f'<line x1="{sx(x)}" y1="{sy(a)}" x2="{sx(x)}" y2="{sy(b)}" '
                             f'stroke="{color}" stroke-dasharray="2 2"/>')
                parts.append(f'<rect x="{sx(x) - 4}" y="{sy(f["value"]) - 4}" width="8" height="8" '
                             f'fill="none" stroke="{color}"/>')
        parts.append("</g>")
    for i, method in enumerate(METHODS):
        parts.append(f'<circle cx="{pad + 10 + 110 * i}" cy="{h + 76}" r="4" fill="{COLORS[method]}"/>'
                     f'<text x="{pad + 18 + 110 * i}" y="{h + 80}">{method}</text>')
    parts.append(f'<text x="{pad + 460}" y="{h + 80}">dashed: law c + b log10 N_nv; '
                 'square: forecast, its 95% PI; hollow: forward runs</text>')
    width, height = 3 * (w + pad) + pad, h + 96
    Path(path).write_text(f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
                          f'font-family="sans-serif" font-size="12">\n<rect width="100%" height="100%" fill="#fff"/>\n'
                          + "\n".join(parts) + "\n</svg>\n")


def routing(logs, cells):
    """ES-MoE's gate weight on the newest expert for the test captions of the dataset it just
    learned (steps 2-6, the last attempt of each), per budget: mean and share of steps >= 0.5."""
    pattern = re.compile(r"order (\d) step (\d): trained on \S+ .*test captions \[([^\]]*)\]")
    per_budget = {}
    for log in sorted(Path(logs).glob("*-es-moe-*.log")):
        last = {}
        for line in log.read_text().splitlines():
            m = pattern.match(line)
            if m and int(m.group(2)) > 1:
                last[m.group(1), m.group(2)] = float(m.group(3).split(",")[-1])
        run = re.match(r"c(\d+e\d+)-r(\d+)-", log.name)
        key = (float(run.group(1)), int(run.group(2)))
        per_budget.setdefault(key, []).extend(last.values())
    print("\n## ES-MoE routing: gate weight on the new expert for its own dataset's test captions\n")
    print("| budget | rank | N_nv | steps | mean weight | share >= 0.5 |")
    print("|---|---|---|---|---|---|")
    for (budget, rank), w in sorted(per_budget.items()):
        n_nv = cells.get((budget, rank, "es-moe"), {}).get("n_nv", float("nan"))
        print(f"| {budget:.0e} | {rank} | {n_nv:,} | {len(w)} | {np.mean(w):.3f} | {np.mean(np.array(w) >= 0.5):.2f} |")


def score(cells, boot, pred):
    """Each forecast against the cells measured at its budget, beside the carried value, and
    per law form how many fell inside their intervals and beat the carried value."""
    budget = pred["budget"]
    print(f"\n## Forecast at {budget:.0e} (N_nv {pred['n_nv']:,.0f}) scored\n")
    print("| quantity | law | measured [95%] | forecast [cell 95% PI] | error | inside | "
          "inside with misfit | carried (error) | closer |")
    print("|---|---|---|---|---|---|---|---|---|")
    inside = lambda v, band: band[0] <= v <= band[1]
    tally = {}
    for f in pred["forecasts"]:
        if (found := measured(cells, boot, budget, f["what"])) is None:
            print(f"| {f['what']} | {f['law']} | not run yet | {fmt(f['value'], f['cell_95'])} |||||")
            continue
        value = found[0]
        hits = (inside(value, f["cell_95"]), inside(value, f["cell_misfit_95"]),
                abs(f["value"] - value) < abs(f["carried"] - value))
        t = tally.setdefault(f["law"], [0, 0, 0, 0])
        t[:] = [a + b for a, b in zip(t, (1,) + hits)]
        yes = lambda hit: "yes" if hit else "no"
        print(f"| {f['what']} | {f['law']} | {fmt(*found)} | "
              f"{fmt(f['value'], f['cell_95'])} | {f['value'] - value:+.4f} | {yes(hits[0])} | "
              f"{yes(hits[1])} | {f['carried']:.4f} ({f['carried'] - value:+.4f}) | "
              f"{'law' if hits[2] else 'carried'} |")
    for form, (n, cell, misfit, closer) in tally.items():
        print(f"\nlaw {form}: {n} quantities measured; inside the cell 95% PI {cell}, with misfit "
              f"{misfit}; closer than the carried value {closer}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("runs")
    ap.add_argument("--at", type=float, help="forecast at this budget's backbone")
    ap.add_argument("--n-nv", type=float, help="its N_nv (the model continual will pick)")
    ap.add_argument("--model", help="its shape DxL (for its experts' parameters)")
    ap.add_argument("--epochs", type=float, help="its expert epochs per step (its D/U)")
    ap.add_argument("--out", help="write the forecast here (JSON)")
    ap.add_argument("--score", help="score this forecast against the runs at its budget")
    ap.add_argument("--plot", help="write AF, FF and PF against N_nv here (SVG)")
    ap.add_argument("--logs", help="the runs' logs (<run>.log): ES-MoE's routing per size")
    args = ap.parse_args()
    cells = load(args.runs)
    if not cells:
        sys.exit(f"{args.runs}: no finished run (no */summary.json, no *.json)")
    boot = draws(cells)
    pred = json.loads(Path(args.score).read_text()) if args.score else None
    exclude = [pred["budget"]] if pred else [args.at] if args.at else []
    report(cells, boot, exclude)
    if args.logs:
        routing(args.logs, cells)
    if pred:
        score(cells, boot, pred)
    elif args.at:
        if not (args.n_nv and args.epochs and args.model):
            sys.exit("--at needs --n-nv, --model and --epochs")
        backbone = {"n_nv": args.n_nv, "model": args.model, "epochs": args.epochs}
        pred = predict(cells, boot, args.at, backbone, exclude)
        print(f"\n## Forecast at {args.at:.0e} (N_nv {args.n_nv:,.0f}), fitted on {pred['fitted_on']}\n")
        print("| quantity | law | forecast [line 95%] | cell 95% PI | with the law's misfit | "
              "carried from the largest size |")
        print("|---|---|---|---|---|---|")
        band = lambda b: f"[{b[0]:.4f}, {b[1]:.4f}]"
        for f in pred["forecasts"]:
            print(f"| {f['what']} | {f['law']} | {fmt(f['value'], f['law_95'])} | "
                  f"{band(f['cell_95'])} | {band(f['cell_misfit_95'])} | {f['carried']:.4f} |")
        if args.out:
            Path(args.out).write_text(json.dumps(pred, indent=1, default=float) + "\n")
    if args.plot:
        plot(cells, boot, exclude, args.plot, pred)


if __name__ == "__main__":
    main()
