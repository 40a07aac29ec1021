"""The GGX lobe of docs/model.md §3 in a groove's ``u = x / w`` coordinate, and its integrals along
straight boundary pieces with their partial derivatives: the per-view arithmetic of the closed
form in `jscratch.ndf` (whose docstring derives it), kept in a module of its own. Functions of
arrays of any (broadcasting) shape; jittable and vmappable.

- `lobe(hx, hy, hz, alpha) -> Lobe`, `lobe_terms`, `lobe_params`: the factorised GGX.
- `piece_values(n_gl, ua, ub, Ya, Yb, p, with_partials)`: ``∫ Y (F1 + F2) du`` per piece.
- `nodes(dtype)`, `gauss_legendre(n)`: the quadrature rule.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

__all__ = ["Lobe", "lobe", "prefactor", "lobe_terms", "lobe_params", "piece_values", "nodes",
           "gauss_legendre"]


def _safe_sqrt(x):
    """sqrt with a finite gradient at 0 (where it returns 0 and gradient 0)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1)), 0)


def nodes(dtype) -> int:
    """Gauss-Legendre nodes per piece for the smooth lobe and the sharp lobe's short pieces: 4 in
    float32 (the integrands' poles lie outside a Bernstein ellipse of parameter ~3.7 around
    each piece, so the rule's error is ~3.7^-8 = 3e-5 relative, under float32's 1e-3 tolerance;
    measured: the same worst error against the independent reference as 8 nodes), 16 in float64."""
    return 4 if dtype == jnp.float32 else 16


@functools.lru_cache(maxsize=None)
def gauss_legendre(n: int):
    """`n`-point Gauss-Legendre nodes and weights on [-1, 1] (numpy, cached)."""
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w


class Lobe(NamedTuple):
    """Per pair-view constants of the GGX factorisation (`jscratch.ndf` docstring), from `lobe`."""

    k: Array  # sqrt(1 - alpha^2)
    hx: Array  # half vector across the scratch (normalised h)
    hz: Array  # half vector's normal component
    g: Array  # 1 / (1 + k hz)
    beta2: Array  # alpha^2 + k^2 hy^2
    beta: Array
    u1: Array  # the sharp peak's position, groove widths
    q1: Array  # the sharp peak's half-width, groove widths
    pref: Array  # alpha^2 / (4 pi)


def prefactor(alpha):
    """The GGX lobe's constant factor ``alpha^2 / (4 pi)`` (`Lobe.pref`)."""
    return alpha * alpha / (4 * jnp.pi)


def lobe(hx, hy, hz, alpha) -> Lobe:
    """The constants of the lobe for a local half vector ``(hx, hy, hz)`` and roughness
    ``alpha``."""
    a2 = alpha * alpha
    k = _safe_sqrt(1 - a2)  # finite gradient at alpha = 1
    g = 1 / (1 + k * hz)
    beta2 = a2 + k * k * hy * hy
    beta = jnp.sqrt(beta2)
    return Lobe(k, hx, hz, g, beta2, beta, -g * k * hx / 2, g * beta / 2, prefactor(alpha))


def lobe_terms(L: Lobe, u):
    """`(T1, T2)` at `u`; `T1 = g B / (g^2 beta^2 + 4 (u - u1)^2)`, `T2 = B / (B + kN)`."""
    B = 1 + 4 * u * u
    N = L.hz * (1 - 4 * u * u) - 4 * L.hx * u
    du = u - L.u1
    T1 = L.g * B / (L.g * L.g * L.beta2 + 4 * du * du)
    T2 = B / (B + L.k * N)
    return T1, T2


def lobe_params(L: Lobe) -> tuple:
    """The 11 scalar parameters `piece_values` takes, as a tuple (layout below)."""
    g, k, hx, hz = L.g, L.k, L.hx, L.hz
    a = -2 * g * k * hx / L.beta
    m = 2 * k * (hz + g * k * hx * hx) / L.beta2
    c = (g * g + g, (2 * g + 1) * m + a * a, (2 * g + 1) * a, m * m - a * a, 2 * a * m)
    return (*c, L.u1, L.q1, g, k, hx, hz)


# `lobe_params` returns `(c0, c10, c11, c20, c21, u1, q1, g, k, hx, hz)`. With `s = (u - u1) / q1`
# and `e = 1 / (1 + s^2)` the sharp lobe is
# `F1 = T1^2 + T1 = c0 + c10 e + c11 s e + c20 e^2 + c21 s e^2` (module docstring); `g` is only
# used to evaluate `T1` in its cancellation-free form and carries no partial derivative of its own
# (along consistent parameters the two forms are the same function). The smooth lobe is
# `F2 = T2^2 + T2`, `T2 = B / (B + k N)`, `N = hz (1 - 4u^2) - 4 hx u`.


def _t1_closed(p, sa, ds, ea, eb, Ym, dY):
    """Closed form of the sharp lobe over `s in [sa, sa + ds]` (needs `|ds| >= 1`; callers pass a
    safe value where the branch is not used), `Y = Ym + dY (s - s_m) / ds`; `ea, eb` are
    `1 / (1 + s^2)` at the two ends.

    Returns `(E0, E1, B0, B1)`: `E0 = ∫ F1 ds`, `E1 = ∫ (s - s_m) F1 ds`, and the same integrals
    of the basis `(1, e, s e, e^2, s e^2)` as 5-tuples (`E = B . c`), so that
    `∫ Y F1 ds = Ym E0 + (dY / ds) E1`."""
    sb = sa + ds
    sm = sa + ds / 2
    I0 = jnp.arctan2(ds, 1 + sa * sb)
    # log((1 + sb^2) / (1 + sa^2)) as +-log1p of a non-negative argument, the ratio or its
    # inverse minus one, written without cancellation: one transcendental, accurate for ratios
    # near 1 and far from it.
    ps = ds * (sa + sb)  # sb^2 - sa^2
    up = ps >= 0
    I1 = 0.5 * jnp.where(up, 1, -1) * jnp.log1p(jnp.where(up, ps * ea, -ps * eb))
    K1 = 0.5 * (ds * ea) * ((sa + sb) * eb)
    K0 = 0.5 * I0 + 0.5 * (ds * ea) * ((1 - sa * sb) * eb)
    B0 = (ds, I0, I1, K0, K1)
    B1 = (0, I1 - sm * I0, ds - I0 - sm * I1, K1 - sm * K0, (I0 - K0) - sm * K1)
    E0 = sum(c * b for c, b in zip(p[:5], B0))
    E1 = sum(c * b for c, b in zip(p[1:5], B1[1:]))
    return E0, E1, B0, B1


class _Lobes(NamedTuple):
    """The integrand at abscissae `u` (any shape): `F1 = T1^2 + T1`, `T2`, `1 / (B + k N)`, `B`,
    `N` and the sharp lobe's basis `(e, s e, e^2, s e^2)`, `e = 1 / (1 + s^2)`."""

    F1: Array
    T2: Array
    inv2: Array
    B: Array
    N: Array
    basis: tuple


def _lobes(u, p) -> _Lobes:
    """Both lobes at `u` with two reciprocals: `T1 = g B / (4 (q1^2 + d^2))` (`g^2 beta^2 =
    4 q1^2`, `d = u - u1`) shares one with `e = q1^2 / (q1^2 + d^2)` and `s e`; `T2 = B / (B + k N)`
    has the other."""
    c0, c10, c11, c20, c21, u1, q1, g, k, hx, hz = p
    u2 = u * u
    B = 1 + 4 * u2
    N = hz * (1 - 4 * u2) - 4 * hx * u
    d = u - u1
    inv1 = 1 / (q1 * q1 + d * d)
    T1 = g * B * inv1 / 4
    inv2 = 1 / (B + k * N)
    e = q1 * q1 * inv1
    se = q1 * d * inv1
    return _Lobes(T1 * T1 + T1, B * inv2, inv2, B, N, (e, se, e * e, se * e))


def piece_values(n_gl: int, ua, ub, Ya, Yb, p, with_partials: bool):
    """`∫_{ua}^{ub} Y(u) (F1 + F2) du` for each piece (`(6,)` arrays), `Y` linear from `Ya` to
    `Yb`, lobe parameters `p` (`lobe_params`). Pieces must lie in the lit range.

    With `with_partials`, also the partial derivatives of each piece's value with respect to
    `ua, ub, Ya, Yb` (`(6,)` each) and each of the 11 entries of `p` (`(6,)` each), from the
    moments the forward pass already has (Leibniz rule at the piece ends; integration by parts
    for the peak's position `u1` and half-width `q1`; linearity in the lobe coefficients).

    Values alone unroll the Gauss-Legendre nodes (every operation elementwise on the pieces'
    shape: measured faster on the CPU); with partials the nodes are a trailing axis, whose sums
    keep XLA from recomputing the node values in each partial's fusion (measured fewer flops)."""
    c0, c10, c11, c20, c21, u1, q1, g, k, hx, hz = p
    ct = (c10, c11, c20, c21)
    xs, ws = gauss_legendre(n_gl)
    du = ub - ua
    half = du / 2
    um = ua + half
    Ym = (Ya + Yb) / 2
    dY = Yb - Ya
    # Closed form of the sharp lobe on long pieces.
    ds = du / q1
    sa = (ua - u1) / q1
    sm = sa + ds / 2
    use_cf = jnp.abs(ds) >= jnp.maximum(1, 0.5 * jnp.abs(sm))
    ds_safe = jnp.where(use_cf, ds, 1)
    sa_safe = jnp.where(use_cf, sa, 0)
    sb_safe = sa_safe + ds_safe
    ea = 1 / (1 + sa_safe * sa_safe)
    eb = 1 / (1 + sb_safe * sb_safe)
    E0, E1, B0, B1 = _t1_closed(p, sa_safe, ds_safe, ea, eb, Ym, dY)
    cf = q1 * (Ym * E0 + (dY / ds_safe) * E1)
    if not with_partials:
        gl_t1 = gl_t2 = 0
        for x, w in zip(xs.tolist(), ws.tolist()):
            at = _lobes(um + half * x, p)
            wy = w * (Ym + (dY / 2) * x)
            gl_t1 = gl_t1 + wy * at.F1
            gl_t2 = gl_t2 + wy * (at.T2 * at.T2 + at.T2)
        return jnp.where(use_cf, cf, half * gl_t1) + half * gl_t2

    x = jnp.asarray(xs, ua.dtype)
    w = jnp.asarray(ws, ua.dtype)
    uu = um[..., None] + half[..., None] * x
    at = _lobes(uu, p)
    F2 = at.T2 * at.T2 + at.T2
    wy = w * (Ym[..., None] + (dY / 2)[..., None] * x)
    gl_t2 = half * jnp.sum(wy * F2, axis=-1)
    gl_t1 = half * jnp.sum(wy * at.F1, axis=-1)
    value = jnp.where(use_cf, cf, gl_t1) + gl_t2

    # Mean and centred first moment of D = F1 + F2 over the piece in its own parameter
    # tau in [0, 1]: m0 = ∫ D dtau, mc = ∫ (tau - 1/2) D dtau (no division by du: exact for
    # zero-length pieces and edges parallel to the scratch).
    m0_2 = jnp.sum(w * F2, axis=-1) / 2
    mc_2 = jnp.sum(w * x * F2, axis=-1) / 4
    Ft = sum(c * b for c, b in zip(ct, at.basis))  # F1 - c0
    m0t_gl = jnp.sum(w * Ft, axis=-1) / 2
    mc_gl = jnp.sum(w * x * at.F1, axis=-1) / 4
    Et0 = sum(c * b for c, b in zip(ct, B0[1:]))
    m0t_1 = jnp.where(use_cf, Et0 / ds_safe, m0t_gl)
    mc_1 = jnp.where(use_cf, E1 / (ds_safe * ds_safe), mc_gl)
    m0 = m0t_1 + c0 + m0_2
    mc = mc_1 + mc_2
    ma, mb = m0 / 2 - mc, m0 / 2 + mc

    # Integrand at the ends.
    end_a, end_b = _lobes(ua, p), _lobes(ub, p)
    Da = end_a.F1 + end_a.T2 * end_a.T2 + end_a.T2
    Db = end_b.F1 + end_b.T2 * end_b.T2 + end_b.T2
    # A point piece (both ends equal in u and Y: empty after clipping) stays empty under small
    # changes; its end partials cancel in exact arithmetic but can be huge near a sharp peak.
    point = (ua == ub) & (Ya == Yb)
    d_ua = jnp.where(point, 0, -Ya * Da - dY * ma)
    d_ub = jnp.where(point, 0, Yb * Db - dY * mb)
    d_Ya = du * ma
    d_Yb = du * mb

    # Sharp lobe: linear in the coefficients.
    d_c0 = Ym * du
    d_c = [
        jnp.where(use_cf, q1 * (Ym * b0 + (dY / ds_safe) * b1), half * jnp.sum(wy * b, axis=-1))
        for b0, b1, b in zip(B0[1:], B1[1:], at.basis)
    ]
    # Peak position and half-width, by parts (with F1 - c0, which decays away from the peak).
    sb = sa + ds
    Fta = sum(c * b for c, b in zip(ct, end_a.basis))
    Ftb = sum(c * b for c, b in zip(ct, end_b.basis))
    d_u1 = -(Yb * Ftb - Ya * Fta) + dY * m0t_1
    It_over_q1 = jnp.where(
        use_cf, Ym * Et0 + (dY / ds_safe) * E1, (ds / 2) * jnp.sum(wy * Ft, axis=-1)
    )
    d_q1 = -(Yb * sb * Ftb - Ya * sa * Fta) + dY * (mc_1 * ds + sm * m0t_1) + It_over_q1
    # Smooth lobe: dF2 = -(2 T2 + 1) T2^2 (N dk + k dN) / B, and T2^2 / B = T2 / (B + k N).
    f = half[..., None] * wy * (-(2 * at.T2 + 1) * at.T2 * at.inv2)
    d_k = jnp.sum(f * at.N, axis=-1)
    d_hx = jnp.sum(f * (-4 * k * uu), axis=-1)
    d_hz = jnp.sum(f * (k * (1 - 4 * uu * uu)), axis=-1)
    zero = jnp.zeros_like(d_c0)
    d_p = tuple(
        jnp.where(point, 0, d)
        for d in (d_c0, *d_c, d_u1, d_q1, zero, d_k, d_hx, d_hz)
    )
    return value, (d_ua, d_ub, d_Ya, d_Yb, d_p)
