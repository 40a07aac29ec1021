"""The circular-arc (ball-cutter) groove: its profile, normal and pair integral (docs/model.md §13).

A ball-end cutter of radius ``R`` plunged to depth ``p`` cuts the groove

    z(x) = R - p - sqrt(R^2 - x^2),   |x| < a = sqrt(2 R p - p^2),

whose wall angle is ``theta(x) = asin(x / R)``. For one pixel footprint ``F`` and one such
scratch under a half vector ``h`` the kernel returns, as `jscratch.ndf.pair_integral` does for the
paper's profile,

    D_hat = ∫∫_{F ∩ groove} D_x(h, n(x)) dx dy   (m^2),   A = area(F ∩ groove)   (m^2).

**Public API:**

- `arc_pair_integral(h, footprint, p0, p1, plunge, radius, alpha) -> (D_hat, A)`: pure,
  jittable, vmappable, reverse-mode differentiable in every float argument (`plunge` and
  `radius` included), float32 and float64 (it follows the dtype of its inputs).
- `arc_groove(plunge, radius) -> (width, depth)` and `arc_lit_integral(geometry, h, alpha) ->
  D_hat`: the two stages of `arc_pair_integral` (``ndf.pair_geometry(footprint, p0, p1,
  *arc_groove(plunge, radius))``, then one view's integral on it); the native kernel's
  ``profile="arc"`` (`jscratch.native.pairs`) evaluates the same and its gradients.
- Building blocks: `arc_height`, `arc_half_width` (``a``), `arc_normal`, `arc_point_ndf`,
  `groove_coordinates` (``V = a / R`` and ``U``, below), `u_of_v`, `v_of_u`.

**How it works** (derived in docs/model.md §13). With ``v = x / R = sin(theta)`` and
``u = tan(theta / 2) / 2`` the normal is the paper's normal at ``u`` (`jscratch.ndf.normal` with
``x / w = u``), so the GGX of the normal is the same rational function of ``u`` as in
`jscratch.lobe` (``D = pref (F1 + F2)``, ``F1 = T1^2 + T1`` the sharp lobe, ``F2 = T2^2 + T2`` the
smooth one). The groove is ``|u| <= U = sqrt(rho / (2 - rho)) / 2`` (``rho = p / R``; ``U <= 1/2``),
and ``v = 4u / (1 + 4u^2)``. Green's theorem in ``v`` (docs/model.md §3) gives
``D_hat = -R ∮ Y(v) D~ dv``; the boundary pieces of ``F ∩ groove`` are `jscratch.ndf.pair_geometry`'s
(a paper groove of width ``2R`` and the depth whose half-width is ``a``: its pieces are in
``x / (2R) = v / 2``). Along a piece ``Y`` is linear in ``v``, and in ``u`` each piece integral is

    J = ∫ w(u) (F1 + F2) du,   w(u) = Y(v(u)) v'(u),   v'(u) = 4 (1 - 4u^2) / (1 + 4u^2)^2.

``F1 - c0 = P(s) / (1 + s^2)^2`` (``s = (u - u1) / q1``, ``P`` a cubic) has double poles at
``s = ±i``, a distance ``q1 ~ alpha / 4`` from the real axis. They are subtracted: the cubic
``H`` that matches ``Φ(s) = w(u) P(s)`` and ``Φ'`` at ``s = ±i`` (Hermite) has
``H / (1 + s^2)^2 = (α0 + α1 s) e^2 + (γ0 + γ1 s) e`` (``e = 1 / (1 + s^2)``), integrated in
closed form (``arctan``, ``log``, rational), and the remainder ``(Φ - H) / (1 + s^2)^2``, analytic
at ``s = ±i``, goes with ``w (c0 + F2)`` to an ``n``-point Gauss-Legendre rule in ``u``. Its
nearest singularities are ``w``'s poles ``u = ±i/2`` and ``F2``'s, so on any piece inside
``|u| <= 1/2`` the rule converges like ``ρ^(-2n)`` with a Bernstein ellipse ``ρ >= 1 + sqrt 2``
(error bound in docs/model.md §13). Where the sharp lobe is broad (``q1 >= Q_SUB``) or the piece is
short compared with its distance from the peak, nothing is subtracted: the rule integrates
``w (F1 + F2)`` directly (ellipse ``ρ >= 2``). ``n`` is `nodes` (8 in float32, 24 in float64).

Degenerate input (zero plunge, ``p >= R``, footprints that miss, edges parallel to the scratch,
ends on groove edges) gives finite values and gradients: divisions and square roots that can meet
zero go through guarded (double-``where``) forms. Reverse mode is written by hand: each piece's
partials with respect to its ends, their ``Y`` and the lobe parameters come from the same pass
over the nodes as its value (`_piece_partials`; the native kernel's formulas,
``jscratch/native/native_arc.h``, docs/model.md §13), the slab cut has `jscratch.ndf`'s
transpose, and autodiff chains the rest (the ends' map to ``u``, the slab, the lobe). Forward
mode (`jax.jvp`) is not available. A view integrates at most three pieces at a time (the first
pieces that are not points, or all six in two groups: XLA's CPU code for six at once was several
times slower).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jscratch import lobe, ndf
from jscratch.errors import InputError

__all__ = [
    "arc_pair_integral",
    "arc_lit_integral",
    "arc_groove",
    "pair_integral_of",
    "arc_height",
    "arc_half_width",
    "arc_normal",
    "arc_point_ndf",
    "groove_coordinates",
    "u_of_v",
    "v_of_u",
    "nodes",
    "Q_SUB",
]

#: Sharp-lobe half-width (in ``u``) below which its poles are subtracted: above it they lie at
#: least this far from the real axis and the plain rule converges (ellipse ``ρ >= 2``); below it
#: ``|1 + 4 z^2| >= 1 - 4 Q_SUB^2`` at the pole ``z = u1 + i q1`` keeps the subtraction's
#: coefficients of the size of the weight.
Q_SUB = 0.375
#: ``rho = p / R`` is capped below 1 only where it sets `jscratch.ndf.pair_geometry`'s depth
#: (``-2R log(1 - rho)``, infinite at 1); the half-width differs from ``R`` by ``R 2^-41``.
_RHO_CAP = 1 - 2.0**-20


def nodes(dtype) -> int:
    """Gauss-Legendre nodes per boundary piece: 8 in float32, 24 in float64 (docs/model.md §13;
    the native kernel uses half as many on pieces far from every pole)."""
    return 8 if dtype == jnp.float32 else 24


def _safe_sqrt(x):
    """sqrt with a finite gradient at 0 (where it returns 0 and gradient 0)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1)), 0)


def _safe_div(a, b):
    """`a / b`, 0 where `b == 0` (finite gradients)."""
    ok = b != 0
    return jnp.where(ok, a / jnp.where(ok, b, 1), 0)


def _rho(plunge, radius):
    return jnp.clip(_safe_div(plunge, radius), 0, 1)


def arc_half_width(plunge: ArrayLike, radius: ArrayLike) -> Array:
    """Half-width ``a = sqrt(2 R p - p^2)`` (m) of the groove a ball of radius `radius` cuts at
    plunge `plunge` (m); the plunge is taken in ``[0, R]`` (``a = R`` from ``p = R`` on)."""
    plunge, radius = jnp.asarray(plunge), jnp.asarray(radius)
    rho = _rho(plunge, radius)
    return radius * _safe_sqrt(rho * (2 - rho))


def groove_coordinates(plunge: ArrayLike, radius: ArrayLike):
    """``(V, U)``: the groove's half-width in ``v = x / R`` (``V = a / R``) and in
    ``u = tan(theta / 2) / 2`` (``U = sqrt(rho / (2 - rho)) / 2``, ``rho = p / R`` in [0, 1])."""
    rho = _rho(jnp.asarray(plunge), jnp.asarray(radius))
    return _safe_sqrt(rho * (2 - rho)), 0.5 * _safe_sqrt(rho / (2 - rho))


def arc_height(x: ArrayLike, plunge: ArrayLike, radius: ArrayLike) -> Array:
    """Groove height ``z(x) = R - p - sqrt(R^2 - x^2)`` (m, <= 0) at the across-scratch
    coordinate `x` (m, any shape), 0 outside the groove (``|x| >= a``)."""
    x, plunge, radius = jnp.asarray(x), jnp.asarray(plunge), jnp.asarray(radius)
    a = arc_half_width(plunge, radius)
    p = radius * _rho(plunge, radius)
    inside = jnp.abs(x) < a
    z = radius - p - _safe_sqrt(radius * radius - jnp.where(inside, x * x, 0))
    return jnp.where(inside, jnp.minimum(z, 0), 0)


def arc_normal(x: ArrayLike, radius: ArrayLike) -> Array:
    """Groove normal ``(-x/R, 0, sqrt(1 - x^2/R^2)) = (-sin theta, 0, cos theta)`` in the
    scratch-local frame, `(..., 3)` (``|x| <= R``)."""
    v = jnp.asarray(x) / jnp.asarray(radius)
    return jnp.stack([-v, jnp.zeros_like(v), _safe_sqrt((1 - v) * (1 + v))], axis=-1)


def arc_point_ndf(h_local: ArrayLike, x: ArrayLike, radius: ArrayLike,
                  alpha: ArrayLike) -> Array:
    """``D_x(h, n(x))`` on the arc: the GGX of `arc_normal` for the local half vector `h_local`
    (``(..., 3)``, normalised here), 1/sr."""
    h = jnp.asarray(h_local)
    h = h / jnp.linalg.norm(h, axis=-1, keepdims=True)
    return ndf.ggx(jnp.sum(arc_normal(x, radius) * h, axis=-1), alpha)


def v_of_u(u):
    """``v = sin(theta) = 4u / (1 + 4u^2)`` for ``u = tan(theta / 2) / 2`` (monotone on
    ``|u| <= 1/2``)."""
    return 4 * u / (1 + 4 * u * u)


def u_of_v(v):
    """The inverse of `v_of_u` on ``|v| <= 1``: ``u = v / (2 (1 + sqrt(1 - v^2)))``."""
    return v / (2 * (1 + _safe_sqrt((1 - v) * (1 + v))))


def _vdd(x, y):
    """Divided difference ``(v(x) - v(y)) / (x - y) = 4 (1 - 4xy) / ((1 + 4x^2)(1 + 4y^2))``
    (any dtype, complex included)."""
    return 4 * (1 - 4 * x * y) / ((1 + 4 * x * x) * (1 + 4 * y * y))


# ---------------------------------------------------------------------------------------------
# Piece integrals.


def _lobes(u, p):
    """``(F2, e, s)`` at `u`: the smooth lobe ``T2^2 + T2``, ``e = 1 / (1 + s^2)`` and ``s``."""
    c0, c10, c11, c20, c21, u1, q1, g, k, hx, hz = p
    B = 1 + 4 * u * u
    N = hz * (1 - 4 * u * u) - 4 * hx * u
    T2 = B / (B + k * N)
    s = (u - u1) / q1
    return T2 * T2 + T2, 1 / (1 + s * s), s


def _basis(sa, ds, ea, eb):
    """``(∫ e, ∫ s e, ∫ e^2, ∫ s e^2)`` over ``s in [sa, sa + ds]`` (``e = 1 / (1 + s^2)``;
    `ea`, `eb` its end values), written without cancellation for ``|ds| >= 1``: the ``arctan``
    difference as one ``atan2``, the ``log`` ratio as ``log1p`` of a non-negative argument."""
    sb = sa + ds
    I0 = jnp.arctan2(ds, 1 + sa * sb)
    ps = ds * (sa + sb)  # sb^2 - sa^2
    up = ps >= 0
    I1 = 0.5 * jnp.where(up, 1, -1) * jnp.log1p(jnp.where(up, ps * ea, -ps * eb))
    # ∫ e^2 = (atan s + s e) / 2 and ∫ s e^2 = -e / 2, differences taken in product form.
    K0 = 0.5 * I0 + 0.5 * (ds * ea) * ((1 - sa * sb) * eb)
    K1 = 0.5 * (ds * ea) * ((sa + sb) * eb)
    return I0, I1, K0, K1


def _subtracted(ua, du, u1, q1):
    """Where the sharp lobe's poles are subtracted (`sub`: a sharp lobe, and a piece long compared
    with its distance from the peak; elsewhere the poles ``s = ±i`` are far outside the piece's
    ellipse), and there the piece's ``ds = du / q1``, ``sa = (ua - u1) / q1``, ``q1`` and ``du``
    (safe values elsewhere): ``(sub, ds_s, sa_s, q1_s, du_s)``."""
    ds = du / q1
    sa = (ua - u1) / q1
    sm = sa + ds / 2
    sub = (q1 < Q_SUB) & (jnp.abs(ds) >= jnp.maximum(1, 0.5 * jnp.abs(sm)))
    return (sub, jnp.where(sub, ds, 1), jnp.where(sub, sa, 0), jnp.where(sub, q1, Q_SUB / 2),
            jnp.where(sub, du, 1))


def _piece_integrals(n_gl, ua, ub, Ya, Yb, p):
    """``J = ∫_{ua}^{ub} Y(v(u)) v'(u) (F1 + F2) du`` for each piece (`(6,)` arrays in ``u``,
    inside the lit slab; `Y` linear in ``v`` from `Ya` to `Yb`), lobe parameters `p`
    (`lobe.lobe_params`). Module docstring: subtraction of the sharp lobe's poles, closed form of
    the subtracted part, Gauss-Legendre on the rest."""
    c0, c10, c11, c20, c21, u1, q1, g, k, hx, hz = p
    du = ub - ua
    half = du / 2
    um = ua + half
    dY = Yb - Ya
    den = _vdd(ub, ua)  # (v(ub) - v(ua)) / du, > 0 unless the piece is the point u = ±1/2
    sub, ds_s, sa_s, q1_s, du_s = _subtracted(ua, du, u1, q1)
    den_s = jnp.where(sub & (den > 0), den, 1)

    # Hermite data of Φ(s) = w(u) P(s) at s = i, u = z = u1 + i q1 (complex arithmetic).
    cdt = jnp.result_type(du.dtype, jnp.complex64)
    z = jax.lax.complex(jnp.broadcast_to(u1, du.shape), jnp.broadcast_to(q1_s, du.shape))
    z = z.astype(cdt)
    Bz = 1 + 4 * z * z
    vp = 4 * (1 - 4 * z * z) / (Bz * Bz)
    vpp = -32 * z * (3 - 4 * z * z) / (Bz * Bz * Bz)
    dYdv = dY / (du_s * den_s)
    Yz = Ya + dYdv * ((z - ua) * _vdd(z, ua))
    wz = Yz * vp
    wpz = dYdv * vp * vp + Yz * vpp
    Pi = jax.lax.complex(c20, c21).astype(cdt)
    dPi = jax.lax.complex(c21 - 2 * c11, 2 * c10).astype(cdt)
    F = wz * Pi
    G = q1_s * wpz * Pi + wz * dPi
    # H's coefficients; zero where nothing is subtracted (the rest below is then w F1).
    al0, al1 = jnp.where(sub, jnp.real(F), 0), jnp.where(sub, jnp.imag(F), 0)
    ga0, ga1 = jnp.where(sub, jnp.imag(G) / 2, 0), jnp.where(sub, -(jnp.real(G) - al1) / 2, 0)
    # ∫ H e^2 ds over the piece in closed form: the basis integrals of `lobe` (e, s e, e^2, s e^2).
    sb_s = sa_s + ds_s
    ea = 1 / (1 + sa_s * sa_s)
    eb = 1 / (1 + sb_s * sb_s)
    I0, I1, K0, K1 = _basis(sa_s, ds_s, ea, eb)
    closed = q1_s * (al0 * K0 + al1 * K1 + ga0 * I0 + ga1 * I1)

    # Gauss-Legendre in u on the rest.
    xs, ws = lobe.gauss_legendre(n_gl)
    x = jnp.asarray(xs, du.dtype)
    wq = jnp.asarray(ws, du.dtype)
    uu = um[..., None] + half[..., None] * x
    tau = (1 + x) / 2
    # Y at the nodes: v(u) - v(ua) = (u - ua) v[u, ua] (no cancellation, no division by du).
    frac = jnp.where((den > 0)[..., None],
                     tau * _vdd(uu, ua[..., None]) / jnp.where(den > 0, den, 1)[..., None], tau)
    Yu = Ya[..., None] + dY[..., None] * frac
    B = 1 + 4 * uu * uu
    wu = Yu * 4 * (1 - 4 * uu * uu) / (B * B)
    F2, e, s = _lobes(uu, p)
    # The remainder (Φ - H) e^2 = (w P - H) e^2, written term by term of the basis (w (F1 - c0)
    # where nothing is subtracted).
    Rs = ((wu * c10 - ga0[..., None]) + (wu * c11 - ga1[..., None]) * s) * e + (
        (wu * c20 - al0[..., None]) + (wu * c21 - al1[..., None]) * s) * e * e
    gl = half * jnp.sum(wq * (wu * (c0 + F2) + Rs), axis=-1)
    return gl + jnp.where(sub, closed, 0)


def _piece_partials(n_gl, ua, ub, Ya, Yb, p):
    """The partial derivatives of each piece's `_piece_integrals` with respect to its ends
    ``ua, ub``, their ``Ya, Yb`` and the lobe parameters `p` (each ``(k,)``, the pieces' shape),
    by hand (module docstring; the native kernel's formulas, ``native_arc.h``); zero for a point
    (``ua == ub``, ``Ya == Yb``), whose two ends move together."""
    c0, c10, c11, c20, c21, u1, q1, g, k, hx, hz = p
    dt = ua.dtype
    du = ub - ua
    half = du / 2
    um = ua + half
    dY = Yb - Ya
    den = _vdd(ub, ua)
    denp = den > 0
    den1 = jnp.where(denp, den, 1)
    dYden = dY / den1
    sub, ds_s, sa_s, q1_s, du_s = _subtracted(ua, du, u1, q1)
    idu = 1 / du_s
    dYdv = dYden * idu
    cdt = jnp.result_type(dt, jnp.complex64)
    z = jax.lax.complex(jnp.broadcast_to(u1, du.shape),
                        jnp.broadcast_to(q1_s, du.shape)).astype(cdt)
    z2 = z * z
    iB = 1 / (1 + 4 * z2)
    iB2 = iB * iB
    vp = 4 * (1 - 4 * z2) * iB2
    vpp = -32 * z * (3 - 4 * z2) * iB2 * iB
    Ba = 1 + 4 * ua * ua
    muz = idu * (z - ua) * (4 / Ba) * (1 - 4 * ua * z) * iB
    Yz = Ya + dYden * muz
    wz = Yz * vp
    wpz = dYdv * vp * vp + Yz * vpp
    Pi = jax.lax.complex(c20, c21).astype(cdt)
    dPi = jax.lax.complex(c21 - 2 * c11, 2 * c10).astype(cdt)
    zero = jnp.zeros_like(du)

    def coef(F, G):
        return (jnp.where(sub, jnp.real(F), zero), jnp.where(sub, jnp.imag(F), zero),
                jnp.where(sub, jnp.imag(G) / 2, zero),
                jnp.where(sub, -(jnp.real(G) - jnp.imag(F)) / 2, zero))

    h = coef(wz * Pi, q1_s * wpz * Pi + wz * dPi)
    sb_s = sa_s + ds_s
    ea = 1 / (1 + sa_s * sa_s)
    eb = 1 / (1 + sb_s * sb_s)
    I0, I1, K0, K1 = _basis(sa_s, ds_s, ea, eb)

    def closed(a):
        return q1_s * (a[0] * K0 + a[1] * K1 + a[2] * I0 + a[3] * I1)

    # The rule's sums over the nodes (one pass: the value's terms and every partial's).
    xs, ws = lobe.gauss_legendre(n_gl)
    x = jnp.asarray(xs, dt)
    w = jnp.asarray(ws, dt)

    def E(v):  # a per-piece value against the node axis
        return v[..., None]

    tau = (1 + x) / 2
    uu = E(um) + E(half) * x
    u2 = uu * uu
    B = 1 + 4 * u2
    iBu = 1 / B
    m4u2 = 1 - 4 * u2
    vpj = 4 * m4u2 * iBu * iBu
    mu = jnp.where(E(denp), tau * (4 * (1 - 4 * uu * E(ua)) * iBu / E(Ba)), tau)
    wu = (E(Ya) + E(dYden) * mu) * vpj
    N = hz * m4u2 - 4 * hx * uu
    inv2 = 1 / (B + k * N)
    T2 = B * inv2
    F2 = T2 * T2 + T2
    s = (uu - u1) / q1
    e = 1 / (1 + s * s)
    se, ee = s * e, e * e
    see, eee = se * e, ee * e
    seee = see * e
    A0, A1 = wu * c10 - E(h[2]), wu * c11 - E(h[3])
    B0, B1 = wu * c20 - E(h[0]), wu * c21 - E(h[1])
    Dt = c0 + F2 + c10 * e + c11 * se + c20 * ee + c21 * see
    Rp = B1 * (4 * eee - 3 * ee) - 4 * B0 * seee + A1 * (2 * ee - e) - 2 * A0 * see
    ww, wv = w * wu, w * vpj
    def S(v):  # the rule's sum over the nodes
        return jnp.sum(v, axis=-1)

    S_vD, S_mD = S(wv * Dt), S(wv * mu * Dt)
    S_w, S_we, S_wse, S_wee, S_wsee = S(ww), S(ww * e), S(ww * se), S(ww * ee), S(ww * see)
    S_Rp, S_sRp = S(w * Rp), S(w * s * Rp)
    S_e, S_se, S_ee, S_see = S(w * e), S(w * se), S(w * ee), S(w * see)
    f = ww * (-(2 * T2 + 1) * T2 * inv2)
    S_k, S_hx, S_hz = S(f * N), S(f * (-4 * k * uu)), S(f * (k * m4u2))

    def hsum(a):
        return a[2] * S_e + a[3] * S_se + a[0] * S_ee + a[1] * S_see

    def lfull(F, G):
        a = coef(F, G)
        return closed(a) - half * hsum(a)

    I = 1j  # noqa: E741
    F1, G1 = vp * Pi, q1_s * vpp * Pi + vp * dPi
    wm, wmp = muz * vp, idu * vp * vp + muz * vpp
    Fm, Gm = wm * Pi, q1_s * wmp * Pi + wm * dPi
    a1, am = coef(F1, G1), coef(Fm, Gm)
    J1 = closed(a1) - half * hsum(a1) + half * S_vD
    Jm = closed(am) - half * hsum(am) + half * S_mD
    M1 = jnp.where(sub, closed(a1) * idu, 0) + (S_vD - hsum(a1)) / 2
    Mm = jnp.where(sub, closed(am) * idu, 0) + (S_mD - hsum(am)) / 2
    vppp = -96 * (1 - 24 * z2 + 16 * z2 * z2) * iB2 * iB2
    wppz = 3 * dYdv * vp * vpp + Yz * vppp
    eb2, ea2 = eb * eb, ea * ea
    kin_sa = q1_s * (h[0] * (eb2 - ea2) + h[1] * (sb_s * eb2 - sa_s * ea2) + h[2] * (eb - ea)
                     + h[3] * (sb_s * eb - sa_s * ea))
    kin_ds = q1_s * (h[0] * eb2 + h[1] * sb_s * eb2 + h[2] * eb + h[3] * sb_s * eb)
    dFu = wpz * Pi
    dGu = q1_s * wppz * Pi + wpz * dPi
    gu1 = lfull(dFu, dGu) + jnp.where(sub, -kin_sa / q1, 0) + half * (-S_Rp / q1)
    gq1 = (lfull(I * dFu, dFu + I * dGu)
           + jnp.where(sub, closed(h) / q1_s + (-sa_s * kin_sa - ds_s * kin_ds) / q1, 0)
           + half * (-S_sRp / q1))
    zc = jnp.zeros_like(wz)
    gc = (half * S_w,
          lfull(zc, 2 * I * wz) + half * S_we,
          lfull(zc, -2 * wz) + half * S_wse,
          lfull(wz, q1_s * wpz) + half * S_wee,
          lfull(I * wz, I * (q1_s * wpz) + wz) + half * S_wsee)
    gYb = Jm / den1
    gYa = J1 - gYb

    def at_end(u):
        Bu = 1 + 4 * u * u
        Nu = hz * (1 - 4 * u * u) - 4 * hx * u
        T = Bu / (Bu + k * Nu)
        su = (u - u1) / q1
        eu = 1 / (1 + su * su)
        D = c0 + T * T + T + c10 * eu + c11 * su * eu + c20 * eu * eu + c21 * su * eu * eu
        return D, 4 * (1 - 4 * u * u) / (Bu * Bu)

    Da, vpa = at_end(ua)
    Db, vpb = at_end(ub)
    gub = vpb * (Yb * Db - dYden * Mm / den1)
    gua = -vpa * (Ya * Da + dYden * (M1 - Mm / den1))
    point = (ua == ub) & (Ya == Yb)
    dp = (*gc, gu1, gq1, zero, half * S_k, half * S_hx, half * S_hz)
    return tuple(jnp.where(point, zero, d) for d in (gua, gub, gYa, gYb)) + (
        tuple(jnp.where(point, zero, d) for d in dp),)


def _sum_to(x, like):
    """`x` summed over the leading axes it has beyond `like`'s shape (a broadcast's transpose)."""
    like = jnp.asarray(like)
    return jnp.sum(x, axis=tuple(range(x.ndim - like.ndim))).reshape(like.shape)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _pieces(n_gl, ua, ub, Ya, Yb, p):
    """`_piece_integrals` with `_piece_partials` as its reverse pass."""
    return _piece_integrals(n_gl, ua, ub, Ya, Yb, p)


def _pieces_fwd(n_gl, ua, ub, Ya, Yb, p):
    d_ua, d_ub, d_Ya, d_Yb, d_p = _piece_partials(n_gl, ua, ub, Ya, Yb, p)
    return _piece_integrals(n_gl, ua, ub, Ya, Yb, p), (d_ua, d_ub, d_Ya, d_Yb, d_p, p)


def _pieces_bwd(n_gl, res, ct):
    d_ua, d_ub, d_Ya, d_Yb, d_p, p = res
    return (ct * d_ua, ct * d_ub, ct * d_Ya, ct * d_Yb,
            tuple(_sum_to(ct * d, q) for d, q in zip(d_p, p)))


_pieces.defvjp(_pieces_fwd, _pieces_bwd)


# ---------------------------------------------------------------------------------------------
# The pair integral.


def _as_inputs(*xs):
    dt = jnp.result_type(*[jnp.asarray(x) for x in xs], jnp.float32)
    return tuple(jnp.asarray(v, dt) for v in xs)


def arc_groove(plunge: ArrayLike, radius: ArrayLike) -> tuple[Array, Array]:
    """``(width, depth)`` (m) of the paper groove (`jscratch.ndf`) with the same half-width as the
    ball cutter's groove of radius `radius` at plunge `plunge` (m): ``(2R, -2R log(1 - rho))``,
    ``rho = p / R`` taken in ``[0, 1 - 2^-20]`` (docs/model.md §13). `ndf.pair_geometry` at these
    is the arc's geometry (its pieces in ``x / 2R = v / 2``), which `arc_lit_integral` and the
    native kernel's ``profile="arc"`` read."""
    plunge, radius = jnp.asarray(plunge), jnp.asarray(radius)
    rho = jnp.minimum(_rho(plunge, radius), _RHO_CAP)
    return 2 * radius, -2 * radius * jnp.log1p(-rho)


def arc_lit_integral(geometry: ndf.PairGeometry, h: Float[ArrayLike, "3"],
                     alpha: Float[ArrayLike, ""], *, pieces: int = ndf.N_PIECES
                     ) -> Float[Array, ""]:
    """One view's ``D_hat`` (m^2) for an arc groove, from its geometry
    ``ndf.pair_geometry(footprint, p0, p1, *arc_groove(plunge, radius))`` under the half vector
    `h` (``(3,)``, board frame, normalised here) with roughness `alpha`, in the geometry's dtype.
    The counterpart of `jscratch.ndf.lit_integral` for this profile: the groove's half-width in
    ``u`` is ``U = u_of_v(2 X)`` (``X`` the geometry's half-width in widths), the lit slab is cut
    in ``v / 2`` (`ndf`'s cut), the ends mapped to ``u`` and the pieces integrated by
    `_piece_integrals`. `pieces` (static) as in `ndf.lit_integral`: only the geometry's first
    `pieces` pieces that are not points (up to ``ndf.N_COMPACT``; more: all ``ndf.N_PIECES``),
    exact in value and gradient wherever ``geometry.count <= pieces``. Jittable, vmappable,
    reverse-mode differentiable (by hand: the pieces' partials of `_piece_partials`, the cut's
    transpose of `jscratch.ndf`)."""
    return _lit_integral(geometry, h, alpha, int(pieces), True)


def _lit_integral(geometry, h, alpha, pieces: int, hand_vjp: bool):
    """`arc_lit_integral`; ``hand_vjp=False`` differentiates the same forward by plain autodiff
    (the reference the tests compare the hand-written partials with)."""
    dt = geometry.area.dtype
    h, alpha = jnp.asarray(h, dt), jnp.asarray(alpha, dt)
    G = geometry
    hn = h / jnp.sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2])
    hx = hn[0] * G.b[0] + hn[1] * G.b[1]
    hy = hn[0] * G.t[0] + hn[1] * G.t[1]
    hz = hn[2]
    U = u_of_v(2 * G.X)
    u_m, u_p = ndf.lit_interval(hx, hz)
    u_lo = jnp.maximum(-U, u_m)
    u_hi = jnp.maximum(jnp.minimum(U, u_p), u_lo)
    first = (tuple(x[:pieces] for x in G.first) if pieces <= ndf.N_COMPACT else G.pieces)
    (ca, cb, Ya, Yb), (lo_a, hi_a, lo_b, hi_b) = ndf.cut_to_slab(
        *first, v_of_u(u_lo) / 2, v_of_u(u_hi) / 2, hand_vjp=hand_vjp)

    def to_u(x, lo, hi):
        # Slab bounds and groove edges are known in u exactly; other ends are mapped.
        mapped = jnp.where(x == -G.X, -U, jnp.where(x == G.X, U, u_of_v(2 * x)))
        return jnp.where(lo, u_lo, jnp.where(hi, u_hi, mapped))

    ua, ub = to_u(ca, lo_a, hi_a), to_u(cb, lo_b, hi_b)
    ub = jnp.where(ca == cb, ua, ub)
    L = lobe.lobe(hx, hy, hz, alpha)
    integrate = functools.partial(_pieces if hand_vjp else _piece_integrals, nodes(dt))
    p = lobe.lobe_params(L)
    # At most N_COMPACT pieces a call: XLA's CPU code for all six at once ran 3-10x slower than
    # for two groups of three (`benchmarks/RESULTS.md`).
    J = sum(jnp.sum(integrate(ua[i:i + ndf.N_COMPACT], ub[i:i + ndf.N_COMPACT],
                              Ya[i:i + ndf.N_COMPACT], Yb[i:i + ndf.N_COMPACT], p))
            for i in range(0, ua.shape[-1], ndf.N_COMPACT))
    # -R ∮ Y D dv, with G.scale = -2R (orientation sign).
    return G.scale * L.pref * (J / 2)


def arc_pair_integral(
    h: Float[ArrayLike, "3"],
    footprint: Float[ArrayLike, "4 2"],
    p0: Float[ArrayLike, "2"],
    p1: Float[ArrayLike, "2"],
    plunge: Float[ArrayLike, ""],
    radius: Float[ArrayLike, ""],
    alpha: Float[ArrayLike, ""],
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """The pair integral of docs/model.md §3 for a ball-cutter groove (docs/model.md §13).

    **Arguments:**

    - `h`: `(3,)` board-frame half vector, `h_z > 0` (normalised here).
    - `footprint`: `(4, 2)` convex quad, board metres (either orientation).
    - `p0, p1`: `(2,)` scratch endpoints (m).
    - `plunge`: the cutter's plunge ``p`` below the board surface (m; taken in ``[0, R]``);
      `radius`: the ball's radius ``R`` (m, > 0); `alpha`: GGX roughness in (0, 1).

    **Returns:** `(D_hat, A)`: ``∫∫_{F ∩ groove} D_x dx dy`` and ``area(F ∩ groove)``, both m^2,
    in the dtype of the inputs.
    """
    h, footprint, p0, p1, plunge, radius, alpha = _as_inputs(h, footprint, p0, p1, plunge,
                                                             radius, alpha)
    G = ndf.pair_geometry(footprint, p0, p1, *arc_groove(plunge, radius))
    return arc_lit_integral(G, h, alpha), G.area


def pair_integral_of(profile: str):
    """The pair integral ``(h, footprint, p0, p1, width, depth, alpha) -> (D_hat, A)`` of a
    `jscratch.scene.Scratches.profile`: `jscratch.ndf.pair_integral` for ``"paper"``; for
    ``"arc"`` (``width = 2R``, ``depth`` from `arc_groove`) `arc_lit_integral` on that groove's
    `jscratch.ndf.pair_geometry`, which equals `arc_pair_integral` at the plunge."""
    if profile == "paper":
        return ndf.pair_integral
    if profile != "arc":
        raise InputError(f"pair_integral_of: profile must be 'paper' or 'arc'; got {profile!r}")

    def arc_pair(h, footprint, p0, p1, width, depth, alpha):
        G = ndf.pair_geometry(footprint, p0, p1, width, depth)
        return arc_lit_integral(G, h, alpha), G.area

    return arc_pair
