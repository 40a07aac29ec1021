"""Grid binning, the kernels under `jscratch.bvh`: scratches to a flat padded (pixel, scratch) list.

The paper finds pixel/scratch pairs with an OptiX BVH. We use a uniform grid (the image itself) and
the jax-md neighbour-list pattern instead: a host-side `allocate` measures the capacities a
scene needs (times a margin), a jitted `update` rebins at those fixed capacities and raises an
`overflow` flag instead of dropping pairs, and the host driver `build_pairs` re-allocates and
recomputes on overflow, so it never hands back an incomplete list.

**Which pairs.** Pixel `(r, c)` has the closed axis-aligned footprint of docs/model.md §1; scratch `i`
has the closed groove rectangle of docs/model.md §2 (local `|x| <= x_max`, `0 <= y <= |p1 - p0|`).
The list holds every pair whose footprint and groove intersect with positive area (none is ever
missed), plus pairs that only touch or miss by at most a slack `tol = 16 eps (Sx + Sy)` (`eps` the
machine epsilon of the input dtype: about `1.1e-6 m` in float32, `2e-15 m` in float64) that absorbs
rounding; such pairs contribute zero (or a rounding-sized amount). Scratches whose groove has zero
area (zero length, or zero depth so `x_max = 0`) get no pairs at all.

**How (per-scratch work proportional to the scratch's own length in pixels).** Each groove is cut
into *strips*: one per image column it crosses when it runs more along x than y in pixel units
(else one per row). Strips of all scratches share one flat list whose length (`strip_capacity`) is
measured, so a board-diagonal scratch takes ~W strips and a short one a few, and no scratch is
padded to the longest. Within a strip the groove covers a short run of cells along the other axis
(at most `rows_per_strip`, measured: 3 for the defaults of docs/model.md §5, whose grooves are narrower
than a pixel). Every candidate cell is then tested exactly (separating axes of the rectangle and the
square, four axes) and the survivors are compacted, in scratch order, into the flat pair list of
`pair_capacity` slots. The flat list beats a per-pixel `(P, K)` layout on padding because pairs
per pixel vary a lot (K must cover the busiest pixel); see `benchmarks/results/bvh.md`.

**Rebinning only when needed (skin).** With `skin > 0` the binning uses grooves inflated by `skin`
across and at both ends. `needs_rebin` checks, inside jit and in O(N), whether every current
groove still lies inside the inflated groove it was binned with (exact containment of the 4
corners); while it does, the old list still holds every pair (the extra pairs contribute zero), and
`maybe_update` skips the rebin. A pure translation by less than `skin` along and across never
needs a rebin.

These kernels take raw arrays (``p0, p1, width, depth``; they run inside jit, where a
`scene.Scratches` check cannot) and bin zero-depth grooves too (no pairs). `jscratch.bvh` is the
public face: it takes `scene.Scratches` and `scene.Board`, owns the multi-view `bvh.PairLists`
(this shared list, the per-view culled lists of `jscratch.cull`, capacities and overflow) and the
host layout for the renderer.

**Natively on the CPU.** Where the native kernel is available (`jscratch.native.available`:
enabled, CPU backend, built), `update` runs the strip and cell stage as one custom call
(`native.bin_cells`, `jscratch/native/native_bin.cc`): a loop over scratches, their strips and
each strip's cells that writes the kept pairs straight into the list, instead of the padded
`(strip_capacity, rows_per_strip)` candidate array, its cumsum, scatter and gathers. The
per-scratch quantities (`_strip_setup`) stay jnp, and the loop evaluates `_bin`'s tests with its
formulas in its order (and XLA's fused multiply-adds), so both paths give the same `Pairs`, bit
for bit (`tests/test_grid.py`). `allocate` measures with the jnp path. Under `jax.vmap` the
native stage runs once per batch element.

Imports: `jscratch.ndf`, `jscratch.native`.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jscratch import native
from jscratch.compile_options import few_calls_jit
from jscratch.errors import InputError
from jscratch.ndf import groove_half_width, local_frame


__all__ = [
    "DEFAULT_MARGIN",
    "GridSpec",
    "Pairs",
    "allocate",
    "build_pairs",
    "checked_scratches",
    "compact",
    "groove_half_width",
    "maybe_update",
    "needs_rebin",
    "pair_tolerance",
    "update",
]

DEFAULT_MARGIN = 1.25
"""Default capacity multiplier applied to the measured strip and pair counts."""


_ROUND = 64  # capacities are rounded up to a multiple of this (fewer distinct shapes to compile)


class GridSpec(eqx.Module):
    """Static binning configuration and capacities (no arrays: hashable, passes through `jit`).

    **Fields:**

    - `board`: `(Sx, Sy)` board size in metres.
    - `shape`: `(H, W)` image size in pixels.
    - `strip_capacity`: slots in the flat strip list (one strip = one scratch crossing one image
      column or row).
    - `rows_per_strip`: candidate cells per strip.
    - `pair_capacity`: slots `L` in the returned `Pairs`.
    - `skin`: metres by which grooves are inflated for binning (see `needs_rebin`).
    - `margin`: capacity multiplier used by `allocate` (kept for re-allocation).
    """

    board: tuple[float, float] = eqx.field(static=True)
    shape: tuple[int, int] = eqx.field(static=True)
    strip_capacity: int = eqx.field(static=True)
    rows_per_strip: int = eqx.field(static=True)
    pair_capacity: int = eqx.field(static=True)
    skin: float = eqx.field(static=True, default=0.0)
    margin: float = eqx.field(static=True, default=DEFAULT_MARGIN)

    def __check_init__(self):
        _check_board_shape(self.board, self.shape)
        for name in ("strip_capacity", "rows_per_strip", "pair_capacity"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise InputError(f"GridSpec.{name} must be a positive int, got {value!r}")
        if not (math.isfinite(self.skin) and self.skin >= 0):
            raise InputError(f"GridSpec.skin must be finite and >= 0 m, got {self.skin!r}")
        if not (math.isfinite(self.margin) and self.margin >= 1):
            raise InputError(f"GridSpec.margin must be >= 1, got {self.margin!r}")


class Pairs(eqx.Module):
    """Flat padded list of (pixel, scratch) pairs.

    **Fields:**

    - `pixel`: `(L,)` int32 flat pixel index `r * W + c`, row 0 at the top of the image (docs/model.md §1);
      0 in padding slots.
    - `scratch`: `(L,)` int32 scratch index; padding slots hold the sentinel `N` (the number of
      scratches).
    - `valid`: `(L,)` bool, true for real pairs.
    - `overflow`: `()` bool, true when the capacities were too small: the list is then incomplete
      and must not be used (re-allocate; `build_pairs` does).
    - `bin_p0`, `bin_p1`: `(N, 2)` endpoints the list was binned with (metres), or `None`.
    - `bin_half_width`: `(N,)` half-width of the binned (inflated) grooves, `x_max + skin` (metres),
      or `None`.
    - `bin_extend`: `()` how far the binned grooves were extended past each end (`skin`, metres),
      or `None`.
    - `bin_tol`: `()` slack of the pair test the list was built with (`pair_tolerance`,
      metres), or `None`.

    The `bin_*` fields are what `needs_rebin` compares against; a list built elsewhere (e.g. a
    per-pixel `(P, K)` layout flattened with `pixel = repeat(arange(P), K)`) may leave them `None`.
    Pairs are in scratch order (then along the scratch); a pixel's pairs are not contiguous.
    """

    pixel: Int[Array, " L"]
    scratch: Int[Array, " L"]
    valid: Bool[Array, " L"]
    overflow: Bool[Array, ""]
    bin_p0: Float[Array, "N 2"] | None = None
    bin_p1: Float[Array, "N 2"] | None = None
    bin_half_width: Float[Array, " N"] | None = None
    bin_extend: Float[Array, ""] | None = None
    bin_tol: Float[Array, ""] | None = None


# --------------------------------------------------------------------------------------------
# Validation helpers


def _check_board_shape(board, shape):
    if len(tuple(board)) != 2 or not all(
        isinstance(s, (int, float)) and math.isfinite(s) and s > 0 for s in board
    ):
        raise InputError(f"board must be (Sx, Sy) with positive finite metres, got {board!r}")
    if len(tuple(shape)) != 2 or not all(
        isinstance(n, (int, np.integer)) and n >= 1 for n in shape
    ):
        raise InputError(f"shape must be (H, W) with positive ints, got {shape!r}")
    if int(shape[0]) * int(shape[1]) >= 2**31 - 1:
        raise InputError(f"shape {shape!r} has too many pixels for int32 indices")


def checked_scratches(p0, p1, width, depth, values: bool = True):
    """Static shape/dtype checks and (``values``) in-jit finiteness checks (`eqx.error_if`);
    returns broadcast float arrays."""
    p0 = jnp.asarray(p0)
    p1 = jnp.asarray(p1)
    if p0.ndim != 2 or p0.shape[-1] != 2:
        raise InputError(f"p0 must have shape (N, 2), got {p0.shape}")
    if p1.shape != p0.shape:
        raise InputError(f"p1 must have the shape of p0 {p0.shape}, got {p1.shape}")
    n = p0.shape[0]
    dtype = jnp.result_type(p0, p1, width, depth)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    width = jnp.asarray(width, dtype)
    depth = jnp.asarray(depth, dtype)
    for name, a in (("width", width), ("depth", depth)):
        if a.shape not in ((), (n,)):
            raise InputError(f"{name} must be a scalar or have shape ({n},), got {a.shape}")
    p0 = p0.astype(dtype)
    p1 = p1.astype(dtype)
    width = jnp.broadcast_to(width, (n,))
    depth = jnp.broadcast_to(depth, (n,))
    if not values:
        return p0, p1, width, depth
    p0 = eqx.error_if(p0, ~jnp.all(jnp.isfinite(p0)), "p0 has non-finite entries")
    p1 = eqx.error_if(p1, ~jnp.all(jnp.isfinite(p1)), "p1 has non-finite entries")
    width = eqx.error_if(
        width, ~jnp.all(jnp.isfinite(width) & (width > 0)), "width must be finite and > 0"
    )
    depth = eqx.error_if(
        depth, ~jnp.all(jnp.isfinite(depth) & (depth >= 0)), "depth must be finite and >= 0"
    )
    return p0, p1, width, depth


def _host_check(p0, p1, width, depth):
    """Host-side (numpy) checks naming the bad argument, for the non-jitted entry points."""
    p0n, p1n, wn, dn = (np.asarray(a) for a in (p0, p1, width, depth))
    if p0n.ndim != 2 or p0n.shape[-1] != 2:
        raise InputError(f"p0 must have shape (N, 2), got {p0n.shape}")
    if p1n.shape != p0n.shape:
        raise InputError(f"p1 must have the shape of p0 {p0n.shape}, got {p1n.shape}")
    for name, a in (("p0", p0n), ("p1", p1n), ("width", wn), ("depth", dn)):
        if not np.all(np.isfinite(a)):
            bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
            raise InputError(f"{name} has non-finite entries (first at index {bad})")
    if np.any(wn <= 0):
        raise InputError(f"width must be > 0 m for every scratch, got {float(np.min(wn))!r} (the smallest)")
    if np.any(dn < 0):
        raise InputError(f"depth must be >= 0 m for every scratch, got {float(np.min(dn))!r} (the smallest)")


# --------------------------------------------------------------------------------------------
# Geometry


def pair_tolerance(board: tuple[float, float], dtype) -> float:
    """Slack (metres) of the pair test: `16 eps (Sx + Sy)` for the floating dtype `dtype`."""
    return 16.0 * float(jnp.finfo(dtype).eps) * (float(board[0]) + float(board[1]))


# The scratch frame and groove half-width are the kernel's (docs/model.md §1-§2), not re-derived here.
_frame = local_frame


# --------------------------------------------------------------------------------------------
# Binning


class _StripSetup(eqx.Module):
    """Per-scratch binning quantities (`_strip_setup`), shared by `_bin` and `_measure`. Grid
    units: a cell is a unit square; ``u`` runs along the strips (columns where `col_major`),
    ``v`` across them. Arrays ``(N,)`` unless noted."""

    t: Array  # (N, 2) unit vector along the scratch
    b: Array  # (N, 2) unit vector across it
    half_w: Array  # groove half-width + skin, m
    half_l: Array  # half the length + skin, m
    centre: Array  # (N, 2) midpoint, m
    col_major: Array  # bool: strips are columns
    tu: Array  # t and b in grid units, (u, v) components
    tv: Array
    bu: Array
    bv: Array
    mu: Array  # the midpoint in grid units
    mv: Array
    n_v: Array  # cells per strip
    k_lo: Array  # first strip
    k_hi: Array  # last strip
    n_strips: Array  # int32: strips generated, k_hi - k_lo + 2 (one spare: see _bin)
    rows_bound: Array  # int32: bound on cells per strip (for allocate)
    length: Array  # m
    tol: float  # slack of the exact pair test, m
    tolg: float  # slack of candidate generation, grid units (twice `tol`)


def _strip_setup(p0, p1, width, depth, board, shape, skin) -> _StripSetup:
    """Per-scratch binning quantities (`_StripSetup`); shared by update and allocate."""
    dtype = p0.dtype
    sx_m, sy_m = (float(s) for s in board)
    h_px, w_px = (int(n) for n in shape)
    tol = pair_tolerance(board, dtype)
    t, b, length = _frame(p0, p1)
    half_w = groove_half_width(width, depth) + skin  # across
    half_l = 0.5 * length + skin  # along
    centre = 0.5 * (p0 + p1)
    active = (half_w > 0) & (half_l > 0)

    # Grid coordinates: gx = x W/Sx (columns), gy = (Sy - y) H/Sy (rows), cells are unit squares.
    kx, ky = w_px / sx_m, h_px / sy_m
    tgx, tgy = t[:, 0] * kx, -t[:, 1] * ky
    bgx, bgy = b[:, 0] * kx, -b[:, 1] * ky
    mgx, mgy = centre[:, 0] * kx, (sy_m - centre[:, 1]) * ky
    col_major = jnp.abs(tgx) >= jnp.abs(tgy)  # strips are columns
    tu = jnp.where(col_major, tgx, tgy)
    tv = jnp.where(col_major, tgy, tgx)
    bu = jnp.where(col_major, bgx, bgy)
    bv = jnp.where(col_major, bgy, bgx)
    mu = jnp.where(col_major, mgx, mgy)
    mv = jnp.where(col_major, mgy, mgx)
    n_u = jnp.where(col_major, w_px, h_px)
    n_v = jnp.where(col_major, h_px, w_px)
    # Candidate generation uses twice the final test's slack, so it is a superset of what the
    # exact test keeps despite rounding.
    tolg = 2.0 * tol * max(kx, ky)
    hu = half_l * jnp.abs(tu) + half_w * jnp.abs(bu)
    k_lo = _floor_index(mu - hu - tolg, n_u)
    k_hi = _floor_index(mu + hu + tolg, n_u)
    k_lo = jnp.maximum(k_lo, 0)
    k_hi = jnp.minimum(k_hi, n_u - 1)
    # One spare strip: XLA may evaluate k_lo separately for this count and for `_bin`'s gather of
    # it (each fusion recomputes its elementwise inputs), and where `mu - hu - tolg` rounds to an
    # integer the two may differ by one. With the spare, the strips generated from either value
    # cover [k_lo, k_hi]; `_bin` drops those past k_hi or off the grid (found on a groove ending
    # 2.8e-7 m from the board edge, which was binned into row H).
    n_strips = jnp.where(active & (k_hi >= k_lo), k_hi - k_lo + 2, 0).astype(jnp.int32)
    # Bound on cells per strip (for allocate): v-extent of one strip's candidate range.
    tau_len = jnp.minimum(2 * half_l, (1 + 2 * half_w * jnp.abs(bu) + 2 * tolg) / jnp.abs(tu))
    v_ext = jnp.abs(tv) * tau_len + 2 * half_w * jnp.abs(bv) + 2 * tolg
    rows_bound = jnp.where(active, jnp.floor(v_ext * (1 + 1e-6) + 1e-6) + 2, 0)
    rows_bound = jnp.minimum(rows_bound, n_v).astype(jnp.int32)
    return _StripSetup(t, b, half_w, half_l, centre, col_major, tu, tv, bu, bv, mu, mv, n_v, k_lo,
                       k_hi, n_strips, rows_bound, length, tol, tolg)


def _strip_floats(g: _StripSetup) -> Array:
    """``(N, 12)``: the floats a strip needs from its scratch, in the order `_bin` and the native
    stage (`native.bin_cells`) read them."""
    return jnp.stack(
        [g.tu, g.tv, g.bu, g.bv, g.mu, g.mv, g.half_w, g.half_l,
         g.centre[:, 0], g.centre[:, 1], g.t[:, 0], g.t[:, 1]],
        axis=-1,
    )  # fmt: skip


def _binned_pairs(p0, p1, g: _StripSetup, skin, pixel, scratch, valid, overflow) -> Pairs:
    """The `Pairs` of one binning pass: its slots and the envelope it binned (for `needs_rebin`)."""
    dtype = p0.dtype
    return Pairs(pixel=pixel, scratch=scratch, valid=valid, overflow=overflow, bin_p0=p0,
                 bin_p1=p1, bin_half_width=g.half_w, bin_extend=jnp.asarray(skin, dtype),
                 bin_tol=jnp.asarray(g.tol, dtype))


def _floor_index(g, n):
    """floor(g) as int32, clipped to [-1, n] first so that huge coordinates cannot overflow."""
    return jnp.floor(jnp.clip(g, -1.0, n.astype(g.dtype))).astype(jnp.int32)


def _bin(p0, p1, width, depth, *, board, shape, skin, strip_capacity, rows, pair_capacity):
    """Core binning at fixed capacities. Returns (Pairs, (strips_needed, max_rows, pairs_needed))."""
    n = p0.shape[0]
    dtype = p0.dtype
    sx_m, sy_m = (float(s) for s in board)
    h_px, w_px = (int(v) for v in shape)
    g = _strip_setup(p0, p1, width, depth, board, shape, skin)
    tol, tolg = g.tol, g.tolg

    # Flat strip list: slot s belongs to scratch owner[s] (scatter the start offsets, then cummax).
    n_strips = g.n_strips
    offsets = jnp.cumsum(n_strips) - n_strips
    strips_needed = jnp.sum(n_strips)
    slot = jnp.arange(strip_capacity, dtype=jnp.int32)
    owner = jnp.zeros(strip_capacity, jnp.int32).at[offsets].max(
        jnp.arange(n, dtype=jnp.int32), mode="drop"
    )
    owner = jax.lax.cummax(owner)
    strip_ok = slot < strips_needed
    # One gather of everything a strip needs (floats stacked, then the ints/bools).
    fl = _strip_floats(g)[owner]
    tu, tv, bu, bv, mu, mv, half_w, half_l, cx_m, cy_m, tx, ty = (fl[:, j] for j in range(12))
    k = g.k_lo[owner] + slot - offsets[owner]
    n_u = jnp.where(g.col_major[owner], w_px, h_px)
    strip_ok = strip_ok & (k >= 0) & (k <= g.k_hi[owner]) & (k < n_u)  # the spare (setup)
    col_major = g.col_major[owner]
    n_v = g.n_v[owner]

    # Along-scratch parameter range whose cross-section can reach the strip [k, k + 1].
    lo = (k.astype(dtype) - mu) - half_w * jnp.abs(bu) - tolg
    hi = (k.astype(dtype) + 1 - mu) + half_w * jnp.abs(bu) + tolg
    tau1, tau2 = lo / tu, hi / tu
    tau_a = jnp.clip(jnp.minimum(tau1, tau2), -half_l, half_l)
    tau_b = jnp.clip(jnp.maximum(tau1, tau2), -half_l, half_l)
    va, vb = mv + tau_a * tv, mv + tau_b * tv
    spread = half_w * jnp.abs(bv) + tolg
    r_lo = jnp.maximum(_floor_index(jnp.minimum(va, vb) - spread, n_v), 0)
    r_hi = jnp.minimum(_floor_index(jnp.maximum(va, vb) + spread, n_v), n_v - 1)
    n_rows = jnp.where(strip_ok, jnp.maximum(r_hi - r_lo + 1, 0), 0)
    max_rows = jnp.max(n_rows, initial=0)

    # Candidate cells (strip_capacity, rows) and the exact separating-axis test, board metres.
    j = jnp.arange(rows, dtype=jnp.int32)
    minor = r_lo[:, None] + j
    cand = j < n_rows[:, None]
    col = jnp.where(col_major[:, None], k[:, None], minor)
    row = jnp.where(col_major[:, None], minor, k[:, None])
    hx, hy = 0.5 * sx_m / w_px, 0.5 * sy_m / h_px
    dx = (col.astype(dtype) + 0.5) * (sx_m / w_px) - cx_m[:, None]
    dy = (sy_m - (row.astype(dtype) + 0.5) * (sy_m / h_px)) - cy_m[:, None]
    atx, aty = jnp.abs(tx)[:, None], jnp.abs(ty)[:, None]
    hw, hl = half_w[:, None], half_l[:, None]
    # b = (t_y, -t_x): |b_x| = |t_y|, |b_y| = |t_x|.
    sep_x = jnp.abs(dx) <= hx + hw * aty + hl * atx + tol
    sep_y = jnp.abs(dy) <= hy + hw * atx + hl * aty + tol
    d_b = dx * ty[:, None] - dy * tx[:, None]
    d_t = dx * tx[:, None] + dy * ty[:, None]
    sep_b = jnp.abs(d_b) <= hw + hx * aty + hy * atx + tol
    sep_t = jnp.abs(d_t) <= hl + hx * atx + hy * aty + tol
    keep = (cand & sep_x & sep_y & sep_b & sep_t).reshape(-1)

    # Compaction (order preserving) into the pair list: one scatter of the candidate index, then
    # gathers (cheaper on CPU than scattering pixel and scratch separately).
    pos = jnp.cumsum(keep.astype(jnp.int32)) - 1
    pairs_needed = pos[-1] + 1
    target = jnp.where(keep, pos, pair_capacity)
    n_cells = keep.shape[0]
    src = jnp.full(pair_capacity, n_cells, jnp.int32).at[target].set(
        jnp.arange(n_cells, dtype=jnp.int32), mode="drop"
    )
    valid = src < n_cells
    src = jnp.minimum(src, n_cells - 1)
    pixel = (row * w_px + col).reshape(-1)
    # Off-grid cells never become pairs (the strip and row ranges are clipped to the grid, but XLA
    # may recompute a range's first index in another fusion with different rounding at an
    # integer boundary; see `_strip_setup`): checked on the index actually written.
    pix_src = pixel[src]
    cell_src = (row.reshape(-1)[src], col.reshape(-1)[src])
    valid = valid & (cell_src[0] >= 0) & (cell_src[0] < h_px) & (cell_src[1] >= 0) & (
        cell_src[1] < w_px)
    pix_out = jnp.where(valid, pix_src, 0)
    scr_out = jnp.where(valid, owner[src // rows], n)
    overflow = (
        (strips_needed > strip_capacity) | (max_rows > rows) | (pairs_needed > pair_capacity)
    )
    pairs = _binned_pairs(p0, p1, g, skin, pix_out, scr_out, valid, overflow)
    return pairs, (strips_needed, max_rows, pairs_needed)


@functools.partial(jax.jit, static_argnames="checked")
def update(
    spec: GridSpec,
    p0: Float[ArrayLike, "N 2"],
    p1: Float[ArrayLike, "N 2"],
    width: Float[ArrayLike, "N"],
    depth: Float[ArrayLike, "N"],
    *,
    checked: bool = True,
) -> Pairs:
    """Bin scratches to pixels at the fixed capacities of `spec` (jittable).

    **Arguments:**

    - `spec`: a `GridSpec` from `allocate` (board, image shape, capacities, skin).
    - `p0`, `p1`: `(N, 2)` scratch endpoints, board metres.
    - `width`, `depth`: `(N,)` or scalar, metres (`width > 0`, `depth >= 0`).
    - `checked` (static): ``False`` leaves out the runtime checks of those values (the shapes
      are still checked), for a caller that guarantees them: the design step, which replaces
      non-finite values first. Its compiled program then holds no host callback, so JAX's
      persistent compilation cache can keep it.

    **Returns:**

    `Pairs` with `pair_capacity` slots. If any capacity was too small, `overflow` is true and
    the list is incomplete: re-allocate (or use `build_pairs`). Floats follow the inputs'
    dtype; gradients are stopped (binning is piecewise constant). On the CPU with the native
    kernel the strip and cell stage runs natively (the same result).
    """
    p0, p1, width, depth = checked_scratches(p0, p1, width, depth, values=checked)
    p0, p1, width, depth = jax.lax.stop_gradient((p0, p1, width, depth))
    binner = _bin_native if native.available(p0.dtype) else _bin
    pairs, _ = binner(
        p0, p1, width, depth,
        board=spec.board, shape=spec.shape, skin=spec.skin,
        strip_capacity=spec.strip_capacity, rows=spec.rows_per_strip,
        pair_capacity=spec.pair_capacity,
    )  # fmt: skip
    return pairs


_update_jit = update  # already jitted; the name marks host-driver calls


def _bin_native(p0, p1, width, depth, *, board, shape, skin, strip_capacity, rows, pair_capacity):
    """`_bin` with the strip and cell stage run by `native.bin_cells` (same arguments, same
    `Pairs` and stats, bit for bit)."""
    sx_m, sy_m = (float(s) for s in board)
    h_px, w_px = (int(v) for v in shape)
    g = _strip_setup(p0, p1, width, depth, board, shape, skin)
    fl = _strip_floats(g)
    ints = jnp.stack([g.k_lo, g.k_hi, g.n_strips, g.col_major.astype(jnp.int32)], axis=-1)
    pixel, scratch, valid, overflow, stats = native.bin_cells(
        fl, ints, shape=(h_px, w_px), strip_capacity=strip_capacity, rows=rows,
        pair_capacity=pair_capacity, tol=g.tol, tolg=g.tolg, csx=sx_m / w_px, csy=sy_m / h_px,
        hx=0.5 * sx_m / w_px, hy=0.5 * sy_m / h_px, sy=sy_m,
    )  # fmt: skip
    pairs = _binned_pairs(p0, p1, g, skin, pixel, scratch, valid, overflow)
    return pairs, (stats[0], stats[1], stats[2])


# `_setup_counts` and `_measure` run for `allocate`, which checks the values on the host first:
# without the runtime checks they hold no host callback (JAX's persistent cache can keep them).
@few_calls_jit(filter=True)
def _setup_counts(p0, p1, width, depth, board, shape, skin):
    p0, p1, width, depth = checked_scratches(p0, p1, width, depth, values=False)
    g = _strip_setup(p0, p1, width, depth, board, shape, skin)
    return jnp.sum(g.n_strips), jnp.max(g.rows_bound, initial=1)


@few_calls_jit(filter=True)
def _measure(p0, p1, width, depth, board, shape, skin, strip_capacity, rows, pair_capacity):
    p0, p1, width, depth = checked_scratches(p0, p1, width, depth, values=False)
    # (the native stage where `update` runs it: the same counts, and no compilation of the jnp
    # stage at the provable capacities, the largest part of a design's setup)
    binner = _bin_native if native.available(p0.dtype) else _bin
    _, stats = binner(
        p0, p1, width, depth, board=board, shape=shape, skin=skin,
        strip_capacity=strip_capacity, rows=rows, pair_capacity=pair_capacity,
    )  # fmt: skip
    return stats


def _round_up(x: float) -> int:
    return max(_ROUND, int(math.ceil(x / _ROUND)) * _ROUND)


def allocate(
    p0: Float[ArrayLike, "N 2"],
    p1: Float[ArrayLike, "N 2"],
    width: Float[ArrayLike, "N"],
    depth: Float[ArrayLike, "N"],
    *,
    board: tuple[float, float],
    shape: tuple[int, int],
    margin: float = DEFAULT_MARGIN,
    skin: float = 0.0,
) -> GridSpec:
    """Measure the capacities a scene needs and return them times `margin` (host, not jitted).

    Runs the binning once at provably sufficient capacities and counts strips, cells per strip
    and pairs. `strip_capacity` and `pair_capacity` are the counts times `margin`, rounded up to
    a multiple of 64; `rows_per_strip` is the measured maximum (a geometric bound that moves only
    when grooves widen, so no margin).

    **Arguments:**

    - `p0`, `p1`: `(N, 2)` endpoints (metres); `width`, `depth`: `(N,)` or scalar (metres).
    - `board`: `(Sx, Sy)` metres. `shape`: `(H, W)` pixels.
    - `margin`: capacity multiplier, `>= 1`.
    - `skin`: metres by which grooves are inflated (across and at both ends) for binning, so that
      moves that keep each groove inside its inflated one need no rebin (`needs_rebin`).

    **Returns:**

    A `GridSpec`.
    """
    _check_board_shape(board, shape)
    board = (float(board[0]), float(board[1]))
    shape = (int(shape[0]), int(shape[1]))
    if not (math.isfinite(margin) and margin >= 1):
        raise InputError(f"margin must be >= 1, got {margin!r}")
    if not (math.isfinite(skin) and skin >= 0):
        raise InputError(f"skin must be finite and >= 0 m, got {skin!r}")
    _host_check(p0, p1, width, depth)
    strips, rows = (int(v) for v in _setup_counts(p0, p1, width, depth, board, shape, skin))
    strip_cap = _round_up(strips)
    rows = max(rows, 1)
    while True:  # the bound is rigorous; the loop only guards against it being wrong
        needed = _measure(
            p0, p1, width, depth, board, shape, skin, strip_cap, rows, strip_cap * rows
        )
        s_need, r_need, p_need = (int(v) for v in needed)
        if s_need <= strip_cap and r_need <= rows:
            break
        strip_cap, rows = _round_up(max(s_need, strip_cap)), max(r_need, rows + 1)
    return GridSpec(
        board=board,
        shape=shape,
        strip_capacity=_round_up(margin * s_need),
        rows_per_strip=max(r_need, 1),
        pair_capacity=_round_up(margin * p_need),
        skin=float(skin),
        margin=float(margin),
    )


def build_pairs(
    p0: Float[ArrayLike, "N 2"],
    p1: Float[ArrayLike, "N 2"],
    width: Float[ArrayLike, "N"],
    depth: Float[ArrayLike, "N"],
    *,
    board: tuple[float, float],
    shape: tuple[int, int],
    spec: GridSpec | None = None,
    margin: float = DEFAULT_MARGIN,
    skin: float = 0.0,
) -> tuple[Pairs, GridSpec]:
    """Host driver: bin with `spec` (allocating one if `None`), re-allocating on overflow.

    **Arguments:** as `allocate`, plus `spec` to reuse (its board and shape must match;
    `margin` and `skin` are then taken from it).

    **Returns:**

    `(pairs, spec)`: a complete `Pairs` (`overflow` false) and the spec it was built with
    (a new one if the old one overflowed; keep it for the next call).
    """
    _check_board_shape(board, shape)
    board = (float(board[0]), float(board[1]))
    shape = (int(shape[0]), int(shape[1]))
    _host_check(p0, p1, width, depth)
    if spec is None:
        spec = allocate(p0, p1, width, depth, board=board, shape=shape, margin=margin, skin=skin)
    elif spec.board != board or spec.shape != shape:
        raise InputError(
            f"spec is for board {spec.board} and shape {spec.shape}, not {board} and {shape}"
        )
    pairs = _update_jit(spec, p0, p1, width, depth, checked=False)  # (checked above)
    if bool(pairs.overflow):
        spec = allocate(
            p0, p1, width, depth, board=board, shape=shape, margin=spec.margin, skin=spec.skin
        )
        pairs = _update_jit(spec, p0, p1, width, depth, checked=False)
        if bool(pairs.overflow):  # cannot happen: allocate measured this very scene
            raise RuntimeError("binning overflowed right after allocation (bug)")
    return pairs, spec


# --------------------------------------------------------------------------------------------
# Rebinning test


@functools.partial(jax.jit, static_argnames="checked")
def needs_rebin(
    pairs: Pairs,
    p0: Float[ArrayLike, "N 2"],
    p1: Float[ArrayLike, "N 2"],
    width: Float[ArrayLike, "N"],
    depth: Float[ArrayLike, "N"],
    *,
    checked: bool = True,
) -> Bool[Array, ""]:
    """Whether `pairs` may miss a pair of the current scratches (jittable, O(N)).

    False exactly when every current groove of positive area lies inside the (skin-inflated)
    groove that `pairs` was binned with (its four corners are tested against the old rectangle)
    and `pairs` did not overflow. Then every pair of the current scene is in `pairs`. With
    `skin = 0` any change that grows a groove beyond its old rectangle asks for a rebin.

    **Arguments:** `pairs` from `update` (with its `bin_*` fields); current `p0`, `p1`
    `(N, 2)` and `width`, `depth` (`(N,)` or scalar), metres; `checked` as for `update`.

    **Returns:** `()` bool.
    """
    if any(
        f is None
        for f in (pairs.bin_p0, pairs.bin_p1, pairs.bin_half_width, pairs.bin_extend, pairs.bin_tol)
    ):
        raise InputError("pairs has no bin_* fields (was it built by update/build_pairs?)")
    p0, p1, width, depth = checked_scratches(p0, p1, width, depth, values=checked)
    if p0.shape != pairs.bin_p0.shape:
        raise InputError(f"p0 has shape {p0.shape} but pairs was binned for {pairs.bin_p0.shape}")
    p0, p1, width, depth = jax.lax.stop_gradient((p0, p1, width, depth))
    t_o, b_o, len_o = _frame(pairs.bin_p0.astype(p0.dtype), pairs.bin_p1.astype(p0.dtype))
    m_o = 0.5 * (pairs.bin_p0 + pairs.bin_p1).astype(p0.dtype)
    half_w_o = pairs.bin_half_width.astype(p0.dtype)
    half_l_o = 0.5 * len_o + pairs.bin_extend.astype(p0.dtype)
    t, b, length = _frame(p0, p1)
    x_max = groove_half_width(width, depth)
    d = 0.5 * (p0 + p1) - m_o

    def reach(axis):  # max |(corner - m_o) . axis| over the four corners of the new groove
        return (
            jnp.abs(jnp.sum(d * axis, -1))
            + 0.5 * length * jnp.abs(jnp.sum(t * axis, -1))
            + x_max * jnp.abs(jnp.sum(b * axis, -1))
        )

    # Half the binning slack absorbs rounding (an unchanged scene must not ask for a rebin); the
    # list holds every cell within the full slack of the old rectangle.
    slack = 0.5 * pairs.bin_tol.astype(p0.dtype)
    # A groove binned with zero area (no skin) got no pairs at all: any area now needs a rebin.
    binned = (half_w_o > 0) & (half_l_o > 0)
    inside = binned & (reach(b_o) <= half_w_o + slack) & (reach(t_o) <= half_l_o + slack)
    nonempty = (length > 0) & (x_max > 0)
    return jnp.any(nonempty & ~inside) | pairs.overflow


@jax.jit
def maybe_update(
    spec: GridSpec,
    pairs: Pairs,
    p0: Float[ArrayLike, "N 2"],
    p1: Float[ArrayLike, "N 2"],
    width: Float[ArrayLike, "N"],
    depth: Float[ArrayLike, "N"],
) -> Pairs:
    """`update(spec, ...)` if `needs_rebin` says so, else `pairs` unchanged (jittable,
    `lax.cond`). Check `overflow` of the result outside jit, as for `update`."""
    p0, p1, width, depth = checked_scratches(p0, p1, width, depth)
    return jax.lax.cond(
        needs_rebin(pairs, p0, p1, width, depth),
        lambda: update(spec, p0, p1, width, depth),
        lambda: pairs,
    )


# --------------------------------------------------------------------------------------------
# Compaction


@functools.partial(jax.jit, static_argnames="capacity")
def compact(pairs: Pairs, capacity: int) -> Pairs:
    """Re-pack the valid pairs of `pairs` (order kept) into `capacity` slots (jittable).

    **Arguments:** `pairs`; `capacity` (static int >= 1), e.g. the largest count of valid pairs
    over the views times a margin.

    **Returns:** `Pairs` with `capacity` slots; `overflow` is set (or kept) when more than
    `capacity` pairs are valid. Padding slots get pixel 0 and the sentinel scratch index taken
    from the padding of `pairs` (or `N` from `bin_p0` when `pairs` has no padding).
    """
    if not isinstance(capacity, (int, np.integer)) or capacity < 1:
        raise InputError(f"capacity must be a positive int, got {capacity!r}")
    capacity = int(capacity)
    if pairs.bin_p0 is not None:
        sentinel = jnp.asarray(pairs.bin_p0.shape[0], jnp.int32)
    else:
        sentinel = jnp.max(jnp.where(pairs.valid, -1, pairs.scratch), initial=-1)
        sentinel = jnp.where(sentinel < 0, jnp.max(pairs.scratch, initial=0) + 1, sentinel)
    keep = pairs.valid
    pos = jnp.cumsum(keep.astype(jnp.int32)) - 1
    count = jnp.sum(keep.astype(jnp.int32))
    target = jnp.where(keep, pos, capacity)
    pixel = jnp.zeros(capacity, jnp.int32).at[target].set(pairs.pixel, mode="drop")
    scratch = jnp.full(capacity, sentinel, jnp.int32).at[target].set(pairs.scratch, mode="drop")
    valid = jnp.arange(capacity, dtype=jnp.int32) < count
    return eqx.tree_at(
        lambda p: (p.pixel, p.scratch, p.valid, p.overflow),
        pairs,
        (pixel, scratch, valid, pairs.overflow | (count > capacity)),
    )
