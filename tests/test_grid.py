"""Tests of jscratch.grid (through `jscratch.bvh`, its public face): the pair list against an
all-pairs brute force (separating axes, checked itself against polygon clipping), in float64 and
float32 under jit; overflow and regrowth; the skin's rebin test; compaction; the groove half width;
a groove ending on the board's edge; the input errors; the native strip and cell stage against the
jnp one, bit for bit."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import bvh, grid, native

BOARD = (0.3, 0.3)


# ---------------------------------------------------------------------------------------------
# Independent references (numpy, float64)


def _local_frame(p0, p1):
    v = p1 - p0
    length = np.hypot(v[:, 0], v[:, 1])
    t = np.where(length[:, None] > 0, v / np.where(length > 0, length, 1)[:, None], [0.0, 1.0])
    b = np.stack([t[:, 1], -t[:, 0]], -1)
    return t, b, length


def _x_max(width, depth):
    return 0.5 * width * np.sqrt(1 - np.exp(-2 * depth / width))


def brute_penetration(p0, p1, width, depth, board, shape, chunk=16):
    """All pairs: `(N, H, W)` overlap depth (m) of groove and footprint, min over the 4 separating
    axes, from projections of the polygons' vertices (float64). `> 0` iff positive-area overlap.
    Computed `chunk` scratches at a time (memory)."""
    n = len(p0)
    if n > chunk:
        w = np.broadcast_to(np.asarray(width, np.float64), (n,))
        d = np.broadcast_to(np.asarray(depth, np.float64), (n,))
        return np.concatenate([
            brute_penetration(p0[i:i + chunk], p1[i:i + chunk], w[i:i + chunk], d[i:i + chunk],
                              board, shape, chunk)
            for i in range(0, n, chunk)
        ])
    p0 = np.asarray(p0, np.float64)
    p1 = np.asarray(p1, np.float64)
    n = len(p0)
    w = np.broadcast_to(np.asarray(width, np.float64), (n,))
    d = np.broadcast_to(np.asarray(depth, np.float64), (n,))
    sx, sy = board
    h_px, w_px = shape
    xm = _x_max(w, d)[:, None]
    t, b, _ = _local_frame(p0, p1)
    verts = np.stack([p0 + xm * b, p0 - xm * b, p1 - xm * b, p1 + xm * b], 1)  # (N, 4, 2)
    xe = np.arange(w_px + 1) * (sx / w_px)  # column edges, left to right
    ye = sy - np.arange(h_px + 1) * (sy / h_px)  # row edges, top to bottom
    gx0, gx1 = verts[..., 0].min(1), verts[..., 0].max(1)
    gy0, gy1 = verts[..., 1].min(1), verts[..., 1].max(1)
    ox = np.minimum(gx1[:, None], xe[None, 1:]) - np.maximum(gx0[:, None], xe[None, :-1])
    oy = np.minimum(gy1[:, None], ye[None, :-1]) - np.maximum(gy0[:, None], ye[None, 1:])
    out = np.minimum(ox[:, None, :], oy[:, :, None])
    for ax in (b, t):
        pv = np.einsum("nkd,nd->nk", verts, ax)
        px = np.stack([xe[None, :-1] * ax[:, :1], xe[None, 1:] * ax[:, :1]])  # (2, N, W)
        py = np.stack([ye[None, 1:] * ax[:, 1:], ye[None, :-1] * ax[:, 1:]])  # (2, N, H)
        f0 = px.min(0)[:, None, :] + py.min(0)[:, :, None]
        f1 = px.max(0)[:, None, :] + py.max(0)[:, :, None]
        o = np.minimum(pv.max(1)[:, None, None], f1) - np.maximum(pv.min(1)[:, None, None], f0)
        out = np.minimum(out, o)
    # A degenerate groove (zero length or x_max = 0) has zero area; rounding in the projections
    # above could leave it a 1e-18 m overlap.
    _, _, length = _local_frame(p0, p1)
    degenerate = (length == 0) | (xm[:, 0] == 0)
    out[degenerate] = np.minimum(out[degenerate], 0.0)
    return out


def _clip_area(poly, rect):
    """Area of a convex polygon clipped to an axis-aligned rectangle (Sutherland-Hodgman)."""
    x0, x1, y0, y1 = rect
    pts = list(poly)
    for k, c, s in ((0, x0, 1), (0, x1, -1), (1, y0, 1), (1, y1, -1)):
        out = []
        for a, b_ in zip(pts, pts[1:] + pts[:1]):
            ina, inb = s * (a[k] - c) >= 0, s * (b_[k] - c) >= 0
            if ina:
                out.append(a)
            if ina != inb:
                f = (c - a[k]) / (b_[k] - a[k])
                out.append(a + f * (b_ - a))
        pts = out
        if not pts:
            return 0.0
    x = np.array([q[0] for q in pts])
    y = np.array([q[1] for q in pts])
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def pair_sets(pairs, shape):
    v = np.asarray(pairs.valid)
    s = np.asarray(pairs.scratch)[v]
    r, c = np.divmod(np.asarray(pairs.pixel)[v], shape[1])
    got = set(zip(s.tolist(), r.tolist(), c.tolist()))
    assert len(got) == int(v.sum()), "duplicate pairs"
    return got


def check_against_brute(pairs, p0, p1, width, depth, board, shape, tol):
    """Every positive-area pair is present; every present pair is within 2 tol of touching."""
    assert not bool(pairs.overflow)
    pen = brute_penetration(p0, p1, width, depth, board, shape)
    must = set(map(tuple, np.argwhere(pen > 0).tolist()))
    may = set(map(tuple, np.argwhere(pen >= -2 * tol).tolist()))
    got = pair_sets(pairs, shape)
    missed = must - got
    assert not missed, f"{len(missed)} missed pairs, e.g. {sorted(missed)[:5]}"
    spurious = got - may
    assert not spurious, f"{len(spurious)} spurious pairs, e.g. {sorted(spurious)[:5]}"
    return got, must, pen


# ---------------------------------------------------------------------------------------------
# Scenes


def make_scene(rng, n, board, shape, *, wide=False):
    """A mix of short, long, board-crossing, axis-aligned, on-cell-edge, zero-length and
    zero-depth scratches (float64 numpy arrays)."""
    sx, sy = board
    h_px, w_px = shape
    px, py = sx / w_px, sy / h_px
    k = n // 8
    parts = []
    # short and long random
    for lo, hi, m in ((0.3 * px, 3 * px, 2 * k), (0.005, 0.025, 2 * k), (0.1, 0.4, k)):
        mid = rng.uniform(0, 1, (m, 2)) * board
        ang = rng.uniform(0, 2 * np.pi, m)
        half = 0.5 * rng.uniform(lo, hi, m)[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1)
        parts.append((np.clip(mid - half, 0, board), np.clip(mid + half, 0, board)))
    # board-crossing: corner to corner and edge to opposite edge
    m = max(k // 2, 2)
    a = np.stack([np.zeros(m), rng.uniform(0, sy, m)], -1)
    b_ = np.stack([np.full(m, sx), rng.uniform(0, sy, m)], -1)
    a[0], b_[0] = (0, 0), (sx, sy)
    a[1], b_[1] = (0, sy), (sx, 0)
    parts.append((a, b_))
    # axis-aligned and on cell edges / corners
    m = max(k // 4, 2)
    cols = rng.integers(0, w_px, m)
    rows = rng.integers(0, h_px, m)
    lens = rng.integers(1, 6, m)
    ya = sy - rows * py
    parts.append((np.stack([cols * px, ya], -1), np.stack([(cols + lens) * px, ya], -1)))
    parts.append((np.stack([cols * px, ya], -1), np.stack([cols * px, ya - lens * py], -1)))
    # diagonals through cell corners
    parts.append((np.stack([cols * px, ya], -1), np.stack([(cols + lens) * px, ya - lens * py], -1)))
    # axis-aligned at random offsets
    mid = rng.uniform(0, 1, (m, 2)) * board
    parts.append((mid, mid + [0.01, 0.0]))
    parts.append((mid, mid + [0.0, -0.013]))
    # zero length
    mid = rng.uniform(0, 1, (m, 2)) * board
    parts.append((mid, mid.copy()))
    p0 = np.concatenate([p[0] for p in parts])
    p1 = np.concatenate([p[1] for p in parts])
    p0, p1 = np.clip(p0, 0, board), np.clip(p1, 0, board)
    nn = len(p0)
    width = np.full(nn, 2.5e-4)
    depth = np.full(nn, 1.28e-4)
    if wide:  # grooves up to a few pixels wide
        width = rng.uniform(2.5e-4, 3 * max(px, py), nn)
        depth = width * rng.uniform(0.1, 1.0, nn)
    depth[::17] = 0.0  # zero-area grooves
    # on-cell-edge grooves: horizontal scratch whose groove edge lies on a row edge
    xm = _x_max(width, depth)
    m = max(k // 4, 2)
    idx = np.arange(nn - 2 * m, nn - m)
    rows = rng.integers(1, h_px, m)
    yc = sy - rows * py + xm[idx]
    p0[idx] = np.stack([rng.uniform(0, sx / 2, m), yc], -1)
    p1[idx] = p0[idx] + [0.02, 0.0]
    idx = np.arange(nn - m, nn)
    cols = rng.integers(1, w_px, m)
    xc = cols * px - xm[idx]
    p0[idx] = np.stack([xc, rng.uniform(0, sy / 2, m)], -1)
    p1[idx] = p0[idx] + [0.0, 0.02]
    return p0, p1, width, depth


# ---------------------------------------------------------------------------------------------
# Binning equals brute force


@pytest.mark.float64
@pytest.mark.parametrize(
    "board, shape, n, wide",
    [
        (BOARD, (64, 64), 400, True),
        ((0.4, 0.25), (48, 96), 240, True),
        (BOARD, (512, 512), 96, False),
    ],
)
def test_no_missed_pairs_float64(board, shape, n, wide):
    rng = np.random.default_rng(hash((shape, n)) % 2**32)
    p0, p1, width, depth = make_scene(rng, n, board, shape, wide=wide)
    pairs, spec = bvh.build_pairs(p0, p1, width, depth, board=board, shape=shape)
    assert pairs.pixel.dtype == jnp.int32 and pairs.scratch.dtype == jnp.int32
    got, must, pen = check_against_brute(
        pairs, p0, p1, width, depth, board, shape, bvh.pair_tolerance(board, jnp.float64)
    )
    # zero-area grooves never get pairs; the padding holds the sentinel N
    zero = np.nonzero((np.hypot(*(p1 - p0).T) == 0) | (depth == 0))[0]
    assert len(zero) > 0 and not any(s in set(zero.tolist()) for s, _, _ in got)
    assert np.all(np.asarray(pairs.scratch)[~np.asarray(pairs.valid)] == len(p0))
    # in float64 the slack is 2e-15 m: the list equals the brute-force positive-area set up to
    # pairs that touch (zero overlap, from the on-edge scratches)
    extra = got - must
    assert all(abs(pen[e]) < 1e-12 for e in extra)
    assert len(extra) < 0.05 * len(must)
    # padding efficiency: real pairs over slots, close to 1/margin
    assert int(np.asarray(pairs.valid).sum()) / spec.pair_capacity > 0.6
    # per-scratch work follows the scratch's own extent, not the image size: at most
    # (extent of the groove along its major grid axis, in pixels) + 2 strips per scratch, plus
    # the one spare strip per scratch that makes the strip range robust to XLA evaluating its
    # first strip twice with different rounding (grid._strip_setup)
    t, b, length = _local_frame(p0, p1)
    xm = _x_max(width, depth)
    kx, ky = shape[1] / board[0], shape[0] / board[1]
    ext = np.maximum(
        (length * np.abs(t[:, 0]) + 2 * xm * np.abs(b[:, 0])) * kx,
        (length * np.abs(t[:, 1]) + 2 * xm * np.abs(b[:, 1])) * ky,
    )
    area = (length > 0) & (xm > 0)
    bound = np.sum(np.where(area, np.floor(ext) + 3, 0))
    assert spec.strip_capacity <= bvh.DEFAULT_MARGIN * bound + 64


def test_no_missed_pairs_float32_and_jit():
    board, shape = (0.3, 0.2), (80, 120)
    rng = np.random.default_rng(7)
    p0, p1, width, depth = (a.astype(np.float32) for a in make_scene(rng, 320, board, shape))
    spec = bvh.allocate(p0, p1, width, depth, board=board, shape=shape)
    pairs = bvh.update(spec, p0, p1, width, depth)  # bvh.update is jax.jit-compiled
    assert pairs.bin_p0.dtype == jnp.float32 and pairs.bin_half_width.dtype == jnp.float32
    got, must, _ = check_against_brute(
        pairs, p0, p1, width, depth, board, shape, bvh.pair_tolerance(board, jnp.float32)
    )
    assert len(got - must) < 0.05 * len(must)


def test_brute_force_reference_agrees_with_polygon_clipping():
    # The reference itself: overlap depth > 0 iff the clipped polygon has positive area.
    board, shape = BOARD, (16, 16)
    rng = np.random.default_rng(3)
    p0, p1, width, depth = make_scene(rng, 64, board, shape, wide=True)
    pen = brute_penetration(p0, p1, width, depth, board, shape)
    t, b, _ = _local_frame(p0, p1)
    xm = _x_max(width, depth)[:, None]
    sx, sy = board
    idx = np.argwhere(np.abs(pen) > 1e-9)
    idx = idx[rng.choice(len(idx), 3000, replace=False)]
    n_pos = 0
    for i, r, c in idx:
        poly = [p0[i] + xm[i] * b[i], p1[i] + xm[i] * b[i], p1[i] - xm[i] * b[i], p0[i] - xm[i] * b[i]]
        rect = (c * sx / 16, (c + 1) * sx / 16, sy - (r + 1) * sy / 16, sy - r * sy / 16)
        area = _clip_area(poly, rect)
        assert (area > 1e-16) == (pen[i, r, c] > 0), (i, r, c, area, pen[i, r, c])
        n_pos += area > 0
    assert 100 < n_pos < len(idx)


# ---------------------------------------------------------------------------------------------
# Overflow and regrowth


@pytest.mark.float64
def test_overflow_flag_in_jit_and_driver_regrows(random_layout):
    board, shape = BOARD, (64, 64)
    rng = np.random.default_rng(11)
    n = 200
    mid, u = random_layout(rng, n, 0.05, 0.25)
    short = (mid - 0.002 * u, mid + 0.002 * u)
    long_ = (mid - 0.04 * u, mid + 0.04 * u)
    width, depth = np.full(n, 2.5e-4), np.full(n, 1.28e-4)
    spec = bvh.allocate(*short, width, depth, board=board, shape=shape)
    update = bvh.update  # a jax.jit-compiled function: the flag is raised inside jit
    assert not bool(update(spec, *short, width, depth).overflow)
    assert bool(update(spec, *long_, width, depth).overflow)  # too many strips and pairs
    # wider grooves need more cells per strip than measured
    assert bool(update(spec, *short, 40 * width, 40 * depth).overflow)
    # only the pair capacity too small
    tiny = bvh.GridSpec(board, shape, spec.strip_capacity, spec.rows_per_strip, 64)
    assert bool(update(tiny, *short, width, depth).overflow)
    # the driver regrows and returns the complete list
    pairs, spec2 = bvh.build_pairs(*long_, width, depth, board=board, shape=shape, spec=spec)
    assert spec2.pair_capacity > spec.pair_capacity
    check_against_brute(pairs, *long_, width, depth, board, shape, 1e-14)
    # reusing a large enough spec keeps it
    pairs3, spec3 = bvh.build_pairs(*short, width, depth, board=board, shape=shape, spec=spec2)
    assert spec3 is spec2
    check_against_brute(pairs3, *short, width, depth, board, shape, 1e-14)


# ---------------------------------------------------------------------------------------------
# Rebinning test


@pytest.mark.float64
def test_needs_rebin_and_maybe_update(random_layout):
    board, shape = BOARD, (64, 64)
    rng = np.random.default_rng(5)
    n = 120
    mid, u = random_layout(rng, n, 0.03, 0.27)
    p0, p1 = mid - 0.006 * u, mid + 0.006 * u
    p1[0] = p0[0]  # a zero-length scratch
    width, depth = np.full(n, 2.5e-4), np.full(n, 1.28e-4)
    skin = 1e-3
    pairs, spec = bvh.build_pairs(p0, p1, width, depth, board=board, shape=shape, skin=skin)
    needs = bvh.needs_rebin  # jax.jit-compiled
    assert not bool(needs(pairs, p0, p1, width, depth))
    # the list with skin holds every pair of the unmoved scene
    check_against_brute_superset(pairs, p0, p1, width, depth, board, shape)
    # translations under the skin (along and across) keep the list valid
    shift = rng.uniform(-0.99, 0.99, (n, 2)) * skin / np.sqrt(2)
    assert not bool(needs(pairs, p0 + shift, p1 + shift, width, depth))
    check_against_brute_superset(pairs, p0 + shift, p1 + shift, width, depth, board, shape)
    # moving the zero-length scratch anywhere needs no rebin (it has no pairs)
    q0 = p0.copy()
    q0[0] += 0.1
    assert not bool(needs(pairs, q0, q0 + (p1 - p0), width, depth))
    # one scratch moving by more than the skin, or widening past it, needs a rebin
    q0, q1 = p0.copy(), p1.copy()
    q0[7] += [1.01 * skin, 0]
    q1[7] += [1.01 * skin, 0]
    assert bool(needs(pairs, q0, q1, width, depth))
    # widening past the skin (x_max 1e-4 -> 3e-3 m) needs one; widening inside it does not
    wider = np.where(np.arange(n) == 3, 30 * width, width)
    assert bool(needs(pairs, p0, p1, wider, np.where(np.arange(n) == 3, 30 * depth, depth)))
    assert not bool(needs(pairs, p0, p1, wider, depth))  # x_max 1e-4 -> 6.9e-4 m < 1e-4 + skin
    # lengthening one scratch by more than the skin at an end
    q1 = p1.copy()
    q1[9] += 2 * skin * u[9]
    assert bool(needs(pairs, p0, q1, width, depth))
    # rotation about the midpoint: small angles fit in the skin, large ones do not
    rot = lambda a: np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])  # noqa: E731
    for angle, expect in ((0.02, False), (0.3, True)):
        q0, q1 = p0.copy(), p1.copy()
        q0[5] = mid[5] + rot(angle) @ (p0[5] - mid[5])
        q1[5] = mid[5] + rot(angle) @ (p1[5] - mid[5])
        assert bool(needs(pairs, q0, q1, width, depth)) == expect
    # without skin: unchanged scene needs none, any growth does
    # (the skin's capacities are ample for the same scene without skin: no new allocation)
    spec0 = bvh.GridSpec(board, shape, spec.strip_capacity, spec.rows_per_strip, spec.pair_capacity)
    pairs0, spec0b = bvh.build_pairs(p0, p1, width, depth, board=board, shape=shape, spec=spec0)
    assert spec0b is spec0
    check_against_brute(pairs0, p0, p1, width, depth, board, shape, 1e-14)
    assert not bool(needs(pairs0, p0, p1, width, depth))
    assert bool(needs(pairs0, p0 + [1e-6, 0], p1 + [1e-6, 0], width, depth))
    # a groove binned with zero area (depth 0, no skin) has no pairs: giving it depth needs one
    flat = np.where(np.arange(n) == 4, 0.0, depth)
    pairs_flat, _ = bvh.build_pairs(p0, p1, width, flat, board=board, shape=shape, spec=spec0)
    assert not bool(needs(pairs_flat, p0, p1, width, flat))
    assert bool(needs(pairs_flat, p0, p1, width, depth))
    # maybe_update in jit: keeps the list when not needed, rebins when needed
    mu = bvh.maybe_update  # jax.jit-compiled
    same = mu(spec, pairs, p0 + shift, p1 + shift, width, depth)
    np.testing.assert_array_equal(same.bin_p0, pairs.bin_p0)
    np.testing.assert_array_equal(same.pixel, pairs.pixel)
    moved = mu(spec, pairs, p0 + 0.01, p1 + 0.01, width, depth)
    np.testing.assert_allclose(moved.bin_p0, p0 + 0.01)
    ref = bvh.update(spec, p0 + 0.01, p1 + 0.01, width, depth)
    np.testing.assert_array_equal(moved.pixel, ref.pixel)
    np.testing.assert_array_equal(moved.valid, ref.valid)


def check_against_brute_superset(pairs, p0, p1, width, depth, board, shape):
    assert not bool(pairs.overflow)
    pen = brute_penetration(p0, p1, width, depth, board, shape)
    must = set(map(tuple, np.argwhere(pen > 0).tolist()))
    missed = must - pair_sets(pairs, shape)
    assert not missed, f"{len(missed)} missed pairs"





def test_compact():
    pairs = bvh.Pairs(
        pixel=jnp.array([3, 1, 4, 1, 5, 0], jnp.int32),
        scratch=jnp.array([0, 1, 2, 2, 1, 9], jnp.int32),
        valid=jnp.array([True, False, True, True, True, False]),
        overflow=jnp.array(False),
    )
    c = jax.jit(bvh.compact, static_argnums=1)(pairs, 5)
    np.testing.assert_array_equal(c.pixel, [3, 4, 1, 5, 0])
    np.testing.assert_array_equal(c.scratch, [0, 2, 2, 1, 9])
    np.testing.assert_array_equal(c.valid, [True, True, True, True, False])
    assert not bool(c.overflow)
    small = bvh.compact(pairs, 3)
    assert bool(small.overflow)
    np.testing.assert_array_equal(small.pixel, [3, 4, 1])


# ---------------------------------------------------------------------------------------------
# Small pieces and errors


@pytest.mark.float64
def test_groove_half_width_matches_spec():
    w, d = 2.5e-4, 1.28e-4
    assert float(bvh.groove_half_width(w, d)) == pytest.approx(0.5 * w * np.sqrt(1 - np.exp(-2 * d / w)), rel=1e-14)
    assert float(bvh.groove_half_width(w, 0.0)) == 0.0


def test_errors():
    p0 = np.zeros((3, 2))
    p1 = np.ones((3, 2)) * 0.1
    kw = dict(board=BOARD, shape=(8, 8))
    with pytest.raises(ValueError, match="p0 must have shape"):
        bvh.allocate(np.zeros((3, 3)), p1, 1e-4, 1e-4, **kw)
    with pytest.raises(ValueError, match="p1 must have the shape"):
        bvh.build_pairs(p0, p1[:2], 1e-4, 1e-4, **kw)
    with pytest.raises(ValueError, match="p0 has non-finite"):
        bvh.build_pairs(np.where(np.eye(3, 2) > 0, np.nan, p0), p1, 1e-4, 1e-4, **kw)
    with pytest.raises(ValueError, match="width must be > 0"):
        bvh.allocate(p0, p1, -1e-4, 1e-4, **kw)
    with pytest.raises(ValueError, match="board must be"):
        bvh.allocate(p0, p1, 1e-4, 1e-4, board=(0.3, -1), shape=(8, 8))
    with pytest.raises(ValueError, match="shape must be"):
        bvh.allocate(p0, p1, 1e-4, 1e-4, board=BOARD, shape=(8,))
    with pytest.raises(ValueError, match="margin must be"):
        bvh.allocate(p0, p1, 1e-4, 1e-4, margin=0.5, **kw)
    with pytest.raises(ValueError, match="pair_capacity must be"):
        bvh.GridSpec(BOARD, (8, 8), 64, 3, 0)
    pairs, spec = bvh.build_pairs(p0, p1, 1e-4, 1e-4, **kw)
    with pytest.raises(ValueError, match="spec is for board"):
        bvh.build_pairs(p0, p1, 1e-4, 1e-4, board=BOARD, shape=(9, 8), spec=spec)
    with pytest.raises(ValueError, match=r"width must be a scalar or have shape \(3,\)"):
        bvh.update(spec, p0, p1, np.ones(4), 1e-4)
    # inside jit: NaN and bad values raise at run time with the argument's name
    upd = bvh.update
    with pytest.raises(Exception, match="p1 has non-finite entries"):
        upd(spec, p0, np.where(np.eye(3, 2) > 0, np.nan, p1), 1e-4, 1e-4)
    with pytest.raises(Exception, match="depth must be finite and >= 0"):
        upd(spec, p0, p1, 1e-4, -1e-4)
    with pytest.raises(ValueError, match="capacity must be a positive int"):
        bvh.compact(pairs, 0)
    no_bins = bvh.Pairs(pairs.pixel, pairs.scratch, pairs.valid, pairs.overflow)
    with pytest.raises(ValueError, match="no bin_"):
        bvh.needs_rebin(no_bins, p0, p1, 1e-4, 1e-4)
    assert isinstance(pairs, eqx.Module)


def test_groove_at_bottom_edge_stays_on_the_grid():
    # A groove whose endpoint lies 2.8e-7 m from the board's bottom edge, in float32 under jit:
    # its first strip must be computed consistently (strip count and strips), or the groove gets
    # a pair in row H, off the grid.
    p0 = jnp.asarray([[0.23985297977924347, 0.01634475588798523]], jnp.float32)
    p1 = jnp.asarray([[0.2512361705303192, 2.7995437790195865e-07]], jnp.float32)
    w = jnp.asarray([0.0004338251892477274], jnp.float32)
    d = jnp.asarray([5.6192737247329205e-05], jnp.float32)
    pairs, _ = bvh.build_pairs(p0, p1, w, d, board=(0.3, 0.3), shape=(256, 256), spec=None,
                               skin=0.0)
    pix = np.asarray(pairs.pixel)[np.asarray(pairs.valid)]
    assert pix.size > 0 and pix.max() < 256 * 256


# ---------------------------------------------------------------------------------------------
# The native strip and cell stage (`native.bin_cells`) equals the jnp one, bit for bit

needs_native = pytest.mark.skipif(not native.available(jnp.float32),
                                  reason=f"native kernel unavailable: {native.status()['why']}")


def _binner(native_path, spec):
    """`grid.update`'s binning at `spec`'s capacities, jitted, by the native or the jnp path:
    ``(Pairs, stats)``."""
    binner = grid._bin_native if native_path else grid._bin

    @jax.jit
    def f(p0, p1, width, depth):
        p0, p1, width, depth = grid.checked_scratches(p0, p1, width, depth)
        return binner(p0, p1, width, depth, board=spec.board, shape=spec.shape, skin=spec.skin,
                      strip_capacity=spec.strip_capacity, rows=spec.rows_per_strip,
                      pair_capacity=spec.pair_capacity)

    return f


def assert_same_pairs(a, b):
    """Every field of two `Pairs` the same bits (and dtypes)."""
    for name in ("pixel", "scratch", "valid", "overflow", "bin_p0", "bin_p1", "bin_half_width",
                 "bin_extend", "bin_tol"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.dtype == y.dtype and x.shape == y.shape, name
        bad = np.flatnonzero(x.reshape(-1) != y.reshape(-1))
        assert bad.size == 0, f"{name} differs at {bad.size} slots, first {bad[:5]}"


def assert_native_equals_jnp(spec, *scene):
    (a, sa), (b, sb) = (_binner(nat, spec)(*scene) for nat in (False, True))
    assert_same_pairs(a, b)
    assert tuple(map(int, sa)) == tuple(map(int, sb))
    return a, tuple(map(int, sa))


def _edge_scene(rng, n, board, shape):
    """Endpoints on and within a few rounding steps of the board's edges and corners, grooves
    ending exactly on cell boundaries, zero-length and zero-depth scratches."""
    sx, sy = board
    h_px, w_px = shape
    tiny = rng.choice([0.0, 1e-12, 3e-9, 2.8e-7, 1e-5], (n, 2))
    on = rng.integers(0, 2, (n, 2))  # 0: the low edge, 1: the high edge
    p0 = np.where(on == 0, tiny, [sx, sy] - tiny)
    free = rng.integers(0, 2, n).astype(bool)  # half of them slide along their edge
    p0[free, 0] = rng.uniform(0, sx, free.sum())
    ang = rng.uniform(0, 2 * np.pi, n)
    length = rng.choice([0.0, sx / w_px, 3 * sy / h_px, 0.02], n)
    p1 = np.clip(p0 + length[:, None] * np.stack([np.cos(ang), np.sin(ang)], -1), 0, board)
    k = n // 4  # grooves from cell corner to cell corner
    c = rng.integers(0, w_px + 1, (k, 2)) * (sx / w_px)
    r = sy - rng.integers(0, h_px + 1, (k, 2)) * (sy / h_px)
    p0[:k], p1[:k] = np.stack([c[:, 0], r[:, 0]], -1), np.stack([c[:, 1], r[:, 1]], -1)
    width = np.full(n, 2.5e-4)
    depth = np.where(rng.uniform(size=n) < 0.1, 0.0, 1.28e-4)
    return p0, p1, width, depth


@needs_native
@pytest.mark.parametrize("dtype", [np.float32, pytest.param(np.float64, marks=pytest.mark.float64)])
@pytest.mark.parametrize("board, shape", [(BOARD, (64, 64)), ((0.4, 0.25), (48, 96))])
def test_native_bin_is_bit_identical(dtype, board, shape):
    """Native and jnp binning give the same `Pairs` and stats on mixed scenes (short, long,
    board-crossing, on-cell-edge, zero-length, zero-depth, wide grooves), on scenes at the
    board's edges and corners, with and without skin, square and non-square pixels."""
    rng = np.random.default_rng(5)
    scenes = [make_scene(rng, 400, board, shape), make_scene(rng, 240, board, shape, wide=True),
              _edge_scene(rng, 400, board, shape)]
    sc = tuple(np.concatenate([s[i] for s in scenes]).astype(dtype) for i in range(4))
    for skin in (0.0, 3e-4):
        spec = bvh.allocate(*sc, board=board, shape=shape, skin=skin)
        pairs, stats = assert_native_equals_jnp(spec, *sc)
        assert not bool(pairs.overflow) and stats[2] > 1000, (skin, stats)


# Scratches (float32, 256 x 256 px, width 2.5e-4 m, depth 1.28e-4 m; found by search) on which a
# native pass that leaves out one of XLA's fused multiply-adds, or adds one XLA does not make,
# keeps or drops a cell the jnp path does not. Each is sensitive to at least one of: the
# thresholds of the x and y tests, the b and t tests' thresholds (fused on non-square pixels; on
# square ones XLA shares hx |ty| and hx |tx| between them and does not fuse), the cell's offsets
# dx and dy, the across- and along-groove distances d_b and d_t (which product is fused).
_FMA_SENSITIVE = {
    (0.3, 0.3): [  # square pixels
        ((0.28939956426620483, 0.06447827816009521), (0.08814550191164017, 0.16357623040676117)),
        ((0.14187341928482056, 0.07636111974716187), (0.30000001192092896, 0.27460142970085144)),
        ((0.27088093757629395, 0.10414189100265503), (0.2931610345840454, 0.17575038969516754)),
        ((0.11098752915859222, 0.10339796543121338), (0.30000001192092896, 0.14483962953090668)),
        ((0.2647748291492462, 0.20767663419246674), (0.16449899971485138, 0.30000001192092896)),
        ((0.26325929164886475, 0.19442053139209747), (0.1827825903892517, 0.06916120648384094)),
        ((0.0, 0.15855808556079865), (0.08205462992191315, 0.08440258353948593)),
    ],
    (0.3, 0.2): [  # non-square pixels
        ((0.062092375010252, 0.08305155485868454), (0.0, 0.0867336094379425)),
        ((0.1593717634677887, 0.20000000298023224), (0.30000001192092896, 0.016131943091750145)),
        ((0.22572647035121918, 0.09679306298494339), (0.09239745140075684, 0.0)),
        ((0.0, 0.0), (0.1264769732952118, 0.20000000298023224)),
        ((0.09292838722467422, 0.0), (0.22809024155139923, 0.18341410160064697)),
        ((0.011074230074882507, 0.06948401778936386), (0.2497318983078003, 0.0)),
        ((0.023150337859988213, 0.17319762706756592), (0.1964128017425537, 0.031087450683116913)),
        ((0.18726807832717896, 0.0), (0.2850271165370941, 0.11275522410869598)),
    ],
}


@needs_native
@pytest.mark.parametrize("board", sorted(_FMA_SENSITIVE))
def test_native_bin_follows_xla_fused_multiply_adds(board):
    """On scratches where the contraction decides a borderline cell, the native pass still
    equals the jnp one (a port with plain products, or fused ones where XLA does not fuse, would
    not)."""
    scratches = _FMA_SENSITIVE[board]
    p0, p1 = (np.asarray([s[i] for s in scratches], np.float32) for i in (0, 1))
    n = len(p0)
    width, depth = np.full(n, 2.5e-4, np.float32), np.full(n, 1.28e-4, np.float32)
    spec = bvh.allocate(p0, p1, width, depth, board=board, shape=(256, 256))
    assert_native_equals_jnp(spec, p0, p1, width, depth)


@needs_native
@pytest.mark.parametrize("dtype", [np.float32, pytest.param(np.float64, marks=pytest.mark.float64)])
def test_native_bin_overflow_is_bit_identical(dtype):
    """Each of the three capacities too small: the same overflow flag, stats and (truncated)
    list from both paths."""
    board, shape = BOARD, (64, 64)
    sc = tuple(np.asarray(a, dtype) for a in make_scene(np.random.default_rng(8), 320, board,
                                                            shape, wide=True))
    spec = bvh.allocate(*sc, board=board, shape=shape, margin=1.0)
    _, (strips, rows, pairs) = assert_native_equals_jnp(spec, *sc)
    for small in (dict(strip_capacity=strips // 2), dict(rows_per_strip=rows - 1),
                  dict(pair_capacity=pairs // 3), dict(strip_capacity=64, rows_per_strip=1,
                                                        pair_capacity=64)):
        tight = bvh.GridSpec(**{**dict(board=board, shape=shape,
                                       strip_capacity=spec.strip_capacity,
                                       rows_per_strip=spec.rows_per_strip,
                                       pair_capacity=spec.pair_capacity), **small})
        got, stats = assert_native_equals_jnp(tight, *sc)
        assert bool(got.overflow), small
        if "pair_capacity" in small and len(small) == 1:
            assert stats == (strips, rows, pairs) and bool(np.all(np.asarray(got.valid)))


@needs_native
def test_update_runs_native_inside_jit_and_cond():
    """`update` (and `maybe_update`'s `lax.cond`, jitted; and vmapped) runs the native pass: no
    scatter left in the program, the result equal to the jnp path's."""
    board, shape = BOARD, (64, 64)
    sc = tuple(np.asarray(a, np.float32) for a in make_scene(np.random.default_rng(9), 320,
                                                                 board, shape))
    spec = bvh.allocate(*sc, board=board, shape=shape, skin=2e-4)
    ref, _ = _binner(False, spec)(*sc)
    text = jax.jit(grid.update).lower(spec, *sc).as_text()
    assert "jscratch_bin_f32" in text and "scatter" not in text
    assert_same_pairs(bvh.update(spec, *sc), ref)
    moved = (sc[0] + np.float32(1e-3), sc[1] + np.float32(1e-3), sc[2], sc[3])
    ref_moved, _ = _binner(False, spec)(*moved)

    @jax.jit
    def step(pairs, p0, p1, width, depth, force):
        return jax.lax.cond(force, lambda: bvh.update(spec, p0, p1, width, depth),
                            lambda: bvh.maybe_update(spec, pairs, p0, p1, width, depth))

    for force in (True, False):
        assert_same_pairs(step(ref, *moved, force), ref_moved)  # 1 mm > skin: rebinned
        assert_same_pairs(step(ref, *sc, force), ref)  # unmoved (or rebinned to the same)
    batched = jax.vmap(bvh.update, in_axes=(None, 0, 0, None, None))(
        spec, np.stack([sc[0], moved[0]]), np.stack([sc[1], moved[1]]), sc[2], sc[3])
    for i, r in enumerate((ref, ref_moved)):  # vmapped: one native call per element
        assert_same_pairs(jax.tree_util.tree_map(lambda x: x[i], batched), r)
    with native.override(enabled=False):  # traced anew: the jnp path
        text = jax.jit(lambda *a: grid.update.__wrapped__(spec, *a)).lower(*sc).as_text()
    assert "jscratch_bin" not in text and "scatter" in text
