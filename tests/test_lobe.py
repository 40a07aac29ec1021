"""Tests of jscratch.lobe: the factorised GGX ``(alpha^2 / 4 pi)(T1^2 + T1 + T2^2 + T2)`` equals the
textbook GGX of the groove normal ``n(u)`` (from the profile's slope) at every lit ``u``;
`piece_values` (closed form on long pieces, Gauss-Legendre on short ones) against scipy quadrature
of the textbook GGX, in float64 and float32; its end and ``Y`` partials against central finite
differences; the Gauss-Legendre rule's exactness."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from jscratch import lobe


def _ggx_of_normal(u, h, alpha):
    """Textbook GGX D(n(u).h) / pref: n from the slope 4u / (1 - 4u^2) of the groove profile."""
    slope = 4 * u / (1 - 4 * u * u)
    c = (-slope * h[0] + h[2]) / math.sqrt(1 + slope * slope)
    if c <= 0:
        return 0.0
    d = alpha**2 / (math.pi * (c * c * (alpha**2 - 1) + 1) ** 2)
    return d / (alpha**2 / (4 * math.pi))


def _lit(h):
    """The lit u-range (n(u).h > 0) inside the groove (-1/2, 1/2), by the quadratic's roots."""
    hx, hz = h[0], h[2]
    r = math.hypot(hx, hz)
    lo, hi = sorted(((-hx - r) / (2 * hz), (-hx + r) / (2 * hz)))
    return max(lo, -0.5 + 1e-9), min(hi, 0.5 - 1e-9)


def _half_vector(rng):
    h = rng.normal(size=3)
    h[2] = abs(h[2]) + 0.2
    return h / np.linalg.norm(h)


@pytest.mark.float64
def test_factorised_lobe_is_the_textbook_ggx():
    rng = np.random.default_rng(0)
    for alpha in (0.02, 0.1, 0.5, 0.95):
        h = _half_vector(rng)
        L = lobe.lobe(*(jnp.float64(v) for v in h), jnp.float64(alpha))
        lo, hi = _lit(h)
        u = np.linspace(lo, hi, 41)[1:-1]
        T1, T2 = (np.asarray(t) for t in lobe.lobe_terms(L, jnp.asarray(u)))
        ref = np.array([_ggx_of_normal(x, h, alpha) for x in u])
        np.testing.assert_allclose(T1 * T1 + T1 + T2 * T2 + T2, ref, rtol=1e-10)
    assert float(lobe.prefactor(0.5)) == pytest.approx(0.25 / (4 * math.pi))


def _pieces(rng, h, n):
    """n pieces inside the lit range: a few long ones (closed form) and short ones (quadrature)."""
    lo, hi = _lit(h)
    ua = rng.uniform(lo, hi, n)
    length = np.where(np.arange(n) % 2 == 0, rng.uniform(0.3, 1.0, n), rng.uniform(1e-4, 0.02, n))
    ub = np.clip(ua + length * (hi - lo) * rng.choice([-1, 1], n), lo, hi)
    return ua, ub, rng.uniform(0.0, 2.0, n), rng.uniform(0.0, 2.0, n)


@pytest.mark.float64
@pytest.mark.parametrize("alpha", [0.01, 0.08, 0.6])
def test_piece_values_against_quadrature(alpha):
    rng = np.random.default_rng(int(alpha * 1000))
    h = _half_vector(rng)
    ua, ub, Ya, Yb = _pieces(rng, h, 6)
    L = lobe.lobe(*(jnp.float64(v) for v in h), jnp.float64(alpha))
    p = lobe.lobe_params(L)
    got = np.asarray(lobe.piece_values(lobe.nodes(jnp.float64), *(jnp.asarray(a) for a in (ua, ub, Ya, Yb)),
                                       p, False))
    with_partials, _ = lobe.piece_values(lobe.nodes(jnp.float64), *(jnp.asarray(a) for a in (ua, ub, Ya, Yb)),
                                         p, True)
    for i in range(6):
        Y = lambda u: Ya[i] + (Yb[i] - Ya[i]) * (u - ua[i]) / (ub[i] - ua[i])  # noqa: E731
        lo, hi = sorted((ua[i], ub[i]))
        u1 = float(L.u1)
        pts = [u1] if lo < u1 < hi else None
        ref = integrate.quad(lambda u: Y(u) * _ggx_of_normal(u, h, alpha), lo, hi, points=pts,
                             limit=500, epsabs=0, epsrel=1e-12)[0]
        ref *= np.sign(ub[i] - ua[i])
        assert got[i] == pytest.approx(ref, rel=1e-8, abs=1e-12 * abs(ref)), (i, got[i], ref)
        assert float(with_partials[i]) == pytest.approx(ref, rel=1e-8)


def test_piece_values_float32():
    rng = np.random.default_rng(5)
    h = _half_vector(rng)
    alpha = 0.05
    ua, ub, Ya, Yb = _pieces(rng, h, 8)
    L = lobe.lobe(*(jnp.float32(v) for v in h), jnp.float32(alpha))
    args = [jnp.asarray(a, jnp.float32) for a in (ua, ub, Ya, Yb)]
    got = lobe.piece_values(lobe.nodes(jnp.float32), *args, lobe.lobe_params(L), False)
    assert got.dtype == jnp.float32 and lobe.nodes(jnp.float32) == 4
    for i in range(8):
        Y = lambda u: Ya[i] + (Yb[i] - Ya[i]) * (u - ua[i]) / (ub[i] - ua[i])  # noqa: E731
        lo, hi = sorted((ua[i], ub[i]))
        ref = np.sign(ub[i] - ua[i]) * integrate.quad(
            lambda u: Y(u) * _ggx_of_normal(u, h, alpha), lo, hi, limit=500, epsrel=1e-10)[0]
        # float32: relative to the piece's scale (its |Y| times the lobe's peak times its length)
        scale = max(Ya[i], Yb[i]) * (hi - lo) * 4 / alpha**2
        assert abs(float(got[i]) - ref) <= 1e-3 * abs(ref) + 1e-6 * scale, (i, float(got[i]), ref)


@pytest.mark.float64
def test_piece_partials_against_finite_differences():
    rng = np.random.default_rng(2)
    h = _half_vector(rng)
    L = lobe.lobe(*(jnp.float64(v) for v in h), jnp.float64(0.1))
    p = lobe.lobe_params(L)
    ua, ub, Ya, Yb = (jnp.asarray(a) for a in _pieces(rng, h, 6))
    n = lobe.nodes(jnp.float64)
    _, (d_ua, d_ub, d_Ya, d_Yb, _) = lobe.piece_values(n, ua, ub, Ya, Yb, p, True)
    value = lambda *a: np.asarray(lobe.piece_values(n, *a, p, False))  # noqa: E731
    args = [ua, ub, Ya, Yb]
    for k, d in enumerate((d_ua, d_ub, d_Ya, d_Yb)):
        step = 1e-6
        plus = list(args)
        minus = list(args)
        plus[k] = args[k] + step
        minus[k] = args[k] - step
        fd = (value(*plus) - value(*minus)) / (2 * step)
        np.testing.assert_allclose(np.asarray(d), fd, rtol=1e-5, atol=1e-6 * np.max(np.abs(fd)))


def test_gauss_legendre_is_exact_for_degree_2n_minus_1():
    for n in (4, 16):
        x, w = lobe.gauss_legendre(n)
        for deg in (0, 1, 2 * n - 2, 2 * n - 1):
            exact = 0.0 if deg % 2 else 2.0 / (deg + 1)
            assert float(np.sum(w * x**deg)) == pytest.approx(exact, abs=1e-13)
        assert lobe.gauss_legendre(n) is lobe.gauss_legendre(n)  # cached
    assert lobe.nodes(jnp.float64) == 16
