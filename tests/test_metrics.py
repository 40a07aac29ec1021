"""Tests of jscratch.metrics (docs/model.md §7): SSIM against an independent numpy implementation,
PSNR by hand, ghosting bookkeeping, the sigma-1 blur, clipping and errors. Host code only (no JAX
compilation)."""

import math

import numpy as np
import pytest
import scipy.ndimage
from skimage.filters import gaussian

from jscratch.metrics import image_metrics, texture_distance


def _rng_images(seed, shape=(3, 24, 28)):
    x = np.random.default_rng(seed).random(shape)
    return scipy.ndimage.gaussian_filter(x, (0, 1.5, 1.5))


def _ssim_ref(a, b, win=7, data_range=1.0):
    """SSIM (Wang et al. 2004) with a win x win uniform window, sample covariance, mean over the
    window positions fully inside the image: written from the definition, not from skimage."""
    k1, k2 = 0.01, 0.03
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    h, w = a.shape
    vals = []
    n = win * win
    for r in range(h - win + 1):
        for c in range(w - win + 1):
            x = a[r : r + win, c : c + win].ravel()
            y = b[r : r + win, c : c + win].ravel()
            mx, my = x.mean(), y.mean()
            vx = np.sum((x - mx) ** 2) / (n - 1)
            vy = np.sum((y - my) ** 2) / (n - 1)
            cxy = np.sum((x - mx) * (y - my)) / (n - 1)
            vals.append(
                (2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2))
            )
    return float(np.mean(vals))


def test_ssim_psnr_against_independent_reference_without_blur():
    t = _rng_images(0)
    i = np.clip(t + 0.05 * np.random.default_rng(1).standard_normal(t.shape), 0, 1)
    m = image_metrics(i, t, sigma=0)
    for j in range(3):
        assert m["ssim"][j] == pytest.approx(_ssim_ref(i[j], t[j]), abs=1e-9)
        mse = np.mean((i[j] - t[j]) ** 2)
        assert m["psnr"][j] == pytest.approx(10 * math.log10(1.0 / mse), rel=1e-12)


def test_blur_is_gaussian_sigma_one_nearest():
    t = _rng_images(2)
    i = _rng_images(3)
    m = image_metrics(i, t)  # sigma = 1 px (docs/model.md §7)
    blur = lambda x: np.stack([scipy.ndimage.gaussian_filter(v, 1.0, mode="nearest") for v in x])
    bi, bt = blur(i), blur(t)
    for j in range(3):
        assert m["ssim"][j] == pytest.approx(_ssim_ref(bi[j], bt[j]), abs=1e-9)
        mse = np.mean((bi[j] - bt[j]) ** 2)
        assert m["psnr"][j] == pytest.approx(10 * math.log10(1.0 / mse), rel=1e-9)


def test_constant_offset_psnr_and_identical_images():
    t = np.full((2, 16, 16), 0.4)
    t[1] = 0.7
    m = image_metrics(t + 0.1, t)
    assert m["psnr"] == pytest.approx([20.0, 20.0], rel=1e-9)  # 10 log10(1 / 0.01)
    same = image_metrics(t, t)
    assert same["ssim"] == [1.0, 1.0]
    assert same["psnr"] == [math.inf, math.inf]


def test_ghosting_picks_the_other_target_a_view_resembles():
    t = _rng_images(4)
    # View 0 shows target 2 exactly, view 1 its own target, view 2 a mix of targets 2 and 0.
    i = np.stack([t[2], t[1], 0.5 * t[2] + 0.5 * t[0]])
    m = image_metrics(i, t)
    assert m["ghosting"][0] == pytest.approx(1.0)
    assert m["ghosting_from"][0] == 2
    assert m["ssim"][1] == pytest.approx(1.0)
    assert m["ghosting_from"][1] in (0, 2)
    blur = lambda x: scipy.ndimage.gaussian_filter(x, 1.0, mode="nearest")
    cand = {k: _ssim_ref(blur(i[2]), blur(t[k])) for k in (0, 1)}
    k = max(cand, key=cand.get)
    assert m["ghosting_from"][2] == k
    assert m["ghosting"][2] == pytest.approx(cand[k], abs=1e-9)


def test_single_view_and_clipping():
    t = _rng_images(5, (1, 16, 16))
    m = image_metrics(t, t)
    assert math.isnan(m["ghosting"][0]) and m["ghosting_from"] == [-1]
    # Display values above 1 are clipped (what a PNG shows) unless clip=False.
    over = np.ones((1, 16, 16))
    over[0, :8] = 3.0
    tgt = np.ones((1, 16, 16))
    assert image_metrics(over, tgt)["psnr"] == [math.inf]
    assert image_metrics(over, tgt, clip=False)["psnr"][0] < 10.0


@pytest.mark.parametrize(
    "images, targets, kw, err, match",
    [
        (np.zeros((2, 16, 16)), np.zeros((3, 16, 16)), {}, ValueError, "same shape"),
        (np.zeros((16, 16)), np.zeros((16, 16)), {}, ValueError, r"display_images must have shape \(M, H, W\)"),
        (np.zeros((1, 16, 16)), np.full((1, 16, 16), 1.5), {}, ValueError, r"targets must be display values in \[0, 1\]"),
        (np.full((1, 16, 16), np.nan), np.zeros((1, 16, 16)), {}, ValueError, "display_images has 256 non-finite"),
        (np.zeros((1, 16, 16)), np.zeros((1, 16, 16), np.uint8), {}, ValueError, "targets must be floating"),
        (np.zeros((1, 5, 16)), np.zeros((1, 5, 16)), {}, ValueError, "at least 7x7"),
        (np.zeros((1, 16, 16)), np.zeros((1, 16, 16)), {"sigma": -1.0}, ValueError, "sigma"),
        (np.zeros((1, 16, 16)), np.zeros((1, 16, 16)), {"sigma": True}, ValueError,
         "sigma must be a finite number >= 0 .pixels., got True"),
    ],
)
def test_errors(images, targets, kw, err, match):
    with pytest.raises(err, match=match):
        image_metrics(images, targets, **kw)
    if not kw:  # texture_distance checks its images as image_metrics does
        with pytest.raises(err, match=match):
            texture_distance(images, targets)


def test_sigma_is_any_real_number():
    t = _texture_images(2, 16, 16)
    want = image_metrics(t, t[::-1], sigma=1.0)
    assert image_metrics(t, t[::-1], sigma=np.float32(1.0)) == want
    assert image_metrics(t, t[::-1], sigma=np.array(1.0)) == want


def _texture_images(m=3, h=24, w=20, seed=0):
    """Smooth random images in [0, 1], ``(m, h, w)`` float64 numpy."""
    r = np.random.default_rng(seed)
    base = gaussian(r.uniform(size=(m, h, w)), sigma=(0, 1.5, 1.5))
    return (base - base.min()) / (base.max() - base.min())


def test_texture_distance():
    t = _texture_images(2, 64, 64)
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
