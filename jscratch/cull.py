"""Culling pairs that cannot matter: a rigorous per-pair bound on the scratch NDF (`cull_ratio`),
the per-view cull (`cull`) and the coverage cull (`cull_coverage`) of a pair list, and the
pair-views a shared list's renderer skips (`view_keep`). The per-view lists at fixed capacities
built from them are `bvh.PairLists`.

**View culling: the bound.** For one view, pixel `P` with half vector `h` and scratch `i`,
docs/model.md §3 gives `D_hat = ∫∫_{F ∩ groove} D_x(h, n(x)) dx dy <= A * max_x D_x(h, n(x))`. In the
scratch-local frame the groove normals are `n(psi) = (-sin psi, 0, cos psi)` for `|psi| <= psi_max`
(Eq. 5 with `tan(psi/2) = 2u`, `u = x/w`), and the wall is steepest at the groove edge:
`tan(psi_max/2) = 2 x_max / w = sqrt(s)`, `s = 1 - exp(-2d/w)`, so `cos psi_max = (1-s)/(1+s)` and
`sin psi_max = 2 sqrt(s)/(1+s)`. With `h = (hx, hy, hz)` in that frame, `n.h = hz cos psi - hx sin psi`,
whose maximum over the arc is

    c_max = sqrt(hx^2 + hz^2)                       if atan2(|hx|, hz) <= psi_max (peak on the arc)
          = hz cos psi_max + |hx| sin psi_max       otherwise,

and `c_max <= sqrt(1 - hy^2)` always: this is the "scratch direction far from perpendicular to `h`"
case (large `|hy|`), the second branch the "every groove normal far from `h`" case. For `alpha < 1`
the GGX `D(c) = chi+(c) alpha^2 / (pi (c^2 (alpha^2 - 1) + 1)^2)` increases on `[0, 1]` from
`alpha^2/pi` to its peak `1/(pi alpha^2)`, so

    D_hat <= A D(c_max) = rho A / (pi alpha^2),    rho = alpha^4 / (c_max^2 (alpha^2 - 1) + 1)^2

(`rho = 0` when `c_max <= 0`: chi+ zeroes every wall; for `alpha >= 1` GGX peaks at `c -> 0+` and
`rho = alpha^4` bounds it). `rho` is in `[0, 1]`: the fraction of the most the pair could ever
contribute. `c_max` gets 4 ulps added, and `rho` 8 ulps of itself (the rounding of its last five
operations, which the margin on `c_max` does not cover where `c_max` is small: grazing half
vectors), so that the bound survives rounding. `cull_ratio` computes
`rho` per pair in O(1) (no integral); `cull` drops the pair when `rho < eps`. `eps = 0` keeps all.
The bound holds for the ball's arc too (`Scratches.profile == "arc"`, stored as the paper groove
with its footprint, ``w = 2R``): the arc's wall angles ``asin(x / R)`` lie within that groove's
``2 atan(x / R)`` (``asin s <= 2 atan s`` on ``[0, 1]``), so its normals are a subset of the arc
above. With ``profile="arc"`` the bound uses the arc's own fan, ``sin theta_max = a / R =
sqrt(s)``, ``cos theta_max = exp(-d/w)``: never looser, and tighter the deeper the plunge.

**Skipping pair-views** (`view_keep`, `render.render_pairs`' ``skip_eps``). A shared list
renders every pair under every view; pair-view ``v`` of a pair is skipped when ``rho_v < eps``
and ``v`` is not the pair's brightest view, so each skipped value is below ``eps A / (pi
alpha^2)`` (the per-pixel bound below holds) and no groove loses all its light and gradient. The
native kernel computes the same bound per SIMD lane and skips the work of a view that no lane of
a block keeps (docs/model.md §11).

**View culling: the rendered error.** Per pixel the dropped pairs lower `D_P = sum_i D_hat_i / S_P`
(never raise it) by

    0 <= D_P - D_P_culled < eps * sum_dropped A_i / (pi alpha_i^2 S_P) <= eps * c / (pi alpha_min^2),

with `c = sum_i A_i / S_P` the pixel's coverage. The coverage must come from the *unculled* list
(a culled pair still covers the board; `render.render` does this), so the board term of docs/model.md §4 is
unchanged and the radiance error is the same bound times the shading factor:
`0 <= radiance - radiance_culled < eps * (I wi_z / r^2) G F / (4 wi_z wo_z) * sum_dropped A_i /
(pi alpha_i^2 S_P)`, i.e. at most `eps` times the radiance the pixel would have if every groove in
it were a mirror at its GGX peak. `tests/test_bvh.py` checks the per-pixel bound by independent
quadrature on random scenes. `grid.compact` re-packs a culled list into fewer slots so that the
culling saves shading time. The default `DEFAULT_EPS` comes from the time-against-error table
in `benchmarks/results/bvh.md`.

**Coverage culling.** The coverage enters shading only through the board term
`max(0, 1 - c) D_S(h)` (docs/model.md §4, `D_S` the flat board's GGX at the pixel's half vector), so a pair
left out of the coverage sum raises `D` by at most `D_S(h) A_i / S_P`. `cull_coverage` keeps a
pair for the coverage pass only where `D_S(h) > eps / (pi alpha_i^2)` in some view, which bounds that
error by the same `eps A_i / (pi alpha_i^2 S_P)` as view culling (the two errors have opposite
signs and each stays within its bound). Away from the board's mirror direction `D_S` is tiny and
most pairs drop out: for the default 3-view design 70% of the pixels need no coverage pairs at
`eps = 1e-3`.

Imports: `jscratch.grid` (pair lists), `jscratch.ndf`.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jscratch.errors import InputError
from jscratch.grid import Pairs, checked_scratches
from jscratch.ndf import local_frame
from jscratch.scene import PROFILES

__all__ = [
    "DEFAULT_EPS",
    "cull",
    "cull_coverage",
    "cull_ratio",
    "view_keep",
]

DEFAULT_EPS = 1e-3
"""Default culling threshold of `cull` and `cull_coverage` (a fraction of a pair's largest
possible contribution): on the scenes of `benchmarks/results/bvh.md` (20k scratches, 256x256, 4
views) it keeps ~55 % of the pairs for a radiance error of ~3e-4 of the image's peak (`1e-2`: ~31 %
kept, ~2e-3). A design does not cull by default (`DesignConfig.cull_eps = 0`, docs/model.md §11)."""


@functools.partial(jax.jit, static_argnames="profile")
def cull_ratio(
    pairs: Pairs,
    p0: Float[ArrayLike, "N 2"],
    p1: Float[ArrayLike, "N 2"],
    width: Float[ArrayLike, "N"],
    depth: Float[ArrayLike, "N"],
    alpha: Float[ArrayLike, "N"],
    h_pixel: Float[ArrayLike, "P 3"],
    profile: str = "paper",
) -> Float[Array, " L"]:
    """Rigorous bound `rho` per pair with `D_hat <= rho * A / (pi alpha^2)` (jittable).

    In the scratch-local frame the groove normals are `n = (-sin psi, 0, cos psi)` for `psi` in
    `[-psi_max, psi_max]`, `tan psi_max = |h'(x_max)|`, so with `h_local = (hx, hy, hz)`,
    `n.h <= c_max`, the maximum of `hz cos psi + |hx| sin psi` over that arc (at most
    `sqrt(1 - hy^2)`). For `alpha < 1` GGX is increasing in `n.h` on `[0, 1]`, so
    `D_hat <= A D_ggx(c_max) = rho A / (pi alpha^2)` with
    `rho = alpha^4 / (c_max^2 (alpha^2 - 1) + 1)^2` (and `rho = 0` when `c_max <= 0`: the groove
    faces away and chi+ zeroes it). For `alpha >= 1` GGX peaks at `n.h -> 0+` and `rho = alpha^4`.
    `c_max` gets 4 ulps added and `rho` 8 ulps of itself so that the bound survives rounding.
    Derivation: module docstring.

    **Arguments:** `pairs`; current `p0`, `p1` `(N, 2)`, `width`, `depth`, `alpha` (`(N,)` or
    scalar); `h_pixel` `(P, 3)` unit board-frame half vector per pixel (`P = H * W`); `profile`
    (static) the groove's (`Scratches.profile`): the ball cutter's arc has a narrower fan of
    normals than the paper groove of the same footprint, so its bound is tighter.

    **Returns:** `(L,)` bound ratio, in `[0, 1]` for `alpha < 1`; padding slots get 0.
    """
    p0, p1, width, depth = checked_scratches(p0, p1, width, depth)
    n = p0.shape[0]
    dtype = p0.dtype
    alpha = jnp.asarray(alpha, dtype)
    if alpha.shape not in ((), (n,)):
        raise InputError(f"alpha must be a scalar or have shape ({n},), got {alpha.shape}")
    alpha = jnp.broadcast_to(alpha, (n,))
    alpha = eqx.error_if(
        alpha, ~jnp.all(jnp.isfinite(alpha) & (alpha > 0)), "alpha must be finite and > 0"
    )
    h_pixel = jnp.asarray(h_pixel, dtype)
    if h_pixel.ndim != 2 or h_pixel.shape[-1] != 3:
        raise InputError(f"h_pixel must have shape (H*W, 3), got {h_pixel.shape}")
    h_pixel = eqx.error_if(h_pixel, ~jnp.all(jnp.isfinite(h_pixel)), "h_pixel has non-finite entries")
    _, b, length = local_frame(p0, p1)
    cos_m, sin_m = _wall(width, depth, profile)
    i = jnp.clip(pairs.scratch, 0, n - 1)
    h = h_pixel[jnp.clip(pairs.pixel, 0, h_pixel.shape[0] - 1)]
    rho = _rho(h, b[i], length[i], cos_m[i], sin_m[i], alpha[i])
    return jnp.where(pairs.valid, rho, 0.0)


def _wall(width, depth, profile: str):
    """``(cos, sin)`` of the steepest wall angle of each groove: the paper groove's ``psi_max``,
    ``tan(psi_max / 2) = sqrt(s)``, ``s = 1 - exp(-2d/w)``; the ball cutter's arc (stored as the
    paper groove with its footprint, `arc.arc_groove`) ``theta_max``, ``sin theta_max = a / R =
    sqrt(s)``, ``cos theta_max = sqrt(1 - s) = exp(-d/w)`` (a narrower fan of normals, so a
    tighter bound)."""
    if profile not in PROFILES:
        raise InputError(f"profile={profile!r}: expected one of {', '.join(map(repr, PROFILES))}")
    s = -jnp.expm1(-2.0 * depth / width)
    if profile == "arc":
        return jnp.exp(-depth / width), jnp.sqrt(s)
    return (1 - s) / (1 + s), 2 * jnp.sqrt(s) / (1 + s)


def _rho(h, b, length, cos_m, sin_m, a):
    """`cull_ratio`'s bound from the board-frame half vector `h` (``(..., 3)``, unit), the
    scratch's across vector `b` (``(..., 2)``), `length`, wall angle and roughness `a`
    (broadcast against ``h[..., 0]``)."""
    dtype = h.dtype
    hx = h[..., 0] * b[..., 0] + h[..., 1] * b[..., 1]
    hz = h[..., 2]
    # The maximiser psi* = atan2(|hx|, hz) lies on the arc iff hz > 0 and |hx| cos <= hz sin.
    on_arc = (hz > 0) & (jnp.abs(hx) * cos_m <= hz * sin_m)
    c_max = jnp.where(on_arc, jnp.sqrt(hx * hx + hz * hz), hz * cos_m + jnp.abs(hx) * sin_m)
    c_max = jnp.minimum(c_max + 4 * jnp.finfo(dtype).eps, 1.0)
    a2 = a * a
    denom = jnp.where(a < 1, c_max * c_max * (a2 - 1) + 1, 1.0)
    rho = jnp.where(c_max <= 0, 0.0, a2 * a2 / (denom * denom))  # (a NaN stays NaN)
    rho = rho * (1 + 8 * jnp.finfo(dtype).eps)  # (the last operations' rounding)
    rho = jnp.where(a < 1, jnp.minimum(rho, 1.0), rho)
    return jnp.where((length > 0) | (a >= 1), rho, 0.0)  # zero-length: D_hat = A = 0


def view_keep(
    h: Float[ArrayLike, "V n 3"],
    p0: Float[ArrayLike, "n 2"],
    p1: Float[ArrayLike, "n 2"],
    width: Float[ArrayLike, "n"],
    depth: Float[ArrayLike, "n"],
    alpha: Float[ArrayLike, "n"],
    eps: float,
    profile: str = "paper",
) -> Bool[Array, "V n"]:
    """Which pair-views of ``n`` pairs under ``V`` views to evaluate at tolerance `eps`
    (jittable; what `render.render_pairs`' ``skip_eps`` skips, docs/model.md §11).

    Pair-view ``(v, i)`` is skipped when its bound ``rho_v`` (`cull_ratio`) is below `eps` and
    ``v`` is not the pair's brightest view (largest ``rho``): a skipped pair-view's ``D_hat``
    is below ``eps A / (pi alpha^2)``, and no groove loses every view. ``eps = 0`` keeps all; a
    NaN bound keeps every view of its pair (the NaN reaches the result).

    **Arguments:** `h` ``(V, n, 3)`` each pair's board-frame half vector per view (normalised
    here); the pair's scratch `p0`, `p1` ``(n, 2)``, `width`, `depth`, `alpha` ``(n,)`` (m, m,
    m, 1; for ``profile="arc"`` the stored groove, `arc.arc_groove`); `eps` (static float).

    **Returns:** ``(V, n)`` bool.
    """
    h = jnp.asarray(h)
    if eps == 0:
        return jnp.ones(h.shape[:-1], bool)
    h = h / jnp.sqrt(jnp.sum(h * h, axis=-1, keepdims=True))
    _, b, length = local_frame(jnp.asarray(p0), jnp.asarray(p1))
    cos_m, sin_m = _wall(jnp.asarray(width), jnp.asarray(depth), profile)
    rho = _rho(h, b[None], length[None], cos_m[None], sin_m[None], jnp.asarray(alpha)[None])
    return ~((rho < eps) & (rho < jnp.max(rho, axis=0, keepdims=True)))


def _host_checked_eps(where: str, eps) -> None:
    """`InputError` (one line) for a concrete `eps` that is not a finite scalar >= 0; a traced
    one is left to `_checked_eps`' runtime check."""
    if isinstance(eps, jax.core.Tracer):
        return
    try:
        value = np.asarray(eps, np.float64)
    except (TypeError, ValueError):
        value = None
    if value is None or value.shape != () or not (np.isfinite(value) and value >= 0):
        raise InputError(f"{where}: eps must be a finite scalar >= 0, got {eps!r}")


def _checked_eps(eps, dtype) -> Array:
    """The culling tolerance as a scalar of `dtype`; `eqx.error_if` unless finite and >= 0."""
    eps = jnp.asarray(eps, dtype)
    if eps.shape != ():
        raise InputError(f"eps must be a scalar, got shape {eps.shape}")
    return eqx.error_if(eps, ~(jnp.isfinite(eps) & (eps >= 0)), "eps must be finite and >= 0")


def cull(pairs: Pairs, p0, p1, width, depth, alpha, h_pixel, eps=DEFAULT_EPS,
         profile: str = "paper") -> Pairs:
    """Clear `valid` of pairs whose `D_hat` bound is below `eps * A / (pi alpha^2)` (jittable).

    A pair is dropped when `rho < eps` (`cull_ratio`); `eps = 0` keeps every pair. Per pixel
    the dropped pairs change `D_P` by at most `(1/S_P) sum_dropped rho_i A_i / (pi alpha_i^2)
    < eps (1/S_P) sum_dropped A_i / (pi alpha_i^2)` (and never increase it). The coverage `c` of
    docs/model.md §4 must still come from the unculled list, else the board term adds its own
    error (module docstring). Use `grid.compact` to turn the dropped slots into saved time.

    **Arguments:** as `cull_ratio` (`profile` the groove's, static), plus `eps >= 0` (scalar;
    may be traced; a concrete bad value is refused at once, `InputError`).

    **Returns:** `Pairs` of the same capacity with fewer valid slots.
    """
    _host_checked_eps("cull", eps)
    return _cull(pairs, p0, p1, width, depth, alpha, h_pixel, eps, profile)


@functools.partial(jax.jit, static_argnames="profile")
def _cull(
    pairs: Pairs,
    p0: Float[ArrayLike, "N 2"],
    p1: Float[ArrayLike, "N 2"],
    width: Float[ArrayLike, "N"],
    depth: Float[ArrayLike, "N"],
    alpha: Float[ArrayLike, "N"],
    h_pixel: Float[ArrayLike, "P 3"],
    eps: float | Float[ArrayLike, ""] = DEFAULT_EPS,
    profile: str = "paper",
) -> Pairs:
    rho = cull_ratio(pairs, p0, p1, width, depth, alpha, h_pixel, profile)
    eps = _checked_eps(eps, rho.dtype)
    valid = pairs.valid & ~(rho < eps)
    return eqx.tree_at(lambda p: p.valid, pairs, valid)


def cull_coverage(pairs: Pairs, alpha, board_ndf, eps=DEFAULT_EPS) -> Pairs:
    """Clear `valid` of pairs whose coverage cannot matter at tolerance `eps` (jittable).

    A pair is kept when `board_ndf[pixel] * pi * alpha^2 > eps`, with `board_ndf` the flat
    board's GGX `D_S(h)` at each pixel's half vector, largest over the views (1/sr). Leaving a pair
    out of the coverage sum changes `D` by at most `D_S A / S_P <= eps A / (pi alpha^2 S_P)`, the
    bound of `cull` (module docstring). `eps = 0` keeps every pair.

    **Arguments:** `pairs` (the unculled list); `alpha` `(N,)` or scalar; `board_ndf` `(P,)`
    (e.g. ``render.board_ndf(views, board).max(0)``); `eps >= 0` (a concrete bad value is
    refused at once, `InputError`).

    **Returns:** `Pairs` of the same capacity with fewer valid slots.
    """
    _host_checked_eps("cull_coverage", eps)
    return _cull_coverage(pairs, alpha, board_ndf, eps)


@jax.jit
def _cull_coverage(
    pairs: Pairs,
    alpha: Float[ArrayLike, "N"],
    board_ndf: Float[ArrayLike, "P"],
    eps: float | Float[ArrayLike, ""] = DEFAULT_EPS,
) -> Pairs:
    """`cull_coverage`, jitted."""
    board_ndf = jnp.asarray(board_ndf)
    if board_ndf.ndim != 1:
        raise InputError(f"board_ndf must have shape (H*W,), got {board_ndf.shape}")
    dtype = board_ndf.dtype
    n = pairs.bin_p0.shape[0] if pairs.bin_p0 is not None else None
    alpha = jnp.asarray(alpha, dtype)
    if alpha.ndim == 0:
        a = jnp.broadcast_to(alpha, pairs.scratch.shape)
    else:
        if n is not None and alpha.shape != (n,):
            raise InputError(f"alpha must be a scalar or have shape ({n},), got {alpha.shape}")
        a = alpha.at[pairs.scratch].get(mode="clip")
    eps = _checked_eps(eps, dtype)
    d = board_ndf.at[pairs.pixel].get(mode="clip")
    valid = pairs.valid & ((d * jnp.pi * a * a > eps) | (eps == 0))
    return eqx.tree_at(lambda p: p.valid, pairs, valid)
