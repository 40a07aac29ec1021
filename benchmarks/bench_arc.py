"""Forward and forward+backward time per pair of `arc.arc_pair_integral` (the ball cutter's
groove, docs/model.md §13) against `ndf.pair_integral` on the same pairs, float32.

    python benchmarks/bench_arc.py [--pairs 8192] [--repeats 7] [--best] [--native-only]

Pairs: `ndf_cases.random_cases` (half vectors, footprints, scratches, alpha), each scratch cut by
the default ball (R = 0.125 mm) at a plunge uniform in the default machine range
(0.005..0.1 mm); the paper kernel sees the profile of width 4R with the same half-width. Set
``JSCRATCH_NATIVE=0`` to compare jnp with jnp. Prints ns per pair, medians (``--best``: the
fastest) of `block_until_ready` runs after one warm-up; compile time excluded.

Then the native whole-pair kernel (`native.pairs`, where it is available) with
``profile="arc"`` against ``profile="paper"`` on the same pairs at ``--views`` views (the arc's
(width, depth) from `arc.arc_groove`, the paper's as above): ns per pair-view, forward
(`native.pair_values`) and forward+backward (value and gradient of `native.pairs`).
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import arc, lobe, native, ndf
from jscratch.bench.ndf_cases import random_cases

R = 1.25e-4


def ns_per_pair(f, args, n, repeats, best=False):
    jax.block_until_ready(f(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t)
    return 1e9 * (min(ts) if best else statistics.median(ts)) / n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=8192)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--best", action="store_true",
                    help="the fastest run instead of the median (steadier on a shared machine)")
    ap.add_argument("--native-only", action="store_true", help="only the native kernel's table")
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
    for name, (fn, args) in ({} if a.native_only else runs).items():
        fwd = jax.jit(jax.vmap(fn))
        total = jax.jit(jax.value_and_grad(lambda *x, fn=fn: jnp.sum(sum(jax.vmap(fn)(*x))),
                                           argnums=tuple(range(7))))
        print(f"| `{name}` | {ns_per_pair(fwd, args, a.pairs, a.repeats, a.best):.0f} | "
              f"{ns_per_pair(total, args, a.pairs, a.repeats, a.best):.0f} |")
    if not native.available(jnp.float32):
        print(f"\nnative kernel unavailable: {native.status()['why']}")
        return
    H = np.stack([np.roll(C.h, 17 * v, axis=0) for v in range(a.views)]).astype(f32)
    wa, da = (np.asarray(t, f32) for t in arc.arc_groove(plunge, np.full(a.pairs, R)))
    valid = np.ones(a.pairs, bool)
    print(f"\n| native `pairs` ({a.views} views, float32) | forward (ns/pair-view) | "
          "forward+backward (ns/pair-view) |\n|---|---|---|")
    for profile, ng, wd in (("paper", lobe.nodes(f32), (w, d)), ("arc", arc.nodes(f32), (wa, da))):
        args = (*base[1:], *(np.asarray(x, f32) for x in wd), C.alpha.astype(f32), valid, H)
        fwd = jax.jit(lambda *x, p=profile, ng=ng: native.pair_values(ng, *x, profile=p))

        def loss(p0, p1, w_, d_, al, h, rest, p=profile, ng=ng):
            fp, valid = rest
            D, A = native.pairs(ng, fp, p0, p1, w_, d_, al, valid, h, p)
            return jnp.sum(D) + jnp.sum(A)

        total = jax.jit(jax.value_and_grad(loss, argnums=tuple(range(6))))
        targs = (*args[1:6], args[7], (args[0], args[6]))
        nv = a.pairs * a.views
        print(f"| `{profile}` (n_gl {ng}) | {ns_per_pair(fwd, args, nv, a.repeats, a.best):.0f} | "
              f"{ns_per_pair(total, targs, nv, a.repeats, a.best):.0f} |")


if __name__ == "__main__":
    main()
