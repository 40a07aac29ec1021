"""Sections 1-2 of `python -m jscratch.bench`: the kernel (closed form against Gauss-Legendre
quadrature, error against the independent reference `jscratch.bench.ndf_reference` on the cases
of `jscratch.bench.ndf_cases`) and the numerical stability sweep."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import ndf
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
                c_b, t_b = 0.0, float("nan")
            else:
                c_b, t_b, _ = time_compiled(_per_pair_grads(one), *T,
                                            options=grad_compiler_options())
            rows.append({
                "method": name, "dtype": np.dtype(dtype).name,
                "ns_per_pair_fwd": t_f / n_pairs_time * 1e9,
                "ns_per_pair_fwd_bwd": t_b / n_pairs_time * 1e9,
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


def bench_stability(quick: bool, out: Path) -> dict:

    n = 2048 if quick else 131072
    C = stability_cases(n)
    # The same functions and chunk shape as the kernel section's closed-form timings, so the
    # compilations are shared (`compile_once`).
    chunk = _kernel_timing_pairs(quick)
    fwd, grads = _vmapped(ndf.pair_integral), _per_pair_grads(ndf.pair_integral)
    C32 = C.astype(np.float32).args()
    C64 = C.astype(np.float64).args()
    first = np.arange(chunk) % n  # a whole first chunk: the shapes the functions compile for
    head = tuple(a[first] for a in C32)
    D32, A32 = _run_in_chunks(compile_once(fwd, *head)[0], C32, chunk)
    D64, A64 = _run_in_chunks(compile_once(fwd, *(a[first] for a in C64))[0], C64, chunk)
    g = _run_in_chunks(compile_once(grads, *head, options=grad_compiler_options())[0], C32,
                       chunk)
    bad_g = int(np.any([~np.isfinite(x.reshape(n, -1)).any(axis=1) for x in g], axis=0).sum())
    # The float64 closed form at the float32-rounded inputs is the reference here.
    Dref, Aref = _run_in_chunks(compile_once(fwd, *(a[first].astype(np.float64) for a in C32))[0],
                                tuple(a.astype(np.float64) for a in C32), chunk)
    scale = Aref / (np.pi * C.astype(np.float32).alpha.astype(np.float64))
    tol = np.maximum(1e-3 * np.abs(Dref), 1e-5 * scale)
    ratio = np.where(tol > 0, np.abs(D32 - Dref) / np.where(tol > 0, tol, 1), np.abs(D32) * 1e30)
    worst = int(np.argmax(ratio))
    bins = []
    edges = [1e-4, 1e-3, 1e-2, 1e-1, 0.9 + 1e-9]
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (C.alpha >= lo) & (C.alpha < hi)
        if sel.any():
            bins.append({"alpha": f"[{lo:g}, {hi:g})", "n": int(sel.sum()),
                         "worst_err_over_tol": float(ratio[sel].max()),
                         "median_err_over_tol": float(np.median(ratio[sel]))})
    res = {
        "n_cases": n,
        "nonfinite_values_f32": int((~np.isfinite(D32)).sum() + (~np.isfinite(A32)).sum()),
        "nonfinite_values_f64": int((~np.isfinite(D64)).sum() + (~np.isfinite(A64)).sum()),
        "cases_with_nonfinite_gradients_f32": bad_g,
        "worst_f32_err_over_tol": float(ratio[worst]),
        "within_tolerance_fraction": float(np.mean(ratio <= 1)),
        "worst_case": {k: np.asarray(v[worst]).tolist() for k, v in zip(C._fields, C.args())},
        "by_alpha": bins,
        "note": "tolerance = max(1e-3 |ref|, 1e-5 A/(pi alpha)) (the kernel's float32 accuracy bound); "
                "reference = float64 closed form at the float32-rounded inputs.",
    }
    res["markdown"] = (
        f"{n} cases; non-finite values f32/f64: {res['nonfinite_values_f32']}/"
        f"{res['nonfinite_values_f64']}; cases with non-finite f32 gradients: {bad_g}; worst "
        f"f32 error / tolerance: {res['worst_f32_err_over_tol']:.3g}; within tolerance: "
        f"{100 * res['within_tolerance_fraction']:.3f}%\n\n" + md_table(bins, ["alpha", "n", "worst_err_over_tol", "median_err_over_tol"])
    )
    return res

