"""Tests of jscratch.loss: hand-computed values, finite-difference gradients, filter-bank
properties, the VGG-19 loader against a scipy reference, and the converter script."""

import dataclasses
import importlib.util
import math
import pathlib
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage
import scipy.signal
from skimage.metrics import structural_similarity

from jscratch import loss as loss_mod
from jscratch.errors import DesignFileError, InputError
from jscratch.ssim import ssim_mean

SHAPE = (2, 32, 32)  # one image shape for (almost) everything: few compilations
R = math.sqrt(0.5)
E = math.exp(-0.5)
K1 = np.array([E, 1.0, E]) / (1.0 + 2.0 * E)  # 1D weights of g, sigma = 1 px


def _rand(seed, shape=SHAPE, dtype=np.float64):
    return np.random.default_rng(seed).random(shape).astype(dtype)


def _smooth(seed, shape=SHAPE):
    """Smooth random images in [0, 1] (natural-image-like, no exact ReLU ties)."""
    x = scipy.ndimage.gaussian_filter(_rand(seed, shape), (0, 2, 2))
    return (x - x.min()) / (x.max() - x.min())


# ----------------------------------------------------------------------------------------------
# E_p, blur, L2


@pytest.mark.float64
def test_gaussian_kernel3_values():
    g = np.asarray(loss_mod.gaussian_kernel3(), dtype=np.float64)
    np.testing.assert_allclose(g, np.outer(K1, K1), rtol=1e-15)
    assert g.sum() == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(K1, [0.27406862, 0.45186276, 0.27406862], atol=1e-8)
    with pytest.raises(ValueError, match="sigma"):
        loss_mod.gaussian_kernel3(0.0)
    for bad in (True, "1", np.array([1.0, 2.0]), np.nan):
        with pytest.raises(InputError, match="^sigma must be a finite positive number"):
            loss_mod.gaussian_kernel3(bad)
    for one in (np.float32(1.0), jnp.float32(1.0), np.array(1.0), 1):  # any real number
        np.testing.assert_array_equal(np.asarray(loss_mod.gaussian_kernel3(one)), g)


@pytest.mark.float64
def test_blur3_matches_scipy_nearest():
    x = _rand(0)
    ref = np.stack([scipy.ndimage.convolve(v, np.outer(K1, K1), mode="nearest") for v in x])
    np.testing.assert_allclose(np.asarray(loss_mod.blur3(jnp.asarray(x))), ref, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("dtype", [np.float32, pytest.param(np.float64, marks=pytest.mark.float64)])
def test_perceptual_constant_offset(dtype):
    # Edge-replicate boundary: a constant stays constant, so E_p = M c^2 exactly.
    t = _rand(1, dtype=dtype)
    c = dtype(0.3)
    ep = loss_mod.perceptual_loss(jnp.asarray(t + c), jnp.asarray(t))
    assert ep.dtype == dtype
    # float32: XLA's CPU reduction over 1024 pixels is sequential (error up to ~n eps/2).
    tol = 1e-4 if dtype == np.float32 else 1e-12
    assert float(ep) == pytest.approx(SHAPE[0] * 0.09, rel=tol)


@pytest.mark.float64
def test_perceptual_delta_interior_and_corner():
    h = w = 8
    a = 0.7
    t = np.zeros((2, h, w))
    i = t.copy()
    i[0, 4, 3] = a  # interior delta: every tap of g lands inside
    i[1, 0, 0] = a  # corner delta: edge replication folds the outside taps back
    ep = float(loss_mod.perceptual_loss(jnp.asarray(i), jnp.asarray(t)))
    interior = a**2 * np.sum(K1**2) ** 2 / (h * w)
    corner = a**2 * ((K1[0] + K1[1]) ** 2 + K1[0] ** 2) ** 2 / (h * w)
    assert ep == pytest.approx(interior + corner, rel=1e-13)


def test_l2_hand():
    t = np.zeros((2, 4, 4))
    i = t.copy()
    i[0] = 0.5
    i[1, 1, 2] = 2.0
    assert float(loss_mod.l2_loss(jnp.asarray(i), jnp.asarray(t))) == pytest.approx(0.25 + 4.0 / 16)


# ----------------------------------------------------------------------------------------------
# Gram and the filter bank


def test_gram_hand():
    f = np.array([[[1.0, 2.0], [3.0, 4.0]], [[0.0, 1.0], [0.0, 1.0]]])  # (C=2, 2, 2)
    expected = np.array([[30.0, 6.0], [6.0, 2.0]]) / (2 * 4)
    np.testing.assert_allclose(np.asarray(loss_mod.gram(jnp.asarray(f))), expected, rtol=1e-15)
    # batched over leading axes
    g2 = loss_mod.gram(jnp.stack([jnp.asarray(f), 2 * jnp.asarray(f)]))
    np.testing.assert_allclose(np.asarray(g2[1]), 4 * expected, rtol=1e-15)


@pytest.mark.float64
def test_filter_bank_constant_images():
    fb = loss_mod.FilterBank()
    x = np.full(SHAPE, 0.6)
    x[1] = 0.2
    feats = fb(jnp.asarray(x))
    assert [f.shape for f in feats] == [(2, 17, 32 >> s, 32 >> s) for s in range(4)]
    for f in feats:
        f = np.asarray(f)
        assert np.all(np.abs(f[:, 1:]) <= 1e-16)  # every oriented channel is zero (to rounding)
        np.testing.assert_allclose(f[:, 0], x[:, :1, :1] * np.ones_like(f[:, 0]), rtol=1e-15)
    # Gram of a constant c: only G[0, 0] = c^2 / 17; E_g(c1 vs c2) = (c1^2 - c2^2)^2 / 17^2.
    eg = float(loss_mod.gram_loss(jnp.asarray(x), jnp.asarray(x[::-1].copy()), fb))
    assert eg == pytest.approx(2 * (0.36 - 0.04) ** 2 / 289, rel=1e-12)


@pytest.mark.float64
def test_filter_bank_step_edges():
    fb = loss_mod.FilterBank()
    x = np.zeros(SHAPE)
    x[0, :, 16:] = 1.0  # view 0: dark left, bright right (intensity grows along +x)
    x[1, :16, :] = 1.0  # view 1: bright top (intensity grows along +y = up)
    f = np.asarray(fb(jnp.asarray(x))[0])
    ex = np.zeros((17, 32, 32))
    ex[0] = x[0]
    edge = np.s_[:, 15:17]
    ex[1][edge] = 0.5  # D1 at 0 deg: central difference 1/2 on both sides of the step
    ex[2][edge] = ex[8][edge] = 0.5 * R  # 45 and 315 deg
    # D2 across the step: +1 (dark side, column 15), -1 (bright side, column 16); 45/135 deg: 1/2.
    for k, scale in ((0, 1.0), (1, 0.5), (3, 0.5)):
        ex[10 + 2 * k][:, 15] = scale  # relu(D2): valley on the dark side
        ex[9 + 2 * k][:, 16] = scale  # relu(-D2): ridge on the bright side
    np.testing.assert_allclose(f[0], ex, atol=1e-15)
    # The horizontal step: rotated copy (the up direction is channel D1 at 90 deg).
    ey = np.zeros((17, 32, 32))
    ey[0] = x[1]
    ey[3][15:17] = 0.5
    ey[2][15:17] = ey[4][15:17] = 0.5 * R
    np.testing.assert_allclose(f[1, :9], ey[:9], atol=1e-15)


def _rot_perm():
    return (
        [0]
        + [1 + (k - 2) % 8 for k in range(8)]
        + [9 + 2 * ((k - 2) % 4) + s for k in range(4) for s in range(2)]
    )


@pytest.mark.float64
def test_filter_bank_rotation_permutes_channels():
    fb = loss_mod.FilterBank()
    x = _rand(2)
    xr = np.rot90(x, axes=(-2, -1)).copy()  # +90 degrees (counter-clockwise)
    fa, fr = fb(jnp.asarray(x)), fb(jnp.asarray(xr))
    perm = _rot_perm()
    for a, b in zip(fa, fr):
        np.testing.assert_allclose(
            np.asarray(b), np.rot90(np.asarray(a)[:, perm], axes=(-2, -1)), atol=1e-13
        )
        ga, gb = np.asarray(loss_mod.gram(a)), np.asarray(loss_mod.gram(b))
        np.testing.assert_allclose(gb, ga[:, perm][:, :, perm], atol=1e-13)
    t = _smooth(3)
    tr = np.rot90(t, axes=(-2, -1)).copy()
    eg = float(loss_mod.gram_loss(jnp.asarray(x), jnp.asarray(t), fb))
    egr = float(loss_mod.gram_loss(jnp.asarray(xr), jnp.asarray(tr), fb))
    assert egr == pytest.approx(eg, rel=1e-12)
    assert eg > 0


def test_filter_bank_odd_size_and_too_small():
    fb = loss_mod.FilterBank(n_scales=2)
    f = fb(jnp.zeros((1, 9, 7)))
    assert [v.shape for v in f] == [(1, 17, 9, 7), (1, 17, 4, 3)]
    with pytest.raises(ValueError, match="too small"):
        loss_mod.FilterBank()(jnp.zeros((1, 15, 32)))
    with pytest.raises(ValueError, match="n_scales"):
        loss_mod.FilterBank(n_scales=0)


# ----------------------------------------------------------------------------------------------
# Gradients against float64 central differences


def _weighted(r, t, w):
    """``w[0] E_p + w[1] E_g``: one compilation checks both terms (weights are traced)."""
    return w[0] * loss_mod.perceptual_loss(r, t) + w[1] * loss_mod.gram_loss(r, t)


_VG = jax.jit(jax.value_and_grad(_weighted))


def _fd_check(vg, x, *args, seeds=(0, 1), eps=1e-6, rtol=1e-6):
    """Directional derivative of ``vg`` (a jitted value_and_grad in its first argument) against
    float64 central differences along random directions."""
    val, g = vg(x, *args)
    g = np.asarray(g)
    assert np.all(np.isfinite(g)) and np.any(g != 0)
    for s in seeds:
        v = np.random.default_rng(100 + s).standard_normal(x.shape)
        fd = (float(vg(x + eps * v, *args)[0]) - float(vg(x - eps * v, *args)[0])) / (2 * eps)
        assert float(np.sum(g * v)) == pytest.approx(fd, rel=rtol, abs=1e-12 * abs(float(val)))


@pytest.mark.float64
def test_gradients_match_finite_differences():
    t = jnp.asarray(_smooth(4))
    i = jnp.asarray(_smooth(5) * 0.8 + 0.1 * _rand(6))
    for w in ([1.0, 0.0], [0.0, 1.0], [1.0, loss_mod.LAMBDA_G]):  # E_p, E_g, the default total
        _fd_check(_VG, i, t, jnp.asarray(w))


@pytest.mark.float64
def test_float32_follows_input_and_agrees_with_float64():
    t64, i64 = _smooth(7), _smooth(8)
    w = jnp.asarray([1.0, loss_mod.LAMBDA_G])
    v64, g64 = _VG(jnp.asarray(i64), jnp.asarray(t64), w)
    no_x = loss_mod.LossConfig(lambda_x=0.0)  # E_p + LAMBDA_G E_g, as _VG computes
    ref = float(loss_mod.make_loss(no_x)(jnp.asarray(i64), jnp.asarray(t64)))  # eager, public path
    assert float(v64) == pytest.approx(ref, rel=1e-12)
    v32, g32 = _VG(jnp.asarray(i64, jnp.float32), jnp.asarray(t64), w.astype(jnp.float32))
    assert v32.dtype == jnp.float32 and g32.dtype == jnp.float32
    assert float(v32) == pytest.approx(float(v64), rel=1e-4)
    g64 = np.asarray(g64)
    assert np.linalg.norm(np.asarray(g32) - g64) <= 1e-3 * np.linalg.norm(g64)
    # a float64 target is cast to the render's float32
    assert loss_mod.perceptual_loss(jnp.asarray(i64, jnp.float32), jnp.asarray(t64)).dtype == jnp.float32


# ----------------------------------------------------------------------------------------------
# Config, make_loss, bind, calibration


@pytest.mark.float64
def test_make_loss_kinds_and_bind():
    t, i = jnp.asarray(_smooth(9)), jnp.asarray(_smooth(10))
    ep, eg, l2 = loss_mod.perceptual_loss(i, t), loss_mod.gram_loss(i, t), loss_mod.l2_loss(i, t)
    loss_l2 = loss_mod.make_loss(loss_mod.LossConfig(kind="l2", lambda_p=2.0, lambda_x=0.0))
    assert float(loss_l2(i, t)) == pytest.approx(2.0 * float(l2), rel=1e-14)
    assert float(loss_l2.terms(i, t)["l2"]) == pytest.approx(float(l2), rel=1e-14)
    # E_x is added to the L2 loss too (its weight rule reading the L2 term where it reads E_p)
    ex = float(loss_mod.ghost_loss(i, t, jnp.zeros((t.shape[0],) * 2)))
    for scale, factor in (("fixed", 1.0), ("squared", min(1.0, float(l2) / (
            t.shape[0] * loss_mod.GHOST_EP_REF)) ** 2 * 2 / (t.shape[0] - 1))):
        with_x = loss_mod.make_loss(loss_mod.LossConfig(kind="l2", lambda_x=0.5,
                                                        ghost_scale=scale))
        assert set(with_x.terms(i, t)) == {"total", "l2", "E_x"}
        want = float(l2) + 0.5 * factor * ex
        assert float(with_x(i, t)) == pytest.approx(want, rel=1e-12)
        assert float(with_x.bind(t)(i)) == pytest.approx(want, rel=1e-12)
    loss_p = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual", lambda_x=0.0))
    assert loss_p.features is None
    assert float(loss_p(i, t)) == pytest.approx(float(ep), rel=1e-14)
    loss = loss_mod.make_loss(loss_mod.LossConfig(lambda_g=3.0, lambda_x=0.0))
    expected = float(ep) + 3.0 * float(eg)
    assert float(loss(i, t)) == pytest.approx(expected, rel=1e-13)
    no_x = loss_mod.make_loss(loss_mod.LossConfig(lambda_x=0.0))
    assert float(no_x(i, t)) == pytest.approx(float(ep) + loss_mod.LAMBDA_G * float(eg), 1e-13)
    with_x = loss_mod.make_loss().terms(i, t)  # the default adds LAMBDA_X E_x, "squared"
    m = t.shape[0]
    wx = loss_mod.LAMBDA_X * min(1.0, float(ep) / (m * loss_mod.GHOST_EP_REF)) ** 2 * 2 / (m - 1)
    assert float(with_x["total"]) == pytest.approx(
        float(ep) + loss_mod.LAMBDA_G * float(eg) + wx * float(with_x["E_x"]), 1e-12)
    fixed = loss_mod.make_loss(loss_mod.LossConfig(ghost_scale="fixed")).terms(i, t)
    assert float(fixed["total"]) == pytest.approx(
        float(ep) + loss_mod.LAMBDA_G * float(eg) + loss_mod.LAMBDA_X * float(fixed["E_x"]), 1e-12)
    assert float(loss_mod.total_loss(i, t, lambda_g=3.0)) == pytest.approx(expected, rel=1e-13)
    terms = loss.terms(i, t)
    assert set(terms) == {"total", "E_p", "E_g"}
    bound = loss.bind(t)
    assert float(eqx.filter_jit(bound)(i)) == pytest.approx(expected, rel=1e-12)
    assert float(eqx.filter_jit(lambda f, a, b: f(a, b))(loss, i, t)) == pytest.approx(
        expected, rel=1e-12
    )
    assert set(dataclasses.asdict(loss_mod.LossConfig())) == {"kind", "lambda_p", "lambda_g", "vgg_weights",
                                                      "lambda_x", "ghost_baseline", "ghost_scale"}


def test_calibrate_lambda_g():
    t, i = jnp.asarray(_smooth(11)), jnp.asarray(_rand(12))
    lam = loss_mod.calibrate_lambda_g(i, t, ratio=0.5)
    assert lam * float(loss_mod.gram_loss(i, t)) == pytest.approx(0.5 * float(loss_mod.perceptual_loss(i, t)))
    with pytest.raises(ValueError, match="E_g"):
        loss_mod.calibrate_lambda_g(t, t)
    with pytest.raises(ValueError, match="ratio"):
        loss_mod.calibrate_lambda_g(i, t, ratio=-1.0)


def test_bad_inputs():
    t = jnp.zeros(SHAPE)
    with pytest.raises(ValueError, match=r"render must have shape \(M, H, W\)"):
        loss_mod.perceptual_loss(jnp.zeros((32, 32)), jnp.zeros((32, 32)))
    with pytest.raises(ValueError, match="target must have the same shape"):
        loss_mod.l2_loss(t, jnp.zeros((3, 32, 32)))
    with pytest.raises(InputError, match="render must be a floating"):
        loss_mod.gram_loss(jnp.zeros(SHAPE, jnp.int32), t)
    with pytest.raises(InputError, match="target must be floating"):
        loss_mod.perceptual_loss(t, np.zeros(SHAPE, np.uint8))
    with pytest.raises(ValueError, match="kind must be one of"):
        loss_mod.LossConfig(kind="vgg")
    with pytest.raises(ValueError, match="lambda_p"):
        loss_mod.LossConfig(lambda_p=float("nan"))
    with pytest.raises(ValueError, match="lambda_g must be given with vgg_weights"):
        loss_mod.LossConfig(vgg_weights="x.npz")
    with pytest.raises(InputError, match="LossConfig"):
        loss_mod.make_loss({"kind": "l2"})
    with pytest.raises(DesignFileError, match="not found"):
        loss_mod.make_loss(loss_mod.LossConfig(vgg_weights="/nonexistent/vgg.npz", lambda_g=1.0))
    bound = loss_mod.make_loss()
    for bad, says in ((jnp.full(SHAPE, 3.0), r"range \[3, 3\]$"),
                      (t.at[0, 1, 2].set(jnp.inf), r"range \[0, inf\] with non-finite values$"),
                      (t.at[1, 0, 0].set(-0.5), r"range \[-0.5, 0\]$")):
        with pytest.raises(InputError, match=r"^bind: target must be finite display values in "
                                             r"\[0, 1\], got " + says):
            bound.bind(bad)


# ----------------------------------------------------------------------------------------------
# VGG-19 loader on a tiny random file

WIDTHS = {"conv1": 4, "conv2": 5, "conv3": 6, "conv4": 6, "conv5": 7}


def _tiny_vgg(seed=0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out, prev = {}, 3
    for name, _ in loss_mod.VGG19_LAYERS:
        o = WIDTHS[name[:5]]
        out[f"{name}.weight"] = (rng.standard_normal((o, prev, 3, 3)) * np.sqrt(2 / (9 * prev))).astype(
            np.float32
        )
        out[f"{name}.bias"] = rng.uniform(0.0, 0.1, o).astype(np.float32)
        prev = o
    return out


@pytest.fixture(scope="module")
def tiny_vgg_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("vgg") / "tiny_vgg19.npz"
    np.savez(path, **_tiny_vgg(), **{"conv5_2.weight": np.zeros(1, np.float32)})  # extra: ignored
    return path


def _vgg_reference(arrays, images):
    """Direct numpy/scipy VGG forward pass (cross-correlation, zero padding, floor max pool)."""
    mean = np.array([0.485, 0.456, 0.406])[:, None, None]
    std = np.array([0.229, 0.224, 0.225])[:, None, None]
    outs = []
    for img in images:
        x = (np.repeat(img[None], 3, axis=0) - mean) / std
        taps = []
        for name, _ in loss_mod.VGG19_LAYERS:
            if name.endswith("_1") and name != "conv1_1":
                c, h, w = x.shape
                x = x[:, : h // 2 * 2, : w // 2 * 2].reshape(c, h // 2, 2, w // 2, 2).max((2, 4))
            wgt = arrays[f"{name}.weight"].astype(np.float64)
            b = arrays[f"{name}.bias"].astype(np.float64)
            y = np.stack(
                [
                    b[o]
                    + sum(
                        scipy.signal.correlate2d(x[i], wgt[o, i], mode="same", boundary="fill")
                        for i in range(x.shape[0])
                    )
                    for o in range(wgt.shape[0])
                ]
            )
            x = np.maximum(y, 0.0)
            if name in loss_mod.VGG19_TAPS:
                taps.append(x)
        outs.append(taps)
    return [np.stack([o[l] for o in outs]) for l in range(len(loss_mod.VGG19_TAPS))]


def _np_gram(f):
    m, c, h, w = f.shape
    f = f.reshape(m, c, h * w)
    return np.einsum("man,mbn->mab", f, f) / (c * h * w)


@pytest.mark.float64
def test_vgg_features_loss_and_gradient_match_scipy(tiny_vgg_file):
    # One compilation: value_and_grad of the configured loss, with the features and terms as aux.
    loss = loss_mod.make_loss(loss_mod.LossConfig(vgg_weights=str(tiny_vgg_file), lambda_g=0.5,
                                                  lambda_x=0.0))
    assert isinstance(loss.features, loss_mod.VGG19Features)

    def f(r, t, loss):
        terms = loss.terms(r, t)
        return terms["total"], (loss.features(r), terms)

    vg = eqx.filter_jit(jax.value_and_grad(f, has_aux=True))
    images = _smooth(13, (2, 32, 34))  # odd pooled sizes exercise the floor
    target = _smooth(14, (2, 32, 34))
    (total, (got, terms)), _ = vg(jnp.asarray(images), jnp.asarray(target), loss)
    ref = _vgg_reference(_tiny_vgg(), images)
    assert [g.shape for g in got] == [
        (2, WIDTHS[f"conv{b}"], h, w)
        for b, (h, w) in zip(range(1, 6), [(32, 34), (16, 17), (8, 8), (4, 4), (2, 2)])
    ]
    for g, r in zip(got, ref):
        assert g.dtype == jnp.float64
        np.testing.assert_allclose(np.asarray(g), r, rtol=1e-10, atol=1e-12)
    assert float(jnp.max(got[-1])) > 0  # the deepest tap is not all zero
    # E_g and E_p from the scipy features / scipy blur, independently of jscratch.
    ref_t = _vgg_reference(_tiny_vgg(), target)
    eg = np.sum(np.mean([np.sum((_np_gram(a) - _np_gram(b)) ** 2, (1, 2)) for a, b in zip(ref, ref_t)], 0))
    g2 = np.outer(K1, K1)
    ep = sum(np.mean(scipy.ndimage.convolve(a - b, g2, mode="nearest") ** 2) for a, b in zip(images, target))
    assert float(terms["E_g"]) == pytest.approx(eg, rel=1e-9)
    assert float(terms["E_p"]) == pytest.approx(ep, rel=1e-12)
    assert float(total) == pytest.approx(ep + 0.5 * eg, rel=1e-9)
    _fd_check(lambda r, t, l: (vg(r, t, l)[0][0], vg(r, t, l)[1]), jnp.asarray(images), jnp.asarray(target), loss, seeds=(0,))


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda a: a.pop("conv3_2.bias"), "lacks key conv3_2.bias"),
        (lambda a: a.__setitem__("conv2_1.weight", np.zeros((5, 4, 5, 5), np.float32)), "conv2_1.weight must have shape"),
        (lambda a: a.__setitem__("conv4_1.weight", np.zeros((6, 3, 3, 3), np.float32)), "conv4_1.weight has 3 input channels"),
        (lambda a: a.__setitem__("conv1_1.weight", np.zeros((4, 1, 3, 3), np.float32)), "conv1_1.weight has 1 input channels"),
        (lambda a: a.__setitem__("conv5_1.bias", np.zeros(3, np.float32)), r"conv5_1.bias must have shape \(7,\)"),
        (lambda a: a["conv1_2.weight"].__setitem__((0, 0, 0, 0), np.nan), "conv1_2 has non-finite"),
    ],
)
def test_vgg_loader_structure_errors(tmp_path, edit, match):
    arrays = _tiny_vgg()
    edit(arrays)
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match=match):
        loss_mod.load_vgg19(path)


def test_vgg_loader_unreadable_file(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="not a valid .npz file"):
        loss_mod.load_vgg19(path)


def _converter():
    path = pathlib.Path(__file__).resolve().parents[1] / "scripts" / "convert_vgg19.py"
    spec = importlib.util.spec_from_file_location("convert_vgg19", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_converter_maps_torchvision_keys(tmp_path):
    conv = _converter()
    arrays = _tiny_vgg(seed=3)
    rng = np.random.default_rng(4)
    state, prev = {}, WIDTHS["conv5"]
    for name, idx in conv.TORCHVISION_VGG19_CONVS.items():
        if f"{name}.weight" in arrays:
            w, b = arrays[f"{name}.weight"], arrays[f"{name}.bias"]
        else:  # conv5_2 .. conv5_4
            w = rng.standard_normal((prev, prev, 3, 3)).astype(np.float32)
            b = np.zeros(prev, np.float32)
        state[f"features.{idx}.weight"], state[f"features.{idx}.bias"] = w, b
    state["classifier.0.weight"] = np.zeros((2, 2), np.float32)
    assert {k: v for k, v in loss_mod.VGG19_LAYERS} == {
        k: v for k, v in conv.TORCHVISION_VGG19_CONVS.items() if k in dict(loss_mod.VGG19_LAYERS)
    }
    out = conv.convert_state_dict(state)
    assert len(out) == 32 and "classifier.0.weight" not in out
    path = tmp_path / "converted.npz"
    np.savez(path, **out)
    feats = loss_mod.load_vgg19(path)
    for got, want in zip(feats.weights, (arrays[f"{n}.weight"] for n, _ in loss_mod.VGG19_LAYERS)):
        np.testing.assert_array_equal(np.asarray(got), want)
    with pytest.raises(ValueError, match="vgg19_bn"):
        conv.convert_state_dict({**state, "features.1.running_mean": np.zeros(4)})
    del state["features.10.bias"]
    with pytest.raises(ValueError, match=r"lacks features\.10\.bias \(for conv3_1\)"):
        conv.convert_state_dict(state)


# ----------------------------------------------------------------------------------------------
# The ghosting term E_x

@pytest.mark.float64
def test_ghost_loss_zero_at_target_positive_for_ghost_and_descends(smooth_images):
    t = jnp.asarray(smooth_images())
    assert float(loss_mod.ghost_loss(t, t)) == pytest.approx(0.0, abs=1e-12)
    # view 0 shows a mix of its target and view 1's: a ghost
    ghost = t.at[0].set(0.5 * t[0] + 0.5 * t[1])
    e = float(loss_mod.ghost_loss(ghost, t))
    s = np.asarray(loss_mod.cross_ssim(ghost, t))
    b = np.asarray(loss_mod.cross_ssim(t, t))
    assert e > 0.05 and e == pytest.approx(np.sum(np.maximum(s - b, 0) * (1 - np.eye(3))), rel=1e-9)
    # a small step against the gradient lowers the ghost's resemblance to target 1
    g = jax.grad(loss_mod.ghost_loss)(ghost, t)
    assert np.all(np.asarray(g[1:]) == 0) or float(jnp.abs(g[1:]).max()) < float(jnp.abs(g[0]).max())
    step = ghost - 0.5 * g / float(jnp.abs(g).max())
    assert float(loss_mod.cross_ssim(step, t)[0, 1]) < s[0, 1]
    assert float(loss_mod.ghost_loss(step, t)) < e



@pytest.mark.float64
def test_lambda_x_in_loss_terms(smooth_images):
    t = jnp.asarray(smooth_images())
    r = t.at[0].set(t[1])
    plain = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual", lambda_x=0.0)).terms(r, t)
    with_x = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual", lambda_x=0.1,
                                                    ghost_scale="fixed")).bind(t).terms(r)
    assert "E_x" not in plain and float(with_x["E_x"]) > 0
    assert float(with_x["total"]) == pytest.approx(float(plain["total"]) + 0.1 * float(with_x["E_x"]),
                                                   rel=1e-6)
    with pytest.raises(ValueError, match="lambda_x"):
        loss_mod.LossConfig(lambda_x=-1.0)



@pytest.mark.float64
@pytest.mark.parametrize("baseline", ["zero", "targets"])
def test_bound_ghost_matches_pairwise_ssim(smooth_images, baseline):
    """`Loss.bind` precomputes the target's blur, SSIM moments and baseline: ``E_x`` and its
    gradient are those of the pairwise `ssim_mean` of the blurred images, computed per call."""
    t = jnp.asarray(smooth_images())
    r = 0.6 * t + 0.4 * jnp.roll(t, 1, axis=0)  # each view partly its neighbour: ghosts
    cfg = loss_mod.LossConfig(kind="perceptual", lambda_x=0.1, ghost_baseline=baseline)
    bound = loss_mod.make_loss(cfg).bind(t)
    assert bound.target_ghost is not None

    def ref(x):
        bx, bt = loss_mod.blur3(x), loss_mod.blur3(t)
        b = ssim_mean(bt[:, None], bt[None, :]) if baseline == "targets" else jnp.zeros((3, 3))
        return sum(jax.nn.relu(ssim_mean(bx[j], bt[k]) - b[j, k])
                   for j in range(3) for k in range(3) if k != j)

    got = lambda x: bound.terms(x)["E_x"]  # noqa: E731
    assert float(got(r)) == pytest.approx(float(ref(r)), rel=1e-12) and float(ref(r)) > 0
    np.testing.assert_allclose(np.asarray(jax.grad(got)(r)), np.asarray(jax.grad(ref)(r)),
                               rtol=1e-9, atol=1e-14)


@pytest.mark.float64
def test_ghost_baseline_zero_penalises_raw_cross_ssim(smooth_images):
    t = jnp.asarray(smooth_images())
    cfg = loss_mod.LossConfig(kind="perceptual", lambda_x=0.1, ghost_baseline="zero",
                              ghost_scale="fixed")
    got = loss_mod.make_loss(cfg).bind(t).terms(t)
    # independent: scikit-image SSIM of every (render j, target k != j) pair of the blurred images
    b = np.asarray(loss_mod.blur3(t), np.float64)
    ref = sum(max(0.0, structural_similarity(b[j], b[k], data_range=1.0))
              for j in range(3) for k in range(3) if k != j)
    assert ref > 0.05  # the targets resemble each other: a perfect render is penalised too
    assert float(got["E_x"]) == pytest.approx(ref, rel=1e-4)
    assert float(got["total"]) == pytest.approx(0.1 * ref, rel=1e-4)  # E_p = 0 here
    excess = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual", lambda_x=0.1,
                                                    ghost_baseline="targets"))
    assert float(excess.bind(t).terms(t)["E_x"]) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="ghost_baseline"):
        loss_mod.LossConfig(ghost_baseline="none")


@pytest.mark.float64
def test_ghost_weight_factor_rule_and_no_gradient():
    """`ghost_weight_factor`: 1 for "fixed"; "relative": 2 / (M - 1) at or above the reference E_p
    per view, times E_p / (M E_ref) below it ("squared", the default: times its square); its
    value carries no gradient, so the total's gradient is E_p's (and E_g's) plus the factor times
    E_x's."""
    f = loss_mod.ghost_weight_factor
    ref = loss_mod.GHOST_EP_REF
    assert f("fixed", jnp.asarray(1e-9), 3) == 1.0
    assert float(f("relative", jnp.asarray(3 * ref), 3)) == 1.0
    assert float(f("relative", jnp.asarray(50 * ref), 5)) == pytest.approx(0.5, rel=1e-15)
    assert float(f("relative", jnp.asarray(3 * ref / 4), 3)) == pytest.approx(0.25, rel=1e-14)
    assert float(f("relative", jnp.asarray(5 * ref / 3), 5)) == pytest.approx(0.5 / 3, rel=1e-14)
    assert float(jax.grad(lambda e: f("relative", e, 3))(jnp.asarray(ref / 10))) == 0.0
    # "squared": the same at and above the reference, the square of the share below it
    assert float(f("squared", jnp.asarray(50 * ref), 5)) == pytest.approx(0.5, rel=1e-15)
    assert float(f("squared", jnp.asarray(3 * ref / 4), 3)) == pytest.approx(0.0625, rel=1e-14)
    assert float(f("squared", jnp.asarray(5 * ref / 3), 5)) == pytest.approx(0.5 / 9, rel=1e-14)
    assert float(jax.grad(lambda e: f("squared", e, 3))(jnp.asarray(ref / 10))) == 0.0
    t = jnp.asarray(_smooth(9))
    i = t * 1.05 + 0.01 * jnp.asarray(_smooth(10))  # close to the target: E_p below the reference
    loss = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual", lambda_x=0.01))
    ep = float(loss_mod.perceptual_loss(i, t))
    w = 0.01 * float(f("squared", jnp.asarray(ep), t.shape[0]))
    assert 0 < w < 0.01 * 2 / (t.shape[0] - 1)  # below the reference: scaled down
    zero = jnp.zeros((t.shape[0],) * 2)
    g = jax.grad(lambda r: loss(r, t))(i)
    g_ref = jax.grad(lambda r: loss_mod.perceptual_loss(r, t)
                     + w * loss_mod.ghost_loss(r, t, zero))(i)
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_ref), rtol=1e-10, atol=1e-16)



@pytest.mark.parametrize("shape", [(3, 3), (1,), (2,), (2, 2, 1)])
def test_ghost_loss_refuses_a_baseline_of_the_wrong_shape(shape):
    r = jnp.zeros((2, 8, 8), jnp.float32)
    t = jnp.full((2, 8, 8), 0.5, jnp.float32)
    with pytest.raises(InputError, match=r"^ghost_loss: `baseline` must have shape \(M, M\) = "
                                         rf"\(2, 2\), one value per pair of views; got "
                                         rf"{re.escape(str(shape))}$"):
        loss_mod.ghost_loss(r, t, baseline=jnp.zeros(shape, jnp.float32))
    assert float(loss_mod.ghost_loss(r, t, baseline=np.zeros((2, 2), np.float32))) >= 0
