"""Tests of jscratch.ssim: the differentiable mean SSIM against scikit-image's
``structural_similarity`` (7 x 7 uniform window, data range 1), in float64 and float32, batched,
and its gradient against central finite differences; the local moments against numpy's sliding
windows."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from jscratch.ssim import ssim_mean, ssim_moments

@pytest.mark.float64
def test_ssim_mean_matches_skimage(smooth_images):
    x, y = smooth_images(2, seed=1)
    for a, b in ((x, y), (x, 0.3 * x + 0.2), (y, y)):
        ref = structural_similarity(a, b, data_range=1.0)
        got = float(ssim_mean(jnp.asarray(a), jnp.asarray(b)))
        assert got == pytest.approx(ref, abs=1e-10)


def test_ssim_mean_float32_and_batched(smooth_images):
    x, y = smooth_images(3, seed=2), smooth_images(3, seed=3)
    got = ssim_mean(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32))
    assert got.shape == (3,) and got.dtype == jnp.float32
    ref = [structural_similarity(a, b, data_range=1.0) for a, b in zip(x, y)]
    np.testing.assert_allclose(np.asarray(got), ref, atol=2e-5)
    same = ssim_mean(jnp.asarray(x, jnp.float32), jnp.asarray(x, jnp.float32))
    np.testing.assert_allclose(np.asarray(same), 1.0, atol=1e-6)


@pytest.mark.float64
def test_ssim_mean_gradient_matches_finite_differences(smooth_images):
    x, y = (jnp.asarray(smooth_images(1, 12, 11, seed=k)[0]) for k in (4, 5))
    g = np.asarray(jax.grad(lambda a: ssim_mean(a, y))(x))
    rng = np.random.default_rng(6)
    for _ in range(3):
        d = rng.normal(size=x.shape)
        h = 1e-5
        fd = (float(ssim_mean(x + h * d, y)) - float(ssim_mean(x - h * d, y))) / (2 * h)
        assert np.sum(g * d) == pytest.approx(fd, rel=1e-6, abs=1e-10)


@pytest.mark.float64
def test_ssim_moments_match_sliding_windows_and_feed_ssim_mean(smooth_images):
    x, y = smooth_images(2, h=12, w=10, seed=3), smooth_images(3, h=12, w=10, seed=4)
    win = np.lib.stride_tricks.sliding_window_view(x, (7, 7), axis=(-2, -1))  # (2, 6, 4, 7, 7)
    mean, var = ssim_moments(jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(mean), win.mean(axis=(-2, -1)), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(var), win.reshape(*win.shape[:-2], 49).var(-1, ddof=1),
                               rtol=1e-10, atol=1e-15)
    # given moments (broadcast over the pairs) give the SSIM that computing them gives
    xs, ys = jnp.asarray(x)[:, None], jnp.asarray(y)[None, :]
    my, vy = ssim_moments(jnp.asarray(y))
    got = ssim_mean(xs, ys, (mean[:, None], var[:, None]), (my[None], vy[None]))
    assert got.shape == (2, 3)
    np.testing.assert_allclose(np.asarray(got), np.asarray(ssim_mean(xs, ys)), rtol=1e-14)


def test_ssim_mean_refuses_mismatched_or_too_small_images():
    """Shapes are static, so the refusal holds under jit too; scikit-image refuses a window that
    does not fit."""
    from jscratch.errors import InputError

    with pytest.raises(InputError, match=r"^ssim_mean: `x` and `y` must be images \(\.\.\., H, W\) "
                                         r"of one size; got shapes \(8, 8\) and \(9, 9\)$"):
        ssim_mean(jnp.zeros((8, 8)), jnp.zeros((9, 9)))
    with pytest.raises(InputError, match=r"leading axes of `x` \(2, 8, 8\) and `y` \(3, 8, 8\)"):
        ssim_mean(jnp.zeros((2, 8, 8)), jnp.zeros((3, 8, 8)))
    for shape in ((6, 8), (8, 6)):
        with pytest.raises(InputError, match=r"^ssim_mean: images must be at least 7x7 px"):
            jax.jit(ssim_mean)(jnp.zeros(shape), jnp.zeros(shape))
    assert ssim_mean(jnp.zeros((2, 7, 7)), jnp.zeros((7, 7))).shape == (2,)


def test_ssim_mean_float32_keeps_its_digits_on_flat_bright_images():
    """Flat, bright images (a line drawing's paper, a lit board's background): in float32 the
    variance ``E[x^2] - E[x]^2`` about 0 cancels to noise (negative variances, SSIM above 1, errors
    of 1e-4); taken about each image's mean it keeps its digits. Against scikit-image in float64,
    on the same float32 inputs."""
    rng = np.random.default_rng(3)
    worst = 0.0
    for _ in range(60):
        a, b = rng.uniform(0.3, 1.0, 2)
        noise = rng.normal(size=(2, 16, 16)) * 10.0 ** rng.uniform(-6, -2)
        x, y = (a + noise[0]).astype(np.float32), (b + noise[1]).astype(np.float32)
        got = float(ssim_mean(jnp.asarray(x), jnp.asarray(y)))
        want = structural_similarity(x.astype(np.float64), y.astype(np.float64), data_range=1.0)
        assert got <= 1.0
        worst = max(worst, abs(got - want))
    assert worst < 1e-5, worst
    line_art = np.full((2, 32, 32), 0.97)
    line_art[0, 10:12] = 0.1
    line_art[1, :, 5:7] = 0.2
    noisy = line_art + rng.normal(size=line_art.shape) * 0.01
    got = ssim_mean(jnp.float32(noisy[:, None]), jnp.float32(line_art[None]))
    want = [[structural_similarity(n, t, data_range=1.0) for t in line_art] for n in noisy]
    np.testing.assert_allclose(np.asarray(got), want, atol=1e-5)
    assert float(jnp.min(ssim_moments(jnp.full((8, 8), 0.9, jnp.float32))[1])) >= 0.0
