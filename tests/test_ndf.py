"""Tests of `jscratch.ndf` against an independent reference (`jscratch.bench.ndf_reference`: exact
clipping in mpmath, adaptive QUADPACK/tanh-sinh of the chord-length form, split at the GGX peak
and the chi+ roots), finite differences, invariances and hypothesis property tests."""

from __future__ import annotations

import functools

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import quad

from jscratch.bench import ndf_cases
from jscratch.bench import ndf_reference
from jscratch import ndf

# One jitted vmapped kernel per (function, dtype): batches of any length compile once per shape.
_kernel = jax.jit(jax.vmap(ndf.pair_integral))


def _grad_all(*args):
    def total(*a):
        D, A = ndf.pair_integral(*a)
        return D + A

    return jax.grad(total, argnums=tuple(range(7)))(*args)


_grads = jax.jit(jax.vmap(_grad_all))


@functools.lru_cache(maxsize=None)
def _population():
    fams = ndf_cases.all_families()
    names = np.concatenate([[k] * v.len() for k, v in fams.items()])
    return ndf_cases.concat(fams.values()), names


@functools.lru_cache(maxsize=None)
def _reference(dtype_name):
    C, _ = _population()
    # The reference integrates exactly at the inputs rounded to the tested dtype.
    return ndf_reference.reference_batch(C.astype(np.dtype(dtype_name)))


@functools.lru_cache(maxsize=None)
def _population_run(dtype_name):
    return _run(_population()[0], np.dtype(dtype_name))


def _run(C, dtype):
    D, A = _kernel(*C.astype(dtype).args())
    return np.asarray(D, np.float64), np.asarray(A, np.float64)


def _report(err, names, what):
    worst = {n: float(np.max(err[names == n])) for n in np.unique(names)}
    return f"{what}: worst error/tolerance per family {worst}"


def test_population_is_large_and_covers_every_family():
    C, names = _population()
    assert C.len() >= 500 + 300
    assert (names == "random").sum() >= 500
    expected = {
        "alpha", "grazing_hz", "hy_zero", "width", "depth_ratio", "vertex_on_edge",
        "parallel_perpendicular", "endpoints", "zero_length", "far_along", "miss",
    }
    assert expected <= set(names)
    assert C.alpha.min() <= 1e-4 and C.alpha.max() >= 0.9
    assert C.h[:, 2].min() <= 0.02 + 1e-12


@pytest.mark.parametrize("dtype, rel, floor", [pytest.param("float64", 1e-8, 1e-12, marks=pytest.mark.float64), ("float32", 1e-3, 1e-5)])
def test_closed_form_matches_reference(dtype, rel, floor):
    C, names = _population()
    Dr, Ar = _reference(dtype)
    D, A = _population_run(dtype)
    assert np.all(np.isfinite(D)) and np.all(np.isfinite(A))
    alpha = C.astype(np.dtype(dtype)).alpha.astype(np.float64)
    tol = np.maximum(rel * np.abs(Dr), floor * Ar / (np.pi * alpha))
    err = np.abs(D - Dr) / np.where(tol > 0, tol, 1.0)
    err = np.where(tol > 0, err, np.abs(D) * 1e300)  # tol == 0 only where the pair misses: D must be 0
    assert np.all(err <= 1.0), _report(err, names, "D_hat")
    # A is a polygon area: exact to rounding.
    tolA = rel * Ar + 1e-6 * rel * C.width.astype(np.float64) ** 2
    errA = np.abs(A - Ar) / tolA
    assert np.all(errA <= 1.0), _report(errA, names, "A")


@pytest.mark.float64
def test_quadrature_converges_to_reference_on_smooth_pairs():
    """Gauss-Legendre is a different method: it must converge where the integrand is smooth
    (moderate alpha) and agree with the reference there."""
    C, _ = _population()
    Dr, Ar = _reference("float64")
    sel = (C.alpha >= 0.2) & (Dr > 0)
    Cs = C.take(np.where(sel)[0])
    errs = []
    for n in (16, 128):
        Dq, Aq = jax.jit(jax.vmap(lambda *a, n=n: ndf.pair_integral_quadrature(*a, n)))(*Cs.args())
        errs.append(np.median(np.abs(np.asarray(Dq) - Dr[sel]) / Dr[sel]))
    assert errs[1] < 1e-6
    assert errs[1] < errs[0]


# ---------------------------------------------------------------------------------------------
# The eight intersection types (paper Fig. 7), with hand-checkable expected values.
#
# Scratch along +y from (0.1, 0.1), length 0.01, w = 2.5e-4, d = w (x_max = (w/2) sqrt(1 - e^-2)
# ~ 1.0811e-4), h = (0, 0, 1): D_x is then symmetric in x and the expected D_hat of a clipped
# rectangle [x0, x1] x [y0, y1] is (y1 - y0) * ∫_{x0}^{x1} D_x dx, a one-dimensional integral done
# here by scipy, and A = (y1 - y0)(x1 - x0).

_W = 2.5e-4
_XM = 0.5 * _W * np.sqrt(-np.expm1(-2.0))
_P0 = np.array([0.1, 0.1])
_P1 = np.array([0.1, 0.11])
_ALPHA = 0.1
_H = np.array([0.0, 0.0, 1.0])


def _dx(x):
    u = x / _W
    c = (1 - 4 * u * u) / (1 + 4 * u * u)
    return _ALPHA**2 / (np.pi * (c * c * (_ALPHA**2 - 1) + 1) ** 2)


def _strip(x0, x1):
    return quad(_dx, x0, x1, epsabs=0, epsrel=1e-13)[0]


def _rect(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def _check(fp, D_exp, A_exp):
    args = (_H, fp, _P0, _P1, _W, _W, _ALPHA)
    D, A = ndf.pair_integral(*[jnp.asarray(a, jnp.float64) for a in args])
    np.testing.assert_allclose(float(A), A_exp, rtol=1e-12, atol=1e-24)
    np.testing.assert_allclose(float(D), D_exp, rtol=1e-10)
    D32, A32 = ndf.pair_integral(*[jnp.asarray(a, jnp.float32) for a in args])
    np.testing.assert_allclose(float(D32), D_exp, rtol=2e-3)
    np.testing.assert_allclose(float(A32), A_exp, rtol=2e-3)


@pytest.mark.float64
def test_type1_groove_crosses_footprint():
    # Footprint wider than the groove, scratch passes through: clipped region = full groove width.
    fp = _rect(0.1 - 5e-4, 0.104, 0.1 + 5e-4, 0.105)
    _check(fp, 1e-3 * _strip(-_XM, _XM), 1e-3 * 2 * _XM)


@pytest.mark.float64
def test_type2_scratch_ends_inside_footprint():
    fp = _rect(0.1 - 5e-4, 0.1095, 0.1 + 5e-4, 0.1105)  # the end y = 0.11 is inside
    _check(fp, 5e-4 * _strip(-_XM, _XM), 5e-4 * 2 * _XM)


@pytest.mark.float64
def test_type3_scratch_entirely_inside_footprint():
    fp = _rect(0.095, 0.099, 0.105, 0.111)
    _check(fp, 0.01 * _strip(-_XM, _XM), 0.01 * 2 * _XM)


@pytest.mark.float64
def test_type4_footprint_inside_groove():
    fp = _rect(0.1 - 3e-5, 0.105, 0.1 + 5e-5, 0.10501)
    _check(fp, 1e-5 * _strip(-3e-5, 5e-5), 1e-5 * 8e-5)


@pytest.mark.float64
def test_type5_footprint_straddles_one_groove_wall():
    fp = _rect(0.1 + 5e-5, 0.105, 0.1 + 5e-4, 0.1051)
    _check(fp, 1e-4 * _strip(5e-5, _XM), 1e-4 * (_XM - 5e-5))


@pytest.mark.float64
def test_type6_footprint_covers_a_groove_corner():
    fp = _rect(0.1 + 2e-5, 0.1099, 0.1 + 5e-4, 0.1101)  # the end and the right wall inside
    _check(fp, 1e-4 * _strip(2e-5, _XM), 1e-4 * (_XM - 2e-5))


@pytest.mark.float64
def test_type7_narrow_footprint_across_the_groove_end():
    fp = _rect(0.1 - 4e-5, 0.0999, 0.1 + 1e-5, 0.1002)  # inside the width, straddles y = 0
    _check(fp, 2e-4 * _strip(-4e-5, 1e-5), 2e-4 * 5e-5)


@pytest.mark.float64
def test_type8_rotated_footprint_corner_in_the_groove():
    """A diamond whose bottom corner lies on the scratch axis: the clipped region is a triangle
    |x| <= y - y0 (for y - y0 <= x_max) topped by the full width: chord(x) = Y - |x| - ... Here the
    diamond is large, so the clipped region is {|x| <= x_max, y >= y0 + |x|, y <= y0 + r} with
    chord(x) = r - |x| and A = 2 r x_max - x_max^2."""
    r = 1e-3
    y0 = 0.104
    fp = np.array([[0.1, y0], [0.1 + r, y0 + r], [0.1, y0 + 2 * r], [0.1 - r, y0 + r]])
    # Above y0 + r the diamond narrows again, but only beyond |x| = r - (y - y0 - r) >= x_max for
    # y <= y0 + 2r - x_max: chord(x) = (2r - |x|) - |x| = 2r - 2|x|.
    D_exp = quad(lambda x: (2 * r - 2 * abs(x)) * _dx(x), -_XM, 0, epsabs=0, epsrel=1e-13)[0] * 2
    A_exp = 2 * (2 * r * _XM - _XM**2)
    _check(fp, D_exp, A_exp)


# ---------------------------------------------------------------------------------------------
# Invariances (float64, generic random pairs).


def _generic(n=24):
    C = ndf_cases.random_cases(n=64, seed=7)
    Dr, _ = ndf_reference.reference_batch(C)
    return C.take(np.where(Dr > 0)[0][:n])


@pytest.mark.float64
def test_swapping_endpoints_changes_nothing():
    C = _generic()
    D, A = _run(C, np.float64)
    Cs = C._replace(p0=C.p1, p1=C.p0)
    D2, A2 = _run(Cs, np.float64)
    np.testing.assert_allclose(D2, D, rtol=1e-10)
    np.testing.assert_allclose(A2, A, rtol=1e-10)


@pytest.mark.float64
def test_rigid_motion_changes_nothing():
    C = _generic()
    D, A = _run(C, np.float64)
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    o = np.array([0.15, 0.15])
    shift = np.array([0.01, -0.02])

    def move(p):
        return (p - o) @ R.T + o + shift

    h = C.h.copy()
    h[:, :2] = C.h[:, :2] @ R.T
    Cm = C._replace(h=h, footprint=move(C.footprint), p0=move(C.p0), p1=move(C.p1))
    D2, A2 = _run(Cm, np.float64)
    np.testing.assert_allclose(D2, D, rtol=1e-9)
    np.testing.assert_allclose(A2, A, rtol=1e-9)


@pytest.mark.float64
def test_splitting_the_footprint_sums_to_the_whole():
    C = _generic()
    D, A = _run(C, np.float64)
    fp = C.footprint  # axis-aligned squares, CCW from the lower-left corner
    xm = (fp[:, 0, 0] + fp[:, 1, 0]) / 2 + 1e-4  # off-centre cut
    left = fp.copy()
    left[:, 1, 0] = xm
    left[:, 2, 0] = xm
    right = fp.copy()
    right[:, 0, 0] = xm
    right[:, 3, 0] = xm
    D1, A1 = _run(C._replace(footprint=left), np.float64)
    D2, A2 = _run(C._replace(footprint=right), np.float64)
    np.testing.assert_allclose(D1 + D2, D, rtol=1e-9, atol=1e-12 * np.max(D))
    np.testing.assert_allclose(A1 + A2, A, rtol=1e-9)


@pytest.mark.float64
def test_splitting_the_scratch_sums_to_the_whole():
    C = _generic()
    D, A = _run(C, np.float64)
    mid = C.p0 + 0.37 * (C.p1 - C.p0)
    D1, A1 = _run(C._replace(p1=mid), np.float64)
    D2, A2 = _run(C._replace(p0=mid), np.float64)
    np.testing.assert_allclose(D1 + D2, D, rtol=1e-9, atol=1e-12 * np.max(D))
    np.testing.assert_allclose(A1 + A2, A, rtol=1e-9)


@pytest.mark.float64
def test_clockwise_footprint_gives_the_same_values():
    C = _generic()
    D, A = _run(C, np.float64)
    D2, A2 = _run(C._replace(footprint=C.footprint[:, ::-1]), np.float64)
    np.testing.assert_allclose(D2, D, rtol=1e-10)
    np.testing.assert_allclose(A2, A, rtol=1e-10)


@pytest.mark.float64
def test_area_equals_exact_polygon_clip():
    C, _ = _population()
    Cs = C.take(np.arange(0, C.len(), 7))
    _, A = _run(Cs, np.float64)
    Ar = np.array([ndf_reference.reference_area(*a[1:6]) for a in zip(*Cs.args())])
    np.testing.assert_allclose(A, Ar, rtol=1e-11, atol=1e-24)


# ---------------------------------------------------------------------------------------------
# Gradients.


@pytest.mark.float64
def test_gradients_match_central_differences():
    """Every input, float64, generic pairs: grad vs a 4th-order central difference."""
    C = _generic(12)
    grads = [np.asarray(g) for g in _grads(*C.args())]
    scales = [1e-5, 2e-9, 2e-9, 2e-9, 2e-10, 2e-10, 1e-6]  # step per argument
    f = jax.jit(lambda *a: sum(ndf.pair_integral(*a)))
    for i in range(C.len()):
        args = [np.asarray(a[i], np.float64) for a in C.args()]
        val = float(f(*args))
        for k, step in enumerate(scales):
            flat = args[k].reshape(-1)
            fd = np.zeros_like(flat)
            for j in range(flat.size):
                def at(dx):
                    a = [x.copy() for x in args]
                    a[k] = (flat + dx * np.eye(flat.size)[j]).reshape(args[k].shape)
                    return float(f(*a))

                fd[j] = (8 * (at(step) - at(-step)) - (at(2 * step) - at(-2 * step))) / (12 * step)
            g = grads[k][i].reshape(-1)
            scale = np.max(np.abs(g)) + np.max(np.abs(fd)) + 1e-30
            assert np.max(np.abs(g - fd)) <= 1e-5 * scale + 1e-9 * abs(val), (i, k, g, fd)


def _grads_by(hand_vjp, jit=True):
    def total(*a):
        D, A = ndf._pair_integral(*a, hand_vjp)
        return D + A

    f = jax.vmap(jax.grad(total, argnums=tuple(range(7))))
    return jax.jit(f) if jit else f


@functools.lru_cache(maxsize=None)
def _autodiff_grads_f64(dtype_name):
    """Plain reverse-mode autodiff through the same forward, float64, at the population's inputs
    rounded to `dtype_name`: the reference for the hand-written derivative. Evaluated op by op:
    XLA's fused, jitted autodiff gives a different half-vector gradient on some grazing pairs
    (jax 0.10.1 CPU; see `tests/test_native.py`)."""
    C = _population()[0].astype(np.dtype(dtype_name)).astype(np.float64)
    return [np.asarray(g).reshape(C.len(), -1) for g in _grads_by(False, jit=False)(*C.args())]


@pytest.mark.float64
def test_hand_written_vjp_matches_autodiff_float64():
    """The analytic reverse pass of the piece integrals (Leibniz ends, integration by parts for the
    peak, linearity in the lobe coefficients) against autodiff of the same forward, on every
    pair of the population (933, all adversarial families), every argument."""
    C, names = _population()
    ref = _autodiff_grads_f64("float64")
    got = [np.asarray(g).reshape(C.len(), -1) for g in _grads_by(True)(*C.args())]
    for k in range(7):
        scale = np.max(np.abs(ref[k]), axis=1)
        tol = 1e-7 * scale + 1e-9 * np.percentile(scale, 90)
        err = np.max(np.abs(got[k] - ref[k]), axis=1) / tol
        assert err.max() <= 1, (k, err.max(), names[np.argmax(err)])


@pytest.mark.float64
def test_hand_written_vjp_float32_accuracy():
    """Float32 gradients against float64 autodiff at the same (rounded) inputs: as accurate as
    float32 autodiff of the same forward. Kinks (a vertex exactly on a groove edge) and
    hy = 0 peaks are ill-conditioned in float32 for both, hence the percentiles."""
    C, _ = _population()
    C32 = C.astype(np.float32)
    ref = _autodiff_grads_f64("float32")
    hand = [np.asarray(g, np.float64).reshape(C.len(), -1) for g in _grads_by(True)(*C32.args())]
    auto = [np.asarray(g, np.float64).reshape(C.len(), -1) for g in _grads_by(False)(*C32.args())]
    for k in range(7):
        s = np.max(np.abs(ref[k]), axis=1)
        scale = s + 1e-5 * np.percentile(s, 90)
        e_hand = np.max(np.abs(hand[k] - ref[k]), axis=1) / scale
        e_auto = np.max(np.abs(auto[k] - ref[k]), axis=1) / scale
        assert np.median(e_hand) <= 1e-5, (k, np.median(e_hand))
        assert np.percentile(e_hand, 90) <= 1e-3, (k, np.percentile(e_hand, 90))
        assert np.percentile(e_hand, 99) <= 2 * np.percentile(e_auto, 99) + 1e-3, k


@pytest.mark.parametrize("dtype", [np.float32, pytest.param(np.float64, marks=pytest.mark.float64)])
def test_gradients_finite_on_every_adversarial_case(dtype):
    C, names = _population()
    grads = _grads(*C.astype(dtype).args())
    for k, g in enumerate(grads):
        bad = ~np.isfinite(np.asarray(g)).reshape(C.len(), -1).all(axis=1)
        assert not bad.any(), (k, np.unique(names[bad]))


@pytest.mark.parametrize("dtype", ["float32", pytest.param("float64", marks=pytest.mark.float64)])
def test_zero_length_and_miss_give_exact_zeros(dtype):
    _, names = _population()
    D, A = _population_run(dtype)
    for name in ("zero_length", "miss"):
        sel = names == name
        assert sel.sum() >= 6
        assert np.all(D[sel] == 0) and np.all(A[sel] == 0), name


# ---------------------------------------------------------------------------------------------
# Building blocks.


@pytest.mark.float64
def test_building_blocks():
    w, d = 2.5e-4, 1.28e-4
    xm = float(ndf.groove_half_width(w, d))
    assert abs(float(ndf.height_profile(xm * (1 - 1e-9), w, d))) < 1e-12
    assert float(ndf.height_profile(0.0, w, d)) == pytest.approx(-d)
    assert float(ndf.height_profile(2 * xm, w, d)) == 0.0
    x = np.linspace(-0.4 * w, 0.4 * w, 9)
    n = np.asarray(ndf.normal(x, w))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-12)
    # The normal is perpendicular to the profile's tangent (1, 0, h'(x)).
    eps = 1e-12
    slope = (np.asarray(ndf.height_profile(x + eps, w, d)) - np.asarray(ndf.height_profile(x - eps, w, d))) / (2 * eps)
    np.testing.assert_allclose(n[:, 0] + n[:, 2] * slope, 0.0, atol=1e-6)
    # GGX integrates to 1 over projected solid angle: ∫ D cos dω = 1.
    a = 0.3
    val = quad(lambda th: float(ndf.ggx(np.cos(th), a)) * np.cos(th) * np.sin(th) * 2 * np.pi, 0, np.pi / 2, epsrel=1e-10)[0]
    assert val == pytest.approx(1.0, rel=1e-8)
    assert float(ndf.ggx(-0.1, a)) == 0.0
    # point_ndf equals ggx(n.h).
    hl = np.array([0.2, 0.1, 0.9])
    hl = hl / np.linalg.norm(hl)
    np.testing.assert_allclose(
        np.asarray(ndf.point_ndf(hl, x, w, a)), np.asarray(ndf.ggx(n @ hl, a)), rtol=1e-12
    )
    um, up = ndf.lit_interval(hl[0], hl[2])
    for r in (float(um), float(up)):
        assert abs(hl[2] * (1 - 4 * r * r) - 4 * hl[0] * r) < 1e-12


# ---------------------------------------------------------------------------------------------
# Property tests: finiteness over the extreme ranges (float32, one compilation).

_one32 = jax.jit(lambda *a: (ndf.pair_integral(*a), _grad_all(*a)))


@hypothesis.settings(max_examples=150, deadline=None)
@hypothesis.given(
    alpha=st.floats(1e-4, 0.9),
    hz=st.floats(0.02, 1.0),
    phi=st.floats(-np.pi, np.pi),
    wexp=st.floats(np.log10(1.2e-6), np.log10(0.12)),
    dw=st.floats(1e-3, 50.0),
    cx=st.floats(-2.0, 2.0),
    cy=st.floats(-2.0, 2.0),
    theta=st.sampled_from([0.0, np.pi / 2, np.pi / 4, 1.234]),
    length=st.sampled_from([0.0, 1e-4, 0.01, 0.4]),
)
# An adversarial float32 case: an empty boundary piece outside the lit range.
@hypothesis.example(alpha=1e-4, hz=1.0, phi=0.0, wexp=-5.90625, dw=1.0, cx=0.0, cy=1.0,
                    theta=1.234, length=1e-4)
def test_values_and_gradients_finite_over_extreme_ranges(alpha, hz, phi, wexp, dw, cx, cy, theta, length):
    s = 0.3 / 256
    fp = np.array([[0.15, 0.15], [0.15 + s, 0.15], [0.15 + s, 0.15 + s], [0.15, 0.15 + s]])
    w = 10.0**wexp
    rxy = np.sqrt(max(1 - hz * hz, 0.0))
    h = np.array([rxy * np.cos(phi), rxy * np.sin(phi), hz])
    t = np.array([np.cos(theta), np.sin(theta)])
    p0 = np.array([0.15 + cx * s, 0.15 + cy * s]) - 0.5 * length * t
    p1 = p0 + length * t
    args = [np.asarray(a, np.float32) for a in (h, fp, p0, p1, w, dw * w, alpha)]
    (D, A), grads = _one32(*args)
    assert np.isfinite(float(D)) and np.isfinite(float(A))
    assert float(D) >= -1e-6 * float(A) / (np.pi * alpha) - 1e-30
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("dtype, rtol", [pytest.param(np.float64, 1e-12, marks=pytest.mark.float64), (np.float32, 1e-5)])
def test_fewer_pieces_equal_the_full_kernel_where_the_count_allows(dtype, rtol):
    """`lit_integral(pair_geometry(...), ..., pieces=k)` gives `pair_integral`'s `D_hat`, values
    and gradients, wherever the geometry's `count <= k`, and differs where it is larger (a wrong
    count would show); every family has pairs of both kinds. Past `N_COMPACT` it is the full
    kernel. Gradients differ only by rounding,
    which the ill-conditioned hy = 0 peaks amplify in float32 (as in
    `test_hand_written_vjp_float32_accuracy`), hence percentiles there."""
    C, names = _population()
    Cd = C.astype(dtype)
    geometry = jax.jit(jax.vmap(ndf.pair_geometry))(Cd.footprint, Cd.p0, Cd.p1, Cd.width,
                                                    Cd.depth)
    count = np.asarray(geometry.count)
    assert count.min() == 0 and count.max() >= 5 and np.mean(count == 2) > 0.3

    def kernel(pieces):
        def D(h, fp, p0, p1, w, d, a):
            return ndf.lit_integral(ndf.pair_geometry(fp, p0, p1, w, d), h, a, pieces=pieces)

        return jax.jit(jax.vmap(lambda *a: (D(*a), jax.grad(D, argnums=tuple(range(7)))(*a))))

    def full(*a):
        return ndf.pair_integral(*a)[0]

    D, g = jax.jit(jax.vmap(lambda *a: (full(*a), jax.grad(full, argnums=tuple(range(7)))(*a))))(
        *Cd.args())
    D, g = np.asarray(D), [np.asarray(x, np.float64).reshape(len(D), -1) for x in g]
    for k in (1, 2, ndf.N_COMPACT, ndf.N_COMPACT + 1):
        D2, g2 = kernel(k)(*Cd.args())
        D2 = np.asarray(D2)
        if k > ndf.N_COMPACT:  # beyond the compacted pieces: all of them, the full kernel
            np.testing.assert_allclose(D2, D, rtol=rtol, atol=0)
            continue
        ok = count <= k
        assert ok.sum() >= 50 and (~ok).sum() >= 2
        np.testing.assert_allclose(D2[ok], D[ok], rtol=rtol, atol=0)
        for a, b in zip(g2, g):
            a = np.asarray(a, np.float64).reshape(len(D), -1)[ok]
            b = b[ok]
            scale = np.max(np.abs(b), axis=1)
            diff = np.max(np.abs(a - b), axis=1)
            den = scale + 1e-6 * np.percentile(scale, 90)
            err = np.where(diff == 0, 0, diff / np.where(den > 0, den, 1))
            if dtype == np.float64:
                assert np.percentile(err, 99) <= 1e-8 and err.max() <= 1e-3, err.max()
            else:
                assert np.median(err) <= 1e-5 and np.percentile(err, 90) <= 1e-3, err.max()
        # Where the count exceeds the budget the missing pieces matter.
        differs = np.abs(D2[~ok] - D[~ok]) > 1e-3 * np.abs(D[~ok])
        assert np.mean(differs) > 0.5, k
    # A zero count is a miss: nothing to integrate.
    miss = count == 0
    assert np.all(D[miss] == 0) and np.all(np.asarray(geometry.area)[miss] == 0)


@pytest.mark.parametrize("dtype", [np.float32, pytest.param(np.float64, marks=pytest.mark.float64)])
def test_piece_count_estimate_is_the_count_but_for_ties(dtype):
    """`piece_count_estimate` (what the renderer sorts pairs by) equals `pair_geometry`'s count
    on every random pair, and on all but a few of the adversarial ones (pieces that only touch
    the groove or a scratch end: vertices on edges, ends on footprint edges, zero lengths)."""
    C, names = _population()
    C = C.astype(dtype)
    a = (C.footprint, C.p0, C.p1, C.width, C.depth)
    count = np.asarray(jax.jit(jax.vmap(lambda *x: ndf.pair_geometry(*x).count))(*a))
    est = np.asarray(jax.jit(jax.vmap(ndf.piece_count_estimate))(*a))
    same = est == count
    assert np.all(same[names == "random"])
    assert np.mean(same) >= 0.95, np.mean(same)
    assert set(np.unique(names[~same])) <= {"vertex_on_edge", "endpoints", "zero_length"}


def test_cut_to_slab_clamps_ends_and_flags_them():
    """`ndf.cut_to_slab`: a piece inside the slab is kept (Y re-centred on the cut region), a
    crossing end moves to the bound with Y interpolated there and is flagged, a piece outside
    becomes a point on the bound."""
    ua = jnp.array([-0.1, -0.3, 0.3, 0.0, 0.0, 0.0])
    ub = jnp.array([0.1, 0.1, 0.35, 0.0, 0.0, 0.0])
    Ya = jnp.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    Yb = jnp.array([1.0, 2.0, 1.0, 0.0, 0.0, 0.0])
    (ca, cb, Ya2, Yb2), (lo_a, hi_a, lo_b, hi_b) = ndf.cut_to_slab(ua, ub, Ya, Yb, -0.2, 0.2)
    np.testing.assert_allclose(np.asarray(ca[:3]), [-0.1, -0.2, 0.2])
    np.testing.assert_allclose(np.asarray(cb[:3]), [0.1, 0.1, 0.2])
    assert list(np.asarray(lo_a[:3])) == [False, True, False]
    assert list(np.asarray(hi_a[:3])) == [False, False, True]
    assert list(np.asarray(hi_b[:3])) == [False, False, True] and not np.any(np.asarray(lo_b))
    # Y differences are kept: 1 along the first piece, 2 * (0.3 / 0.4) along the cut second one.
    np.testing.assert_allclose(np.asarray(Yb2 - Ya2)[:3], [1.0, 1.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(float(Ya2[1] - Ya2[0]), 0.5, atol=1e-6)


@pytest.mark.float64
@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_float32_gradients_hold_over_the_scenes_alpha_range(profile):
    """At the ends of `scene.ALPHA_RANGE` the float32 pair integral and its alpha and width
    gradients agree with float64 (the same float32 inputs) to 2e-3 of ``D / alpha`` and
    ``D / w`` over lit random pairs: the range is where float32 is accurate (past 0.99 the
    alpha gradient of the paper profile loses about 1e-2)."""
    from jscratch import arc
    from jscratch.scene import ALPHA_RANGE

    f = arc.pair_integral_of(profile)
    rng = np.random.default_rng(7)
    n, P = 400, 0.000625
    x0 = rng.uniform(0.002, 0.008, (n, 2))
    fps = np.stack([x0, x0 + [P, 0], x0 + [P, P], x0 + [0, P]], 1)
    mid = x0 + rng.uniform(0, P, (n, 2))
    phi = rng.uniform(0, 2 * np.pi, n)
    t = np.stack([np.cos(phi), np.sin(phi)], -1)
    beta = rng.uniform(-0.3, 0.3, n)  # h in the grooves' fans of normals: lit at any alpha
    h = np.concatenate([np.sin(beta)[:, None] * np.stack([-t[:, 1], t[:, 0]], -1),
                        np.cos(beta)[:, None]], -1)
    w, d = rng.uniform(1e-4, 3e-4, n), rng.uniform(0.3e-4, 2e-4, n)
    value_and_grads = jax.jit(jax.vmap(jax.value_and_grad(lambda *q: f(*q)[0], argnums=(4, 6))))
    for a in ALPHA_RANGE:
        args = [np.asarray(x, np.float32) for x in
                (h, fps, mid - 0.002 * t, mid + 0.002 * t, w, d, np.full(n, a))]

        def run(dt):
            D, (gw, ga) = value_and_grads(*(jnp.asarray(x, dt) for x in args))
            return (np.asarray(x, np.float64) for x in (D, gw, ga))

        (D32, gw32, ga32), (D64, gw64, ga64) = run(jnp.float32), run(jnp.float64)
        lit = D64 > 1e-3 * D64.max()
        assert lit.sum() > 50
        for g32, g64, scale in ((ga32, ga64, a), (gw32, gw64, args[4])):
            err = (np.abs(g32 - g64) * scale)[lit] / D64[lit]
            assert err.max() < 2e-3, (profile, a, float(err.max()))
        assert float(np.max(np.abs(D32 - D64)[lit] / D64[lit])) < 1e-3
