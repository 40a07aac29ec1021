"""Tests of jscratch.bvh, the renderer's pair lists: `bvh.PairLists` through its life (allocate,
update, overflow, grow, rebin), the host layout of `bin_pairs` and `cull_pairs` (every kept pair
exactly once, in its pixel block, in input order) against plain numpy bookkeeping, and the input
errors. The binning itself is tested in test_grid.py, the culling bound in test_cull.py."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import bvh, cull

BOARD = (0.3, 0.3)


def _kept(p):
    """Sorted (pixel, scratch) tuples of a `Pairs`' valid slots."""
    v = np.asarray(p.valid)
    return sorted(zip(np.asarray(p.pixel)[v].tolist(), np.asarray(p.scratch)[v].tolist()))


def test_layout_packs_each_block_in_input_order():
    from jscratch.scene import Board

    board = Board(shape=(6, 5))  # 30 pixels; 4 shards -> blocks of ceil(6/4) * 5 = 10 pixels
    rng = np.random.default_rng(0)
    pix = rng.integers(0, 30, 200).astype(np.int32)
    scr = np.arange(200, dtype=np.int32)
    keeps = [rng.random(200) < 0.5, rng.random(200) < 0.2]
    out_pix, out_scr, out_val = bvh.layout(pix, scr, keeps, 200, board, 4, 64)
    assert bvh.pixels_per_shard(board, 4) == 10
    assert out_pix.shape == out_scr.shape == out_val.shape and out_pix.shape[0] == 2
    ls = out_pix.shape[1] // 4
    counts = [np.bincount(pix[k] // 10, minlength=4) for k in keeps]
    assert ls >= max(c.max() for c in counts) and ls % 64 == 0
    for j, k in enumerate(keeps):
        for b in range(4):
            seg = slice(b * ls, (b + 1) * ls)
            v = out_val[j, seg]
            # the block's kept pairs, in input order, then padding (first pixel, sentinel N)
            want = np.flatnonzero(k & (pix // 10 == b))
            np.testing.assert_array_equal(out_scr[j, seg][v], scr[want])
            np.testing.assert_array_equal(out_pix[j, seg][v], pix[want])
            assert np.all(out_scr[j, seg][~v] == 200) and np.all(out_pix[j, seg][~v] == 10 * b)
            assert v[:len(want)].all() and not v[len(want):].any()


def test_bin_pairs_and_cull_pairs_hold_the_grid_and_cull_lists():
    import math

    from jscratch.scene import Board, Scratches, views_on_circle
    from jscratch.shading import half_vectors

    board = Board(shape=(16, 16))
    s = Scratches.random(jax.random.PRNGKey(1), 80, board, dtype=jnp.float32)
    views = views_on_circle(2, math.radians(50), board=board)
    full, _ = bvh.build_pairs(s.p0, s.p1, s.width, s.depth, board=BOARD, shape=(16, 16))
    for shards in (1, 4):
        pairs = bvh.bin_pairs(s, board, shards=shards, chunk=1024)
        assert _kept(pairs) == _kept(full) and pairs.pixel.shape[0] % 1024 == 0
        per_view = bvh.cull_pairs(pairs, s, views, board, 1e-2, shards=shards, chunk=1024)
        assert per_view.pixel.shape[0] == 2
        hs = half_vectors(views, board, jnp.float32)
        for j in range(2):
            ref = cull.cull(pairs, s.p0, s.p1, s.width, s.depth, s.alpha, hs[j], 1e-2)
            got = bvh.Pairs(per_view.pixel[j], per_view.scratch[j], per_view.valid[j], per_view.overflow)
            assert _kept(got) == _kept(ref)
    with pytest.raises(ValueError, match="eps"):
        bvh.cull_pairs(pairs, s, views, board, 0.0)


def test_pair_lists_allocate_update_overflow_grow_rebin():
    """`bvh.PairLists` through its life: allocated lists hold exactly the pairs `cull` keeps
    (checked against `cull` on the shared list, an independent path: no compaction), too-small
    capacities report overflow (not silently dropped pairs), `grow_lists` fixes that, and
    `rebin_lists` gives the shared list `build_pairs` gives for moved scratches."""
    from jscratch.scene import Board, Scratches, views_on_circle
    from jscratch.shading import board_ndf, half_vectors

    board = Board(shape=(24, 24))
    views = views_on_circle(3, np.radians(50), board=board)
    s = Scratches.random(jax.random.PRNGKey(3), 150, board, width=2.5e-4, depth=1.28e-4,
                         dtype=jnp.float32)
    hs = half_vectors(views, board, jnp.float32)
    ndf_max = jnp.max(board_ndf(views, board, jnp.float32), axis=0)
    lists = bvh.allocate_lists(s, board, hs, ndf_max, cull_eps=1e-3, coverage_eps=1e-3)
    assert len(lists.caps) == 4 and not bool(lists.overflow)
    with pytest.raises(ValueError, match="not culled yet"):
        lists.for_render()
    upd = jax.jit(bvh.update_lists)(lists, s, hs, ndf_max)
    assert not bool(upd.overflow)

    def kept(p):
        v = np.asarray(p.valid)
        return sorted(zip(np.asarray(p.pixel)[v].tolist(), np.asarray(p.scratch)[v].tolist()))

    per_view, cov = upd.for_render()
    for j in range(3):
        ref = cull.cull(lists.shared, s.p0, s.p1, s.width, s.depth, s.alpha, hs[j], 1e-3)
        assert kept(per_view[j]) == kept(ref) and len(kept(ref)) == int(upd.counts[j])
        assert per_view[j].pixel.shape == (lists.caps[j],)
    assert kept(cov) == kept(cull.cull_coverage(lists.shared, s.alpha, ndf_max, 1e-3))
    assert 0 < len(kept(per_view[0])) < len(kept(lists.shared))
    # capacities too small: overflow reported; grow_lists restores complete lists
    small = bvh.PairLists(lists.shared, lists.spec, lists.counts, caps=(8, 8, 8, 8),
                          cull_eps=1e-3, coverage_eps=1e-3)
    over = bvh.update_lists(small, s, hs, ndf_max)
    assert bool(over.overflow)
    grown = bvh.update_lists(bvh.grow_lists(small, over.counts), s, hs, ndf_max)
    assert not bool(grown.overflow)
    assert [kept(p) for p in grown.for_render()[0]] == [kept(p) for p in per_view]
    # unculled: every view renders the shared list, coverage from the same list
    plain = bvh.allocate_lists(s, board, hs)
    assert plain.for_render()[0] is plain.shared and plain.for_render()[1] is None
    # moved scratches: the rebinned shared list is build_pairs' list
    moved = Scratches(s.p0 + 0.01, s.p1 + 0.01, s.width, s.depth, s.alpha)
    assert bool(bvh.needs_rebin(lists.shared, moved.p0, moved.p1, moved.width, moved.depth))
    reb = bvh.rebin_lists(lists, moved, board)
    ref, _ = bvh.build_pairs(moved.p0, moved.p1, moved.width, moved.depth, board=BOARD,
                             shape=(24, 24))
    assert kept(reb.shared) == kept(ref) and reb.caps == lists.caps
    with pytest.raises(ValueError, match="cull_eps"):
        bvh.allocate_lists(s, board, hs, cull_eps=float("nan"))


def test_pair_list_arguments_that_are_not_are_refused_in_one_line():
    """`bin_pairs`, `cull_pairs`, `render.render` and `render_pairs`: a scene argument, a shard
    count, a tolerance or a pair list of the wrong kind is refused by its name (`InputError`),
    not with a ZeroDivisionError or AttributeError from inside."""
    from jscratch.errors import InputError
    from jscratch.render import render, render_pairs
    from jscratch.scene import Board, Scratches, views_on_circle

    b = Board(shape=(16, 16))
    v = views_on_circle(2, board=b)
    s = Scratches.random(jax.random.PRNGKey(0), 30, board=b)
    p = bvh.bin_pairs(s, b)
    cases = [
        (lambda: bvh.bin_pairs(s, b, shards=0), r"^bin_pairs: `shards` .* int >= 1; got 0"),
        (lambda: bvh.bin_pairs(s, b, shards=1.5), r"^bin_pairs: `shards`"),
        (lambda: bvh.bin_pairs([s], b), r"^bin_pairs: `scratches` must be a jscratch.Scratches"),
        (lambda: bvh.bin_pairs(s, (0.3, 0.3)), r"^bin_pairs: `board` must be a jscratch.Board"),
        (lambda: bvh.cull_pairs(None, s, v, b, 1e-3), r"^cull_pairs: `pairs` must be a bvh"),
        (lambda: bvh.cull_pairs(p, s, v, b, "a"),
         r"^cull_pairs: `eps` must be a finite number > 0"),
        (lambda: bvh.cull_pairs(p, s, v, b, 1e-3, shards=0), r"^cull_pairs: `shards`"),
        (lambda: render_pairs(s, v, b, None), r"^render_pairs: `pairs` must be a bvh.Pairs"),
        (lambda: render_pairs(s, v, b, p, coverage_pairs=1), r"^render_pairs: `coverage_pairs`"),
        (lambda: render(s, v, b, eps="a"), r"^render: `eps` must be a finite number >= 0; got 'a'"),
        (lambda: render(s, v, b, eps=None),
         r"^render: `eps` must be a finite number >= 0; got None"),
    ]
    for call, match in cases:
        with pytest.raises(InputError, match=match):
            call()
    # numbers given as numpy or JAX scalars and 0-d arrays are numbers
    for eps in (np.float32(1e-3), jnp.float32(1e-3), np.array(1e-3)):
        assert bvh.cull_pairs(p, s, v, b, eps).pixel.shape[0] == 2
        assert render(s, v, b, eps=eps).shape == (2, 16, 16)


def test_render_pairs_takes_bin_pairs_lists_stacked_per_view_and_binned_in_float64():
    """`render_pairs`' check of what a list was binned for (`bvh.check_binned_for`) passes the
    lists it was given before: `bin_pairs` lists stacked per view ``(M, L)``, and a list binned
    from the float64 endpoints of float32 scratches (float32 rounding is not a move)."""
    from jscratch.render import render_pairs
    from jscratch.scene import Board, Scratches, views_on_circle

    b = Board(shape=(16, 16))
    v = views_on_circle(2, board=b)
    s = Scratches.random(jax.random.PRNGKey(3), 40, board=b)
    p = bvh.bin_pairs(s, b)
    ref = np.asarray(render_pairs(s, v, b, p))
    stacked = jax.tree.map(lambda x: jnp.stack([x, x]), p)
    np.testing.assert_allclose(render_pairs(s, v, b, stacked, coverage_pairs=p), ref, rtol=1e-6)
    with jax.enable_x64(True):
        s64 = jax.tree.map(lambda x: jnp.asarray(np.asarray(x, np.float64)), s)
        p64 = bvh.bin_pairs(s64, b)
    assert p64.bin_p0.dtype == np.float64
    np.testing.assert_allclose(render_pairs(s, v, b, p64), ref, rtol=1e-6)
