"""Brute-force supersampled validation renderer (docs/model.md §1, §2 and §4; no analytic integral).

The independent ground truth for `jscratch.render`: every pixel footprint is supersampled with an
``n x n`` jittered stratified pattern (one uniform point per stratum, fresh for every pixel); at each
sample point ``q`` and for every scratch whose groove contains ``q`` it computes the real groove
geometry (docs/model.md §1-§2: local coordinates ``x = (q - p0).b``, ``y = (q - p0).t``; inside
when ``|x| < x_max`` and ``0 <= y <= |p1 - p0|``; the normal from the slope of the height profile
``h(x) = -(w/2) log(1 - 4x^2/w^2) - d``, differentiated by autodiff, not from Eq. 5) and evaluates the
GGX point NDF there. The pixel's ``D_P`` and coverage ``c`` are sample means::

    D_P ~ (1/S) sum_samples sum_{i: q in groove_i} D_x(h, n_i(q))     c ~ (1/S) sum_samples #{i: q in groove_i}

Overlapping grooves: each groove that contains a sample contributes its own ``D_x`` and its own
area, exactly the additive superposition of the analytic model (``D_P = sum_i D_hat_i / S_P``,
``c = sum_i A_i / S_P``); this is the model's rule, not a physical union of cuts.

Shading is re-implemented here from docs/model.md §4 (in algebraically different but equivalent forms)
so that it checks `render.shade` too. Nothing here imports `jscratch.ndf`.

**As carved** (``ball_radius=R``): each scratch's groove is instead the circular arc a ball-end
cutter of radius ``R`` cuts at plunge ``p``, the scratch's ``depth`` field (``z(x) = R - p -
sqrt(R^2 - x^2)`` over ``|x| < sqrt(2Rp - p^2)``, normal ``(-x, 0, sqrt(R^2 - x^2)) / R``);
``width`` is then unused. Used by `jscratch.design.maker` to render what the machine will carve.
Scratches whose `jscratch.scene.Scratches.profile` is ``"arc"`` are such cuts too, each with its
own ``R = w / 2`` and plunge ``p = R (1 - exp(-d / w))`` (the inverse of the ``depth`` the arc
profile stores).

Cost: ``M * n^2`` point evaluations per (pixel, scratch) pair. The unbiased estimate's error falls
like ``n^-1.5`` for a smooth groove edge crossing a pixel (stratified sampling of a discontinuous
integrand) and is much larger when the groove is thinner than the sample spacing.

**Public API:**

- `brute_sums(scratches, views, board, *, n, key, pairs=None) -> (D_P (M, H*W), c (H*W,))`
- `brute_render(...) -> radiance (M, H, W)`
- `brute_shade(D_P, c, views, board) -> radiance (M, H*W)`
- `height_profile_slope(x, width, depth)`, `groove_half_width(width, depth)`
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jscratch.errors import InputError, whole_number
from jscratch.scene import check_scratches, check_views
from jscratch.shading import pixel_centres, pixel_edges

__all__ = [
    "brute_render",
    "brute_shade",
    "brute_sums",
    "groove_half_width",
    "height_profile_slope",
]


def _height(x, width, depth):
    """Eq. 2: ``h(x) = -(w/2) log(1 - 4 x^2 / w^2) - d`` (m), for ``|x| < w/2``."""
    return -0.5 * width * jnp.log1p(-4.0 * (x / width) ** 2) - depth


def height_profile_slope(x, width, depth):
    """``dh/dx`` of the Eq. 2 profile by autodiff (dimensionless), elementwise."""
    return jnp.vectorize(jax.grad(_height))(x, width, depth)


def groove_half_width(width, depth):
    """Half width of the region where the profile is below the board, from ``h(x) = 0``:
    ``1 - 4x^2/w^2 = exp(-2d/w)``, so ``x_max = (w/2) sqrt(1 - exp(-2d/w))`` (m)."""
    return 0.5 * width * jnp.sqrt(-jnp.expm1(-2.0 * depth / width))


def _ggx_cos(c, a):
    """GGX NDF in its textbook form ``chi+(c) a^2 / (pi (c^2 (a^2 - 1) + 1)^2)``."""
    den = c * c * (a * a - 1.0) + 1.0
    return jnp.where(c > 0, a * a / (jnp.pi * den * den), 0.0)


def _pair_samples(key, n, xe, ye, W, P, ball, pixel, p0, p1, width, depth, alpha, h_views):
    """Sample-mean ``D`` per view ``(M,)`` and coverage of one scratch over one pixel footprint;
    with `ball` the groove is a ball's cut: `width` is then the ball's radius, `depth` the plunge."""
    dt = width.dtype
    q_pix = pixel % P
    r, c = q_pix // W, q_pix % W
    x0, x1, y0, y1 = xe[c], xe[c + 1], ye[r + 1], ye[r]
    jitter = jax.random.uniform(jax.random.fold_in(key, q_pix), (n, n, 2), dt)
    k = jnp.arange(n, dtype=dt)
    u = (k[:, None] + jitter[..., 0]) / n  # (n, n) in [0, 1)
    v = (k[None, :] + jitter[..., 1]) / n
    qx = x0 + u * (x1 - x0)
    qy = y0 + v * (y1 - y0)
    d = p1 - p0
    length = jnp.sqrt(jnp.sum(d * d))
    ok = length > 0
    t = jnp.where(ok, d, jnp.asarray([1.0, 0.0], dt)) / jnp.where(ok, length, 1.0)
    b = jnp.stack([t[1], -t[0]])
    lx = (qx - p0[0]) * b[0] + (qy - p0[1]) * b[1]
    ly = (qx - p0[0]) * t[0] + (qy - p0[1]) * t[1]
    if not ball:
        xm = groove_half_width(width, depth)
    else:  # the ball's cut at plunge `depth`
        R = width
        xm = jnp.sqrt(jnp.maximum(2.0 * R * depth - depth * depth, 0.0))
    inside = ok & (jnp.abs(lx) < xm) & (ly >= 0) & (ly <= length)
    lx_safe = jnp.where(inside, lx, 0.0)
    if not ball:
        slope = height_profile_slope(lx_safe, width, depth)
    else:
        slope = lx_safe / jnp.sqrt(R * R - lx_safe * lx_safe)
    nrm = jnp.stack([-slope, jnp.zeros_like(slope), jnp.ones_like(slope)], -1)
    nrm = nrm / jnp.sqrt(1.0 + slope * slope)[..., None]  # (n, n, 3), local frame
    h_loc = jnp.stack([h_views[:, :2] @ b, h_views[:, :2] @ t, h_views[:, 2]], -1)  # (M, 3)
    cos = jnp.einsum("ijk,mk->mij", nrm, h_loc)
    D = jnp.where(inside[None], _ggx_cos(cos, alpha), 0.0)
    return D.mean((1, 2)), inside.mean(dtype=dt)


def _half_vectors(views, board, dtype):
    ctr = pixel_centres(board, dtype)
    p = jnp.concatenate([ctr, jnp.zeros_like(ctr[:, :1])], -1)
    wo = views.camera.astype(dtype)[:, None] - p[None]
    wi = views.light.astype(dtype)[:, None] - p[None]
    wo = wo / jnp.linalg.norm(wo, axis=-1, keepdims=True)
    r2 = jnp.sum(wi**2, -1)
    wi = wi / jnp.sqrt(r2)[..., None]
    hv = wo + wi
    return wo, wi, hv / jnp.linalg.norm(hv, axis=-1, keepdims=True), r2


def _check(where: str, scratches, views, board, n, batch) -> None:
    """The host checks of `brute_sums` and `brute_render`: `n` and `batch` ints >= 1, and the
    scene by the rules `render` and `render_reference` check it by (`jscratch.scene`: values,
    endpoints on the board, views), each skipped where its arrays are traced."""
    for name, v in (("n", n), ("batch", batch)):
        if whole_number(v) is None or v < 1:
            raise InputError(f"{where}: `{name}` must be an int >= 1; got {v!r}")
    s = scratches
    if not any(isinstance(a, jax.core.Tracer) for a in (s.p0, s.p1, s.width, s.depth, s.alpha)):
        check_scratches(s.p0, s.p1, s.width, s.depth, s.alpha, board=(board.Sx, board.Sy),
                        source=where)
    if not any(isinstance(a, jax.core.Tracer) for a in (views.camera, views.light,
                                                         views.intensity)):
        check_views(views.camera, views.light, views.intensity, source=where)


def brute_sums(scratches, views, board, *, n: int = 16, key=None, pairs=None,
               batch: int = 256, ball_radius: float | None = None) -> tuple[Float[Array, "m p"], Float[Array, " p"]]:
    """Supersampled patch NDF ``D_P`` ``(M, H*W)`` (1/sr) and coverage ``c`` ``(H*W,)``.

    **Arguments:**

    - `scratches`, `views`, `board`: the scene (`jscratch.scene` modules); computation in the
      scratches' dtype.
    - `n`: strata per footprint side (``n^2`` samples per pixel).
    - `key`: PRNG key (default ``PRNGKey(0)``); pixel ``p`` uses ``fold_in(key, p)``, so every
      scratch over a pixel sees the same sample points.
    - `pairs`: optional `bvh.Pairs` ``(L,)`` restricting which scratches are tested against which
      pixel (for speed); default: every scratch against every pixel (fully independent of binning).
    - `batch`: pairs per `lax.map` step (memory ``batch * n^2 * M``).
    - `ball_radius`: None (the scratches' own profile) or ``R`` (m): the grooves are a ball's cut
      at plunge ``depth`` (module docstring).

    **Raises:** `InputError`, one line: `n` or `batch` not an int >= 1, or a scene that breaks
    the scene's rules (as `render` checks them: endpoints on the board too), where concrete.
    """
    _check("brute_sums", scratches, views, board, n, batch)
    return _sums(scratches, views, board, n=n, key=key, pairs=pairs, batch=batch,
                 ball_radius=ball_radius)


def _sums(scratches, views, board, *, n, key, pairs, batch, ball_radius):
    """`brute_sums` after its checks."""
    dt = scratches.dtype
    key = jax.random.PRNGKey(0) if key is None else key
    xe, ye = (jnp.asarray(e, dt) for e in pixel_edges(board))
    P, N = board.n_pixels, scratches.n
    if pairs is None:
        pix = jnp.repeat(jnp.arange(P, dtype=jnp.int32), N)
        scr = jnp.tile(jnp.arange(N, dtype=jnp.int32), P)
        valid = jnp.ones((P * N,), bool)
    else:
        pix = jnp.asarray(pairs.pixel).reshape(-1)
        scr = jnp.asarray(pairs.scratch).reshape(-1)
        valid = jnp.asarray(pairs.valid).reshape(-1)
    h = jnp.swapaxes(_half_vectors(views, board, dt)[2], 0, 1)  # (P, M, 3)
    s = scratches
    ball = ball_radius is not None or s.profile == "arc"
    one = functools.partial(_pair_samples, key, n, xe, ye, board.W, P, ball)

    def pair(args):
        p, i, ok = args
        g = lambda a: a.at[i].get(mode="clip")
        w, d = g(s.width), g(s.depth)
        if ball_radius is not None:
            w = jnp.asarray(ball_radius, dt)
        elif ball:  # the arc profile's (2R, -2R log(1 - p/R)) back to (R, p)
            w, d = 0.5 * w, -0.5 * w * jnp.expm1(-d / w)
        D, c = one(p, g(s.p0), g(s.p1), w, d, g(s.alpha), h[p])
        return jnp.where(ok, D, 0.0), jnp.where(ok, c, 0.0)

    if N == 0 or pix.shape[0] == 0:
        return jnp.zeros((views.m, P), dt), jnp.zeros((P,), dt)
    D, c = jax.lax.map(pair, (pix, scr, valid), batch_size=batch)
    D_P = jnp.zeros((P, views.m), dt).at[pix].add(D).T
    cov = jnp.zeros((P,), dt).at[pix].add(c)
    return D_P, cov


def brute_shade(D_P, coverage, views, board) -> Float[Array, "m p"]:
    """docs/model.md §4 shading, written independently of `render.shade`.

    ``G1 = 2 / (1 + sqrt(1 + a_G^2 tan^2 theta))`` (equal to the form of docs/model.md §4),
    GGX in the textbook ``cos`` form, Schlick Fresnel; ``radiance = I (D_P + max(0, 1-c) D_S) G F / (4 wo_z r2)``.
    """
    dt = D_P.dtype
    wo, wi, h, r2 = _half_vectors(views, board, dt)

    def g1(vz):
        tan2 = (1.0 - vz * vz) / (vz * vz)
        return 2.0 / (1.0 + jnp.sqrt(1.0 + board.a_G**2 * tan2))

    D = D_P + jnp.clip(1.0 - coverage, 0.0, None) * _ggx_cos(h[..., 2], board.a_S)
    G = g1(wi[..., 2]) * g1(wo[..., 2])
    F = board.F0 + (1.0 - board.F0) * (1.0 - jnp.einsum("mpk,mpk->mp", wo, h)) ** 5
    brdf = D * G * F / (4.0 * wi[..., 2] * wo[..., 2])
    return views.intensity.astype(dt)[:, None] * brdf * wi[..., 2] / r2


def brute_render(scratches, views, board, *, n: int = 16, key=None, pairs=None,
                 batch: int = 256, ball_radius: float | None = None) -> Float[Array, "m h w"]:
    """Brute-force radiance ``(M, H, W)`` (W/(sr m^2)): `brute_sums` then `brute_shade`.
    Arguments and checks as in `brute_sums`."""
    _check("brute_render", scratches, views, board, n, batch)
    D_P, c = _sums(scratches, views, board, n=n, key=key, pairs=pairs, batch=batch,
                   ball_radius=ball_radius)
    return brute_shade(D_P, c[None], views, board).reshape(views.m, board.H, board.W)



