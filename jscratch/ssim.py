"""A differentiable SSIM equal to scikit-image's (`ssim_mean`): the measure of the
ghosting of docs/model.md §7, which `jscratch.loss.ghost_loss` penalises. Pure jax; imports
only `jscratch.errors`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jscratch.errors import InputError

__all__ = ["ssim_mean", "ssim_moments"]

SSIM_WINDOW = 7  # skimage.metrics.structural_similarity's default uniform window
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2  # its constants for data_range 1
_N = SSIM_WINDOW * SSIM_WINDOW
_CN = _N / (_N - 1)  # sample covariance


def _mean(a):
    # The 7x7 box sum as a 7-row sum then a 7-column sum: 14 adds per pixel, not 49 (a different
    # order of the same float sums).
    w = SSIM_WINDOW
    ones, lead = (1,) * a.ndim, (1,) * (a.ndim - 2)
    a = jax.lax.reduce_window(a, 0.0, jax.lax.add, lead + (w, 1), ones, "VALID")
    return jax.lax.reduce_window(a, 0.0, jax.lax.add, lead + (1, w), ones, "VALID") / _N


def _centred(x):
    """``(x - c, c)``, ``c``: the image mean of ``x`` (``(..., 1, 1)``, no gradient through it).
    The second moments below are the same for any shift, and in float32 ``E[x^2] - E[x]^2`` of a
    flat, bright image cancels to noise (a negative variance, an SSIM above 1) unless taken
    about a value near ``x``."""
    c = jax.lax.stop_gradient(jnp.mean(x, axis=(-2, -1), keepdims=True))
    return x - c, c


def ssim_moments(x: Float[Array, "... H W"]) -> tuple[Float[Array, "... h w"], Float[Array, "... h w"]]:
    """The local mean and sample variance of ``x`` over each 7x7 window inside the image
    (``h, w = H - 6, W - 6``): what `ssim_mean` needs of one image, to compute once for an image
    compared with several."""
    xc, c = _centred(x)
    mc = _mean(xc)
    return mc + c, _CN * (_mean(xc * xc) - mc * mc)


def ssim_mean(x: Float[Array, "... H W"], y: Float[Array, "... H W"],
              moments_x: tuple[Array, Array] | None = None,
              moments_y: tuple[Array, Array] | None = None) -> Float[Array, "..."]:
    """Mean SSIM of ``x`` against ``y`` as ``skimage.metrics.structural_similarity`` computes it
    (7x7 uniform window, sample covariance, ``data_range = 1``, mean over the pixels whose window
    lies inside the image), differentiable: the measure of the ghosting of docs/model.md §7.

    **Arguments:** `x`, `y`: ``(..., H, W)`` with ``H, W >= 7``; `moments_x`, `moments_y`:
    their `ssim_moments` if already computed (broadcast like ``x`` and ``y``). **Returns:**
    ``(...)``.

    **Raises:** `InputError`, one line, when ``x`` and ``y`` differ in ``(H, W)`` or their
    leading axes do not broadcast, or ``H`` or ``W`` is below 7 (no window fits: scikit-image
    refuses it too). Shapes are static: the check holds under jit.
    """
    sx, sy = jnp.shape(x), jnp.shape(y)
    if len(sx) < 2 or len(sy) < 2 or sx[-2:] != sy[-2:]:
        raise InputError(f"ssim_mean: `x` and `y` must be images (..., H, W) of one size; got "
                         f"shapes {sx} and {sy}")
    try:
        np.broadcast_shapes(sx, sy)
    except ValueError:
        raise InputError(f"ssim_mean: the leading axes of `x` {sx} and `y` {sy} do not "
                         f"broadcast") from None
    if min(sx[-2:]) < SSIM_WINDOW:
        raise InputError(f"ssim_mean: images must be at least {SSIM_WINDOW}x{SSIM_WINDOW} px (the "
                         f"window); got H, W = {sx[-2]}, {sx[-1]}")
    mx, vx = ssim_moments(x) if moments_x is None else moments_x
    my, vy = ssim_moments(y) if moments_y is None else moments_y
    (xc, cx), (yc, cy) = _centred(x), _centred(y)  # the covariance about each image's mean
    vxy = _CN * (_mean(xc * yc) - (mx - cx) * (my - cy))
    s = ((2 * mx * my + SSIM_C1) * (2 * vxy + SSIM_C2)) / (
        (mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))
    return jnp.mean(s, axis=(-2, -1))
