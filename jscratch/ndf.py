"""The scratch NDF: groove geometry and the per-pair boundary integral (docs/model.md §1-§3).

One pixel footprint ``F`` (convex quad, board metres) and one scratch (``p0, p1, width, depth,
alpha``) under a half vector ``h`` give

    D_hat = ∫∫_{F ∩ groove} D_x(h, n(x)) dx dy      (m^2)
    A     = area(F ∩ groove)                         (m^2)

**Public API:**

- `pair_integral(h, footprint, p0, p1, width, depth, alpha) -> (D_hat, A)`: the closed-form
  boundary integral (below). Pure, jittable, vmappable, differentiable in every float argument,
  float32 and float64 (it follows the dtype of its inputs).
- Its two stages, for renderers with several views: `pair_geometry(footprint, p0, p1, width,
  depth) -> PairGeometry` (no view changes it: `A` and the boundary pieces, non-points first,
  with their `count`), and `lit_integral(geometry, h, alpha, *, pieces=k)` per view, which may
  integrate the first `k` pieces only: exact where `count <= k`, and that much less work.
- `pair_integral_quadrature(h, footprint, p0, p1, width, depth, alpha, n)`: the same integral by
  ``n``-point Gauss-Legendre quadrature of the chord-length form ``∫ chord(x) D_x(x) dx`` over the
  lit part of the groove. Independent of the boundary machinery; the comparison point of the
  run-time-against-error benchmark.
- Building blocks: `height_profile`, `groove_half_width` (``x_max``), `normal`, `ggx`,
  `point_ndf`, `local_frame`, `lit_interval`.

**How the closed form works.** In the scratch frame (docs/model.md §1) write ``u = x / w``. The GGX
of docs/model.md §3 with ``k = sqrt(1 - alpha^2)``, ``B = 1 + 4u^2``, ``N = hz (1 - 4u^2) - 4 hx u``,
``P1 = B - kN``, ``P2 = B + kN`` is, with ``T1 = B / P1`` and ``T2 = B / P2`` (use
``P1 + P2 = 2B``),

    D_x = (alpha^2 / 4 pi) (T1^2 + T1 + T2^2 + T2).

``P1 = (4/g) ((u - u1)^2 + q1^2)`` with ``g = 1/(1 + k hz)``, peak ``u1 = -g k hx / 2``, half
width ``q1 = g beta / 2`` and ``beta^2 = alpha^2 + k^2 hy^2`` (``hy`` from a normalised ``h``;
this form has no cancellation however sharp the peak). With ``s = (u - u1) / q1``,

    T1 = g + (a s + m) / (1 + s^2),   a = -2 g k hx / beta,   m = 2k (hz + g k hx^2) / beta^2,

so ``T1^2 + T1`` is a combination of ``1, 1/(1+s^2), s/(1+s^2), 1/(1+s^2)^2, s/(1+s^2)^2`` whose
integrals against ``1`` and ``s`` are ``arctan``, ``log`` and rational terms. ``arctan``
differences are taken as ``atan2(sb - sa, 1 + sa sb)`` and ``log`` ratios with ``log1p``, so a
peak of height ``1/(pi alpha^2)`` at ``alpha = 1e-4`` keeps full float32 accuracy. On pieces short
compared with their distance from the peak (``|ds| < max(1, |s_mid| / 2)``), where those terms
would cancel, ``T1`` is integrated by Gauss-Legendre instead: there the integrand's poles
``s = ±i`` are far outside the piece (Bernstein ellipse parameter at least 3.7), so the rule is
exact to rounding. ``T2 <= T1`` is smooth and bounded by 1 on the lit range (its poles lie on the
unlit side, about half a groove width away), and is integrated by the same fixed Gauss-Legendre
rule on every piece (4 nodes in float32, 16 in float64; `lobe.nodes`). The lobe's arithmetic
lives in `jscratch.lobe`.

**One clipping path for every intersection type.** By Green's theorem with
``P = -Y(y) D(u)``, ``Y(y) = clamp(y, 0, L) - y_ref``,

    D_hat = -w ∮_{∂F} Y(y) D~(u) du,    D~ = D on the lit slab [u_lo, u_hi], 0 outside,

since ``∂Y/∂y`` is the indicator of ``0 <= y <= L``. The slab ``[u_lo, u_hi]`` is
``[-x_max, x_max] / w`` cut to where ``N > 0`` (``chi+``). The evaluation has two stages:

1. *Per pair, for every view* (`_groove`, `_strip_pieces`): the footprint in the scratch frame
   cut to the scratch's length, ``Q = F ∩ {0 <= y <= L}``, as six boundary pieces: each
   footprint edge's part inside ``0 <= y <= L`` (a Liang-Barsky interval), where ``Y`` is
   linear, and the two chains where the boundary runs below ``y = 0`` (above ``y = L``), where
   ``Y`` is constant and ``D~ du`` exact, so each contributes ``Y * ∫ D~ du`` between the points
   where it leaves and re-enters. Nothing here depends on the half vector, so a renderer that
   vmaps the kernel over views (with the scratch and footprint unbatched) computes it, and its
   reverse pass, once per pair.
   The pieces are then cut to the groove ``[-x_max, x_max] / w`` (`_cut`; a piece outside
   becomes a point): ``A`` is their sum with ``D = 1``, and the pieces that are not points
   (`PairGeometry.count` of them, typically two: the footprint edges the groove crosses; the
   first `N_COMPACT` also kept apart by `_compact`) are what every view integrates.
2. *Per view* (`lit_integral`, `_lit_sum`): the pieces clamped to the lit slab, which lies
   inside the groove, and integrated; a renderer integrates only the first pieces, as many as
   the largest `count` of a chunk of pairs (`jscratch.render`'s jnp path, which sorts pairs by
   `count`; on the CPU the renderer runs both stages natively, `jscratch.native.pair_values`).

Six pieces per pair, whatever the footprint-groove configuration (all eight types of the
paper's Fig. 7, and footprints larger or smaller than the groove). ``y_ref`` (the mean ``y`` of
the clipped edges, and again of the pieces cut to the slab: a constant shift on a closed
boundary) and coordinates taken relative to a footprint vertex keep a small footprint far along
a long scratch, or a slab that only nicks ``Q``, free of cancellation.

**Derivatives.** Reverse mode is hand-written where autodiff is costly (on the CPU the XLA
reverse graph of the closed form and its clipping would dominate a gradient step). A piece's value
``I = ∫_{ua}^{ub} Y D du`` has ``∂I/∂ub = Yb D(ub) - (Yb - Ya) m_b``, ``∂I/∂Yb = (ub - ua) m_b``
(and the mirror for ``a``) with ``m_b = ∫_0^1 tau D dtau`` along the piece; the sharp lobe is
linear in its coefficients ``c`` (the basis integrals come with the closed form) and depends on
the peak position ``u1`` and half-width ``q1`` only through ``s``, which integration by parts turns
into end values and the moments already computed; the smooth lobe's parameter derivatives use the
same Gauss-Legendre nodes. The per-view stage is one `jax.custom_vjp` (`_lit_sum`): its
forward pass chains these partials through the hand-written transpose of the slab clamp
(`_cut_transpose`), so the backward pass is a few products (autodiff of the clamp, the closed
form's branches and the view algebra compiled to many small XLA fusions that moved more bytes
than the arithmetic). The strip clip's parameters are found without gradient and carry the
derivative of the one constraint that sets each (implicit function theorem), so its branch logic
never enters the reverse pass. `_pair_integral(..., hand_vjp=False)` differentiates the same
forward by plain autodiff; the tests compare the two on every test pair.

**Native per-view stage.** On the CPU the per-view stage (the view's slab and lobe, `_cut`, the
piece integrals and their partials, `_cut_transpose`, and the view algebra's Jacobian) runs as
one native kernel, `jscratch/native/native_lit.cc` (an XLA FFI custom call, `jscratch.native`; one SIMD
lane per pair-view; a values-only variant for forward passes), where XLA's fusions recomputed
the shared arithmetic for each partial: the same formulas (float64: equal to the jnp code to
1e-9, `tests/test_native.py`), ~4x less time. Other backends, a machine without a C++
compiler, or ``JSCRATCH_NATIVE=0`` use the jnp code (`_view`, `lobe`, `_lit_sum`).

Degenerate input (zero-length scratch, zero depth, vertices on groove edges, edges parallel to
the scratch) gives finite values and finite gradients: every division and square root that can
meet zero goes through a guarded (double-``where``) form.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jscratch import lobe, native
from jscratch.errors import InputError, real_number, shape_arg, shown

__all__ = [
    "pair_integral",
    "pair_integral_quadrature",
    "height_profile",
    "groove_half_width",
    "normal",
    "ggx",
    "point_ndf",
    "local_frame",
    "lit_interval",
    "pair_geometry",
    "cut_to_slab",
    "lit_integral",
    "PairGeometry",
    "N_PIECES",
    "N_COMPACT",
    "piece_count_estimate",
]


# ---------------------------------------------------------------------------------------------
# Small guarded primitives.


def _safe_sqrt(x):
    """sqrt with a finite gradient at 0 (where it returns 0 and gradient 0)."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1)), 0)


def _dot2(v, d):
    """`v . d` over a trailing axis of length 2, written out."""
    return v[..., 0] * d[0] + v[..., 1] * d[1]


def _two_sum(a, b):
    """Error-free sum (Knuth): `a + b = s + e` exactly."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _two_prod(a, b):
    """Error-free product (Dekker, Veltkamp splitting; no FMA needed): `a * b = p + e`."""
    split = 4097.0 if a.dtype == jnp.float32 else 134217729.0  # 2^12 + 1, 2^27 + 1

    def halves(v):
        c = split * v
        hi = c - (c - v)
        return hi, v - hi

    p = a * b
    (ah, al), (bh, bl) = halves(a), halves(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _cross_accurate(o, p0, p1):
    """`(o - p0) x (p1 - p0)` (2-D cross product) to a relative error of a few ulps of the
    result, even when it is tiny compared with `|o - p0| |p1 - p0|`: compensated sums and
    products. It fixes where a scratch axis lies relative to a footprint to far better than the
    board coordinates' ulp, which a sharp GGX peak (width `alpha w`, nanometres) needs."""
    (ex, ex_lo), (ey, ey_lo) = _two_sum(o[0], -p0[0]), _two_sum(o[1], -p0[1])
    (dx, dx_lo), (dy, dy_lo) = _two_sum(p1[0], -p0[0]), _two_sum(p1[1], -p0[1])
    (a, a_lo), (b, b_lo) = _two_prod(ex, dy), _two_prod(ey, dx)
    small = (a_lo - b_lo) + (ex * dy_lo + ex_lo * dy) - (ey * dx_lo + ey_lo * dx)
    return (a - b) + small


# ---------------------------------------------------------------------------------------------
# Geometry (docs/model.md §2).


def height_profile(x: ArrayLike, width: ArrayLike, depth: ArrayLike) -> Array:
    """Groove height profile (Eq. 2) `h(x) = -(w/2) log(1 - 4x^2/w^2) - d`, clipped at the board
    surface: 0 where the profile lies above it (``|x| >= x_max``).

    **Arguments:** `x` local across-scratch coordinate (m, any shape); `width`, `depth` (m).

    **Returns:** height (m, <= 0), the shape of `x` broadcast with the others.
    """
    x, width, depth = jnp.asarray(x), jnp.asarray(width), jnp.asarray(depth)
    u2 = 4 * (x / width) ** 2
    inside = u2 < 1
    prof = -(width / 2) * jnp.log1p(-jnp.where(inside, u2, 0)) - depth
    return jnp.where(inside, jnp.minimum(prof, 0), 0)


def groove_half_width(width: ArrayLike, depth: ArrayLike) -> Array:
    """Groove half-width `x_max = (w/2) sqrt(1 - exp(-2d/w))` (m): where the profile meets the board."""
    width, depth = jnp.asarray(width), jnp.asarray(depth)
    return 0.5 * width * _safe_sqrt(-jnp.expm1(-2 * depth / width))


def normal(x: ArrayLike, width: ArrayLike) -> Array:
    """Groove normal in the scratch-local frame (Eq. 5), `u = x/w`:
    `n = (-4u, 0, 1 - 4u^2) / (1 + 4u^2)`.

    **Returns:** `(..., 3)` unit vectors (local x across, y along, z up).
    """
    u = jnp.asarray(x) / jnp.asarray(width)
    B = 1 + 4 * u * u
    return jnp.stack([-4 * u / B, jnp.zeros_like(u), (1 - 4 * u * u) / B], axis=-1)


def ggx(cos_theta: ArrayLike, alpha: ArrayLike) -> Array:
    """GGX NDF with `chi+` (Eq. 6-7): `chi+(c) alpha^2 / (pi (c^2 (alpha^2 - 1) + 1)^2)` (1/sr)."""
    c = jnp.asarray(cos_theta)
    a2 = jnp.asarray(alpha) ** 2
    den = 1 - (1 - a2) * c * c
    return jnp.where(c > 0, a2 / (jnp.pi * den * den), 0)


def point_ndf(h_local: ArrayLike, x: ArrayLike, width: ArrayLike, alpha: ArrayLike) -> Array:
    """`D_x(h, n(x))`: the GGX of the groove normal at local `x` for the local half vector
    `h_local = (hx, hy, hz)` (normalised here). Shapes broadcast; `h_local` has a trailing 3."""
    h = jnp.asarray(h_local)
    h = h / jnp.linalg.norm(h, axis=-1, keepdims=True)
    n = normal(x, width)
    return ggx(jnp.sum(n * h, axis=-1), alpha)


def local_frame(p0: ArrayLike, p1: ArrayLike):
    """Scratch frame (docs/model.md §1): `(t, b, L)`, `t` along, `b = (t_y, -t_x)` across, `L` the
    length (m). A zero-length scratch gets `t = (0, 1)` (finite gradients)."""
    p0, p1 = jnp.asarray(p0), jnp.asarray(p1)
    d = p1 - p0
    L2 = jnp.sum(d * d, axis=-1)
    L = _safe_sqrt(L2)
    pos = L2 > 0
    Ls = jnp.where(pos, L, 1)[..., None]
    t = jnp.where(pos[..., None], d / Ls, jnp.array([0.0, 1.0], d.dtype))
    b = jnp.stack([t[..., 1], -t[..., 0]], axis=-1)
    return t, b, L


def lit_interval(hx: ArrayLike, hz: ArrayLike):
    """`(u_minus, u_plus)`: the roots of `N(u) = hz (1 - 4u^2) - 4 hx u`; `N > 0` between them
    (`hz > 0`). Written without cancellation for either sign of `hx`."""
    hx, hz = jnp.asarray(hx), jnp.asarray(hz)
    r = jnp.sqrt(hx * hx + hz * hz)
    rp = r + jnp.abs(hx)  # >= r > 0
    near = hz / (2 * rp)  # the root on the side hx points away from
    far = rp / (2 * hz)
    u_plus = jnp.where(hx >= 0, near, far)
    u_minus = jnp.where(hx >= 0, -far, -near)
    return u_minus, u_plus


# ---------------------------------------------------------------------------------------------
# Boundary pieces.


def _ratio_clipped(num, den):
    """`num / den` clipped to [-2, 2], with finite gradients for tiny or zero `den`."""
    ok = (jnp.abs(num) <= 2 * jnp.abs(den)) & (den != 0)
    r = num / jnp.where(ok, den, 1)
    out = 2 * jnp.sign(num) * jnp.sign(den)
    return jnp.where(ok, r, jnp.where(den == 0, 2 * jnp.sign(num), out))


def _lerp(a, b, d, t):
    """`a + t d` with `d = b - a`, taken from the nearer end so that `t = 1` gives `b` exactly
    (a vertex at a sharp peak must stay where it is)."""
    return jnp.where(t <= 0.5, a + t * d, b - (1 - t) * d)


def _lb(a, delta, lo, hi):
    """Liang-Barsky: the parameter interval `[t_in, t_out]` (clipped to [-2, 2]) where
    `lo <= a + t delta <= hi`."""
    r_lo, r_hi = _ratio_clipped(lo - a, delta), _ratio_clipped(hi - a, delta)
    inside = (a >= lo) & (a <= hi)
    t_in = jnp.where(delta > 0, r_lo, jnp.where(delta < 0, r_hi, jnp.where(inside, -2, 2)))
    t_out = jnp.where(delta > 0, r_hi, jnp.where(delta < 0, r_lo, jnp.where(inside, 2, -2)))
    return t_in, t_out


@jax.custom_jvp
def _implicit(t, residual, slope):
    """A clipping parameter `t` (computed without gradient) given the derivative of the root of
    `residual(t) = 0`, where `residual = a + t delta - bound` is linear in `t` with `slope = delta`:
    the value is `t` itself, the tangent `-d(residual) / delta` (implicit function theorem). This
    keeps the clipping logic (Liang-Barsky branches, guards) out of the reverse pass, whose XLA
    graph otherwise grows large enough to dominate a gradient step, and costs nothing in a
    forward-only evaluation (`residual` is then dead code)."""
    return t


@_implicit.defjvp
def _implicit_jvp(primals, tangents):
    t, _, slope = primals
    _, d_residual, _ = tangents
    return t, -d_residual / jnp.where(slope == 0, 1, slope)


def _strip_pieces(u, y, y_lo, y_hi):
    """The boundary of `Q = F ∩ {y_lo <= y <= y_hi}` (the footprint cut to the scratch's length)
    as six pieces; it does not depend on the half vector, so a renderer computes it once per pair
    for all views.

    `u, y`: `(4,)` footprint vertices (local, `y` relative to vertex 0). Returns
    `(ua, ub, Ya, Yb)`, each `(6,)`: the four footprint edges clipped to the strip (possibly
    empty: one point, bit for bit), where `Y = y - y_ref` is linear, then the chains along
    `y_lo` and `y_hi` (constant `Y`) from where the boundary leaves the strip to where it comes
    back.

    `y_ref` is any constant (Green's theorem on a closed boundary); the mean `y` of the clipped
    edges keeps `Y` of the size of `Q`, not of the footprint's distance from the scratch start.
    It carries no gradient (the result does not depend on it). The clipping parameters are
    found without gradient; each then carries the derivative of the one constraint that sets it
    (`_implicit`), or none at a vertex."""
    sg = jax.lax.stop_gradient
    ub_, yb_ = jnp.roll(u, -1), jnp.roll(y, -1)
    du, dy = ub_ - u, yb_ - y
    dy0 = sg(dy)
    tiy, toy = _lb(sg(y), dy0, sg(y_lo), sg(y_hi))
    t0, t1 = jnp.maximum(tiy, 0), jnp.minimum(toy, 1)
    empty = t1 <= t0
    t1 = jnp.maximum(t1, t0)
    vert0, vert1 = t0 <= 0, t1 >= 1
    bound0 = jnp.where(dy0 > 0, y_lo, y_hi)  # the y bound an edge enters by
    bound1 = jnp.where(dy0 > 0, y_hi, y_lo)
    t0 = jnp.where(vert0, t0, _implicit(t0, y + t0 * dy - bound0, dy0))
    t1 = jnp.where(vert1, t1, _implicit(t1, y + t1 * dy - bound1, dy0))
    e_ua = _lerp(u, ub_, du, t0)
    e_ya = jnp.where(vert0, y, bound0)  # an end set by a bound lies on it exactly
    # An empty piece is one point, bit for bit (`lobe.piece_values` recognises points by equality).
    e_ub = jnp.where(empty, e_ua, _lerp(u, ub_, du, t1))
    e_yb = jnp.where(empty, e_ya, jnp.where(vert1, yb_, bound1))

    # Where the boundary leaves the strip across a bound, and where it comes back: the end of the
    # (possibly empty) clipped piece of the edge that crosses it.
    def chain(level, enter, leave):
        return jnp.sum(jnp.where(enter, e_ub, 0)), jnp.sum(jnp.where(leave, e_ua, 0))

    lo_in, lo_out = chain(y_lo, (y >= y_lo) & (yb_ < y_lo), (y < y_lo) & (yb_ >= y_lo))
    hi_in, hi_out = chain(y_hi, (y <= y_hi) & (yb_ > y_hi), (y > y_hi) & (yb_ <= y_hi))
    wgt = sg(jnp.abs(e_ub - e_ua) + jnp.abs(e_yb - e_ya))
    sw = jnp.sum(wgt)
    # Only a point of F in the strip, at y_hi: Y from there (the chain there adds no gradient).
    hi_touch = jnp.any(((y <= y_hi) & (yb_ > y_hi)) | ((y > y_hi) & (yb_ <= y_hi)))
    y_ref = jnp.where(
        sw > 0, jnp.sum(wgt * sg(e_ya + e_yb) / 2) / jnp.where(sw > 0, sw, 1),
        jnp.where(hi_touch, sg(y_hi), sg(y_lo)),
    )
    Y_lo, Y_hi = y_lo - y_ref, y_hi - y_ref
    ua = jnp.concatenate([e_ua, jnp.stack([lo_in, hi_in])])
    ub = jnp.concatenate([e_ub, jnp.stack([lo_out, hi_out])])
    Ya = jnp.concatenate([e_ya - y_ref, jnp.stack([Y_lo, Y_hi])])
    Yb = jnp.concatenate([e_yb - y_ref, jnp.stack([Y_lo, Y_hi])])
    return ua, ub, Ya, Yb


class _Cut(NamedTuple):
    """`_strip_pieces`' pieces cut to a slab `lo <= u <= hi` (`_cut`), with what the hand-written
    transpose (`_cut_transpose`) needs. All `(6,)`."""

    ua: Array  # ends clamped into the slab
    ub: Array
    Ya: Array  # Y at the ends, re-centred on the cut region
    Yb: Array
    ta: Array  # where each end lies on its original piece (0 .. 1)
    tb: Array
    ta_free: Array  # ta moves with the slab bound (the end is a crossing, not clamped in t)
    tb_free: Array
    lo_a: Array  # end a was clamped to lo (to hi)
    hi_a: Array
    lo_b: Array
    hi_b: Array
    point: Array  # nothing of the piece in the slab: one point
    dY: Array
    inv_du: Array  # 1 / (ub - ua) of the original piece (1 where it is 0)


def _centre(ca, cb, Ya, Yb):
    """The length-weighted mean `Y` of pieces (no gradient): the re-centring constant."""
    sg = jax.lax.stop_gradient
    wgt = sg(jnp.abs(cb - ca) + jnp.abs(Yb - Ya))
    sw = jnp.sum(wgt)
    return sg(jnp.where(sw > 0, jnp.sum(wgt * (Ya + Yb) / 2) / jnp.where(sw > 0, sw, 1), 0))


def _cut(ua, ub, Ya, Yb, lo, hi) -> _Cut:
    """The pieces of `_strip_pieces` cut to the slab `lo <= u <= hi` (the part a view lights, or
    the whole groove): each end clamped into the slab, `Y` where the piece crosses a bound; a
    piece outside the slab becomes a point. Then `Y` is re-centred on the cut region (a constant
    shift: the pieces form a closed boundary), so a slab that only nicks `Q` keeps `Y` of its
    own size. Written with `where`, not `clip`, so that autodiff and `_cut_transpose` agree at
    ties: an end exactly on a bound keeps its own derivative."""
    du, dY = ub - ua, Yb - Ya
    lo_a, hi_a = ua < lo, ua > hi
    lo_b, hi_b = ub < lo, ub > hi
    moved_a, moved_b = lo_a | hi_a, lo_b | hi_b
    ca = jnp.where(lo_a, lo, jnp.where(hi_a, hi, ua))
    cb = jnp.where(lo_b, lo, jnp.where(hi_b, hi, ub))
    nz = du != 0
    inv_du = 1 / jnp.where(nz, du, 1)

    def param(c, moved, default):
        """Where the clamped end lies on the piece; `free` where that moves with the bound."""
        r = (c - ua) * inv_du
        m = moved & nz
        free = m & (r > 0) & (r < 1)
        return jnp.where(m, jnp.where(r <= 0, 0, jnp.where(r >= 1, 1, r)), default), free

    ta, ta_free = param(ca, moved_a, 0)
    tb, tb_free = param(cb, moved_b, 1)
    Ya2 = _lerp(Ya, Yb, dY, ta)
    Yb2 = _lerp(Ya, Yb, dY, tb)
    # A piece with nothing in the slab (across the scratch but cut to zero length, or along it
    # and outside) is one point, bit for bit and in its derivative, as `lobe.piece_values` expects.
    point = jnp.where(nz, ca == cb, moved_a)
    cb = jnp.where(point, ca, cb)
    Yb2 = jnp.where(point, Ya2, Yb2)
    ref = _centre(ca, cb, Ya2, Yb2)
    return _Cut(ca, cb, Ya2 - ref, Yb2 - ref, ta, tb, ta_free, tb_free, lo_a, hi_a, lo_b, hi_b,
                point, dY, inv_du)


def cut_to_slab(ua, ub, Ya, Yb, lo, hi, *, hand_vjp: bool = True):
    """`pair_geometry`'s pieces cut to the slab `lo <= u <= hi` as a view cuts them (`_cut`;
    `jscratch.arc` cuts in its own coordinate): `((ua, ub, Ya, Yb), (lo_a, hi_a, lo_b, hi_b))`,
    the flags saying which ends were clamped to which bound. Reverse mode through the cut's
    hand-written transpose (`_cut_transpose`), as `pair_geometry`'s own cut; ``hand_vjp=False``:
    plain autodiff of the same forward (a reference)."""
    cut = _cut_pieces if hand_vjp else _cut_values
    return cut(ua, ub, Ya, Yb, lo, hi), (ua < lo, ua > hi, ub < lo, ub > hi)


def _cut_transpose(c: _Cut, g_ca, g_cb, g_Ya, g_Yb):
    """Transpose of `_cut`: from derivatives with respect to the cut pieces' `(ua, ub, Ya, Yb)`
    (`(6,)` each) to those with respect to the uncut pieces (`(6,)` each) and the slab bounds
    `lo, hi` (summed over the pieces)."""
    zero = jnp.zeros_like(g_ca)
    # A point's second end is its first.
    g_ca = g_ca + jnp.where(c.point, g_cb, zero)
    g_Ya = g_Ya + jnp.where(c.point, g_Yb, zero)
    g_cb, g_Yb = jnp.where(c.point, zero, g_cb), jnp.where(c.point, zero, g_Yb)
    # Y at an end is the lerp of the piece's Y at t.
    g_Ya0, g_Yb0 = g_Ya * (1 - c.ta) + g_Yb * (1 - c.tb), g_Ya * c.ta + g_Yb * c.tb
    # t = (c - ua) / (ub - ua) where the end is a crossing.
    ga = jnp.where(c.ta_free, g_Ya * c.dY * c.inv_du, zero)
    gb = jnp.where(c.tb_free, g_Yb * c.dY * c.inv_du, zero)
    g_ca, g_cb = g_ca + ga, g_cb + gb
    g_ua = ga * (c.ta - 1) + gb * (c.tb - 1)
    g_ub = -(ga * c.ta + gb * c.tb)
    # The clamp.
    g_ua = g_ua + jnp.where(c.lo_a | c.hi_a, zero, g_ca)
    g_ub = g_ub + jnp.where(c.lo_b | c.hi_b, zero, g_cb)
    g_lo = jnp.sum(jnp.where(c.lo_a, g_ca, zero) + jnp.where(c.lo_b, g_cb, zero))
    g_hi = jnp.sum(jnp.where(c.hi_a, g_ca, zero) + jnp.where(c.hi_b, g_cb, zero))
    return g_ua, g_ub, g_Ya0, g_Yb0, g_lo, g_hi


def _lit_sum_values(n_gl, ua, ub, Ya, Yb, lo, hi, p):
    c = _cut(ua, ub, Ya, Yb, lo, hi)
    return jnp.sum(lobe.piece_values(n_gl, c.ua, c.ub, c.Ya, c.Yb, p, False))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _lit_sum(n_gl, ua, ub, Ya, Yb, lo, hi, p):
    """`∑ ∫ Y (F1 + F2) du` over boundary pieces cut to the lit slab `[lo, hi]`, lobe
    parameters `p` (`lobe.lobe_params`), with a hand-written reverse pass: the piece partials of
    `lobe.piece_values` chained through `_cut_transpose` in the forward pass, so the backward pass
    is a few products (the autodiff graph of the cut and of the closed form's branches was
    several times the forward's cost on the CPU)."""
    return _lit_sum_values(n_gl, ua, ub, Ya, Yb, lo, hi, p)


def _lit_sum_fwd(n_gl, ua, ub, Ya, Yb, lo, hi, p):
    c = _cut(ua, ub, Ya, Yb, lo, hi)
    value, (d_ua, d_ub, d_Ya, d_Yb, d_p) = lobe.piece_values(n_gl, c.ua, c.ub, c.Ya, c.Yb, p, True)
    partials = _cut_transpose(c, d_ua, d_ub, d_Ya, d_Yb)
    return jnp.sum(value), (partials, tuple(jnp.sum(d) for d in d_p))


def _lit_sum_bwd(n_gl, res, ct):
    partials, d_p = res
    return (*(ct * d for d in partials), tuple(ct * d for d in d_p))


_lit_sum.defvjp(_lit_sum_fwd, _lit_sum_bwd)


def _cut_values(ua, ub, Ya, Yb, lo, hi):
    c = _cut(ua, ub, Ya, Yb, lo, hi)
    return c.ua, c.ub, c.Ya, c.Yb


@jax.custom_vjp
def _cut_pieces(ua, ub, Ya, Yb, lo, hi):
    """`_cut`'s pieces with its hand-written transpose (`_cut_transpose`) as the reverse pass."""
    return _cut_values(ua, ub, Ya, Yb, lo, hi)


def _cut_pieces_fwd(ua, ub, Ya, Yb, lo, hi):
    c = _cut(ua, ub, Ya, Yb, lo, hi)
    return (c.ua, c.ub, c.Ya, c.Yb), c


def _cut_pieces_bwd(c, g):
    return _cut_transpose(c, *g)


_cut_pieces.defvjp(_cut_pieces_fwd, _cut_pieces_bwd)


class _Groove(NamedTuple):
    """The view-independent part of one pair: the footprint in the scratch frame and `Q`'s
    boundary (`_strip_pieces`)."""

    u: Array  # (4,) footprint vertices across the scratch, in groove widths (u = x / w)
    y: Array  # (4,) along the scratch, m, relative to vertex 0
    y_lo: Array  # the scratch start (y = 0) relative to vertex 0, m
    y_hi: Array  # the scratch end (y = L)
    sign: Array  # +1 for a counter-clockwise footprint, -1 for a clockwise one
    X: Array  # groove half-width x_max / w
    t: Array  # (2,) along the scratch
    b: Array  # (2,) across the scratch
    pieces: tuple  # Q's boundary: (ua, ub, Ya, Yb), each (6,)


def _strip_frame(footprint, p0, p1):
    """The footprint in the scratch frame: `(t, b, L, q, x_c, y, y_lo, y_hi)`: `q` the vertices
    relative to vertex 0, `x_c` vertex 0's across coordinate (m), `y` the along coordinates
    relative to vertex 0 and the scratch's start and end `y_lo, y_hi` on the same axis (m)."""
    t, b, L = local_frame(p0, p1)
    # Origin at vertex 0: `footprint - c` is exact for pixel footprints (Sterbenz), and the
    # origin's own across-scratch coordinate is computed with compensated arithmetic.
    c = footprint[0]
    q = footprint - c
    cp = c - p0
    # Elementwise products, not `@`: under vmap a tiny batched matmul is slow on the CPU.
    x_c = jnp.where(L > 0, _cross_accurate(c, p0, p1) / jnp.where(L > 0, L, 1), _dot2(cp, b))
    y_c = _dot2(cp, t)
    return t, b, L, q, x_c, _dot2(q, t), -y_c, L - y_c


#: Boundary pieces per pair: the four footprint edges and the two chains (`_strip_pieces`).
N_PIECES = 6
#: How many of them `pair_geometry` also keeps compacted (non-points first): most pairs have 2
#: or 3 (`lit_integral`'s budgets up to this integrate those; larger budgets all six).
N_COMPACT = 3


def _compact(pieces, k: int):
    """The first `k` pieces that are not points, in order, then points at the origin; and how
    many pieces are not points. `pieces`: `(ua, ub, Ya, Yb)`, each `(N_PIECES,)`."""
    ua, ub, Ya, Yb = pieces
    keep = ~((ua == ub) & (Ya == Yb))
    pos = jnp.cumsum(keep) - 1
    sel = keep[None, :] & (pos[None, :] == jnp.arange(k)[:, None])  # (k, 6): slot <- piece
    return (tuple(jnp.sum(jnp.where(sel, x[None, :], 0), axis=1) for x in pieces),
            jnp.sum(keep, dtype=jnp.int32))


def piece_count_estimate(footprint: Float[ArrayLike, "4 2"], p0: Float[ArrayLike, "2"],
                         p1: Float[ArrayLike, "2"], width: Float[ArrayLike, ""],
                         depth: Float[ArrayLike, ""]) -> Array:
    """A cheap estimate of `pair_geometry(...).count` (int32; about a tenth of its flops): the
    footprint edges whose part within the scratch's length reaches into the groove, and the
    scratch ends whose crossing by the footprint does. It differs from the count only on ties
    (pieces that touch the groove in one point); a renderer sorts pairs by it, and only the
    speed depends on it."""
    footprint, p0, p1, width, depth = _as_inputs(footprint, p0, p1, width, depth)
    _, b, _, q, x_c, y, y_lo, y_hi = _strip_frame(footprint, p0, p1)
    u = (_dot2(q, b) + x_c) / width
    X = groove_half_width(width, depth) / width
    du, dy = jnp.roll(u, -1) - u, jnp.roll(y, -1) - y
    flat = dy == 0
    inv = 1 / jnp.where(flat, 1, dy)
    ta, tb = (y_lo - y) * inv, (y_hi - y) * inv
    inside = (y >= y_lo) & (y <= y_hi)
    t0 = jnp.where(flat, jnp.where(inside, 0, 1), jnp.maximum(0, jnp.minimum(ta, tb)))
    t1 = jnp.where(flat, jnp.where(inside, 1, 0), jnp.minimum(1, jnp.maximum(ta, tb)))
    ua, ub = u + t0 * du, u + t1 * du
    edges = (t1 > t0) & (jnp.minimum(ua, ub) <= X) & (jnp.maximum(ua, ub) >= -X)

    def chain(t, level):  # where the boundary crosses y = level: its u-span meets the groove
        crosses = ~flat & (t > 0) & (t < 1) & ((y - level) * (y + dy - level) < 0)
        uc = u + t * du
        big = jnp.asarray(1e30, u.dtype)
        lo = jnp.min(jnp.where(crosses, uc, big))
        hi = jnp.max(jnp.where(crosses, uc, -big))
        return (jnp.sum(crosses) >= 2) & (lo <= X) & (hi >= -X) & (hi > lo)

    return jnp.sum(edges, dtype=jnp.int32) + chain(ta, y_lo) + chain(tb, y_hi)


def _groove(footprint, p0, p1, width, depth) -> _Groove:
    t, b, L, q, x_c, y, y_lo, y_hi = _strip_frame(footprint, p0, p1)
    u = (_dot2(q, b) + x_c) / width
    # Orientation of the footprint (so a clockwise quad also gives positive values).
    qn = jnp.roll(q, -1, axis=0)
    area2 = jnp.sum(q[:, 0] * qn[:, 1] - qn[:, 0] * q[:, 1])
    sign = jnp.where(area2 >= 0, 1, -1).astype(q.dtype)
    X = groove_half_width(width, depth) / width
    return _Groove(u, y, y_lo, y_hi, sign, X, t, b, _strip_pieces(u, y, y_lo, y_hi))


def _view(G, h):
    """`(hx, hy, hz, u_lo, u_hi)` for a `_Groove` or `PairGeometry` `G`: the local components of the normalised half vector and the lit
    slab, `[-X, X]` cut to where `N > 0`."""
    hn = h / jnp.sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2])
    hx = hn[0] * G.b[0] + hn[1] * G.b[1]
    hy = hn[0] * G.t[0] + hn[1] * G.t[1]
    hz = hn[2]
    u_m, u_p = lit_interval(hx, hz)
    u_lo = jnp.maximum(-G.X, u_m)
    u_hi = jnp.maximum(jnp.minimum(G.X, u_p), u_lo)
    return hx, hy, hz, u_lo, u_hi


def _as_inputs(*xs):
    dt = jnp.result_type(*[jnp.asarray(x) for x in xs], jnp.float32)
    return tuple(jnp.asarray(v, dt) for v in xs)


#: `pair_integral`'s arguments and their shapes (one pair: `jax.vmap` adds the batch axes).
_PAIR_SHAPES = dict(h=(3,), footprint=(4, 2), p0=(2,), p1=(2,), width=(), depth=(), alpha=())


def _pair_inputs(where: str, *args):
    """`_as_inputs` of `pair_integral`'s arguments, after `InputError` (one line) for one without
    its shape, or an `alpha` outside (0, 1) (values are checked where concrete, not traced)."""
    for (name, shape), x in zip(_PAIR_SHAPES.items(), args):
        shape_arg(where, name, x, shape)
    alpha = real_number(args[-1])
    if alpha is not None and not 0 < alpha < 1:
        raise InputError(f"{where}: `alpha` must lie in (0, 1), got {shown(args[-1])}")
    return _as_inputs(*args)


class PairGeometry(NamedTuple):
    """The view-independent part of one pixel-scratch pair (`pair_geometry`), which every view's
    `lit_integral` reads. Arrays in the inputs' dtype (`count`: int32); under `jax.vmap` each
    field gains a leading pair axis."""

    pieces: tuple  # (ua, ub, Ya, Yb), each (N_PIECES,): the boundary of F ∩ groove
    first: tuple  # (ua, ub, Ya, Yb), each (N_COMPACT,): the first pieces that are not points
    count: Array  # how many pieces are not points (0 where the footprint misses the groove)
    area: Array  # A = area(F ∩ groove), m^2
    scale: Array  # -w * (footprint orientation sign), m
    t: Array  # (2,) unit vector along the scratch
    b: Array  # (2,) unit vector across the scratch
    X: Array  # groove half-width in widths, x_max / w


def _pair_geometry(footprint, p0, p1, width, depth, hand_vjp: bool = True) -> PairGeometry:
    G = _groove(footprint, p0, p1, width, depth)
    # Q's boundary cut to the groove, once per pair: the area, and the pieces every view cuts
    # further to its lit slab (inside the groove), those that are not points first.
    ua, ub, Ya, Yb = (_cut_pieces if hand_vjp else _cut_values)(*G.pieces, -G.X, G.X)
    scale = -width * G.sign
    area = scale * jnp.sum((Ya + Yb) / 2 * (ub - ua))
    first, count = _compact((ua, ub, Ya, Yb), N_COMPACT)
    return PairGeometry((ua, ub, Ya, Yb), first, count, area, scale, G.t, G.b, G.X)


def pair_geometry(footprint: Float[ArrayLike, "4 2"], p0: Float[ArrayLike, "2"],
                  p1: Float[ArrayLike, "2"], width: Float[ArrayLike, ""],
                  depth: Float[ArrayLike, ""]) -> PairGeometry:
    """Stage 1 of `pair_integral`, which no view changes: the footprint cut to the scratch's
    length and to its groove, as `N_PIECES` boundary pieces with the `count` that are not points
    first (typically two: the footprint edges the groove crosses), and the area `A`. Same
    arguments as `pair_integral`; jittable, vmappable, differentiable (reverse mode)."""
    return _pair_geometry(*_as_inputs(footprint, p0, p1, width, depth))


def _lit_integral(geometry: PairGeometry, h, alpha, pieces: int, hand_vjp: bool = True):
    # Points contribute exactly nothing, value or gradient (`lobe.piece_values`, `_cut_transpose`),
    # so the first non-points are exact where they are all.
    first = (tuple(x[:pieces] for x in geometry.first) if pieces <= N_COMPACT
             else geometry.pieces)
    if hand_vjp and native.available(h.dtype):
        # The same integral, by the native kernel (its reverse pass: the kernel's partials).
        lit = native.lit(lobe.nodes(h.dtype), *first, geometry.X, h, geometry.b, geometry.t,
                          alpha)
        return geometry.scale * lobe.prefactor(alpha) * lit
    hx, hy, hz, u_lo, u_hi = _view(geometry, h)
    L = lobe.lobe(hx, hy, hz, alpha)
    lit = (_lit_sum if hand_vjp else _lit_sum_values)(
        lobe.nodes(h.dtype), *first, u_lo, u_hi, lobe.lobe_params(L))
    return geometry.scale * L.pref * lit


def lit_integral(geometry: PairGeometry, h: Float[ArrayLike, "3"], alpha: Float[ArrayLike, ""],
                 *, pieces: int = N_PIECES) -> Array:
    """Stage 2 of `pair_integral`, per view: `D_hat` from `geometry` (`pair_geometry`) under the
    half vector `h` with roughness `alpha`, in the geometry's dtype.

    `pieces` (static, 0..`N_PIECES`) integrates only the geometry's first `pieces` pieces that
    are not points (up to `N_COMPACT`; more integrates all `N_PIECES`): exact, in value and
    gradient, wherever `geometry.count <= pieces` (points contribute exactly nothing), and
    wrong elsewhere; the cost is about proportional to `pieces`. A renderer picks it per chunk of pairs from their counts (`jscratch.render`)."""
    dt = geometry.area.dtype
    return _lit_integral(geometry, jnp.asarray(h, dt), jnp.asarray(alpha, dt), int(pieces))


def pair_integral(
    h: Float[ArrayLike, "3"],
    footprint: Float[ArrayLike, "4 2"],
    p0: Float[ArrayLike, "2"],
    p1: Float[ArrayLike, "2"],
    width: Float[ArrayLike, ""],
    depth: Float[ArrayLike, ""],
    alpha: Float[ArrayLike, ""],
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Closed-form pair integral of docs/model.md §3 for one footprint and one scratch.

    **Arguments:**

    - `h`: `(3,)` board-frame half vector, `h_z > 0` (normalised here).
    - `footprint`: `(4, 2)` convex quad, counter-clockwise, board metres.
    - `p0, p1`: `(2,)` scratch endpoints (m).
    - `width, depth`: scratch width `w` and depth `d` (m); `alpha`: GGX roughness in (0, 1).

    **Returns:** `(D_hat, A)`: `∫∫_{F ∩ groove} D_x dx dy` and `area(F ∩ groove)`, both m^2, in the
    dtype of the inputs. The same as `lit_integral(pair_geometry(footprint, ...), h, alpha)` and
    that geometry's `area`: a renderer with several views computes the geometry once.

    Reverse-mode derivatives are hand-written (`_lit_sum`, `_cut_pieces`); forward mode (`jax.jvp`)
    is not available.

    **Raises:** `InputError`, one line: a wrong shape, or a concrete `alpha` outside (0, 1).
    """
    return _pair_integral(h, footprint, p0, p1, width, depth, alpha, True)


def _pair_integral(h, footprint, p0, p1, width, depth, alpha, hand_vjp: bool):
    h, footprint, p0, p1, width, depth, alpha = _pair_inputs(
        "pair_integral", h, footprint, p0, p1, width, depth, alpha)
    geometry = _pair_geometry(footprint, p0, p1, width, depth, hand_vjp)
    return _lit_integral(geometry, h, alpha, N_PIECES, hand_vjp), geometry.area


def _chord(u, y, y_lo, y_hi, uq):
    """Vertical section length at abscissae `uq` of the convex polygon `(u, y)` clipped to
    `y_lo <= y <= y_hi`."""
    ua, ya = u[:, None], y[:, None]
    ub, yb = jnp.roll(u, -1)[:, None], jnp.roll(y, -1)[:, None]
    du = ub - ua
    ok = (du != 0) & (uq >= jnp.minimum(ua, ub)) & (uq <= jnp.maximum(ua, ub))
    t = (uq - ua) / jnp.where(ok, du, 1)
    yq = ya + t * (yb - ya)
    big = jnp.asarray(jnp.finfo(u.dtype).max / 4, u.dtype)
    top = jnp.max(jnp.where(ok, yq, -big), axis=0)
    bot = jnp.min(jnp.where(ok, yq, big), axis=0)
    any_ok = jnp.any(ok, axis=0)
    c = jnp.minimum(top, y_hi) - jnp.maximum(bot, y_lo)
    return jnp.where(any_ok, jnp.maximum(c, 0), 0)


def pair_integral_quadrature(h, footprint, p0, p1, width, depth, alpha, n: int):
    """`pair_integral` by `n`-point Gauss-Legendre quadrature (`n` a static int) of
    `w ∫ chord(u) D_x(u) du` over the lit groove range `[u_lo, u_hi]`, with the GGX in its
    factored (cancellation-free) form. Same arguments and returns as `pair_integral`; `A` is the
    same rule applied to `chord(u)` over `[-x_max, x_max] / w`."""
    h, footprint, p0, p1, width, depth, alpha = _pair_inputs(
        "pair_integral_quadrature", h, footprint, p0, p1, width, depth, alpha)
    G = _groove(footprint, p0, p1, width, depth)
    hx, hy, hz, u_lo, u_hi = _view(G, h)
    L = lobe.lobe(hx, hy, hz, alpha)
    x, w = (jnp.asarray(v, h.dtype) for v in lobe.gauss_legendre(int(n)))

    def rule(a, b, f):
        half = (b - a) / 2
        uq = a + half * (x + 1)
        return half * jnp.sum(w * f(uq))

    def fd(uq):
        T1, T2 = lobe.lobe_terms(L, uq)
        return _chord(G.u, G.y, G.y_lo, G.y_hi, uq) * L.pref * (T1 * T1 + T1 + T2 * T2 + T2)

    D_hat = width * rule(u_lo, u_hi, fd)
    A = width * rule(-G.X, G.X, lambda uq: _chord(G.u, G.y, G.y_lo, G.y_hi, uq))
    return D_hat, A


