"""Where a PyTorch reference spends its time, by operator: how much of it is matrix products
(MKL / oneDNN) and so how far any implementation can get ahead of it without faster products.

    python3 scripts/pytorch_op_profile.py SCRIPT [ARGS...]

Runs SCRIPT (one of the bench's references, e.g. scripts/pytorch_embed_text.py) as __main__
with ARGS under torch.profiler (CPU activities), warm-up included, and prints the top operators
by self time, then one JSON line: the total self time of all operators, that of the matrix
products (the GEMM operators in PRODUCTS below) and their share. Run it with no warm-up and one
timed pass, and compare the products' time with the pass time the reference itself printed
just before: what is left of the pass is what any implementation with products exactly as
fast as PyTorch's can still save. (The profiler adds its own overhead to every operator; for
a reference with many small operators, such as the LM's, that overhead is large.)
"""
import json
import runpy
import sys

from torch.profiler import ProfilerActivity, profile

# The GEMMs only (fused attention, RNN cells and the like count as the rest).
PRODUCTS = {"aten::addmm", "aten::mm", "aten::bmm", "aten::baddbmm", "aten::addbmm"}


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    script = sys.argv[1]
    sys.argv = sys.argv[1:]
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        runpy.run_path(script, run_name="__main__")
    events = prof.key_averages()
    print(events.table(sort_by="self_cpu_time_total", row_limit=12), file=sys.stderr)
    total = sum(e.self_cpu_time_total for e in events) / 1e6
    products = sum(e.self_cpu_time_total for e in events if e.key in PRODUCTS) / 1e6
    print(json.dumps({
        "script": script,
        "args": sys.argv[1:],
        "op_self_s": total,
        "product_self_s": products,
        "product_share": products / total,
    }))


if __name__ == "__main__":
    main()
