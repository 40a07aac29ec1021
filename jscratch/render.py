"""Differentiable multi-view rendering of a scratched board (SPEC sections 1, 4 and 5).

The forward model: for every view ``j`` and pixel ``P`` the patch NDF ``D_P`` and the scratch
coverage ``c`` are sums of the per-pair integrals ``jscratch.ndf.pair_integral`` over the
(pixel, scratch) pairs that ``jscratch.bvh`` finds, divided by the footprint area ``S_P``; the pixel
is then shaded at its footprint centre (SPEC section 4) into linear radiance.

**Scene objects** (equinox modules, data only):

- `Board`: board size ``Sx, Sy`` (m), image shape ``(H, W)`` and the board material (``F0``,
  Smith roughness ``a_G``, board GGX roughness ``a_S``); all static.
- `Scratches`: ``p0, p1`` ``(N, 2)`` (m), ``width, depth`` ``(N,)`` (m), ``alpha`` ``(N,)``.
- `Views`: ``camera, light`` ``(M, 3)`` (m), ``intensity`` ``(M,)`` (W/sr).
- `views_on_circle`: the paper's view layout (SPEC section 5).

**Rendering:**

- `render(scratches, views, board, *, eps=0.0)`: host driver; bins (`bin_pairs`), culls per
  view when ``eps > 0`` (`cull_pairs`, ``bvh.cull``) and calls `render_pairs`.
- `render_pairs(scratches, views, board, pairs)`: the differentiable core, jittable, for use
  inside a loss; the pair list is integer data computed outside the differentiated function
  (`bin_pairs` makes one).
- `render_reference(scratches, views, board)`: float64 all-pairs reference (every scratch against
  every pixel, dense sum, plain autodiff), for small scenes and tests.
- `display(radiance)`: the display transform (gamma 2.2 with a finite slope at 0).
- `pixel_footprints`, `pixel_centres`, `half_vectors`, `shade`: the pieces, public for notebooks,
  the brute-force renderer (`jscratch.brute`) and `bvh.cull`.

**Memory design.** `render_pairs` evaluates the pairs in fixed-size chunks inside a `lax.scan`
and segment-sums each chunk into per-pixel accumulators, so the forward pass holds
``O(M H W + N + chunk)`` floats whatever the number of pairs ``L``. Its reverse pass is a
`jax.custom_vjp`: the residuals are the inputs only (parameters, half vectors and the integer pair
list); the backward pass walks the same chunks again, recomputes each chunk's per-pair VJP and
scatter-adds it into the per-scratch parameter gradients (and the per-pixel half-vector
gradients), so a gradient step also holds ``O(M H W + N + chunk)`` floats beyond the pair list.
Cost: the backward pass re-evaluates the forward kernel once (as `jax.checkpoint` would).
Consequence: forward-mode autodiff (``jax.jvp``) is not available through `render_pairs`.

**Work skipped.** Before the scans, each shard's pairs are sorted (stably, O(L)) by class
(`_pair_classes`): by how many of the `ndf.N_PIECES` boundary pieces of footprint ∩ groove
are not points (`ndf.PairGeometry.count`: at most 2, 3, more), padding last. Per chunk the
kernel computes each pair's view-independent geometry once (`ndf.pair_geometry`) and then, per
view, integrates only the first `k` pieces (`ndf.lit_integral(..., pieces=k)`), `k` the
smallest of `PIECE_BUDGETS` that holds every count of the chunk (one `lax.switch` branch per
budget, forward and reverse); chunks of padding are not evaluated. Most pairs of a scene have
two pieces (the footprint edges the groove crosses) where the general kernel integrates six.
The budget is chosen from the counts the kernel computes itself, so the sorting decides only
the speed: the results are those of the full kernel whatever the layout.

**Multiple devices.** Given a `jax.sharding.Mesh`, `render_pairs` shards the *pixel* axis
over the mesh axes with `jax.shard_map`: the ``H*W`` pixels (row-major) are split into
``n_shards`` contiguous blocks of ``Pb = ceil(H / n_shards) W`` pixels (strips of rows), device
``s`` owns block ``s``: its half vectors, its accumulators and its slice of the output, which
comes back sharded over image rows (when ``n_shards`` divides ``H``; else XLA reshards it).
Parameters (scratches, views) are replicated; in the backward pass each device's parameter
gradients are ``psum``-ed, pixel-side gradients stay on their device. The pair list must be laid
out by block (``n_shards`` equal segments, segment ``s`` holding only pixels of block ``s``):
`bin_pairs` and `cull_pairs` build that with ``shards=n_shards`` and `render` does it from the
mesh; `render_pairs` checks it (see its "Errors").
The call and its result are the same as on one device (up to summation order). Each segment is
padded to the fullest block, so a board whose scratches crowd into few blocks balances poorly.

Computation follows the dtype of ``scratches`` (float32 for users, float64 for references);
``views`` are cast to it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jscratch import ndf

__all__ = [
    "DEFAULT_CHUNK",
    "DISPLAY_GAMMA",
    "DISPLAY_KNEE",
    "Board",
    "Scratches",
    "Views",
    "bin_pairs",
    "cull_pairs",
    "display",
    "grad_compiler_options",
    "half_vectors",
    "board_ndf",
    "pixel_centres",
    "pixel_footprints",
    "render",
    "render_pairs",
    "render_reference",
    "shade",
    "views_on_circle",
]

#: Pairs per chunk in `render_pairs` (per device). Peak memory of the per-pair work scales with it.
DEFAULT_CHUNK = 16384
#: Display gamma: display value ``radiance ** (1 / DISPLAY_GAMMA)`` above the knee.
DISPLAY_GAMMA = 2.2
#: Knee of the display transform (linear radiance, W/(sr m^2)); display value ``0.0152`` there.
DISPLAY_KNEE = 1e-4


# --------------------------------------------------------------------------------------------
# Scene objects
# --------------------------------------------------------------------------------------------


def _to_shape(shape) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"Board: `shape` must be (H, W), two positive ints; got {shape!r}") from None
    return (h, w)


class Board(eqx.Module):
    """The board ``[0, Sx] x [0, Sy]`` (m) in the plane ``z = 0``, its image grid and material.

    Every field is static (hashable, no array leaves): changing one recompiles a jitted render.

    **Arguments:**

    - `shape`: image ``(H, W)`` in pixels; row 0 lies along the board edge ``y = Sy`` (SPEC 1).
    - `Sx`, `Sy`: board size (m). Default 0.3.
    - `F0`: Schlick reflectance at normal incidence. Default 0.91 (aluminium).
    - `a_G`: roughness of the Smith GGX shadowing-masking term. Default 0.04.
    - `a_S`: GGX roughness of the flat (unscratched) board. Default 0.04.
    """

    shape: tuple[int, int] = eqx.field(static=True, default=(256, 256), converter=_to_shape)
    Sx: float = eqx.field(static=True, default=0.3, converter=float)
    Sy: float = eqx.field(static=True, default=0.3, converter=float)
    F0: float = eqx.field(static=True, default=0.91, converter=float)
    a_G: float = eqx.field(static=True, default=0.04, converter=float)
    a_S: float = eqx.field(static=True, default=0.04, converter=float)

    def __check_init__(self):
        h, w = self.shape
        if h < 1 or w < 1:
            raise ValueError(f"Board: `shape` must be positive (H, W); got {self.shape}")
        for name in ("Sx", "Sy"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"Board: `{name}` must be a positive finite length (m); got {v}")
        if not 0.0 <= self.F0 <= 1.0:
            raise ValueError(f"Board: `F0` must lie in [0, 1]; got {self.F0}")
        for name in ("a_G", "a_S"):
            v = getattr(self, name)
            if not 0.0 < v <= 1.0:
                raise ValueError(f"Board: `{name}` must lie in (0, 1]; got {v}")

    @property
    def H(self) -> int:
        return self.shape[0]

    @property
    def W(self) -> int:
        return self.shape[1]

    @property
    def n_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def pixel_area(self) -> float:
        """Footprint area ``S_P`` (m^2)."""
        return (self.Sx / self.W) * (self.Sy / self.H)


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _float_dtype(*xs):
    dt = jnp.result_type(*xs)
    if not jnp.issubdtype(dt, jnp.floating):
        dt = jnp.result_type(float)
    return dt


class Scratches(eqx.Module):
    """``N`` straight scratches (SPEC sections 1-2).

    **Arguments:**

    - `p0`, `p1`: endpoints, ``(N, 2)``, board metres.
    - `width`: profile width ``w`` (m), ``(N,)`` or a scalar broadcast to ``(N,)``. Default ``1e-4``.
    - `depth`: depth ``d`` (m), ``(N,)`` or scalar. Default ``1e-4``.
    - `alpha`: intrinsic GGX roughness in ``(0, 1)`` (the domain of `ndf.pair_integral`),
      ``(N,)`` or scalar. Default ``0.04``.

    All five arrays share one floating dtype (that of ``p0, p1``; integers become the default float).
    Shapes are checked always; values (finite, ``width, depth > 0``, ``0 < alpha <= 1``) when the
    arrays are concrete. Inside jit, `render_pairs` checks values with `eqx.error_if`.
    """

    p0: Float[Array, "n 2"]
    p1: Float[Array, "n 2"]
    width: Float[Array, " n"]
    depth: Float[Array, " n"]
    alpha: Float[Array, " n"]

    def __init__(self, p0: ArrayLike, p1: ArrayLike, width: ArrayLike = 1e-4,
                 depth: ArrayLike = 1e-4, alpha: ArrayLike = 0.04):
        p0 = jnp.asarray(p0)
        p1 = jnp.asarray(p1)
        dtype = _float_dtype(p0, p1)
        for name, p in (("p0", p0), ("p1", p1)):
            if p.ndim != 2 or p.shape[1] != 2:
                raise ValueError(f"Scratches: `{name}` must have shape (N, 2); got {p.shape}")
        if p0.shape != p1.shape:
            raise ValueError(f"Scratches: `p0` {p0.shape} and `p1` {p1.shape} must have the same shape")
        n = p0.shape[0]
        self.p0 = p0.astype(dtype)
        self.p1 = p1.astype(dtype)
        for name, v in (("width", width), ("depth", depth), ("alpha", alpha)):
            v = jnp.asarray(v, dtype=dtype)
            if v.ndim == 0:
                v = jnp.broadcast_to(v, (n,))
            if v.shape != (n,):
                raise ValueError(f"Scratches: `{name}` must have shape (N,) = ({n},) or be a scalar;"
                                 f" got {v.shape}")
            setattr(self, name, v)

    def __check_init__(self):
        arrays = (self.p0, self.p1, self.width, self.depth, self.alpha)
        if any(_is_tracer(a) for a in arrays):
            return
        names = ("p0", "p1", "width", "depth", "alpha")
        for name, a in zip(names, arrays):
            bad = ~np.isfinite(np.asarray(a))
            if bad.any():
                i = int(np.argwhere(bad.reshape(a.shape[0], -1).any(-1))[0, 0])
                raise ValueError(f"Scratches: `{name}` of scratch {i} is not finite")
        for name in ("width", "depth"):
            a = np.asarray(getattr(self, name))
            if (a <= 0).any():
                i = int(np.argmax(a <= 0))
                raise ValueError(f"Scratches: `{name}` must be > 0; scratch {i} has {a[i]}")
        a = np.asarray(self.alpha)
        if ((a <= 0) | (a >= 1)).any():
            i = int(np.argmax((a <= 0) | (a >= 1)))
            raise ValueError(f"Scratches: `alpha` must lie in (0, 1); scratch {i} has {a[i]}")

    @property
    def n(self) -> int:
        return self.p0.shape[0]

    @property
    def dtype(self):
        return self.p0.dtype

    @staticmethod
    def random(key, n: int, board: Board | None = None, *, length=(0.005, 0.025),
               width: float = 1e-4, depth: float = 1e-4, alpha: float = 0.04,
               dtype=None) -> "Scratches":
        """The SPEC section 5 initial layout: midpoints uniform on the board, directions uniform,
        lengths uniform in ``length`` (m); a segment that would leave the board is shortened about
        its midpoint (keeping its direction) so both endpoints lie on the board.

        **Arguments:** `key` a PRNG key; `n` number of scratches; `board` (default `Board()`);
        `length` ``(min, max)`` (m); `width, depth, alpha` scalars; `dtype` (default float).

        **Returns:** `Scratches`.
        """
        board = Board() if board is None else board
        dtype = jnp.result_type(float) if dtype is None else dtype
        p0, p1 = _random_endpoints(key, n, float(board.Sx), float(board.Sy),
                                   tuple(float(x) for x in length), jnp.dtype(dtype))
        return Scratches(p0, p1, width, depth, alpha)


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5))
def _random_endpoints(key, n: int, Sx: float, Sy: float, length: tuple, dtype):
    """`Scratches.random`'s endpoints ``(n, 2), (n, 2)`` in one compiled call."""
    k1, k2, k3 = jax.random.split(key, 3)
    size = jnp.asarray([Sx, Sy], dtype)
    mid = jax.random.uniform(k1, (n, 2), dtype) * size
    phi = jax.random.uniform(k2, (n,), dtype, 0.0, 2 * jnp.pi)
    half = 0.5 * jax.random.uniform(k3, (n,), dtype, length[0], length[1])
    t = jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)

    def reach(direction):  # largest s with mid + s * direction on the board, (n,)
        pos = (size - mid) / jnp.where(direction > 0, direction, 1)
        neg = mid / jnp.where(direction < 0, -direction, 1)
        r = jnp.where(direction > 0, pos, jnp.where(direction < 0, neg, jnp.inf))
        return r.min(-1)

    s = jnp.minimum(half, jnp.minimum(reach(t), reach(-t)))
    return jnp.clip(mid - s[:, None] * t, 0, size), jnp.clip(mid + s[:, None] * t, 0, size)


class Views(eqx.Module):
    """``M`` view/light configurations (SPEC section 4).

    **Arguments:**

    - `camera`: camera positions ``(M, 3)`` (m), above the board (``z > 0``).
    - `light`: point-light positions ``(M, 3)`` (m), above the board (``z > 0``).
    - `intensity`: light intensities ``I_j`` (W/sr), ``(M,)`` or a scalar. Default 1.

    Shapes are checked always; values (finite, ``z > 0``, ``intensity >= 0``) when concrete.
    """

    camera: Float[Array, "m 3"]
    light: Float[Array, "m 3"]
    intensity: Float[Array, " m"]

    def __init__(self, camera: ArrayLike, light: ArrayLike, intensity: ArrayLike = 1.0):
        camera = jnp.asarray(camera)
        light = jnp.asarray(light)
        dtype = _float_dtype(camera, light)
        for name, p in (("camera", camera), ("light", light)):
            if p.ndim != 2 or p.shape[1] != 3:
                raise ValueError(f"Views: `{name}` must have shape (M, 3); got {p.shape}")
        if camera.shape != light.shape:
            raise ValueError(f"Views: `camera` {camera.shape} and `light` {light.shape} must have"
                             " the same shape")
        m = camera.shape[0]
        intensity = jnp.asarray(intensity, dtype)
        if intensity.ndim == 0:
            intensity = jnp.broadcast_to(intensity, (m,))
        if intensity.shape != (m,):
            raise ValueError(f"Views: `intensity` must have shape (M,) = ({m},) or be a scalar;"
                             f" got {intensity.shape}")
        self.camera = camera.astype(dtype)
        self.light = light.astype(dtype)
        self.intensity = intensity

    def __check_init__(self):
        if any(_is_tracer(a) for a in (self.camera, self.light, self.intensity)):
            return
        for name in ("camera", "light", "intensity"):
            a = np.asarray(getattr(self, name))
            if not np.isfinite(a).all():
                j = int(np.argwhere(~np.isfinite(a.reshape(a.shape[0], -1)).any(-1))[0, 0])
                raise ValueError(f"Views: `{name}` of view {j} is not finite")
        for name in ("camera", "light"):
            z = np.asarray(getattr(self, name))[:, 2]
            if (z <= 0).any():
                j = int(np.argmax(z <= 0))
                raise ValueError(f"Views: `{name}` of view {j} is at z = {z[j]}: it must be above"
                                 " the board (z > 0)")
        i = np.asarray(self.intensity)
        if (i < 0).any():
            j = int(np.argmax(i < 0))
            raise ValueError(f"Views: `intensity` of view {j} is negative ({i[j]})")

    @property
    def m(self) -> int:
        return self.camera.shape[0]


def _direction(polar, azimuth):
    return np.array([math.sin(polar) * math.cos(azimuth), math.sin(polar) * math.sin(azimuth),
                     math.cos(polar)])


def flat_highlight(camera, light) -> np.ndarray:
    """Where the flat board mirrors the light into the camera: the point of ``z = 0`` on the
    segment from ``camera`` to the light's mirror image ``(Lx, Ly, -Lz)`` (board metres, ``(..., 2)``).

    At that point the half vector is the board normal, so the flat board's GGX peak
    ``1 / (pi a_S^2)`` shows there.
    """
    c = np.asarray(camera, np.float64)
    l = np.asarray(light, np.float64)
    s = c[..., 2:3] / (c[..., 2:3] + l[..., 2:3])
    return c[..., :2] + s * (l[..., :2] - c[..., :2])


def views_on_circle(M: int, theta: float, distance: float = 1.0, offset: float | None = None,
                    board: Board | None = None, *, light_azimuth: float = 0.0,
                    camera_theta: float | None = None, intensity: ArrayLike = 1.0,
                    dtype=None) -> Views:
    """The paper's view layout (section 4.1, SPEC section 5), angles in radians.

    One light at polar angle ``theta`` (from the board normal) and azimuth ``light_azimuth``;
    camera ``j`` at polar angle ``camera_theta`` (default ``theta``) and azimuth
    ``2 pi j / M + offset``; all at ``distance`` from the board centre. Every view shares the light.

    A camera that sees the light mirrored by the flat board is refused: if the flat-board
    highlight (`flat_highlight`, where the half vector is the board normal) falls on the board,
    the board's own specular peak would dominate that view. With the light and cameras on one
    circle this is the camera near the light's mirror azimuth ``light_azimuth + pi``.

    **Arguments:**

    - `M`: number of views (>= 1).
    - `theta`: polar angle of the light (rad), in ``[0, pi/2)``.
    - `distance`: distance of light and cameras from the board centre (m). Default 1.
    - `offset`: azimuth of camera 0 relative to ``light_azimuth`` (rad). Default: ``pi / M`` for
      even ``M`` (the mirror azimuth midway between two cameras, every camera ``pi / M`` from it
      and from the light); for odd ``M``, ``pi / (2M)`` (every camera at least ``pi / (2M)`` from
      both the light and its mirror) when that keeps every flat-board highlight off the board,
      else ``0`` (the mirror midway between two cameras, ``pi / M`` from both; camera 0 then shares
      the light's azimuth, a retro-reflection view).
    - `board`: the board (its centre and extent). Default `Board()`.
    - `light_azimuth`, `camera_theta`, `intensity` ((M,) or scalar, W/sr), `dtype`.

    **Returns:** `Views` with ``camera, light`` ``(M, 3)`` and ``intensity`` ``(M,)``.
    """
    board = Board() if board is None else board
    if int(M) != M or M < 1:
        raise ValueError(f"views_on_circle: `M` must be a positive int; got {M!r}")
    M = int(M)
    camera_theta = theta if camera_theta is None else camera_theta
    for name, v in (("theta", theta), ("camera_theta", camera_theta)):
        if not (math.isfinite(v) and 0.0 <= v < math.pi / 2):
            hint = (f" (angles are in radians: did you mean {math.radians(v):.4f}?)"
                    if math.isfinite(v) and 1.6 <= v < 90 else "")
            raise ValueError(f"views_on_circle: `{name}` must lie in [0, pi/2) rad so that it is"
                             f" above the board; got {v}{hint}")
    if not (math.isfinite(distance) and distance > 0):
        raise ValueError(f"views_on_circle: `distance` must be positive (m); got {distance}")
    centre = np.array([board.Sx / 2, board.Sy / 2, 0.0])
    light = centre + distance * _direction(theta, light_azimuth)

    def layout(offset):
        azimuths = [2 * math.pi * j / M + offset + light_azimuth for j in range(M)]
        cameras = np.stack([centre + distance * _direction(camera_theta, a) for a in azimuths])
        spot = flat_highlight(cameras, light[None])
        on = ((spot[:, 0] >= 0) & (spot[:, 0] <= board.Sx) & (spot[:, 1] >= 0)
              & (spot[:, 1] <= board.Sy))
        return azimuths, cameras, spot, on

    if offset is None:
        azimuths, cameras, spot, on = layout(math.pi / (2 * M) if M % 2 else math.pi / M)
        if on.any() and M % 2:
            azimuths, cameras, spot, on = layout(0.0)
    else:
        azimuths, cameras, spot, on = layout(float(offset))
    if on.any():
        j = int(np.argmax(on))
        raise ValueError(
            f"views_on_circle: camera {j} (azimuth {math.degrees(azimuths[j]) % 360:.1f} deg) sees"
            f" the light mirrored by the flat board at board point ({spot[j, 0]:.4f},"
            f" {spot[j, 1]:.4f}) m, inside the board: the board's specular peak would dominate"
            " that view. Change `offset`, `M`, `theta`/`camera_theta` or `distance`.")
    dtype = jnp.result_type(float) if dtype is None else dtype
    return Views(jnp.asarray(cameras, dtype), jnp.asarray(np.repeat(light[None], M, 0), dtype),
                 jnp.asarray(intensity, dtype))


# --------------------------------------------------------------------------------------------
# Pixels and shading
# --------------------------------------------------------------------------------------------


def _edges(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Pixel edges in float64: x edges ``(W+1,)`` left to right, y edges ``(H+1,)`` top to bottom."""
    xe = np.arange(board.W + 1, dtype=np.float64) * board.Sx / board.W
    ye = board.Sy - np.arange(board.H + 1, dtype=np.float64) * board.Sy / board.H
    ye[-1] = 0.0
    return xe, ye


def pixel_footprints(board: Board, dtype=None) -> Float[Array, "p 4 2"]:
    """Pixel footprints (SPEC section 1) as counter-clockwise quads.

    **Returns:** ``(H*W, 4, 2)`` board metres; pixel ``r*W + c`` is
    ``(x0, y0), (x1, y0), (x1, y1), (x0, y1)`` with ``x0 = c Sx/W``, ``y1 = Sy - r Sy/H``.
    """
    xe, ye = _edges(board)
    c = np.tile(np.arange(board.W), board.H)
    r = np.repeat(np.arange(board.H), board.W)
    x0, x1, y0, y1 = xe[c], xe[c + 1], ye[r + 1], ye[r]
    fp = np.stack([np.stack([x0, y0], -1), np.stack([x1, y0], -1), np.stack([x1, y1], -1),
                   np.stack([x0, y1], -1)], 1)
    return jnp.asarray(fp, jnp.result_type(float) if dtype is None else dtype)


def pixel_centres(board: Board, dtype=None) -> Float[Array, "p 2"]:
    """Footprint centres ``(H*W, 2)`` (board metres), pixel ``r*W + c``."""
    xe, ye = _edges(board)
    c = np.tile(np.arange(board.W), board.H)
    r = np.repeat(np.arange(board.H), board.W)
    ctr = np.stack([0.5 * (xe[c] + xe[c + 1]), 0.5 * (ye[r] + ye[r + 1])], -1)
    return jnp.asarray(ctr, jnp.result_type(float) if dtype is None else dtype)


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
    """Board-frame unit half vectors at every footprint centre, ``(M, H*W, 3)`` (SPEC section 4),
    as `bvh.cull` wants them (``h_pixel = half_vectors(...)[j]``)."""
    dtype = views.camera.dtype if dtype is None else dtype
    return _geometry(views, board, dtype).h


def board_ndf(views: Views, board: Board, dtype=None) -> Float[Array, "m p"]:
    """The flat board's GGX ``D(h; a_S)`` at every footprint centre, ``(M, H*W)`` (1/sr): the
    board term of `shade` per unit uncovered area, as `bvh.cull_coverage` wants it (largest over
    the views)."""
    return _ggx_unit(half_vectors(views, board, dtype), board.a_S)


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
    """Per-pixel shading (SPEC section 4) at the footprint centres.

    ``f = (D_P + max(0, 1 - c) D_ggx(h_z; a_S)) G F / (4 wi_z wo_z)``,
    ``radiance = I f wi_z / r2``.

    **Arguments:** `D_P` patch NDF ``(M, H*W)`` (1/sr); `coverage` ``c`` ``(M, H*W)`` or ``(H*W,)``;
    `views`; `board`.

    **Returns:** linear radiance ``(M, H*W)`` (W/(sr m^2)), in the dtype of `D_P`.
    """
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

    The slope at 0 is ``(2 - g) P``: ``232.6`` for the defaults (``gamma = 2.2``, ``k = 1e-4``, where
    ``y = 0.0152``, about 4/255). Negative inputs (the renderer produces none beyond rounding) follow
    the same quadratic. No clipping above 1. Elementwise, any shape, follows the input dtype.
    """
    return _display(jnp.asarray(radiance), float(gamma), float(knee))


@functools.partial(jax.jit, static_argnums=(1, 2))
def _display(x, gamma: float, knee: float) -> Array:
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    g = 1.0 / gamma
    P = knee ** (g - 1.0)
    low = (2.0 - g) * P * x + (g - 1.0) * (P / knee) * x * x
    high = jnp.maximum(x, knee) ** g  # double-where: no inf slope of x**g at 0 in the dead branch
    return jnp.where(x < knee, low, high)


# --------------------------------------------------------------------------------------------
# Pair accumulation with bounded memory (custom VJP, chunked, optionally sharded)
# --------------------------------------------------------------------------------------------


class _Cfg(NamedTuple):
    H: int
    W: int
    Sx: float
    Sy: float
    chunk: int  # pairs per chunk, per device
    mesh: Any  # jax.sharding.Mesh or None
    axes: tuple  # mesh axis names the pixel axis is sharded over
    Pb: int  # pixels per shard (the whole padded pixel axis is Pb * n_shards)
    per_view: bool  # pair outputs are (view, pixel): index v * P_pad + pixel; else pixel only
    need_D: bool
    need_A: bool


def _board_of(cfg: _Cfg) -> Board:
    return Board(shape=(cfg.H, cfg.W), Sx=cfg.Sx, Sy=cfg.Sy)


def _footprint(cfg: _Cfg, xe, ye, pix):
    """The footprint ``(4, 2)`` of pixel ``pix = r*W + c`` from the pixel edges."""
    r = pix // cfg.W
    c = pix % cfg.W
    x0, x1, y0, y1 = xe[c], xe[c + 1], ye[r + 1], ye[r]
    return jnp.stack([jnp.stack([x0, y0]), jnp.stack([x1, y0]), jnp.stack([x1, y1]),
                      jnp.stack([x0, y1])])


def _split_index(cfg: _Cfg, out):
    """Global pair output index -> ``(pixel, local index)``: the board pixel (clipped into the
    board, for padding slots) and the index into this shard's flat accumulator (``Pb`` pixels,
    or ``M * Pb`` (view, pixel) slots when ``per_view``)."""
    P_pad = cfg.Pb * _n_shards(cfg.mesh, cfg.axes)
    shard = 0 if cfg.mesh is None else jax.lax.axis_index(cfg.axes)
    if cfg.per_view:
        v, pix = out // P_pad, out % P_pad
        local = v * cfg.Pb + (pix - shard * cfg.Pb)
    else:
        pix = out
        local = pix - shard * cfg.Pb
    return jnp.minimum(pix, cfg.H * cfg.W - 1), local


def _gather(params, h_loc, scr, local):
    """Per-pair parameters ``(chunk, ...)`` and half vectors ``(V, chunk, 3)``."""
    p0, p1, w, d, a = params
    take = lambda x: x.at[scr].get(mode="clip")  # sentinel N -> N-1; masked below
    return (take(p0), take(p1), take(w), take(d), take(a),
            h_loc.at[:, local].get(mode="clip"))


#: Piece budgets (`ndf.lit_integral`'s `pieces`): a chunk of pairs is integrated with the
#: smallest budget that holds the largest `ndf.PairGeometry.count` among its valid pairs.
PIECE_BUDGETS = (2, ndf.N_COMPACT, ndf.N_PIECES)


def _chunk_geometry(cfg: _Cfg, xe, ye, pix, valid, p0, p1, w, d):
    """`ndf.pair_geometry` of a chunk's pairs (fields with a leading ``(chunk,)`` axis, ``count``
    set to ``None``) and the budget index (`PIECE_BUDGETS`) its valid pairs' counts need.
    Padding slots get a benign off-board dummy pair first (double-where), so no value or
    gradient there can be NaN; their counts are ignored."""
    dt = w.dtype
    v1 = valid[:, None]
    p0 = jnp.where(v1, p0, jnp.asarray([-1.0, -1.0], dt))
    p1 = jnp.where(v1, p1, jnp.asarray([-0.99, -1.0], dt))
    w = jnp.where(valid, w, jnp.asarray(1e-4, dt))
    d = jnp.where(valid, d, jnp.asarray(1e-4, dt))
    footprints = jax.vmap(functools.partial(_footprint, cfg, xe, ye))(pix)
    geometry = jax.vmap(ndf.pair_geometry)(footprints, p0, p1, w, d)
    most = jnp.max(jnp.where(valid, geometry.count, 0))
    budget = sum((most > k).astype(jnp.int32) for k in PIECE_BUDGETS[:-1])
    return geometry._replace(count=None), budget


def _chunk_lit(pieces: int, geometry, valid, a, h):
    """Per-pair ``D_hat`` ``(V, chunk)``, one row per view of ``h`` ``(V, chunk, 3)``, from the
    chunk's geometry with `ndf.lit_integral(..., pieces=pieces)`; zero on padding slots. The
    geometry is shared by the views (vmap keeps it unbatched)."""
    dt = a.dtype
    a = jnp.where(valid, a, jnp.asarray(0.5, dt))
    h = jnp.where(valid[None, :, None], h, jnp.asarray([0.0, 0.0, 1.0], dt))
    lit = functools.partial(ndf.lit_integral, pieces=pieces)
    D = jax.vmap(jax.vmap(lit), in_axes=(None, 0, None))(geometry, h, a)
    return jnp.where(valid[None], D, jnp.zeros((), dt))


def _budgets(fn):
    """`lax.switch` branches: ``fn(pieces, ...)`` for each of `PIECE_BUDGETS`."""
    return [functools.partial(fn, k) for k in PIECE_BUDGETS]


def _edges_in(cfg: _Cfg, dtype):
    xe, ye = _edges(_board_of(cfg))
    return jnp.asarray(xe, dtype), jnp.asarray(ye, dtype)


def _chunks(cfg: _Cfg, *xs):
    return tuple(x.reshape(-1, cfg.chunk) for x in xs)


def _varying(cfg: _Cfg, tree):
    """Inside `jax.shard_map`, mark scan-carry initial values as device-varying."""
    if cfg.mesh is None:
        return tree
    return jax.tree_util.tree_map(lambda x: jax.lax.pcast(x, cfg.axes, to="varying"), tree)


def _flat_h(cfg: _Cfg, h_loc):
    """This shard's half vectors ``(V, Pb, 3)`` as the rows the pairs index: ``(V, Pb, 3)`` for a
    shared list, ``(1, V * Pb, 3)`` for per-view outputs."""
    return h_loc.reshape(1, -1, 3) if cfg.per_view else h_loc


def _fwd_local(cfg: _Cfg, params, h_loc, out, scr, valid):
    """This shard's sums: ``D`` ``(M, Pb)`` and ``A`` ``(1 or M, Pb)`` over its pairs."""
    dt = params[2].dtype
    xe, ye = _edges_in(cfg, dt)
    h_rows = _flat_h(cfg, h_loc)
    V, n_loc = h_rows.shape[:2]

    def add_chunk(carry, xs):
        Ds, As = carry
        oc, sc, vc = xs
        pix, local = _split_index(cfg, oc)
        p0, p1, w, d, a, h = _gather(params, h_rows, sc, local)
        geometry, budget = _chunk_geometry(cfg, xe, ye, pix, vc, p0, p1, w, d)
        if cfg.need_D:
            D = jax.lax.switch(budget, _budgets(_chunk_lit), geometry, vc, a, h)
            Ds = Ds.at[:, local].add(D, mode="drop")
        if cfg.need_A:
            As = As.at[local].add(jnp.where(vc, geometry.area, 0), mode="drop")
        return Ds, As

    def body(carry, xs):
        # Chunks of padding only (`_sort_pairs` puts them last) are skipped.
        return jax.lax.cond(jnp.any(xs[2]), add_chunk, lambda c, _: c, carry, xs), None

    init = _varying(cfg, (jnp.zeros((V, n_loc), dt), jnp.zeros((n_loc,), dt)))
    (Ds, As), _ = jax.lax.scan(body, init, _chunks(cfg, out, scr, valid))
    return Ds.reshape(-1, cfg.Pb), As.reshape(-1, cfg.Pb)


def _bwd_local(cfg: _Cfg, params, h_loc, out, scr, valid, gD, gA):
    dt = params[2].dtype
    xe, ye = _edges_in(cfg, dt)
    h_rows = _flat_h(cfg, h_loc)
    gD = gD.reshape(h_rows.shape[:2])
    gA = gA.reshape(-1)

    def lit_vjp(pieces, geometry, valid, a, h, ct):
        """The per-view stage's value and reverse pass in one `lax.switch` branch, so no
        residuals cross the switch."""
        _, vjp = jax.vjp(lambda g, a, h: _chunk_lit(pieces, g, valid, a, h), geometry, a, h)
        return vjp(ct)

    def add_chunk(carry, xs):
        gp0, gp1, gw, gd, ga, gh = carry
        oc, sc, vc = xs
        pix, local = _split_index(cfg, oc)
        p0, p1, w, d, a, h = _gather(params, h_rows, sc, local)
        geometry, geometry_vjp, budget = jax.vjp(
            lambda *x: _chunk_geometry(cfg, xe, ye, pix, vc, *x), p0, p1, w, d, has_aux=True)
        # Only the outputs the caller uses are differentiated (no dead reverse work).
        if cfg.need_D:
            ctD = gD.at[:, local].get(mode="clip")
            g_geometry, da, dh = jax.lax.switch(budget, _budgets(lit_vjp), geometry, vc, a, h,
                                                ctD)
        else:
            g_geometry = jax.tree_util.tree_map(jnp.zeros_like, geometry)
            da, dh = jnp.zeros_like(a), jnp.zeros_like(h)
        if cfg.need_A:
            ctA = jnp.where(vc, gA.at[local].get(mode="clip"), 0)
            g_geometry = g_geometry._replace(area=g_geometry.area + ctA)
        d0, d1, dw, dd = geometry_vjp(g_geometry)
        # The sentinel index N is out of range: mode="drop" discards padding slots (already zero).
        gp0 = gp0.at[sc].add(d0, mode="drop")
        gp1 = gp1.at[sc].add(d1, mode="drop")
        gw = gw.at[sc].add(dw, mode="drop")
        gd = gd.at[sc].add(dd, mode="drop")
        ga = ga.at[sc].add(da, mode="drop")
        gh = gh.at[:, local].add(dh, mode="drop")
        return gp0, gp1, gw, gd, ga, gh

    def body(carry, xs):
        return jax.lax.cond(jnp.any(xs[2]), add_chunk, lambda c, _: c, carry, xs), None

    # (zeros_like of the device-local half vectors is already device-varying)
    init = _varying(cfg, tuple(jnp.zeros_like(x) for x in params)) + (jnp.zeros_like(h_rows),)
    grads, _ = jax.lax.scan(body, init, _chunks(cfg, out, scr, valid))
    dparams = grads[:5]
    if cfg.mesh is not None:  # parameters are replicated: their gradient sums over all shards
        dparams = jax.lax.psum(dparams, cfg.axes)
    return dparams, grads[5].reshape(h_loc.shape)


def _maybe_shard(cfg: _Cfg, fn, in_specs, out_specs):
    """`fn` under `jax.shard_map` over ``cfg.mesh`` (identity without a mesh). Specs use ``"p"``
    for the pixel axis sharded over ``cfg.axes``."""
    if cfg.mesh is None:
        return fn
    spec = lambda s: jax.tree_util.tree_map(
        lambda t: PartitionSpec(*(cfg.axes if a == "p" else None for a in t)), s,
        is_leaf=lambda t: isinstance(t, tuple) and all(isinstance(a, (str, type(None))) for a in t))
    return jax.shard_map(fn, mesh=cfg.mesh, in_specs=spec(in_specs), out_specs=spec(out_specs))


# Sharding of each argument: params replicated, half vectors and outputs split on the pixel axis,
# the (block-laid-out) pair list split into its per-shard segments.
_REP, _PIX, _PAIRS, _HV = (), (None, "p"), ("p",), (None, "p", None)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _pair_sums(cfg: _Cfg, params, h_views, out, scr, valid):
    """Per-pixel sums over the pairs: ``sum D_hat`` ``(M, P_pad)`` and ``sum A``
    ``(1 or M, P_pad)``; ``h_views`` ``(M, P_pad, 3)``. ``out, scr, valid`` ``(L,)``: ``n_shards``
    equal segments, segment ``s`` holding only pairs of pixels ``[s Pb, (s+1) Pb)``, each a
    multiple of ``chunk`` long (in any order; `_sort_pairs`' order is the fast one)."""
    fn = _maybe_shard(cfg, functools.partial(_fwd_local, cfg),
                      (_REP, _HV, _PAIRS, _PAIRS, _PAIRS), (_PIX, _PIX))
    return fn(params, h_views, out, scr, valid)


def _pair_sums_fwd(cfg, params, h_views, out, scr, valid):
    res = (params, h_views, out, scr, valid)
    return _pair_sums(cfg, *res), res


def _pair_sums_bwd(cfg, res, g):
    params, h_views, out, scr, valid = res
    gD, gA = g
    fn = _maybe_shard(cfg, functools.partial(_bwd_local, cfg),
                      (_REP, _HV, _PAIRS, _PAIRS, _PAIRS, _PIX, _PIX), (_REP, _HV))
    dparams, dh = fn(params, h_views, out, scr, valid, gD, gA)
    return dparams, dh, None, None, None


_pair_sums.defvjp(_pair_sums_fwd, _pair_sums_bwd)


def _mesh_axes(mesh, axis_names) -> tuple:
    if mesh is None:
        return ()
    if axis_names is None:
        return tuple(mesh.axis_names)
    return (axis_names,) if isinstance(axis_names, str) else tuple(axis_names)


def _n_shards(mesh, axes) -> int:
    if mesh is None:
        return 1
    return int(np.prod([mesh.shape[a] for a in axes]))


def _round_up(x: int, m: int) -> int:
    return -(-x // m) * m


def _pixels_per_shard(board: Board, shards: int) -> int:
    """Pixels per shard: whole rows, ``ceil(H / shards) * W`` (the pixel axis is padded to
    ``shards`` times this)."""
    return -(-board.H // shards) * board.W


def _pair_classes(cfg: _Cfg, params, out, scr, valid):
    """Per pair, 1 + the index of the smallest of `PIECE_BUDGETS` that holds its
    `ndf.PairGeometry.count`, 0 for padding; int8. Only the order of the evaluation depends on
    it (`_sort_pairs`), not the results: each chunk's budget is chosen by the kernel from the
    counts it computes itself (`_chunk_geometry`)."""
    p0, p1, w, d = params[:4]
    xe, ye = _edges_in(cfg, p0.dtype)
    P_pad = cfg.Pb * _n_shards(cfg.mesh, cfg.axes)

    def count(args):
        out, scr = args
        pix = jnp.minimum(out % P_pad if cfg.per_view else out, cfg.H * cfg.W - 1)
        take = lambda x: x.at[scr].get(mode="clip")
        return ndf.pair_geometry(_footprint(cfg, xe, ye, pix), take(p0), take(p1), take(w),
                                 take(d)).count.astype(jnp.int8)

    # (chunk by chunk: no per-pair footprint array is materialised)
    n = jax.lax.map(count, (out, scr), batch_size=cfg.chunk)
    klass = 1 + sum((n > k).astype(jnp.int8) for k in PIECE_BUDGETS[:-1])
    return jax.lax.stop_gradient(jnp.where(valid, klass, 0).astype(jnp.int8))


def _sort_pairs(out, scr, valid, klass, shards: int):
    """Each shard's segment of the pair list grouped by class (`_pair_classes`: 1, 2, ..., then
    0, the padding), each group in its own order (a stable partition, O(L)). Chunks then mostly
    hold one class: chunks of padding are skipped and the others integrate only as many pieces
    as their pairs have (`PIECE_BUDGETS`). A pair list built with spare capacity
    (`bvh.build_pairs`, per-view culled lists) otherwise costs a full kernel evaluation per
    padding slot, and every pair the six pieces that few pairs have."""
    L = out.shape[0]
    Ls = L // shards
    # (a barrier: a pair list closed over as a constant would otherwise be folded at compile time)
    klass = jax.lax.optimization_barrier(klass)
    pos = jnp.zeros((shards, Ls), jnp.int32)
    start = jnp.zeros((shards, 1), jnp.int32)
    for c in (*range(1, len(PIECE_BUDGETS) + 1), 0):
        g = (klass == c).reshape(shards, Ls)
        pos = jnp.where(g, start + jnp.cumsum(g, axis=1, dtype=jnp.int32) - 1, pos)
        start = start + jnp.sum(g, axis=1, keepdims=True, dtype=jnp.int32)
    pos = (pos + (jnp.arange(shards, dtype=jnp.int32) * Ls)[:, None]).reshape(-1)
    source = jnp.zeros((L,), jnp.int32).at[pos].set(jnp.arange(L, dtype=jnp.int32),
                                                      unique_indices=True)
    return out[source], scr[source], valid[source]


def _run_pair_sums(scratches: Scratches, board: Board, h_views, out, scr, valid, *, per_view,
                   chunk, mesh, axes, need_D, need_A):
    """Pad every shard's segment of the pair list to a multiple of the chunk, pad the pixel axis
    to ``Pb * n_shards`` and call `_pair_sums`; returns sums over the board's ``P`` pixels."""
    shards = _n_shards(mesh, axes)
    P = board.n_pixels
    Pb = _pixels_per_shard(board, shards)
    Ls = out.shape[0] // shards
    chunk = int(min(chunk, _round_up(max(Ls, 1), 64)))
    Ls_pad = _round_up(max(Ls, 1), chunk)
    n = scratches.n

    def pad(x, fill):
        x = x.reshape(shards, Ls)
        x = jnp.concatenate([x, jnp.full((shards, Ls_pad - Ls), fill, x.dtype)], 1)
        return x.reshape(-1)

    if Ls_pad != Ls:
        out, scr, valid = pad(out, 0), pad(scr, n), pad(valid, False)
    if Pb * shards != P:
        fill = jnp.zeros(h_views.shape[:1] + (Pb * shards - P, 3), h_views.dtype).at[..., 2].set(1)
        h_views = jnp.concatenate([h_views, fill], 1)
    cfg = _Cfg(board.H, board.W, board.Sx, board.Sy, chunk, mesh, axes, Pb, per_view, need_D,
               need_A)
    params = (scratches.p0, scratches.p1, scratches.width, scratches.depth, scratches.alpha)
    klass = _pair_classes(cfg, params, out, scr, valid)
    out, scr, valid = _sort_pairs(out, scr, valid, klass, shards)
    Ds, As = _pair_sums(cfg, params, h_views, out, scr, valid)
    return Ds[:, :P], As[:, :P]


# --------------------------------------------------------------------------------------------
# Renderers
# --------------------------------------------------------------------------------------------


def _value_checks(scratches: Scratches, views: Views) -> list:
    """``(condition, message)`` checks of the scene's values (see `_guard`)."""
    s = scratches
    finite = jnp.all(jnp.isfinite(s.p0)) & jnp.all(jnp.isfinite(s.p1)) & jnp.all(
        jnp.isfinite(s.width)) & jnp.all(jnp.isfinite(s.depth)) & jnp.all(jnp.isfinite(s.alpha))
    return [
        (~finite, "render: a scratch parameter (p0, p1, width, depth or alpha) is NaN or infinite"),
        (jnp.any(s.width <= 0) | jnp.any(s.depth <= 0),
         "render: scratch `width` and `depth` must be > 0"),
        (jnp.any(s.alpha <= 0) | jnp.any(s.alpha >= 1), "render: scratch `alpha` must lie in (0, 1)"),
        (~(jnp.all(jnp.isfinite(views.camera)) & jnp.all(jnp.isfinite(views.light))
           & jnp.all(jnp.isfinite(views.intensity))),
         "render: a view (camera, light or intensity) is NaN or infinite"),
        (jnp.any(views.camera[:, 2] <= 0) | jnp.any(views.light[:, 2] <= 0),
         "render: every camera and light must be above the board (z > 0)"),
    ]


def _guard(x, checks, mesh):
    """Apply ``(condition, message)`` checks to ``x``. Concrete conditions (an eager call) raise
    `ValueError` at once. Traced ones use `eqx.error_if` on one device; over a mesh a runtime
    error raised on one device would leave the others waiting in a collective (XLA aborts the
    process), so there the result is poisoned instead: returns ``(x, poisoned)`` with
    ``poisoned`` a traced bool (or ``False``) for the caller to turn into NaN radiance."""
    poisoned = False
    for bad, msg in checks:
        if not isinstance(bad, jax.core.Tracer):
            if bool(bad):
                raise ValueError(msg)
        elif mesh is None:
            x = eqx.error_if(x, bad, msg)
        else:
            poisoned = poisoned | bad
    return x, poisoned


def _check_values(scratches: Scratches, views: Views):
    """`eqx.error_if` value checks (work inside jit, single device); returns checked copies."""
    w, _ = _guard(scratches.width, _value_checks(scratches, views), None)
    return eqx.tree_at(lambda t: t.width, scratches, w), views


def _pair_arrays(pairs, M: int, n: int, name: str, shards: int, P_pad: int):
    """Flatten a pair list to output indices, keeping ``shards`` equal per-shard segments (each
    input list is ``shards`` equal segments; they are interleaved so that segment ``s`` of the
    result holds segment ``s`` of every view): a single `Pairs` ``(L,)`` shared by all views
    (output = pixel), a `Pairs` with leading view axis ``(M, L)``, or a sequence of ``M`` `Pairs`
    (output ``v * P_pad + pixel``). Returns ``(out, scratch, valid, overflow, shared)``."""

    def segments(x):
        if x.shape[-1] % shards:
            raise ValueError(
                f"render_pairs: `{name}` has length {x.shape[-1]}, not a multiple of the {shards}"
                f" pixel shards of the mesh; build it with bin_pairs(..., shards={shards})")
        return x.reshape(x.shape[:-1] + (shards, x.shape[-1] // shards))

    if isinstance(pairs, (list, tuple)):
        if len(pairs) != M:
            raise ValueError(f"render_pairs: `{name}` has {len(pairs)} pair lists for {M} views")
        parts = [_pair_arrays(p, 1, n, name, shards, P_pad) for p in pairs]
        cat = lambda xs: jnp.concatenate([segments(x) for x in xs], 1).reshape(-1)
        return (cat([p[0] + j * P_pad for j, p in enumerate(parts)]), cat([p[1] for p in parts]),
                cat([p[2] for p in parts]),
                functools.reduce(jnp.logical_or, [p[3] for p in parts]), False)
    pix, scr, valid = jnp.asarray(pairs.pixel), jnp.asarray(pairs.scratch), jnp.asarray(pairs.valid)
    if not (pix.shape == scr.shape == valid.shape) or pix.ndim not in (1, 2):
        raise ValueError(f"render_pairs: `{name}` fields pixel, scratch, valid must share a shape"
                         f" (L,) or (M, L); got {pix.shape}, {scr.shape}, {valid.shape}")
    if not (jnp.issubdtype(pix.dtype, jnp.integer) and jnp.issubdtype(scr.dtype, jnp.integer)):
        raise ValueError(f"render_pairs: `{name}` pixel and scratch indices must be integers")
    overflow = jnp.any(jnp.asarray(pairs.overflow))
    valid = valid.astype(bool)
    if pix.ndim == 2:
        if pix.shape[0] != M:
            raise ValueError(f"render_pairs: `{name}` has a leading view axis of {pix.shape[0]}"
                             f" for {M} views")
        out = pix + (jnp.arange(M, dtype=pix.dtype) * P_pad)[:, None]
        inter = lambda x: jnp.swapaxes(segments(x), 0, 1).reshape(-1)  # (shards, M, Ls) order
        return inter(out), inter(scr), inter(valid), overflow, False
    segments(pix)
    return pix, scr, valid, overflow, True


def _pair_checks(out, scr, valid, overflow, *, shared: bool, M: int, P: int, Pb: int,
                 shards: int, n: int, name: str) -> list:
    """``(condition, message)`` checks of a flattened pair list for `eqx.error_if`: no overflow,
    indices in range, and (with several shards) every valid pair in its shard's pixel block."""
    P_pad = Pb * shards
    view, pix = (jnp.zeros_like(out), out) if shared else (out // P_pad, out % P_pad)
    bad = valid & ((out < 0) | (pix >= P) | (view >= M) | (scr < 0) | (scr >= n))
    checks = [(overflow, f"render_pairs: `{name}` overflowed its capacity (incomplete pair list);"
                         " rebuild it with bvh.build_pairs"),
              (jnp.any(bad), f"render_pairs: `{name}` has a valid pair with a pixel or scratch"
                             " index out of range")]
    if shards > 1:
        seg = jnp.arange(out.shape[0]) // (out.shape[0] // shards)
        checks.append((jnp.any(valid & (pix // Pb != seg)),
                       f"render_pairs: `{name}` is not laid out for {shards} pixel shards (segment"
                       f" s must hold only pixels [s*{Pb}, (s+1)*{Pb})); build it with"
                       f" bin_pairs(..., shards={shards})"))
    return checks


def render_pairs(scratches: Scratches, views: Views, board: Board, pairs,
                 coverage_pairs=None, *, chunk: int = DEFAULT_CHUNK,
                 mesh: jax.sharding.Mesh | None = None,
                 axis_names: str | Sequence[str] | None = None) -> Float[Array, "m h w"]:
    """Render linear radiance from precomputed pair lists (jittable, differentiable).

    **Arguments:**

    - `scratches`, `views`, `board`: the scene. Computation in ``scratches.dtype``.
    - `pairs`: the (pixel, scratch) pairs, as `bvh.Pairs` (fields ``pixel, scratch, valid,
      overflow``): one list ``(L,)`` shared by every view, one with a leading view axis ``(M, L)``,
      or a sequence of ``M`` lists (e.g. culled per view). Pixel indices are ``r*W + c``.
    - `coverage_pairs`: the pair list the coverage ``c`` is summed over (a shared, unculled ``(L,)``
      list). Default: ``pairs`` itself when shared, else each view's own list (exact only when the
      per-view lists are unculled: a culled pair still covers the board).
    - `chunk`: pairs per chunk per device (memory knob; results do not depend on it beyond rounding).
    - `mesh`, `axis_names`: shard the pixel axis over these mesh axes (default: all axes of
      `mesh`); the pair lists must then be laid out for ``n_shards`` pixel blocks (`bin_pairs` /
      `cull_pairs` with ``shards=n_shards``; see the module docstring).

    **Returns:** radiance ``(M, H, W)`` (W/(sr m^2)).

    Errors: non-finite or out-of-range scratch or view values, a camera or light below the board,
    an overflowed pair list, out-of-range pair indices, a pair list not laid out for the mesh.
    Called eagerly: `ValueError`. Under jit on one device: `eqx.error_if` (a runtime error).
    Under jit with a mesh: NaN radiance (a runtime error on one device of a multi-device program
    would leave the others stuck in a collective; `render` checks the scene before it renders).
    Gradients: reverse mode only (a `jax.custom_vjp` recomputes the pairs chunk by chunk).
    """
    dtype = scratches.dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"render_pairs: scratches must be floating point; got {dtype}")
    M, P, n = views.m, board.n_pixels, scratches.n
    axes = _mesh_axes(mesh, axis_names)
    shards = _n_shards(mesh, axes)
    Pb = _pixels_per_shard(board, shards)
    # The checks hang on a small replicated parameter, not on the (sharded) pair arrays.
    checks = _value_checks(scratches, views)
    views = jax.tree_util.tree_map(lambda x: x.astype(dtype), views)
    geo_h = half_vectors(views, board, dtype)  # (M, P, 3)

    def flat(p, m, what):
        out, scr, valid, over, shared = _pair_arrays(p, m, n, what, shards, Pb * shards)
        checks.extend(_pair_checks(out, scr, valid, over, shared=shared, M=m, P=P, Pb=Pb,
                                   shards=shards, n=n, name=what))
        return out, scr, valid, shared

    # A shared list is evaluated for every view at once (views vmapped inside the chunk, the
    # scratch geometry gathered once); per-view lists are flattened to outputs v*P_pad + pixel.
    out, scr, valid, shared = flat(pairs, M, "pairs")
    if coverage_pairs is not None:
        cout, cscr, cvalid, cshared = flat(coverage_pairs, 1, "coverage_pairs")
        if not cshared:
            raise ValueError("render_pairs: `coverage_pairs` must be one shared (L,) list")
    w, poisoned = _guard(scratches.width, checks, mesh)
    scratches = eqx.tree_at(lambda t: t.width, scratches, w)
    kw = dict(chunk=chunk, mesh=mesh, axes=axes)
    if n == 0:
        Ds, As = jnp.zeros((M, P), dtype), jnp.zeros((1 if shared else M, P), dtype)
    else:
        Ds, As = _run_pair_sums(scratches, board, geo_h, out, scr, valid, per_view=not shared,
                                need_D=True, need_A=coverage_pairs is None, **kw)
    if coverage_pairs is not None:
        if n == 0:
            As = jnp.zeros((1, P), dtype)
        else:
            h_dummy = jnp.zeros((1, P, 3), dtype).at[..., 2].set(1)
            _, As = _run_pair_sums(scratches, board, h_dummy, cout, cscr, cvalid, per_view=False,
                                   need_D=False, need_A=True, **kw)
    S = board.pixel_area
    rad = shade(Ds / S, As / S, views, board)
    if poisoned is not False:  # traced checks over a mesh (see `_guard`)
        rad = jnp.where(poisoned, jnp.nan, rad)
    return rad.reshape(M, board.H, board.W)


@functools.lru_cache(maxsize=None)
def grad_compiler_options() -> dict:
    """XLA compiler options for a jitted function that differentiates `render_pairs` (pass them
    as ``jax.jit(f, compiler_options=grad_compiler_options())``).

    On the CPU: ``xla_cpu_use_fusion_emitters=False``. Measured on a 2-core CPU (jax 0.10.1, see
    ``benchmarks/RESULTS.md``): a render value-and-gradient compiles ~35% faster and runs ~17%
    faster; a forward-only render runs 15-25% slower with it, so it is not for forward-only
    functions. Elsewhere, or where this XLA does not know the option (checked once by compiling a
    trivial function), ``{}``.
    """
    if jax.default_backend() != "cpu":
        return {}
    opts = {"xla_cpu_use_fusion_emitters": False}
    try:
        jax.jit(lambda x: x + 1).lower(np.float32(0)).compile(opts)
    except Exception:  # an XLA without this option: compile with the defaults
        return {}
    return opts


def _bucket(n: int, chunk: int) -> int:
    """Pair-list length for ``n`` pairs: a multiple of 1024 (small) or of ``chunk``, and within
    ~12% of ``n`` by rounding to 8 steps per octave, so repeated renders of similar scenes reuse
    compilations."""
    n = max(n, 1)
    step = 2 ** max(0, n.bit_length() - 4)
    return _round_up(_round_up(n, step), min(chunk, 1024))


def _layout(pix: np.ndarray, scr: np.ndarray, keeps, n: int, board: Board, shards: int,
            chunk: int):
    """Pack the kept pairs of each mask in ``keeps`` into ``shards`` equal segments, segment ``s``
    holding the pairs of pixels ``[s Pb, (s+1) Pb)`` (``Pb = ceil(H / shards) W``) in their input
    order, each segment ``_bucket``-ed to the largest count over segments and masks. Padding slots
    hold the segment's first pixel and the sentinel scratch ``n``. Returns numpy ``(pixel,
    scratch, valid)``, each ``(len(keeps), shards * Ls)``."""
    Pb = _pixels_per_shard(board, shards)
    idx = [np.flatnonzero(k) for k in keeps]
    blocks = [pix[i] // Pb for i in idx]
    counts = [np.bincount(b, minlength=shards) for b in blocks]
    Ls = _bucket(int(max(c.max() for c in counts)), chunk)
    shape = (len(keeps), shards * Ls)
    out_pix = np.broadcast_to(np.repeat(np.arange(shards) * Pb, Ls), shape).astype(np.int32)
    out_scr = np.full(shape, n, np.int32)
    out_val = np.zeros(shape, bool)
    for j, (i, b, c) in enumerate(zip(idx, blocks, counts)):
        order = np.argsort(b, kind="stable")  # by block, input order kept within a block
        starts = np.concatenate([[0], np.cumsum(c)[:-1]])
        dest = b[order] * Ls + np.arange(i.size) - np.repeat(starts, c)
        out_pix[j, dest] = pix[i[order]]
        out_scr[j, dest] = scr[i[order]]
        out_val[j, dest] = True
    return out_pix, out_scr, out_val


def _pairs_of(pix, scr, val):
    from jscratch import bvh

    return bvh.Pairs(pixel=jnp.asarray(pix), scratch=jnp.asarray(scr), valid=jnp.asarray(val),
                     overflow=jnp.asarray(False))


def bin_pairs(scratches: Scratches, board: Board, *, chunk: int = DEFAULT_CHUNK,
              shards: int = 1):
    """The complete (pixel, scratch) pair list of a scene, compacted (host code).

    Bins with ``bvh.build_pairs`` and packs the valid pairs into ``shards`` equal segments by
    pixel block (the layout `render_pairs` needs with a mesh of ``shards`` devices; one segment
    without), each segment's length rounded up (`_bucket`: within ~12%, a multiple of 1024 or of
    ``chunk``) so that similar scenes share a compilation of `render_pairs`; padding slots hold
    the sentinel scratch ``N``.

    **Returns:** `bvh.Pairs` ``(L,)`` for `render_pairs`.
    """
    from jscratch import bvh

    full, _ = bvh.build_pairs(scratches.p0, scratches.p1, scratches.width, scratches.depth,
                              board=(board.Sx, board.Sy), shape=board.shape)
    pix, scr, val = _layout(np.asarray(full.pixel).reshape(-1),
                            np.asarray(full.scratch).reshape(-1),
                            [np.asarray(full.valid).reshape(-1)], scratches.n, board, shards,
                            chunk)
    return _pairs_of(pix[0], scr[0], val[0])


def cull_pairs(pairs, scratches: Scratches, views: Views, board: Board, eps: float, *,
               chunk: int = DEFAULT_CHUNK, shards: int = 1):
    """Per-view culled pair lists from a shared list (host code).

    Culls ``pairs`` (a shared ``(L,)`` list, e.g. from `bin_pairs`) for every view with
    ``bvh.cull`` (pairs whose rigorous ``D_hat`` bound is below ``eps A / (pi alpha^2)``) and packs
    each view's survivors into one ``(M, Lv)`` list laid out for ``shards`` pixel shards as in
    `bin_pairs`. Render it with ``coverage_pairs=pairs``: a culled pair still covers the board.

    **Returns:** `bvh.Pairs` ``(M, Lv)`` for `render_pairs`.
    """
    from jscratch import bvh

    if eps <= 0 or not math.isfinite(eps):
        raise ValueError(f"cull_pairs: `eps` must be finite and > 0; got {eps}")
    hs = half_vectors(views, board, scratches.dtype)
    keep = [np.asarray(bvh.cull(pairs, scratches.p0, scratches.p1, scratches.width,
                                scratches.depth, scratches.alpha, hs[j], eps).valid)
            for j in range(views.m)]
    return _pairs_of(*_layout(np.asarray(pairs.pixel), np.asarray(pairs.scratch), keep,
                              scratches.n, board, shards, chunk))


_checked_scene = eqx.filter_jit(_check_values)


@functools.lru_cache(maxsize=None)
def _jitted_render_pairs(chunk, mesh, axis_names):
    return eqx.filter_jit(functools.partial(render_pairs, chunk=chunk, mesh=mesh,
                                            axis_names=axis_names))


def render(scratches: Scratches, views: Views, board: Board, *, eps: float = 0.0,
           chunk: int = DEFAULT_CHUNK, mesh: jax.sharding.Mesh | None = None,
           axis_names: str | Sequence[str] | None = None, return_pairs: bool = False):
    """Bin, cull and render: the convenience driver (host code; not for inside jit).

    Bins with `bin_pairs`; when ``eps > 0`` culls every view's pairs with `cull_pairs`
    (``bvh.cull``: pairs whose rigorous ``D_hat`` bound is below ``eps A / (pi alpha^2)``); lays
    the lists out for the mesh's pixel shards; renders with a jitted `render_pairs`. Coverage
    always uses the unculled list.

    **Arguments:** `scratches`, `views`, `board`; `eps` culling tolerance (0 keeps every pair);
    `chunk`, `mesh`, `axis_names` as in `render_pairs`; `return_pairs` also return the pair
    lists used.

    **Returns:** radiance ``(M, H, W)`` (W/(sr m^2)); with `return_pairs`, ``(radiance, pairs,
    coverage_pairs)``.
    """
    if eps < 0 or not math.isfinite(eps):
        raise ValueError(f"render: `eps` must be finite and >= 0; got {eps}")
    axis_names = tuple(axis_names) if isinstance(axis_names, list) else axis_names
    shards = _n_shards(mesh, _mesh_axes(mesh, axis_names))
    full_c = bin_pairs(scratches, board, chunk=chunk, shards=shards)
    if eps == 0:
        pairs, cov_pairs = full_c, None
    else:
        pairs = cull_pairs(full_c, scratches, views, board, eps, chunk=chunk, shards=shards)
        cov_pairs = full_c
    if mesh is not None:  # on one device first: sharded, a bad value would only give NaN
        jax.block_until_ready(_checked_scene(scratches, views))
    fn = _jitted_render_pairs(chunk, mesh, axis_names)
    rad = fn(scratches, views, board, pairs, cov_pairs)
    if return_pairs:
        return rad, pairs, (full_c if cov_pairs is None else cov_pairs)
    return rad


def render_reference(scratches: Scratches, views: Views, board: Board, *,
                     pixel_batch: int = 64) -> Float[Array, "m h w"]:
    """All-pairs reference: every scratch against every pixel, ``D_P`` and ``c`` as dense sums of
    `ndf.pair_integral` (no binning, no custom VJP: plain autodiff), then `shade`.

    Cost ``M * H*W * N`` pair integrals: small scenes only. Use float64 scratches for a reference.

    **Arguments:** the scene; `pixel_batch` pixels per `lax.map` step.

    **Returns:** radiance ``(M, H, W)`` (W/(sr m^2)).
    """

    dtype = scratches.dtype
    scratches, views = _check_values(scratches, views)
    views = jax.tree_util.tree_map(lambda x: x.astype(dtype), views)
    fps = pixel_footprints(board, dtype)  # (P, 4, 2)
    hs = jnp.swapaxes(half_vectors(views, board, dtype), 0, 1)  # (P, M, 3)
    s = scratches

    def one_pixel(args):
        fp, h = args
        over_scratches = jax.vmap(ndf.pair_integral, in_axes=(None, None, 0, 0, 0, 0, 0))
        over_views = jax.vmap(over_scratches, in_axes=(0, None, None, None, None, None, None))
        D, A = over_views(h, fp, s.p0, s.p1, s.width, s.depth, s.alpha)  # (M, N)
        return D.sum(-1), A[0].sum(-1)

    P = board.n_pixels
    if s.n == 0:
        D = jnp.zeros((P, views.m), dtype)
        A = jnp.zeros((P,), dtype)
    else:
        # Pad the pixel axis to a multiple of the batch (one compiled kernel, no remainder call).
        batch = max(1, min(int(pixel_batch), P))
        pad = _round_up(P, batch) - P
        fps = jnp.concatenate([fps, jnp.broadcast_to(fps[-1:], (pad, 4, 2))])
        hs = jnp.concatenate([hs, jnp.broadcast_to(hs[-1:], (pad,) + hs.shape[1:])])
        D, A = jax.lax.map(one_pixel, (fps, hs), batch_size=batch)
        D, A = D[:P], A[:P]
    S = board.pixel_area
    rad = shade(D.T / S, A[None] / S, views, board)
    return rad.reshape(views.m, board.H, board.W)
