"""Micro-benchmark of a full rebin, `grid.update`, by the native strip and cell stage
(`native.bin_cells`) against the jnp path, at the design's default size.

Scene: docs/model.md §5 (N = 20,000 scratches, midpoints uniform on a 0.3 m board, directions
uniform, lengths uniform in [0.005, 0.025] m; width 2.5e-4 m, depth 1.28e-4 m), a 256 x 256
image, float32, CPU, capacities from `grid.allocate` (margin 1.25, skin 0). Each path is
compiled once (`jit(update).lower(...).compile()`, the native one with the native kernel enabled,
the jnp one traced under `native.override(enabled=False)`), checked to give the same pairs,
warmed up, then timed: the median of ``--repeats`` `block_until_ready` calls. The machine's load
(``os.getloadavg``) is printed before and after: timings on a shared machine are noisy.

Run from the repository root:

    python benchmarks/bench_bin.py              # 20 calls per path
    python benchmarks/bench_bin.py --repeats 50 --n 20000 --size 256
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import numpy as np

from jscratch import grid, native

BOARD = (0.3, 0.3)


def scene(n, seed=0):
    rng = np.random.default_rng(seed)
    mid = rng.uniform(0, 1, (n, 2)) * BOARD
    ang = rng.uniform(0, 2 * np.pi, n)
    half = 0.5 * rng.uniform(0.005, 0.025, n)[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    p0 = np.clip(mid - half, 0, BOARD).astype(np.float32)
    p1 = np.clip(mid + half, 0, BOARD).astype(np.float32)
    return p0, p1, np.full(n, 2.5e-4, np.float32), np.full(n, 1.28e-4, np.float32)


def compiled(spec, args, enabled):
    """`grid.update` for `spec`, traced afresh with the native kernel `enabled` or not."""
    with native.override(enabled=enabled):
        fn = jax.jit(lambda *a: grid.update.__wrapped__(spec, *a))
        return fn.lower(*args).compile()


def median_ms(fn, args, repeats):
    for _ in range(3):
        jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times), 1e3 * min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000, help="scratches")
    ap.add_argument("--size", type=int, default=256, help="image side, pixels")
    ap.add_argument("--repeats", type=int, default=20, help="timed calls per path")
    a = ap.parse_args(argv)
    if not native.available(np.float32):
        raise SystemExit(f"the native kernel is unavailable: {native.status()['why']}")
    args = scene(a.n)
    shape = (a.size, a.size)
    spec = grid.allocate(*args, board=BOARD, shape=shape)
    fns = {"jnp": compiled(spec, args, False), "native": compiled(spec, args, True)}
    out = {k: fn(*args) for k, fn in fns.items()}
    for name in ("pixel", "scratch", "valid", "overflow"):
        assert np.array_equal(getattr(out["jnp"], name), getattr(out["native"], name)), name
    pairs = int(np.asarray(out["native"].valid).sum())
    print(f"grid.update, N={a.n}, {a.size}x{a.size} px, {pairs} pairs, capacities "
          f"strips={spec.strip_capacity} rows={spec.rows_per_strip} "
          f"pairs={spec.pair_capacity}, float32, {jax.devices()[0].device_kind}, "
          f"{native.threads()} threads allowed")
    print("load average before: %.2f %.2f %.2f" % os.getloadavg())
    res = {}
    for _ in range(2):  # alternate, so that a change of load hits both paths
        for k, fn in fns.items():
            res.setdefault(k, []).append(median_ms(fn, args, a.repeats // 2 or 1))
    print("load average after:  %.2f %.2f %.2f" % os.getloadavg())
    for k, rs in res.items():
        print(f"{k:>6}: median {statistics.median(r[0] for r in rs):7.2f} ms "
              f"(halves {', '.join(f'{r[0]:.2f}' for r in rs)}; fastest {min(r[1] for r in rs):.2f} ms)")
    j, nat = (statistics.median(r[0] for r in res[k]) for k in ("jnp", "native"))
    print(f"speed-up: {j / nat:.1f}x")


if __name__ == "__main__":
    main()
