"""Ensembles of seeds past C_sat (issue #55): the captured test CE of every ensemble of the seeds
of each subset's 3·10¹³ best size (`motionscale model loss --model RUN …`: the mean of the
members' next-token probabilities, from each run folder's final weights), and the law
L(k) = L_inf + c/k fitted on the ensembles of up to K_FIT members, with its forecast at
k = K_PREDICT: k seeds of a C_sat run cost k·C_sat FLOPs.

    python3 ensembles.py MOTIONSCALE RUNS_DIR [K_FIT]   # writes ensembles.csv beside this file

RUNS_DIR is the sweep's `--out` folder (the run folders' config.json name their token set by
the paths the sweep was run with: run this from that folder's working directory).
"""
import csv, itertools, pathlib, re, subprocess, sys

HERE = pathlib.Path(__file__).resolve().parent
BIN, RUNS = sys.argv[1], pathlib.Path(sys.argv[2])
K_FIT = int(sys.argv[3]) if len(sys.argv) > 3 else 3
K_PREDICT = 5
CELLS = {"all-1_2": "c3e13-320x4-v1024-dall-1_2", "all-1": "c3e13-256x4-v1024-dall-1",
         "all-1_4": "c3e13-320x4-v1024-dall-1_4"}
SEEDS = ["", "-s1", "-s2", "-s3", "-s4"]


def captured_ce(members):
    out = subprocess.run([BIN, "model", "loss", *sum((["--model", str(m)] for m in members), [])],
                         check=True, capture_output=True, text=True).stdout
    return float(re.search(r"^\s+real\s+CE (\S+)", out, re.M).group(1))


def fit(points):
    """Least squares of L = L_inf + c/k over (k, L) points."""
    xs, ys = [1 / k for k, _ in points], [l for _, l in points]
    n, mx, my = len(xs), sum(xs) / len(xs), sum(ys) / len(ys)
    c = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)
    return my - c * mx, c


def main():
    rows = []
    for data, base in CELLS.items():
        runs = [RUNS / f"{base}{s}" / "train" for s in SEEDS]
        runs = [r for r in runs if (r / "model.safetensors").is_file()]
        # Every ensemble of the first three seeds (the fit's), and all the seeds together.
        groups = [c for k in range(1, 4) for c in itertools.combinations(runs[:3], k)]
        groups += [tuple(runs)] if len(runs) > 3 else []
        for members in groups:
            rows.append({"data": data, "k": len(members),
                         "members": " ".join(m.parent.name for m in members),
                         "captured_ce": f"{captured_ce(members):.4f}"})
            print(rows[-1], flush=True)
    with open(HERE / "ensembles.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    for data in CELLS:
        points = [(r["k"], float(r["captured_ce"])) for r in rows if r["data"] == data and r["k"] <= K_FIT]
        l_inf, c = fit(points)
        mean = {k: sum(l for kk, l in points if kk == k) / sum(kk == k for kk, _ in points)
                for k in sorted({k for k, _ in points})}
        got = [float(r["captured_ce"]) for r in rows if r["data"] == data and r["k"] == K_PREDICT]
        scored = f"; measured {got[0]:.4f}, error {l_inf + c / K_PREDICT - got[0]:+.4f}" if got else ""
        print(f"{data}: L(k) = {l_inf:.4f} + {c:.4f}/k on k <= {K_FIT} ({len(points)} ensembles); "
              f"means {', '.join(f'k={k} {v:.4f}' for k, v in mean.items())}; "
              f"forecast k={K_PREDICT}: {l_inf + c / K_PREDICT:.4f}{scored}")


if __name__ == "__main__":
    main()
