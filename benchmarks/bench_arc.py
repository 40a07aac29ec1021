"""Forward and forward+backward time per pair of `arc.arc_pair_integral` (the ball cutter's
groove, docs/model.md §13) against `ndf.pair_integral` on the same pairs, float32.

    python benchmarks/bench_arc.py [--pairs 8192] [--repeats 7]

Pairs: `ndf_cases.random_cases` (half vectors, footprints, scratches, alpha), each scratch cut by
the default ball (R = 0.125 mm) at a plunge uniform in the default machine range
(0.005..0.1 mm); the paper kernel sees the profile of width 4R with the same half-width. Set
``JSCRATCH_NATIVE=0`` to compare jnp with jnp (the arc kernel has no native port). Prints ns per
pair, medians of `block_until_ready` runs after one warm-up; compile time excluded.
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import arc, ndf
from jscratch.bench.ndf_cases import random_cases

R = 1.25e-4


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
    ap.add_argument("--pairs", type=int, default=8192)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args(argv)
    C = random_cases(a.pairs)
    rng = np.random.default_rng(0)
    plunge = rng.uniform(5e-6, 1e-4, a.pairs)
    half = np.sqrt(2 * R * plunge - plunge * plunge)
    w = np.full(a.pairs, 4 * R)
    d = -(w / 2) * np.log1p(-4 * half * half / (w * w))
    f32 = np.float32
    base = (C.h.astype(f32), C.footprint.astype(f32), C.p0.astype(f32), C.p1.astype(f32))
    runs = {
        "arc.arc_pair_integral": (arc.arc_pair_integral,
                                  (*base, plunge.astype(f32), np.full(a.pairs, R, f32),
                                   C.alpha.astype(f32))),
        "ndf.pair_integral": (ndf.pair_integral,
                              (*base, w.astype(f32), d.astype(f32), C.alpha.astype(f32))),
    }
    print("| kernel | forward (ns/pair) | forward+backward (ns/pair) |\n|---|---|---|")
    for name, (fn, args) in runs.items():
        fwd = jax.jit(jax.vmap(fn))
        total = jax.jit(jax.value_and_grad(lambda *x, fn=fn: jnp.sum(sum(jax.vmap(fn)(*x))),
                                           argnums=tuple(range(7))))
        print(f"| `{name}` | {ns_per_pair(fwd, args, a.pairs, a.repeats):.0f} | "
              f"{ns_per_pair(total, args, a.pairs, a.repeats):.0f} |")


if __name__ == "__main__":
    main()
