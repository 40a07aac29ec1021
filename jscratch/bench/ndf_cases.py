"""Test and benchmark cases (pair populations) for the scratch pair integral `jscratch.ndf.pair_integral`.

A case is one (pixel footprint, scratch, half vector) pair; a `Cases` batch holds numpy float64
arrays with a leading batch axis, in the argument order of the kernel. Everything is deterministic
(fixed seeds), so tests and the benchmark see the same pairs.

**Public API:**

- `Cases(h, footprint, p0, p1, width, depth, alpha)`: shapes `(n, 3)`, `(n, 4, 2)`, `(n, 2)`,
  `(n, 2)`, `(n,)`, `(n,)`, `(n,)`; board metres, `h` unit with `h_z > 0`, footprints convex CCW.
  Methods `astype(dtype)`, `take(index)`, `args()` (the tuple of arrays), `len()`.
- `concat(list_of_cases) -> Cases`.
- `random_cases(n=512, seed=20261120) -> Cases`: realistic pairs (0.3 m board, 256 px footprints,
  widths around 2.5e-4 m, alpha 0.01..0.5, half vectors from views at 20..70 degrees or near the lit
  direction).
- `adversarial_families() -> dict[str, Cases]`: one family per numerical hazard of
  the pair integral (see each `_fam_*`).
- `all_families() -> dict[str, Cases]`: `{"random": random_cases(), **adversarial_families()}`.
- `local_half_vector(h_local, p0, p1) -> h_board`, `lit_half_vector(u0, hy, p0, p1)`: helpers.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

BOARD = 0.3
PIXEL = BOARD / 256  # footprint side of a 256 x 256 image, metres
W0, D0 = 2.5e-4, 1.28e-4  # paper's optimisation start (docs/model.md §5)
U = 2.0**-12  # a length unit (~2.44e-4 m) in which exact binary geometry is written


class Cases(NamedTuple):
    h: np.ndarray
    footprint: np.ndarray
    p0: np.ndarray
    p1: np.ndarray
    width: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray

    def astype(self, dtype) -> "Cases":
        return Cases(*(np.asarray(a).astype(dtype) for a in self))

    def take(self, index) -> "Cases":
        return Cases(*(np.asarray(a)[index] for a in self))

    def args(self) -> tuple:
        return tuple(self)

    def len(self) -> int:
        return int(self.h.shape[0])


def concat(parts) -> Cases:
    parts = list(parts)
    return Cases(*(np.concatenate([getattr(p, f) for p in parts]) for f in Cases._fields))


def _build(rows) -> Cases:
    """rows: list of dicts with the seven fields."""
    return Cases(
        h=np.array([r["h"] for r in rows], dtype=np.float64).reshape(-1, 3),
        footprint=np.array([r["footprint"] for r in rows], dtype=np.float64).reshape(-1, 4, 2),
        p0=np.array([r["p0"] for r in rows], dtype=np.float64).reshape(-1, 2),
        p1=np.array([r["p1"] for r in rows], dtype=np.float64).reshape(-1, 2),
        width=np.array([r["width"] for r in rows], dtype=np.float64),
        depth=np.array([r["depth"] for r in rows], dtype=np.float64),
        alpha=np.array([r["alpha"] for r in rows], dtype=np.float64),
    )


def x_max(width, depth):
    """Groove half-width (docs/model.md §2), float64."""
    return 0.5 * width * np.sqrt(-np.expm1(-2.0 * depth / width))


def square(x0, y0, s):
    """Axis-aligned CCW square footprint with lower-left corner (x0, y0) and side s."""
    return np.array([[x0, y0], [x0 + s, y0], [x0 + s, y0 + s], [x0, y0 + s]])


def diamond(cx, cy, r):
    """CCW square rotated by 45 degrees: vertices at distance r from (cx, cy) along the axes."""
    return np.array([[cx, cy - r], [cx + r, cy], [cx, cy + r], [cx - r, cy]])


def _frame(p0, p1):
    d = np.asarray(p1, float) - np.asarray(p0, float)
    t = d / np.hypot(*d)
    return t, np.array([t[1], -t[0]])


def local_half_vector(h_local, p0, p1):
    """Board half vector whose scratch-local components are `h_local = (hx, hy, hz)`."""
    t, b = _frame(p0, p1)
    hx, hy, hz = h_local
    v = np.array([hx * b[0] + hy * t[0], hx * b[1] + hy * t[1], hz])
    return v / np.linalg.norm(v)


def lit_half_vector(u0, hy, p0, p1):
    """Unit board half vector that lights the groove at `u = x/w = u0` (n(u0).h is maximal there)
    with local along-scratch component `hy`."""
    phi = 2.0 * np.arctan(2.0 * u0)
    rho = np.sqrt(1.0 - hy * hy)
    return local_half_vector((-rho * np.sin(phi), hy, rho * np.cos(phi)), p0, p1)


def _crossing(theta, centre, length, frac=0.5):
    """Scratch of direction angle theta (from +x) through `centre`, `frac` of it before it."""
    t = np.array([np.cos(theta), np.sin(theta)])
    p0 = np.asarray(centre, float) - frac * length * t
    return p0, p0 + length * t


def _row(h, footprint, p0, p1, width, depth, alpha):
    return dict(h=h, footprint=footprint, p0=p0, p1=p1, width=width, depth=depth, alpha=alpha)


# ---------------------------------------------------------------------------------------------
# Realistic random population.


def random_cases(n: int = 512, seed: int = 20261120) -> Cases:
    """`n` realistic pairs. Footprints: pixels of a 256 x 256 image of the 0.3 m board. Scratches:
    lengths 5..25 mm, any direction, through a point of the footprint grown by one groove width (a
    few pairs miss or only touch), ends anywhere from before the footprint to after it (so some
    ends lie inside). Widths log-uniform in [1e-4, 6e-4] m, depth/width in [0.2, 2], alpha
    log-uniform in [0.01, 0.5]. Half vectors: half from a camera and a light at 1 m from the board
    centre at polar angles 20..70 degrees and random azimuths (mostly dark pairs), half near the
    direction that lights a random point of the groove (lit pairs, sharp peaks inside)."""
    rng = np.random.default_rng(seed)
    rows = []
    centre_board = np.array([BOARD / 2, BOARD / 2, 0.0])
    for i in range(n):
        r, c = rng.integers(4, 252, size=2)
        x0, y0 = c * PIXEL, BOARD - (r + 1) * PIXEL
        fp = square(x0, y0, PIXEL)
        w = float(np.exp(rng.uniform(np.log(1e-4), np.log(6e-4))))
        d = w * float(rng.uniform(0.2, 2.0))
        alpha = float(np.exp(rng.uniform(np.log(0.01), np.log(0.5))))
        xm = x_max(w, d)
        q = np.array([x0, y0]) + rng.uniform(-xm, PIXEL + xm, size=2)
        theta = rng.uniform(0, 2 * np.pi)
        length = rng.uniform(0.005, 0.025)
        # Mostly crossing; 1 in 5 has its start near the footprint, 1 in 5 its end.
        mode = i % 5
        if mode == 0:
            frac = rng.uniform(-PIXEL, PIXEL) / length
        elif mode == 1:
            frac = 1.0 + rng.uniform(-PIXEL, PIXEL) / length
        else:
            frac = rng.uniform(0.0, 1.0)
        p0, p1 = _crossing(theta, q, length, frac)
        p = np.array([x0 + PIXEL / 2, y0 + PIXEL / 2, 0.0])
        if i % 2 == 0:
            th_c, th_l = rng.uniform(np.radians(20), np.radians(70), size=2)
            az_c, az_l = rng.uniform(0, 2 * np.pi, size=2)
            cam = centre_board + np.array(
                [np.sin(th_c) * np.cos(az_c), np.sin(th_c) * np.sin(az_c), np.cos(th_c)]
            )
            lig = centre_board + np.array(
                [np.sin(th_l) * np.cos(az_l), np.sin(th_l) * np.sin(az_l), np.cos(th_l)]
            )
            wo = (cam - p) / np.linalg.norm(cam - p)
            wi = (lig - p) / np.linalg.norm(lig - p)
            h = (wo + wi) / np.linalg.norm(wo + wi)
        else:
            u0 = rng.uniform(-xm / w, xm / w)
            hy = alpha * rng.normal() * 0.7
            h = lit_half_vector(u0, np.clip(hy, -0.9, 0.9), p0, p1)
            if h[2] < 0.05:  # keep h_z > 0 comfortably
                h = lit_half_vector(0.0, 0.0, p0, p1)
        rows.append(_row(h, fp, p0, p1, w, d, alpha))
    return _build(rows)


# ---------------------------------------------------------------------------------------------
# Adversarial families: the numerical hazards of the pair integral (docs/model.md §3): sharp
# peaks down to alpha = 1e-4, grazing half vectors, footprints much larger or smaller than the
# groove, vertices on groove edges, scratches parallel to footprint edges.

_FP = square(0.15, 0.15, PIXEL)
_FC = np.array([0.15 + PIXEL / 2, 0.15 + PIXEL / 2])


def _fam_alpha():
    """alpha from 1e-4 to 0.9, a scratch crossing a pixel at a generic angle, lit at the groove
    centre, at 0.6 and 0.98 of the half-width (near the wall edge), and with hy = alpha/2."""
    rows = []
    p0, p1 = _crossing(0.3, _FC, 0.02)
    xm = x_max(W0, D0)
    for alpha in np.geomspace(1e-4, 0.9, 14):
        for u0, hy in ((0.0, 0.0), (0.6 * xm / W0, 0.0), (-0.98 * xm / W0, 0.0), (0.3 * xm / W0, alpha / 2)):
            rows.append(_row(lit_half_vector(u0, hy, p0, p1), _FP, p0, p1, W0, D0, alpha))
    return _build(rows)


def _fam_grazing():
    """h_z from 0.02 to 0.3: h across the scratch (both sides), along it, and at 30 degrees; deep
    (d/w = 50, walls up to vertical) and ordinary grooves; alpha 0.01 and 0.3."""
    rows = []
    theta = 1.1
    p0, p1 = _crossing(theta, _FC, 0.02)
    for hz in (0.02, 0.035, 0.07, 0.15, 0.3):
        for psi in (0.0, np.pi, np.pi / 2, np.pi / 6):
            s = np.sqrt(1 - hz * hz)
            h_local = (s * np.cos(psi), s * np.sin(psi), hz)
            h = local_half_vector(h_local, p0, p1)
            for dw in (1.0, 50.0):
                for alpha in (0.01, 0.3):
                    rows.append(_row(h, _FP, p0, p1, W0, dw * W0, alpha))
    return _build(rows)


def _fam_hy_zero():
    """Local h_y exactly 0 in floating point: scratches along +y (h = (hx, 0, hz)), along -x
    (h = (0, hy, hz)), and along the diagonal (1, 1) (h = (c, -c, hz)); sharp alphas; lit at the
    centre, half-way out and at 0.999 of the half-width."""
    rows = []
    xm = x_max(W0, D0)
    c = _FC
    geoms = [
        (np.array([c[0], c[1] - 0.01]), np.array([c[0], c[1] + 0.01]), "y"),
        (np.array([c[0] + 0.01, c[1]]), np.array([c[0] - 0.01, c[1]]), "x"),
        (np.array([c[0] - 0.0078125, c[1] - 0.0078125]), np.array([c[0] + 0.0078125, c[1] + 0.0078125]), "d"),
    ]
    for p0, p1, kind in geoms:
        t, b = _frame(p0, p1)
        for u0 in (0.0, 0.5 * xm / W0, 0.999 * xm / W0):
            phi = 2 * np.arctan(2 * u0)
            hx, hz = -np.sin(phi), np.cos(phi)
            if kind == "y":  # b = (1, 0) exactly
                h = np.array([hx, 0.0, hz])
            elif kind == "x":  # t = (-1, 0), b = (0, 1)
                h = np.array([0.0, hx, hz])
            else:  # t = (a, a), b = (a, -a)
                h = np.array([hx / np.sqrt(2), -hx / np.sqrt(2), hz])
            for alpha in (1e-4, 1e-3, 0.04):
                rows.append(_row(h, _FP, p0, p1, W0, D0, alpha))
    out = _build(rows)
    # The point of the family: h.t is exactly zero in float64 and float32.
    for dt in (np.float64, np.float32):
        cs = out.astype(dt)
        d = cs.p1 - cs.p0
        tt = d / np.sqrt((d * d).sum(-1, keepdims=True)).astype(dt)
        assert np.all(cs.h[:, 0] * tt[:, 0] + cs.h[:, 1] * tt[:, 1] == 0)
    return out


def _fam_width():
    """Width from 1/1000 to 100 footprint widths (d = w/2 and d = 2w) for a scratch through the
    footprint centre; lit at the centre and at an off-centre point inside the footprint."""
    rows = []
    p0, p1 = _crossing(0.4, _FC, 0.02)
    for w in PIXEL * np.geomspace(1e-3, 100.0, 11):
        for dw in (0.5, 2.0):
            d = dw * w
            xm = x_max(w, d)
            for alpha, u0 in ((0.04, 0.0), (0.3, 0.0), (0.04, 0.35 * min(xm, PIXEL / 2) / w)):
                rows.append(_row(lit_half_vector(u0, 0.0, p0, p1), _FP, p0, p1, w, d, alpha))
    return _build(rows)


def _fam_depth():
    """depth/width from 1e-3 to 50 at w = 2.5e-4 m; lit half-way out (normals tilt with d/w), at
    the centre with a small hy, and at a fixed wall slope."""
    rows = []
    p0, p1 = _crossing(2.0, _FC, 0.02)
    for dw in np.geomspace(1e-3, 50.0, 12):
        d = dw * W0
        xm = x_max(W0, d)
        for alpha in (0.04, 0.2):
            for u0, hy in ((0.5 * xm / W0, 0.0), (0.0, 0.01), (0.2, 0.0)):
                rows.append(_row(lit_half_vector(u0, hy, p0, p1), _FP, p0, p1, W0, d, alpha))
    return _build(rows)


def _fam_vertex_on_edge():
    """Footprint vertices exactly on a groove edge. Scratch along +y from (0.125, 0.1), w = 2^-12,
    d = 50 w, so x_max = w/2 = 2^-13 exactly in every precision and the local x of a vertex is an
    exact difference: squares whose edge lies on the groove side from inside and from outside,
    diamonds with a vertex on the side (pointing in and out) or at a groove corner, a square corner
    at the groove corner, a footprint edge on the groove end; plus ordinary d/w with vertices at
    the float64 x_max (on the edge to rounding) and the footprint reaching into the groove."""
    rows = []
    x0, y0 = 0.125, 0.1
    w, d = 2.0**-12, 50 * 2.0**-12
    xm = 2.0**-13
    p0, p1 = np.array([x0, y0]), np.array([x0, y0 + 0.015625])
    s = 2.0**-10  # footprint side, exact
    fps = [
        square(x0 + xm - s, 0.105, s),  # right edge on the groove's right side, from inside
        square(x0 + xm, 0.105, s),  # left edge on the right side, from outside (A = 0)
        square(x0 - xm - s, 0.105, s),  # right edge on the left side, from outside (A = 0)
        diamond(x0 + xm - s / 2, 0.105, s / 2),  # right vertex on the right side, from inside
        diamond(x0 + xm + s / 2, 0.105, s / 2),  # left vertex on the right side (A = 0)
        diamond(x0 + xm, y0, s / 4),  # diamond centred on the groove's corner
        square(x0 + xm - s, y0 - s, s),  # top-right corner at the groove corner (A = 0)
        square(x0 + xm - s / 2, y0, s),  # bottom edge on the groove end
        square(x0 - xm, y0 - xm, 2 * xm),  # exactly as wide as the groove, across its end
    ]
    for fp in fps:
        for u0 in (0.0, 0.45):
            h = lit_half_vector(u0, 0.0, p0, p1)
            for alpha in (0.04, 1e-3):
                rows.append(_row(h, fp, p0, p1, w, d, alpha))
    # Ordinary d/w: vertex at the float64 x_max, footprint reaching into the groove.
    xm2 = x_max(W0, D0)
    for fp in (diamond(x0 + xm2 - s / 2, 0.105, s / 2), square(x0 - xm2, 0.105, s)):
        for u0 in (0.0, 0.9 * xm2 / W0):
            rows.append(_row(lit_half_vector(u0, 0.0, p0, p1), fp, p0, p1, W0, D0, 0.04))
    return _build(rows)


def _fam_parallel():
    """Scratches exactly parallel or perpendicular to the footprint edges: along +-x and +-y
    through the centre, along y with the groove straddling the footprint's left edge, along x just
    inside the bottom edge; sharp and moderate alpha, lit at the centre and off-centre."""
    rows = []
    x0, y0 = 0.15, 0.15
    c = _FC
    xm = x_max(W0, D0)
    geoms = [
        (np.array([c[0], c[1] - 0.01]), np.array([c[0], c[1] + 0.01])),
        (np.array([c[0], c[1] + 0.01]), np.array([c[0], c[1] - 0.01])),
        (np.array([c[0] - 0.01, c[1]]), np.array([c[0] + 0.01, c[1]])),
        (np.array([c[0] + 0.01, c[1]]), np.array([c[0] - 0.01, c[1]])),
        (np.array([x0 + 0.3 * xm, c[1] - 0.01]), np.array([x0 + 0.3 * xm, c[1] + 0.01])),
        (np.array([c[0] - 0.01, y0 + 0.5 * xm]), np.array([c[0] + 0.01, y0 + 0.5 * xm])),
    ]
    for p0, p1 in geoms:
        for alpha in (1e-3, 0.04):
            for u0 in (0.0, 0.7 * xm / W0):
                rows.append(_row(lit_half_vector(u0, 0.0, p0, p1), _FP, p0, p1, W0, D0, alpha))
    return _build(rows)


def _fam_endpoints():
    """Scratch ends inside, exactly on (edge and vertex) and outside the footprint, at a generic
    angle and axis-aligned: both ends inside (scratch inside the footprint), one end inside, an end
    on the right edge pointing in and out, an end on a vertex, ends just outside (1e-9 m) and far."""
    rows = []
    x0, y0 = 0.15, 0.15
    s = PIXEL
    c = _FC
    g = np.array([np.cos(0.7), np.sin(0.7)])
    geoms = [
        (c - 0.3 * s * g, c + 0.3 * s * g),  # both inside
        (c, c + 0.01 * g),  # one inside (start)
        (c - 0.01 * g, c),  # one inside (end)
        (np.array([x0 + s, c[1]]), np.array([x0 + s - 0.01, c[1]])),  # on right edge, pointing in
        (np.array([x0 + s, c[1]]), np.array([x0 + s + 0.01, c[1]])),  # on right edge, pointing out (A = 0)
        (np.array([x0 + s, c[1] + 0.2 * s]), np.array([x0 + s, c[1] + 0.2 * s]) - 0.01 * g),  # on edge, generic
        (np.array([x0, y0]), np.array([x0, y0]) + 0.01 * g),  # on a vertex, pointing in
        (np.array([x0, y0]), np.array([x0, y0]) - 0.01 * g),  # on a vertex, pointing out
        (np.array([x0 + s + 1e-9, c[1]]), np.array([x0 + s + 0.01, c[1]])),  # just outside, along x
        (np.array([x0 - 1e-9, c[1]]) - 0.01 * g, np.array([x0 - 1e-9, c[1]])),  # just outside, generic
        (c + 0.002 * g, c + 0.012 * g),  # outside, far
    ]
    for p0, p1 in geoms:
        for alpha, u0 in ((0.04, 0.0), (0.3, 0.2)):
            rows.append(_row(lit_half_vector(u0, 0.0, p0, p1), _FP, p0, p1, W0, D0, alpha))
    return _build(rows)


def _fam_zero_length():
    """Zero-length scratches (p0 == p1 exactly): inside the footprint, on an edge, on a vertex,
    outside; D_hat = A = 0."""
    rows = []
    x0, y0 = 0.15, 0.15
    pts = [_FC, np.array([x0 + PIXEL, _FC[1]]), np.array([x0, y0]), _FC + 0.01]
    for p in pts:
        for alpha in (1e-4, 0.04, 0.9):
            rows.append(_row(np.array([0.3, 0.1, np.sqrt(0.9)]), _FP, p, p.copy(), W0, D0, alpha))
    return _build(rows)


def _fam_far_along():
    """A small footprint far along a board-long scratch: scratches corner to corner (slightly off
    the diagonal) and edge to edge; pixel (0.3/256) and 0.3/1024 footprints near the far end and in
    the middle, each crossed by the scratch; lit at the centre and half-way out."""
    rows = []
    xm = x_max(W0, D0)
    scratches = [
        (np.array([0.001, 0.002]), np.array([0.299, 0.2985])),
        (np.array([0.0005, 0.15]), np.array([0.2995, 0.1507])),
    ]
    for p0, p1 in scratches:
        t, _ = _frame(p0, p1)
        length = np.hypot(*(p1 - p0))
        for s in (PIXEL, BOARD / 1024):
            for f in (0.97, 0.5):
                q = p0 + f * length * t
                fp = square(q[0] - 0.37 * s, q[1] - 0.61 * s, s)
                for u0 in (0.0, 0.5 * xm / W0):
                    rows.append(_row(lit_half_vector(u0, 0.0, p0, p1), fp, p0, p1, W0, D0, 0.04))
    return _build(rows)


def _fam_miss():
    """Footprints that miss the groove (positive distance): beside it, beyond its end, diagonal."""
    rows = []
    c = _FC
    g = np.array([np.cos(0.7), np.sin(0.7)])
    n = np.array([g[1], -g[0]])
    geoms = [
        (c + 2 * PIXEL * n, c + 2 * PIXEL * n + 0.01 * g),
        (c + 2 * PIXEL * g, c + 0.012 * g),
        (c - 0.012 * g, c - 2 * PIXEL * g),
    ]
    for p0, p1 in geoms:
        for alpha in (1e-4, 0.04):
            rows.append(_row(lit_half_vector(0.0, 0.0, p0, p1), _FP, p0, p1, W0, D0, alpha))
    return _build(rows)


def adversarial_families() -> dict[str, Cases]:
    """The adversarial families of the pair integral's numerical hazards (and footprints that
    miss), name -> Cases."""
    return {
        "alpha": _fam_alpha(),
        "grazing_hz": _fam_grazing(),
        "hy_zero": _fam_hy_zero(),
        "width": _fam_width(),
        "depth_ratio": _fam_depth(),
        "vertex_on_edge": _fam_vertex_on_edge(),
        "parallel_perpendicular": _fam_parallel(),
        "endpoints": _fam_endpoints(),
        "zero_length": _fam_zero_length(),
        "far_along": _fam_far_along(),
        "miss": _fam_miss(),
    }


def all_families() -> dict[str, Cases]:
    """`{"random": random_cases(), **adversarial_families()}`."""
    return {"random": random_cases(), **adversarial_families()}
