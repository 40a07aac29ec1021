"""Image quality metrics of a multi-view design (docs/model.md §7), host side (numpy/scikit-image).

Per view ``j``, with ``g`` a Gaussian of sigma 1 px (``skimage.filters.gaussian``, boundary mode
``"nearest"``) applied to the display images ``I_j`` and the targets ``T_j``:

- ``ssim[j] = SSIM(g * I_j, g * T_j)`` (``skimage.metrics.structural_similarity``, 7x7 uniform
  window, ``data_range = 1``);
- ``psnr[j] = PSNR(g * T_j, g * I_j)`` in dB (``data_range = 1``; ``inf`` for identical images);
- ``ghosting[j] = max_{k != j} SSIM(g * I_j, g * T_k)``: how much view ``j`` resembles another
  view's target (lower is better; compare with ``ssim[j]``); ``ghosting_from[j]`` is that ``k``.
  With a single view there is no other target: ``nan`` and ``-1``.
"""

from __future__ import annotations

import numpy as np
from skimage.filters import gaussian
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from jscratch.errors import InputError, real_number, shown

__all__ = ["LBP_POINTS", "LBP_RADIUS", "METRIC_SIGMA", "image_metrics", "texture_distance"]

#: Gaussian sigma (pixels) applied to renders and targets before the metrics.
METRIC_SIGMA = 1.0
_SSIM_WIN = 7  # skimage's default window side; images must be at least this large


def _as_stack(x, name: str) -> np.ndarray:
    x = np.asarray(x)
    if x.dtype == object or not np.issubdtype(x.dtype, np.number):
        raise InputError(f"{name} must be a numeric array, got dtype {x.dtype}")
    if np.issubdtype(x.dtype, np.integer):
        raise InputError(f"{name} must be floating display values in [0, 1], got dtype {x.dtype}")
    if x.ndim != 3:
        raise InputError(f"{name} must have shape (M, H, W) (views, rows, columns), got {x.shape}")
    bad = ~np.isfinite(x)
    if bad.any():
        j, r, c = np.argwhere(bad)[0]
        raise InputError(
            f"{name} has {int(bad.sum())} non-finite values (first: view {j}, pixel ({r}, {c}) "
            f"= {x[j, r, c]})"
        )
    return x.astype(np.float64)


def _as_pair(display_images, targets) -> tuple[np.ndarray, np.ndarray]:
    """Renders and targets as float64 ``(M, H, W)`` stacks of one shape, at least 7x7 px, the
    targets in ``[0, 1]``; `InputError` (one line) otherwise."""
    imgs = _as_stack(display_images, "display_images")
    tgts = _as_stack(targets, "targets")
    if imgs.shape != tgts.shape:
        raise InputError(
            f"display_images {imgs.shape} and targets {tgts.shape} must have the same shape"
        )
    if tgts.min() < 0.0 or tgts.max() > 1.0:
        raise InputError(
            f"targets must be display values in [0, 1], got range [{tgts.min()}, {tgts.max()}]"
        )
    h, w = imgs.shape[1:]
    if min(h, w) < _SSIM_WIN:
        raise InputError(f"images must be at least {_SSIM_WIN}x{_SSIM_WIN} px, got {h}x{w}")
    return imgs, tgts


def image_metrics(
    display_images,
    targets,
    sigma: float = METRIC_SIGMA,
    clip: bool = True,
) -> dict[str, list]:
    """SSIM, PSNR and cross-view ghosting per view (docs/model.md §7).

    **Arguments:**

    - `display_images`: ``(M, H, W)`` rendered display values (``render.display`` of the radiance;
      numpy or JAX array, floating).
    - `targets`: ``(M, H, W)`` target display values in ``[0, 1]``.
    - `sigma`: Gaussian sigma in pixels applied to both before comparing (docs/model.md §7: 1).
    - `clip`: clip the display images to ``[0, 1]`` first (what a screen or PNG shows); default
      True.

    **Returns:**

    ``{"ssim": [M floats], "psnr": [M floats, dB], "ghosting": [M floats],
    "ghosting_from": [M ints]}`` (plain Python types, ready for JSON; ``psnr`` may be ``inf``,
    ``ghosting`` is ``nan`` when ``M == 1``).

    **Raises:**

    `InputError` (a ``ValueError``), one line, for shape mismatches, non-float or non-finite
    values, targets outside ``[0, 1]``, images smaller than 7x7 or a bad ``sigma``.
    """
    given, sigma = sigma, real_number(sigma)
    if sigma is None or not (np.isfinite(sigma) and sigma >= 0):
        raise InputError(f"sigma must be a finite number >= 0 (pixels), got {shown(given)}")
    imgs, tgts = _as_pair(display_images, targets)
    m = imgs.shape[0]
    if clip:
        imgs = np.clip(imgs, 0.0, 1.0)

    def blur(x):
        if sigma == 0:
            return x
        return gaussian(x, sigma=sigma, mode="nearest", preserve_range=True)

    bi = [blur(x) for x in imgs]
    bt = [blur(x) for x in tgts]
    # SSIM of every (render j, target k) pair: diagonal = ssim, off-diagonal = ghosting candidates.
    s = np.array(
        [[structural_similarity(bi[j], bt[k], data_range=1.0) for k in range(m)] for j in range(m)]
    )
    psnr = []
    for j in range(m):
        if np.array_equal(bi[j], bt[j]):
            psnr.append(float("inf"))  # skimage would divide by zero
        else:
            psnr.append(float(peak_signal_noise_ratio(bt[j], bi[j], data_range=1.0)))
    ghosting, ghosting_from = [], []
    for j in range(m):
        if m == 1:
            ghosting.append(float("nan"))
            ghosting_from.append(-1)
            continue
        others = [k for k in range(m) if k != j]
        k = others[int(np.argmax(s[j, others]))]
        ghosting.append(float(s[j, k]))
        ghosting_from.append(int(k))
    return {
        "ssim": [float(s[j, j]) for j in range(m)],
        "psnr": psnr,
        "ghosting": ghosting,
        "ghosting_from": ghosting_from,
    }


#: Local binary patterns of `texture_distance`: 8 neighbours at radius 1 px, rotation-invariant
#: "uniform" codes (10 bins).
LBP_POINTS, LBP_RADIUS = 8, 1.0


def texture_distance(display_images, targets, clip: bool = True) -> list[float]:
    """Per-view distance between the local texture statistics of a render and its target.

    A measure of the *look* of the scratches that neither loss optimises (so it can judge
    ``E_g`` without being ``E_g``): the chi-square distance
    ``0.5 sum_b (h_b - t_b)^2 / (h_b + t_b)`` between the normalised histograms of the
    rotation-invariant uniform local binary patterns (``skimage.feature.local_binary_pattern``,
    ``P = 8`` neighbours at ``R = 1`` px, 10 codes) of the unblurred display image and of the
    target, both quantised to 8 bits. It is 0 for equal statistics and at most 1; it compares
    micro-texture (edges, lines, flat regions, noise) independently of where it is, which is
    what a Gram loss is meant to match.

    **Arguments:** `display_images`, `targets`: ``(M, H, W)`` display values (as
    `image_metrics`); `clip`: clip the renders to ``[0, 1]`` first.

    **Returns:** ``M`` floats (lower is better). **Raises:** `InputError`, one line, as
    `image_metrics` (shapes, values, targets outside ``[0, 1]``, images below 7x7 px).
    """
    from skimage.feature import local_binary_pattern

    imgs, tgts = _as_pair(display_images, targets)
    if clip:
        imgs = np.clip(imgs, 0.0, 1.0)
    nb = LBP_POINTS + 2

    def hist(x):
        q = np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)
        code = local_binary_pattern(q, LBP_POINTS, LBP_RADIUS, method="uniform")
        h = np.bincount(code.astype(np.int64).ravel(), minlength=nb).astype(np.float64)
        return h / h.sum()

    out = []
    for a, b in zip(imgs, tgts):
        ha, hb = hist(a), hist(b)
        s = ha + hb
        out.append(float(0.5 * np.sum(np.where(s > 0, (ha - hb) ** 2 / np.where(s > 0, s, 1), 0))))
    return out
