"""The ball cutter's groove (`jscratch.arc`, docs/model.md §13): the kernel against an independent
high-precision reference, exact areas, symmetries, gradients against central differences, the
quadrature's convergence rate, finiteness over extreme inputs, and the shallow-cut limit where the
arc and the paper's profile coincide."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest

from jscratch import arc, lobe, ndf
from jscratch.bench import ndf_cases as nc
from jscratch.bench import ndf_reference as nr

R = 1.25e-4  # the default machine profile's ball radius (m)
PIX = nc.PIXEL


# ---------------------------------------------------------------------------------------------
# Independent reference: mpmath quadrature of ∫ chord(x) D_x(x) dx in the wall angle
# theta (x = R sin theta), 30 digits, split at the polygon's vertices, the lit range's ends and
# the GGX peak plus/minus multiples of its width.


def _mpf(v):
    return mpmath.mpf(float(v))


def reference(h, fp, p0, p1, plunge, radius, alpha, dps=30):
    """`(D_hat, A)` (python floats) at the inputs as exact binary floats."""
    with mpmath.mp.workdps(dps):
        p0m, t, b, L = nr.local_frame(p0, p1)
        Rm = _mpf(radius)
        p = min(_mpf(plunge), Rm)
        if t is None or p <= 0:
            return 0.0, 0.0
        a = mpmath.sqrt(2 * Rm * p - p * p)
        poly = []
        for q in np.asarray(fp, np.float64):
            rx, ry = _mpf(q[0]) - p0m[0], _mpf(q[1]) - p0m[1]
            poly.append((rx * b[0] + ry * b[1], rx * t[0] + ry * t[1]))
        poly = nr.clip_to_box(poly, -a, a, mpmath.mpf(0), L)
        if len(poly) < 3:
            return 0.0, 0.0
        A = nr.polygon_area(poly)
        hv = [_mpf(v) for v in np.asarray(h, np.float64)]
        hn = mpmath.sqrt(sum(v * v for v in hv))
        hx = (hv[0] * b[0] + hv[1] * b[1]) / hn
        hz = hv[2] / hn
        a2 = _mpf(alpha) ** 2
        # n(theta) = (-sin theta, 0, cos theta): n.h = r cos(theta + phi).
        r = mpmath.sqrt(hx * hx + hz * hz)
        phi = mpmath.atan2(hx, hz)
        tmax = mpmath.asin(a / Rm) if a < Rm else mpmath.pi / 2
        lo, hi = max(-tmax, -mpmath.pi / 2 - phi), min(tmax, mpmath.pi / 2 - phi)
        if not lo < hi:
            return 0.0, float(A)

        def f(th):
            c = r * mpmath.cos(th + phi)
            if c <= 0:
                return mpmath.mpf(0)
            den = c * c * (a2 - 1) + 1
            chord = nr.section(poly, Rm * mpmath.sin(th))
            return chord * a2 / (mpmath.pi * den * den) * Rm * mpmath.cos(th)

        width = mpmath.sqrt(abs(1 - (1 - a2) * r * r)) + mpmath.mpf(10) ** (-dps // 2)
        pts = {lo, hi}
        for P in poly:
            if abs(P[0]) < Rm and lo < mpmath.asin(P[0] / Rm) < hi:
                pts.add(mpmath.asin(P[0] / Rm))
        for m in (0, 0.5, 2, 8, 32, 128):
            for sgn in (-1, 1):
                if lo < -phi + sgn * m * width < hi:
                    pts.add(-phi + sgn * m * width)
        return float(mpmath.quad(f, sorted(pts))), float(A)


# ---------------------------------------------------------------------------------------------
# Cases: (h, footprint, p0, p1, plunge, radius, alpha), numpy float64.


def _lit_h(v0, hy, p0, p1):
    """Unit half vector whose GGX peak lies at v = x / R = v0 on the arc."""
    th = np.arcsin(v0)
    rho = np.sqrt(1 - hy * hy)
    return nc.local_half_vector((-rho * np.sin(th), hy, rho * np.cos(th)), p0, p1)


def _case(rng, family):
    x0 = y0 = 0.15
    fp = nc.square(x0, y0, PIX)
    rho = float(np.exp(rng.uniform(np.log(1e-3), 0)))
    alpha = float(np.exp(rng.uniform(np.log(1e-4), np.log(0.9))))
    if family == "sharp":
        alpha = float(np.exp(rng.uniform(np.log(1e-4), np.log(1e-3))))
    if family == "deep":
        rho = float(rng.choice([1.0, 1 - 1e-7, rng.uniform(0.9, 1.0)]))
    if family == "shallow":
        rho = float(np.exp(rng.uniform(np.log(1e-6), np.log(1e-3))))
    p = rho * R
    a = np.sqrt(2 * R * p - p * p)
    if family == "small":  # a footprint smaller than the groove, inside it
        s = a * rng.uniform(0.05, 0.5)
        fp = nc.square(x0, y0, s)
        q = np.array([x0, y0]) + rng.uniform(0, s, size=2)
    elif family == "large":  # a footprint much larger than the groove
        fp = nc.square(x0, y0, 100 * PIX)
        q = np.array([x0, y0]) + rng.uniform(0, 100 * PIX, size=2)
    else:
        q = np.array([x0, y0]) + rng.uniform(-a, PIX + a, size=2)
    theta = rng.uniform(0, 2 * np.pi)
    if family == "grazing":  # a footprint edge nearly along the groove, near its edge
        theta = rng.choice([0, np.pi / 2]) + rng.normal() * 1e-4
        q = np.array([x0, y0 + rng.uniform(0, PIX)]) + np.array([a * (1 + rng.normal() * 1e-3), 0])
    length = rng.uniform(0.002, 0.02)
    p0, p1 = nc._crossing(theta, q, length, rng.uniform(-0.2, 1.2))
    if family == "grazing":
        hz = 10 ** rng.uniform(-4, -1)
        hy = rng.normal() * 0.3
        hx = np.sqrt(max(1 - hz * hz - hy * hy, 0)) * rng.choice([-1, 1])
        h = nc.local_half_vector((hx, hy, hz), p0, p1)
    elif family == "sharp" or rng.uniform() < 0.6:
        h = _lit_h(rng.uniform(-a / R, a / R), np.clip(alpha * rng.normal(), -0.9, 0.9), p0, p1)
    else:
        h = nc.local_half_vector((rng.normal() * 0.5, rng.normal() * 0.5, 1.0), p0, p1)
    return (h, fp, p0, p1, p, R, alpha)


FAMILIES = {"random": 40, "grazing": 16, "sharp": 16, "deep": 12, "shallow": 8, "small": 8,
            "large": 8}


@functools.lru_cache(maxsize=None)
def _population():
    rng = np.random.default_rng(20261125)
    cases, names = [], []
    for fam, n in FAMILIES.items():
        for _ in range(n):
            # Inputs exactly representable in float32: one reference serves both dtypes.
            cases.append(tuple(np.asarray(v, np.float32).astype(np.float64)
                               for v in _case(rng, fam)))
            names.append(fam)
    return cases, np.array(names)


def _stack(cases, dtype):
    return tuple(np.stack([np.asarray(c[k], dtype) for c in cases]) for k in range(7))


@functools.lru_cache(maxsize=None)
def _reference():
    cases, _ = _population()
    out = np.array([reference(*c) for c in cases])
    return out[:, 0], out[:, 1]


def _grad_all(*args):
    def total(*a):
        D, A = arc.arc_pair_integral(*a)
        return D + A

    return jax.grad(total, argnums=tuple(range(7)))(*args)


# One compiled kernel (values and gradients) per dtype, batches padded to one size: the
# reverse pass takes most of the suite's compile time.
_value_and_grads = jax.jit(jax.vmap(lambda *a: (arc.arc_pair_integral(*a), _grad_all(*a))))
BATCH = {np.dtype(np.float32): 4096, np.dtype(np.float64): 512}


def _run_all(cases, dtype):
    """`((D, A), grads)` for a list of cases (numpy float64 results)."""
    n, nb = len(cases), BATCH[np.dtype(dtype)]
    assert n <= nb
    args = _stack(list(cases) + [cases[0]] * (nb - n), dtype)
    (D, A), grads = _value_and_grads(*args)
    return ((np.asarray(D, np.float64)[:n], np.asarray(A, np.float64)[:n]),
            [np.asarray(g, np.float64)[:n] for g in grads])


def _run(cases, dtype):
    return _run_all(cases, dtype)[0]


def _alpha(cases):
    return np.array([c[6] for c in cases])


# ---------------------------------------------------------------------------------------------
# Values against the reference.


@pytest.mark.parametrize("dtype, rel, floor, rel_a", [
    pytest.param("float64", 1e-11, 1e-13, 1e-12, marks=pytest.mark.float64),
    # float32: the paper kernel's bound (docs/model.md §3). At alpha ~ 1e-4 a 1-ulp change of the
    # inputs moves D by up to ~1e-2 relative; the kernel's own error is far below that.
    ("float32", 1e-3, 1e-5, 1e-5),
])
def test_values_match_the_reference(dtype, rel, floor, rel_a):
    """`|D - D_ref| <= rel |D_ref| + floor A / (pi alpha)` on every family; `A` to `rel_a` of the
    largest area it is a difference of (the footprint's)."""
    cases, names = _population()
    D, A = _run(cases, np.dtype(dtype))
    Dr, Ar = _reference()
    tol = rel * np.abs(Dr) + floor * Ar / (np.pi * _alpha(cases)) + 1e-300
    err = np.abs(D - Dr) / tol
    worst = {n: float(np.max(err[names == n])) for n in FAMILIES}
    assert np.all(err <= 1), worst
    e1 = np.array([c[1][1] - c[1][0] for c in cases])
    e3 = np.array([c[1][3] - c[1][0] for c in cases])
    fp_area = np.abs(e1[:, 0] * e3[:, 1] - e1[:, 1] * e3[:, 0])
    assert np.all(np.abs(A - Ar) <= rel_a * fp_area), np.max(np.abs(A - Ar) / fp_area)
    # Most pairs are lit: the population tests the peak, not zeros.
    assert np.mean(Dr > 0) > 0.6


@pytest.mark.float64
def test_area_is_the_exact_rectangle():
    """A footprint across the whole groove: `A = 2a` times the footprint's extent along it, and
    at normal incidence `D = 3 mm x ∫ D(theta) R cos(theta) dtheta` (scipy, smooth integrand)."""
    from scipy.integrate import quad

    p0, p1 = np.array([0.1, 0.0]), np.array([0.1, 0.01])
    fp = np.array([[0.099, 0.002], [0.101, 0.002], [0.101, 0.005], [0.099, 0.005]])
    rhos = (1e-6, 0.3, 1.0, 1.7)
    cases = [(np.array([0.0, 0.0, 1.0]), fp, p0, p1, rho * R, R, 0.2) for rho in rhos]
    D, A = _run(cases, np.float64)
    for i, rho in enumerate(rhos):
        a = float(arc.arc_half_width(rho * R, R))
        assert A[i] == pytest.approx(2 * a * 0.003, rel=1e-12)
        th = np.arcsin(min(a / R, 1.0))
        val = quad(lambda t: 0.04 / (np.pi * (np.cos(t) ** 2 * (0.04 - 1) + 1) ** 2) * R * np.cos(t),
                   -th, th, epsabs=0, epsrel=1e-13)[0]
        assert D[i] == pytest.approx(0.003 * val, rel=1e-11)


# ---------------------------------------------------------------------------------------------
# Symmetries (float32: what users run).


def _generic(n=24):
    cases, names = _population()
    return [c for c, f in zip(cases, names) if f == "random"][:n]


def test_symmetries():
    """Swapping the ends, a clockwise footprint, and mirroring everything across the scratch's
    axis give the same values."""
    cases = _generic()
    D, A = _run(cases, np.float32)
    swapped = [(h, fp, p1, p0, p, r, a) for h, fp, p0, p1, p, r, a in cases]
    cw = [(h, fp[::-1], p0, p1, p, r, a) for h, fp, p0, p1, p, r, a in cases]

    def mirror(c):
        h, fp, p0, p1, p, r, a = c
        t = (p1 - p0) / np.linalg.norm(p1 - p0)

        def ref(q):  # reflection across the line through p0 along t
            d = q - p0
            return p0 + 2 * (d @ t) * t - d

        hm = np.array([*ref(np.asarray(h[:2]) + p0) - p0, h[2]])
        return (hm, np.array([ref(q) for q in fp[::-1]]), p0, p1, p, r, a)

    mirrored = [mirror(c) for c in cases]
    for other in (swapped, cw, mirrored):
        D2, A2 = _run(other, np.float32)
        tol = 1e-3 * np.abs(D) + 1e-5 * A / (np.pi * _alpha(cases)) + 1e-30
        assert np.all(np.abs(D2 - D) <= tol)
        np.testing.assert_allclose(A2, A, rtol=1e-5, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Gradients.


@pytest.mark.float64
def test_gradients_match_central_differences():
    """Every input (the plunge and the radius included), float64: grad against a 4th-order
    central difference, on generic pairs with alpha >= 0.02 (the difference step must resolve
    the peak)."""
    cases = [(h, fp, p0, p1, p, r, max(a, 0.02)) for h, fp, p0, p1, p, r, a in _generic(10)]
    (D, A), grads = _run_all(cases, np.float64)
    scales = [1e-6, 1e-9, 1e-9, 1e-9, None, 1e-10, None]
    # Every perturbed input of every pair in batches: (pair, argument, entry, step).
    steps = (1, -1, 2, -2)
    rows, keys = [], []
    for i, c in enumerate(cases):
        for k, step in enumerate(scales):
            step = step or 1e-6 * float(c[k])
            for j in range(np.size(c[k])):
                for m in steps:
                    a = list(c)
                    flat = np.array(c[k], np.float64).reshape(-1)
                    flat[j] += m * step
                    a[k] = flat.reshape(np.shape(c[k]))
                    rows.append(tuple(a))
                keys.append((i, k, j, step))
    vals = []
    for b in range(0, len(rows), BATCH[np.dtype(np.float64)]):
        Db, Ab = _run(rows[b:b + BATCH[np.dtype(np.float64)]], np.float64)
        vals.append(Db + Ab)
    vals = np.concatenate(vals).reshape(-1, 4)
    fds = {key: (8 * (v[0] - v[1]) - (v[2] - v[3])) / (12 * key[3]) for key, v in zip(keys, vals)}
    for i, c in enumerate(cases):
        val = D[i] + A[i]
        x = [np.asarray(v, np.float64) for v in c]
        for k in range(7):
            flat = x[k].reshape(-1)
            fd = np.array([fds[key] for key in keys if key[:2] == (i, k)])
            g = grads[k][i].reshape(-1)
            scale = np.max(np.abs(g)) + np.max(np.abs(fd)) + 1e-30
            assert np.max(np.abs(g - fd)) <= 1e-5 * scale + 1e-9 * abs(val) / max(
                np.max(np.abs(flat)), 1e-6), (i, k, g, fd)


# ---------------------------------------------------------------------------------------------
# The quadrature's convergence rate (docs/model.md §13): on one boundary piece across the whole
# lit part of a hemisphere (p = R), with broad lobes (the slowest cases: the ellipse parameter
# near its bound 2), the n-node rule's error is below 8 x 2^-2n of ∫ |Y v' D| du (the scale of
# the bound's M; measured: at most 7x).


@pytest.mark.float64
def test_quadrature_error_decays_at_the_stated_rate():
    configs = [((0, 0, 1), 0.9), ((0.2, 0.7, 0.2), 0.9), ((0, 0.6, 0.3), 0.2),
               ((0.3, 0.8, 0.5), 0.5), ((0.2, 0.55, 0.3), 0.3), ((0.5, 0, 0.86), 1e-3),
               ((0.01, 0.999, 0.03), 0.01), ((-0.9, 0.1, 0.1), 0.05)]
    Ya, Yb = -1.0, 2.0  # Y linear in v along the piece
    for hl, alpha in configs:
        hx, hy, hz = np.asarray(hl, np.float64) / np.linalg.norm(hl)
        L = lobe.lobe(hx, hy, hz, alpha)
        um, up = (float(t) for t in ndf.lit_interval(hx, hz))
        lo, hi = max(-0.5, um), min(0.5, up)
        with mpmath.mp.workdps(30):
            hm = [_mpf(t) for t in (hx, hy, hz)]
            va, vb = (4 * _mpf(u) / (1 + 4 * _mpf(u) ** 2) for u in (lo, hi))

            def f(u, absolute=False):
                v = 4 * u / (1 + 4 * u * u)
                Y = Ya + (Yb - Ya) * (v - va) / (vb - va)
                Y = abs(Y) if absolute else Y
                vp = 4 * (1 - 4 * u * u) / (1 + 4 * u * u) ** 2
                return Y * vp * nr.point_ndf(u, *hm, _mpf(alpha))

            u1, q1 = float(L.u1), float(L.q1)
            near = (u1 + m * q1 for m in (-8, -1, 0, 1, 8))
            pts = sorted({lo, hi, *(t for t in near if lo < t < hi)})
            J_ref = float(mpmath.quad(f, [_mpf(t) for t in pts]))
            J_abs = float(mpmath.quad(lambda u: f(u, True), [_mpf(t) for t in pts]))
        for n in (4, 6, 8, 12):
            J = arc._piece_integrals(n, *(jnp.array([t], jnp.float64) for t in (lo, hi, Ya, Yb)),
                                     lobe.lobe_params(L))
            J = float(L.pref * J[0])
            assert abs(J - J_ref) <= J_abs * (8 * 2.0 ** (-2 * n) + 1e-14), (hl, alpha, n, J, J_ref)


# ---------------------------------------------------------------------------------------------
# Stability sweep: values and gradients finite over extreme and degenerate inputs.


def _sweep(n, seed):
    rng = np.random.default_rng(seed)
    x0 = y0 = 0.15
    rows = []
    for i in range(n):
        rho = [0.0, 1e-9, 1e-6, 1e-3, rng.uniform(0, 1), 1 - 1e-7, 1.0, 1.5, -0.1][i % 9]
        r = R * 10.0 ** rng.choice([-1, 0, 1])
        alpha = float(np.exp(rng.uniform(np.log(1e-4), np.log(0.9))))
        s = PIX * 10.0 ** rng.choice([-4, -2, 0, 2])
        fp = nc.square(x0, y0, s)
        a = r * np.sqrt(max(min(rho, 1) * (2 - min(rho, 1)), 0))
        mode = (i // 8) % 4
        if mode == 0:  # a vertex exactly on the groove's edge
            q = np.array([x0 - a, y0])
            theta = np.pi / 2
        elif mode == 1:  # a footprint edge along the scratch
            q = np.array([x0, y0]) + rng.uniform(-a, s + a, size=2)
            theta = float(rng.choice([0, np.pi / 2]))
        else:
            q = np.array([x0, y0]) + rng.uniform(-a, s + a, size=2)
            theta = rng.uniform(0, 2 * np.pi)
        length = [0.0, 1e-7, 0.01, 0.3][i % 4]
        p0, p1 = nc._crossing(theta, q, length, rng.uniform(-0.5, 1.5))
        hz = 10 ** rng.uniform(-4, 0)
        az = rng.uniform(0, 2 * np.pi)
        rxy = np.sqrt(1 - hz * hz)
        h = np.array([rxy * np.cos(az), rxy * np.sin(az), hz])
        if i % 3 == 0:
            h = _lit_h(rng.uniform(-1, 1) * a / r, np.clip(alpha * rng.normal(), -0.9, 0.9), p0,
                       p1) if length > 0 else h
        rows.append((h, fp, p0, p1, rho * r, r, alpha))
    return rows


@pytest.mark.parametrize("dtype, n", [(np.float32, 4096),
                                      pytest.param(np.float64, 512, marks=pytest.mark.float64)])
def test_values_and_gradients_finite_over_extreme_ranges(dtype, n):
    """Plunge -0.1 R .. 1.5 R (through 0 and R exactly), R from 12.5 µm to 1.25 mm, alpha
    1e-4 .. 0.9, h_z down to 1e-4, footprints from 1e-4 to 100 pixels, vertices on the groove's
    edge, edges along the scratch, zero-length scratches: no non-finite value or gradient, and no
    value below rounding."""
    rows = _sweep(n, 7)
    (D, A), grads = _run_all(rows, dtype)
    assert np.all(np.isfinite(D)) and np.all(np.isfinite(A))
    for k, g in enumerate(grads):
        assert np.all(np.isfinite(np.asarray(g))), k
    assert np.all(D >= -1e-5 * A / (np.pi * _alpha(rows)) - 1e-30)
    zero = np.array([r[4] <= 0 or np.all(r[2] == r[3]) for r in rows])
    assert np.all(D[zero] == 0) and np.all(A[zero] == 0)


# ---------------------------------------------------------------------------------------------
# The shallow cut: the arc and the paper's profile of width 4R and the same half-width a
# coincide to third order (wall angles asin(x/R) and 2 atan(x / 2R) differ by x^3 / 4R^3), so
# the two kernels agree to O((a/R)^3) = O(rho^1.5).


@pytest.mark.float64
def test_shallow_cut_approaches_the_paper_profile():
    cases = [c for c in _generic(40) if c[6] > 0.05][:8]
    paper = jax.jit(jax.vmap(ndf.pair_integral))
    errs = {}
    for rho in (1e-2, 1e-4):
        arcs = [(h, fp, p0, p1, rho * r, r, alpha) for h, fp, p0, p1, _, r, alpha in cases]
        D1, A1 = _run(arcs, np.float64)
        a = np.array([float(arc.arc_half_width(c[4], c[5])) for c in arcs])
        w = 4 * np.array([c[5] for c in arcs])
        d = -(w / 2) * np.log1p(-4 * a * a / (w * w))  # the paper groove of half-width a
        np.testing.assert_allclose(np.asarray(ndf.groove_half_width(w, d)), a, rtol=1e-12)
        args = _stack(arcs, np.float64)
        D2, A2 = (np.asarray(t) for t in paper(*args[:4], w, d, args[6]))
        np.testing.assert_allclose(A1, A2, rtol=1e-9, atol=1e-18)
        errs[rho] = float(np.max(np.abs(D1 - D2) / (A1 / (np.pi * _alpha(arcs)) + 1e-300)))
    assert errs[1e-2] < 1e-2 and errs[1e-4] < 1e-5, errs
    assert errs[1e-4] < errs[1e-2] / 300, errs  # O(rho^1.5): 1000x for 100x shallower


# ---------------------------------------------------------------------------------------------
# Building blocks.


@pytest.mark.float64
def test_building_blocks():
    p = 0.4 * R
    a = float(arc.arc_half_width(p, R))
    assert a == pytest.approx(np.sqrt(2 * R * p - p * p), rel=1e-14)
    assert float(arc.arc_height(0.0, p, R)) == pytest.approx(-p, rel=1e-12)
    assert abs(float(arc.arc_height(a * (1 - 1e-9), p, R))) < 1e-12
    assert float(arc.arc_height(1.5 * a, p, R)) == 0.0
    x = np.linspace(-0.9 * a, 0.9 * a, 9)
    n = np.asarray(arc.arc_normal(x, R))
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-14)
    eps = 1e-12
    slope = (np.asarray(arc.arc_height(x + eps, p, R))
             - np.asarray(arc.arc_height(x - eps, p, R))) / (2 * eps)
    np.testing.assert_allclose(n[:, 0] + n[:, 2] * slope, 0.0, atol=1e-5)
    # The identity the kernel rests on: the arc's normal at v = x / R is the paper's normal at
    # u = tan(theta / 2) / 2 (width 1), and v(u) = 4u / (1 + 4u^2) inverts u(v).
    v = x / R
    u = np.asarray(arc.u_of_v(v))
    np.testing.assert_allclose(np.asarray(ndf.normal(u, 1.0)), n, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(np.asarray(arc.v_of_u(u)), v, rtol=1e-14)
    V, U = (float(t) for t in arc.groove_coordinates(p, R))
    assert V == pytest.approx(a / R, rel=1e-14)
    assert U == pytest.approx(float(arc.u_of_v(V)), rel=1e-13)
    assert float(arc.groove_coordinates(R, R)[1]) == 0.5
    hl = np.array([0.2, 0.1, 0.9]) / np.linalg.norm([0.2, 0.1, 0.9])
    np.testing.assert_allclose(np.asarray(arc.arc_point_ndf(hl, x, R, 0.3)),
                               np.asarray(ndf.ggx(n @ hl, 0.3)), rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# The per-view stage and the native kernel's ``profile="arc"`` (docs/model.md §12, §13).


def _geometry_views(cases, dtype):
    """Per case: `arc_lit_integral` on the geometry of `arc_groove`, vmapped."""
    def one(h, fp, p0, p1, p, r, a):
        G = ndf.pair_geometry(fp, p0, p1, *arc.arc_groove(p, r))
        return arc.arc_lit_integral(G, h, a), G.area

    return jax.jit(jax.vmap(one))(*(jnp.asarray(x) for x in _stack(cases, dtype)))


@pytest.mark.float64
def test_lit_integral_on_the_arc_groove_is_the_pair_integral():
    """`arc_lit_integral(pair_geometry(..., *arc_groove(p, R)), h, alpha)` is
    `arc_pair_integral`'s value (and `A` its area), and its width is 2R."""
    cases, _ = _population()
    D, A = (np.asarray(t) for t in _geometry_views(cases, np.float64))
    D0, A0 = _run(cases, np.float64)
    np.testing.assert_array_equal(A, A0)
    np.testing.assert_allclose(D, D0, rtol=1e-14, atol=1e-300)
    w, d = arc.arc_groove(0.3 * R, R)
    assert float(w) == 2 * R
    a = float(arc.arc_half_width(0.3 * R, R))
    assert float(ndf.groove_half_width(w, d)) == pytest.approx(a, rel=1e-14)


@functools.lru_cache(maxsize=None)
def _lit_grad_fn(hand_vjp, pieces):
    def lit(h, fp, p0, p1, p, r, a):
        G = ndf.pair_geometry(fp, p0, p1, *arc.arc_groove(p, r))
        return arc._lit_integral(G, h, a, pieces, hand_vjp)

    return jax.jit(jax.vmap(jax.value_and_grad(lit, argnums=tuple(range(7)))))


def _lit_grads(cases, dtype, hand_vjp, pieces=ndf.N_PIECES):
    """Per case: the value and gradients (every input) of `arc_lit_integral(..., pieces=)` on
    the geometry of `arc_groove`, its per-view stage differentiated by hand or by plain
    autodiff."""
    D, g = _lit_grad_fn(hand_vjp, pieces)(*(jnp.asarray(x) for x in _stack(cases, dtype)))
    return np.asarray(D, np.float64), [np.asarray(x, np.float64).reshape(len(cases), -1) for x in g]


@pytest.mark.float64
def test_piece_budget_is_exact_where_the_count_fits():
    """`arc_lit_integral(..., pieces=k)` (what a render's chunk runs: the first k pieces that are
    not points) gives the value of all `ndf.N_PIECES` (summed in two groups of three) and the
    same gradient with respect to every input, to rounding, on the cases whose geometry has at
    most k pieces (and another value on some of those with more)."""
    cases, _ = _population()

    def counts(h, fp, p0, p1, p, r, a):
        return ndf.pair_geometry(fp, p0, p1, *arc.arc_groove(p, r)).count

    count = np.asarray(jax.vmap(counts)(*(jnp.asarray(x) for x in _stack(cases, np.float64))))
    D6, g6 = _lit_grads(cases, np.float64, True)
    for k in (2, ndf.N_COMPACT):
        fits = count <= k
        assert fits.sum() >= len(cases) // 2 and (k == ndf.N_COMPACT or not fits.all())
        Dk, gk = _lit_grads(cases, np.float64, True, k)
        np.testing.assert_allclose(Dk[fits], D6[fits], rtol=1e-15, atol=0)
        # (and the budget is used: where more pieces are lit, fewer integrate less)
        assert k == ndf.N_COMPACT or np.any(Dk[~fits] != D6[~fits])
        for a, b in zip(gk, g6):
            a, b = a[fits], b[fits]
            assert np.all(np.isfinite(a))
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13 * np.abs(b).max())


@pytest.mark.float64
def test_hand_written_partials_match_autodiff():
    """The jnp per-view stage's hand-written reverse pass (`_piece_partials`, the cut's
    transpose) against plain autodiff of the same forward, every family: float64 within 1e-11 of
    each input's gradient scale over the population; float32, against that float64 reference,
    as accurate as float32 autodiff (99th percentile of the error within 2x, worst within 3x, of
    each gradient's scale)."""
    cases, _ = _population()
    D, ref = _lit_grads(cases, np.float64, False)
    D_h, got = _lit_grads(cases, np.float64, True)
    np.testing.assert_allclose(D_h, D, rtol=1e-13, atol=1e-14 * np.max(np.abs(D)))
    for g, r in zip(got, ref):
        assert np.all(np.isfinite(g))
        assert np.max(np.abs(g - r)) <= 1e-11 * np.max(np.abs(r)) + 1e-300
    _, auto32 = _lit_grads(cases, np.float32, False)
    _, hand32 = _lit_grads(cases, np.float32, True)
    for h, a, r in zip(hand32, auto32, ref):
        scale = np.max(np.abs(r)) + 1e-300
        e_h, e_a = np.abs(h - r) / scale, np.abs(a - r) / scale
        assert np.percentile(e_h, 99) <= 2 * np.percentile(e_a, 99) + 1e-7
        assert e_h.max() <= 3 * e_a.max() + 1e-7, (e_h.max(), e_a.max())


def _native_inputs(rows, dtype):
    """`native.pair_values`' arguments (one view) for rows of `(h, fp, p0, p1, p, R, alpha)`."""
    h, fp, p0, p1, p, r, a = (np.asarray(x, np.float64) for x in _stack(rows, np.float64))
    rho = np.minimum(np.clip(np.where(r > 0, p / r, 0), 0, 1), arc._RHO_CAP)
    w, d = 2 * r, -2 * r * np.log1p(-rho)  # `arc.arc_groove`
    cast = lambda x: jnp.asarray(x, dtype)
    return (cast(fp), cast(p0), cast(p1), cast(w), cast(d), cast(a),
            jnp.ones(len(rows), bool), cast(h[None]))


@pytest.mark.float64
@pytest.mark.parametrize("dtype, rel, floor",
                         [(np.float64, 1e-11, 1e-13), (np.float32, 1e-3, 1e-5)])
def test_native_kernel_matches_the_reference(dtype, rel, floor):
    """`native.pair_values(..., profile="arc")` against the mpmath reference, with the jnp
    kernel's tolerance (`test_values_match_the_reference`)."""
    from jscratch import native

    if not native.available(jnp.float32):
        pytest.skip(f"native kernel unavailable: {native.status()['why']}")
    jax.config.update("jax_enable_x64", True)
    cases, names = _population()
    D, A = native.pair_values(arc.nodes(dtype), *_native_inputs(cases, dtype), profile="arc")
    D, A = np.asarray(D[0], np.float64), np.asarray(A, np.float64)
    Dr, Ar = _reference()
    tol = rel * np.abs(Dr) + floor * Ar / (np.pi * _alpha(cases)) + 1e-300
    err = np.abs(D - Dr) / tol
    assert np.all(err <= 1), {n: float(np.max(err[names == n])) for n in FAMILIES}


def test_native_kernel_finite_over_extreme_ranges():
    """The stability sweep (`_sweep`, float32) through `native.pair_vjp(..., profile="arc")`:
    no non-finite value or gradient; zero plunge and zero length give exact zeros."""
    from jscratch import native

    if not native.available(jnp.float32):
        pytest.skip(f"native kernel unavailable: {native.status()['why']}")
    rows = _sweep(4096, 7)
    args = _native_inputs(rows, jnp.float32)
    ng = arc.nodes(jnp.float32)
    D, A = native.pair_values(ng, *args, profile="arc")
    ct = (jnp.ones(D.shape, jnp.float32), jnp.ones(A.shape, jnp.float32))
    grads = native.pair_vjp(ng, *args, *ct, profile="arc")
    for x in (D, A, *grads):
        assert np.all(np.isfinite(np.asarray(x)))
    D, A = np.asarray(D[0], np.float64), np.asarray(A, np.float64)
    assert np.all(D >= -1e-5 * A / (np.pi * _alpha(rows)) - 1e-30)
    zero = np.array([r[4] <= 0 or np.all(r[2] == r[3]) for r in rows])
    assert np.all(D[zero] == 0) and np.all(A[zero] == 0)
