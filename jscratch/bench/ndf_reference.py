"""Independent high-precision reference for the scratch pair integral (docs/model.md §1-§3).

Written without the closed form: for one pixel footprint and one scratch it

1. moves the footprint into the scratch-local frame (docs/model.md §1) in `mpmath` arithmetic,
2. clips it to the groove box `x in [-x_max, x_max]`, `y in [0, |p1 - p0|]` (Sutherland-Hodgman,
   exact up to the working precision),
3. writes the clipped polygon's vertical section length `chord(x)` (piecewise linear between the
   vertices' x coordinates), and
4. integrates `D_hat = ∫ chord(x) D_x(x) dx` with `mpmath.quad` (tanh-sinh) on subintervals split at
   every vertex x, at the `chi+` roots of `N(u) = hz (1 - 4u^2) - 4 hx u` (outside of which the
   integrand is zero and is not integrated), and at the GGX peak `u*` plus/minus geometric multiples
   of the lobe width.

`A` is the shoelace area of the clipped polygon. `h` is normalised exactly (mpf) before use: `D_x`
depends on its direction only (see `_pair_setup`). All inputs are read as exact binary floats (float32 inputs are promoted to
float64 exactly), so the reference for float32 inputs is the exact integral at the rounded inputs.

**Public API:**

- `reference_pair(h, footprint, p0, p1, width, depth, alpha) -> (D_hat, A)`: python floats, m^2.
- `reference_batch(cases) -> (D_hat, A)`: numpy float64 arrays for a `ndf_cases.Cases` batch.
- `clipped_polygon(footprint, p0, p1, width, depth)`: local-frame vertices of `F ∩ groove` (mpf).
- `groove_half_width(width, depth)`, `point_ndf(u, h_local, alpha)`: mpf building blocks.
"""

from __future__ import annotations

import math

import mpmath
import numpy as np

from jscratch.errors import InputError

DPS = 30

mp = mpmath.mp


def _mpf(v):
    # float(...) of a numpy float32/float64 scalar is exact; mpf of a python float is exact.
    return mpmath.mpf(float(v))


def groove_half_width(width, depth):
    """`x_max = (w/2) sqrt(1 - exp(-2d/w))` (docs/model.md §2), metres, as an mpf."""
    w = _mpf(width) if not isinstance(width, mpmath.mpf) else width
    d = _mpf(depth) if not isinstance(depth, mpmath.mpf) else depth
    return (w / 2) * mpmath.sqrt(-mpmath.expm1(-2 * d / w))


def local_frame(p0, p1):
    """Scratch frame: returns `(p0, t, b, L)` with mpf entries; `t, b` are None when `p0 == p1`."""
    p0m = [_mpf(p0[0]), _mpf(p0[1])]
    p1m = [_mpf(p1[0]), _mpf(p1[1])]
    dx, dy = p1m[0] - p0m[0], p1m[1] - p0m[1]
    L = mpmath.sqrt(dx * dx + dy * dy)
    if L == 0:
        return p0m, None, None, L
    t = (dx / L, dy / L)
    b = (t[1], -t[0])
    return p0m, t, b, L


def _clip_halfplane(poly, inside, intersect):
    out = []
    n = len(poly)
    for i in range(n):
        P = poly[i]
        Q = poly[(i + 1) % n]
        pin, qin = inside(P), inside(Q)
        if pin:
            out.append(P)
            if not qin:
                out.append(intersect(P, Q))
        elif qin:
            out.append(intersect(P, Q))
    return out


def _cut_x(c):
    def f(P, Q):
        s = (c - P[0]) / (Q[0] - P[0])
        return (c, P[1] + s * (Q[1] - P[1]))

    return f


def _cut_y(c):
    def f(P, Q):
        s = (c - P[1]) / (Q[1] - P[1])
        return (P[0] + s * (Q[0] - P[0]), c)

    return f


def clip_to_box(poly, x_lo, x_hi, y_lo, y_hi):
    """Sutherland-Hodgman clip of a convex polygon (list of (x, y) mpf) to a closed box."""
    for inside, cut in (
        (lambda P: P[0] >= x_lo, _cut_x(x_lo)),
        (lambda P: P[0] <= x_hi, _cut_x(x_hi)),
        (lambda P: P[1] >= y_lo, _cut_y(y_lo)),
        (lambda P: P[1] <= y_hi, _cut_y(y_hi)),
    ):
        if not poly:
            return []
        poly = _clip_halfplane(poly, inside, cut)
    return poly


def clipped_polygon(footprint, p0, p1, width, depth):
    """Local-frame vertices (list of (x, y) mpf) of `footprint ∩ groove`; [] if the scratch has
    zero length or they do not meet."""
    with mp.workdps(DPS):
        p0m, t, b, L = local_frame(p0, p1)
        if t is None:
            return []
        poly = []
        for q in np.asarray(footprint, dtype=np.float64):
            rx, ry = _mpf(q[0]) - p0m[0], _mpf(q[1]) - p0m[1]
            poly.append((rx * b[0] + ry * b[1], rx * t[0] + ry * t[1]))
        xm = groove_half_width(width, depth)
        return clip_to_box(poly, -xm, xm, mpmath.mpf(0), L)


def polygon_area(poly):
    """Shoelace area (absolute value) of a polygon given as a list of (x, y)."""
    n = len(poly)
    s = mpmath.mpf(0)
    for i in range(n):
        P, Q = poly[i], poly[(i + 1) % n]
        s += P[0] * Q[1] - Q[0] * P[1]
    return abs(s) / 2


def section(poly, x):
    """Length of the vertical section of a convex polygon at abscissa `x`."""
    ys = []
    n = len(poly)
    for i in range(n):
        P, Q = poly[i], poly[(i + 1) % n]
        lo, hi = min(P[0], Q[0]), max(P[0], Q[0])
        if not (lo <= x <= hi):
            continue
        if P[0] == Q[0]:
            ys += [P[1], Q[1]]
        else:
            ys.append(P[1] + (x - P[0]) * (Q[1] - P[1]) / (Q[0] - P[0]))
    if not ys:
        return mpmath.mpf(0)
    return max(ys) - min(ys)


def point_ndf(u, hx, hy, hz, alpha):
    """`D_x` of docs/model.md §3 at `u = x/w` for local half vector components (mpf), with chi+."""
    B = 1 + 4 * u * u
    N = hz * (1 - 4 * u * u) - 4 * hx * u
    if N <= 0:
        return mpmath.mpf(0)
    c = N / B
    a2 = alpha * alpha
    den = c * c * (a2 - 1) + 1
    return a2 / (mpmath.pi * den * den)


def _positive_interval(hx, hz):
    """The u-interval where N(u) > 0 (hz > 0: between the two real roots)."""
    r = mpmath.sqrt(hx * hx + hz * hz)
    # Roots of 4 hz u^2 + 4 hx u - hz = 0, written without cancellation.
    if hx >= 0:
        u_lo = -(hx + r) / (2 * hz)
        u_hi = hz / (2 * (hx + r))
    else:
        u_hi = (r - hx) / (2 * hz)
        u_lo = -hz / (2 * (r - hx))
    return u_lo, u_hi


def _peak(hx, hy, hz, alpha):
    """GGX peak `u*` (max of n(u).h: the normal angle phi = 2 atan(2u) equals -atan2(hx, hz)) and the
    lobe width in u."""
    theta = mpmath.atan2(hx, hz)
    u_star = -mpmath.tan(theta / 2) / 2
    rho2 = hx * hx + hz * hz
    k2 = 1 - alpha * alpha
    # Width in phi of 1/(1 - k^2 rho^2 cos^2) ~ sqrt(1 - k^2 rho^2); du/dphi = (1 + 4u^2)/4.
    s_phi = mpmath.sqrt(abs(1 - k2 * rho2)) + mpmath.mpf(10) ** (-DPS // 2)
    return u_star, s_phi * (1 + 4 * u_star * u_star) / 4


_MULTS = (0.5, 2.0, 8.0, 32.0, 128.0)


def _pair_setup(h, footprint, p0, p1, width, depth, alpha):
    """Everything exact (mpf) about one pair: clipped polygon, pieces, local h, peak, N>0 range."""
    poly = clipped_polygon(footprint, p0, p1, width, depth)
    if len(poly) < 3:
        return None
    A = polygon_area(poly)
    if A == 0:
        return None
    _, t, b, _ = local_frame(p0, p1)
    hv = [_mpf(v) for v in np.asarray(h, dtype=np.float64)]
    # D_x depends on the direction of h only. A float unit vector is unit only to rounding, and at
    # alpha = 1e-4 the peak height 1/(pi (alpha^2 + hy^2)) would depend on 1 - |h|^2 ~ 1e-16 (1e-7
    # in float32) to first order, so the reference fixes |h| = 1 exactly.
    hn = mpmath.sqrt(hv[0] ** 2 + hv[1] ** 2 + hv[2] ** 2)
    hv = [v / hn for v in hv]
    hx = hv[0] * b[0] + hv[1] * b[1]
    hy = hv[0] * t[0] + hv[1] * t[1]
    hz = hv[2]
    w = _mpf(width)
    al = _mpf(alpha)
    xs = sorted(set(P[0] for P in poly))
    pieces = []
    for xa, xb in zip(xs[:-1], xs[1:]):
        pieces.append((xa, xb, section(poly, xa), section(poly, xb)))
    u_lo, u_hi = _positive_interval(hx, hz)
    u_star, s_u = _peak(hx, hy, hz, al)
    peak_pts = [u_star * w]
    for m in _MULTS:
        peak_pts += [(u_star - m * s_u) * w, (u_star + m * s_u) * w]
    return dict(
        poly=poly, A=A, hx=hx, hy=hy, hz=hz, w=w, alpha=al, pieces=pieces,
        x_lo=u_lo * w, x_hi=u_hi * w, peak_pts=sorted(peak_pts),
    )


def _integrate_mpmath(S):
    """`∫ chord D_x dx` in mpf with the GGX written directly as in docs/model.md §3."""
    total = mpmath.mpf(0)
    hx, hy, hz, w, al = S["hx"], S["hy"], S["hz"], S["w"], S["alpha"]
    for xa, xb, ca, cb in S["pieces"]:
        a, bnd = max(xa, S["x_lo"]), min(xb, S["x_hi"])
        if not a < bnd:
            continue
        slope = (cb - ca) / (xb - xa)

        def f(x, xa=xa, ca=ca, slope=slope):
            return (ca + slope * (x - xa)) * point_ndf(x / w, hx, hy, hz, al)

        pts = [a] + [p for p in S["peak_pts"] if a < p < bnd] + [bnd]
        total += mpmath.quad(f, pts)
    return total


def _integrate_scipy(S):
    """`∫ chord D_x dx` by adaptive Gauss-Kronrod (QUADPACK) in float64, with the GGX written in
    the normal angle so that float64 keeps full relative accuracy at the peak: `phi = 2 atan(2u)`,
    `n.h = rho cos(phi - phi*)`, `1 - k^2 (n.h)^2 = E + K sin^2(phi - phi*)` with `E = 1 - k^2 rho^2`
    and `K = k^2 rho^2` taken from the exact (mpf) inputs."""
    from scipy.integrate import quad

    hx, hz, w, al = S["hx"], S["hz"], S["w"], S["alpha"]
    rho2 = hx * hx + hz * hz
    k2 = 1 - al * al
    E = float(1 - k2 * rho2)
    K = float(k2 * rho2)
    phi_star = float(mpmath.atan2(-hx, hz))
    c0 = float(al * al / mpmath.pi)
    wf = float(w)
    atan, sin = math.atan, math.sin
    total = 0.0
    for xa, xb, ca, cb in S["pieces"]:
        a, bnd = max(xa, S["x_lo"]), min(xb, S["x_hi"])
        if not a < bnd:
            continue
        # chord as a + slope*(x - mid) about the subinterval midpoint, all in float64.
        xm = (a + bnd) / 2
        cm = ca + (cb - ca) * (xm - xa) / (xb - xa)
        slope = float((cb - ca) / (xb - xa))
        cmf, xmf = float(cm), float(xm)

        def f(x):
            dphi = 2 * atan(2 * x / wf) - phi_star
            s = sin(dphi)
            den = E + K * s * s
            return (cmf + slope * (x - xmf)) * c0 / (den * den)

        pts = [float(a)] + [float(p) for p in S["peak_pts"] if a < p < bnd] + [float(bnd)]
        for lo, hi in zip(pts[:-1], pts[1:]):
            if hi > lo:
                val, _ = quad(f, lo, hi, epsabs=0.0, epsrel=1e-13, limit=200)
                total += val
    return total


def reference_pair(h, footprint, p0, p1, width, depth, alpha, *, method="scipy"):
    """Reference `(D_hat, A)` (python floats, m^2) for one pair; arguments as in
    `jscratch.ndf.pair_integral` (numpy arrays or floats, any float dtype).

    `method="scipy"` (default, ~1 ms) integrates in float64 with QUADPACK (relative error ~1e-13);
    `method="mpmath"` (~50 ms) integrates at 30 digits; geometry is mpf in both."""
    with mp.workdps(DPS):
        S = _pair_setup(h, footprint, p0, p1, width, depth, alpha)
        if S is None:
            return 0.0, 0.0
        if method == "mpmath":
            D = float(_integrate_mpmath(S))
        elif method == "scipy":
            D = _integrate_scipy(S)
        else:
            raise InputError(f"method must be 'scipy' or 'mpmath', got {method!r}")
        return D, float(S["A"])


def chord_area(footprint, p0, p1, width, depth):
    """`∫ chord(x) dx` of the clipped polygon (must equal its area): a check of the pieces."""
    with mp.workdps(DPS):
        S = _pair_setup(np.array([0.0, 0.0, 1.0]), footprint, p0, p1, width, depth, 0.5)
        if S is None:
            return 0.0
        return float(sum((ca + cb) * (xb - xa) / 2 for xa, xb, ca, cb in S["pieces"]))


def reference_batch(cases, method="scipy"):
    """Reference values for every pair of a `Cases` batch -> `(D_hat, A)` float64 arrays `(n,)`."""
    n = cases.h.shape[0]
    D = np.empty(n)
    A = np.empty(n)
    for i in range(n):
        D[i], A[i] = reference_pair(
            cases.h[i],
            cases.footprint[i],
            cases.p0[i],
            cases.p1[i],
            cases.width[i],
            cases.depth[i],
            cases.alpha[i],
            method=method,
        )
    return D, A


def reference_area(footprint, p0, p1, width, depth):
    """Exact (working-precision) area of `footprint ∩ groove`, python float, m^2."""
    with mp.workdps(DPS):
        poly = clipped_polygon(footprint, p0, p1, width, depth)
        if len(poly) < 3:
            return 0.0
        return float(polygon_area(poly))
