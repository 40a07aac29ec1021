"""Differentiable multi-view rendering of a scratched board (docs/model.md §1, §4 and §5).

The forward model: for every view ``j`` and pixel ``P`` the patch NDF ``D_P`` and the scratch
coverage ``c`` are sums of the per-pair integrals ``jscratch.ndf.pair_integral`` over the
(pixel, scratch) pairs that ``jscratch.bvh`` finds, divided by the footprint area ``S_P``; the pixel
is then shaded at its footprint centre (docs/model.md §4) into linear radiance.

The scene objects (`Board`, `Scratches`, `Views`, `views_on_circle`) live in `jscratch.scene`
and the shading (`pixel_footprints`, `half_vectors`, `shade`, `display`) in `jscratch.shading`;
both are re-exported here.

**Rendering:**

- `render(scratches, views, board, *, eps=0.0)`: host driver; bins (`bin_pairs`), culls per
  view when ``eps > 0`` (`cull_pairs`, `bvh.cull`) and calls `render_pairs`.
- `render_pairs(scratches, views, board, pairs)`: the differentiable core, jittable, for use
  inside a loss; the pair list is integer data computed outside the differentiated function
  (`bin_pairs` makes one).
- `render_reference(scratches, views, board)`: float64 all-pairs reference (every scratch against
  every pixel, dense sum, plain autodiff), for small scenes and tests.

**Memory and the reverse pass.** Pairs are evaluated in chunks in a `lax.scan`, segment-summed
per pixel (``O(M H W + N + chunk)`` floats for any number of pairs); the reverse pass (a
`jax.custom_vjp`) walks the same chunks. On one device with the native kernel the gradient's
forward pass keeps each pair's Jacobian (`native.pair_jacobian`, ``10 M + 6`` floats a pair);
otherwise chunks are re-evaluated (`native.pair_vjp`, or the jnp path's VJP). Reverse mode only.

**The pair kernel** follows `Scratches.profile` (the paper's groove or the ball's arc). With the
native kernel (CPU) a chunk is one call: each pair's geometry once, then every view over its own
pieces, the pairs in order of their piece count inside the kernel (docs/model.md §12).
Elsewhere (``JSCRATCH_NATIVE=0``, other backends) the jnp path runs `ndf.pair_geometry` vmapped,
then per view `ndf.lit_integral(..., pieces=k)` (`k` the smallest of `PIECE_BUDGETS` the chunk
needs) or `arc.arc_lit_integral`. Padding is sorted last per shard and skipped by chunks.

**Multiple devices.** Given a `jax.sharding.Mesh`, the pixel axis is split into strips of rows
(`jax.shard_map`), parameters replicated and their gradients ``psum``-ed; the pair lists must be
laid out per strip (`bin_pairs` / `cull_pairs` with ``shards=``, as `render` does). The result is
the one-device result up to summation order (docs/architecture.md, "Several devices").

Computation follows the dtype of ``scratches`` (float32 for users, float64 for references);
``views`` are cast to it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec
from jaxtyping import Array, Float

from jscratch import arc, lobe, native, ndf
from jscratch.compile_options import grad_compiler_options
from jscratch.bvh import (DEFAULT_CHUNK, bin_pairs, check_binned_for, check_chunk, cull_pairs,
                          flat_pairs, pair_checks, pixels_per_shard, view_keep)
from jscratch.errors import InputError, instance_arg, real_number
from jscratch.scene import (
    Board,
    Scratches,
    Views,
    check_scratches,
    check_views,
    flat_highlight,
    scene_checks,
    views_on_circle,
)
from jscratch.shading import (
    DISPLAY_GAMMA,
    DISPLAY_KNEE,
    board_ndf,
    display,
    half_vectors,
    pixel_centres,
    pixel_edges,
    pixel_footprints,
    shade,
)

__all__ = [
    "DEFAULT_CHUNK", "DISPLAY_GAMMA", "DISPLAY_KNEE", "Board", "Scratches", "Views",
    "bin_pairs", "cull_pairs", "display", "flat_highlight", "pixel_edges",
    "grad_compiler_options", "half_vectors", "board_ndf", "pixel_centres", "pixel_footprints",
    "render", "render_pairs", "render_reference", "shade", "views_on_circle",
]



# --------------------------------------------------------------------------------------------
# Pair accumulation with bounded memory (custom VJP, chunked, optionally sharded)
# --------------------------------------------------------------------------------------------


class _Cfg(NamedTuple):
    H: int
    W: int
    Sx: float
    Sy: float
    chunk: int  # pairs per chunk, per device
    mesh: Any  # jax.sharding.Mesh or None
    axes: tuple  # mesh axis names the pixel axis is sharded over
    Pb: int  # pixels per shard (the whole padded pixel axis is Pb * n_shards)
    per_view: bool  # pair outputs are (view, pixel): index v * P_pad + pixel; else pixel only
    need_D: bool
    need_A: bool
    profile: str  # `Scratches.profile`
    skip_eps: float = 0.0  # pair-views skipped below this bound (`bvh.view_keep`; shared lists)

    def keep(self, p0, p1, w, d, a, h):
        """The jnp path's pair-views to evaluate ``(V, chunk)`` (`bvh.view_keep`; the native
        kernel decides the same itself), or None for all."""
        if self.skip_eps == 0 or not self.need_D:
            return None
        return view_keep(h, p0, p1, w, d, a, self.skip_eps, self.profile)

    def nodes(self, dtype) -> int:
        """Gauss-Legendre nodes per piece of the profile's lit integral (the native kernel's)."""
        return (arc.nodes if self.profile == "arc" else lobe.nodes)(dtype)


def _board_of(cfg: _Cfg) -> Board:
    return Board(shape=(cfg.H, cfg.W), Sx=cfg.Sx, Sy=cfg.Sy)


def _footprint(cfg: _Cfg, xe, ye, pix):
    """The footprint ``(4, 2)`` of pixel ``pix = r*W + c`` from the pixel edges."""
    r = pix // cfg.W
    c = pix % cfg.W
    x0, x1, y0, y1 = xe[c], xe[c + 1], ye[r + 1], ye[r]
    return jnp.stack([jnp.stack([x0, y0]), jnp.stack([x1, y0]), jnp.stack([x1, y1]),
                      jnp.stack([x0, y1])])


def _split_index(cfg: _Cfg, out):
    """Global pair output index -> ``(pixel, local index)``: the board pixel (clipped into the
    board, for padding slots) and the index into this shard's flat accumulator (``Pb`` pixels,
    or ``M * Pb`` (view, pixel) slots when ``per_view``)."""
    P_pad = cfg.Pb * _n_shards(cfg.mesh, cfg.axes)
    shard = 0 if cfg.mesh is None else jax.lax.axis_index(cfg.axes)
    if cfg.per_view:
        v, pix = out // P_pad, out % P_pad
        local = v * cfg.Pb + (pix - shard * cfg.Pb)
    else:
        pix = out
        local = pix - shard * cfg.Pb
    return jnp.minimum(pix, cfg.H * cfg.W - 1), local


def _gather(params, h_loc, scr, local):
    """Per-pair parameters ``(chunk, ...)`` and half vectors ``(V, chunk, 3)``."""
    p0, p1, w, d, a = params
    take = lambda x: x.at[scr].get(mode="clip")  # sentinel N -> N-1; masked below
    return (take(p0), take(p1), take(w), take(d), take(a),
            h_loc.at[:, local].get(mode="clip"))


#: Piece budgets (`ndf.lit_integral`'s `pieces`): a chunk of pairs is integrated with the
#: smallest budget that holds the largest `ndf.PairGeometry.count` among its valid pairs.
PIECE_BUDGETS = (2, ndf.N_COMPACT, ndf.N_PIECES)


def _chunk_geometry(cfg: _Cfg, xe, ye, pix, valid, p0, p1, w, d):
    """`ndf.pair_geometry` of a chunk's pairs (fields with a leading ``(chunk,)`` axis, ``count``
    set to ``None``) and the budget index (`PIECE_BUDGETS`) its valid pairs' counts need.
    Padding slots get a benign off-board dummy pair first (double-where), so no value or
    gradient there can be NaN; their counts are ignored."""
    dt = w.dtype
    v1 = valid[:, None]
    p0 = jnp.where(v1, p0, jnp.asarray([-1.0, -1.0], dt))
    p1 = jnp.where(v1, p1, jnp.asarray([-0.99, -1.0], dt))
    w = jnp.where(valid, w, jnp.asarray(1e-4, dt))
    d = jnp.where(valid, d, jnp.asarray(1e-4, dt))
    footprints = jax.vmap(functools.partial(_footprint, cfg, xe, ye))(pix)
    geometry = jax.vmap(ndf.pair_geometry)(footprints, p0, p1, w, d)
    most = jnp.max(jnp.where(valid, geometry.count, 0))
    budget = sum((most > k).astype(jnp.int32) for k in PIECE_BUDGETS[:-1])
    return geometry._replace(count=None), budget


def _chunk_lit(profile: str, pieces: int, geometry, valid, a, h):
    """Per-pair ``D_hat`` ``(V, chunk)``, one row per view of ``h`` ``(V, chunk, 3)``, from the
    chunk's geometry with `ndf.lit_integral(..., pieces=pieces)` (`arc.arc_lit_integral` for the
    arc profile, with the same budget); zero on padding slots. The geometry is shared by the
    views (vmap keeps it unbatched)."""
    dt = a.dtype
    a = jnp.where(valid, a, jnp.asarray(0.5, dt))
    h = jnp.where(valid[None, :, None], h, jnp.asarray([0.0, 0.0, 1.0], dt))
    lit = functools.partial(arc.arc_lit_integral if profile == "arc" else ndf.lit_integral,
                            pieces=pieces)
    D = jax.vmap(jax.vmap(lit), in_axes=(None, 0, None))(geometry, h, a)
    return jnp.where(valid[None], D, jnp.zeros((), dt))


def _chunk_native(cfg: _Cfg, xe, ye, pix, valid, p0, p1, w, d, a, h):
    """The native kernel's inputs for a chunk: the footprints ``(chunk, 4, 2)``, the gathered
    parameters, `valid` and the half vectors ``(V, chunk, 3)`` (none where ``D`` is not needed);
    the kernel gives padding slots exact zeros."""
    footprints = jax.vmap(functools.partial(_footprint, cfg, xe, ye))(pix)
    return footprints, p0, p1, w, d, a, valid, (h if cfg.need_D else h[:0])


def _budgets(cfg: _Cfg, fn):
    """`lax.switch` branches: ``fn(profile, pieces, ...)`` for each of `PIECE_BUDGETS`."""
    return [functools.partial(fn, cfg.profile, k) for k in PIECE_BUDGETS]


def _edges_in(cfg: _Cfg, dtype):
    xe, ye = pixel_edges(_board_of(cfg))
    return jnp.asarray(xe, dtype), jnp.asarray(ye, dtype)


def _chunks(cfg: _Cfg, *xs):
    return tuple(x.reshape(-1, cfg.chunk) for x in xs)


def _varying(cfg: _Cfg, tree):
    """Inside `jax.shard_map`, mark scan-carry initial values as device-varying."""
    if cfg.mesh is None:
        return tree
    return jax.tree_util.tree_map(lambda x: jax.lax.pcast(x, cfg.axes, to="varying"), tree)


def _flat_h(cfg: _Cfg, h_loc):
    """This shard's half vectors ``(V, Pb, 3)`` as the rows the pairs index: ``(V, Pb, 3)`` for a
    shared list, ``(1, V * Pb, 3)`` for per-view outputs."""
    return h_loc.reshape(1, -1, 3) if cfg.per_view else h_loc


def _scan_chunks(add_chunk, init, xs, idle=None):
    """`lax.scan` of ``add_chunk`` over chunks ``xs`` skipping those of padding only (``xs[2]``:
    valid); with `idle` (a skipped chunk's output) it returns ``(carry, output)``, else a carry."""
    step = add_chunk if idle is not None else lambda c, x: (add_chunk(c, x), None)
    return jax.lax.scan(lambda c, x: jax.lax.cond(jnp.any(x[2]), step,
                                                  lambda c, _: (c, idle), c, x), init, xs)


def _fwd_local(cfg: _Cfg, params, h_loc, out, scr, valid):
    """This shard's sums: ``D`` ``(M, Pb)`` and ``A`` ``(1 or M, Pb)`` over its pairs."""
    dt = params[2].dtype
    xe, ye = _edges_in(cfg, dt)
    h_rows = _flat_h(cfg, h_loc)
    V, n_loc = h_rows.shape[:2]

    def add_chunk(carry, xs):
        Ds, As = carry
        oc, sc, vc = xs
        pix, local = _split_index(cfg, oc)
        p0, p1, w, d, a, h = _gather(params, h_rows, sc, local)
        if native.available(dt):
            args = _chunk_native(cfg, xe, ye, pix, vc, p0, p1, w, d, a, h)
            D, A = native.pair_values(cfg.nodes(dt), *args, profile=cfg.profile,
                                      skip_eps=cfg.skip_eps)
            Ds = Ds.at[:, local].add(D, mode="drop") if cfg.need_D else Ds
            return Ds, (As.at[local].add(A, mode="drop") if cfg.need_A else As)
        geometry, budget = _chunk_geometry(cfg, xe, ye, pix, vc, p0, p1, w, d)
        if cfg.need_D:
            D = jax.lax.switch(budget, _budgets(cfg, _chunk_lit), geometry, vc, a, h)
            keep = cfg.keep(p0, p1, w, d, a, h)
            D = D if keep is None else jnp.where(keep, D, jnp.zeros((), dt))
            Ds = Ds.at[:, local].add(D, mode="drop")
        if cfg.need_A:
            As = As.at[local].add(jnp.where(vc, geometry.area, 0), mode="drop")
        return Ds, As

    init = _varying(cfg, (jnp.zeros((V, n_loc), dt), jnp.zeros((n_loc,), dt)))
    (Ds, As), _ = _scan_chunks(add_chunk, init, _chunks(cfg, out, scr, valid))
    return Ds.reshape(-1, cfg.Pb), As.reshape(-1, cfg.Pb)


def _bwd_local(cfg: _Cfg, params, h_loc, out, scr, valid, gD, gA):
    dt = params[2].dtype
    xe, ye = _edges_in(cfg, dt)
    h_rows = _flat_h(cfg, h_loc)
    gD = gD.reshape(h_rows.shape[:2])
    gA = gA.reshape(-1)

    def lit_vjp(profile, pieces, geometry, valid, a, h, ct):
        """The per-view stage's value and reverse pass in one `lax.switch` branch, so no
        residuals cross the switch."""
        _, vjp = jax.vjp(lambda g, a, h: _chunk_lit(profile, pieces, g, valid, a, h), geometry, a, h)
        return vjp(ct)

    def add_chunk(carry, xs):
        oc, sc, vc = xs
        pix, local = _split_index(cfg, oc)
        p0, p1, w, d, a, h = _gather(params, h_rows, sc, local)
        if native.available(dt):
            args = _chunk_native(cfg, xe, ye, pix, vc, p0, p1, w, d, a, h)
            ctD = gD.at[:, local].get(mode="clip")[:len(args[-1])]  # (no rows without D)
            ctA = gA.at[local].get(mode="clip") if cfg.need_A else jnp.zeros_like(w)
            *dp, dh = native.pair_vjp(cfg.nodes(dt), *args, ctD, ctA, profile=cfg.profile,
                                      skip_eps=cfg.skip_eps)
            return scatter(carry, sc, local, *dp, dh if cfg.need_D else jnp.zeros_like(h))
        geometry, geometry_vjp, budget = jax.vjp(
            lambda *x: _chunk_geometry(cfg, xe, ye, pix, vc, *x), p0, p1, w, d, has_aux=True)
        # Only the outputs the caller uses are differentiated (no dead reverse work).
        if cfg.need_D:
            ctD = gD.at[:, local].get(mode="clip")
            keep = cfg.keep(p0, p1, w, d, a, h)
            ctD = ctD if keep is None else jnp.where(keep, ctD, jnp.zeros((), dt))
            g_geometry, da, dh = jax.lax.switch(budget, _budgets(cfg, lit_vjp), geometry, vc, a, h,
                                                ctD)
        else:
            g_geometry = jax.tree_util.tree_map(jnp.zeros_like, geometry)
            da, dh = jnp.zeros_like(a), jnp.zeros_like(h)
        if cfg.need_A:
            ctA = jnp.where(vc, gA.at[local].get(mode="clip"), 0)
            g_geometry = g_geometry._replace(area=g_geometry.area + ctA)
        return scatter(carry, sc, local, *geometry_vjp(g_geometry), da, dh)

    def scatter(grads, sc, local, *parts):
        # The sentinel index N is out of range: mode="drop" discards padding slots (already zero).
        *per_scratch, gh = grads
        out = tuple(g.at[sc].add(x, mode="drop") for g, x in zip(per_scratch, parts))
        return out + (gh.at[:, local].add(parts[-1], mode="drop"),)

    # (zeros_like of the device-local half vectors is already device-varying)
    init = _varying(cfg, tuple(jnp.zeros_like(x) for x in params)) + (jnp.zeros_like(h_rows),)
    grads, _ = _scan_chunks(add_chunk, init, _chunks(cfg, out, scr, valid))
    dparams = grads[:5]
    if cfg.mesh is not None:  # parameters are replicated: their gradient sums over all shards
        dparams = jax.lax.psum(dparams, cfg.axes)
    return dparams, grads[5].reshape(h_loc.shape)


def _maybe_shard(cfg: _Cfg, fn, in_specs, out_specs):
    """`fn` under `jax.shard_map` over ``cfg.mesh`` (identity without a mesh). Specs use ``"p"``
    for the pixel axis sharded over ``cfg.axes``."""
    if cfg.mesh is None:
        return fn
    spec = lambda s: jax.tree_util.tree_map(
        lambda t: PartitionSpec(*(cfg.axes if a == "p" else None for a in t)), s,
        is_leaf=lambda t: isinstance(t, tuple) and all(isinstance(a, (str, type(None))) for a in t))
    return jax.shard_map(fn, mesh=cfg.mesh, in_specs=spec(in_specs), out_specs=spec(out_specs))


# Sharding of each argument: params replicated, half vectors and outputs split on the pixel axis,
# the (block-laid-out) pair list split into its per-shard segments.
_REP, _PIX, _PAIRS, _HV = (), (None, "p"), ("p",), (None, "p", None)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _pair_sums(cfg: _Cfg, params, h_views, out, scr, valid):
    """Per-pixel sums over the pairs: ``sum D_hat`` ``(M, P_pad)`` and ``sum A``
    ``(1 or M, P_pad)``; ``h_views`` ``(M, P_pad, 3)``. ``out, scr, valid`` ``(L,)``: ``n_shards``
    equal segments, segment ``s`` holding only pairs of pixels ``[s Pb, (s+1) Pb)``, each a
    multiple of ``chunk`` long (in any order; `_sort_pairs`' order is the fast one)."""
    fn = _maybe_shard(cfg, functools.partial(_fwd_local, cfg),
                      (_REP, _HV, _PAIRS, _PAIRS, _PAIRS), (_PIX, _PIX))
    return fn(params, h_views, out, scr, valid)


def _jac_fwd(cfg: _Cfg, params, h_loc, out, scr, valid):
    """`_fwd_local`'s sums by `native.pair_jacobian`, and each chunk's Jacobians."""
    dt = params[2].dtype
    (xe, ye), h_rows = _edges_in(cfg, dt), _flat_h(cfg, h_loc)
    V, n_loc = h_rows.shape[:2]

    def add_chunk(carry, xs):
        Ds, As = carry
        pix, local = _split_index(cfg, xs[0])
        p0, p1, w, d, a, h = _gather(params, h_rows, xs[1], local)
        D, A, *J = native.pair_jacobian(cfg.nodes(dt), *_chunk_native(
            cfg, xe, ye, pix, xs[2], p0, p1, w, d, a, h), profile=cfg.profile,
            skip_eps=cfg.skip_eps)
        Ds = Ds.at[:, local].add(D, mode="drop") if cfg.need_D else Ds
        return (Ds, As.at[local].add(A, mode="drop") if cfg.need_A else As), tuple(J)

    Vd = V if cfg.need_D else 0
    zeros = tuple(jnp.zeros(sh, dt) for sh in ((Vd, cfg.chunk, 7), (Vd, cfg.chunk, 3),
                                                (cfg.chunk, 6)))
    init = (jnp.zeros((V, n_loc), dt), jnp.zeros((n_loc,), dt))  # (padding chunks: J zeros)
    (Ds, As), J = _scan_chunks(add_chunk, init, _chunks(cfg, out, scr, valid), zeros)
    return (Ds.reshape(-1, cfg.Pb), As.reshape(-1, cfg.Pb)), J


def _jac_bwd(cfg: _Cfg, params, h_loc, out, scr, valid, J, gD, gA, need_h: bool = True):
    """The reverse pass from `_jac_fwd`'s Jacobians (cotangents times Jacobians, the seven
    per-pair derivatives scatter-added per scratch at once); the half vectors' cotangent only
    when `need_h` (zeros otherwise: a design's half vectors are constants, and their scatter-add
    costs ~6 % of the default design's render value and gradient)."""
    h_rows = _flat_h(cfg, h_loc)
    gD, gA = gD.reshape(h_rows.shape[:2]), gA.reshape(-1)

    def add_chunk(carry, xs):
        oc, sc, vc, JD, Jh, JA = xs
        _, local = _split_index(cfg, oc)
        ctD = gD.at[:, local].get(mode="clip") if cfg.need_D else jnp.zeros(JD.shape[:2], gD.dtype)
        g = jnp.sum(ctD[..., None] * JD, axis=0)  # (a fusion: an einsum here transposes)
        if cfg.need_A:
            g = g.at[:, :6].add(jnp.where(vc, gA.at[local].get(mode="clip"), 0)[:, None] * JA)
        gh = carry[1].at[:, local].add(ctD[..., None] * Jh, mode="drop") if (
            cfg.need_D and need_h) else carry[1]
        return carry[0].at[sc].add(g, mode="drop"), gh  # (one scatter, not one per parameter)

    n, dt = params[2].shape[0], params[2].dtype
    init = (jnp.zeros((n, 7), dt), jnp.zeros_like(h_rows))
    (g, gh), _ = _scan_chunks(add_chunk, init, _chunks(cfg, out, scr, valid) + tuple(J))
    grads = (g[:, 0:2], g[:, 2:4], g[:, 4], g[:, 5], g[:, 6])
    return (tuple(x.reshape(y.shape).astype(y.dtype) for x, y in zip(grads, params)),
            gh.reshape(h_loc.shape))


_PRIMAL, _ZERO = jax.custom_derivatives.CustomVJPPrimal, jax.custom_derivatives.SymbolicZero


def _pair_sums_fwd(cfg, params, h_views, out, scr, valid):
    # (symbolic zeros: the arguments come wrapped, with whether they are perturbed; a design's
    # half vectors are not, and then the reverse pass leaves their cotangent out)
    need_h, wrapped = bool(getattr(h_views, "perturbed", True)), lambda x: isinstance(x, _PRIMAL)
    res = jax.tree_util.tree_map(lambda x: x.value if wrapped(x) else x,
                                 (params, h_views, out, scr, valid), is_leaf=wrapped)
    # One device with the native kernel: keep the pairs' Jacobians (the module docstring); the
    # last residual is `(J,)` when the half vectors' cotangent is wanted, `(J, None)` when not
    if cfg.mesh is None and native.available(res[0][2].dtype):
        sums, J = _jac_fwd(cfg, *res)
        return sums, res + ((J,) if need_h else (J, None),)
    return _pair_sums(cfg, *res), res + (None,)


def _pair_sums_bwd(cfg, res, g):
    params, h_views, out, scr, valid, J = res
    gD, gA = (jnp.zeros(x.aval.shape, x.aval.dtype) if isinstance(x, _ZERO) else x for x in g)
    if J is not None:
        dparams, dh = _jac_bwd(cfg, params, h_views, out, scr, valid, J[0], gD, gA,
                               need_h=len(J) == 1)
        return dparams, dh, None, None, None
    fn = _maybe_shard(cfg, functools.partial(_bwd_local, cfg),
                      (_REP, _HV, _PAIRS, _PAIRS, _PAIRS, _PIX, _PIX), (_REP, _HV))
    dparams, dh = fn(params, h_views, out, scr, valid, gD, gA)
    return dparams, dh, None, None, None


_pair_sums.defvjp(_pair_sums_fwd, _pair_sums_bwd, symbolic_zeros=True)


def _mesh_axes(mesh, axis_names) -> tuple:
    if mesh is None:
        return ()
    if axis_names is None:
        return tuple(mesh.axis_names)
    return (axis_names,) if isinstance(axis_names, str) else tuple(axis_names)


def _n_shards(mesh, axes) -> int:
    if mesh is None:
        return 1
    return int(np.prod([mesh.shape[a] for a in axes]))


def _round_up(x: int, m: int) -> int:
    return -(-x // m) * m


def _pair_classes(cfg: _Cfg, params, out, scr, valid):
    """Per pair (int8), 1 + the index of the smallest of `PIECE_BUDGETS` that holds its
    `ndf.piece_count_estimate` (a tenth of the geometry's cost), 0 for padding: only the order of
    the evaluation depends on it (each chunk's budget comes from the counts it computes)."""
    p0, p1, w, d = params[:4]
    xe, ye = _edges_in(cfg, p0.dtype)
    P_pad = cfg.Pb * _n_shards(cfg.mesh, cfg.axes)

    def count(args):
        out, scr = args
        pix = jnp.minimum(out % P_pad if cfg.per_view else out, cfg.H * cfg.W - 1)
        take = lambda x: x.at[scr].get(mode="clip")
        return ndf.piece_count_estimate(_footprint(cfg, xe, ye, pix), take(p0), take(p1),
                                        take(w), take(d)).astype(jnp.int8)

    # (chunk by chunk: no per-pair footprint array is materialised)
    n = jax.lax.map(count, (out, scr), batch_size=cfg.chunk)
    klass = 1 + sum((n > k).astype(jnp.int8) for k in PIECE_BUDGETS[:-1])
    return jax.lax.stop_gradient(jnp.where(valid, klass, 0).astype(jnp.int8))


def _sort_pairs(out, scr, valid, klass, shards: int):
    """Each shard's segment of the pair list grouped by class (1, 2, ..., then 0, the padding),
    each group in its own order (a stable partition, O(L)): chunks of padding are skipped and the
    others mostly hold one piece budget."""
    L = out.shape[0]
    Ls = L // shards
    # (a barrier: a pair list closed over as a constant would otherwise be folded at compile time)
    klass = jax.lax.optimization_barrier(klass)
    pos = jnp.zeros((shards, Ls), jnp.int32)
    start = jnp.zeros((shards, 1), jnp.int32)
    for c in (*range(1, len(PIECE_BUDGETS) + 1), 0):
        g = (klass == c).reshape(shards, Ls)
        pos = jnp.where(g, start + jnp.cumsum(g, axis=1, dtype=jnp.int32) - 1, pos)
        start = start + jnp.sum(g, axis=1, keepdims=True, dtype=jnp.int32)
    pos = (pos + (jnp.arange(shards, dtype=jnp.int32) * Ls)[:, None]).reshape(-1)
    source = jnp.zeros((L,), jnp.int32).at[pos].set(jnp.arange(L, dtype=jnp.int32),
                                                      unique_indices=True)
    return out[source], scr[source], valid[source]


def _run_pair_sums(scratches: Scratches, board: Board, h_views, out, scr, valid, *, per_view,
                   chunk, mesh, axes, need_D, need_A, skip_eps=0.0):
    """Pad every shard's segment of the pair list to a multiple of the chunk, pad the pixel axis
    to ``Pb * n_shards`` and call `_pair_sums`; returns sums over the board's ``P`` pixels."""
    shards = _n_shards(mesh, axes)
    P = board.n_pixels
    Pb = pixels_per_shard(board, shards)
    Ls = out.shape[0] // shards
    chunk = int(min(chunk, _round_up(max(Ls, 1), 64)))
    Ls_pad = _round_up(max(Ls, 1), chunk)
    n = scratches.n

    def pad(x, fill, k):
        x = x.reshape(k, Ls)
        x = jnp.concatenate([x, jnp.full((k, Ls_pad - Ls), fill, x.dtype)], 1)
        return x.reshape(-1)

    if Pb * shards != P:
        fill = jnp.zeros(h_views.shape[:1] + (Pb * shards - P, 3), h_views.dtype).at[..., 2].set(1)
        h_views = jnp.concatenate([h_views, fill], 1)
    cfg = _Cfg(board.H, board.W, board.Sx, board.Sy, chunk, mesh, axes, Pb, per_view, need_D,
               need_A, scratches.profile, float(skip_eps))
    params = (scratches.p0, scratches.p1, scratches.width, scratches.depth, scratches.alpha)

    def order(params, out, scr, valid, k):  # pad and sort ``k`` segments
        if Ls_pad != Ls:
            out, scr, valid = pad(out, 0, k), pad(scr, n, k), pad(valid, False, k)
        # (the native kernel integrates each pair's own pieces and orders each chunk by piece
        # count itself: only padding is put last)
        klass = (valid.astype(jnp.int8) if native.available(params[2].dtype)
                 else _pair_classes(cfg, params, out, scr, valid))
        return _sort_pairs(out, scr, valid, klass, k)

    if mesh is None:
        out, scr, valid = order(params, out, scr, valid, shards)
    else:  # each device pads and sorts its own segment: outside `shard_map`, XLA would gather
        # the whole pair list to every device at every call
        out, scr, valid = _maybe_shard(cfg, functools.partial(order, k=1),
                                       (_REP, _PAIRS, _PAIRS, _PAIRS), (_PAIRS,) * 3)(
            jax.lax.stop_gradient(params), out, scr, valid)
    Ds, As = _pair_sums(cfg, params, h_views, out, scr, valid)
    return Ds[:, :P], As[:, :P]


# --------------------------------------------------------------------------------------------
# Renderers
# --------------------------------------------------------------------------------------------


def _guard(x, checks, mesh):
    """Apply ``(condition, message)`` checks to ``x``. Concrete conditions (an eager call) raise
    `ValueError` at once. Traced ones use `eqx.error_if` on one device; over a mesh a runtime
    error raised on one device would leave the others waiting in a collective (XLA aborts the
    process), so there the result is poisoned instead: returns ``(x, poisoned)`` with
    ``poisoned`` a traced bool (or ``False``) for the caller to turn into NaN radiance."""
    poisoned = False
    for bad, msg in checks:
        if not isinstance(bad, jax.core.Tracer):
            if bool(bad):
                raise InputError(msg)
        elif mesh is None:
            x = eqx.error_if(x, bad, msg)
        else:
            poisoned = poisoned | bad
    return x, poisoned


def _check_values(scratches: Scratches, views: Views):
    """`eqx.error_if` value checks (work inside jit, single device); returns checked copies."""
    w, _ = _guard(scratches.width, scene_checks(scratches, views), None)
    return eqx.tree_at(lambda t: t.width, scratches, w), views


def render_pairs(scratches: Scratches, views: Views, board: Board, pairs,
                 coverage_pairs=None, *, chunk: int = DEFAULT_CHUNK,
                 mesh: jax.sharding.Mesh | None = None,
                 axis_names: str | Sequence[str] | None = None,
                 checked: bool = True, skip_eps: float = 0.0) -> Float[Array, "m h w"]:
    """Render linear radiance from precomputed pair lists (jittable, differentiable).

    **Arguments:**

    - `scratches`, `views`, `board`: the scene. Computation in ``scratches.dtype``.
    - `pairs`: the (pixel, scratch) pairs, as `bvh.Pairs` (fields ``pixel, scratch, valid,
      overflow``): one list ``(L,)`` shared by every view, one with a leading view axis ``(M, L)``,
      or a sequence of ``M`` lists (e.g. culled per view). Pixel indices are ``r*W + c``.
    - `coverage_pairs`: the pair list the coverage ``c`` is summed over (a shared, unculled ``(L,)``
      list). Default: ``pairs`` itself when shared, else each view's own list (exact only when the
      per-view lists are unculled: a culled pair still covers the board).
    - `skip_eps` (static float in ``[0, 1]``, shared `pairs` only): skip the pair-views
      `cull.view_keep` drops at this tolerance (each below ``skip_eps A / (pi alpha^2)``, never a
      pair's brightest view; their values and gradients are zero, the coverage keeps every pair;
      docs/model.md §11). The native kernel computes the bound itself and skips the work of a
      view that no pair of a SIMD block keeps; the jnp path evaluates the pair-views and zeroes
      them. ``0`` (default) skips none.
    - `chunk`: pairs per chunk per device (memory knob; results do not depend on it beyond rounding).
    - `mesh`, `axis_names`: shard the pixel axis over these mesh axes (default: all axes of
      `mesh`); the pair lists must then be laid out for ``n_shards`` pixel blocks (`bin_pairs` /
      `cull_pairs` with ``shards=n_shards``; see the module docstring).
    - `checked`: ``False`` leaves out the traced value and pair-list checks below (the shapes
      are still checked), for a caller that guarantees them: the design step, whose own checks
      cover every parameter it updates, saves their tracing, compilation and per-call cost.

    **Returns:** radiance ``(M, H, W)`` (W/(sr m^2)).

    Errors: non-finite or out-of-range scratch or view values, a camera or light below the board,
    an overflowed pair list, out-of-range pair indices, a pair list not laid out for the mesh;
    called eagerly, also a list binned for other scratches or another board
    (`bvh.check_binned_for`; a list from `bin_pairs` records what it binned). Called eagerly:
    `ValueError`. Under jit on one device: `eqx.error_if` (a runtime error).
    Under jit with a mesh: NaN radiance (a runtime error on one device of a multi-device program
    would leave the others stuck in a collective; `render` checks the scene before it renders).
    Gradients: reverse mode only (a `jax.custom_vjp`; see the module docstring).
    """
    _check_scene_types("render_pairs", scratches, views, board)
    check_chunk("render_pairs", chunk)
    dtype = scratches.dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise InputError(f"render_pairs: scratches must be floating point; got {dtype}")
    if checked and not any(isinstance(a, jax.core.Tracer) for a in (scratches.p0, scratches.p1)):
        # Called eagerly: the endpoints too (inside jit the board is static: `render` checks).
        check_scratches(scratches.p0, scratches.p1, scratches.width, scratches.depth,
                        scratches.alpha, board=(board.Sx, board.Sy), source="render_pairs")
        for name, p in (("pairs", pairs), ("coverage_pairs", coverage_pairs)):
            check_binned_for("render_pairs", name, p, scratches, board)
    M, P, n = views.m, board.n_pixels, scratches.n
    axes = _mesh_axes(mesh, axis_names)
    shards = _n_shards(mesh, axes)
    Pb = pixels_per_shard(board, shards)
    # The checks hang on a small replicated parameter, not on the (sharded) pair arrays.
    checks = scene_checks(scratches, views) if checked else []
    views = jax.tree_util.tree_map(lambda x: x.astype(dtype), views)
    geo_h = half_vectors(views, board, dtype)  # (M, P, 3)

    def flat(p, m, what):
        out, scr, valid, over, shared = flat_pairs(p, m, n, what, shards, Pb * shards)
        if checked:
            checks.extend(pair_checks(out, scr, valid, over, shared=shared, M=m, P=P, Pb=Pb,
                                       shards=shards, n=n, name=what))
        return out, scr, valid, shared

    # A shared list is evaluated for every view at once (views vmapped inside the chunk, the
    # scratch geometry gathered once); per-view lists are flattened to outputs v*P_pad + pixel.
    out, scr, valid, shared = flat(pairs, M, "pairs")
    if not (isinstance(skip_eps, (int, float)) and 0 <= skip_eps <= 1):
        raise InputError(f"render_pairs: skip_eps must be a float in [0, 1], got {skip_eps!r}")
    if skip_eps > 0 and not shared:
        raise InputError("render_pairs: skip_eps > 0 needs one pair list shared by the views "
                         "(per-view lists are culled already)")
    if coverage_pairs is not None:
        cout, cscr, cvalid, cshared = flat(coverage_pairs, 1, "coverage_pairs")
        if not cshared:
            raise InputError("render_pairs: `coverage_pairs` must be one shared (L,) list")
    w, poisoned = _guard(scratches.width, checks, mesh)
    scratches = eqx.tree_at(lambda t: t.width, scratches, w)
    kw = dict(chunk=chunk, mesh=mesh, axes=axes)
    if n == 0:
        Ds, As = jnp.zeros((M, P), dtype), jnp.zeros((1 if shared else M, P), dtype)
    else:
        Ds, As = _run_pair_sums(scratches, board, geo_h, out, scr, valid, per_view=not shared,
                                need_D=True, need_A=coverage_pairs is None,
                                skip_eps=skip_eps, **kw)
    if coverage_pairs is not None:
        if n == 0:
            As = jnp.zeros((1, P), dtype)
        else:
            h_dummy = jnp.zeros((1, P, 3), dtype).at[..., 2].set(1)
            _, As = _run_pair_sums(scratches, board, h_dummy, cout, cscr, cvalid, per_view=False,
                                   need_D=False, need_A=True, **kw)
    S = board.pixel_area
    rad = shade(Ds / S, As / S, views, board)
    if poisoned is not False:  # traced checks over a mesh (see `_guard`)
        rad = jnp.where(poisoned, jnp.nan, rad)
    return rad.reshape(M, board.H, board.W)


_checked_scene = eqx.filter_jit(_check_values)


def _check_scene_types(where: str, scratches, views, board) -> None:
    """A one-line `InputError` when an argument is not the scene type it must be (e.g. the
    arguments given in another order)."""
    for name, value, kind in (("scratches", scratches, Scratches), ("views", views, Views),
                              ("board", board, Board)):
        instance_arg(where, name, value, kind)


@functools.lru_cache(maxsize=None)
def _jitted_render_pairs(chunk, mesh, axis_names):
    return eqx.filter_jit(functools.partial(render_pairs, chunk=chunk, mesh=mesh,
                                            axis_names=axis_names))


def render(scratches: Scratches, views: Views, board: Board, *, eps: float = 0.0,
           chunk: int = DEFAULT_CHUNK, mesh: jax.sharding.Mesh | None = None,
           axis_names: str | Sequence[str] | None = None, return_pairs: bool = False):
    """Bin, cull and render: the convenience driver (host code; not for inside jit).

    Bins with `bin_pairs`; when ``eps > 0`` culls every view's pairs with `cull_pairs`
    (`bvh.cull`: pairs whose rigorous ``D_hat`` bound is below ``eps A / (pi alpha^2)``); lays
    the lists out for the mesh's pixel shards; renders with a jitted `render_pairs`. Coverage
    always uses the unculled list.

    **Arguments:** `scratches`, `views`, `board`; `eps` culling tolerance (0 keeps every pair);
    `chunk`, `mesh`, `axis_names` as in `render_pairs`; `return_pairs` also return the pair
    lists used.

    **Returns:** radiance ``(M, H, W)`` (W/(sr m^2)); with `return_pairs`, ``(radiance, pairs,
    coverage_pairs)``.
    """
    _check_scene_types("render", scratches, views, board)
    given, eps = eps, real_number(eps)
    if eps is None or not (math.isfinite(eps) and eps >= 0):
        raise InputError(f"render: `eps` must be a finite number >= 0; got {given!r}")
    check_views(views.camera, views.light, views.intensity, source="render")
    axis_names = tuple(axis_names) if isinstance(axis_names, list) else axis_names
    shards = _n_shards(mesh, _mesh_axes(mesh, axis_names))
    # (`bin_pairs` checks the chunk and the scratches, endpoints on the board, for `render`)
    full_c = bin_pairs(scratches, board, chunk=chunk, shards=shards, source="render")
    if eps == 0:
        pairs, cov_pairs = full_c, None
    else:
        pairs = cull_pairs(full_c, scratches, views, board, eps, chunk=chunk, shards=shards)
        cov_pairs = full_c
    if mesh is not None:  # on one device first: sharded, a bad value would only give NaN
        jax.block_until_ready(_checked_scene(scratches, views))
    fn = _jitted_render_pairs(chunk, mesh, axis_names)
    rad = fn(scratches, views, board, pairs, cov_pairs)
    if return_pairs:
        return rad, pairs, (full_c if cov_pairs is None else cov_pairs)
    return rad


def render_reference(scratches: Scratches, views: Views, board: Board, *,
                     pixel_batch: int = 64) -> Float[Array, "m h w"]:
    """All-pairs reference: every scratch against every pixel, ``D_P`` and ``c`` as dense sums of
    `arc.pair_integral_of` the scratches' profile (no binning, no custom VJP: plain autodiff),
    then `shade`.

    Cost ``M * H*W * N`` pair integrals: small scenes only. Use float64 scratches for a reference.

    **Arguments:** the scene; `pixel_batch` pixels per `lax.map` step.

    **Returns:** radiance ``(M, H, W)`` (W/(sr m^2)).
    """
    _check_scene_types("render_reference", scratches, views, board)
    dtype = scratches.dtype
    if not any(isinstance(a, jax.core.Tracer) for a in (scratches.p0, scratches.p1)):
        check_scratches(scratches.p0, scratches.p1, scratches.width, scratches.depth,
                        scratches.alpha, board=(board.Sx, board.Sy), source="render_reference")
    scratches, views = _check_values(scratches, views)
    views = jax.tree_util.tree_map(lambda x: x.astype(dtype), views)
    fps = pixel_footprints(board, dtype)  # (P, 4, 2)
    hs = jnp.swapaxes(half_vectors(views, board, dtype), 0, 1)  # (P, M, 3)
    s = scratches

    def one_pixel(args):
        fp, h = args
        over_scratches = jax.vmap(arc.pair_integral_of(s.profile), in_axes=(None, None, 0, 0, 0, 0, 0))
        over_views = jax.vmap(over_scratches, in_axes=(0, None, None, None, None, None, None))
        D, A = over_views(h, fp, s.p0, s.p1, s.width, s.depth, s.alpha)  # (M, N)
        return D.sum(-1), A[0].sum(-1)

    P = board.n_pixels
    if s.n == 0:
        D = jnp.zeros((P, views.m), dtype)
        A = jnp.zeros((P,), dtype)
    else:
        # Pad the pixel axis to a multiple of the batch (one compiled kernel, no remainder call).
        batch = max(1, min(int(pixel_batch), P))
        pad = _round_up(P, batch) - P
        fps = jnp.concatenate([fps, jnp.broadcast_to(fps[-1:], (pad, 4, 2))])
        hs = jnp.concatenate([hs, jnp.broadcast_to(hs[-1:], (pad,) + hs.shape[1:])])
        D, A = jax.lax.map(one_pixel, (fps, hs), batch_size=batch)
        D, A = D[:P], A[:P]
    S = board.pixel_area
    rad = shade(D.T / S, A[None] / S, views, board)
    return rad.reshape(views.m, board.H, board.W)
