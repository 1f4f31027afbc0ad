"""Group a `perf report --stdio --no-children --sort dso,sym` listing into categories.

    python3 scripts/profile_categories.py REPORT.txt OUT.json [BENCH.json]
    (prints a Markdown table; with the bench's JSON, when it timed one thing, each category's
    CPU milliseconds per call too)

The categories answer #40's question of where a step's time goes on a machine class: gemm's
microkernels (the FMAs), gemm's packing and driver, our kernels (`nn`, `lm`, … and the
closures they hand to rayon, which perf names `core::ops::function::…`), memset/memcpy, libm,
threads (rayon's workers, the scheduler, futexes, yields) and the rest of the OS.
"""
import json
import re
import sys

LINE = re.compile(r"^\s*([\d.]+)%\s+(\S+)\s+\[([.k])\]\s+(.*?)\s*$")

THREAD_WORDS = ("rayon", "crossbeam", "std::thread", "futex", "sched", "yield", "switch",
                "spin", "wake", "pthread", "idle", "hrtimer")


def category(dso, kind, sym):
    """The category of one symbol of `dso` (`kind` is perf's `.` user or `k` kernel)."""
    if "gemm_f32::microkernel" in sym:
        return "gemm: microkernels"
    if sym.startswith(("gemm_common::", "gemm_f32::", "gemm::")):
        return "gemm: packing and driver"
    if any(w in sym for w in THREAD_WORDS):
        return "threads: rayon, scheduler, futexes"
    if kind == "k":
        return "OS: page faults, other kernel"
    if sym.startswith("__mem"):
        return "memset / memcpy"
    if dso.startswith("libm"):
        return "libm (exp, …)"
    if sym.startswith(("nn::", "lm::", "tokenizer::", "text::", "evaluator::", "core::ops::function")):
        return "our kernels (and their closures)"
    if sym.startswith(("candle_core::", "candle_nn::")):
        return "candle ops"
    return "other"


def cpu_seconds_per_call(bench):
    """The bench's own CPU seconds per timed call, when it timed exactly one thing."""
    found = []

    def walk(v):
        if isinstance(v, dict):
            if isinstance(v.get("own_cpu_s_per_call"), (int, float)):
                found.append(v["own_cpu_s_per_call"])
            for w in v.values():
                walk(w)
        elif isinstance(v, list):
            for w in v:
                walk(w)
    walk(bench)
    return found[0] if len(found) == 1 else None


def main():
    report, out = sys.argv[1], sys.argv[2]
    cpu_s = None
    if len(sys.argv) > 3:
        with open(sys.argv[3]) as f:
            cpu_s = cpu_seconds_per_call(json.load(f))
    shares, top = {}, []
    with open(report) as f:
        for line in f:
            m = LINE.match(line)
            if not m:
                continue
            pct, dso, kind, sym = float(m[1]), m[2], m[3], m[4]
            cat = category(dso, kind, sym)
            shares[cat] = shares.get(cat, 0.0) + pct
            top.append((pct, cat, sym))
    listed = sum(shares.values())
    shares["symbols under 0.05% each"] = max(0.0, 100.0 - listed)
    order = sorted(shares.items(), key=lambda kv: -kv[1])
    if cpu_s is None:
        print("| category | share of samples |\n|---|---|")
    else:
        print(f"| category | share of samples | CPU ms per call (of {1e3 * cpu_s:.0f}) |\n|---|---|---|")
    for cat, pct in order:
        ms = "" if cpu_s is None else f" {10 * pct * cpu_s:.1f} |"
        print(f"| {cat} | {pct:.1f}% |{ms}")
    print("\n| symbol (top 15) | category | share |\n|---|---|---|")
    for pct, cat, sym in sorted(top, reverse=True)[:15]:
        print(f"| `{sym[:90]}` | {cat} | {pct:.2f}% |")
    with open(out, "w") as f:
        json.dump({"categories": dict(order), "cpu_s_per_call": cpu_s,
                   "top_symbols": [{"symbol": s, "category": c, "share": p}
                                   for p, c, s in sorted(top, reverse=True)[:40]]}, f, indent=1)


if __name__ == "__main__":
    main()
