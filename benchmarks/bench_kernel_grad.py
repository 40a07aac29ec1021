"""Forward and forward+backward time per pair of `ndf.pair_integral`, split by output (D, A) and
by which arguments are differentiated: where the kernel's reverse pass spends its time.

    python benchmarks/bench_kernel_grad.py [--pairs 4096] [--repeats 7]

To compare with another kernel, check out its `jscratch/ndf.py` and rerun. Prints a Markdown table (ns per pair, medians of
`block_until_ready` runs after one warm-up; compile time excluded).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np


from jscratch import ndf
from jscratch.bench.ndf_cases import random_cases


def ns_per_pair(f, args, n, repeats):
    jax.block_until_ready(f(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t)
    return 1e9 * statistics.median(ts) / n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args(argv)
    args = tuple(jnp.asarray(x) for x in random_cases(a.pairs).astype(np.float32).args())
    outputs = {"D + A": lambda D, A: D + A, "D": lambda D, A: D, "A": lambda D, A: A}
    wrt = {"all 7 arguments": tuple(range(7)), "h, p0, p1, w, d, alpha": (0, 2, 3, 4, 5, 6),
           "p0, p1, w, d": (2, 3, 4, 5)}
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, {os.cpu_count()} CPUs, "
          f"{a.pairs} random float32 pairs\n")
    print("| output | forward | " + " | ".join(f"fwd+bwd wrt {k}" for k in wrt) + " |")
    print("|---|---|" + "---|" * len(wrt))
    for name, sel in outputs.items():
        def total(*x, sel=sel):
            return jnp.sum(jax.vmap(lambda *b: sel(*ndf.pair_integral(*b)))(*x))

        row = [ns_per_pair(jax.jit(total), args, a.pairs, a.repeats)]
        for argnums in wrt.values():
            row.append(ns_per_pair(jax.jit(jax.grad(total, argnums=argnums)), args, a.pairs,
                                   a.repeats))
        print(f"| {name} | " + " | ".join(f"{v:.0f}" for v in row) + " |")


if __name__ == "__main__":
    main()
