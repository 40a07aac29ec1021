"""Tests of jscratch.design.params in float32 (what a design runs): both parameterisations give
back the physical scratches (the midpoint one by hand: midpoint, angle, length), the groups and
`group_tree`, the carvable groove's plunge coordinate, and an unknown parameterisation refused."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch.design.carvable import groove_map
from jscratch.design.params import DesignParams, group_tree
from jscratch.designfile import DesignError
from jscratch.scene import Board, Scratches


def _scene():
    board = Board(shape=(16, 16), Sx=0.3, Sy=0.2)
    s = Scratches.random(jax.random.PRNGKey(0), 40, board, width=2.5e-4, depth=1.28e-4,
                         alpha=0.05, dtype=jnp.float32)
    return board, s


@pytest.mark.parametrize("kind", ["endpoints", "midpoint"])
def test_float32_round_trip(kind):
    board, s = _scene()
    p = DesignParams.from_physical(s, np.array([1.5, 0.5]), board, kind)
    assert p.geom.dtype == jnp.float32 and p.geom.shape == (40, 4) and p.board_size == (0.3, 0.2)
    back = p.scratches()
    np.testing.assert_allclose(np.asarray(back.p0), np.asarray(s.p0), atol=3e-6)
    np.testing.assert_allclose(np.asarray(back.p1), np.asarray(s.p1), atol=3e-6)
    np.testing.assert_allclose(np.asarray(back.width), 2.5e-4, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(back.depth), 1.28e-4, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(back.alpha), 0.05, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(p.intensity()), [1.5, 0.5], rtol=1e-6)
    assert p.plunge() is None


def test_midpoint_geometry_by_hand():
    board, s = _scene()
    p = DesignParams.from_physical(s, 1.0, board, "midpoint")
    g = np.asarray(p.geom, np.float64)
    d = np.asarray(s.p1, np.float64) - np.asarray(s.p0, np.float64)
    np.testing.assert_allclose(g[:, 2], np.arctan2(d[:, 1], d[:, 0]), atol=1e-5)
    np.testing.assert_allclose(np.exp(g[:, 3]), np.hypot(d[:, 0], d[:, 1]), rtol=1e-5)
    mid = 1 / (1 + np.exp(-4 * g[:, :2])) * [0.3, 0.2]
    np.testing.assert_allclose(mid, (np.asarray(s.p0) + np.asarray(s.p1)) / 2, atol=3e-6)
    # a length and angle moved by hand: the endpoints follow about the midpoint
    q = DesignParams(p.geom.at[0, 2].set(0.0).at[0, 3].set(math.log(0.01)), p.log_width,
                     p.log_depth, p.logit_alpha, p.log_intensity, "midpoint", p.board_size)
    e0, e1 = (np.asarray(e[0], np.float64) for e in q.endpoints())
    np.testing.assert_allclose(e1 - e0, [0.01, 0.0], atol=1e-6)
    np.testing.assert_allclose((e0 + e1) / 2, mid[0], atol=1e-6)


def test_groups_and_group_tree():
    board, s = _scene()
    p = DesignParams.from_physical(s, np.ones(3), board)
    for name, leaf in (("endpoints", p.geom), ("width", p.log_width), ("depth", p.log_depth),
                       ("alpha", p.logit_alpha), ("intensity", p.log_intensity)):
        assert p.group(name) is leaf
    t = group_tree(p, {"endpoints": 1, "width": 2, "depth": 3, "alpha": 4, "intensity": 5})
    assert (t.geom, t.log_width, t.log_depth, t.logit_alpha, t.log_intensity) == (1, 2, 3, 4, 5)
    assert jax.tree_util.tree_structure(t) == jax.tree_util.tree_structure(
        group_tree(p, {k: 0 for k in ("endpoints", "width", "depth", "alpha", "intensity")}))
    with pytest.raises(DesignError, match="parameterisation must be one of"):
        DesignParams.from_physical(s, 1.0, board, "polar")


def test_carvable_plunge_coordinate():
    board, s = _scene()
    R = 2e-4
    g = groove_map(R, 1e-5, 8e-5)
    p = DesignParams.from_physical(s, 1.0, board, groove=g)
    pl = np.asarray(p.plunge(), np.float64)
    assert pl.shape == (40,) and np.all((pl >= 1e-5 * (1 - 1e-6)) & (pl <= 8e-5 * (1 + 1e-6)))
    back = p.scratches()
    # the cut's half width sqrt(2 R p - p^2) is the groove's x_max
    xm = 0.5 * np.asarray(back.width, np.float64) * np.sqrt(
        -np.expm1(-2 * np.asarray(back.depth, np.float64) / np.asarray(back.width, np.float64)))
    np.testing.assert_allclose(xm, np.sqrt(2 * R * pl - pl**2), rtol=2e-3)


def test_an_optimised_alpha_stays_in_the_scenes_range():
    """`DesignParams.alpha` is ``sigmoid(logit_alpha)`` held in `scene.ALPHA_RANGE`: a logit
    pushed past either end gives the end (a scratch the scene's rules accept), not a value the
    health check would stop the run for; inside the range it is the plain sigmoid, bit for bit."""
    from jscratch.scene import ALPHA_RANGE

    board = Board(shape=(8, 8))
    s = Scratches(np.float32([[0.01, 0.02]] * 3), np.float32([[0.05, 0.02]] * 3), 2.5e-4, 1e-4,
                  np.float32([0.04, 0.5, 0.9]))
    p = DesignParams.from_physical(s, np.ones(1), board)
    np.testing.assert_array_equal(np.asarray(p.alpha()), np.asarray(jax.nn.sigmoid(p.logit_alpha)))
    far = eqx.tree_at(lambda q: q.logit_alpha, p, jnp.float32([-30.0, 30.0, 2.0]))
    a = np.asarray(far.scratches().alpha, np.float64)
    assert a[0] == pytest.approx(ALPHA_RANGE[0], rel=1e-6) and a[1] == pytest.approx(ALPHA_RANGE[1])
    assert ALPHA_RANGE[0] < a[2] < ALPHA_RANGE[1]
