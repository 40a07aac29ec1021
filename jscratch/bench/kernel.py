"""Sections 1-2 of `python -m jscratch.bench`: the kernel (closed form against Gauss-Legendre
quadrature, error against the independent reference `jscratch.bench.ndf_reference` on the cases
of `jscratch.bench.ndf_cases`) and the numerical stability sweep of every pair kernel."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import arc, lobe, native, ndf
from jscratch.bench import ndf_cases, ndf_reference
from jscratch.bench.timing import compile_once, md_table, plot, time_compiled
from jscratch.render import grad_compiler_options

# ---------------------------------------------------------------------------------------------
# 1. Kernel: closed form vs Gauss-Legendre.


def _kernel_population(quick: bool):

    if quick:
        fams = {"random": ndf_cases.random_cases(n=96), **{
            k: v.take(np.arange(0, v.len(), 3)) for k, v in ndf_cases.adversarial_families().items()
        }}
    else:
        fams = ndf_cases.all_families()
    return ndf_cases.concat(fams.values())


def _errors(D, Dr, Ar, alpha):
    """Relative error where the reference is significant (> 1e-6 of a fully lit pair's scale
    A / (pi alpha)), and the largest absolute error in units of that scale over all pairs."""
    scale = Ar / (np.pi * alpha)
    sig = (Dr > 1e-6 * scale) & (Dr > 0)
    rel = np.abs(D[sig] - Dr[sig]) / Dr[sig]
    absn = np.abs(D - Dr) / np.where(scale > 0, scale, 1.0)
    absn = np.where(scale > 0, absn, np.abs(D))
    bad = int((~np.isfinite(D)).sum())
    return {
        "max_rel": float(np.max(rel)) if rel.size else 0.0,
        "median_rel": float(np.median(rel)) if rel.size else 0.0,
        "max_abs_scaled": float(np.max(absn)),
        "nonfinite": bad,
    }


def _quadrature(*args, n: int):

    return ndf.pair_integral_quadrature(*args, n)


@functools.lru_cache(maxsize=None)
def _vmapped(one):
    """The pair integral `one` vmapped over pairs (one function object per `one`)."""
    return jax.vmap(one)


@functools.lru_cache(maxsize=None)
def _per_pair_grads(one):
    """Per-pair gradients of ``D + A`` with respect to all 7 arguments of the pair integral `one`
    (forward and reverse pass of every pair), vmapped; one function object per `one`, so the
    kernel and stability sections share its compilation (`compile_once`)."""

    def total(*a):
        D, A = one(*a)
        return D + A

    return jax.vmap(jax.grad(total, argnums=tuple(range(7))))


def _run_in_chunks(compiled, args, chunk: int):
    """Run `compiled` (for ``chunk`` pairs) over arrays of any length ``n``: pads the last chunk
    by repeating pairs and returns the outputs as float64 numpy arrays of length ``n``."""
    n = len(args[0])
    outs = []
    for i in range(0, n, chunk):
        idx = np.arange(i, i + chunk) % n
        outs.append([np.asarray(o, np.float64) for o in compiled(*(a[idx] for a in args))])
    return [np.concatenate(o)[:n] for o in zip(*outs)]


def _kernel_timing_pairs(quick: bool) -> int:
    return 4096 if quick else 65536


def bench_kernel(quick: bool, out: Path) -> dict:

    C = _kernel_population(quick)
    n_pairs_time = _kernel_timing_pairs(quick)
    reps = int(np.ceil(n_pairs_time / C.len()))
    rows = []
    dtypes = (np.float32,) if quick else (np.float32, np.float64)
    gl_orders = (16, 64) if quick else (8, 16, 32, 64, 128)
    for dtype in dtypes:
        Cd = C.astype(dtype)
        t0 = time.perf_counter()
        Dr, Ar = ndf_reference.reference_batch(Cd)
        ref_s = time.perf_counter() - t0
        alpha = Cd.alpha.astype(np.float64)
        # The timing batch: the population tiled to n_pairs_time pairs.
        T = [jnp.asarray(np.concatenate([a] * reps)[:n_pairs_time]) for a in Cd.args()]
        P = Cd.args()
        methods = [("closed form", None)] + [(f"GL n={n}", n) for n in gl_orders]
        for name, n in methods:
            one = ndf.pair_integral if n is None else functools.partial(_quadrature, n=n)
            fwd = _vmapped(one)
            c_f, t_f, _ = time_compiled(fwd, *T)
            D = _run_in_chunks(compile_once(fwd, *T)[0], P, n_pairs_time)[0]
            err = _errors(D, Dr, Ar, alpha)
            # Quick mode times the closed form's backward only (the stability section reuses
            # that compilation); each backward compile takes seconds.
            if quick and n is not None:
                c_b, t_b = 0.0, None  # not timed: `md_table` shows "-", bench.json null
            else:
                c_b, t_b, _ = time_compiled(_per_pair_grads(one), *T,
                                            options=grad_compiler_options())
            rows.append({
                "method": name, "dtype": np.dtype(dtype).name,
                "ns_per_pair_fwd": t_f / n_pairs_time * 1e9,
                "ns_per_pair_fwd_bwd": None if t_b is None else t_b / n_pairs_time * 1e9,
                "Mpairs_per_s_fwd": n_pairs_time / t_f / 1e6,
                "compile_s": c_f + c_b,
                **err,
            })
        rows[-1]["reference_s"] = ref_s
    cols = ["method", "dtype", "ns_per_pair_fwd", "ns_per_pair_fwd_bwd", "Mpairs_per_s_fwd",
            "max_rel", "median_rel", "max_abs_scaled", "nonfinite", "compile_s"]
    _pareto_plot(rows, out / "kernel_pareto.png")
    return {"n_pairs_error": C.len(), "n_pairs_timing": n_pairs_time, "rows": rows,
            "markdown": md_table(rows, cols),
            "note": "max_rel/median_rel over pairs whose reference exceeds 1e-6 A/(pi alpha); "
                    "max_abs_scaled = max |D - ref| / (A / (pi alpha)) over all pairs."}


def _pareto_plot(rows, path):
    def draw(ax):
        for dtype, marker in (("float32", "o"), ("float64", "s")):
            for r in rows:
                if r["dtype"] != dtype:
                    continue
                color = "C3" if r["method"] == "closed form" else "C0"
                xy = (r["ns_per_pair_fwd"], max(r["max_rel"], 1e-17))
                ax.scatter(*xy, marker=marker, color=color)
                ax.annotate(f"{r['method']} {dtype[-2:]}", xy, fontsize=6, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_xscale("log")
        ax.set_yscale("log")

    plot(path, draw, "time per pair, forward (ns)", "max relative error vs reference",
          "Pair integral: run time against error (red: closed form)")


# ---------------------------------------------------------------------------------------------
# 2. Stability sweep.


def stability_cases(n: int, seed: int = 1):
    """`n` pairs over the extreme ranges (numpy float64 `Cases`): alpha log-uniform in
    [1e-4, 0.9]; hz in [0.02, 1] (a third below 0.1); hy exactly 0 for a quarter, else
    +-10^U(-8, 0) of the tangential part; width over footprint 10^U(-3, 2); depth over width
    10^U(-3, log10 50); footprint positions across and along the groove, endpoints inside,
    zero-length scratches (1 in 50) and scratch directions snapped to the axes (1 in 5)."""

    rng = np.random.default_rng(seed)
    s = ndf_cases.PIXEL
    x0 = y0 = 0.15
    fp = np.broadcast_to(ndf_cases.square(x0, y0, s), (n, 4, 2)).copy()
    alpha = 10 ** rng.uniform(-4, np.log10(0.9), n)
    hz = np.where(rng.random(n) < 1 / 3, rng.uniform(0.02, 0.1, n), rng.uniform(0.1, 1.0, n))
    w = s * 10 ** rng.uniform(-3, 2, n)
    d = w * 10 ** rng.uniform(-3, np.log10(50), n)
    theta = rng.uniform(0, 2 * np.pi, n)
    snap = rng.random(n) < 0.2
    theta = np.where(snap, np.round(theta / (np.pi / 2)) * (np.pi / 2), theta)
    t = np.stack([np.cos(theta), np.sin(theta)], -1)
    bvec = np.stack([t[:, 1], -t[:, 0]], -1)
    centre = np.array([x0 + s / 2, y0 + s / 2])
    off = (rng.uniform(-1, 1, n) * (s + w))[:, None] * bvec
    length = np.where(rng.random(n) < 0.02, 0.0, 10 ** rng.uniform(-4, np.log10(0.4), n))
    frac = rng.uniform(-0.2, 1.2, n)
    p0 = centre + off - (frac * length)[:, None] * t
    p1 = p0 + length[:, None] * t
    # Half vector in the local frame: hy = 0 exactly for a quarter (board h built from b only).
    rxy = np.sqrt(1 - hz**2)
    hy_frac = np.where(rng.random(n) < 0.25, 0.0, np.sign(rng.normal(size=n)) * 10 ** rng.uniform(-8, 0, n))
    hy = rxy * hy_frac
    hx = np.sign(rng.normal(size=n)) * np.sqrt(np.maximum(rxy**2 - hy**2, 0))
    h = np.concatenate([hx[:, None] * bvec + hy[:, None] * t, hz[:, None]], -1)
    return ndf_cases.Cases(h, fp, p0, p1, w, d, alpha)


def _sweep_errors(D32, A32, Dr, Ar, alpha, pixel_area):
    """Float32 ``(D, A)`` against the float64 reference ``(Dr, Ar)`` (float64 numpy, ``(n,)``):
    ``ratio`` = error over the tolerance ``max(1e-3 |Dr|, 1e-5 Ar / (pi alpha))`` per case, and the
    worst error in units of the brightest value a pixel can have, ``pixel_area / (pi alpha^2)``
    (a fully covered pixel at the GGX peak: what a render can show); the area's worst error in
    units of the pixel's area."""
    scale = Ar / (np.pi * alpha)
    tol = np.maximum(1e-3 * np.abs(Dr), 1e-5 * scale)
    ratio = np.where(tol > 0, np.abs(D32 - Dr) / np.where(tol > 0, tol, 1), np.abs(D32) * 1e30)
    return ratio, {
        "nonfinite_values": int((~np.isfinite(D32)).sum() + (~np.isfinite(A32)).sum()),
        "worst_err_over_tol": float(ratio.max()),
        "cases_over_tol": int((ratio > 1).sum()),
        "within_tolerance_fraction": float(np.mean(ratio <= 1)),
        "worst_err_over_pixel_peak": float(np.max(np.abs(D32 - Dr) * np.pi * alpha**2
                                                  / pixel_area)),
        "worst_area_err_over_pixel": float(np.max(np.abs(A32 - Ar)) / pixel_area),
    }


def _arc_cases(C: "ndf_cases.Cases") -> "ndf_cases.Cases":
    """`C` read as ball-cutter grooves: radius ``R = width / 2``, plunge ``rho R`` with ``rho =
    1 - exp(-depth / width)`` (the paper groove's depth read back), stored as `arc.arc_groove`
    stores them (its depth capped where ``rho`` reaches the arc's cap; deeper is the same
    groove)."""
    radius = C.width / 2
    _, depth = arc.arc_groove(-np.expm1(-C.depth / C.width) * radius, radius)
    return C._replace(depth=np.asarray(depth, C.depth.dtype))


def _native_sweep(profile: str, C32: "ndf_cases.Cases"):
    """The native kernel (float32, one view per pair) over the sweep: ``(D, A)`` as float64 numpy
    and, per case, whether every derivative is finite: the design's Jacobian pass
    (`native.pair_jacobian`: ``J_D``, ``J_h``, ``J_A``) and the reverse pass at unit cotangents
    (`native.pair_vjp`)."""
    n_gl = lobe.nodes(jnp.float32) if profile == "paper" else arc.nodes(jnp.float32)
    h = jnp.asarray(C32.h)[None]
    args = tuple(jnp.asarray(a) for a in (C32.footprint, C32.p0, C32.p1, C32.width, C32.depth,
                                          C32.alpha))
    valid = jnp.ones(C32.width.shape, bool)
    D, A, J_D, J_h, J_A = jax.jit(functools.partial(native.pair_jacobian, n_gl,
                                                    profile=profile))(*args, valid, h)
    ones = jnp.ones(C32.width.shape, jnp.float32)
    vjp = jax.jit(functools.partial(native.pair_vjp, n_gl, profile=profile))(
        *args, valid, h, ones[None], ones)
    n = C32.width.shape[0]
    per_case = (J_D[0], J_h[0], J_A, *vjp[:5], vjp[5][0])  # one view: (n, ...) each
    finite = [np.isfinite(np.asarray(x)).reshape(n, -1).all(axis=1) for x in per_case]
    return (np.asarray(D[0], np.float64), np.asarray(A, np.float64),
            np.logical_and.reduce(finite))


def _by_alpha(alpha, ratio) -> list[dict]:
    """The worst and median of ``ratio`` (error over tolerance) per decade of ``alpha``."""
    bins = []
    edges = [1e-4, 1e-3, 1e-2, 1e-1, 0.9 + 1e-9]
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (alpha >= lo) & (alpha < hi)
        if sel.any():
            bins.append({"alpha": f"[{lo:g}, {hi:g})", "n": int(sel.sum()),
                         "worst_err_over_tol": float(ratio[sel].max()),
                         "median_err_over_tol": float(np.median(ratio[sel]))})
    return bins


_ARC_PAIR = arc.pair_integral_of("arc")  # one function object: one compilation per shape


def bench_stability(quick: bool, out: Path) -> dict:
    """The sweep of `stability_cases` through every pair kernel a render can run, in float32
    against the float64 closed form of the same groove at the float32-rounded inputs: the
    single-pair kernels (`ndf.pair_integral`, the paper's profile, whose per-view stage is
    `native.lit` where the native kernel is available; `arc.arc_lit_integral`, the ball cutter's
    arc, in jnp: the fallback and GPU path) and the native whole-pair kernel with both profiles
    (a design's path on the CPU). The top-level figures are `ndf.pair_integral`'s; ``paths`` has
    one row per kernel."""

    n = 2048 if quick else 131072
    C = stability_cases(n)
    # The same functions and chunk shape as the kernel section's closed-form timings, so the
    # compilations are shared (`compile_once`).
    chunk = _kernel_timing_pairs(quick)
    first = np.arange(chunk) % n  # a whole first chunk: the shapes the functions compile for
    pixel_area = float(ndf_cases.PIXEL) ** 2
    paths = []
    for profile in ("paper", "arc"):
        Cp = C if profile == "paper" else _arc_cases(C)
        Cp32 = Cp.astype(np.float32)
        one = ndf.pair_integral if profile == "paper" else _ARC_PAIR
        fwd, grads = _vmapped(one), _per_pair_grads(one)
        C32 = Cp32.args()
        C64 = tuple(a.astype(np.float64) for a in C32)
        head = tuple(a[first] for a in C32)
        # The float64 closed form at the float32-rounded inputs is the reference here.
        Dr, Ar = _run_in_chunks(compile_once(fwd, *(a[first] for a in C64))[0], C64, chunk)
        alpha = Cp32.alpha.astype(np.float64)
        D32, A32 = _run_in_chunks(compile_once(fwd, *head)[0], C32, chunk)
        g = _run_in_chunks(compile_once(grads, *head, options=grad_compiler_options())[0], C32,
                           chunk)
        good_g = np.logical_and.reduce([np.isfinite(x.reshape(n, -1)).all(axis=1) for x in g])
        ratio, row = _sweep_errors(D32, A32, Dr, Ar, alpha, pixel_area)
        row["cases_with_nonfinite_gradients"] = int((~good_g).sum())
        groove = "paper profile" if profile == "paper" else "arc"
        jnp_name = "ndf.pair_integral" if profile == "paper" else "arc.arc_lit_integral"
        paths.append({"kernel": f"{jnp_name}, {groove}", **row})
        if profile == "paper":  # the top-level figures
            top = dict(row)
            D64, A64 = _run_in_chunks(compile_once(fwd, *(a[first] for a in Cp.args()))[0],
                                      Cp.args(), chunk)
            top["nonfinite_values_f64"] = int((~np.isfinite(D64)).sum() + (~np.isfinite(A64)).sum())
            worst = int(np.argmax(ratio))
            worst_case = {k: np.asarray(v[worst]).tolist() for k, v in zip(C._fields, C.args())}
            bins = _by_alpha(C.alpha, ratio)
        if native.available(jnp.float32):
            Dn, An, good_n = _native_sweep(profile, Cp32)
            _, row = _sweep_errors(Dn, An, Dr, Ar, alpha, pixel_area)
            paths.append({"kernel": f"native, {groove}", **row,
                          "cases_with_nonfinite_gradients": int((~good_n).sum())})
        else:
            paths.append({"kernel": f"native, {groove}",
                          "skipped": f"native kernel unavailable: {native.status()['why']}"})
    res = {
        "n_cases": n,
        "nonfinite_values_f32": top["nonfinite_values"],
        "nonfinite_values_f64": top["nonfinite_values_f64"],
        "cases_with_nonfinite_gradients_f32": top["cases_with_nonfinite_gradients"],
        "worst_f32_err_over_tol": top["worst_err_over_tol"],
        "within_tolerance_fraction": top["within_tolerance_fraction"],
        "worst_case": worst_case,
        "by_alpha": bins,
        "paths": paths,
        "note": "tolerance = max(1e-3 |ref|, 1e-5 A/(pi alpha)) (the kernel's float32 accuracy "
                "bound); reference = float64 closed form of the same groove at the float32-rounded "
                "inputs; pixel peak = pixel area / (pi alpha^2). The arc rows read each case's "
                "width as 2R, its depth capped at the arc's (`arc.arc_groove`).",
    }
    cols = ["kernel", "nonfinite_values", "cases_with_nonfinite_gradients", "worst_err_over_tol",
            "cases_over_tol", "worst_err_over_pixel_peak", "worst_area_err_over_pixel"]
    res["markdown"] = (
        f"{n} cases; non-finite values f32/f64: {res['nonfinite_values_f32']}/"
        f"{res['nonfinite_values_f64']}; cases with non-finite f32 gradients: "
        f"{res['cases_with_nonfinite_gradients_f32']}; worst f32 error / tolerance: "
        f"{res['worst_f32_err_over_tol']:.3g}; within tolerance: "
        f"{100 * res['within_tolerance_fraction']:.3f}%\n\n"
        + md_table(bins, ["alpha", "n", "worst_err_over_tol", "median_err_over_tol"])
        + "\n\nEvery pair kernel, float32 against the float64 closed form of its groove:\n\n"
        + md_table([p for p in paths if "skipped" not in p], cols)
    )
    return res
