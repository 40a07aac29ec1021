"""Tests of the prune/re-seed rounds (`jscratch.design.prune`): a round keeps the parameter tree,
the Adam state and the pair list consistent, moves exactly the lowest-scoring scratches, puts them
where a view is too dark and turned so that they light up in that view, and an interrupted run
resumed across a round is bitwise the uninterrupted one.

One tiny configuration (2 views, 32x32 px, 300 scratches), so the step compiles once.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np

from jscratch.design import DesignConfig, design
from jscratch.design import prune, solver
from jscratch.design.run import initial_state, pair_lists, rebin, setup

SIZE = 32


def _config(**kw):
    base = dict(n_scratches=300, iterations=6, cull_eps=0.0, checkpoint_every=2, prune_every=2,
                prune_fraction=0.1, prune_per_pixel=0.0, prune_until=1.0,
                dense_from=0.0, groove="free")  # re-seeded widths: init_width
    base.update(kw)
    return DesignConfig(**base)


def _ckpt(path):
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    return json.loads(bytes(data.pop("meta")).decode()), data


def test_round_moves_lowest_scratches_consistently(two_view_scene, caplog):
    targets, views, board = two_view_scene
    cfg = _config()
    params, opt, ctx = setup(targets, views, board, cfg)
    st, warm = initial_state(params, opt, ctx, targets, cfg)
    warm.join()
    # one real step so that the Adam moments are non-zero
    new, opt_state, *_ = solver.step(st.params, st.opt_state, st.lists, ctx, opt)
    # the scores were compiled beside the step (the run prunes): scoring compiles nothing more
    with jax.log_compiles(True), caplog.at_level("WARNING"):
        sc = prune.scores(new, st.lists, ctx)
    assert not [r for r in caplog.records if "Compiling" in r.getMessage()]
    p2, o2, idx = prune.prune_reseed(new, opt_state, st.lists, ctx, cfg, 2)
    assert len(idx) == 30 and len(np.unique(idx)) == 30
    # exactly the 30 lowest scores moved
    assert sc[idx].max() <= np.sort(sc)[30]
    others = np.setdiff1d(np.arange(300), idx)
    # same tree, shapes and dtypes
    assert jax.tree_util.tree_structure(p2) == jax.tree_util.tree_structure(new)
    assert jax.tree_util.tree_structure(o2) == jax.tree_util.tree_structure(opt_state)
    for a, b in zip(jax.tree_util.tree_leaves((p2, o2)), jax.tree_util.tree_leaves((new, opt_state))):
        assert a.shape == b.shape and a.dtype == b.dtype
    # unmoved scratches and the intensities untouched; moved ones changed
    for name in ("geom", "log_width", "log_depth"):
        np.testing.assert_array_equal(np.asarray(getattr(p2, name))[others],
                                      np.asarray(getattr(new, name))[others])
        assert not np.any(np.all(np.asarray(getattr(p2, "geom"))[idx] ==
                                 np.asarray(getattr(new, "geom"))[idx], axis=-1))
    np.testing.assert_array_equal(p2.log_intensity, new.log_intensity)
    np.testing.assert_allclose(np.exp(np.asarray(p2.log_width)[idx]), cfg.init_width, rtol=1e-6)
    # Adam: moments of the moved scratches are zero, the others and the count are kept
    mu, mu0 = o2.mu, opt_state.mu
    assert np.all(np.asarray(mu.geom)[idx] == 0) and np.all(np.asarray(o2.nu.log_width)[idx] == 0)
    assert np.any(np.asarray(mu0.geom)[idx] != 0)  # they were not zero before
    np.testing.assert_array_equal(np.asarray(mu.geom)[others], np.asarray(mu0.geom)[others])
    np.testing.assert_array_equal(o2.count, opt_state.count)
    # the rebuilt pair list covers the moved scratches and a step runs on it
    lists = rebin(st.lists, p2, ctx)
    pairs = lists.shared
    assert not bool(lists.overflow)
    moved_pairs = np.isin(np.asarray(pairs.scratch)[np.asarray(pairs.valid)], idx)
    assert moved_pairs.sum() > 0
    out = solver.step(p2, o2, lists, ctx, opt)
    assert np.isfinite(float(out[2]["total"]))


def test_reseeded_scratches_go_where_needed_and_light_up(two_view_scene):
    targets, views, board = two_view_scene
    cfg = _config()
    params, opt, ctx = setup(targets, views, board, cfg)
    # all the error in one pixel of view 1
    dens = np.zeros((2, SIZE, SIZE))
    dens[1, 5, 20] = 1.0
    p0, p1 = prune.new_scratches(dens, ctx.hs, board, 50, cfg, np.random.default_rng(0))
    mid = 0.5 * (p0 + p1)
    px = board.Sx / SIZE
    # midpoints in that pixel's footprint (docs/model.md §1), unless clipped at the board edge (not here)
    assert np.all((mid[:, 0] >= 20 * px) & (mid[:, 0] <= 21 * px))
    assert np.all((mid[:, 1] >= board.Sy - 6 * px) & (mid[:, 1] <= board.Sy - 5 * px))
    t = (p1 - p0) / np.linalg.norm(p1 - p0, axis=1, keepdims=True)
    h = np.asarray(ctx.hs)[1, 5 * SIZE + 20, :2]
    cos = np.abs(t @ (h / np.linalg.norm(h)))
    assert np.all(cos < np.sin(5 * prune.RESEED_TURN))  # perpendicular to h within 5 sigma
    # such scratches light view 1; turned by 90 degrees (along h) they would not
    from jscratch.design.params import DesignParams
    from jscratch.scene import Scratches

    def light(q0, q1):
        n = len(q0)
        s = Scratches(jnp.asarray(q0, jnp.float32), jnp.asarray(q1, jnp.float32),
                      jnp.full((n,), 2.5e-4), jnp.full((n,), 1.28e-4), jnp.full((n,), 0.04))
        prm = DesignParams.from_physical(s, np.asarray(views.intensity), board)
        lists = solver.view_lists(prm, pair_lists(prm, ctx, cfg), ctx)
        return np.asarray(solver.contributions(prm, lists, ctx))[1].sum()

    half = 0.5 * (p1 - p0)
    turned = np.stack([-half[:, 1], half[:, 0]], 1)
    assert light(p0, p1) > 10 * light(mid - turned, mid + turned)


def test_resume_across_a_round_is_bitwise(tmp_path, two_view_scene):
    targets, views, board = two_view_scene
    cfg = _config()
    full = tmp_path / "full.npz"
    res = design(targets, views, board, cfg, checkpoint=full)
    assert res.metrics["prune"] == [[2, 30], [4, 30]]
    part = tmp_path / "part.npz"
    design(targets, views, board, cfg, checkpoint=part, stop_after=2)  # stops before the round
    assert _ckpt(part)[0]["iteration"] == 2 and "prune" not in _ckpt(part)[0]["history"]
    design(targets, views, board, cfg, checkpoint=part, resume=True)
    (mf, cf), (mp, cp) = _ckpt(full), _ckpt(part)
    assert mp["history"] == mf["history"]
    assert cp.keys() == cf.keys()
    for k in cf:
        np.testing.assert_array_equal(cp[k], cf[k], err_msg=k)


def test_dense_design_makes_no_round(two_view_scene):
    """At ``dense_from`` scratches per pixel or more a design records no round and equals
    the same design with ``prune_every = 0``; with the limit just above, the round runs."""
    targets, views, board = two_view_scene
    dense = int(np.ceil(0.4 * board.n_pixels))  # 410 at 32 x 32
    cfg = _config(n_scratches=dense, iterations=3, dense_from=0.4)
    res = design(targets, views, board, cfg)
    assert res.metrics["prune"] == []
    off = design(targets, views, board, dataclasses.replace(cfg, prune_every=0))
    np.testing.assert_array_equal(np.asarray(res.params.geom), np.asarray(off.params.geom))
    # just below the limit the same run makes its round (410 scratches at 0.401 per pixel)
    below = design(targets, views, board, dataclasses.replace(cfg, dense_from=0.401))
    assert below.metrics["prune"] == [[2, 41]]


def test_schedule():
    cfg = _config(iterations=100, prune_every=20, prune_until=0.6)
    assert [i for i in range(100) if prune.due(i, cfg)] == [20, 40, 60]
    assert not any(prune.due(i, _config(prune_every=0)) for i in range(10))


def test_moved_count_is_capped_per_pixel():
    """A round moves ``prune_fraction`` of the scratches, at most ``prune_per_pixel`` per pixel:
    the default moves 1,000 of 20,000 at 256 x 256 px (5 %); without the density limit 1,049 of
    60,000 (1.7 %)."""
    cfg = DesignConfig()
    assert prune.moved_count(20_000, 256 * 256, cfg) == 1000
    assert prune.moved_count(5_000, 128 * 128, cfg) == 250
    free = DesignConfig(dense_from=0.0)
    assert prune.moved_count(60_000, 256 * 256, free) == round(0.016 * 256 * 256) == 1049
    assert prune.moved_count(60_000, 256 * 256,
                             DesignConfig(prune_per_pixel=0.0, dense_from=0.0)) == 3000


def test_no_rounds_at_or_above_the_density_limit():
    """``dense_from`` scratches per image pixel or more: no round moves anything, whatever
    the image size; just below it the fraction and the cap apply."""
    cfg = DesignConfig()
    lim = cfg.dense_from
    for side in (64, 256, 300):
        px = side * side
        at = int(np.ceil(lim * px))
        assert prune.moved_count(at, px, cfg) == 0
        assert prune.moved_count(3 * at, px, cfg) == 0
        below = at - 1
        assert prune.moved_count(below, px, cfg) == min(round(0.05 * below), round(0.016 * px)) > 0
    assert prune.moved_count(60_000, 256 * 256, cfg) == 0
    assert prune.moved_count(80_000, 256 * 256, cfg) == 0
