"""Per scratch and view, how much light a scratch sends to the camera: `scratch_contributions`
(the score of the design's discard and prune rounds, docs/model.md §6). On the CPU the pairs are
evaluated by the native whole-pair kernel (`jscratch.native.pairs`; a shared list's geometry once
for every view), elsewhere by `arc.pair_integral_of` the scratches' profile.

Imports: `jscratch.arc`, `jscratch.bvh` (the chunk size), `jscratch.lobe`, `jscratch.native`, `jscratch.ndf`, `jscratch.scene`, `jscratch.shading`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jscratch import arc, lobe, native
from jscratch.bvh import DEFAULT_CHUNK, check_chunk, check_pair_list
from jscratch.errors import InputError
from jscratch.scene import Board, Scratches, Views
from jscratch.shading import half_vectors, pixel_footprints, shade

__all__ = ["scratch_contributions"]


def _round_up(x: int, m: int) -> int:
    return -(-x // m) * m


def scratch_contributions(scratches: Scratches, views: Views, board: Board, pairs, *,
                          chunk: int = DEFAULT_CHUNK, h=None) -> Float[Array, "m n"]:
    """Per view and scratch, the scratch term of the view's total radiance,
    ``sum over its pairs of D_hat * shade(1, 1) / S_P`` (W/(sr m^2) summed over pixels): how much
    light each scratch sends to each camera (jittable; plain autodiff).

    **Arguments:** the scene; `pairs` one shared `bvh.Pairs` list or a sequence of ``M`` lists
    (one per view); `chunk` pairs per `lax.map` step; `h` the half vectors ``(M, H*W, 3)``
    (default `half_vectors` of the scene).

    **Returns:** ``(M, N)``.
    """
    s = scratches
    n, m, dt = s.n, views.m, s.dtype
    check_chunk("scratch_contributions", chunk)
    check_pair_list("scratch_contributions", "pairs", pairs)
    if h is not None and jnp.shape(h) != (m, board.n_pixels, 3):
        raise InputError(f"scratch_contributions: `h` must have shape {(m, board.n_pixels, 3)} "
                         f"(views, pixels, 3), got {jnp.shape(h)}")
    hs = half_vectors(views, board, dt) if h is None else h
    fps = pixel_footprints(board, dt)
    ones = jnp.ones((m, board.n_pixels), dt)
    k = shade(ones, ones, views, board) / board.pixel_area  # (M, P), board term is 0
    if n > 0 and native.available(dt):
        return _contributions_native(s, hs, k, fps, pairs, chunk)
    lists = pairs if isinstance(pairs, (list, tuple)) else [pairs] * m
    out = []
    for j, p in enumerate(lists):
        i = jnp.clip(p.scratch, 0, n - 1)
        pix = jnp.clip(p.pixel, 0, board.n_pixels - 1)

        def one(args, j=j):
            ii, px = args
            d, _ = arc.pair_integral_of(s.profile)(hs[j, px], fps[px], s.p0[ii], s.p1[ii],
                                                   s.width[ii], s.depth[ii], s.alpha[ii])
            return d

        d = jax.lax.map(one, (i, pix), batch_size=chunk)
        d = jnp.where(p.valid, d * k[j, pix], 0)
        out.append(jax.ops.segment_sum(d, i, num_segments=n))
    return jnp.stack(out)


def _contributions_native(s: Scratches, hs, k, fps, pairs, chunk: int):
    """`scratch_contributions` by the native whole-pair kernel (`native.pair_values`): a shared
    list is evaluated once for every view (the geometry once per pair), per-view lists each for
    their view; chunks of ``chunk`` pairs in a `lax.scan`, summed per scratch."""
    n, dt, P = s.n, s.dtype, fps.shape[0]
    m = hs.shape[0]
    groups = ([(list(range(m)), pairs)] if not isinstance(pairs, (list, tuple))
              else [([j], p) for j, p in enumerate(pairs)])
    out = jnp.zeros((m, n), dt)
    for views_of, p in groups:
        v = jnp.asarray(views_of)
        pix, scr, val = (jnp.asarray(x).reshape(-1) for x in (p.pixel, p.scratch, p.valid))
        c = int(min(chunk, _round_up(max(pix.shape[0], 1), 64)))
        pad = _round_up(max(pix.shape[0], 1), c) - pix.shape[0]
        pix = jnp.concatenate([pix, jnp.zeros((pad,), pix.dtype)])
        scr = jnp.concatenate([scr, jnp.full((pad,), n, scr.dtype)])
        val = jnp.concatenate([val.astype(bool), jnp.zeros((pad,), bool)])

        def add(acc, xs, v=v):
            px, sc, ok = xs
            px = jnp.clip(px, 0, P - 1)
            i = jnp.clip(sc, 0, n - 1)
            nodes = (arc.nodes if s.profile == "arc" else lobe.nodes)(dt)
            D, _ = native.pairs(nodes, fps[px], s.p0[i], s.p1[i], s.width[i], s.depth[i],
                                s.alpha[i], ok, hs[v][:, px], profile=s.profile)
            return acc.at[:, sc].add(D * k[v][:, px], mode="drop"), None

        acc, _ = jax.lax.scan(add, jnp.zeros((len(views_of), n), dt),
                              (pix.reshape(-1, c), scr.reshape(-1, c), val.reshape(-1, c)))
        out = out.at[v].add(acc)
    return out
