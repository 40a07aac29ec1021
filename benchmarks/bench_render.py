"""Benchmark the multi-view renderer (`jscratch.render`): forward and forward+backward time per view,
pairs per second and compiled peak memory for random scenes (SPEC section 5 layout), plus the
speed-up of the analytic renderer over the brute-force supersampler (`jscratch.brute`) at equal
error.

Writes a Markdown table to stdout and to `benchmarks/results/render.md`.

    python benchmarks/bench_render.py                      # all cases (CPU, float32)
    python benchmarks/bench_render.py --cases 20000x256 --no-brute

Timings: `jit(...).lower(...).compile()` timed apart; runs are medians of `--repeats`
`block_until_ready` calls after one warm-up. Peak memory is XLA's compiled memory analysis
(arguments + outputs + temporaries) of the jitted step. Binning (`bvh.build_pairs`) is host work
done once per scene and reported apart (it is not part of a gradient step unless scratches move
by more than the skin).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)  # for the float64 reference; benchmarks run float32

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from jscratch import brute  # noqa: E402
from jscratch import render as R  # noqa: E402

DATE = "2026-11-21"


def _median_time(fn, repeats):
    jax.block_until_ready(fn())  # warm-up
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def _mem(compiled):
    m = compiled.memory_analysis()
    if m is None:
        return float("nan")
    return (m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes) / 2**20


def _scene(n, res, views, dtype=jnp.float32, seed=0):
    board = R.Board(shape=(res, res))
    s = R.Scratches.random(jax.random.PRNGKey(seed), n, board, dtype=dtype)
    v = R.views_on_circle(views, math.radians(40), board=board, dtype=dtype)
    return board, s, v


def bench_case(n, res, views, repeats, chunk):
    board, s, v = _scene(n, res, views)
    t = time.perf_counter()
    pairs = R.bin_pairs(s, board, chunk=chunk)
    t_bin = time.perf_counter() - t
    n_pairs = int(np.asarray(pairs.valid).sum())
    target = jnp.zeros((views, res, res), jnp.float32)

    # The pair list is an argument, not a closed-over constant (XLA would constant-fold it).
    def fwd(s, v, pairs):
        return R.render_pairs(s, v, board, pairs, chunk=chunk)

    def loss(s, v, pairs):
        return jnp.mean((R.display(fwd(s, v, pairs)) - target) ** 2)

    f_fwd = jax.jit(fwd)
    f_bwd = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    row = {"N": n, "res": res, "views": views, "pairs": n_pairs, "L": pairs.pixel.shape[0],
           "bin_s": t_bin}
    for name, f in (("fwd", f_fwd), ("bwd", f_bwd)):
        t = time.perf_counter()
        c = f.lower(s, v, pairs).compile()
        row[f"{name}_compile_s"] = time.perf_counter() - t
        row[f"{name}_s"] = _median_time(lambda: c(s, v, pairs), repeats)
        row[f"{name}_mem_mib"] = _mem(c)
    return row


def _rel_rms(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


def bench_brute(n_scratches, res, ns, repeats):
    """Error (relative RMS of radiance against the float64 analytic render) and time of the
    brute-force renderer for each `n` (n x n samples per pixel), and of the float32 analytic
    renderer; both use the same pair list (binning excluded from both)."""
    board, s64, v64 = _scene(n_scratches, res, 1, jnp.float64, seed=1)
    s32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), s64)
    v32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), v64)
    pairs = R.bin_pairs(s64, board)
    ref = R.render_pairs(s64, v64, board, pairs)
    ana = jax.jit(lambda s, v: R.render_pairs(s, v, board, pairs))
    t_ana = _median_time(lambda: ana(s32, v32), repeats)
    err_ana = _rel_rms(ana(s32, v32), ref)
    rows = []
    for n in ns:
        f = jax.jit(lambda s, v, n=n: brute.brute_render(s, v, board, n=n, pairs=pairs,
                                                          batch=max(16, 65536 // (n * n))))
        f.lower(s32, v32).compile()
        t = _median_time(lambda: f(s32, v32), max(1, repeats // 2))
        rows.append((n, _rel_rms(f(s32, v32), ref), t))
    return {"N": n_scratches, "res": res, "pairs": int(np.asarray(pairs.valid).sum()),
            "t_ana": t_ana, "err_ana": err_ana, "rows": rows}


def _fit_speedup(br):
    """Fit err = c n^-p to the brute rows (log-log least squares) and time = t1 n^2; return the
    fitted p and the brute time extrapolated to the analytic renderer's error."""
    ns = np.array([r[0] for r in br["rows"]], float)
    err = np.array([r[1] for r in br["rows"]])
    t = np.array([r[2] for r in br["rows"]])
    p, logc = np.polyfit(np.log(ns), np.log(err), 1)
    n_eq = math.exp((math.log(br["err_ana"]) - logc) / p)
    t_per_sample = float(np.median(t / ns**2))
    return -p, n_eq, t_per_sample * n_eq**2


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="20000x256,20000x512,60000x256,60000x512",
                    help="comma-separated NxRES cases (scratches x image side in pixels)")
    ap.add_argument("--views", type=int, default=4, help="views rendered together (default 4)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per measurement")
    ap.add_argument("--chunk", type=int, default=R.DEFAULT_CHUNK, help="pairs per chunk")
    ap.add_argument("--no-brute", action="store_true", help="skip the brute-force comparison")
    ap.add_argument("--brute-scene", default="500x64", help="NxRES of the brute-force scene")
    ap.add_argument("--brute-n", default="16,32,64,128,256", help="samples per pixel side")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                   "results", "render.md"))
    args = ap.parse_args(argv)

    lines = [
        "# Renderer benchmark (`benchmarks/bench_render.py`)",
        "",
        f"- Date: {DATE}; machine: `{platform.platform()}`, {os.cpu_count()} CPUs, "
        f"{jax.devices()[0].platform} backend; jax {jax.__version__}.",
        f"- Load average at start: {os.getloadavg()[0]:.1f} (the machine was shared with other "
        "jobs: numbers are provisional; rerun on a quiet machine).",
        f"- Command: `python {' '.join(['benchmarks/bench_render.py'] + sys.argv[1:])}`",
        f"- float32; random scenes of SPEC section 5 (0.3 m board, lengths 5-25 mm, w = d = 1e-4 m,"
        f" alpha = 0.04); {args.views} views from `views_on_circle(theta=40 deg)` rendered "
        "together from one shared pair list; chunk "
        f"{args.chunk}. Per-view time = step time / views. Pairs/s counts (pixel, scratch, view)"
        " evaluations (a backward step evaluates each pair twice: forward and recompute+VJP).",
        "- Memory: XLA compiled memory analysis of the jitted step (arguments + outputs + temps).",
        "",
        "| scratches | image | pairs | bin (s) | fwd compile (s) | fwd / view (ms) | fwd pairs/s |"
        " fwd mem (MiB) | fwd+bwd compile (s) | fwd+bwd / view (ms) | fwd+bwd pairs/s |"
        " fwd+bwd mem (MiB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for case in args.cases.split(","):
        n, res = (int(x) for x in case.lower().split("x"))
        r = bench_case(n, res, args.views, args.repeats, args.chunk)
        pv = r["pairs"] * args.views
        line = (f"| {n} | {res}x{res} | {r['pairs']} | {r['bin_s']:.2f} | "
                f"{r['fwd_compile_s']:.1f} | {1e3 * r['fwd_s'] / args.views:.0f} | "
                f"{pv / r['fwd_s']:.3g} | {r['fwd_mem_mib']:.0f} | {r['bwd_compile_s']:.1f} | "
                f"{1e3 * r['bwd_s'] / args.views:.0f} | {pv / r['bwd_s']:.3g} | "
                f"{r['bwd_mem_mib']:.0f} |")
        lines.append(line)
        print(line, flush=True)

    if not args.no_brute:
        bn, bres = (int(x) for x in args.brute_scene.lower().split("x"))
        br = bench_brute(bn, bres, [int(x) for x in args.brute_n.split(",")], args.repeats)
        p, n_eq, t_eq = _fit_speedup(br)
        out = [
            "",
            f"## Brute force vs analytic ({bn} scratches, {bres}x{bres}, 1 view, "
            f"{br['pairs']} pairs, float32)",
            "",
            "Error: relative RMS of radiance against the float64 analytic render (the analytic "
            "model itself is validated against the float64 all-pairs reference and, to the brute "
            "force's sampling error, in `tests/test_render.py`). Both renderers use the same pair "
            "list; the brute force tests `n x n` jittered samples per pixel against the real "
            "groove geometry.",
            "",
            "| renderer | samples/pixel | rel. RMS error | time (ms) | analytic speed-up |",
            "|---|---|---|---|---|",
            f"| analytic (closed form) | - | {br['err_ana']:.2e} | {1e3 * br['t_ana']:.1f} | 1 |",
        ]
        for n, err, t in br["rows"]:
            out.append(f"| brute force | {n}x{n} | {err:.2e} | {1e3 * t:.1f} | "
                       f"{t / br['t_ana']:.1f} |")
        out += [
            "",
            f"Fit: brute error ~ n^-{p:.2f}; reaching the analytic renderer's error "
            f"({br['err_ana']:.1e}) would take about n = {n_eq:.3g} ({n_eq**2:.3g} samples per "
            f"pixel) and {t_eq:.3g} s, a speed-up of about {t_eq / br['t_ana']:.3g}x at equal "
            "error (extrapolated; the measured rows above are lower bounds on the speed-up at "
            "each brute error level, since the analytic error is far smaller).",
        ]
        lines += out
        print("\n".join(out), flush=True)

    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"\nwritten to {args.out}")


if __name__ == "__main__":
    main()
