"""What a maker needs from a design run: the machine profile and plunges in the design file, the
"as carved" render and the carving-time estimate in ``metrics.json``.

- `plunges`: the plunge of every kept scratch (recorded for carvable designs; fitted by
  height, as `jscratch.fabricate` would, for free ones).
- `as_carved`: render the design with the grooves the ball really cuts (`jscratch.brute`
  with ``ball_radius``, an independent supersampling path) and compare it, per view, with the
  design's own render (the SSIM of docs/model.md §7: Gaussian sigma 1 px, then SSIM). The same samples
  also render the design's own profile, so the report separates the profile's effect from the
  sampling noise.
- `carving_estimate`: the ordered toolpath (`jscratch.toolpath.order_scratches`) and its
  time with the profile's feeds (`jscratch.machine.carving_seconds`).

`jscratch.design.io.save_result` records all of it with every result.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from jscratch import designfile
from jscratch.errors import whole_number
from jscratch.machine import MachineProfile, carving_seconds
from jscratch.metrics import image_metrics

__all__ = ["plunges", "as_carved", "carving_estimate"]


def plunges(design: designfile.Design, profile: MachineProfile) -> tuple[np.ndarray, str]:
    """``(plunge (N,) m, how)``: the recorded plunges, or a per-scratch height fit (`fit_plunge`)."""
    if design.plunge is not None:
        return design.plunge, "recorded"
    from jscratch.fabricate import fit_plunge

    fit = fit_plunge(design.width, design.depth, profile.radius)
    return fit.plunge, "height fit"


def as_carved(design: designfile.Design, profile: MachineProfile, shape, design_display=None, *,
              samples: int = 32, seed: int = 0) -> dict:
    """Per-view SSIM of the as-carved render against the design's render.

    **Arguments:** `design` with views; `profile` the machine; `shape` ``(H, W)`` pixels;
    `design_display` ``(M, H, W)`` the design's own display render (default: rendered here with
    `jscratch.render.render`); `samples` strata per pixel side of the brute-force renderer;
    `seed` its PRNG seed.

    **Returns:** ``{"ssim": [M], "ssim_brute": [M], "ssim_profile_only": [M],
    "ssim_noise_floor": [M], "samples", "seconds", "plunge": how, "plunge_mm",
    "display": (M, H, W) as-carved display values}``. `ssim` compares the as-carved image with the
    design render, the as-carved radiance estimated with a control variate (the design's analytic
    render plus the brute-force difference ball minus design profile on the same samples: unbiased,
    and the two brute renders' sampling noise mostly cancels); `ssim_brute` uses the plain
    brute-force as-carved render (noise-limited); `ssim_profile_only` compares it with the brute
    render of the design's own profile on the same samples; `ssim_noise_floor` that brute render
    with the design render (sampling noise alone).
    """
    from jscratch.brute import brute_render
    from jscratch.render import render
    from jscratch.scene import Board, Scratches, Views
    from jscratch.shading import display

    if design.camera is None:
        raise designfile.DesignError("as carved: the design has no views (camera, light, intensity)")
    if whole_number(samples) is None or samples < 1:
        raise designfile.DesignError(f"as carved: samples must be an int >= 1 (strata per pixel "
                                     f"side), got {samples!r}")
    try:
        ok = len(shape) == 2 and all(int(s) == s and s >= 1 for s in shape)
    except (TypeError, ValueError):
        ok = False
    if isinstance(shape, (str, bytes)) or not ok:
        raise designfile.DesignError(f"as carved: shape must be (H, W), two ints >= 1, got "
                                     f"{shape!r}")
    shape = tuple(int(s) for s in shape)
    if design_display is not None:
        want = (design.camera.shape[0], *shape)
        if np.shape(design_display) != want:
            raise designfile.DesignError(f"as carved: design_display must have shape {want} "
                                         f"(views, H, W), got {np.shape(design_display)}")
    t0 = time.perf_counter()
    board = Board(shape=shape, Sx=float(design.board[0]), Sy=float(design.board[1]))
    views = Views(design.camera.astype(np.float32), design.light.astype(np.float32),
                  design.intensity.astype(np.float32))
    sc = Scratches(design.p0.astype(np.float32), design.p1.astype(np.float32),
                   design.width.astype(np.float32), design.depth.astype(np.float32),
                   design.alpha.astype(np.float32), profile=design.profile)
    rad, pairs, _ = render(sc, views, board, return_pairs=True)
    if design_display is None:
        design_display = np.asarray(display(rad))
    plunge, how = plunges(design, profile)
    # The ball's cut is exactly as wide as the design groove for carvable designs (and the pairs
    # are the design's); for a free design's height fit it can be wider: bin for the cut instead.
    cut_half = np.sqrt(np.maximum(2 * profile.radius * plunge - plunge**2, 0.0))
    ball_pairs = pairs
    if how != "recorded":
        wide = Scratches(sc.p0, sc.p1, np.maximum(2.2 * cut_half, 1e-9).astype(np.float32),
                         np.full(design.n, 1e-2, np.float32), sc.alpha)
        _, ball_pairs, _ = render(wide, views, board, return_pairs=True)
    key = jax.random.PRNGKey(seed)
    carved_sc = Scratches(sc.p0, sc.p1, sc.width, plunge.astype(np.float32), sc.alpha)
    carved_rad = np.asarray(brute_render(carved_sc, views, board, n=samples, key=key, pairs=ball_pairs,
                                         ball_radius=profile.radius), np.float64)
    # (the design's own profile: arcs for an arc design, `brute` follows `Scratches.profile`)
    own_rad = np.asarray(brute_render(sc, views, board, n=samples, key=key, pairs=pairs), np.float64)
    # Control variate: the analytic render of the design's profile plus the brute-force difference
    # (ball - design profile) on the same samples; unbiased for the as-carved radiance, with the
    # sampling noise of the two brute renders mostly cancelling.
    cv_rad = np.maximum(np.asarray(rad, np.float64) + carved_rad - own_rad, 0.0)
    carved = np.asarray(display(cv_rad))
    carved_brute = np.asarray(display(carved_rad))
    own = np.asarray(display(own_rad))
    ref = np.clip(np.asarray(design_display, np.float64), 0.0, 1.0)
    return {
        "ssim": image_metrics(carved, ref)["ssim"],
        "ssim_brute": image_metrics(carved_brute, ref)["ssim"],
        "ssim_profile_only": image_metrics(carved_brute, np.clip(own, 0, 1))["ssim"],
        "ssim_noise_floor": image_metrics(own, ref)["ssim"],
        "samples": samples,
        "plunge": how,
        "plunge_mm": [1e3 * float(plunge.min()), 1e3 * float(plunge.max())] if plunge.size else [0.0, 0.0],
        "seconds": time.perf_counter() - t0,
        "display": carved,
    }


def carving_estimate(design: designfile.Design, profile: MachineProfile, *, time_limit: float = 5.0,
                     plunge=None) -> dict:
    """Carving time of `design` on `profile`: ordered toolpath (greedy + `time_limit` s of 2-opt/
    Or-opt, as `jscratch.fabricate` does with its own limit; 0: greedy alone, the same on every
    run) and `carving_seconds`."""
    from jscratch.toolpath import order_scratches

    p0 = 1000.0 * design.p0
    p1 = 1000.0 * design.p1
    ordering = order_scratches(p0, p1, (0.0, 0.0), improve=time_limit != 0, time_limit=time_limit)
    if plunge is None:
        plunge, _ = plunges(design, profile)
    cut = float(np.hypot(*(p1 - p0).T).sum())
    est = carving_seconds(profile, n=design.n, cut_mm=cut, travel_mm=ordering.travel,
                          plunge_mm_total=1000.0 * float(np.sum(plunge)))
    return {"estimated_seconds": est, "estimated_hours": est / 3600.0, "scratches": design.n,
            "cut_length_m": cut / 1000.0, "travel_m": ordering.travel / 1000.0,
            "seconds_per_scratch": est / max(design.n, 1), "ordering_seconds": ordering.seconds,
            "machine": profile.name}
