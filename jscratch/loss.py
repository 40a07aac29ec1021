"""Image losses for scratch design (docs/model.md §6, paper section 3.4).

All losses compare a stack of rendered display images with a stack of targets, both display values
(nominally in ``[0, 1]``) of shape ``(M, H, W)``: ``M`` views, ``H`` rows (row 0 at the top), ``W``
columns. Computation follows the dtype of ``render`` (``target`` is cast to it), so float32 is the
working precision for users and float64 for references. Every function here is pure, jittable and
differentiable in ``render``.

- ``perceptual_loss``: ``E_p = sum_j mean((g * (I_j - T_j))^2)`` with ``g`` the 3x3 Gaussian of
  ``gaussian_kernel3`` (sigma ``BLUR_SIGMA`` = 1 px, edge-replicate boundary).
- ``l2_loss``: plain ``sum_j mean((I_j - T_j)^2)`` for ablations.
- ``gram_loss``: ``E_g = sum_j mean_l ||Gram(phi_l(I_j)) - Gram(phi_l(T_j))||_F^2`` with Gatys-style
  Gram matrices normalised by channels times positions; ``phi`` is ``FilterBank`` (weight-free,
  default) or ``VGG19Features`` (from a local weights file, ``load_vgg19``), both of
  ``jscratch.features`` and importable from here too.
- ``ghost_loss``: ``E_x``, cross-view ghosting beyond a baseline (``jscratch.ssim``).
- ``total_loss``, ``LossConfig``, ``make_loss``: ``lambda_p E_p + lambda_g E_g + w_x E_x``
  (``w_x`` from ``lambda_x`` by ``ghost_weight_factor``).

The filter bank's design is in ``FilterBank``, the VGG format in ``load_vgg19``, the calibration
of ``LAMBDA_G`` next to it. NaN detection is the optimiser's job: these functions propagate NaN.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jscratch.compile_options import few_calls_jit
from jscratch.errors import InputError, real_number, shown
from jscratch.features import (VGG19_LAYERS, VGG19_TAPS, Features, FilterBank, VGG19Features,
                               gram, load_vgg19, separable3)
from jscratch.options import KnownFields, option
from jscratch.ssim import ssim_mean, ssim_moments

__all__ = [
    "BLUR_SIGMA", "GHOST_EP_REF", "GHOST_SCALES", "LAMBDA_G", "LOSS_KINDS", "VGG19_LAYERS",
    "VGG19_TAPS", "BoundLoss", "FilterBank", "Loss", "LossConfig", "VGG19Features", "blur3",
    "calibrate_lambda_g", "gaussian_kernel3", "gram", "cross_ssim", "ghost_loss",
    "ghost_weight_factor", "gram_loss", "l2_loss", "load_vgg19", "make_loss", "perceptual_loss",
    "total_loss",
]

#: Standard deviation (pixels) of the 3x3 Gaussian ``g`` in ``E_p``. With sigma = 1 px the 1D
#: weights are ``[e, 1, e] / (1 + 2e)``, ``e = exp(-1/2)``, i.e. ``[0.2741, 0.4519, 0.2741]``:
#: a genuine low-pass over the whole 3x3 support (a smaller sigma would make ``g`` nearly a delta
#: and ``E_p`` nearly plain L2); it also matches the sigma of the metrics of docs/model.md §7.
BLUR_SIGMA = 1.0

#: Default ``lambda_g`` for the default ``FilterBank`` features (with ``lambda_p = 1``), measured
#: (benchmarks/RESULTS.md): ``E_g`` trades SSIM for texture (``metrics.texture_distance``)
#: monotonically; at 256 px / 20k free grooves 0 gives SSIM 0.801 / texture 0.246, **20 gives
#: 0.815 / 0.226**, 200 gives 0.755 / 0.202. Not valid for VGG features (``calibrate_lambda_g``).
LAMBDA_G = 20.0

#: Default ``lambda_x``: the weight of ``E_x`` against a zero baseline (the raw cross-view SSIM,
#: the ghosting of docs/model.md §7); 0.01 cut ghosting further but lost much SSIM.
LAMBDA_X = 1e-3

#: ``LossConfig.ghost_scale`` ``"relative"`` / ``"squared"``: the per-view ``E_p`` at and above
#: which ``E_x`` has its full weight (the default design's, 3 views / 20,000 scratches, never goes
#: below it).
GHOST_EP_REF = 2.5e-3

#: Allowed ``LossConfig.kind`` values.
LOSS_KINDS = ("l2", "perceptual", "perceptual+gram")
#: Allowed ``LossConfig.ghost_scale`` values (see `ghost_weight_factor`).
GHOST_SCALES = ("relative", "squared", "fixed")


def _check_images(render, target, name: str = "render") -> tuple[Array, Array]:
    """Validate a ``(render, target)`` pair; returns them as arrays in ``render``'s dtype.

    ``name`` is what the first argument is called in error messages.
    """
    render = jnp.asarray(render)
    target = jnp.asarray(target)
    if not jnp.issubdtype(render.dtype, jnp.floating):
        raise InputError(f"{name} must be a floating-point array, got dtype {render.dtype}")
    if render.ndim != 3:
        raise InputError(
            f"{name} must have shape (M, H, W) (views, rows, columns), got shape {render.shape}"
        )
    if target.shape != render.shape:
        raise InputError(
            f"target must have the same shape as {name} {render.shape}, got {target.shape}"
        )
    if not jnp.issubdtype(target.dtype, jnp.floating):
        raise InputError(
            f"target must be floating-point display values in [0, 1], got dtype {target.dtype}"
        )
    return render, target.astype(render.dtype)


# ----------------------------------------------------------------------------------------------
# The perceptual loss E_p


def _gauss1(sigma: float) -> tuple[float, float, float]:
    """1D weights ``[e, 1, e] / (1 + 2e)``, ``e = exp(-1 / (2 sigma^2))`` (Python floats)."""
    value = real_number(sigma)
    if value is None or not (math.isfinite(value) and value > 0):
        raise InputError(f"sigma must be a finite positive number of pixels, got {sigma!r}")
    sigma = value
    e = math.exp(-1.0 / (2.0 * sigma * sigma))
    return (e / (1.0 + 2.0 * e), 1.0 / (1.0 + 2.0 * e), e / (1.0 + 2.0 * e))


def gaussian_kernel3(sigma: float = BLUR_SIGMA, dtype=None) -> Array:
    """The normalised 3x3 Gaussian kernel ``g`` of ``E_p``.

    ``g[a, b] = k[a] k[b]`` with ``k = [e, 1, e] / (1 + 2e)``, ``e = exp(-1 / (2 sigma^2))``: the
    Gaussian sampled at offsets ``-1, 0, 1`` px and truncated to 3x3, renormalised to sum 1.

    **Arguments:**

    - `sigma`: standard deviation in pixels, ``> 0``. Default ``BLUR_SIGMA`` (1 px).
    - `dtype`: floating dtype of the result (default: JAX's default float).

    **Returns:** ``(3, 3)`` array summing to 1.
    """
    k = np.array(_gauss1(sigma))
    return jnp.asarray(np.outer(k, k), dtype=dtype)


def blur3(images: Float[Array, "... H W"], sigma: float = BLUR_SIGMA) -> Float[Array, "... H W"]:
    """Convolve with the 3x3 Gaussian ``gaussian_kernel3(sigma)`` (``g`` of ``E_p``).

    Boundary: edge replication (numpy/jax ``mode="edge"``, scipy ``mode="nearest"``), so a
    constant image stays constant and every pixel, corners included, is constrained. The output has
    the input's shape and dtype.

    **Arguments:**

    - `images`: ``(..., H, W)`` floating array.
    - `sigma`: Gaussian standard deviation in pixels.

    **Returns:** ``(..., H, W)`` blurred images.
    """
    k = _gauss1(sigma)
    return separable3(images, k, k)


def perceptual_loss(render: Float[Array, "M H W"], target: Float[Array, "M H W"]) -> Array:
    """Perceptual loss ``E_p = sum_j mean_pixels((g * (I_j - T_j))^2)`` (docs/model.md §6, Eq. 12).

    ``g`` is ``gaussian_kernel3()`` (sigma 1 px, edge-replicate boundary, see ``blur3``). A
    constant offset ``c`` between render and target gives exactly ``E_p = M c^2``.

    **Arguments:**

    - `render`: ``(M, H, W)`` rendered display values.
    - `target`: ``(M, H, W)`` target display values (cast to ``render``'s dtype).

    **Returns:** Scalar in ``render``'s dtype.
    """
    render, target = _check_images(render, target)
    d = blur3(render - target)
    return jnp.sum(jnp.mean(d * d, axis=(-2, -1)))


def cross_ssim(render: Float[Array, "M H W"], target: Float[Array, "M H W"]) -> Array:
    """``(M, M)``: ``S[j, k] = ssim_mean(g * I_j, g * T_k)`` (``g``: ``blur3``)."""
    bi, bt = blur3(render), blur3(target)
    return ssim_mean(bi[:, None], bt[None, :])


def ghost_loss(render: Float[Array, "M H W"], target: Float[Array, "M H W"],
               baseline: Float[Array, "M M"] | None = None) -> Array:
    """Cross-view ghosting penalty ``E_x = sum_j sum_{k != j} max(0, S[j, k] - B[j, k])``.

    ``S = cross_ssim(render, target)``: how much view ``j``'s render resembles view ``k``'s target
    (the ghosting of docs/model.md §7, up to the 3x3 truncation of ``g``); ``B = cross_ssim(target,
    target)`` (default): the resemblance a perfect render would have, so the term only penalises
    ghosting *beyond* what the targets share and is 0 at the optimum of ``E_p``.

    **Arguments:** `render`, `target`: ``(M, H, W)``; `baseline`: ``B`` if precomputed (zeros:
    the raw cross-view SSIM is penalised, ``LossConfig.ghost_baseline = "zero"``).

    **Returns:** scalar (0 for ``M = 1``). **Raises:** `InputError`, one line, for a `baseline`
    that is not ``(M, M)`` (shapes are static: also under jit).
    """
    render, target = _check_images(render, target)
    if baseline is not None:
        m, shape = render.shape[0], jnp.shape(baseline)
        if shape != (m, m):
            raise InputError(f"ghost_loss: `baseline` must have shape (M, M) = ({m}, {m}), one "
                             f"value per pair of views; got {shape}")
        baseline = jnp.asarray(baseline).astype(render.dtype)
    return _ghost(render, *_ghost_target(target, baseline))


def _ghost_target(target, baseline=None) -> tuple[Array, Array, Array, Array]:
    """What ``E_x`` needs of the target alone: ``g * T``, its ``ssim_moments`` and ``B``
    (``cross_ssim(target, target)`` unless given)."""
    bt = blur3(target)
    return (bt, *ssim_moments(bt), cross_ssim(target, target) if baseline is None else baseline)


@few_calls_jit(static_argnums=1)
def _bind_ghost(target, zero: bool) -> tuple[Array, Array, Array, Array]:
    """`Loss.bind`'s `_ghost_target`, in one compiled call; ``zero``: a zero baseline."""
    m = target.shape[0]
    return _ghost_target(target, jnp.zeros((m, m), target.dtype) if zero else None)


def _ghost(render, bt, my, vy, baseline) -> Array:
    """``E_x`` of ``render`` from `_ghost_target`'s arrays (in ``render``'s dtype)."""
    j, k = np.nonzero(~np.eye(render.shape[0], dtype=bool))  # only the pairs j != k
    br = blur3(render)
    mx, vx = ssim_moments(br)  # once per view, not per pair
    s = ssim_mean(br[j], bt[k], (mx[j], vx[j]), (my[k], vy[k]))
    return jnp.sum(jax.nn.relu(s - baseline[j, k]))


def ghost_weight_factor(rule: str, e_p, m: int):
    """The factor on ``lambda_x`` (a scalar, no gradient): 1 for ``"fixed"``; ``s * 2 / (M - 1)``
    with ``s = min(1, E_p / (M GHOST_EP_REF))`` for ``"relative"`` and ``s^2`` for ``"squared"``
    (the default). ``E_x`` stays near the targets' own cross-view SSIM while ``E_p`` falls as the
    render approaches its target (more scratches), so a fixed weight lets ghosting take a growing
    share of the loss and costs picture; ``E_x`` sums ``M - 1`` view pairs per view, ``E_p`` one.
    Below the reference ``"relative"`` keeps ``E_x``'s share of the loss what it is at the
    reference, ``"squared"`` lets it fall with ``E_p`` (docs/model.md §6)."""
    if rule == "fixed" or m < 2:
        return 1.0
    share = jnp.minimum(1.0, jax.lax.stop_gradient(e_p) / (m * GHOST_EP_REF))
    if rule == "squared":
        share = share * share
    return share * (2.0 / (m - 1))


def l2_loss(render: Float[Array, "M H W"], target: Float[Array, "M H W"]) -> Array:
    """Plain squared L2 ``sum_j mean_pixels((I_j - T_j)^2)`` (the paper's Fig. 17 baseline).

    **Arguments:**

    - `render`, `target`: ``(M, H, W)`` display values.

    **Returns:** Scalar in ``render``'s dtype.
    """
    render, target = _check_images(render, target)
    d = render - target
    return jnp.sum(jnp.mean(d * d, axis=(-2, -1)))


# ----------------------------------------------------------------------------------------------
# The Gram loss E_g


def _grams(features: Features, images: Array) -> list[Array]:
    return [gram(f) for f in features(images)]


def _gram_distance(grams_i: Sequence[Array], grams_t: Sequence[Array]) -> Array:
    """``sum_j mean_l ||G_l(I_j) - G_l(T_j)||_F^2`` from precomputed ``(M, C, C)`` Grams."""
    per_layer = [jnp.sum((gi - gt) ** 2, axis=(-2, -1)) for gi, gt in zip(grams_i, grams_t)]
    return jnp.sum(jnp.mean(jnp.stack(per_layer), axis=0))


def gram_loss(
    render: Float[Array, "M H W"],
    target: Float[Array, "M H W"],
    features: Features | None = None,
) -> Array:
    """Gram loss ``E_g = sum_j mean_l ||Gram(phi_l(I_j)) - Gram(phi_l(T_j))||_F^2`` (Eq. 13).

    ``Gram`` is ``gram`` (normalised by channels times positions); the layers ``l`` (filter-bank
    scales or VGG taps) are averaged with equal weights (Gatys et al.'s ``w_l = 1/L``).

    **Arguments:**

    - `render`, `target`: ``(M, H, W)`` display values.
    - `features`: ``phi``, a callable ``(M, H, W) -> [(M, C_l, H_l, W_l), ...]``; default
      ``FilterBank()``.

    **Returns:** Scalar in ``render``'s dtype.
    """
    render, target = _check_images(render, target)
    features = FilterBank() if features is None else features
    return _gram_distance(_grams(features, render), _grams(features, target))


def total_loss(render: Float[Array, "M H W"], target: Float[Array, "M H W"], lambda_p: float = 1.0,
               lambda_g: float = LAMBDA_G, features: Features | None = None) -> Array:
    """``E = lambda_p E_p + lambda_g E_g`` (docs/model.md §6, Eq. 14).

    **Arguments:**

    - `render`, `target`: ``(M, H, W)`` display values.
    - `lambda_p`: weight of ``perceptual_loss``.
    - `lambda_g`: weight of ``gram_loss``; default ``LAMBDA_G`` is calibrated for the default
      ``FilterBank``; VGG features need their own value.
    - `features`: ``phi`` of ``gram_loss``; default ``FilterBank()``.

    **Returns:** Scalar in ``render``'s dtype.
    """
    e = lambda_p * perceptual_loss(render, target)
    if not (isinstance(lambda_g, (int, float)) and lambda_g == 0):
        e = e + lambda_g * gram_loss(render, target, features)
    return e


def calibrate_lambda_g(
    render: Float[ArrayLike, "M H W"],
    target: Float[ArrayLike, "M H W"],
    features: Features | None = None,
    ratio: float = 0.25,
) -> float:
    """The ``lambda_g`` for which ``lambda_g E_g = ratio * E_p`` on the given images (host side).

    This is how ``LAMBDA_G`` was chosen for the filter bank; use it with a
    representative render (e.g. a scratch design's current render) to pick ``lambda_g`` for VGG
    weights.

    **Arguments:**

    - `render`, `target`: ``(M, H, W)`` display values.
    - `features`: ``phi``; default ``FilterBank()``.
    - `ratio`: wanted ``lambda_g E_g / E_p`` (``lambda_p = 1``), positive.

    **Returns:** ``ratio * E_p / E_g`` as a Python float.
    """
    given, ratio = ratio, real_number(ratio)
    if ratio is None or not (math.isfinite(ratio) and ratio > 0):
        raise InputError(f"calibrate_lambda_g: `ratio` must be a finite number > 0, got "
                         f"{shown(given)}")
    ep = float(perceptual_loss(render, target))
    eg = float(gram_loss(render, target, features))
    if not (math.isfinite(ep) and math.isfinite(eg)) or eg <= 0:
        raise InputError(f"calibrate_lambda_g: cannot calibrate: E_p = {ep}, E_g = {eg} (need "
                         f"finite, E_g > 0)")
    return ratio * ep / eg


# ----------------------------------------------------------------------------------------------
# Configuration


@dataclasses.dataclass(frozen=True)
class LossConfig(KnownFields):
    """Which loss the optimiser minimises (JSON-friendly: ``dataclasses.asdict``).

    **Fields:**

    - `kind`: ``"l2"`` (``lambda_p * l2_loss``), ``"perceptual"`` (``lambda_p E_p``) or
      ``"perceptual+gram"`` (``lambda_p E_p + lambda_g E_g``, default).
    - `lambda_p`: weight of the pixel term, ``>= 0``; default 1 (paper).
    - `lambda_g`: weight of ``E_g``, ``>= 0``. ``None`` (default) means ``LAMBDA_G`` for the filter
      bank; with ``vgg_weights`` it must be given (``calibrate_lambda_g`` helps).
    - `vgg_weights`: path of a local VGG-19 ``.npz`` (``load_vgg19``); ``None`` uses
      ``FilterBank``.
    - `lambda_x`: weight of the cross-view ghosting term ``E_x`` (``ghost_loss``), ``>= 0``;
      added to any kind (for ``"l2"`` the weight rule reads the L2 term where it reads ``E_p``);
      default `LAMBDA_X`; 0 leaves it out.
    - `ghost_scale`: ``"squared"`` (default), ``"relative"`` or ``"fixed"``: the rule for
      ``E_x``'s weight (`ghost_weight_factor`).
    - `ghost_baseline`: ``"zero"`` (default): ``E_x`` is the raw cross-view SSIM, the ghosting of
      docs/model.md §7 itself; ``"targets"``: only the resemblance beyond the targets' own.

    These are the design's defaults too (`jscratch.design.DesignConfig.loss`); each field's help
    and command-line flag are declared with it (`jscratch.options`).
    """

    kind: str = option("perceptual+gram", "loss: squared L2, E_p, or E_p + lambda_g E_g",
                       flag="--loss", choices=LOSS_KINDS)
    lambda_p: float = option(1.0, "weight of E_p (or of the L2 loss)")
    lambda_g: float | None = option(None, f"weight of E_g (none: {LAMBDA_G:g} for the filter bank; "
                                    "required with --vgg-weights)")
    vgg_weights: str | None = option(None, "local VGG-19 .npz for E_g (scripts/convert_vgg19.py)",
                                     metavar="FILE")
    lambda_x: float = option(LAMBDA_X, "weight of the cross-view ghosting term E_x (0: off)")
    ghost_baseline: str = option("zero", "E_x penalises all of the cross-view SSIM (zero: the "
                                 "ghosting itself) or only what exceeds the targets' own (targets)",
                                 choices=("targets", "zero"))
    ghost_scale: str = option("squared", "E_x's weight: lambda_x (fixed), or lambda_x times "
                              "min(1, E_p per view / GHOST_EP_REF) (relative) or its square "
                              "(squared), times 2 / (views - 1)", choices=GHOST_SCALES)

    def __post_init__(self):
        if self.kind not in LOSS_KINDS:
            raise InputError(f"LossConfig.kind must be one of {LOSS_KINDS}, got {self.kind!r}")
        if self.ghost_scale not in GHOST_SCALES:
            raise InputError(f"LossConfig.ghost_scale must be one of {GHOST_SCALES}, got {self.ghost_scale!r}")
        if self.ghost_baseline not in ("targets", "zero"):
            raise InputError(f"LossConfig.ghost_baseline must be 'targets' or 'zero', got {self.ghost_baseline!r}")
        for name in ("lambda_p", "lambda_g", "lambda_x"):
            v = getattr(self, name)
            if v is None and name == "lambda_g":
                continue
            ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
            if not (ok and math.isfinite(v) and v >= 0):
                raise InputError(f"LossConfig.{name} must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.vgg_weights is not None:
            if not isinstance(self.vgg_weights, (str, os.PathLike)):
                raise InputError(f"LossConfig.vgg_weights must be None or a file path, got "
                                 f"{self.vgg_weights!r}")
            object.__setattr__(self, "vgg_weights", os.fspath(self.vgg_weights))
            if self.kind == "perceptual+gram" and self.lambda_g is None:
                raise InputError(
                    "LossConfig.lambda_g must be given with vgg_weights: LAMBDA_G is calibrated for the "
                    "filter bank only (see jscratch.loss.calibrate_lambda_g)"
                )


class BoundLoss(eqx.Module):
    """A ``Loss`` with the target, its Gram matrices and what ``E_x`` needs of it precomputed:
    ``__call__(render)``.

    Saves the target's feature pass, blur and SSIM moments at every optimisation step.
    """

    loss: Loss
    target: Float[Array, "M H W"]
    target_grams: tuple[Array, ...] | None
    # ``g * T``, its local means and variances (`jscratch.ssim.ssim_moments`), the baseline ``B``
    target_ghost: tuple[Array, Array, Array, Array] | None = None

    def __call__(self, render: Float[Array, "M H W"]) -> Array:
        """Total loss of ``render`` against the bound target (scalar, ``render``'s dtype)."""
        return self.terms(render)["total"]

    def terms(self, render: Float[Array, "M H W"]) -> dict[str, Array]:
        """The terms of the loss (see ``Loss.terms``)."""
        return self.loss._terms(render, self.target, self.target_grams, self.target_ghost)


class Loss(eqx.Module):
    """The configured loss ``render, target -> scalar`` (build with ``make_loss``).

    **Fields:**

    - `kind`: as ``LossConfig.kind`` (static).
    - `lambda_p`, `lambda_g`: weights (Python floats).
    - `features`: ``phi`` of ``E_g`` (``FilterBank`` or ``VGG19Features``), ``None`` unless
      ``kind == "perceptual+gram"``.
    """

    kind: str = eqx.field(static=True)
    lambda_p: float = eqx.field(static=True)
    lambda_g: float = eqx.field(static=True)
    features: FilterBank | VGG19Features | None
    lambda_x: float = eqx.field(static=True, default=0.0)
    ghost_baseline: str = eqx.field(static=True, default="targets")
    ghost_scale: str = eqx.field(static=True, default="fixed")

    def __call__(self, render: Float[Array, "M H W"], target: Float[Array, "M H W"]) -> Array:
        """Total loss (scalar in ``render``'s dtype)."""
        return self._combine(render, target, None)

    def terms(
        self, render: Float[Array, "M H W"], target: Float[Array, "M H W"]
    ) -> dict[str, Array]:
        """The loss and its unweighted terms: ``{"total", "l2"}`` for ``kind == "l2"``, else
        ``{"total", "E_p"}`` plus ``"E_g"`` for ``"perceptual+gram"``; plus ``"E_x"`` when
        ``lambda_x > 0``."""
        return self._terms(render, target, None)

    def bind(self, target: Float[ArrayLike, "M H W"]) -> BoundLoss:
        """Precompute everything that depends on ``target`` alone.

        **Arguments:**

        - `target`: ``(M, H, W)`` floating display values in ``[0, 1]``; kept in their own
          dtype (cast to the render's dtype when the loss is evaluated). `InputError`, one line,
          for other shapes or values.

        **Returns:** A ``BoundLoss``; ``bound(render) == loss(render, target)`` up to rounding.
        """
        target, _ = _check_images(target, target, name="target")
        if not isinstance(target, jax.core.Tracer):  # (host side: concrete values checked)
            t = np.asarray(target)
            if not (np.all(np.isfinite(t)) and t.min() >= 0.0 and t.max() <= 1.0):
                raise InputError(f"bind: target must be finite display values in [0, 1], got "
                                 f"range [{np.nanmin(t):g}, {np.nanmax(t):g}]"
                                 + ("" if np.all(np.isfinite(t)) else " with non-finite values"))
        grams = ghost = None
        if self.kind == "perceptual+gram":
            grams = _target_grams(self.features, target)
        if self.lambda_x > 0:
            ghost = _bind_ghost(target, self.ghost_baseline == "zero")
        return BoundLoss(self, target, grams, ghost)

    def _terms(self, render, target, target_grams, target_ghost=None) -> dict[str, Array]:
        render, target = _check_images(render, target)
        if self.kind == "l2":
            ep = l2_loss(render, target)  # (the image error of E_x's weight rule, as E_p below)
            out = {"total": self.lambda_p * ep, "l2": ep}
        else:
            ep = perceptual_loss(render, target)
            out = {"total": self.lambda_p * ep, "E_p": ep}
        if self.kind == "perceptual+gram":
            if target_grams is None:
                target_grams = _grams(self.features, target)
            else:
                target_grams = [g.astype(render.dtype) for g in target_grams]
            eg = _gram_distance(_grams(self.features, render), target_grams)
            out["E_g"] = eg
            out["total"] = out["total"] + self.lambda_g * eg
        if self.lambda_x > 0:
            m = render.shape[0]
            if target_ghost is None:
                zero = jnp.zeros((m, m), render.dtype) if self.ghost_baseline == "zero" else None
                target_ghost = _ghost_target(target, zero)
            ex = _ghost(render, *(a.astype(render.dtype) for a in target_ghost))
            out["E_x"] = ex
            wx = self.lambda_x * ghost_weight_factor(self.ghost_scale, ep, m)
            out["total"] = out["total"] + wx * ex
        return out

    def _combine(self, render, target, target_grams) -> Array:
        return self._terms(render, target, target_grams)["total"]


@few_calls_jit(filter=True)
def _target_grams(features, target) -> tuple[Array, ...]:
    """`Loss.bind`'s Gram matrices, in one compiled call (not op by op)."""
    return tuple(_grams(features, target))


def make_loss(config: LossConfig | None = None) -> Loss:
    """Build the loss callable ``(render (M, H, W), target (M, H, W)) -> scalar`` of a config.

    Loads VGG-19 weights from ``config.vgg_weights`` when given (``load_vgg19``).

    **Arguments:**

    - `config`: a ``LossConfig``; default ``LossConfig()`` (``E_p + LAMBDA_G E_g + LAMBDA_X E_x``,
      filter bank, the design's loss).

    **Returns:** A ``Loss`` module (jittable; ``loss.bind(target)`` precomputes the target's Grams).
    """
    config = LossConfig() if config is None else config
    if not isinstance(config, LossConfig):
        raise InputError(f"config must be a LossConfig, got {type(config).__name__}")
    features = None
    if config.kind == "perceptual+gram":
        features = FilterBank() if config.vgg_weights is None else load_vgg19(config.vgg_weights)
    lambda_g = LAMBDA_G if config.lambda_g is None else float(config.lambda_g)
    return Loss(config.kind, float(config.lambda_p), lambda_g, features, float(config.lambda_x),
                config.ghost_baseline, config.ghost_scale)
