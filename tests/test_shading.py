"""Tests of jscratch.shading: pixel footprints and centres against hand-computed geometry, half
vectors and the flat board's GGX against a numpy evaluation, `shade` against the independent
`brute.brute_shade`, and `display` (a C1 gamma with a finite slope at 0)."""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import brute, render, shading
from jscratch.scene import Board, views_on_circle

BOARD = render.Board(shape=(10, 10), Sx=0.01, Sy=0.01)  # 1 mm pixels


def test_footprints_and_centres_by_hand():
    board = Board(shape=(2, 3), Sx=0.3, Sy=0.2)  # pixels 0.1 m wide, 0.1 m tall
    fp = np.asarray(shading.pixel_footprints(board, jnp.float32))
    assert fp.shape == (6, 4, 2) and fp.dtype == np.float32
    # pixel r * W + c = 1 * 3 + 2: column 2, row 1 (row 0 along y = Sy)
    np.testing.assert_allclose(fp[5], [[0.2, 0.0], [0.3, 0.0], [0.3, 0.1], [0.2, 0.1]], atol=1e-7)
    np.testing.assert_allclose(fp[0], [[0.0, 0.1], [0.1, 0.1], [0.1, 0.2], [0.0, 0.2]], atol=1e-7)
    # counter-clockwise: positive shoelace area, each the pixel area
    x, y = fp[..., 0], fp[..., 1]
    area = 0.5 * np.sum(x * np.roll(y, -1, 1) - y * np.roll(x, -1, 1), 1)
    np.testing.assert_allclose(area, board.pixel_area, rtol=1e-5)
    ctr = np.asarray(shading.pixel_centres(board, jnp.float32))
    np.testing.assert_allclose(ctr, fp.mean(1), atol=1e-7)
    xe, ye = shading.pixel_edges(board)
    np.testing.assert_allclose(xe, [0, 0.1, 0.2, 0.3])
    np.testing.assert_allclose(ye, [0.2, 0.1, 0])


def test_half_vectors_and_board_ndf_against_numpy():
    board = Board(shape=(6, 7))
    views = views_on_circle(3, math.radians(40), board=board)
    h = np.asarray(shading.half_vectors(views, board, jnp.float32))
    assert h.shape == (3, 42, 3) and h.dtype == np.float32
    p = np.concatenate([np.asarray(shading.pixel_centres(board, jnp.float32), np.float64),
                        np.zeros((42, 1))], -1)
    for j in range(3):
        wo = np.asarray(views.camera[j], np.float64) - p
        wi = np.asarray(views.light[j], np.float64) - p
        ref = wo / np.linalg.norm(wo, axis=1, keepdims=True) + wi / np.linalg.norm(wi, axis=1, keepdims=True)
        ref /= np.linalg.norm(ref, axis=1, keepdims=True)
        np.testing.assert_allclose(h[j], ref, atol=2e-6)
        # GGX D(h) = a^2 / (pi ((a^2 - 1) cos^2 + 1)^2) in its textbook form
        a = board.a_S
        c = ref[:, 2]
        d_ref = a * a / (np.pi * ((a * a - 1) * c * c + 1) ** 2)
        np.testing.assert_allclose(np.asarray(shading.board_ndf(views, board, jnp.float32))[j], d_ref,
                                   rtol=1e-3)


@pytest.mark.float64
def test_shade_matches_independent_brute_shade():
    v = render.views_on_circle(3, 0.6, 0.05, board=BOARD, intensity=jnp.asarray([1.0, 1.5, 0.7]),
                               dtype=jnp.float64)
    key = jax.random.PRNGKey(1)
    D = jax.random.uniform(key, (3, BOARD.n_pixels), jnp.float64, 0, 50)
    c = jax.random.uniform(jax.random.fold_in(key, 1), (BOARD.n_pixels,), jnp.float64, 0, 1.3)
    a = shading.shade(D, c[None], v, BOARD)
    b = brute.brute_shade(D, c[None], v, BOARD)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)


def test_shade_float32_follows_input_and_is_linear_in_the_patch_ndf():
    v = views_on_circle(2, math.radians(50), board=BOARD)
    rng = np.random.default_rng(0)
    D = jnp.asarray(rng.uniform(0, 50, (2, BOARD.n_pixels)), jnp.float32)
    cov = jnp.ones((BOARD.n_pixels,), jnp.float32)  # fully covered: no board term
    r1, r2 = shading.shade(D, cov, v, BOARD), shading.shade(2 * D, cov, v, BOARD)
    assert r1.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(r2), 2 * np.asarray(r1), rtol=1e-6)
    zero = shading.shade(jnp.zeros_like(D), cov, v, BOARD)
    assert float(jnp.max(jnp.abs(zero))) == 0.0
    np.testing.assert_allclose(np.asarray(r1), np.asarray(brute.brute_shade(D, cov[None], v, BOARD)),
                               rtol=1e-5)


@pytest.mark.float64
def test_display_is_c1_gamma_with_finite_slope():
    k, g = shading.DISPLAY_KNEE, 1 / shading.DISPLAY_GAMMA
    x = jnp.asarray([2e-4, 0.01, 0.5, 1.0, 7.0])
    np.testing.assert_allclose(np.asarray(shading.display(x)), np.asarray(x) ** g, rtol=1e-12)
    d = jax.vmap(jax.grad(shading.display))
    lo, hi = jnp.asarray([k * (1 - 1e-9)]), jnp.asarray([k * (1 + 1e-9)])
    np.testing.assert_allclose(np.asarray(shading.display(lo)), np.asarray(shading.display(hi)), rtol=1e-7)
    np.testing.assert_allclose(np.asarray(d(lo)), np.asarray(d(hi)), rtol=1e-6)
    at = float(d(jnp.asarray([k]))[0])  # at the knee itself, too (both sides' slope: g k^(g-1))
    assert abs(at - g * k ** (g - 1)) < 1e-9 * at, at
    s0 = float(d(jnp.zeros(1))[0])
    assert math.isfinite(s0) and abs(s0 - (2 - g) * k ** (g - 1)) < 1e-9 * s0
    xs = jnp.linspace(0, 3 * k, 301)
    assert bool(jnp.all(jnp.diff(shading.display(xs)) > 0))


def test_display_float32():
    x = jnp.asarray([0.0, 5e-5, 1e-4, 0.25, 1.0], jnp.float32)
    y = shading.display(x)
    assert y.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(y)[2:], np.asarray(x, np.float64)[2:] ** (1 / 2.2), rtol=1e-6)
    assert float(y[0]) == 0.0 and 0 < float(y[1]) < float(y[2])


@pytest.mark.parametrize("kw, name, shown", [
    (dict(knee=-1), "knee", "-1"), (dict(knee=0.0), "knee", "0.0"),
    (dict(knee=float("nan")), "knee", "nan"), (dict(gamma=0), "gamma", "0"),
    (dict(gamma=-1), "gamma", "-1"), (dict(gamma=float("inf")), "gamma", "inf"),
    (dict(gamma="a"), "gamma", "'a'"), (dict(knee=np.array([1e-4, 1e-3])), "knee", "array"),
])
def test_display_refuses_a_gamma_or_knee_not_finite_and_positive(kw, name, shown):
    from jscratch.errors import InputError

    with pytest.raises(InputError, match=rf"^display: `{name}` must be a finite number > 0; "
                                         rf"got {re.escape(shown)}"):
        shading.display(jnp.asarray([0.0, 0.5], jnp.float32), **kw)
    assert shading.display(jnp.float32(0.5), gamma=np.float32(2.0), knee=1e-3).dtype == jnp.float32


def test_display_refuses_a_gamma_whose_curve_falls_near_zero():
    """`display` is increasing on ``[0, inf)`` exactly for ``gamma > 1/2`` (the quadratic's slope
    at 0, ``(2 - 1/gamma) P``, is positive): checked by differences, and a smaller gamma refused."""
    from jscratch.errors import InputError

    x = jnp.linspace(0.0, 3e-4, 301, dtype=jnp.float32)
    for gamma in (0.51, 1.0, 2.2, 8.0):
        assert np.all(np.diff(np.asarray(shading.display(x, gamma=gamma))) > 0), gamma
    for gamma in (0.5, 0.3):
        with pytest.raises(InputError, match=r"^display: `gamma` must be > 0.5 \(below, the curve"):
            shading.display(x, gamma=gamma)
