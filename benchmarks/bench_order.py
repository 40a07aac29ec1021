"""Scratch ordering benchmark: rapid travel and wall time for input order, greedy, improved.

    python benchmarks/bench_order.py [--sizes 10000 40000 80000] [--time-limit 40]

Designs are :func:`jscratch.designfile.demo_design` (brushed rings, 5-25 mm scratches on a
0.3 m board); travel in metres. Prints a Markdown table and writes benchmarks/results/fabricate.md.
"""

import argparse
import os
import sys
import time


import numpy as np

from jscratch.bench import machine_line
from jscratch.designfile import demo_design
from jscratch.toolpath import best_directions, greedy_order, improve_order, path_travel


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 40_000, 80_000])
    ap.add_argument("--time-limit", type=float, default=40.0, help="local search limit, s (the CLI default)")
    args = ap.parse_args()
    rows = []
    for n in args.sizes:
        d = demo_design(n, seed=0)
        t_in = path_travel(d.p0, d.p1, np.arange(n), np.zeros(n, bool))
        t0 = time.perf_counter()
        o, f = greedy_order(d.p0, d.p1)
        t_greedy = time.perf_counter() - t0
        tr_greedy = path_travel(d.p0, d.p1, o, f)
        t1 = time.perf_counter()
        o2, _ = improve_order(d.p0, d.p1, o, f, k=10, time_limit=args.time_limit)
        f2 = best_directions(d.p0, d.p1, o2)
        t_imp = time.perf_counter() - t1
        tr = path_travel(d.p0, d.p1, o2, f2)
        rows.append((n, t_in, tr_greedy, t_greedy, tr, t_greedy + t_imp))
        print(f"n={n} done", file=sys.stderr, flush=True)
    head = [
        "# Fabrication: scratch ordering",
        "",
        f"Machine: {machine_line()}; numpy {np.__version__} (no jax in the ordering).",
        f"command: `python benchmarks/bench_order.py --sizes {' '.join(map(str, args.sizes))} --time-limit {args.time_limit:g}`",
        "Travel in metres (demo design, 0.3 m board);",
        "time = wall seconds (improved = greedy + 2-opt/Or-opt within the time limit + direction DP).",
        "",
        "| scratches | input-order travel (m) | greedy travel (m) | greedy time (s) | improved travel (m) | improved vs greedy | total time (s) |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    lines = [
        f"| {n} | {ti:.1f} | {tg:.2f} | {sg:.2f} | {t:.2f} | {100 * (t / tg - 1):+.1f}% | {s:.1f} |"
        for n, ti, tg, sg, t, s in rows
    ]
    text = "\n".join(head + lines) + "\n"
    print(text)
    out = os.path.join(os.path.dirname(__file__), "results", "fabricate.md")
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        f.write(text)


if __name__ == "__main__":
    main()
