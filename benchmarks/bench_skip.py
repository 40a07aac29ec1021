"""The default design step with pair-views skipped inside the kernel (``skip_eps``, docs/model.md
§11) against the full step: one process, the same parameters and pair list (the default design's
after ``--warm`` full steps), one compiled step per tolerance, the tolerances alternated round by
round; medians and minima of the step's wall time, and the share of pair-views each skips.

    python benchmarks/bench_skip.py [--eps 1e-30,2e-5,5e-5,1e-4,1e-3] [--warm 30] [--rounds 15]

``1e-30`` skips nothing that is not exactly zero: it measures what computing the bound costs.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import numpy as np

from jscratch import native
from jscratch.bench import machine_line
from jscratch.bench.rendering import design_step_state
from jscratch.design import solver
from jscratch.design.config import DesignConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--eps", default="1e-30,2e-5,5e-5,1e-4,1e-3",
                    help="comma-separated tolerances (0 is always timed)")
    ap.add_argument("--scratches", type=int, default=20000)
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--warm", type=int, default=30, help="full steps taken before the timing")
    ap.add_argument("--rounds", type=int, default=15)
    args = ap.parse_args()
    print(machine_line())
    p, opt, lists, ctx, adam = design_step_state(DesignConfig(n_scratches=args.scratches),
                                                 args.views, 256, args.warm)
    epss = [0.0] + [float(e) for e in args.eps.split(",") if float(e) != 0]
    ctxs = {e: dataclasses.replace(ctx, skip_eps=e) for e in epss}
    pairs = int(np.asarray(lists.shared.valid).sum())
    print(f"{args.views} views, {args.scratches} scratches, 256 px, after {args.warm} steps: "
          f"{pairs:,} pairs, kernel {native.status()['kernel']}; {args.rounds} rounds")

    def one(e):
        out = solver.step(p, opt, lists, ctxs[e], adam)
        jax.block_until_ready(out[0])
        return out

    kept = {}
    for e in epss:  # compile, warm up, and count the pair-views each evaluates
        one(e)
        kept[e] = int(np.sum(np.asarray(one(e)[5])[:args.views]))
    times = {e: [] for e in epss}
    for _ in range(args.rounds):
        for e in epss:
            t = time.perf_counter()
            one(e)
            times[e].append(time.perf_counter() - t)
    base = np.median(times[0.0])
    print("| skip_eps | pair-views evaluated | median step (ms) | min (ms) | against 0 |")
    print("|---|---|---|---|---|")
    for e in epss:
        med = np.median(times[e])
        print(f"| {e:g} | {kept[e] / kept[0.0]:.1%} | {1e3 * med:.1f} | "
              f"{1e3 * min(times[e]):.1f} | {med / base - 1:+.1%} |")


if __name__ == "__main__":
    main()
