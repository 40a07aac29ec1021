"""Tests of jscratch.features against independent references: the filter bank's stencils against
a 3x3 correlation by scipy, the Gram matrix's derivatives against those of the plain product.
(The filter bank's properties and the VGG-19 loader are tested through ``jscratch.loss`` in
tests/test_loss.py.)"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage

from jscratch import features

pytestmark = pytest.mark.float64

R = math.sqrt(0.5)


def _rand(seed, shape):
    return np.random.default_rng(seed).random(shape)


def _level_kernels() -> np.ndarray:
    """The 9 linear maps ``L, D1_0..3, D2_0..3`` of ``FilterBank`` as 3x3 correlation kernels
    (``K[a, b]``: row offset ``a - 1``, column offset ``b - 1``), from its docstring."""
    s, d, dd = np.array([0.25, 0.5, 0.25]), np.array([-0.5, 0.0, 0.5]), np.array([1.0, -2.0, 1.0])
    gx, gy = np.outer(s, d), -np.outer(d, s)  # y points up: rows grow downwards
    gxx, gyy, gxy = np.outer(s, dd), np.outer(dd, s), -np.outer(d, d)
    ident = np.zeros((3, 3))
    ident[1, 1] = 1.0
    angles = [(1.0, 0.0), (R, R), (0.0, 1.0), (-R, R)]
    return np.stack([ident] + [c * gx + s_ * gy for c, s_ in angles]
                    + [c * c * gxx + 2 * c * s_ * gxy + s_ * s_ * gyy for c, s_ in angles])


def _level_reference(x: np.ndarray) -> np.ndarray:
    """``(M, 17, H, W)`` channels of one level by scipy's correlation (edge-replicate boundary)."""
    y = np.stack([[scipy.ndimage.correlate(v, k, mode="nearest") for k in _level_kernels()]
                  for v in x])
    d1, d2 = y[:, 1:5], y[:, 5:9]
    relu = lambda a: np.maximum(a, 0.0)  # noqa: E731
    rv = np.stack([relu(-d2), relu(d2)], axis=2).reshape(x.shape[0], 8, *x.shape[1:])
    return np.concatenate([y[:, :1], relu(d1), relu(-d1), rv], axis=1)


def test_separable3_matches_scipy_correlate():
    x = _rand(0, (2, 9, 7))
    rows, cols = (0.2, -1.0, 0.7), (0.0, 0.5, -0.3)
    ref = np.stack([scipy.ndimage.correlate(v, np.outer(rows, cols), mode="nearest") for v in x])
    np.testing.assert_allclose(np.asarray(features.separable3(jnp.asarray(x), rows, cols)), ref,
                               rtol=1e-13, atol=1e-15)


def test_filter_bank_levels_match_correlation_reference():
    x = _rand(1, (2, 16, 12))
    fb = features.FilterBank(n_scales=2)
    got = fb(jnp.asarray(x))
    pooled = x.reshape(2, 8, 2, 6, 2).mean(axis=(2, 4))
    for f, level in zip(got, (x, pooled)):
        np.testing.assert_allclose(np.asarray(f), _level_reference(level), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("maps", [features._stencil_maps, features._conv_maps])
def test_both_ways_to_the_linear_maps_match_the_reference(maps):
    """`FilterBank.level` computes large levels by one, small ones by the other."""
    x = _rand(5, (2, 11, 9))
    d1, d2 = maps(jnp.asarray(x))
    y = np.stack([[scipy.ndimage.correlate(v, k, mode="nearest") for k in _level_kernels()[1:]]
                  for v in x])
    np.testing.assert_allclose(np.stack(d1 + d2, axis=1), y, rtol=1e-12, atol=1e-14)


def test_filter_bank_uses_stencils_on_large_levels():
    n = features._STENCIL_PIXELS
    big = jax.make_jaxpr(features.FilterBank(n_scales=1).level)(jnp.zeros((1, 1, n + 1)))
    small = jax.make_jaxpr(features.FilterBank(n_scales=1).level)(jnp.zeros((1, 1, n)))
    has_conv = lambda jaxpr: any("conv" in e.primitive.name for e in jaxpr.eqns)  # noqa: E731
    assert not has_conv(big.jaxpr) and has_conv(small.jaxpr)


def _plain_gram(f):
    c, h, w = f.shape[-3:]
    g = f.reshape(*f.shape[:-3], c, h * w)
    return jnp.einsum("...an,...bn->...ab", g, g) / (c * h * w)


def test_gram_derivatives_match_plain_product():
    f = jnp.asarray(_rand(2, (2, 5, 6, 4)))
    w = jnp.asarray(_rand(3, (2, 5, 5)))  # not symmetric: checks both halves of the cotangent
    np.testing.assert_allclose(np.asarray(features.gram(f)), np.asarray(_plain_gram(f)), rtol=1e-14)
    loss = lambda fn: lambda f: jnp.sum(fn(f) ** 2 * w)  # noqa: E731
    np.testing.assert_allclose(np.asarray(jax.grad(loss(features.gram))(f)),
                               np.asarray(jax.grad(loss(_plain_gram))(f)), rtol=1e-12)
    v = jnp.asarray(_rand(4, f.shape))
    _, t_fast = jax.jvp(features.gram, (f,), (v,))
    _, t_ref = jax.jvp(_plain_gram, (f,), (v,))
    np.testing.assert_allclose(np.asarray(t_fast), np.asarray(t_ref), rtol=1e-12)
    # second order (the rule is itself differentiable)
    h_fast = jax.grad(lambda f: jax.jvp(loss(features.gram), (f,), (v,))[1])(f)
    h_ref = jax.grad(lambda f: jax.jvp(loss(_plain_gram), (f,), (v,))[1])(f)
    np.testing.assert_allclose(np.asarray(h_fast), np.asarray(h_ref), rtol=1e-11)


def test_load_vgg19_names_a_file_that_is_no_npz_archive(tmp_path):
    """Junk, or a single-array .npy, is refused in one line naming the file, not with numpy's
    advice on pickled data."""
    import re

    from jscratch.errors import DesignFileError

    junk, single = tmp_path / "junk.npz", tmp_path / "w.npy"
    junk.write_bytes(b"this is not a zip archive\n" * 10)
    np.save(single, np.zeros(3))
    for path in (junk, single):
        with pytest.raises(DesignFileError, match=rf"^VGG-19 weights file "
                                                  rf"{re.escape(repr(str(path)))} is not a valid "
                                                  r"\.npz file \(not a zip archive") as e:
            features.load_vgg19(path)
        assert "pickle" not in str(e.value)
