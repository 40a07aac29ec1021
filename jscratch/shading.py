"""Shading (docs/model.md §1 and §4): pixel footprints and centres, half vectors, the flat
board's NDF, `shade` (patch NDF and coverage to linear radiance) and `display` (radiance to
display values).

Imports: `jscratch.scene` (`Board`, `Views`).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jscratch.errors import InputError, instance_arg, real_number, shape_arg, shown
from jscratch.scene import Board, Views, array_arg, dtype_arg

__all__ = [
    "DISPLAY_GAMMA",
    "DISPLAY_KNEE",
    "board_ndf",
    "display",
    "half_vectors",
    "pixel_centres",
    "pixel_edges",
    "pixel_footprints",
    "shade",
]

#: Display gamma: display value ``radiance ** (1 / DISPLAY_GAMMA)`` above the knee.
DISPLAY_GAMMA = 2.2
#: Knee of the display transform (linear radiance, W/(sr m^2)); display value ``0.0152`` there.
DISPLAY_KNEE = 1e-4


def pixel_edges(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Pixel edges in float64: x edges ``(W+1,)`` left to right, y edges ``(H+1,)`` top to bottom."""
    xe = np.arange(board.W + 1, dtype=np.float64) * board.Sx / board.W
    ye = board.Sy - np.arange(board.H + 1, dtype=np.float64) * board.Sy / board.H
    ye[-1] = 0.0
    return xe, ye


def pixel_footprints(board: Board, dtype=None) -> Float[Array, "p 4 2"]:
    """Pixel footprints (docs/model.md §1) as counter-clockwise quads.

    **Returns:** ``(H*W, 4, 2)`` board metres; pixel ``r*W + c`` is
    ``(x0, y0), (x1, y0), (x1, y1), (x0, y1)`` with ``x0 = c Sx/W``, ``y1 = Sy - r Sy/H``, in
    `dtype` (float32 or float64; default float).
    """
    instance_arg("pixel_footprints", "board", board, Board)
    dtype = dtype_arg("pixel_footprints", dtype)
    xe, ye = pixel_edges(board)
    c = np.tile(np.arange(board.W), board.H)
    r = np.repeat(np.arange(board.H), board.W)
    x0, x1, y0, y1 = xe[c], xe[c + 1], ye[r + 1], ye[r]
    fp = np.stack([np.stack([x0, y0], -1), np.stack([x1, y0], -1), np.stack([x1, y1], -1),
                   np.stack([x0, y1], -1)], 1)
    return jnp.asarray(fp, dtype)


def pixel_centres(board: Board, dtype=None) -> Float[Array, "p 2"]:
    """Footprint centres ``(H*W, 2)`` (board metres), pixel ``r*W + c``, in `dtype` (float32 or
    float64; default float)."""
    instance_arg("pixel_centres", "board", board, Board)
    dtype = dtype_arg("pixel_centres", dtype)
    xe, ye = pixel_edges(board)
    c = np.tile(np.arange(board.W), board.H)
    r = np.repeat(np.arange(board.H), board.W)
    ctr = np.stack([0.5 * (xe[c] + xe[c + 1]), 0.5 * (ye[r] + ye[r + 1])], -1)
    return jnp.asarray(ctr, dtype)


def _unit(v):
    return v / jnp.sqrt(jnp.sum(v * v, -1, keepdims=True))


class _Geometry(NamedTuple):
    wo: Array  # (M, P, 3)
    wi: Array  # (M, P, 3)
    h: Array  # (M, P, 3)
    r2: Array  # (M, P)


@eqx.filter_jit
def _geometry(views: Views, board: Board, dtype) -> _Geometry:
    p = pixel_centres(board, dtype)
    p3 = jnp.concatenate([p, jnp.zeros_like(p[:, :1])], -1)[None]  # (1, P, 3)
    cam = views.camera.astype(dtype)[:, None]
    lig = views.light.astype(dtype)[:, None]
    wo = _unit(cam - p3)
    dl = lig - p3
    r2 = jnp.sum(dl * dl, -1)
    wi = dl / jnp.sqrt(r2)[..., None]
    return _Geometry(wo, wi, _unit(wi + wo), r2)


def half_vectors(views: Views, board: Board, dtype=None) -> Float[Array, "m p 3"]:
    """Board-frame unit half vectors at every footprint centre, ``(M, H*W, 3)`` (docs/model.md §4),
    as `cull.cull` wants them (``h_pixel = half_vectors(...)[j]``); in `dtype` (float32 or
    float64; default that of the cameras)."""
    return _half_vectors("half_vectors", views, board, dtype)


def _half_vectors(where: str, views, board, dtype):
    """`half_vectors`, after `InputError` (one line, naming `where`) for `views` or `board` of
    another type or a `dtype` other than float32, float64 or None."""
    instance_arg(where, "views", views, Views)
    instance_arg(where, "board", board, Board)
    dtype = views.camera.dtype if dtype is None else dtype_arg(where, dtype)
    return _geometry(views, board, dtype).h


def board_ndf(views: Views, board: Board, dtype=None) -> Float[Array, "m p"]:
    """The flat board's GGX ``D(h; a_S)`` at every footprint centre, ``(M, H*W)`` (1/sr): the
    board term of `shade` per unit uncovered area, as `cull.cull_coverage` wants it (largest over
    the views)."""
    return _ggx_unit(_half_vectors("board_ndf", views, board, dtype), board.a_S)


def _ggx_unit(h, a):
    """GGX ``D(h_z; a)`` for unit ``h`` with the cancellation-free denominator
    ``(h_z^2 (a^2 - 1) + 1) = h_x^2 + h_y^2 + a^2 h_z^2``."""
    hz = h[..., 2]
    den = h[..., 0] ** 2 + h[..., 1] ** 2 + (a * hz) ** 2
    return jnp.where(hz > 0, a * a / (jnp.pi * den * den), 0.0)


def _smith_g1(vz, a):
    return 2 * vz / (vz + jnp.sqrt(a * a + (1 - a * a) * vz * vz))


def shade(D_P: Float[Array, "m p"], coverage: Float[Array, "m p"], views: Views,
          board: Board) -> Float[Array, "m p"]:
    """Per-pixel shading (docs/model.md §4) at the footprint centres.

    ``f = (D_P + max(0, 1 - c) D_ggx(h_z; a_S)) G F / (4 wi_z wo_z)``,
    ``radiance = I f wi_z / r2``.

    **Arguments:** `D_P` patch NDF ``(M, H*W)`` (1/sr); `coverage` ``c`` ``(M, H*W)``, ``(1, H*W)``
    or ``(H*W,)``; `views`; `board`.

    **Returns:** linear radiance ``(M, H*W)`` (W/(sr m^2)), in the dtype of `D_P`.

    **Raises:** `InputError`, one line: `views` or `board` of another type, or `D_P` or
    `coverage` of another shape.
    """
    instance_arg("shade", "views", views, Views)
    instance_arg("shade", "board", board, Board)
    m, p = views.m, board.n_pixels
    shape_arg("shade", "D_P", D_P, (m, p), what=" (M views, H*W pixels)")
    shape_arg("shade", "coverage", coverage, (m, p), (1, p), (p,), what=" (M views, H*W pixels)")
    D_P = array_arg("shade", "D_P", D_P)
    dtype = D_P.dtype
    g = _geometry(views, board, dtype)
    wiz, woz = g.wi[..., 2], g.wo[..., 2]
    D = D_P + jnp.maximum(0.0, 1.0 - coverage) * _ggx_unit(g.h, board.a_S)
    G = _smith_g1(wiz, board.a_G) * _smith_g1(woz, board.a_G)
    F = board.F0 + (1 - board.F0) * (1 - jnp.sum(g.wo * g.h, -1)) ** 5
    f = D * G * F / (4 * wiz * woz)
    return views.intensity.astype(dtype)[:, None] * f * wiz / g.r2


def display(radiance: ArrayLike, gamma: float = DISPLAY_GAMMA,
            knee: float = DISPLAY_KNEE) -> Array:
    """Display values from linear radiance: ``radiance ** (1/gamma)`` with a finite slope at 0.

    Exact form, with ``g = 1/gamma``, knee ``k`` and ``P = k ** (g - 1)``:

    - ``x >= k``: ``y = x ** g`` (the plain gamma);
    - ``x < k``: ``y = (2 - g) P x + (g - 1) (P / k) x**2``, the quadratic through ``0`` that
      matches ``x ** g`` in value and slope at ``k`` (so ``y`` is C1 and increasing on ``[0, inf)``).

    The slope at 0 is ``(2 - g) P``: ``234.9`` for the defaults (``gamma = 2.2``, ``k = 1e-4``,
    where ``y = 0.0152``, about 4/255); it is positive for ``gamma > 1/2`` only, so a smaller
    ``gamma`` is refused. Negative inputs (the renderer produces none beyond rounding) follow
    the same quadratic. No clipping above 1. Elementwise, any shape, follows the input dtype.

    **Raises:** `InputError`, one line, for a `radiance` that is no numeric array, a `gamma` or
    `knee` that is not a finite number > 0, or a `gamma` of 1/2 or less.
    """
    gamma, knee = _positive("gamma", gamma), _positive("knee", knee)
    if gamma <= 0.5:
        raise InputError(f"display: `gamma` must be > 0.5 (below, the curve falls near 0: its "
                         f"slope there, (2 - 1/gamma) knee^(1/gamma - 1), is negative); got "
                         f"{gamma}")
    return _display(array_arg("display", "radiance", radiance), gamma, knee)


def _positive(name: str, v) -> float:
    """`display`'s `gamma` or `knee` as a float: a finite number > 0 (``gamma <= 0`` has no
    ``1 / gamma``, ``knee <= 0`` no ``knee ** (1/gamma - 1)``); `InputError` otherwise. A traced
    value is left to ``float``, which refuses it (both are static)."""
    if isinstance(v, jax.core.Tracer):
        return float(v)
    x = real_number(v)
    if x is None or not (math.isfinite(x) and x > 0):
        raise InputError(f"display: `{name}` must be a finite number > 0; got {shown(v)}")
    return x


@functools.partial(jax.jit, static_argnums=(1, 2))
def _display(x, gamma: float, knee: float) -> Array:
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    g = 1.0 / gamma
    P = knee ** (g - 1.0)
    low = (2.0 - g) * P * x + (g - 1.0) * (P / knee) * x * x
    # double-where: no inf slope of x**g at 0 in the dead branch (not `maximum`, whose gradient
    # at x = knee is split in half between its two arguments)
    high = jnp.where(x < knee, knee, x) ** g
    return jnp.where(x < knee, low, high)
