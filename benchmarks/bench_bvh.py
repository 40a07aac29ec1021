"""Benchmark of `jscratch.bvh`: binning time, padding efficiency, binning against shading, culling.

Scenes follow docs/model.md §5 (midpoints uniform on a 0.3 m board, directions uniform, lengths
uniform in [0.005, 0.025] m; width 2.5e-4 m, depth 1.28e-4 m, alpha 0.04), float32, CPU.

Table 1 (binning): for each scratch count N and image size,
- `allocate`: host-side measurement (wall, first call, compilations included),
- `compile`: `jit(bvh.update).lower(...).compile()`,
- `bin`: median of `block_until_ready` runs of the compiled `update` (a full rebin),
- `needs_rebin`: the O(N) motion test that lets an optimisation step skip the rebin,
- `pairs`, `slots` (pair capacity L), padding efficiency `pairs / L` (flat list) against the
  per-pixel `(P, K)` layout with `K` the busiest pixel's count (`pairs / (P K)`),
- `shade`: median time of `jax.vmap(ndf.pair_integral)` over the L slots of the padded list for
  one view (chunked with `lax.map(batch_size=...)`; `D_hat` and `A` summed per pixel),
- `bin/shade`: the ratio (binning is done once per optimisation step at most, shading per view).

Table 2 (culling, one scene, every view of `views_on_circle`): for each `eps`, the pairs kept
(fraction of the unculled list, over all views), the cull time, the shading time of the compacted
lists, the radiance error against `eps = 0` (max over pixels and views of the error over the
image's peak radiance) and the largest ratio of a pixel's error to its documented bound (must be
<= 1, see the `jscratch.bvh` docstring).

Run from the repository root:

    python benchmarks/bench_bvh.py            # full tables (minutes on 2 cores)
    python benchmarks/bench_bvh.py --quick    # small smoke run

Writes the Markdown to `benchmarks/results/bvh.md` (or `--out`).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import bvh, cull, ndf, render
from jscratch.bench import machine_line

BOARD = (0.3, 0.3)


def scene(n, seed=0, dtype=np.float32):
    rng = np.random.default_rng(seed)
    mid = rng.uniform(0, 1, (n, 2)) * BOARD
    ang = rng.uniform(0, 2 * np.pi, n)
    half = 0.5 * rng.uniform(0.005, 0.025, n)[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    p0 = np.clip(mid - half, 0, BOARD).astype(dtype)
    p1 = np.clip(mid + half, 0, BOARD).astype(dtype)
    width = np.full(n, 2.5e-4, dtype)
    depth = np.full(n, 1.28e-4, dtype)
    alpha = np.full(n, 0.04, dtype)
    return p0, p1, width, depth, alpha


def median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def make_shader(shape, batch):
    """Jitted `(pixel, scratch, valid, fps, h, p0, p1, w, d, a) -> (D_sum, A_sum)` per pixel."""
    n_pix = shape[0] * shape[1]

    def shade(pixel, scratch, valid, fps, h, p0, p1, width, depth, alpha):
        n = p0.shape[0]

        def one(args):  # lax.map(batch_size=) vmaps this over chunks of pairs
            pix, scr, ok = args
            s = jnp.clip(scr, 0, n - 1)
            d_hat, area = ndf.pair_integral(
                h[pix], fps[pix], p0[s], p1[s], width[s], depth[s], alpha[s]
            )
            return jnp.where(ok, d_hat, 0.0), jnp.where(ok, area, 0.0)

        d_hat, area = jax.lax.map(one, (pixel, scratch, valid), batch_size=batch)
        d_sum = jax.ops.segment_sum(d_hat, pixel, n_pix)
        a_sum = jax.ops.segment_sum(area, pixel, n_pix)
        return d_sum, a_sum

    return jax.jit(shade)


def host_compact(pairs, capacity):
    """Valid pairs first, padded to `capacity` (host numpy; as the render driver does)."""
    v = np.asarray(pairs.valid)
    pix = np.asarray(pairs.pixel)[v]
    scr = np.asarray(pairs.scratch)[v]
    k = len(pix)
    out_pix = np.zeros(capacity, np.int32)
    out_scr = np.full(capacity, np.asarray(pairs.scratch).max(initial=0), np.int32)
    out_pix[:k], out_scr[:k] = pix, scr
    return jnp.asarray(out_pix), jnp.asarray(out_scr), jnp.asarray(np.arange(capacity) < k)


def bucket(k, chunk):
    return max(chunk, -(-k // chunk) * chunk)


def binning_table(counts, sizes, repeats, batch, shade_on):
    rows = []
    header = (
        "| N | image | allocate (s) | compile (s) | bin (ms) | needs_rebin (ms) | pairs | slots L "
        "| pairs/L | (P,K) layout: K, pairs/(P K) | shade 1 view (ms) | bin/shade |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|"
    )
    for n in counts:
        p0, p1, width, depth, alpha = scene(n)
        for size in sizes:
            shape = (size, size)
            t = time.perf_counter()
            spec = bvh.allocate(p0, p1, width, depth, board=BOARD, shape=shape)
            t_alloc = time.perf_counter() - t
            t = time.perf_counter()
            upd = jax.jit(bvh.update).lower(spec, p0, p1, width, depth).compile()
            t_comp = time.perf_counter() - t
            pairs = upd(spec, p0, p1, width, depth)
            assert not bool(pairs.overflow)
            t_bin = median_time(lambda: upd(spec, p0, p1, width, depth).pixel, repeats)
            needs = bvh.needs_rebin.lower(pairs, p0, p1, width, depth).compile()
            t_needs = median_time(lambda: needs(pairs, p0, p1, width, depth), repeats)
            n_pairs = int(np.asarray(pairs.valid).sum())
            per_pixel = np.bincount(
                np.asarray(pairs.pixel)[np.asarray(pairs.valid)], minlength=size * size
            )
            k_max = int(per_pixel.max())
            row = (
                f"| {n} | {size}x{size} | {t_alloc:.2f} | {t_comp:.2f} | {1e3 * t_bin:.1f} "
                f"| {1e3 * t_needs:.2f} "
                f"| {n_pairs} | {spec.pair_capacity} | {n_pairs / spec.pair_capacity:.2f} "
                f"| {k_max}, {n_pairs / (size * size * k_max):.3f} "
            )
            if shade_on:
                board = render.Board(shape=shape, Sx=BOARD[0], Sy=BOARD[1])
                views = render.views_on_circle(1, np.radians(30.0), board=board,
                                               dtype=jnp.float32)
                h = render.half_vectors(views, board, jnp.float32)[0]
                fps = render.pixel_footprints(board, jnp.float32)
                shader = make_shader(shape, batch)
                args = (pairs.pixel, pairs.scratch, pairs.valid, fps, h, p0, p1, width, depth,
                        alpha)
                shader_c = shader.lower(*args).compile()
                t_sh = median_time(lambda: shader_c(*args), max(1, repeats // 2))
                row += f"| {1e3 * t_sh:.0f} | {t_bin / t_sh:.3f} |"
            else:
                row += "| - | - |"
            print(row, flush=True)
            rows.append(row)
    return header + "\n" + "\n".join(rows)


def cull_table(n, size, eps_list, n_views, repeats, batch):
    shape = (size, size)
    p0, p1, width, depth, alpha = scene(n, seed=1)
    board = render.Board(shape=shape, Sx=BOARD[0], Sy=BOARD[1])
    views = render.views_on_circle(n_views, np.radians(30.0), board=board, dtype=jnp.float32)
    hs = render.half_vectors(views, board, jnp.float32)
    fps = render.pixel_footprints(board, jnp.float32)
    full, _ = bvh.build_pairs(p0, p1, width, depth, board=BOARD, shape=shape)
    shader = make_shader(shape, batch)
    cull_fn = jax.jit(cull.cull)
    s_p = BOARD[0] * BOARD[1] / (size * size)
    n_full = int(np.asarray(full.valid).sum())

    # eps = 0: the reference D sums and coverage (coverage always from the unculled list)
    cap0 = bucket(n_full, batch)
    ref = []
    for j in range(n_views):
        args = (*host_compact(full, cap0), fps, hs[j], p0, p1, width, depth, alpha)
        ref.append(shader(*args))
    cover = ref[0][1] / s_p
    d_ref = jnp.stack([r[0] for r in ref]) / s_p
    rad_ref = np.asarray(render.shade(d_ref, cover, views, board))
    # radiance per unit D_P at each pixel (shade is affine in D_P)
    unit = np.asarray(render.shade(d_ref + 1.0, cover, views, board)) - rad_ref

    header = (
        "| eps | pairs kept | cull (ms, all views) | single-pair shade (ms, all views) "
        "| shading time saved "
        "| max error / peak radiance | max error / bound |\n|---|---|---|---|---|---|---|"
    )
    rows = []
    t_shade0 = None
    compiled = {}  # one compiled shader per slot count (buckets of `batch` pairs)
    jax.block_until_ready(cull_fn(full, p0, p1, width, depth, alpha, hs[0], 0.0).valid)  # compile
    for eps in eps_list:
        culled = [cull_fn(full, p0, p1, width, depth, alpha, hs[j], eps) for j in range(n_views)]
        t_cull = median_time(
            lambda: [cull_fn(full, p0, p1, width, depth, alpha, hs[j], eps).valid  # noqa: B023
                     for j in range(n_views)], repeats)
        kept = [int(np.asarray(c.valid).sum()) for c in culled]
        # each view's list compacted to its own bucketed capacity (culling saves per view)
        compacted = [host_compact(c, bucket(k, batch)) for c, k in zip(culled, kept)]
        for cp in compacted:
            cap = cp[0].shape[0]
            if cap not in compiled:
                compiled[cap] = shader.lower(*cp, fps, hs[0], p0, p1, width, depth,
                                             alpha).compile()

        def run_all():
            return [compiled[cp[0].shape[0]](*cp, fps, hs[j], p0, p1, width, depth, alpha)[0]
                    for j, cp in enumerate(compacted)]  # noqa: B023

        d_sums = run_all()
        t_sh = median_time(run_all, repeats)
        t_shade0 = t_sh if t_shade0 is None else t_shade0
        rad = np.asarray(render.shade(jnp.stack(d_sums) / s_p, cover, views, board))
        err = rad_ref - rad
        # documented bound: eps * sum_dropped A / (pi alpha^2 S_P), in radiance units
        bound = []
        for j in range(n_views):
            dropped = np.asarray(full.valid) & ~np.asarray(culled[j].valid)
            a = np.asarray(shader(*host_compact(
                bvh.Pairs(full.pixel, full.scratch, jnp.asarray(dropped), full.overflow),
                bucket(int(dropped.sum()), batch)), fps, hs[j], p0, p1, width, depth, alpha)[1])
            bound.append(eps * a / (np.pi * 0.04**2 * s_p) * unit[j])
        bound = np.stack(bound)
        with np.errstate(divide="ignore", invalid="ignore"):
            over = np.where(bound > 0, err / bound, np.where(np.abs(err) > 0, np.inf, 0.0))
        row = (
            f"| {eps:g} | {sum(kept) / (n_views * n_full):.3f} | {1e3 * t_cull:.0f} "
            f"| {1e3 * t_sh:.0f} | {1 - t_sh / t_shade0:.0%} "
            f"| {np.max(np.abs(err)) / np.max(rad_ref):.2e} | {np.max(over):.3f} |"
        )
        print(row, flush=True)
        rows.append(row)
    return header + "\n" + "\n".join(rows)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small smoke run")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per median")
    parser.add_argument("--batch", type=int, default=65536, help="pairs per lax.map chunk")
    parser.add_argument("--no-shade", action="store_true", help="skip the shading timings")
    parser.add_argument("--no-cull", action="store_true", help="skip the culling table")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                      "bvh.md"))
    args = parser.parse_args(argv)
    if args.quick:
        counts, sizes, cull_n, cull_size, views, batch = (2000,), (64, 128), 2000, 64, 2, 4096
    else:
        counts, sizes, cull_n, cull_size, views, batch = (
            (20000, 60000), (256, 512), 20000, 256, 4, args.batch
        )
    eps_list = (0.0, 1e-4, 1e-3, 1e-2, 3e-2, 1e-1)
    print("## Binning\n")
    t1 = binning_table(counts, sizes, args.repeats, batch, not args.no_shade)
    t2 = None
    if not args.no_cull:
        print(f"\n## Culling ({cull_n} scratches, {cull_size}x{cull_size}, {views} views)\n")
        t2 = cull_table(cull_n, cull_size, eps_list, views, args.repeats, batch)
    md = [
        "# bvh benchmark",
        "",
        f"Machine: {machine_line()}; float32.",
        f"Command: `python {' '.join(['benchmarks/bench_bvh.py', *sys.argv[1:]])}`.",
        "Scenes: defaults of docs/model.md §5 (lengths U[5, 25] mm, width 2.5e-4 m, depth 1.28e-4 m, "
        "alpha 0.04) on a 0.3 m board. Times are medians of `block_until_ready` runs; compile "
        "times apart. The machine may be shared: numbers are provisional, rerun on a quiet one.",
        "",
        "## Binning",
        "",
        t1,
    ]
    if t2 is not None:
        md += [
            "",
            f"## Culling ({cull_n} scratches, {cull_size}x{cull_size}, "
            f"{views} views of `views_on_circle(theta=30 deg)`)",
            "",
            "Error: radiance of the culled render minus the unculled one (coverage from the "
            "unculled list), max over pixels and views, over the largest unculled radiance. "
            "Bound: `eps * sum_dropped A_i / (pi alpha_i^2 S_P)` times the pixel's shading factor "
            "(`jscratch.bvh` docstring); the last column must stay <= 1. Shading here is the "
            "single-pair API one view at a time (the pair's geometry computed per view), so "
            "culled lists save its time; the renderer computes each pair's geometry once for "
            "all views from the shared list and is slower with per-view culled lists up to "
            "`eps = 1e-2` (`python -m jscratch.bench`, render section).",
            "",
            t2,
        ]
    text = "\n".join(md) + "\n"
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        f.write(text)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
