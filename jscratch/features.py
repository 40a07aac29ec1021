"""Feature maps and Gram matrices for the texture term ``E_g`` of ``jscratch.loss``
(docs/model.md §6): ``gram``, the weight-free ``FilterBank`` (default ``phi``) and ``VGG19Features``
read from a local weights file by ``load_vgg19``. Also ``separable3``, the separable 3x3 stencil of
edge-padded images that the filter bank and ``jscratch.loss.blur3`` are built from. Pure jax,
jittable, differentiable in the images.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jscratch.errors import DesignFileError, InputError, error_line

__all__ = ["VGG19_LAYERS", "VGG19_TAPS", "Features", "FilterBank", "VGG19Features", "gram",
           "load_vgg19", "separable3"]

#: ``phi`` of ``E_g``: ``(M, H, W)`` images to a list of ``(M, C_l, H_l, W_l)`` feature maps.
Features = Callable[[Array], Sequence[Array]]


def _pad1(x: Array) -> Array:
    """Edge-replicate padding by one pixel on the last two axes."""
    pad = [(0, 0)] * (x.ndim - 2) + [(1, 1), (1, 1)]
    return jnp.pad(x, pad, mode="edge")


def _cols(p: Array, a: float, b: float, c: float) -> Array:
    """3-tap stencil ``a x[c-1] + b x[c] + c x[c+1]`` along the last axis (drops 2 columns)."""
    out = a * p[..., :, :-2] if a else 0.0
    if b:
        out = out + b * p[..., :, 1:-1]
    if c:
        out = out + c * p[..., :, 2:]
    return out


def _rows(p: Array, a: float, b: float, c: float) -> Array:
    """3-tap stencil along the second-to-last axis (drops 2 rows)."""
    out = a * p[..., :-2, :] if a else 0.0
    if b:
        out = out + b * p[..., 1:-1, :]
    if c:
        out = out + c * p[..., 2:, :]
    return out


def separable3(images: Float[Array, "... H W"], rows: Sequence[float],
               cols: Sequence[float]) -> Float[Array, "... H W"]:
    """The 3x3 cross-correlation with ``np.outer(rows, cols)`` of edge-replicated ``images``:
    the 3-tap stencil ``cols`` along each row, then ``rows`` along each column (Python floats;
    zero taps are skipped). Same shape and dtype as ``images``."""
    return _rows(_cols(_pad1(images), *cols), *rows)


def gram(features: Float[Array, "... C H W"]) -> Float[Array, "... C C"]:
    """Gatys-style normalised Gram matrix ``G = F F^T / (C N)``.

    ``F`` is the feature map flattened to ``(C, N)``, ``N = H W`` positions. Dividing by ``N``
    makes ``G`` a mean over positions (independent of image size); dividing also by ``C`` makes
    ``||G_I - G_T||_F^2``, a sum over ``C^2`` entries, independent of the channel count.

    **Arguments:**

    - `features`: ``(..., C, H, W)`` feature maps.

    **Returns:** ``(..., C, C)`` symmetric matrices.
    """
    c, h, w = features.shape[-3:]
    return _gram(features.reshape(*features.shape[:-3], c, h * w)) / (c * h * w)


@jax.custom_jvp
def _gram(f: Array) -> Array:
    """``F F^T`` of ``(..., C, N)`` features."""
    return jnp.einsum("...an,...bn->...ab", f, f)


@_gram.defjvp
def _gram_jvp(primals, tangents):
    # d(F F^T) = A + A^T with A = dF F^T: reverse mode then transposes one product, (S + S^T) F
    # for a cotangent S, instead of the two products (one with a transposed operand) that
    # differentiating the einsum gives.
    (f,), (df,) = primals, tangents
    a = jnp.einsum("...an,...bn->...ab", df, f)
    return _gram(f), a + jnp.swapaxes(a, -1, -2)


_R = math.sqrt(0.5)
# Unit directions e_k = (cos, sin)(45 k degrees) in the displayed image plane (x = column to the
# right, y = up = decreasing row). Written out so that 90-degree rotations permute channels exactly.
_COS8 = (1.0, _R, 0.0, -_R, -1.0, -_R, 0.0, _R)
_SIN8 = (0.0, _R, 1.0, _R, 0.0, -_R, -1.0, -_R)


def _avg_pool2(x: Array) -> Array:
    """2x2 average pooling on the last two axes; an odd last row/column is dropped."""
    h, w = x.shape[-2] // 2, x.shape[-1] // 2
    x = x[..., : 2 * h, : 2 * w].reshape(*x.shape[:-2], h, 2, w, 2)
    return x.mean(axis=(-3, -1))


def _combine(coefs: Sequence[float], maps: Sequence[Array]) -> Array:
    """``sum_i coefs[i] maps[i]`` without the zero terms (``1.0 * m`` is ``m``)."""
    out = None
    for c, m in zip(coefs, maps):
        if c:
            term = m if c == 1.0 else (-m if c == -1.0 else c * m)
            out = term if out is None else out + term
    return out


# The 1D stencils of `FilterBank`: smoothing, central difference, second difference.
_S3, _D3, _DD3 = (0.25, 0.5, 0.25), (-0.5, 0.0, 0.5), (1.0, -2.0, 1.0)


#: `FilterBank.level` computes a level of more pixels than this by `_stencil_maps`.
_STENCIL_PIXELS = 128 * 128


def _stencil_maps(x: Array) -> tuple[list[Array], list[Array]]:
    """``[D1_0..3], [D2_0..3]`` of `FilterBank` as combinations of the 5 separable stencils
    ``Gx, Gy, Gxx, Gyy, Gxy``: each a 3-tap column stencil then a 3-tap row stencil of the
    edge-padded level (shifted slices, which XLA fuses)."""
    p = _pad1(x)
    cs, cd, cdd = _cols(p, *_S3), _cols(p, *_D3), _cols(p, *_DD3)  # (M, H + 2, W)
    gx, gy = _rows(cd, *_S3), -_rows(cs, *_D3)  # y points up: rows grow downwards
    gxx, gyy, gxy = _rows(cdd, *_S3), _rows(cs, *_DD3), -_rows(cd, *_D3)
    d1, d2 = [], []
    for c, s in zip(_COS8[:4], _SIN8[:4]):
        d1.append(_combine((c, s), (gx, gy)))
        d2.append(_combine((c * c, 2.0 * c * s, s * s), (gxx, gxy, gyy)))
    return d1, d2


def _level_kernels() -> np.ndarray:
    """``(8, 1, 3, 3)``: the 3x3 cross-correlation kernels of ``D1_0..3, D2_0..3`` (``K[a, b]``
    weighs the padded pixel at row offset ``a - 1``, column offset ``b - 1``), the outer products
    of `_stencil_maps`' stencils."""
    s, d, dd = np.array(_S3), np.array(_D3), np.array(_DD3)
    gx, gy = np.outer(s, d), -np.outer(d, s)
    gxx, gyy, gxy = np.outer(s, dd), np.outer(dd, s), -np.outer(d, d)
    cs = list(zip(_COS8[:4], _SIN8[:4]))
    ks = [c * gx + s_ * gy for c, s_ in cs] + [c * c * gxx + 2.0 * c * s_ * gxy + s_ * s_ * gyy
                                              for c, s_ in cs]
    return np.stack(ks)[:, None]


_LEVEL_KERNELS = _level_kernels()


def _conv_maps(x: Array) -> tuple[list[Array], list[Array]]:
    """`_stencil_maps` as one 3x3 convolution (`_LEVEL_KERNELS`) of the edge-padded level."""
    kernels = jnp.asarray(_LEVEL_KERNELS, x.dtype)
    y = jax.lax.conv_general_dilated(_pad1(x)[:, None], kernels, (1, 1), "VALID",
                                     dimension_numbers=("NCHW", "OIHW", "NCHW"))
    return [y[:, i] for i in range(4)], [y[:, i] for i in range(4, 8)]


class FilterBank(eqx.Module):
    """Weight-free multi-scale oriented filter bank, the default ``phi`` of ``E_g``.

    Pyramid: level 0 is the image; level ``s + 1`` is the 2x2 average pool of level ``s`` (an odd
    last row/column is dropped). At each level ``L`` (edge-replicate padding, 3x3 stencils, ``s =
    [1, 2, 1]/4`` smoothing across the derivative direction):

    - ``Gx = d_col (x) s_row``, ``Gy = -d_row (x) s_col`` (``d = [-1, 0, 1]/2``; ``y`` points up);
    - ``Gxx = dd_col (x) s_row``, ``Gyy = dd_row (x) s_col`` (``dd = [1, -2, 1]``),
      ``Gxy = -d_col (x) d_row``;
    - ``D1_k = cos(t_k) Gx + sin(t_k) Gy`` for ``t_k = 45 k`` degrees, ``k = 0..7`` (steered first
      derivative along direction ``t_k``);
    - ``D2_k = cos^2 Gxx + 2 cos sin Gxy + sin^2 Gyy`` at ``t_k``, ``k = 0..3`` (steered second
      derivative across lines that run at ``t_k + 90`` degrees).

    The 17 channels per level, in order: ``L`` (local mean intensity), ``relu(D1_k)`` for
    ``k = 0..7`` (half-wave rectified edges, 8 directions), then ``relu(-D2_k), relu(D2_k)`` for
    ``k = 0..3`` (bright ridges, dark valleys). Properties (tested): every channel except ``L`` is
    zero on a constant image (to rounding: below ``1e-16`` times the intensity); rotating the
    image by +90 degrees (``np.rot90``) maps ``D1_k -> D1_{k+2 mod 8}`` and
    ``D2_k -> D2_{k+2 mod 4}`` (to rounding; even sizes at every level), so ``E_g`` is invariant under rotating render and target together.

    **Fields:**

    - `n_scales`: pyramid levels (static), default 4 (256 px images: 256, 128, 64, 32).
    """

    n_scales: int = eqx.field(static=True, default=4)

    def __check_init__(self):
        if not (isinstance(self.n_scales, int) and self.n_scales >= 1):
            raise InputError(f"n_scales must be a positive int, got {self.n_scales!r}")

    @property
    def channels(self) -> int:
        """Channels per level (17)."""
        return 17

    def min_size(self) -> int:
        """Smallest allowed image side: the coarsest level must be at least 2x2."""
        return 2**self.n_scales

    def level(self, x: Float[Array, "M H W"]) -> Float[Array, "M 17 H W"]:
        """The 17 feature channels of one pyramid level ``x``.

        The 8 linear maps ``D1_0..3, D2_0..3`` (``D1_{k+4} = -D1_k`` exactly) are computed in one
        of two ways, equal to rounding: on a level of more than ``_STENCIL_PIXELS`` pixels (the
        finest of a 256 px image), where most of the time goes, by `_stencil_maps` (on the CPU
        several times faster, value and gradient, than the convolution); on smaller ones by
        `_conv_maps`, one 3x3 convolution (few ops: faster to compile).
        """
        if x.shape[-2] * x.shape[-1] > _STENCIL_PIXELS:
            d1, d2 = _stencil_maps(x)
        else:
            d1, d2 = _conv_maps(x)
        relu = jax.nn.relu
        ridge_valley = [r for d in d2 for r in (relu(-d), relu(d))]
        return jnp.stack([x] + [relu(d) for d in d1] + [relu(-d) for d in d1] + ridge_valley, axis=1)

    def __call__(self, images: Float[Array, "M H W"]) -> list[Float[Array, "M 17 h w"]]:
        """Feature maps of each view at each pyramid level.

        **Arguments:**

        - `images`: ``(M, H, W)`` display values; ``H, W >= 2**n_scales``.

        **Returns:** A list of ``n_scales`` arrays ``(M, 17, H_s, W_s)``, ``H_s = floor(H / 2^s)``.
        """
        h, w = images.shape[-2:]
        if min(h, w) < self.min_size():
            raise InputError(
                f"images of {h}x{w} px are too small for a {self.n_scales}-level filter bank "
                f"(each side must be at least {self.min_size()} px)"
            )
        out = []
        x = images
        for s in range(self.n_scales):
            if s:
                x = _avg_pool2(x)
            out.append(self.level(x))
        return out


#: VGG-19 convolution layers up to conv5_1, in order, as ``(name, torchvision features index)``.
VGG19_LAYERS: tuple[tuple[str, int], ...] = (
    ("conv1_1", 0),
    ("conv1_2", 2),
    ("conv2_1", 5),
    ("conv2_2", 7),
    ("conv3_1", 10),
    ("conv3_2", 12),
    ("conv3_3", 14),
    ("conv3_4", 16),
    ("conv4_1", 19),
    ("conv4_2", 21),
    ("conv4_3", 23),
    ("conv4_4", 25),
    ("conv5_1", 28),
)
#: Layers whose ReLU outputs are the Gram features (Gatys et al. 2015).
VGG19_TAPS = ("conv1_1", "conv2_1", "conv3_1", "conv4_1", "conv5_1")
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


class VGG19Features(eqx.Module):
    """VGG-19 feature extractor (ReLU outputs of conv1_1, conv2_1, conv3_1, conv4_1, conv5_1).

    Built by ``load_vgg19`` from a local ``.npz`` file (format in ``load_vgg19``). Grayscale
    display values are replicated to RGB and normalised with the ImageNet mean/std; then the
    torchvision ``vgg19().features`` stack: 3x3 convolutions (stride 1, zero padding 1), ReLU, and
    2x2 max pooling (stride 2, floor) between blocks. Channel widths are whatever the file holds
    (the real network has 64, 128, 256, 512, 512). Weights are constants here: no gradient flows to
    them (``stop_gradient``).

    **Fields:**

    - `weights`: 13 arrays ``(out, in, 3, 3)`` (torch OIHW, cross-correlation).
    - `biases`: 13 arrays ``(out,)``.
    """

    weights: tuple[Float[Array, "o i 3 3"], ...]
    biases: tuple[Float[Array, " o"], ...]

    def min_size(self) -> int:
        """Smallest allowed image side (four 2x2 poolings leave at least one pixel)."""
        return 16

    def __call__(self, images: Float[Array, "M H W"]) -> list[Float[Array, "M C h w"]]:
        """Feature maps of each view at the five tapped layers.

        **Arguments:**

        - `images`: ``(M, H, W)`` display values in ``[0, 1]``; ``H, W >= 16``.

        **Returns:** A list of 5 arrays ``(M, C_l, H_l, W_l)``, ``H_l = floor(H / 2^l)``.
        """
        h, w = images.shape[-2:]
        if min(h, w) < self.min_size():
            raise InputError(f"images of {h}x{w} px are too small for VGG-19 (need >= 16 px)")
        dt = images.dtype
        mean = jnp.asarray(_IMAGENET_MEAN, dt)[:, None, None]
        std = jnp.asarray(_IMAGENET_STD, dt)[:, None, None]
        x = (images[:, None, :, :] - mean) / std  # (M, 3, H, W): gray replicated to RGB
        out = []
        for (name, _), wgt, b in zip(VGG19_LAYERS, self.weights, self.biases):
            if name.endswith("_1") and name != "conv1_1":
                m, c, hh, ww = x.shape
                x = x[:, :, : hh // 2 * 2, : ww // 2 * 2]
                x = x.reshape(m, c, hh // 2, 2, ww // 2, 2).max(axis=(3, 5))
            wgt = jax.lax.stop_gradient(wgt).astype(dt)
            b = jax.lax.stop_gradient(b).astype(dt)
            x = jax.lax.conv_general_dilated(
                x, wgt, (1, 1), ((1, 1), (1, 1)), dimension_numbers=("NCHW", "OIHW", "NCHW")
            )
            x = jax.nn.relu(x + b[:, None, None])
            if name in VGG19_TAPS:
                out.append(x)
        return out


def load_vgg19(path: str | os.PathLike) -> VGG19Features:
    """Load VGG-19 convolution weights from a local ``.npz`` file (nothing is downloaded).

    The file holds, for each layer name ``conv1_1 .. conv5_1`` of ``VGG19_LAYERS``, the keys
    ``<name>.weight`` (``(out, in, 3, 3)``, torch OIHW layout) and ``<name>.bias`` (``(out,)``);
    ``conv1_1`` takes 3 input channels and each layer's ``in`` equals the previous layer's ``out``.
    Other keys (e.g. ``conv5_2`` .. ``conv5_4``) are ignored. ``scripts/convert_vgg19.py`` writes
    such a file from torchvision's ``vgg19`` state dict.

    **Arguments:**

    - `path`: the ``.npz`` file.

    **Returns:** A ``VGG19Features`` module (weights stored as float32, cast to the image dtype when applied).

    **Raises:**

    ``jscratch.errors.DesignFileError`` (a ``ValueError``), one line naming the file: a missing or
    unreadable file, a missing key, a wrong shape or a channel mismatch, or non-finite weights.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DesignFileError(f"VGG-19 weights file not found: {path!r}")
    try:
        with open(path, "rb") as f:
            zipped = f.read(4) in (b"PK\x03\x04", b"PK\x05\x06")  # an archive, or an empty one
        data = np.load(path, allow_pickle=False) if zipped else None
    except Exception as e:  # noqa: BLE001 - report any unreadable file the same way
        raise DesignFileError(f"VGG-19 weights file {path!r} is not a readable .npz file ({error_line(e)})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        # (numpy would try it as a pickle, and advise allow_pickle: no advice for a weights file)
        raise DesignFileError(f"VGG-19 weights file {path!r} is not a valid .npz file (not a zip "
                              f"archive as numpy.savez writes)")
    with data:
        keys = set(data.files)
        weights, biases = [], []
        prev_out = 3
        for name, _ in VGG19_LAYERS:
            for suffix in ("weight", "bias"):
                if f"{name}.{suffix}" not in keys:
                    hint = sorted(keys)[:4]
                    raise DesignFileError(
                        f"VGG-19 weights file {path!r} lacks key {name}.{suffix!s} (found keys "
                        f"{hint}...; convert torchvision weights with scripts/convert_vgg19.py)"
                    )
            wgt = np.asarray(data[f"{name}.weight"])
            b = np.asarray(data[f"{name}.bias"])
            if wgt.ndim != 4 or wgt.shape[2:] != (3, 3):
                raise DesignFileError(
                    f"{name}.weight must have shape (out, in, 3, 3), got {wgt.shape} in {path!r}"
                )
            if wgt.shape[1] != prev_out:
                raise DesignFileError(
                    f"{name}.weight has {wgt.shape[1]} input channels but the previous layer "
                    f"gives {prev_out} (shape {wgt.shape}) in {path!r}"
                )
            if b.shape != (wgt.shape[0],):
                raise DesignFileError(
                    f"{name}.bias must have shape ({wgt.shape[0]},), got {b.shape} in {path!r}"
                )
            if not (np.all(np.isfinite(wgt)) and np.all(np.isfinite(b))):
                raise DesignFileError(f"{name} has non-finite weights in {path!r}")
            prev_out = wgt.shape[0]
            weights.append(jnp.asarray(wgt, jnp.float32))
            biases.append(jnp.asarray(b, jnp.float32))
    return VGG19Features(tuple(weights), tuple(biases))
