"""Tests of issue 17's measures and loss term: the differentiable SSIM against scikit-image, the
ghosting term ``E_x`` (zero at the optimum, positive for a ghost, a gradient that lowers the
ghost), the texture distance, and the options reaching the loss."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.filters import gaussian
from skimage.metrics import structural_similarity

from jscratch import loss as loss_mod
from jscratch.metrics import texture_distance
from jscratch.ssim import ssim_mean


def _images(m=3, h=24, w=20, seed=0):
    r = np.random.default_rng(seed)
    base = gaussian(r.uniform(size=(m, h, w)), sigma=(0, 1.5, 1.5))
    return (base - base.min()) / (base.max() - base.min())


def test_ssim_mean_matches_skimage():
    x, y = _images(2, seed=1)
    for a, b in ((x, y), (x, 0.3 * x + 0.2), (y, y)):
        ref = structural_similarity(a, b, data_range=1.0)
        got = float(ssim_mean(jnp.asarray(a), jnp.asarray(b)))
        assert got == pytest.approx(ref, abs=1e-10)


def test_ghost_loss_zero_at_target_positive_for_ghost_and_descends():
    t = jnp.asarray(_images())
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


def test_lambda_x_in_loss_terms():
    t = jnp.asarray(_images())
    r = t.at[0].set(t[1])
    plain = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual")).terms(r, t)
    with_x = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual", lambda_x=0.1)).bind(t).terms(r)
    assert "E_x" not in plain and float(with_x["E_x"]) > 0
    assert float(with_x["total"]) == pytest.approx(float(plain["total"]) + 0.1 * float(with_x["E_x"]),
                                                   rel=1e-6)
    with pytest.raises(ValueError, match="lambda_x"):
        loss_mod.LossConfig(lambda_x=-1.0)


def test_texture_distance():
    t = _images(2, 64, 64)
    assert texture_distance(t, t) == [0.0, 0.0]
    flat = np.full_like(t, 0.5)
    noisy = np.clip(t + np.random.default_rng(3).normal(scale=0.2, size=t.shape), 0, 1)
    d_flat, d_noisy = texture_distance(flat, t), texture_distance(noisy, t)
    smooth = np.stack([gaussian(x, 0.5) for x in t])
    d_smooth = texture_distance(smooth, t)
    assert all(0 < a <= 1 for a in d_flat + d_noisy)
    # a slightly smoothed image keeps the texture far better than a flat or a noisy one
    assert max(d_smooth) < min(min(d_flat), min(d_noisy))
    with pytest.raises(ValueError, match="same shape"):
        texture_distance(t[:1], t)


def test_ghost_baseline_zero_penalises_raw_cross_ssim():
    t = jnp.asarray(_images())
    cfg = loss_mod.LossConfig(kind="perceptual", lambda_x=0.1, ghost_baseline="zero")
    got = loss_mod.make_loss(cfg).bind(t).terms(t)
    # independent: scikit-image SSIM of every (render j, target k != j) pair of the blurred images
    b = np.asarray(loss_mod.blur3(t), np.float64)
    ref = sum(max(0.0, structural_similarity(b[j], b[k], data_range=1.0))
              for j in range(3) for k in range(3) if k != j)
    assert ref > 0.05  # the targets resemble each other: a perfect render is penalised too
    assert float(got["E_x"]) == pytest.approx(ref, rel=1e-4)
    assert float(got["total"]) == pytest.approx(0.1 * ref, rel=1e-4)  # E_p = 0 here
    default = loss_mod.make_loss(loss_mod.LossConfig(kind="perceptual", lambda_x=0.1))
    assert float(default.bind(t).terms(t)["E_x"]) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="ghost_baseline"):
        loss_mod.LossConfig(ghost_baseline="none")
