"""Where a pair-view's forward + backward goes in the kernel: its two public stages timed and
costed apart (XLA cost analysis), M views sharing each pair's geometry as in the renderer.

    python benchmarks/bench_kernel_parts.py [--views 3] [--repeats 7]

Rows (ns, flops and bytes per pair-view, medians after a warm-up, compile time apart, gradients
compiled with `render.grad_compiler_options`):

- ``whole kernel``: `ndf.pair_integral`, ``D + A``, gradient with respect to the half vectors,
  endpoints, width, depth and alpha;
- ``geometry``: `ndf.pair_geometry` alone (strip clip, cut to the groove, area, compaction),
  once per pair, its outputs summed;
- ``lit, k pieces``: `ndf.lit_integral(..., pieces=k)` from a precomputed geometry (gradient
  with respect to the geometry, half vectors and alpha), per view: ``k = 2`` is what most chunks
  of a scene integrate (`render.PIECE_BUDGETS`);
- ``whole pair, native``: `native.pairs` (what the renderer's chunks run where the native kernel
  is available): the geometry and its Jacobian once per pair, then the M views, ``D + A``,
  gradient with respect to the half vectors, endpoints, width, depth and alpha (a custom call:
  XLA's cost analysis does not see its flops and bytes).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import lobe, native, ndf
from jscratch import render
from jscratch.bench import median_time
from jscratch.bench.ndf_cases import random_cases


def _ns(fn, args, per, repeats):
    return 1e9 * median_time(lambda: fn(*args), repeats)[0] / per


def _row(name, f, args, argnums, per, repeats, costs=True):
    fwd = jax.jit(f).lower(*args).compile()
    grad = jax.jit(jax.grad(f, argnums=argnums),
                   compiler_options=render.grad_compiler_options()).lower(*args).compile()
    ca = grad.cost_analysis()
    ca = ca[0] if isinstance(ca, list) else ca
    cost = (f"{ca['flops'] / per:,.0f} | {ca['bytes accessed'] / per:,.0f}" if costs else "- | -")
    print(f"| {name} | {_ns(fwd, args, per, repeats):.0f} | {_ns(grad, args, per, repeats):.0f} |"
          f" {cost} |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--pairs", type=int, default=16384)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args(argv)
    n, m = a.pairs, a.views
    C = random_cases(n).astype(np.float32)
    h, fp, p0, p1, w, d, al = (jnp.asarray(x) for x in C.args())
    rng = np.random.default_rng(1)
    H = rng.normal(size=(m, n, 3))
    H[..., 2] = np.abs(H[..., 2]) + 0.5
    H = jnp.asarray(H / np.linalg.norm(H, axis=-1, keepdims=True), jnp.float32)
    per = n * m
    print(f"jax {jax.__version__}, {n} random float32 pairs x {m} views; per pair-view:\n")
    print("| part | fwd ns | fwd+bwd ns | fwd+bwd flop | fwd+bwd bytes |")
    print("|---|---|---|---|---|")

    def whole(H, p0, p1, w, d, al):
        per_pair = jax.vmap(ndf.pair_integral)
        D, A = jax.vmap(per_pair, in_axes=(0, None, None, None, None, None, None))(
            H, fp, p0, p1, w, d, al)
        return jnp.sum(D) + jnp.sum(A[0])

    _row("whole kernel", whole, (H, p0, p1, w, d, al), tuple(range(6)), per, a.repeats)

    def geometry(p0, p1, w, d):
        g = jax.vmap(ndf.pair_geometry)(fp, p0, p1, w, d)
        return sum(jnp.sum(x) for x in jax.tree_util.tree_leaves(g)
                   if jnp.issubdtype(x.dtype, jnp.floating))

    _row("geometry (per pair, / M)", geometry, (p0, p1, w, d), (0, 1, 2, 3), per, a.repeats)

    g = jax.jit(jax.vmap(ndf.pair_geometry))(fp, p0, p1, w, d)._replace(count=None)
    for k in sorted({*render.PIECE_BUDGETS}):
        def lit(g, H, al, k=k):
            f = jax.vmap(jax.vmap(lambda g, h, a: ndf.lit_integral(g, h, a, pieces=k)),
                         in_axes=(None, 0, None))
            return jnp.sum(f(g, H, al))

        _row(f"lit, {k} pieces (per view)", lit, (g, H, al), (0, 1, 2), per, a.repeats)

    if native.available(jnp.float32):
        valid, n_gl = jnp.ones((n,), bool), lobe.nodes(jnp.float32)

        def fused(H, p0, p1, w, d, al):
            D, A = native.pairs(n_gl, fp, p0, p1, w, d, al, valid, H)
            return jnp.sum(D) + jnp.sum(A)

        _row("whole pair, native (geometry once, M views)", fused, (H, p0, p1, w, d, al),
             tuple(range(6)), per, a.repeats, costs=False)


if __name__ == "__main__":
    main()
