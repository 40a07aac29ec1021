"""Where a pair-view's forward + backward goes in the current kernel: its parts timed and costed
apart (XLA cost analysis), M views sharing each pair's geometry as in the renderer.

    python benchmarks/bench_kernel_parts.py [--views 3] [--repeats 7]

This script measures the kernel's internals on purpose and so calls private functions of
`jscratch.ndf`; its rows (ns, flops and bytes per pair-view, medians after a warm-up, compile
time apart, gradients compiled with `render.grad_compiler_options`):

- ``whole kernel``: `ndf.pair_integral`, ``D + A``, gradient with respect to the half vectors,
  endpoints, width, depth and alpha;
- ``strip clip``: the view-independent part alone (`_groove`: frame, footprint cut to the
  scratch's length), once per pair;
- ``area``: ``A`` alone (strip clip + cut to the groove + its reverse pass), once per pair;
- ``lit integral``: `_lit_sum` alone, from precomputed pieces, slabs and lobe parameters (cut
  to the lit slab, closed form + Gauss-Legendre with partials, reverse pass), per view.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import ndf
from jscratch import render
from jscratch.bench import median_time
from jscratch.bench.ndf_cases import random_cases


def _ns(fn, args, per, repeats):
    return 1e9 * median_time(lambda: fn(*args), repeats)[0] / per


def _row(name, f, args, argnums, per, repeats):
    fwd = jax.jit(f).lower(*args).compile()
    grad = jax.jit(jax.grad(f, argnums=argnums),
                   compiler_options=render.grad_compiler_options()).lower(*args).compile()
    ca = grad.cost_analysis()
    ca = ca[0] if isinstance(ca, list) else ca
    print(f"| {name} | {_ns(fwd, args, per, repeats):.0f} | {_ns(grad, args, per, repeats):.0f} |"
          f" {ca['flops'] / per:,.0f} | {ca['bytes accessed'] / per:,.0f} |", flush=True)


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
    n_gl = ndf._nodes(jnp.float32)
    print(f"jax {jax.__version__}, {n} random float32 pairs x {m} views; per pair-view:\n")
    print("| part | fwd ns | fwd+bwd ns | fwd+bwd flop | fwd+bwd bytes |")
    print("|---|---|---|---|---|")

    def whole(H, p0, p1, w, d, al):
        per_pair = jax.vmap(ndf.pair_integral)
        D, A = jax.vmap(per_pair, in_axes=(0, None, None, None, None, None, None))(
            H, fp, p0, p1, w, d, al)
        return jnp.sum(D) + jnp.sum(A[0])

    _row("whole kernel", whole, (H, p0, p1, w, d, al), tuple(range(6)), per, a.repeats)

    def strip(p0, p1, w, d):
        G = jax.vmap(ndf._groove)(fp, p0, p1, w, d)
        ua, ub, Ya, Yb = G.pieces
        return jnp.sum(ua * Ya + ub * Yb) + jnp.sum(G.X)

    _row("strip clip (per pair, / M)", strip, (p0, p1, w, d), (0, 1, 2, 3), per, a.repeats)

    def area(p0, p1, w, d):
        def one(fp, p0, p1, w, d):
            G = ndf._groove(fp, p0, p1, w, d)
            return ndf._area_sum(*G.pieces, -G.X, G.X)

        return jnp.sum(jax.vmap(one)(fp, p0, p1, w, d))

    _row("area (per pair, / M)", area, (p0, p1, w, d), (0, 1, 2, 3), per, a.repeats)

    def inputs(h, fp, p0, p1, w, d, al):
        G = ndf._groove(fp, p0, p1, w, d)
        hx, hy, hz, lo, hi = ndf._view(G, h)
        return G.pieces, lo, hi, ndf._Lobe(hx, hy, hz, al).params()

    per_view = jax.vmap(jax.vmap(inputs), in_axes=(0, None, None, None, None, None, None))
    pieces, lo, hi, params = jax.jit(per_view)(H, fp, p0, p1, w, d, al)

    def lit(pieces, lo, hi, params):
        f = lambda pc, lo, hi, p: ndf._lit_sum(n_gl, *pc, lo, hi, p)
        return jnp.sum(jax.vmap(jax.vmap(f))(pieces, lo, hi, params))

    _row("lit integral (per view)", lit, (pieces, lo, hi, params), (0, 1, 2, 3), per, a.repeats)


if __name__ == "__main__":
    main()
