"""Tests of jscratch.design.checkpoint: a `State` saved and loaded back bitwise (parameters, Adam
state, the shared pair list, its spec and capacities, history), and a checkpoint refused when it
is missing, made for other targets, another scene, another config (any option but the resumable
ones) or another design's shapes, or when it is past the iterations asked for."""

import dataclasses
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import bvh
from jscratch.design.checkpoint import State, load_checkpoint, save_checkpoint
from jscratch.design.io import inputs_hash
from jscratch.design.config import DesignConfig
from jscratch.design.params import DesignParams
from jscratch.design.solver import make_adam
from jscratch.designfile import DesignError
from jscratch.errors import DesignFileError
from jscratch.scene import Board, Scratches, views_on_circle
from jscratch.shading import half_vectors


def _state(n):
    board = Board(shape=(16, 16))
    s = Scratches.random(jax.random.PRNGKey(n), n, board, width=2.5e-4, depth=1.28e-4,
                         dtype=jnp.float32)
    views = views_on_circle(2, math.radians(50), board=board)
    params = DesignParams.from_physical(s, np.array([1.0, 2.0]), board)
    adam = make_adam(0.9, 0.999, 1e-12)
    opt = adam.init(params)
    # one Adam update, so that the moments are not all zero
    grads = jax.tree_util.tree_map(lambda a: jnp.full_like(a, 0.5), params)
    _, opt = adam.update(grads, opt, params)
    lists = bvh.allocate_lists(s, board, half_vectors(views, board, jnp.float32))
    return State(7, params, opt, lists, {"total": [1.0, 0.5], "terms": {"E_p": [1.0, 0.5]}}, 2)


IN = {"targets_hash": "abc", "scene_hash": "def"}


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def test_round_trip_is_bitwise(tmp_path):
    state = _state(30)
    cfg = DesignConfig(n_scratches=30)
    path = str(tmp_path / "sub" / "ckpt.npz")
    save_checkpoint(path, state, cfg, IN)
    like = dataclasses.replace(state, params=jax.tree_util.tree_map(jnp.zeros_like, state.params),
                               opt_state=jax.tree_util.tree_map(jnp.zeros_like, state.opt_state),
                               lists=None, history={}, iteration=0, rebins=0)
    back = load_checkpoint(path, like, cfg, IN)
    assert (back.iteration, back.rebins, back.history) == (7, 2, state.history)
    for a, b in zip(_leaves(back.params) + _leaves(back.opt_state),
                    _leaves(state.params) + _leaves(state.opt_state)):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    for f in ("pixel", "scratch", "valid"):
        assert np.array_equal(np.asarray(getattr(back.lists.shared, f)),
                              np.asarray(getattr(state.lists.shared, f)))
    assert back.lists.spec == state.lists.spec and back.lists.caps == state.lists.caps
    # every array of the lists has the shape and dtype it had (a resumed design's step then
    # reuses the uninterrupted one's compilation)
    like_lists = lambda t: [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(t)]  # noqa: E731
    assert like_lists(back.lists) == like_lists(state.lists)
    assert not list(tmp_path.joinpath("sub").glob(".ckpt-*"))  # no temporary file left


def test_refusals(tmp_path):
    state = _state(30)
    cfg = DesignConfig(n_scratches=30)
    path = str(tmp_path / "ckpt.npz")
    with pytest.raises(DesignFileError, match="no checkpoint at"):
        load_checkpoint(path, state, cfg, IN)
    save_checkpoint(path, state, cfg, IN)
    with pytest.raises(DesignError, match="different target images"):
        load_checkpoint(path, state, cfg, dict(IN, targets_hash="xyz"))
    with pytest.raises(DesignError, match=r"another scene \(board, cameras"):
        load_checkpoint(path, state, cfg, dict(IN, scene_hash="xyz"))
    with pytest.raises(DesignError, match="made with seed = 0, not 3"):
        load_checkpoint(path, state, dataclasses.replace(cfg, seed=3), IN)
    # Every option but the resumable ones, nested ones too.
    for change, words in ((dict(groove="free"), "groove = 'carvable', not 'free'"),
                          (dict(lr_endpoints=5e-3), "lr_endpoints = 0.001, not 0.005"),
                          (dict(loss=dataclasses.replace(cfg.loss, kind="l2")),
                           "loss.kind = 'perceptual+gram', not 'l2'")):
        with pytest.raises(DesignError, match=re.escape(words)):
            load_checkpoint(path, state, dataclasses.replace(cfg, **change), IN)
    for change in (dict(iterations=50), dict(checkpoint_every=3), dict(discard=False),
                   dict(discard_tol=0.05), dict(target_ssim=0.8)):
        assert load_checkpoint(path, state, dataclasses.replace(cfg, **change), IN).iteration == 7
    with pytest.raises(DesignError, match="at iteration 7, past the 5 iterations asked for"):
        load_checkpoint(path, state, dataclasses.replace(cfg, iterations=5), IN)
    other = _state(20)
    with pytest.raises(DesignError, match="does not match this design"):
        load_checkpoint(path, other, cfg, IN)


def test_damaged_values_are_refused_when_read(tmp_path):
    """A checkpoint whose parameters or Adam moments hold NaN or infinity is refused on reading,
    naming the leaf: the design step checks what it updates, not the state it resumes from."""
    state = _state(30)
    cfg = DesignConfig(n_scratches=30)
    path = tmp_path / "ckpt.npz"
    save_checkpoint(str(path), state, cfg, IN)
    assert load_checkpoint(str(path), state, cfg, IN).iteration == 7
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    for key, bad in (("params/0", np.nan), ("opt/1", np.inf)):
        damaged = dict(data)
        a = damaged[key].copy()
        a.reshape(-1)[3] = bad
        damaged[key] = a
        np.savez(tmp_path / "damaged.npz", **damaged)
        with pytest.raises(DesignFileError, match=rf"non-finite values \({key.split('/')[0]} "
                                                  rf"leaf {key.split('/')[1]}\)"):
            load_checkpoint(str(tmp_path / "damaged.npz"), state, cfg, IN)


def test_inputs_hash_keys_targets_and_scene():
    board = Board(shape=(16, 16))
    views = views_on_circle(2, math.radians(50), board=board)
    t = np.linspace(0, 1, 2 * 16 * 16).reshape(2, 16, 16)
    h = inputs_hash(t, views, board)
    assert h == inputs_hash(t.copy(), views_on_circle(2, math.radians(50), board=board), board)
    assert inputs_hash(t[::-1], views, board)["targets_hash"] != h["targets_hash"]
    for v, b in ((views_on_circle(2, math.radians(40), board=board), board),
                 (views, Board(shape=(16, 16), Sx=0.2, Sy=0.2)),
                 (views, Board(shape=(16, 16), F0=0.5))):
        other = inputs_hash(t, v, b)
        assert other["scene_hash"] != h["scene_hash"] and other["targets_hash"] == h["targets_hash"]
