"""Carvable grooves by construction: one plunge per scratch, rendered as the ball's own arc or
mapped to the paper's profile.

With `MachineProfile.groove_fit` ``"arc"`` (the default) a plunge ``p`` is rendered as the groove
the ball cuts, the circular arc of docs/model.md §13 (`jscratch.scene.Scratches` with profile
``"arc"``: ``w = 2R``, ``d = -2R log(1 - p/R)``, `jscratch.arc.arc_groove`): nothing is fitted
and the design's render is the carved board's up to the model's own approximations. The fits below
map a plunge to the paper's profile instead (``"height"``, ``"slope"``), for comparison.

A ball-end cutter of radius ``R`` plunged to ``p`` cuts the circular arc
``z(x) = R - p - sqrt(R^2 - x^2)`` over ``|x| < a = sqrt(2Rp - p^2)``; its wall slope angle is
``theta_ball(x) = asin(x / R)``. The renderer's groove (docs/model.md §2) has
``theta(x) = 2 atan(2x / w)`` over ``|x| < x_max``. What shading sees is the distribution of wall
normals over the groove's projected area (docs/model.md §3 integrates the NDF in board area), so the
map chooses, for each plunge, the ``(w, d)`` whose groove

1. has the cut's width exactly (``x_max = a``, so coverage and binning are the cut's), i.e.
   ``d = -(w/2) log(1 - 4 a^2 / w^2)``, and
2. has the remaining parameter ``w`` fitted by least squares at area-uniform points
   ``x_k = a (k + 1/2) / K`` (`criterion`):

   - ``"height"``: the heights ``h(x_k)`` against the
     arc's (both are zero at ``x = a``);
   - ``"slope"``: the wall angles, ``sum_k (theta(x_k) - theta_ball(x_k))^2``; both increase
     with ``x``, so this is the squared 2-Wasserstein distance between the two area-weighted
     slope distributions (what shading integrates);
   - ``"cdf"``: the area below each wall angle, at angles uniform over the cut's range.

   Measured on the default design (`benchmarks/RESULTS.md`): SSIM of the as-carved
   render against the render of the mapped grooves, same plunges, 32x32 samples per pixel:
   height 0.918/0.986/0.966, slope 0.888/0.988/0.960, cdf 0.869/0.990/0.955. The paper profile
   cannot follow the ball's arc everywhere (its wall-angle density ``(w/4) sec^2(theta/2)`` against
   the ball's ``R cos(theta)``); the slope fit weights every ``x`` alike and so gives the steep
   wall tops, which a view whose half vector is 49 degrees from the normal sees, too little
   slope; the height fit ends steeper (``w / 2a`` 1.53 against 1.66 at the deepest plunge) and
   matches those views better at a small cost for the shallow ones.

The fit (optimistix Levenberg-Marquardt, vmapped over a grid of plunges) runs once per machine
(`groove_map`, cached); the optimiser's width parameter is then the plunge logit
``z``: ``p = p_min + (p_max - p_min) sigmoid(z)``, and ``(w, d)`` follow from ``p`` (the
arc's in closed form; a fit's by interpolating ``log(w / 2a - 1)`` on the grid). Every ``p`` lies in ``[p_min, p_max]`` whatever
``z`` is, so every groove is carvable. See `GrooveMap`.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import arc
from jscratch.errors import InputError

__all__ = ["GrooveMap", "groove_map", "ball_slope_fit", "GROOVE_MODES"]

#: ``DesignConfig.groove``: ``"carvable"`` (plunge in the profile's range) or ``"free"`` (w, d free).
GROOVE_MODES = ("carvable", "free")

_SAMPLES = 64
_GRID = 65


def _angles(t, a, x):
    """Wall angles of the paper profile with ``x_max = a`` and ``w = 2a (1 + e^t)`` (units of R)."""
    w = 2.0 * a * (1.0 + jnp.exp(t))
    return 2.0 * jnp.arctan(2.0 * x / w)


def _heights(t, a, x):
    """Heights of that profile: ``-(w/2) log(1 - 4x^2/w^2) - d`` with ``d`` from ``x_max = a``."""
    w = 2.0 * a * (1.0 + jnp.exp(t))
    d = -0.5 * w * jnp.log1p(-((2.0 * a / w) ** 2))
    return -0.5 * w * jnp.log1p(-((2.0 * x / w) ** 2)) - d


def _fit_one(t0, a, criterion):
    """Least-squares ``t`` (``w = 2a (1 + e^t)``, units of R) for half width ``a``: wall angles
    (``"slope"``) or heights (``"height"``); returns ``t`` and the RMS wall-angle error (rad)."""
    import optimistix as optx

    s = (jnp.arange(_SAMPLES, dtype=a.dtype) + 0.5) / _SAMPLES
    x = a * s
    angle = jnp.arcsin(x)
    height = 1.0 - (1.0 - jnp.sqrt(1.0 - a * a)) - jnp.sqrt(1.0 - x * x)  # R - p - sqrt(R^2 - x^2)

    theta = jnp.arcsin(a) * s  # uniform wall angles over the cut's range

    def residual(t, _):
        if criterion == "slope":
            return _angles(t, a, x) - angle
        if criterion == "cdf":  # area below wall angle theta, paper vs ball, uniform in theta
            w = 2.0 * a * (1.0 + jnp.exp(t))
            return (jnp.minimum(0.5 * w * jnp.tan(0.5 * theta), a) - jnp.sin(theta)) / a
        return _heights(t, a, x) - height

    sol = optx.least_squares(residual, optx.LevenbergMarquardt(rtol=1e-9, atol=1e-12), t0,
                             max_steps=200, throw=False)
    r = _angles(sol.value, a, x) - angle
    return sol.value, jnp.sqrt(jnp.mean(r * r))


_fit_vmapped = {c: jax.jit(jax.vmap(functools.partial(_fit_one, criterion=c))) for c in ("slope", "height", "cdf")}


def ball_slope_fit(plunge_over_r, criterion: str = "slope") -> tuple[np.ndarray, np.ndarray]:
    """For plunges ``p / R`` (array), the fitted ``t = log(w / 2a - 1)`` and the RMS wall-angle
    error (radians) between the paper profile ``(w, d)`` and the ball's arc (units of ``R``).
    `criterion` ``"slope"`` (the default, see the module docstring) or ``"height"`` (least-squares
    heights, the alternative measured in `benchmarks/RESULTS.md`)."""
    p = np.asarray(plunge_over_r, np.float64)
    a = np.sqrt(2.0 * p - p * p)
    t0 = np.log(np.maximum(2.0 / a - 1.0, 1e-3))
    # Always in float32, whether or not jax_enable_x64 is on: the map is part of a design's
    # result, so it must not depend on a process-wide flag (a design from a notebook with float64
    # enabled equals the command line's). Its float32 rounding (~1e-7 in t) is far below the
    # fit's own wall-angle error.
    with jax.enable_x64(False):
        t, rms = _fit_vmapped[criterion](jnp.asarray(t0, jnp.float32),
                                         jnp.asarray(a, jnp.float32))
        return np.asarray(t, np.float64), np.asarray(rms, np.float64)


@dataclasses.dataclass(frozen=True)
class GrooveMap:
    """Plunge -> rendered groove, for one cutter (hashable: a static field of `DesignParams`).

    **Fields:** `radius`, `p_min`, `p_max` (m); `fit` the `MachineProfile.groove_fit` (``"arc"``:
    the ball's arc itself, `t_grid` empty and `rms_deg` 0); `t_grid` the fitted
    ``log(w / 2a - 1)`` at `_GRID` plunges evenly spaced in ``[p_min, p_max]``; `rms_deg` the
    largest RMS wall-angle error of the fit over the grid (degrees).
    """

    radius: float
    p_min: float
    p_max: float
    t_grid: tuple
    rms_deg: float
    fit: str = "height"

    @property
    def scratch_profile(self) -> str:
        """The `jscratch.scene.Scratches.profile` the map's grooves render with."""
        return "arc" if self.fit == "arc" else "paper"

    def plunge(self, z):
        """Plunge ``p`` (m) of the unconstrained ``z``: ``p_min + (p_max - p_min) sigmoid(z)``."""
        return self.p_min + (self.p_max - self.p_min) * jax.nn.sigmoid(z)

    def profile(self, z):
        """``(w, d)`` (m) of the paper profile matching the cut at plunge ``plunge(z)`` (jittable)."""
        return self.profile_of_plunge(self.plunge(z))

    def profile_of_plunge(self, p):
        """``(w, d)`` (m) for plunge ``p`` (m), ``p`` within ``[p_min, p_max]`` (jittable)."""
        p = jnp.asarray(p)
        dt = p.dtype
        if self.fit == "arc":
            return arc.arc_groove(p, jnp.asarray(self.radius, dt))
        R = jnp.asarray(self.radius, dt)
        grid = jnp.linspace(self.p_min, self.p_max, len(self.t_grid), dtype=dt)
        t = jnp.interp(p, grid, jnp.asarray(self.t_grid, dt))
        a = jnp.sqrt(jnp.maximum(2.0 * R * p - p * p, 0.0))
        # w = 2a (1 + e^t); d = -(w/2) log(1 - (2a/w)^2) = (w/2) (2 log(1 + e^t) - t - log(2 + e^t)).
        sp = jax.nn.softplus(t)
        w = 2.0 * a * jnp.exp(sp)
        d = 0.5 * w * (2.0 * sp - t - (math.log(2.0) + jax.nn.softplus(t - math.log(2.0))))
        return w, d

    def z_of_plunge(self, p) -> np.ndarray:
        """The ``z`` of plunge ``p`` (m), numpy; ``p`` is clipped just inside ``(p_min, p_max)``."""
        u = (np.asarray(p, np.float64) - self.p_min) / (self.p_max - self.p_min)
        u = np.clip(u, 1e-4, 1 - 1e-4)
        return np.log(u) - np.log1p(-u)

    def plunge_of_width(self, groove_width) -> np.ndarray:
        """Plunge (m) whose cut is `groove_width` (m) wide, clipped to ``[p_min, p_max]``, numpy."""
        a = np.minimum(0.5 * np.asarray(groove_width, np.float64), self.radius)
        p = self.radius - np.sqrt(self.radius**2 - a * a)
        return np.clip(p, self.p_min, self.p_max)

    def plunge_of_profile(self, width, depth) -> np.ndarray:
        """Invert the map (numpy): the plunge whose cut has the half width of ``(w, d)``."""
        from jscratch.designfile import groove_half_width

        return self.plunge_of_width(2.0 * groove_half_width(width, depth))


@functools.lru_cache(maxsize=16)
def groove_map(radius: float, p_min: float, p_max: float, criterion: str = "arc") -> GrooveMap:
    """The plunge -> ``(w, d)`` map for a ball of `radius` over ``[p_min, p_max]`` (m): the arc
    itself (``criterion = "arc"``) or the paper profile fitted by `criterion` (``"slope"``,
    ``"height"`` or ``"cdf"``, `ball_slope_fit`), once (cached). **Raises** `InputError` unless
    ``0 < p_min < p_max < radius`` and `criterion` is one of those."""
    if criterion not in ("arc", *_fit_vmapped):
        raise InputError(f"groove map: criterion must be 'arc', 'slope', 'height' or 'cdf', got "
                         f"{criterion!r}")
    if not (0 < p_min < p_max < radius):
        raise InputError(f"groove map needs 0 < p_min < p_max < radius, got {p_min}, {p_max}, {radius}")
    if criterion == "arc":  # the ball's own groove: nothing to fit
        return GrooveMap(float(radius), float(p_min), float(p_max), (), 0.0, "arc")
    grid = np.linspace(p_min, p_max, _GRID) / radius
    t, rms = ball_slope_fit(grid, criterion)
    return GrooveMap(float(radius), float(p_min), float(p_max), tuple(float(v) for v in t),
                     float(np.degrees(rms.max())), criterion)


def groove_map_of(profile) -> GrooveMap:
    """`groove_map` of a `jscratch.machine.MachineProfile`."""
    p_min, p_max = profile.plunge_range
    return groove_map(profile.radius, p_min, p_max, profile.groove_fit)
