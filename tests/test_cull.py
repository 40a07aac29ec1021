"""Tests of jscratch.cull: the per-scratch ratio bounds the point NDF over the whole groove and is
attained (dense quadrature across the groove), also at grazing half vectors and in float32,
eps = 0 keeps every pair, the culled pairs' D sums stay within the stated error bound (against a
numpy quadrature and against the NDF kernel), the coverage list's radiance error through the
renderer, and the input errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import bvh, cull
from jscratch.errors import InputError

BOARD = (0.3, 0.3)


def _x_max(width, depth):
    return 0.5 * width * np.sqrt(1 - np.exp(-2 * depth / width))


def _ggx(c, alpha):
    return np.where(c > 0, alpha**2 / (np.pi * (c * c * (alpha**2 - 1) + 1) ** 2), 0.0)



def dhat_numeric(h, p0, p1, width, depth, alpha, rect, n_x=2001):
    """`(D_hat, A, n.h)` for a batch of `Q` pairs by midpoint quadrature across the groove (docs/model.md §3)
    with the exact length of each along-scratch line inside the footprint (numpy float64).

    `h` `(Q, 3)` board frame; `p0, p1` `(Q, 2)`; `width, depth, alpha` `(Q,)`; `rect` `(Q, 4)` as
    `(x0, x1, y0, y1)`. Returns `(Q,)`, `(Q,)` and `(Q, n_x)` arrays. Every `D_x` sample is at most
    `max D_x`, so `D_hat <= A max D_x` holds for the quadrature exactly as for the integral."""
    p0, p1, h, rect = (np.asarray(a, np.float64) for a in (p0, p1, h, rect))
    width, depth, alpha = (np.asarray(a, np.float64)[:, None] for a in (width, depth, alpha))
    v = p1 - p0
    length = np.hypot(v[:, 0], v[:, 1])[:, None]
    t = v / length
    b = np.stack([t[:, 1], -t[:, 0]], -1)
    xm = _x_max(width, depth)
    dx = 2 * xm / n_x
    x = -xm + dx * (np.arange(n_x) + 0.5)  # (Q, n_x)
    # along-scratch segment y in [0, L] at offset x: p0 + x b + y t, clipped to the rectangle
    lo, hi = np.zeros_like(x), np.broadcast_to(length, x.shape).copy()
    for k in range(2):
        a0, a1 = rect[:, 2 * k, None], rect[:, 2 * k + 1, None]
        base = p0[:, k, None] + x * b[:, k, None]
        tk = t[:, k, None]
        par = np.abs(tk) < 1e-300
        tsafe = np.where(par, 1.0, tk)
        y0, y1 = (a0 - base) / tsafe, (a1 - base) / tsafe
        inside = (base >= a0) & (base <= a1)
        lo = np.where(par, lo, np.maximum(lo, np.minimum(y0, y1)))
        hi = np.where(par, np.where(inside, hi, lo), np.minimum(hi, np.maximum(y0, y1)))
    seg = np.maximum(hi - lo, 0.0)
    u = x / width
    hx = np.sum(h[:, :2] * b, -1)[:, None]
    hz = h[:, 2, None]
    nh = (-4 * u * hx + (1 - 4 * u * u) * hz) / (1 + 4 * u * u)
    d = _ggx(nh, alpha)
    return np.sum(d * seg, -1) * dx[:, 0], np.sum(seg, -1) * dx[:, 0], nh



def half_vectors(board, shape, camera, light):
    sx, sy = board
    h_px, w_px = shape
    xc = (np.arange(w_px) + 0.5) * sx / w_px
    yc = sy - (np.arange(h_px) + 0.5) * sy / h_px
    p = np.stack(np.meshgrid(xc, yc), -1).reshape(-1, 2)
    p = np.concatenate([p, np.zeros((len(p), 1))], -1)
    wo = camera - p
    wi = light - p
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    h = wo + wi
    return h / np.linalg.norm(h, axis=-1, keepdims=True)



def _one_pair_per_scratch(rng, layout, n, aspect, alpha_hi, hz_factor, below):
    """`n` random scratches (2 cm, depth / width in `aspect`, roughness 0.02 to `alpha_hi`), each
    paired with pixel i of half vector `h[i]` (unit; `h_z` scaled by `hz_factor(rng, n)`, the
    first `below` of them below the board): `(pairs, (p0, p1, width, depth, alpha, h))`."""
    mid, u = layout(rng, n, 0.05, 0.25)
    p0, p1 = mid - 0.01 * u, mid + 0.01 * u
    width = rng.uniform(1e-4, 5e-4, n)
    depth = width * rng.uniform(*aspect, n)
    alpha = rng.uniform(0.02, alpha_hi, n)
    h = rng.normal(size=(n, 3))
    h[:, 2] = np.abs(h[:, 2]) * hz_factor(rng, n)
    h[:below, 2] *= -1  # below the board: the bound must hold regardless
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    pairs = bvh.Pairs(pixel=jnp.arange(n, dtype=jnp.int32), scratch=jnp.arange(n, dtype=jnp.int32),
                      valid=jnp.ones(n, bool), overflow=jnp.array(False))
    return pairs, (p0, p1, width, depth, alpha, h)


def _groove_peak(p0, p1, width, depth, alpha, h):
    """`pi alpha^2 max D_x` over the whole groove (dense quadrature, float64): what `rho` bounds."""
    p0, p1, width, depth, alpha, h = (np.asarray(x, np.float64)
                                      for x in (p0, p1, width, depth, alpha, h))
    big = np.tile([-1.0, 1.0, -1.0, 1.0], (len(alpha), 1))  # the whole groove
    _, _, nh = dhat_numeric(h, p0, p1, width, depth, alpha, big, 20001)
    return _ggx(nh, alpha[:, None]).max(-1) * np.pi * alpha**2


def test_cull_ratio_is_a_tight_bound_of_the_point_ndf(random_layout):
    # rho * (1 / (pi alpha^2)) bounds D_x over the whole groove, and is attained by it.
    pairs, args = _one_pair_per_scratch(np.random.default_rng(2), random_layout, 64, (0.05, 2.0),
                                        0.5, lambda rng, n: rng.uniform(0.05, 3, n), 7)
    rho = np.asarray(cull.cull_ratio(pairs, *args))
    d_max = _groove_peak(*args)
    assert np.all(d_max <= rho * (1 + 1e-9) + 1e-300), np.c_[d_max, rho]
    assert np.all(d_max >= 0.98 * rho - 1e-12), np.c_[d_max, rho]
    assert np.sum(rho < 1e-3) > 5 and np.sum(rho > 0.1) > 5  # both regimes covered


@pytest.mark.float64
def test_cull_ratio_bounds_grazing_and_below_board_half_vectors(random_layout):
    """The bound at the half vectors that stress it: h_z from 1e-4 (grazing) to steep, a few below
    the board, any groove aspect (depth / width 0.02-3) and roughness (0.02-0.9); `rho` bounds
    the point NDF over the whole groove (dense quadrature of the rounded inputs) and is attained,
    in float64 and in float32 (there only thanks to the margin on `rho` itself: at grazing half
    vectors the margin on `c_max` alone left it up to 7e-8 short)."""
    pairs, args64 = _one_pair_per_scratch(np.random.default_rng(5), random_layout, 288,
                                          (0.02, 3.0), 0.9,
                                          lambda rng, n: 10.0 ** rng.uniform(-4, 0.5, n), 9)
    for dtype in (jnp.float64, jnp.float32):
        args = [jnp.asarray(x, dtype) for x in args64]
        rho = np.asarray(cull.cull_ratio(pairs, *args), np.float64)
        d_max = _groove_peak(*args)  # (of the rounded inputs: float32 is held to its own scene)
        assert np.all(d_max <= rho * (1 + 1e-9) + 1e-300), dtype
        assert np.all(d_max >= 0.98 * rho - 1e-12), dtype
    assert np.sum(args64[5][:, 2] < 1e-3) > 30
    assert np.sum(rho < 1e-3) > 10 and np.sum(rho > 0.1) > 10


def test_cull_keeps_all_at_zero_and_obeys_the_error_bound(random_layout):
    board, shape = BOARD, (32, 32)
    rng = np.random.default_rng(9)
    n = 300
    mid, u = random_layout(rng, n, 0.0, 0.3)
    half = 0.5 * rng.uniform(0.005, 0.025, n)[:, None] * u
    p0, p1 = np.clip(mid - half, 0, 0.3), np.clip(mid + half, 0, 0.3)
    width = np.full(n, 2.5e-3)  # wide grooves: more of the arc inside each pixel
    depth = rng.uniform(2e-4, 1.5e-3, n)
    alpha = rng.uniform(0.03, 0.3, n)
    pairs, _ = bvh.build_pairs(p0, p1, width, depth, board=board, shape=shape)
    valid = np.asarray(pairs.valid)
    cull_fn = cull.cull  # jax.jit-compiled
    s_p = board[0] * board[1] / (shape[0] * shape[1])
    total_dropped = 0
    for light_az, cam_az in ((0.0, 2.0), (1.0, 3.5)):
        tilt = np.radians(35)
        light = np.array([0.15 + np.sin(tilt) * np.cos(light_az), 0.15 + np.sin(tilt) * np.sin(light_az), np.cos(tilt)])
        camera = np.array([0.15 + np.sin(tilt) * np.cos(cam_az), 0.15 + np.sin(tilt) * np.sin(cam_az), np.cos(tilt)])
        h = half_vectors(board, shape, camera, light)
        kept0 = cull_fn(pairs, p0, p1, width, depth, alpha, h, 0.0)
        np.testing.assert_array_equal(kept0.valid, pairs.valid)
        rho = np.asarray(cull.cull_ratio(pairs, p0, p1, width, depth, alpha, h))
        for eps in (1e-3, 1e-2, 1e-1):
            kept = np.asarray(cull_fn(pairs, p0, p1, width, depth, alpha, h, eps).valid)
            assert not np.any(kept & ~valid)
            dropped = np.nonzero(valid & ~kept)[0]
            assert np.all(rho[dropped] < eps) and np.all(rho[valid & kept] >= eps)
            i = np.asarray(pairs.scratch)[dropped]
            pix = np.asarray(pairs.pixel)[dropped]
            r, c = np.divmod(pix, shape[1])
            px, py = board[0] / shape[1], board[1] / shape[0]
            rect = np.stack([c * px, (c + 1) * px, board[1] - (r + 1) * py, board[1] - r * py], -1)
            d_hat, area, _ = dhat_numeric(h[pix], p0[i], p1[i], width[i], depth[i], alpha[i], rect, 801)
            a_max = area / (np.pi * alpha[i] ** 2)
            assert np.all(d_hat <= rho[dropped] * a_max * (1 + 1e-9) + 1e-300)
            # per pixel: the culled D_P differs from the unculled one by less than the bound
            err = np.bincount(pix, d_hat / s_p, minlength=shape[0] * shape[1])
            bound = np.bincount(pix, eps * a_max / s_p, minlength=shape[0] * shape[1])
            assert np.all(err <= bound * (1 + 1e-9) + 1e-300)
            total_dropped += len(dropped)
            if eps == 1e-1:
                assert 0 < len(dropped) < valid.sum()
    assert total_dropped > 500



def test_cull_error_bound_with_the_ndf_kernel(random_layout):
    # The rendered path: per-pixel D sums of jscratch.ndf.pair_integral over the unculled and the
    # culled list (grooves of docs/model.md §5, narrower than a pixel), float64.
    from jscratch import ndf

    board, shape = BOARD, (48, 48)
    rng = np.random.default_rng(21)
    n = 400
    mid, u = random_layout(rng, n, 0.0, 0.3)
    half = 0.5 * rng.uniform(0.005, 0.025, n)[:, None] * u
    p0, p1 = np.clip(mid - half, 0, 0.3), np.clip(mid + half, 0, 0.3)
    width, depth = np.full(n, 2.5e-4), np.full(n, 1.28e-4)
    alpha = rng.uniform(0.02, 0.1, n)
    pairs, _ = bvh.build_pairs(p0, p1, width, depth, board=board, shape=shape)
    valid = np.asarray(pairs.valid)
    pix = np.asarray(pairs.pixel)
    s = np.minimum(np.asarray(pairs.scratch), n - 1)
    r, c = np.divmod(pix, shape[1])
    px, py = board[0] / shape[1], board[1] / shape[0]
    x0, x1, y0, y1 = c * px, (c + 1) * px, board[1] - (r + 1) * py, board[1] - r * py
    fps = np.stack([np.stack(v, -1) for v in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))], 1)
    kernel = jax.jit(jax.vmap(ndf.pair_integral))
    s_p = px * py
    n_dropped = 0
    for light_az, cam_az in ((0.3, 2.4), (4.0, 1.0)):
        tilt = np.radians(30)
        up = lambda az: np.array([0.15 + np.sin(tilt) * np.cos(az), 0.15 + np.sin(tilt) * np.sin(az), np.cos(tilt)])  # noqa: E731
        h = half_vectors(board, shape, up(cam_az), up(light_az))
        d_hat, area = (np.asarray(v) for v in kernel(h[pix], fps, p0[s], p1[s], width[s], depth[s], alpha[s]))
        d_hat, area = np.where(valid, d_hat, 0.0), np.where(valid, area, 0.0)
        a_max = area / (np.pi * alpha[s] ** 2)
        rho = np.asarray(cull.cull_ratio(pairs, p0, p1, width, depth, alpha, h))
        assert np.all(d_hat <= rho * a_max * (1 + 1e-6) + 1e-18)
        for eps in (1e-3, 3e-2):
            kept = np.asarray(cull.cull(pairs, p0, p1, width, depth, alpha, h, eps).valid)
            dropped = valid & ~kept
            full = np.bincount(pix, d_hat, minlength=shape[0] * shape[1]) / s_p
            culled = np.bincount(pix, np.where(kept, d_hat, 0.0), minlength=full.size) / s_p
            bound = np.bincount(pix, np.where(dropped, eps * a_max, 0.0), minlength=full.size) / s_p
            err = full - culled
            assert np.all(err >= -1e-9 * full) and np.all(err <= bound * (1 + 1e-6) + 1e-9)
            n_dropped += int(dropped.sum())
    assert n_dropped > 200




def _arc_peak(p0, p1, width, depth, alpha, h, n_theta=40001):
    """`pi alpha^2 max D` over the ball cutter's normals ``(-sin t, 0, cos t)``, ``|t| <= t_max``,
    ``sin t_max = a / R`` (`arc.arc_groove`'s stored ``(w, d) = (2R, -2R log(1 - p/R))``: ``a / R
    = sqrt(1 - exp(-2d/w))``), by dense sampling of the angle (float64): what the arc's `rho`
    bounds."""
    p0, p1, width, depth, alpha, h = (np.asarray(x, np.float64)
                                      for x in (p0, p1, width, depth, alpha, h))
    v = p1 - p0
    t = v / np.hypot(v[:, 0], v[:, 1])[:, None]
    hx = h[:, 0] * t[:, 1] - h[:, 1] * t[:, 0]
    t_max = np.arcsin(np.sqrt(-np.expm1(-2 * depth / width)))
    theta = t_max[:, None] * np.linspace(-1, 1, n_theta)
    nh = -np.sin(theta) * hx[:, None] + np.cos(theta) * h[:, 2, None]
    return _ggx(nh, alpha[:, None]).max(-1) * np.pi * alpha**2


@pytest.mark.float64
def test_cull_ratio_of_the_arc_is_a_tight_bound_of_its_normals(random_layout):
    """``profile="arc"``: `rho` bounds the GGX over the ball cutter's own (narrower) fan of
    normals and is attained by it, in float64 and float32, from grazing half vectors (``h_z``
    from 1e-4) to steep ones, plunge ratios 1e-4-1; it is never above the paper groove's bound
    of the same footprint, and below half of it for some pairs."""
    from jscratch import arc

    rng = np.random.default_rng(12)
    pairs, (p0, p1, _, _, alpha, h) = _one_pair_per_scratch(
        rng, random_layout, 288, (0.1, 1.0), 0.6, lambda rng, n: 10.0 ** rng.uniform(-4, 0.5, n), 9)
    R = 1.25e-4 * np.exp(rng.uniform(-1, 1, 288))
    width, depth = (np.asarray(x, np.float64) for x in arc.arc_groove(
        R * np.exp(rng.uniform(np.log(1e-4), 0, 288)), R))
    for dtype in (jnp.float64, jnp.float32):
        args = [jnp.asarray(x, dtype) for x in (p0, p1, width, depth, alpha, h)]
        rho = np.asarray(cull.cull_ratio(pairs, *args, profile="arc"), np.float64)
        paper = np.asarray(cull.cull_ratio(pairs, *args), np.float64)
        d_max = _arc_peak(*args)
        assert np.all(d_max <= rho * (1 + 1e-9) + 1e-300), dtype
        assert np.all(d_max >= 0.98 * rho - 1e-12), dtype
        assert np.all(rho <= paper) and np.sum(rho < 0.5 * paper) > 10, dtype
    assert np.sum(rho < 1e-4) > 10 and np.sum(rho > 0.1) > 10


@pytest.mark.float64
@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_cull_ratio_bounds_the_arc_groove(random_layout, profile):
    """Ball-cutter arcs (`arc.pair_integral_of("arc")`, stored as ``w = 2R`` and the arc's depth):
    the paper groove's bound holds pair by pair, since the arc's wall angles lie within it, and
    so does the arc's own, tighter one (``profile="arc"``), against the arc's pair integral."""
    from jscratch import arc

    board, shape = BOARD, (32, 32)
    rng = np.random.default_rng(5)
    n, R = 300, 1.25e-4
    mid, u = random_layout(rng, n, 0.0, 0.3)
    half = 0.5 * rng.uniform(0.005, 0.025, n)[:, None] * u
    p0, p1 = np.clip(mid - half, 0, 0.3), np.clip(mid + half, 0, 0.3)
    width, depth = (np.asarray(x) for x in arc.arc_groove(rng.uniform(0.02, 1.0, n) * R, R))
    width = np.broadcast_to(width, (n,))
    alpha = rng.uniform(0.01, 0.3, n)
    pairs, _ = bvh.build_pairs(p0, p1, width, depth, board=board, shape=shape)
    valid, pix = np.asarray(pairs.valid), np.asarray(pairs.pixel)
    s = np.minimum(np.asarray(pairs.scratch), n - 1)
    r, c = np.divmod(pix, shape[1])
    px, py = board[0] / shape[1], board[1] / shape[0]
    x0, x1, y0, y1 = c * px, (c + 1) * px, board[1] - (r + 1) * py, board[1] - r * py
    fps = np.stack([np.stack(v, -1) for v in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))], 1)
    kernel = jax.jit(jax.vmap(arc.pair_integral_of("arc")))
    up = lambda az: np.array([0.15 + 0.6 * np.cos(az), 0.15 + 0.6 * np.sin(az), 0.8])  # noqa: E731
    h = half_vectors(board, shape, up(2.0), up(0.5))
    d_hat, area = (np.where(valid, np.asarray(v), 0.0) for v in kernel(
        h[pix], fps, p0[s], p1[s], width[s], depth[s], alpha[s]))
    rho = np.asarray(cull.cull_ratio(pairs, p0, p1, width, depth, alpha, h, profile=profile))
    assert np.all(d_hat <= rho * area / (np.pi * alpha[s] ** 2) * (1 + 1e-6) + 1e-18)
    assert int((valid & (rho < 1e-3)).sum()) > 100 and float(d_hat.max()) > 0


@pytest.mark.float64
def test_cull_coverage_bound_through_the_renderer():
    # Coverage from the culled list (cull.cull_coverage) against the unculled one, float64, a view
    # whose half vector comes near the board's mirror direction (so some pixels keep their
    # coverage pairs and others drop them; view 1 of the default 3-view layout comes within a few
    # degrees of it): the radiance error per pixel stays within
    # eps * sum_dropped A_i / (pi alpha_i^2 S_P) times the pixel's shading factor.
    import math

    from jscratch import render

    board = render.Board(shape=(32, 32))
    s = render.Scratches.random(jax.random.PRNGKey(3), 300, board, dtype=jnp.float64)
    s = eqx.tree_at(lambda q: q.alpha, s, jnp.asarray(np.random.default_rng(2).uniform(
        0.02, 0.1, 300)))
    views = render.views_on_circle(3, math.radians(50), board=board, dtype=jnp.float64)
    pairs = render.bin_pairs(s, board)
    hs = render.half_vectors(views, board, jnp.float64)
    board_ndf = jnp.max(render.board_ndf(views, board, jnp.float64), axis=0)
    full = np.asarray(render.render_pairs(s, views, board, pairs))
    ones = jnp.ones((3, board.n_pixels), jnp.float64)
    k = np.asarray(render.shade(ones, ones, views, board)).reshape(3, -1)  # radiance per unit D
    from jscratch import ndf

    fps = render.pixel_footprints(board, jnp.float64)
    pix, scr = np.asarray(pairs.pixel), np.minimum(np.asarray(pairs.scratch), s.n - 1)
    _, area = jax.vmap(ndf.pair_integral)(hs[0, pix], fps[pix], s.p0[scr], s.p1[scr],
                                          s.width[scr], s.depth[scr], s.alpha[scr])
    area = np.where(np.asarray(pairs.valid), np.asarray(area), 0.0)
    n_kept_any = 0
    for eps in (1e-3, 1e-2):
        cov = cull.cull_coverage(pairs, s.alpha, board_ndf, eps)
        kept = np.asarray(cov.valid)
        dropped = np.asarray(pairs.valid) & ~kept
        assert dropped.any()
        n_kept_any += int(kept.sum())
        culled = np.asarray(render.render_pairs(s, views, board, pairs, cov))
        a_max = np.where(dropped, area / (np.pi * np.asarray(s.alpha)[scr] ** 2), 0.0)
        bound = eps * np.bincount(pix, a_max, minlength=board.n_pixels) / board.pixel_area
        err = np.abs(culled - full).reshape(3, -1)
        assert np.all(err <= k * bound * (1 + 1e-9) + 1e-12 * np.max(full)), eps
    assert n_kept_any > 0
    # eps = 0 keeps everything.
    assert bool(jnp.all(cull.cull_coverage(pairs, s.alpha, board_ndf, 0.0).valid == pairs.valid))


def test_cull_errors():
    p0 = np.zeros((3, 2), np.float32)
    p1 = np.full((3, 2), 0.1, np.float32)
    pairs, _ = bvh.build_pairs(p0, p1, 1e-4, 1e-4, board=BOARD, shape=(8, 8))
    h = np.tile(np.float32([0.0, 0.0, 1.0]), (64, 1))
    with pytest.raises(ValueError, match="h_pixel must have shape"):
        cull.cull(pairs, p0, p1, 1e-4, 1e-4, 0.04, h[:, :2], 1e-3)
    with pytest.raises(Exception, match="alpha must be finite and > 0"):
        cull.cull(pairs, p0, p1, 1e-4, 1e-4, 0.0, h, 1e-3)
    for bad in (-1.0, float("nan"), "a", [1e-3, 1e-3], None):
        with pytest.raises(InputError, match="^cull: eps must be a finite scalar >= 0"):
            cull.cull(pairs, p0, p1, 1e-4, 1e-4, 0.04, h, bad)
        with pytest.raises(InputError, match="^cull_coverage: eps must be a finite scalar >= 0"):
            cull.cull_coverage(pairs, 0.04, np.ones(64, np.float32), bad)
    # traced: the runtime check (eqx.error_if) still refuses it
    with pytest.raises(Exception, match="eps must be finite and >= 0"):
        jax.jit(lambda e: cull.cull(pairs, p0, p1, 1e-4, 1e-4, 0.04, h, e).valid)(-1.0)
    ok = jax.jit(lambda e: cull.cull_coverage(pairs, 0.04, np.ones(64, np.float32), e).valid)
    assert bool(jnp.all(ok(0.0) == pairs.valid))


@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_view_keep_drops_only_faint_pair_views_and_never_a_pair_s_brightest(profile):
    """`cull.view_keep`: a pair-view is dropped exactly when its bound (`cull_ratio` of that
    view's half vector) is below `eps` and below the pair's largest over the views; every pair
    keeps at least one view; `eps = 0` keeps all; a NaN half vector is kept (its NaN must reach
    the result, not be zeroed)."""
    rng = np.random.default_rng(4)
    n, V = 400, 3
    mid = rng.uniform(0.05, 0.25, (n, 2))
    ang = rng.uniform(0, 2 * np.pi, n)
    u = np.stack([np.cos(ang), np.sin(ang)], -1)
    p0, p1 = mid - 0.01 * u, mid + 0.01 * u
    p0[:5] = p1[:5]  # zero length: D_hat = 0, every bound 0
    width = rng.uniform(1e-4, 5e-4, n)
    depth = width * rng.uniform(0.05, 1.0, n)
    alpha = rng.uniform(0.02, 0.3, n)
    h = rng.normal(size=(V, n, 3))
    h[..., 2] = np.abs(h[..., 2]) * 10.0 ** rng.uniform(-3, 0.5, (V, n))
    h[0, 7] = np.nan
    pairs = bvh.Pairs(pixel=jnp.arange(n, dtype=jnp.int32), scratch=jnp.arange(n, dtype=jnp.int32),
                      valid=jnp.ones(n, bool), overflow=jnp.array(False))
    hn = h / np.linalg.norm(h, axis=-1, keepdims=True)
    hn[0, 7] = [0.0, 0.0, 1.0]  # (`cull_ratio` refuses NaN; its bound is NaN below)
    rho = np.stack([np.asarray(cull.cull_ratio(pairs, p0, p1, width, depth, alpha, hn[v],
                                               profile=profile)) for v in range(V)])
    rho[0, 7] = np.nan
    for eps in (1e-4, 1e-2):
        keep = np.asarray(cull.view_keep(h, p0, p1, width, depth, alpha, eps, profile))
        drop = (rho < eps) & (rho < rho.max(0))
        ok = np.isfinite(rho).all(0)
        np.testing.assert_array_equal(keep[:, ok], ~drop[:, ok])
        assert keep.any(0).all() and keep[:, 7].all()
        assert 0.1 < keep[:, ok].mean() < 0.95
    assert np.asarray(cull.view_keep(h, p0, p1, width, depth, alpha, 0.0, profile)).all()
    with pytest.raises(ValueError, match="profile"):
        cull.view_keep(h, p0, p1, width, depth, alpha, 1e-3, "round")
