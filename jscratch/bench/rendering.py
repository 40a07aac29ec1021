"""Sections 3-5 of `python -m jscratch.bench`: the renderer, the brute-force comparison and the
optimiser (`RUNNERS`, picked up by `jscratch.bench.cli.run_bench`).

- ``render``: forward and forward+backward time per view, pairs per second, the binning share of
  a gradient step and XLA's compiled peak memory, for the standard scenes (20k and 60k scratches
  at 256 and 512 px; ``--quick``: one small scene); then culling ``eps`` against the image error
  it causes and the shading time it saves (run time against error for the renderer). Plot
  ``render_culling.png``.
- ``brute``: the float32 analytic renderer and the brute-force supersampler (`jscratch.brute`,
  ``n x n`` jittered samples per pixel against the real groove geometry) against a float64
  analytic render: error and time of each, the speed-up at each brute-force error level and the
  extrapolated speed-up at the analytic error. Plot ``brute_vs_analytic.png``.
- ``design``: SSIM per view against iterations and wall time for the default design (3 views,
  20,000 scratches, 256 px; ``--quick``: 2 views, 400 scratches, 32 px), by stopping and resuming
  one run from its checkpoint. Plot ``design_ssim.png``.

Every function here returns a dict with a ``markdown`` entry (what `run_bench` prints) and plain
numbers (what it writes to JSON). Scenes follow docs/model.md §5 (`render.Scratches.random`).
"""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import brute, design
from jscratch.bench.timing import md_table, median_time, plot
from jscratch.errors import InputError
from jscratch.render import (
    DEFAULT_CHUNK,
    bin_pairs,
    cull_pairs,
    grad_compiler_options,
    render_pairs,
)
from jscratch.scene import Board, Scratches, Views, views_on_circle
from jscratch.shading import display

DEFAULT_VIEWS = 4


def design_step_state(config, views: int, size: int, warm: int):
    """The default targets' design (`config`, ``views`` views at ``size`` px) set up as
    `jscratch.design.run` sets it up, after ``warm`` steps: ``(params, opt_state, lists, ctx,
    adam)`` for `jscratch.design.solver.step` (the design-step benchmarks' starting point), the
    native kernel built and the allocator set as the design sets them."""
    from jscratch import native
    from jscratch.design import run, solver
    from jscratch.design.io import default_targets

    native.keep_freed_memory()
    native.prepare(config.dtype)

    targets, _ = default_targets(views, (size, size))
    tnp, v, board = run.check_inputs(targets, None, None, config)
    params, adam, ctx = run.setup(tnp, v, board, config)
    state, compiling = run.initial_state(params, adam, ctx, tnp, config)
    compiling.join()
    p, opt, lists = state.params, state.opt_state, state.lists
    for _ in range(warm):
        p, opt, _, new_lists, _, _, _ = solver.step(p, opt, lists, ctx, adam)
        lists = new_lists if new_lists is not None else lists
    return p, opt, lists, ctx, adam


def time_median(fn, repeats: int) -> float:
    """Median wall time of `repeats` `block_until_ready` calls of `fn()` after one warm-up."""
    return median_time(fn, repeats)[0]

def compiled_mib(compiled) -> float:
    m = compiled.memory_analysis()
    if m is None:
        return float("nan")
    return (m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes) / 2**20


def scene(n: int, res: int, views: int, dtype=jnp.float32, seed: int = 0, theta_deg: float = 40.0):
    """`(board, scratches, views)`: `n` random scratches (docs/model.md §5) on a `res x res` board,
    `views` cameras on a circle at `theta_deg` from the normal."""
    board = Board(shape=(res, res))
    s = Scratches.random(jax.random.PRNGKey(seed), n, board, dtype=dtype)
    v = views_on_circle(views, math.radians(theta_deg), board=board, dtype=dtype)
    return board, s, v


class _Case(NamedTuple):
    """What `render_case` built, for `culling_rows` to reuse (no second binning or compile)."""
    board: Board
    scratches: Scratches
    views: Views
    pairs: Any  # bvh.Pairs (L,), the complete shared list
    fwd: Any  # jitted fwd(s, v, pairs, coverage_pairs)
    fwd_compiled: Any  # fwd compiled for (s, v, pairs, None)
    fwd_s: float


def render_case(n: int, res: int, views: int = DEFAULT_VIEWS, repeats: int = 3,
                chunk: int = DEFAULT_CHUNK) -> tuple[dict, _Case]:
    """Time one scene: binning (host, after a first call that compiles it), the jitted forward
    render of all views from one shared pair list, and a jitted value-and-gradient of a
    display-space L2 loss with respect to every scratch and view parameter. Compile times apart;
    medians of `repeats` runs.

    **Returns:** ``(row, case)``: the table row and the scene with its compiled forward."""
    board, s, v = scene(n, res, views)
    pairs = bin_pairs(s, board, chunk=chunk)  # (its first call compiles the binning: not timed)
    t = time.perf_counter()
    pairs = bin_pairs(s, board, chunk=chunk)
    bin_s = time.perf_counter() - t
    n_pairs = int(np.asarray(pairs.valid).sum())
    target = jnp.full((views, res, res), 0.5, jnp.float32)

    # The pair list is an argument, not a closed-over constant (XLA would constant-fold it).
    def fwd(s, v, pairs, cov=None):
        return render_pairs(s, v, board, pairs, cov, chunk=chunk)

    def loss(s, v, pairs):
        return jnp.mean((display(fwd(s, v, pairs)) - target) ** 2)

    row = {"scratches": n, "image": f"{res}x{res}", "views": views, "pairs": n_pairs,
           "bin_s": bin_s}
    jfwd = jax.jit(fwd)
    compiled = {}
    # The gradient is compiled as design's step is (`render.grad_compiler_options`).
    for name, f, opts in (("fwd", jfwd, {}), ("fwd_bwd", jax.jit(jax.value_and_grad(loss, (0, 1))),
                                                 grad_compiler_options())):
        t = time.perf_counter()
        c = compiled[name] = f.lower(s, v, pairs).compile(opts)
        row[f"{name}_compile_s"] = time.perf_counter() - t
        step = time_median(lambda c=c: c(s, v, pairs), repeats)
        row[f"{name}_ms_per_view"] = 1e3 * step / views
        row[f"{name}_pairs_per_s"] = n_pairs * views / step
        row[f"{name}_mem_mib"] = compiled_mib(c)
        row[f"_{name}_s"] = step
    # A gradient step rebins at most once (far less with a skin): the worst-case share.
    row["bin_share_of_step"] = bin_s / (bin_s + row["_fwd_bwd_s"])
    return row, _Case(board, s, v, pairs, jfwd, compiled["fwd"], row["_fwd_s"])


def culling_rows(case: _Case, eps_list, repeats: int = 3) -> list[dict]:
    """Per-view culling (`render.cull_pairs`, i.e. `cull.cull`) of `case`'s scene against its
    unculled render: pairs kept, culling time, forward time of the culled lists and the radiance
    error, max over pixels and views, over the peak radiance. `eps_list[0]` must be 0 (the
    reference: `case`'s own forward, already timed)."""
    if not eps_list or eps_list[0] != 0:
        raise InputError(
            f"culling_rows: eps_list must start with 0 (the reference); got {eps_list}")
    s, v, board, full = case.scratches, case.views, case.board, case.pairs
    views = v.m
    ref = np.asarray(case.fwd_compiled(s, v, full), np.float64)
    n0 = int(np.asarray(full.valid).sum()) * views  # a shared list is evaluated for every view
    rows = [{"eps": 0.0, "pairs_kept": 1.0, "cull_s": 0.0,
             "fwd_ms_per_view": 1e3 * case.fwd_s / views, "time_saved": 0.0,
             "max_err_over_peak": 0.0}]
    for eps in eps_list[1:]:
        t = time.perf_counter()
        pairs = cull_pairs(full, s, v, board, eps)
        cull_s = time.perf_counter() - t
        c = case.fwd.lower(s, v, pairs, full).compile()
        t_run = time_median(lambda: c(s, v, pairs, full), repeats)
        rad = np.asarray(c(s, v, pairs, full), np.float64)
        rows.append({
            "eps": eps,
            "pairs_kept": int(np.asarray(pairs.valid).sum()) / n0,
            "cull_s": cull_s,
            "fwd_ms_per_view": 1e3 * t_run / views,
            "time_saved": 1 - t_run / case.fwd_s,
            "max_err_over_peak": float(np.max(np.abs(rad - ref)) / np.max(ref)),
        })
    return rows


def _rel_rms(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


def brute_rows(n_scratches: int, res: int, ns, repeats: int = 3) -> dict:
    """Error (relative RMS of radiance against the float64 analytic render) and time of the
    brute-force renderer for each `n` (``n x n`` samples per pixel) and of the float32 analytic
    renderer, both on the same pair list (binning excluded from both); plus the fit
    ``error ~ n^-p`` and the brute-force time extrapolated to the analytic error."""
    board, s64, v64 = scene(n_scratches, res, 1, jnp.float64)
    s32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), s64)
    v32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), v64)
    pairs = bin_pairs(s32, board)  # one list for all three renderers
    ana = jax.jit(lambda s, v, pairs: render_pairs(s, v, board, pairs))
    ref = ana(s64, v64, pairs)
    t_ana = time_median(lambda: ana(s32, v32, pairs), repeats)
    err_ana = _rel_rms(ana(s32, v32, pairs), ref)
    rows = []
    for n in ns:
        f = jax.jit(lambda s, v, n=n: brute.brute_render(s, v, board, n=n, pairs=pairs,
                                                          batch=max(16, 65536 // (n * n))))
        f.lower(s32, v32).compile()
        t = time_median(lambda: f(s32, v32), max(1, repeats // 2))
        rows.append({"samples_per_pixel": f"{n}x{n}", "n": n,
                     "rel_rms_error": _rel_rms(f(s32, v32), ref), "time_ms": 1e3 * t,
                     "analytic_speedup_at_this_error": t / t_ana})
    ns_ = np.array([r["n"] for r in rows], float)
    err = np.array([r["rel_rms_error"] for r in rows])
    slope, logc = np.polyfit(np.log(ns_), np.log(err), 1)
    n_eq = math.exp((math.log(err_ana) - logc) / slope)
    t_per_sample = float(np.median(np.array([r["time_ms"] for r in rows]) / 1e3 / ns_**2))
    t_eq = t_per_sample * n_eq**2
    return {"scratches": n_scratches, "image": f"{res}x{res}",
            "pairs": int(np.asarray(pairs.valid).sum()), "analytic_ms": 1e3 * t_ana,
            "analytic_rel_rms_error": err_ana, "rows": rows, "fit_error_exponent": -slope,
            "n_at_analytic_error": n_eq, "extrapolated_speedup_at_equal_error": t_eq / t_ana}


# ---------------------------------------------------------------------------------------------
# Section runners: (quick, out) -> dict with "markdown".


def bench_render(quick: bool, out: Path) -> dict:
    cases = [(1000, 64)] if quick else [(20000, 256), (20000, 512), (60000, 256), (60000, 512)]
    repeats = 1 if quick else 3
    rows, built = map(list, zip(*(render_case(n, r, DEFAULT_VIEWS, repeats) for n, r in cases)))
    eps_list = [0.0, 1e-2] if quick else [0.0, 1e-4, 1e-3, 1e-2, 3e-2, 1e-1]
    cn, cr = cases[0]
    cull = culling_rows(built[0], eps_list, repeats)

    def draw(ax):
        x = [max(r["max_err_over_peak"], 1e-9) for r in cull]
        y = [r["fwd_ms_per_view"] for r in cull]
        ax.loglog(x, y, "o-")
        for r, xi, yi in zip(cull, x, y):
            ax.annotate(f"eps={r['eps']:g}", (xi, yi), fontsize=7)

    plot(out / "render_culling.png", draw, "max radiance error / peak (eps = 0 plotted at 1e-9)",
          "forward ms per view", f"culling: {cn} scratches, {cr} px, {DEFAULT_VIEWS} views")
    cols = ["scratches", "image", "pairs", "bin_s", "fwd_compile_s", "fwd_ms_per_view",
            "fwd_pairs_per_s", "fwd_mem_mib", "fwd_bwd_compile_s", "fwd_bwd_ms_per_view",
            "fwd_bwd_pairs_per_s", "fwd_bwd_mem_mib", "bin_share_of_step"]
    ccols = ["eps", "pairs_kept", "fwd_ms_per_view", "time_saved", "max_err_over_peak"]
    md = (f"{DEFAULT_VIEWS} views rendered together from one shared pair list, float32, "
          "chunk " + str(DEFAULT_CHUNK) + ". Pairs/s counts (pixel, scratch, view) "
          "evaluations; memory is XLA's compiled estimate (arguments + outputs + temporaries); "
          "bin_share_of_step = one full rebin over (rebin + gradient step), an upper bound.\n\n"
          + md_table(rows, cols)
          + f"\n\nCulling ({cn} scratches, {cr}x{cr}; error against eps = 0):\n\n"
          + md_table(cull, ccols))
    return {"cases": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows],
            "culling": cull, "markdown": md}


def bench_brute(quick: bool, out: Path) -> dict:
    if quick:  # the render section's first scene: its binning compilation is reused
        res = brute_rows(1000, 64, [16, 64], repeats=1)
    else:
        res = brute_rows(500, 64, [16, 32, 64, 128, 256], repeats=3)

    def draw(ax):
        ax.loglog([r["time_ms"] for r in res["rows"]], [r["rel_rms_error"] for r in res["rows"]],
                  "o-", label="brute force (n x n samples)")
        ax.loglog([res["analytic_ms"]], [res["analytic_rel_rms_error"]], "r*", ms=12,
                  label="analytic (closed form)")

    plot(out / "brute_vs_analytic.png", draw, "time (ms)", "relative RMS error",
          f"{res['scratches']} scratches, {res['image']}, 1 view")
    md = (f"{res['scratches']} scratches, {res['image']}, {res['pairs']} pairs, float32 against "
          f"a float64 analytic render. Analytic: {res['analytic_ms']:.1f} ms, relative RMS error "
          f"{res['analytic_rel_rms_error']:.2e}.\n\n"
          + md_table(res["rows"], ["samples_per_pixel", "rel_rms_error", "time_ms",
                              "analytic_speedup_at_this_error"])
          + f"\n\nBrute-force error ~ n^-{res['fit_error_exponent']:.2f}; at the analytic error it "
          f"would need n = {res['n_at_analytic_error']:.3g} per side, an extrapolated speed-up of "
          f"{res['extrapolated_speedup_at_equal_error']:.3g}x "
          "(the paper: 400x over Werner et al.).")
    res["markdown"] = md
    return res


def bench_design(quick: bool, out: Path) -> dict:
    if quick:
        cfg = design.DesignConfig(n_scratches=400, iterations=8, discard=False)
        m, size, stops = 2, 32, [4, 8]
    else:
        cfg = design.DesignConfig(discard=False)
        m, size, stops = 3, 256, [5, 10, 25, 50, 75, 100]
    targets, names = design.default_targets(m, (size, size))
    board = Board(shape=(size, size))
    views = views_on_circle(m, math.radians(50), board=board)
    rows, wall = [], 0.0
    with tempfile.TemporaryDirectory() as tmp:
        ck = Path(tmp) / "bench.ckpt.npz"
        for i, k in enumerate(stops):
            t = time.perf_counter()
            r = design.design(targets, views, board, cfg, checkpoint=ck, resume=i > 0, stop_after=k)
            wall += time.perf_counter() - t
            rows.append({"iteration": k, "wall_s": wall, "loss": r.metrics["loss"],
                         "ssim": [round(x, 4) for x in r.metrics["ssim"]],
                         "mean_ssim": float(np.mean(r.metrics["ssim"])),
                         "psnr": [round(x, 2) for x in r.metrics["psnr"]]})

    def draw(ax):
        for j in range(m):
            ax.plot([r["wall_s"] for r in rows], [r["ssim"][j] for r in rows], "o-",
                    label=f"view {j} ({names[j]})")

    plot(out / "design_ssim.png", draw,
          "wall time (s, includes compilation and each resume's setup)", "SSIM",
          f"design: {m} views, {cfg.n_scratches} scratches, {size} px")
    md = (f"{m} views ({', '.join(names)}), {cfg.n_scratches} scratches, {size}x{size}, float32, "
          "no discard; the run is stopped at each row's iteration and resumed from its checkpoint "
          "(wall time is cumulative and includes compilation and the resumes' setup).\n\n"
          + md_table(rows, ["iteration", "wall_s", "loss", "ssim", "mean_ssim", "psnr"]))
    return {"views": m, "size": size, "scratches": cfg.n_scratches, "rows": rows, "markdown": md}


RUNNERS = {"render": bench_render, "brute": bench_brute, "design": bench_design}
