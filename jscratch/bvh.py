"""Pair lists: which (pixel, scratch) pairs each view of a render needs, at fixed capacities.

The paper finds pixel/scratch pairs with an OptiX BVH. jscratch bins on the image grid
(`jscratch.grid`: every pair, none missed) and culls per view with a rigorous bound
(`jscratch.cull`). This module is the stage's public face: it takes `scene.Scratches` and
`scene.Board` and owns the object that holds every list of a multi-view render.

**`PairLists`** holds the shared list (every pair; `Pairs` at `GridSpec`'s capacities), the
per-view culled lists and the coverage list (each compacted to its own capacity), their counts
and the overflow flag. It follows jax-md's neighbour-list pattern:

- host `allocate_lists`: bins the scene and measures the per-view capacities (times a margin);
- jitted `update_lists`: re-culls every view for the current scratches at those fixed
  capacities, reporting overflow in `PairLists.overflow` instead of dropping pairs;
- host `rebin_lists`: rebuilds the shared list when `needs_rebin` (jitted) says a groove left
  the envelope it was binned with (growing the grid's capacities if needed);
- host `grow_lists`: larger per-view capacities after an overflow (`list_counts` measures).

Unculled (``cull_eps == 0``) every view renders the shared list and there are no per-view
lists; with ``coverage_eps == 0`` the coverage pass uses the shared list.

**Host layout for the renderer.** `bin_pairs` (a scene's shared list, compacted) and
`cull_pairs` (one ``(M, Lv)`` list of per-view culled lists) pack the valid pairs into
``shards`` equal segments by pixel block (`pixels_per_shard`, `layout`), the layout
`render.render_pairs` needs with a mesh, each segment's length rounded so that similar scenes
share a compilation.

The grid and cull kernels are re-exported here (`Pairs`, `GridSpec`, `allocate`, `update`,
`build_pairs`, `needs_rebin`, `maybe_update`, `compact`, `pair_tolerance`; `cull`,
`cull_coverage`, `cull_ratio`, `view_keep`): they take raw arrays and run inside jit.
`flat_pairs` and `pair_checks` are `render.render_pairs`' reading of the lists it is given.

Imports: `jscratch.grid`, `jscratch.cull`, `jscratch.scene`, `jscratch.shading` (half vectors).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jscratch.errors import InputError, real_number, whole_number
from jscratch.cull import DEFAULT_EPS as DEFAULT_EPS
from jscratch.cull import cull as cull
from jscratch.cull import cull_coverage as cull_coverage
from jscratch.cull import cull_ratio as cull_ratio
from jscratch.cull import view_keep as view_keep
from jscratch.grid import DEFAULT_MARGIN as DEFAULT_MARGIN
from jscratch.grid import GridSpec as GridSpec
from jscratch.grid import Pairs as Pairs
from jscratch.grid import allocate as allocate
from jscratch.grid import build_pairs as build_pairs
from jscratch.grid import compact as compact
from jscratch.grid import groove_half_width as groove_half_width
from jscratch.grid import maybe_update as maybe_update
from jscratch.grid import needs_rebin as needs_rebin
from jscratch.grid import pair_tolerance as pair_tolerance
from jscratch.grid import update as update
from jscratch.scene import Board, Scratches, Views, check_scratches
from jscratch.shading import half_vectors

__all__ = [
    "DEFAULT_CHUNK",
    "DEFAULT_EPS",
    "DEFAULT_MARGIN",
    "GridSpec",
    "PairLists",
    "Pairs",
    "VIEW_CAP_ROUND",
    "allocate",
    "allocate_lists",
    "bin_pairs",
    "build_pairs",
    "check_chunk",
    "compact",
    "cull",
    "cull_coverage",
    "cull_pairs",
    "cull_ratio",
    "flat_pairs",
    "grow_lists",
    "layout",
    "list_counts",
    "maybe_update",
    "needs_rebin",
    "pair_checks",
    "pair_tolerance",
    "pairs_of",
    "pixels_per_shard",
    "rebin_lists",
    "update",
    "update_lists",
    "view_keep",
]


# --------------------------------------------------------------------------------------------
# Every list of a multi-view render


#: Per-view capacities are rounded up to a multiple of this.
VIEW_CAP_ROUND = 1024


class PairLists(eqx.Module):
    """Every pair list of one multi-view render, at fixed capacities.

    **Fields:**

    - `shared`: `Pairs` ``(L,)``, every (pixel, scratch) pair (grid binning); `spec`: its
      `GridSpec` (capacities, skin, margin).
    - `counts`: ``(M + 1,)`` int pairs kept per list before compaction (views, then coverage)
      when culled; ``(M,)`` copies of the shared count when not.
    - `views`: ``M`` `Pairs`, view ``j`` culled by `cull` and compacted to ``caps[j]`` slots,
      or `None` (unculled, or not yet culled for the current scratches: `update_lists`).
    - `coverage`: the coverage list (`cull_coverage`, compacted to ``caps[M]``), or `None`
      (the shared list serves).
    - `caps`: the ``M + 1`` per-list capacities (static; ``()`` when not culled).
    - `cull_eps`, `coverage_eps`: the culling tolerances (static; 0 = no culling).

    [`overflow`][PairLists.overflow] is true when a list held more pairs than its capacity: the
    lists are then incomplete; the host calls `grow_lists` (or `rebin_lists` for the shared
    list) and recomputes.
    """

    shared: Pairs
    spec: GridSpec
    counts: Int[Array, " k"]
    views: tuple | None = None
    coverage: Pairs | None = None
    caps: tuple = eqx.field(static=True, default=())
    cull_eps: float = eqx.field(static=True, default=0.0)
    coverage_eps: float = eqx.field(static=True, default=0.0)

    @property
    def culled(self) -> bool:
        return self.cull_eps > 0

    @property
    def overflow(self) -> Bool[Array, ""]:
        over = self.shared.overflow
        if self.caps:
            over = over | jnp.any(self.counts > jnp.asarray(self.caps))
        return over

    def for_render(self) -> tuple:
        """``(lists, coverage)`` for `render.render_pairs`: the shared list and `None` (coverage
        from the same list) when unculled; else the per-view lists and the coverage list (the
        shared list when ``coverage_eps == 0``: a culled pair still covers the board)."""
        if not self.culled:
            return self.shared, None
        if self.views is None:
            raise InputError("PairLists: the per-view lists are not culled yet (update_lists)")
        return list(self.views), self.shared if self.coverage is None else self.coverage


def _culled_lists(lists: PairLists, s: Scratches, hs, board_ndf) -> list[Pairs]:
    """The ``M`` per-view culled lists (`cull` with ``hs[j]``) and the coverage list
    (`cull_coverage`, or the shared list), at the shared list's capacity (jittable)."""
    shared = lists.shared
    out = [cull(shared, s.p0, s.p1, s.width, s.depth, s.alpha, hs[j], lists.cull_eps, s.profile)
           for j in range(hs.shape[0])]
    if lists.coverage_eps > 0:
        return out + [cull_coverage(shared, s.alpha, board_ndf, lists.coverage_eps)]
    return out + [shared]


def update_lists(lists: PairLists, scratches: Scratches, hs: Float[Array, "M P 3"],
                 board_ndf: Float[Array, " P"] | None = None) -> PairLists:
    """`lists` culled for `scratches` (jittable; the shared list is kept as is): each view's
    list by `cull` under its half vectors ``hs[j]`` (``(P, 3)``, `shading.half_vectors`), the
    coverage list by `cull_coverage` with `board_ndf` (the flat board's GGX per pixel, largest
    over the views), each compacted to its capacity. An overflowing list is incomplete: check
    `PairLists.overflow` and retry after `grow_lists`; the compacted lists' own flags are cleared
    so that a renderer's overflow check does not fire first."""
    m = hs.shape[0]
    if not lists.culled:
        counts = jnp.stack([jnp.sum(lists.shared.valid)] * m)
        return eqx.tree_at(lambda q: q.counts, lists, counts.astype(jnp.int32))
    culled = _culled_lists(lists, scratches, hs, board_ndf)
    counts = jnp.stack([jnp.sum(c.valid) for c in culled]).astype(jnp.int32)
    no_flag = lambda c, cap: eqx.tree_at(lambda q: q.overflow, compact(c, cap),  # noqa: E731
                                         jnp.zeros((), bool))
    views = tuple(no_flag(c, cap) for c, cap in zip(culled[:m], lists.caps))
    cov = no_flag(culled[m], lists.caps[m]) if lists.coverage_eps > 0 else None
    return PairLists(lists.shared, lists.spec, counts, views, cov, lists.caps, lists.cull_eps,
                     lists.coverage_eps)


@eqx.filter_jit
def list_counts(lists: PairLists, scratches: Scratches, hs, board_ndf=None) -> Int[Array, " k"]:
    """The pairs each list of `update_lists` would keep (``(M + 1,)`` culled, ``(M,)`` not),
    without compacting: what `grow_lists` needs."""
    if not lists.culled:
        return jnp.stack([jnp.sum(lists.shared.valid)] * hs.shape[0]).astype(jnp.int32)
    return jnp.stack([jnp.sum(c.valid) for c in _culled_lists(lists, scratches, hs, board_ndf)])


def grow_lists(lists: PairLists, counts, margin: float | None = None) -> PairLists:
    """`lists` with per-view capacities that hold `counts` times `margin` (default: the grid's),
    rounded up to `VIEW_CAP_ROUND`, never smaller than today's (host code). The lists
    themselves are recomputed by the next `update_lists`."""
    if not lists.culled:
        return lists
    margin = lists.spec.margin if margin is None else float(margin)
    counts = np.asarray(counts)
    old = lists.caps or (0,) * counts.shape[0]
    caps = tuple(max(int(c), VIEW_CAP_ROUND * int(math.ceil(margin * max(int(n), 1)
                                                             / VIEW_CAP_ROUND)))
                 for c, n in zip(old, counts))
    return PairLists(lists.shared, lists.spec, jnp.asarray(counts, jnp.int32), None, None, caps,
                     lists.cull_eps, lists.coverage_eps)


def _arrays(s: Scratches):
    return s.p0, s.p1, s.width, s.depth


def rebin_lists(lists: PairLists, scratches: Scratches, board: Board) -> PairLists:
    """`lists` with the shared list binned again for `scratches` at the same grid capacities
    (allocating larger ones on overflow: `build_pairs`); per-view capacities kept (host code)."""
    shared, spec = build_pairs(*_arrays(scratches), board=(board.Sx, board.Sy),
                               shape=board.shape, spec=lists.spec)
    return PairLists(shared, spec, lists.counts, None, None, lists.caps, lists.cull_eps,
                     lists.coverage_eps)


def allocate_lists(scratches: Scratches, board: Board, hs: Float[Array, "M P 3"],
                   board_ndf: Float[Array, " P"] | None = None, *, cull_eps: float = 0.0,
                   coverage_eps: float = 0.0, skin: float = 0.0,
                   margin: float = DEFAULT_MARGIN) -> PairLists:
    """The `PairLists` of a scene (host code): the shared list binned with grooves inflated by
    `skin` (metres, see `needs_rebin`), and per-list capacities measured for these scratches
    (`list_counts`) times `margin`. Arguments as `update_lists`; ``cull_eps`` /
    ``coverage_eps`` the tolerances of `cull` / `cull_coverage` (finite, ``>= 0``)."""
    for name, v in (("cull_eps", cull_eps), ("coverage_eps", coverage_eps)):
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"allocate_lists: `{name}` must be finite and >= 0; got {v}")
    if coverage_eps > 0 and board_ndf is None:
        raise InputError("allocate_lists: `coverage_eps > 0` needs `board_ndf`")
    shared, spec = build_pairs(*_arrays(scratches), board=(board.Sx, board.Sy),
                               shape=board.shape, skin=skin, margin=margin)
    m = hs.shape[0]
    lists = PairLists(shared, spec, jnp.zeros((m,), jnp.int32), cull_eps=float(cull_eps),
                      coverage_eps=float(coverage_eps))
    counts = list_counts(lists, scratches, hs, board_ndf)
    return grow_lists(eqx.tree_at(lambda q: q.counts, lists, counts), counts, margin)


# --------------------------------------------------------------------------------------------
# Host layout for the renderer: compacted pair lists, split into pixel shards


#: Pairs per chunk in `render.render_pairs` (per device); pair lists are rounded to it.
#: Peak memory of the renderer's per-pair work scales with it.
DEFAULT_CHUNK = 16384


def _round_to(x: int, m: int) -> int:
    return -(-x // m) * m


def pixels_per_shard(board: Board, shards: int) -> int:
    """Pixels per shard: whole rows, ``ceil(H / shards) * W`` (the pixel axis is padded to
    ``shards`` times this)."""
    return -(-board.H // shards) * board.W


def _bucket(n: int, chunk: int) -> int:
    """Pair-list length for ``n`` pairs: a multiple of 1024 (small) or of ``chunk``, and within
    ~12% of ``n`` by rounding to 8 steps per octave, so repeated renders of similar scenes reuse
    compilations."""
    n = max(n, 1)
    step = 2 ** max(0, n.bit_length() - 4)
    return _round_to(_round_to(n, step), min(chunk, 1024))


def layout(pix: np.ndarray, scr: np.ndarray, keeps, n: int, board: Board, shards: int,
            chunk: int):
    """Pack the kept pairs of each mask in ``keeps`` into ``shards`` equal segments, segment ``s``
    holding the pairs of pixels ``[s Pb, (s+1) Pb)`` (``Pb = ceil(H / shards) W``) in their input
    order, each segment ``_bucket``-ed to the largest count over segments and masks. Padding slots
    hold the segment's first pixel and the sentinel scratch ``n``. Returns numpy ``(pixel,
    scratch, valid)``, each ``(len(keeps), shards * Ls)``."""
    Pb = pixels_per_shard(board, shards)
    idx = [np.flatnonzero(k) for k in keeps]
    blocks = [pix[i] // Pb for i in idx]
    counts = [np.bincount(b, minlength=shards) for b in blocks]
    Ls = _bucket(int(max(c.max() for c in counts)), chunk)
    shape = (len(keeps), shards * Ls)
    out_pix = np.broadcast_to(np.repeat(np.arange(shards) * Pb, Ls), shape).astype(np.int32)
    out_scr = np.full(shape, n, np.int32)
    out_val = np.zeros(shape, bool)
    for j, (i, b, c) in enumerate(zip(idx, blocks, counts)):
        order = np.argsort(b, kind="stable")  # by block, input order kept within a block
        starts = np.concatenate([[0], np.cumsum(c)[:-1]])
        dest = b[order] * Ls + np.arange(i.size) - np.repeat(starts, c)
        out_pix[j, dest] = pix[i[order]]
        out_scr[j, dest] = scr[i[order]]
        out_val[j, dest] = True
    return out_pix, out_scr, out_val


def pairs_of(pix, scr, val):
    """A `Pairs` from host arrays (pixel, scratch, valid), no overflow, no bin record."""
    return Pairs(pixel=jnp.asarray(pix), scratch=jnp.asarray(scr), valid=jnp.asarray(val),
                     overflow=jnp.asarray(False))


def check_chunk(where: str, chunk) -> None:
    """`InputError` (one line) unless `chunk`, pairs evaluated per block, is an int >= 1."""
    if whole_number(chunk) is None or chunk < 1:
        raise InputError(f"{where}: `chunk` (pairs per block) must be an int >= 1; got {chunk!r}")


def check_shards(where: str, shards) -> None:
    """`InputError` (one line) unless `shards`, the pixel blocks of a mesh, is an int >= 1."""
    if whole_number(shards) is None or shards < 1:
        raise InputError(f"{where}: `shards` (pixel blocks of the mesh) must be an int >= 1; got "
                         f"{shards!r}")


def check_pair_list(where: str, name: str, pairs) -> None:
    """`InputError` (one line) unless `pairs` is a `Pairs` (or, where `render_pairs` takes
    per-view lists, a list or tuple of them)."""
    ok = isinstance(pairs, Pairs) or (isinstance(pairs, (list, tuple))
                                      and all(isinstance(p, Pairs) for p in pairs))
    if not ok:
        raise InputError(f"{where}: `{name}` must be a bvh.Pairs pair list (bin_pairs), got "
                         f"{type(pairs).__name__}")


def _check_scene_args(where: str, scratches, board) -> None:
    if not isinstance(scratches, Scratches):
        raise InputError(f"{where}: `scratches` must be a jscratch.Scratches, got "
                         f"{type(scratches).__name__}")
    if not isinstance(board, Board):
        raise InputError(f"{where}: `board` must be a jscratch.Board, got {type(board).__name__}")


def bin_pairs(scratches: Scratches, board: Board, *, chunk: int = DEFAULT_CHUNK,
              shards: int = 1, source: str = "bin_pairs"):
    """The complete (pixel, scratch) pair list of a scene, compacted (host code).

    Bins with `build_pairs` and packs the valid pairs into ``shards`` equal segments by
    pixel block (the layout `render_pairs` needs with a mesh of ``shards`` devices; one segment
    without), each segment's length rounded up (`_bucket`: within ~12%, a multiple of 1024 or of
    ``chunk``) so that similar scenes share a compilation of `render_pairs`; padding slots hold
    the sentinel scratch ``N``.

    **Returns:** `bvh.Pairs` ``(L,)`` for `render_pairs`. **Raises:** `InputError` for a
    scratch that breaks the scene's rules (`scene.check_scratches`, endpoints on the board),
    naming `source` (the caller).
    """
    _check_scene_args(source, scratches, board)
    check_chunk(source, chunk)
    check_shards(source, shards)
    check_scratches(scratches.p0, scratches.p1, scratches.width, scratches.depth,
                    scratches.alpha, board=(board.Sx, board.Sy), source=source)
    full, _ = build_pairs(scratches.p0, scratches.p1, scratches.width, scratches.depth,
                          board=(board.Sx, board.Sy), shape=board.shape)
    pix, scr, val = layout(np.asarray(full.pixel).reshape(-1),
                            np.asarray(full.scratch).reshape(-1),
                            [np.asarray(full.valid).reshape(-1)], scratches.n, board, shards,
                            chunk)
    # with the grooves it binned (`needs_rebin`): `render_pairs` refuses it for other scratches
    return Pairs(pixel=jnp.asarray(pix[0]), scratch=jnp.asarray(scr[0]),
                 valid=jnp.asarray(val[0]), overflow=jnp.asarray(False), bin_p0=full.bin_p0,
                 bin_p1=full.bin_p1, bin_half_width=full.bin_half_width,
                 bin_extend=full.bin_extend, bin_tol=full.bin_tol)


def check_binned_for(where: str, name: str, pairs, scratches: Scratches, board: Board) -> None:
    """`InputError` (one line) when a concrete shared list that records the grooves it binned
    (`bin_pairs`, `grid.build_pairs`) was binned for another number of scratches, for another
    board (a valid pair's pixel on `board` lies outside the box of the groove it binned), or may
    miss a pair of these scratches (`needs_rebin`, when the list was binned in the scratches'
    dtype: a groove moved or grew beyond what was binned). Lists without that record, traced
    ones and per-view lists (a leading view axis) pass."""
    if (not isinstance(pairs, Pairs) or pairs.bin_p0 is None or jnp.ndim(pairs.pixel) != 1
            or jnp.ndim(pairs.bin_p0) != 2
            or any(isinstance(x, jax.core.Tracer) for x in (pairs.bin_p0, scratches.p0))):
        return
    k = pairs.bin_p0.shape[0]
    if k != scratches.n:
        raise InputError(f"{where}: `{name}` was binned for {k} scratches, got {scratches.n}: "
                         "bin_pairs(scratches, board) again")
    valid = np.asarray(pairs.valid, bool)
    pix, scr = np.asarray(pairs.pixel)[valid], np.asarray(pairs.scratch)[valid]
    if pix.size and np.all((scr >= 0) & (scr < k)):
        # each pair's pixel on this board against the box of its binned groove (ends extended,
        # half width inflated: `bin_*`)
        p0, p1 = (np.asarray(x, np.float64)[scr] for x in (pairs.bin_p0, pairs.bin_p1))
        pad = (np.asarray(pairs.bin_half_width, np.float64)[scr] + float(pairs.bin_extend)
               + float(pairs.bin_tol))[:, None]
        lo, hi = np.minimum(p0, p1) - pad, np.maximum(p0, p1) + pad
        r, c = np.divmod(pix, board.W)
        dx, dy = board.Sx / board.W, board.Sy / board.H
        slack = 1e-6 * max(dx, dy)
        top = board.Sy - r * dy
        off = ((c + 1) * dx < lo[:, 0] - slack) | (c * dx > hi[:, 0] + slack) | (
            top < lo[:, 1] - slack) | (top - dy > hi[:, 1] + slack)
        if off.any():
            raise InputError(f"{where}: `{name}` was binned for another board: {int(off.sum())} "
                             f"of its {pix.size} pairs lie outside their grooves on this "
                             f"{board.H}x{board.W} board; bin_pairs(scratches, board) again")
    # (the groove test's slack is the binning dtype's rounding: compared in that dtype only)
    same = pairs.bin_p0.dtype == scratches.p0.dtype
    if same and bool(needs_rebin(pairs, scratches.p0, scratches.p1, scratches.width,
                                 scratches.depth)):
        raise InputError(f"{where}: `{name}` may miss pairs of these scratches (a groove moved or "
                         "grew beyond what was binned): bin_pairs(scratches, board) again")


def cull_pairs(pairs, scratches: Scratches, views: Views, board: Board, eps: float, *,
               chunk: int = DEFAULT_CHUNK, shards: int = 1):
    """Per-view culled pair lists from a shared list (host code).

    Culls ``pairs`` (a shared ``(L,)`` list, e.g. from `bin_pairs`) for every view with `cull`
    (pairs whose rigorous ``D_hat`` bound is below ``eps A / (pi alpha^2)``) and packs each
    view's survivors into one ``(M, Lv)`` list laid out for ``shards`` pixel shards as in
    `bin_pairs`. Render it with ``coverage_pairs=pairs``: a culled pair still covers the board.

    **Returns:** `Pairs` ``(M, Lv)`` for `render_pairs`.
    """
    check_pair_list("cull_pairs", "pairs", pairs)
    if isinstance(pairs, (list, tuple)):
        raise InputError("cull_pairs: `pairs` must be one shared list (bin_pairs), got a sequence")
    _check_scene_args("cull_pairs", scratches, board)
    given, eps = eps, real_number(eps)
    if eps is None or not (math.isfinite(eps) and eps > 0):
        raise InputError(f"cull_pairs: `eps` must be a finite number > 0; got {given!r}")
    check_chunk("cull_pairs", chunk)
    check_shards("cull_pairs", shards)
    hs = half_vectors(views, board, scratches.dtype)
    keep = [np.asarray(cull(pairs, scratches.p0, scratches.p1, scratches.width,
                            scratches.depth, scratches.alpha, hs[j], eps, scratches.profile).valid)
            for j in range(views.m)]
    return pairs_of(*layout(np.asarray(pairs.pixel), np.asarray(pairs.scratch), keep,
                            scratches.n, board, shards, chunk))


# --------------------------------------------------------------------------------------------
# The renderer's reading of a pair list


def flat_pairs(pairs, M: int, n: int, name: str, shards: int, P_pad: int):
    """`render.render_pairs`' view of a pair list: flattened to output indices, keeping
    ``shards`` equal per-shard segments (each input list is ``shards`` equal segments; they are
    interleaved so that segment ``s`` of the result holds segment ``s`` of every view): a single
    `Pairs` ``(L,)`` shared by all views (output = pixel), a `Pairs` with leading view axis
    ``(M, L)``, or a sequence of ``M`` `Pairs` (output ``v * P_pad + pixel``). Returns ``(out,
    scratch, valid, overflow, shared)``."""

    check_pair_list("render_pairs", name, pairs)

    def segments(x):
        if x.shape[-1] % shards:
            raise InputError(
                f"render_pairs: `{name}` has length {x.shape[-1]}, not a multiple of the {shards}"
                f" pixel shards of the mesh; build it with bin_pairs(..., shards={shards})")
        return x.reshape(x.shape[:-1] + (shards, x.shape[-1] // shards))

    if isinstance(pairs, (list, tuple)):
        if len(pairs) != M:
            raise InputError(f"render_pairs: `{name}` has {len(pairs)} pair lists for {M} views")
        parts = [flat_pairs(p, 1, n, name, shards, P_pad) for p in pairs]
        cat = lambda xs: jnp.concatenate([segments(x) for x in xs], 1).reshape(-1)
        return (cat([p[0] + j * P_pad for j, p in enumerate(parts)]), cat([p[1] for p in parts]),
                cat([p[2] for p in parts]),
                functools.reduce(jnp.logical_or, [p[3] for p in parts]), False)
    pix, scr, valid = jnp.asarray(pairs.pixel), jnp.asarray(pairs.scratch), jnp.asarray(pairs.valid)
    if not (pix.shape == scr.shape == valid.shape) or pix.ndim not in (1, 2):
        raise InputError(f"render_pairs: `{name}` fields pixel, scratch, valid must share a shape"
                         f" (L,) or (M, L); got {pix.shape}, {scr.shape}, {valid.shape}")
    if not (jnp.issubdtype(pix.dtype, jnp.integer) and jnp.issubdtype(scr.dtype, jnp.integer)):
        raise InputError(f"render_pairs: `{name}` pixel and scratch indices must be integers")
    overflow = jnp.any(jnp.asarray(pairs.overflow))
    valid = valid.astype(bool)
    if pix.ndim == 2:
        if pix.shape[0] != M:
            raise InputError(f"render_pairs: `{name}` has a leading view axis of {pix.shape[0]}"
                             f" for {M} views")
        out = pix + (jnp.arange(M, dtype=pix.dtype) * P_pad)[:, None]
        inter = lambda x: jnp.swapaxes(segments(x), 0, 1).reshape(-1)  # (shards, M, Ls) order
        return inter(out), inter(scr), inter(valid), overflow, False
    segments(pix)
    return pix, scr, valid, overflow, True


def pair_checks(out, scr, valid, overflow, *, shared: bool, M: int, P: int, Pb: int,
                 shards: int, n: int, name: str) -> list:
    """``(condition, message)`` checks of a `flat_pairs` list for `eqx.error_if` (in
    `render_pairs`): no overflow, indices in range, and (with several shards) every valid pair in
    its shard's pixel block."""
    P_pad = Pb * shards
    view, pix = (jnp.zeros_like(out), out) if shared else (out // P_pad, out % P_pad)
    bad = valid & ((out < 0) | (pix >= P) | (view >= M) | (scr < 0) | (scr >= n))
    checks = [(overflow, f"render_pairs: `{name}` overflowed its capacity (incomplete pair list);"
                         " rebuild it with bvh.build_pairs"),
              (jnp.any(bad), f"render_pairs: `{name}` has a valid pair with a pixel or scratch"
                             " index out of range")]
    if shards > 1:
        seg = jnp.arange(out.shape[0]) // (out.shape[0] // shards)
        checks.append((jnp.any(valid & (pix // Pb != seg)),
                       f"render_pairs: `{name}` is not laid out for {shards} pixel shards (segment"
                       f" s must hold only pixels [s*{Pb}, (s+1)*{Pb})); build it with"
                       f" bin_pairs(..., shards={shards})"))
    return checks
