"""Targets and outputs: checks of the targets and views, loading target images (one-line errors
naming the file), the default `skimage.data` targets and `write_outputs` (design file, SVG, PNGs,
plots, metrics)."""

from __future__ import annotations

import hashlib
import json
import math
import os

import numpy as np

from jscratch import designfile
from jscratch.designfile import DesignError
from jscratch.errors import error_line
from jscratch.scene import Board, Views, check_views, flat_highlight
from jscratch.design.config import DEFAULT_IMAGES
from jscratch.design.result import DesignResult


def check_targets(targets, m: int | None) -> np.ndarray:
    t = np.asarray(targets)
    if t.dtype == object or not (np.issubdtype(t.dtype, np.floating) or np.issubdtype(t.dtype, np.integer)):
        raise DesignError(f"targets must be a numeric (M, H, W) array of display values, got dtype {t.dtype}")
    if t.ndim != 3:
        raise DesignError(f"targets must have shape (M, H, W) (one grayscale image per view), got {t.shape}")
    if m is not None and t.shape[0] != m:
        raise DesignError(f"got {t.shape[0]} target images for {m} views: give one target per view")
    if np.issubdtype(t.dtype, np.integer):
        raise DesignError("targets must be floating display values in [0, 1]; convert integer images "
                          "(e.g. uint8 / 255) or use load_target")
    if not np.all(np.isfinite(t)):
        j = int(np.argwhere(~np.isfinite(t))[0, 0])
        raise DesignError(f"target {j} has non-finite values")
    if t.min() < 0 or t.max() > 1:
        j = int(np.argmax(((t < 0) | (t > 1)).reshape(t.shape[0], -1).any(-1)))
        raise DesignError(f"target {j} has values outside [0, 1] (range [{t[j].min()}, {t[j].max()}])")
    if min(t.shape[1:]) < 16:
        raise DesignError(f"targets must be at least 16x16 px, got {t.shape[1]}x{t.shape[2]}")
    return t


def check_design_views(views: Views, board: Board) -> None:
    cam = np.asarray(views.camera, np.float64)
    lig = np.asarray(views.light, np.float64)
    check_views(cam, lig, views.intensity, source="views", error=DesignError)
    spot = flat_highlight(cam, lig)
    on = (spot[:, 0] >= 0) & (spot[:, 0] <= board.Sx) & (spot[:, 1] >= 0) & (spot[:, 1] <= board.Sy)
    if on.any():
        j = int(np.argmax(on))
        raise DesignError(
            f"view {j}: the camera is at the light's mirror direction (the flat board reflects the "
            f"light into it at board point ({spot[j, 0]:.4f}, {spot[j, 1]:.4f}) m), so the board's "
            "own highlight would dominate that view; move the camera or the light")


def targets_hash(t: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(t, np.float64).tobytes()).hexdigest()[:16]


def _to_gray01(img: np.ndarray, name: str) -> np.ndarray:
    from skimage.color import rgb2gray

    img = np.asarray(img)
    if img.ndim == 3 and img.shape[-1] == 4:
        img = img[..., :3]
    if img.ndim == 3 and img.shape[-1] == 3:
        if np.issubdtype(img.dtype, np.integer):
            img = img / float(np.iinfo(img.dtype).max)
        img = rgb2gray(img)
    elif img.ndim != 2:
        raise DesignError(f"target {name}: expected a grayscale or RGB(A) image, got shape {img.shape}")
    if img.dtype == bool:
        img = img.astype(np.float64)
    elif np.issubdtype(img.dtype, np.integer):
        img = img / float(np.iinfo(img.dtype).max)
    img = np.asarray(img, np.float64)
    if not np.all(np.isfinite(img)) or img.min() < 0 or img.max() > 1:
        raise DesignError(f"target {name}: float images must hold values in [0, 1]")
    return img


def _fit(img: np.ndarray, shape: tuple[int, int], name: str, crop: bool) -> np.ndarray:
    from skimage.transform import resize

    h, w = img.shape
    want = shape[1] / shape[0]
    if crop:
        if w / h > want:
            cw = int(round(h * want))
            img = img[:, (w - cw) // 2:(w - cw) // 2 + cw]
        else:
            ch = int(round(w / want))
            img = img[(h - ch) // 2:(h - ch) // 2 + ch]
    elif abs((w / h) / want - 1) > 0.02:
        raise DesignError(f"target {name} is {w}x{h} px (aspect {w / h:.3f}) but the board image is "
                          f"{shape[1]}x{shape[0]} (aspect {want:.3f}): crop it first")
    return np.clip(resize(img, shape, anti_aliasing=True), 0.0, 1.0)


def prepare_target(img: np.ndarray, shape: tuple[int, int], name: str, *, crop: bool = True) -> np.ndarray:
    """An image array (grayscale or RGB(A), any dtype) as display values ``(H, W)`` in ``[0, 1]``:
    grayscale, centre-cropped to the board's aspect (``crop``; else the aspect must match within
    2 %) and resized to ``shape``. `name` names it in `DesignError` messages."""
    return _fit(_to_gray01(img, name), shape, name, crop=crop)


def load_target(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """Read an image file as display values ``(H, W)`` in ``[0, 1]`` (grayscale, resized).

    RGB is converted with `skimage.color.rgb2gray`; an alpha channel is dropped; integer images
    are scaled by their dtype's maximum. The aspect ratio must match ``shape`` within 2 %.

    **Raises:** `DesignError` naming the file when it is missing, unreadable or mismatched.
    """
    from skimage import io

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DesignError(f"target image {path!r} does not exist")
    try:
        img = io.imread(path)
    except Exception as e:  # noqa: BLE001 - any reader failure is an unreadable image
        raise DesignError(f"target image {path!r} is not a readable image ({error_line(e)})") from None
    return prepare_target(img, shape, repr(path), crop=False)


def default_targets(m: int, shape: tuple[int, int]) -> tuple[np.ndarray, list[str]]:
    """``m`` targets from `DEFAULT_IMAGES` (cycled), centre-cropped and resized to ``shape``."""
    from skimage import data

    names = [DEFAULT_IMAGES[j % len(DEFAULT_IMAGES)] for j in range(m)]
    imgs = [prepare_target(getattr(data, n)(), shape, n) for n in names]
    return np.stack(imgs), [f"skimage.data.{n}" for n in names]


def write_png(path: str, img: np.ndarray) -> None:
    """Display values ``(H, W)`` in [0, 1] as an 8-bit grayscale PNG."""
    from skimage import io

    io.imsave(path, (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), check_contrast=False)


def write_outputs(result: DesignResult, out: str | os.PathLike, extra_config: dict | None = None) -> None:
    """Write a result: ``design.npz`` + ``design.svg`` (docs/model.md §9), ``view<j>_render.png``
    and ``view<j>_target.png``, ``comparison.png``, ``loss.png``, ``metrics.json`` and
    ``config.json`` (the `DesignConfig` plus `extra_config`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = os.fspath(out)
    os.makedirs(out, exist_ok=True)
    s, v, b = result.scratches, result.views, result.board
    d = designfile.save_design(os.path.join(out, "design.npz"), np.asarray(s.p0), np.asarray(s.p1),
                               np.asarray(s.width), np.asarray(s.depth), np.asarray(s.alpha),
                               np.array([b.Sx, b.Sy]), np.asarray(v.camera), np.asarray(v.light),
                               np.asarray(v.intensity))
    designfile.write_svg(os.path.join(out, "design.svg"), d)
    m = result.targets.shape[0]
    for j in range(m):
        write_png(os.path.join(out, f"view{j}_render.png"), result.display[j])
        write_png(os.path.join(out, f"view{j}_target.png"), result.targets[j])
    fig, axes = plt.subplots(2, m, figsize=(3 * m, 6.4), squeeze=False)
    for j in range(m):
        axes[0, j].imshow(result.targets[j], cmap="gray", vmin=0, vmax=1)
        axes[0, j].set_title(f"target {j}")
        axes[1, j].imshow(np.clip(result.display[j], 0, 1), cmap="gray", vmin=0, vmax=1)
        mt = result.metrics
        axes[1, j].set_title(f"render {j}: SSIM {mt['ssim'][j]:.3f}, ghost {mt['ghosting'][j]:.3f}",
                             fontsize=8)
        for a in axes[:, j]:
            a.axis("off")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "comparison.png"), dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.arange(len(result.history["total"])), result.history["total"], label="total")
    for k, vals in result.history["terms"].items():
        ax.plot(np.arange(len(vals)), vals, "--", label=k)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out, "loss.png"), dpi=100)
    plt.close(fig)

    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        return x

    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(clean(result.metrics), f, indent=2)
    cfg = {"design": result.config.to_dict(), "board": {"Sx": b.Sx, "Sy": b.Sy, "shape": list(b.shape)},
           "camera": np.asarray(v.camera).tolist(), "light": np.asarray(v.light).tolist(),
           **(extra_config or {})}
    with open(os.path.join(out, "config.json"), "w") as f:
        json.dump(cfg, f, indent=2)
