"""Tests of jscratch.brute, the supersampled reference renderer: the groove profile's slope against
finite differences and its half width against the closed form, and `brute_sums` for one scratch
across one pixel (the paper's profile and the ball's cut) against a 1-D scipy quadrature of
``GGX(n(x).h)`` across the groove, coverage against the groove's area by hand. The agreement
with the analytic renderer is in test_render.py; `brute_shade` is checked in test_shading.py."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from jscratch import brute, render


@pytest.mark.float64
def test_profile_slope_and_half_width():
    w, d = 2.5e-4, 1.28e-4
    x = np.linspace(-0.45 * w, 0.45 * w, 11)
    h = lambda x: -0.5 * w * np.log(1 - 4 * x * x / (w * w)) - d  # noqa: E731
    step = 1e-9
    fd = (h(x + step) - h(x - step)) / (2 * step)
    np.testing.assert_allclose(np.asarray(brute.height_profile_slope(jnp.asarray(x), w, d)), fd,
                               rtol=1e-6, atol=1e-9)
    xm = float(brute.groove_half_width(w, d))
    assert h(xm) == pytest.approx(0.0, abs=1e-15)  # the groove meets the surface at x_max
    assert xm == pytest.approx(0.5 * w * math.sqrt(1 - math.exp(-2 * d / w)), rel=1e-12)


def _one_pixel_scene(width, depth, alpha):
    """A 1 cm pixel crossed bottom to top by one scratch along board y at x = 5 mm (float32)."""
    board = render.Board(shape=(1, 1), Sx=0.01, Sy=0.01)
    cam, light = np.array([0.004, 0.005, 0.05]), np.array([0.008, 0.005, 0.04])
    views = render.Views(jnp.asarray([cam], jnp.float32), jnp.asarray([light], jnp.float32), 1.0)
    sc = render.Scratches(jnp.asarray([[0.005, 0.0]], jnp.float32), jnp.asarray([[0.005, 0.01]], jnp.float32),
                          jnp.float32(width), jnp.float32(depth), jnp.float32(alpha))
    ctr = np.array([0.005, 0.005, 0.0])
    wo, wi = cam - ctr, light - ctr
    h = wo / np.linalg.norm(wo) + wi / np.linalg.norm(wi)
    return board, views, sc, h / np.linalg.norm(h)


def _ggx(cth, alpha):
    return 0.0 if cth <= 0 else alpha**2 / (math.pi * (cth * cth * (alpha**2 - 1) + 1) ** 2)


def test_paper_groove_across_a_pixel_against_quadrature():
    """D_P S_P = L * integral over x of GGX(n(x).h), n from the profile's slope; c S_P = 2 x_max L."""
    w, d, alpha = 2e-3, 8e-4, 0.3
    board, views, sc, h = _one_pixel_scene(w, d, alpha)
    D, c = brute.brute_sums(sc, views, board, n=96)
    xm = 0.5 * w * math.sqrt(1 - math.exp(-2 * d / w))

    # Local frame: t = +y, b = (t_y, -t_x) = (1, 0): local x is board x.
    def f(x):
        slope = (4 * x / w) / (1 - 4 * x * x / (w * w))
        n = np.array([-slope, 0.0, 1.0]) / math.sqrt(1 + slope * slope)
        return _ggx(float(n @ h), alpha)

    ref = 0.01 * integrate.quad(f, -xm, xm, limit=200)[0] / 1e-4
    assert float(c[0]) == pytest.approx(2 * xm * 0.01 / 1e-4, rel=2e-2)
    assert float(D[0, 0]) == pytest.approx(ref, rel=3e-2)
    assert ref > 0.05  # the groove reflects towards this camera: the comparison is not 0 = 0


def test_ball_brute_render_against_quadrature():
    """One scratch across a pixel, the ball's groove: D_P S_P = L * integral of GGX(n(x).h) dx."""
    Rb, p, alpha = 2e-3, 6e-4, 0.3
    board, views, sc, h = _one_pixel_scene(1e-3, p, alpha)
    D, c = brute.brute_sums(sc, views, board, n=96, ball_radius=Rb)
    a = math.sqrt(2 * Rb * p - p * p)

    def f(x):
        n = np.array([-x, 0.0, math.sqrt(Rb * Rb - x * x)]) / Rb
        return _ggx(float(n @ h), alpha)

    ref = 0.01 * integrate.quad(f, -a, a, limit=200)[0] / 1e-4
    assert float(c[0]) == pytest.approx(2 * a * 0.01 / 1e-4, rel=2e-2)
    assert float(D[0, 0]) == pytest.approx(ref, rel=3e-2)


def test_brute_refuses_what_render_refuses():
    """The scene checks of `render` (endpoints on the board), and `n`, `batch` ints >= 1, in
    one line each, also under the name of `brute_sums`; traced scenes are left to the caller."""
    import jax

    from jscratch.errors import InputError

    board, views, sc, _ = _one_pixel_scene(2e-3, 8e-4, 0.3)
    off = render.Scratches(jnp.asarray([[0.005, 0.0]], jnp.float32),
                           jnp.asarray([[0.005, 0.02]], jnp.float32), 2e-3, 8e-4, 0.3)
    with pytest.raises(InputError, match=r"^brute_render: scratch 0: p1 = \(0.005, 0.02\) m lies "
                                         r"off the board \[0, 0.01\] x \[0, 0.01\] m"):
        brute.brute_render(off, views, board, n=2)
    for n in (0, -1, 2.5):
        with pytest.raises(InputError, match=rf"^brute_render: `n` must be an int >= 1; got {n}$"):
            brute.brute_render(sc, views, board, n=n)
    with pytest.raises(InputError, match=r"^brute_sums: `batch` must be an int >= 1; got 0$"):
        brute.brute_sums(sc, views, board, n=2, batch=0)
    traced = jax.jit(lambda s: brute.brute_render(s, views, board, n=2))(sc)
    assert traced.shape == (1, 1, 1) and bool(jnp.isfinite(traced).all())
