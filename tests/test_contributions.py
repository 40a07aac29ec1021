"""Tests of jscratch.contributions: `scratch_contributions` by the native whole-pair kernel
against the jnp path, and both against the plain per-pair sum of `ndf.pair_integral`."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import bvh, contributions, native, ndf, render
from jscratch.scene import Board, Scratches, views_on_circle

BOARD = Board(shape=(24, 24))
CHUNK = 256


def _scene(dtype):
    s = Scratches.random(jax.random.PRNGKey(4), 150, BOARD, length=(0.01, 0.05), width=2e-3,
                         depth=1e-3, alpha=0.1, dtype=dtype)
    v = views_on_circle(3, math.radians(45), board=BOARD)
    return s, v


def _pairs(s):
    return render.bin_pairs(s, BOARD, chunk=CHUNK)


@pytest.mark.skipif(not native.available(jnp.float32),
                    reason=f"native kernel unavailable: {native.status()['why']}")
@pytest.mark.float64
def test_native_scratch_contributions_equal_jnp_path():
    """`scratch_contributions` by the native whole-pair kernel and by the jnp path
    (``JSCRATCH_NATIVE=0``), float64, a shared list and per-view lists; and each view's total
    equals the plain sum over the pairs of `ndf.pair_integral` times the shading factor."""
    s, v = _scene(jnp.float64)
    pairs = _pairs(s)
    for lists in (pairs, [pairs] * 3):
        out = {}
        for on in (True, False):
            with native.override(enabled=on):
                out[on] = np.asarray(jax.jit(lambda s, v, p: contributions.scratch_contributions(
                    s, v, BOARD, p, chunk=CHUNK))(s, v, lists))
        assert np.max(np.abs(out[False])) > 0
        np.testing.assert_allclose(out[True], out[False], rtol=0,
                                   atol=1e-12 * np.max(np.abs(out[False])))
    total = out[True].sum(1)
    ones = jnp.ones((3, BOARD.n_pixels), jnp.float64)
    k = render.shade(ones, ones, v, BOARD) / BOARD.pixel_area
    from jscratch.shading import half_vectors
    hs = half_vectors(v, BOARD, jnp.float64)
    fps = render.pixel_footprints(BOARD, jnp.float64)
    p = jax.tree_util.tree_map(np.asarray, pairs)
    i, px = p.scratch[p.valid], p.pixel[p.valid]
    D = jax.vmap(lambda j: jax.vmap(ndf.pair_integral)(
        hs[j, px], fps[px], s.p0[i], s.p1[i], s.width[i], s.depth[i], s.alpha[i])[0])(
        jnp.arange(3))
    np.testing.assert_allclose(total, np.sum(np.asarray(D) * np.asarray(k)[:, px], 1),
                               rtol=1e-10)


def test_bad_arguments_are_refused_by_their_names():
    from jscratch.errors import InputError

    b = Board(shape=(16, 16))
    v = views_on_circle(2, board=b)
    s = Scratches.random(jax.random.PRNGKey(0), 30, board=b)
    p = bvh.bin_pairs(s, b)
    with pytest.raises(InputError, match=r"^scratch_contributions: `chunk` .* int >= 1; got 0"):
        contributions.scratch_contributions(s, v, b, p, chunk=0)
    with pytest.raises(InputError, match=r"^scratch_contributions: `h` must have shape "
                                         r"\(2, 256, 3\) \(views, pixels, 3\), got \(2, 3\)"):
        contributions.scratch_contributions(s, v, b, p, h=jnp.zeros((2, 3)))
    with pytest.raises(InputError, match=r"^scratch_contributions: `pairs` must be a bvh.Pairs"):
        contributions.scratch_contributions(s, v, b, None)
    assert contributions.scratch_contributions(s, v, b, p).shape == (2, 30)
