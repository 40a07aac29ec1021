"""Targets and results on disk: checks of the targets and views, loading target images (one-line
errors naming the file), the default `skimage.data` targets, `load_scene` (the inputs a
`SceneConfig` describes), the digests a checkpoint is keyed to (`inputs_hash`), and the round
trip of a result: `save_result` / `load_result`."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import tempfile
import uuid

import numpy as np

from jscratch import designfile
from jscratch.designfile import DesignError
from jscratch.errors import InputError, error_line, real_number, whole_number
from jscratch.scene import Board, Views, check_views, flat_highlight
from jscratch.design.config import DEFAULT_IMAGES, SceneConfig
from jscratch.design.result import DesignResult


def check_targets(targets, m: int | None) -> np.ndarray:
    try:
        t = np.asarray(targets)
    except ValueError:  # ragged nested lists
        raise DesignError("targets must be an (M, H, W) array of display values: the images "
                          "given have different shapes") from None
    if t.dtype == object or not (np.issubdtype(t.dtype, np.floating) or np.issubdtype(t.dtype, np.integer)):
        raise DesignError(f"targets must be a numeric (M, H, W) array of display values, got dtype {t.dtype}")
    if t.ndim != 3 or t.size == 0:
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


def inputs_hash(targets: np.ndarray, views, board) -> dict[str, str]:
    """What a checkpoint is keyed to besides its config: short SHA-256 digests of the target
    images (float64 values) and of the scene (the views' cameras, lights and intensities, and
    the board's fields)."""
    h = hashlib.sha256()
    for name in ("camera", "light", "intensity"):
        h.update(np.ascontiguousarray(np.asarray(getattr(views, name)), np.float64).tobytes())
    h.update(repr([board.shape, board.Sx, board.Sy, board.F0, board.a_G, board.a_S]).encode())
    return {"targets_hash": targets_hash(targets), "scene_hash": h.hexdigest()[:16]}


def _to_gray01(img: np.ndarray, name: str) -> np.ndarray:
    from skimage.color import rgb2gray

    img = np.asarray(img)
    if img.size == 0:
        raise DesignError(f"target {name}: an empty image, shape {img.shape}")
    if img.ndim == 4 and img.shape[0] == 1:  # a one-frame animation (GIF)
        img = img[0]
    if img.ndim == 3 and img.shape[-1] in (2, 4):  # grayscale or RGB with alpha: alpha dropped
        img = img[..., :-1]
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
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
        if img.size == 0:
            raise DesignError(f"target {name} is {w}x{h} px: nothing is left of it when cropped to "
                              f"the board image's aspect {want:.3g}")
    elif abs((w / h) / want - 1) > 0.02:
        raise DesignError(f"target {name} is {w}x{h} px (aspect {w / h:.3f}) but the board image is "
                          f"{shape[1]}x{shape[0]} (aspect {want:.3f}): crop it first")
    return np.clip(resize(img, shape, anti_aliasing=True), 0.0, 1.0)


def prepare_target(img: np.ndarray, shape: tuple[int, int], name: str, *, crop: bool = True) -> np.ndarray:
    """An image array (grayscale or RGB(A), any dtype) as display values ``(H, W)`` in ``[0, 1]``:
    grayscale, centre-cropped to the board's aspect (``crop``; else the aspect must match within
    2 %) and resized to ``shape``. `name` names it in `DesignError` messages."""
    return _fit(_to_gray01(img, name), _image_shape(shape), name, crop=crop)


def load_target(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """Read an image file as display values ``(H, W)`` in ``[0, 1]`` (grayscale, resized).

    The image is taken as a viewer shows it: turned by its EXIF orientation, CMYK as RGB. RGB is
    converted with `skimage.color.rgb2gray`; an alpha channel is dropped; integer images are
    scaled by their dtype's maximum. The aspect ratio must match ``shape`` within 2 %.

    **Raises:** `DesignError` naming the file when it is missing, unreadable or mismatched.
    """
    from skimage import io

    if not isinstance(path, (str, os.PathLike)):
        raise DesignError(f"a target image must be a file path, got {path!r}")
    path = os.fspath(path)
    if not os.path.isfile(path):
        what = "is a folder, not an image" if os.path.isdir(path) else "does not exist"
        raise DesignError(f"target image {path!r} {what}")
    try:
        img = _as_shown(path)
        img = io.imread(path) if img is None else img
    except Exception as e:  # noqa: BLE001 - any reader failure is an unreadable image
        if "allow_pickle" in str(e):  # numpy's advice on a junk .npz: no image array in it
            raise DesignError(f"target image {path!r} is not a valid image or .npz file") from None
        if "find a backend" in str(e):  # imageio's words for a format that no reader knows
            raise DesignError(f"target image {path!r} is not a readable image "
                              "(no image reader knows its format)") from None
        raise DesignError(f"target image {path!r} is not a readable image ({error_line(e)})") from None
    return prepare_target(img, _image_shape(shape), repr(path), crop=False)


def _as_shown(path: str) -> np.ndarray | None:
    """The pixels of an image that a viewer shows otherwise than they are stored: rotated or
    mirrored by its EXIF orientation, or CMYK (as RGB); None for every other image (read as
    stored)."""
    from PIL import Image, ImageOps  # (scikit-image's own image library)

    try:
        with Image.open(path) as im:
            if im.mode != "CMYK" and im.getexif().get(0x0112, 1) == 1:
                return None
            im = ImageOps.exif_transpose(im)
            if im.mode not in ("1", "L", "LA", "RGB", "RGBA", "I;16", "I", "F"):
                im = im.convert("RGBA" if im.mode in ("P", "PA") else "RGB")  # palette, CMYK, ..
            return np.asarray(im)
    except Exception:  # noqa: BLE001 - not an image PIL reads: scikit-image reads it, or says why
        return None


def _image_shape(shape) -> tuple[int, int]:
    """``shape`` as ``(H, W)`` positive ints; `DesignError` otherwise."""
    try:
        h, w = shape
        ok = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1
                 for v in (h, w))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DesignError(f"an image shape must be (H, W) in pixels (positive ints), got {shape!r}")
    return int(h), int(w)


def default_targets(m: int, shape: tuple[int, int]) -> tuple[np.ndarray, list[str]]:
    """``m`` targets from `DEFAULT_IMAGES` (cycled), centre-cropped and resized to ``shape``."""
    from skimage import data

    if not (isinstance(m, (int, np.integer)) and not isinstance(m, bool) and m >= 1):
        raise DesignError(f"default_targets: the number of views must be an int >= 1, got {m!r}")
    shape = _image_shape(shape)
    names = [DEFAULT_IMAGES[j % len(DEFAULT_IMAGES)] for j in range(m)]
    imgs = [prepare_target(getattr(data, n)(), shape, n) for n in names]
    return np.stack(imgs), [f"skimage.data.{n}" for n in names]


def load_scene(scene: SceneConfig) -> tuple[np.ndarray, list[str], Views, Board]:
    """The inputs a `SceneConfig` describes: ``(targets (M, H, W), names, views, board)``: the
    target files (or `default_targets`) at the scene's size, its views on a circle and its board.
    Raises `DesignError` naming the file or field."""
    if not isinstance(scene, SceneConfig):
        raise DesignError(f"load_scene: scene must be a SceneConfig (SceneConfig.from_dict for a "
                          f"dict), got {type(scene).__name__}")
    shape = (scene.size, scene.size)
    board = scene.make_board()
    if scene.targets:
        targets = np.stack([load_target(t, shape) for t in scene.targets])
        names = list(scene.targets)
    else:
        targets, names = default_targets(scene.n_views, shape)
    return targets, names, scene.make_views(targets.shape[0], board), board


def write_png(path: str, img: np.ndarray) -> None:
    """Display values ``(H, W)`` in [0, 1] as an 8-bit grayscale PNG."""
    from skimage import io

    img = np.asarray(img)
    if not np.all(np.isfinite(img)):  # (a cast would write them as arbitrary greys)
        raise DesignError(f"write_png: {path!r}: the image holds non-finite values")
    io.imsave(path, (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), check_contrast=False)


#: The files `save_result` writes into a result folder (besides PNG pictures).
RESULT_FILES = ("design.npz", "design.svg", "result.npz", "metrics.json", "config.json")


def save_result(result: DesignResult, out: str | os.PathLike, *, scene: SceneConfig | None = None,
                names: list[str] | None = None, as_carved_samples: int = 0,
                order_time: float = 0.0) -> dict:
    """Write everything a design result holds into folder `out` (created if needed):

    - ``design.npz``: the kept scratches, board, views, the machine profile and, for carvable
      grooves, each scratch's plunge (the file `python -m jscratch.fabricate` carves;
      docs/model.md §9) and ``design.svg``;
    - ``result.npz``: the optimised parameters (all ``N`` scratches), ``keep``, ``targets``,
      ``radiance``, ``display`` and the loss history (what `load_result` needs besides the above);
    - ``metrics.json``: `result.metrics` plus the machine, the groove mode, the carving estimate
      (the toolpath in greedy order with the best directions, plus ``order_time`` s of 2-opt:
      by default none, so that the estimate is the same on every run; the 2-opt that
      `jscratch.fabricate` runs shortens the travel, and the hours less, the cutting dominating)
      and, with ``as_carved_samples > 0``, the
      as-carved SSIM (`jscratch.design.maker.as_carved`; also ``view<j>_carved.png``);
    - ``config.json``: ``{"design": DesignConfig, "scene": SceneConfig or None, "targets": names,
      "board", "camera", "light"}``, which ``python -m jscratch.design --config`` reads back;
    - ``view<j>_render.png``, ``view<j>_target.png``, ``comparison.png``, ``loss.png``.

    `scene` and `names` default to the result's own (`DesignResult.scene`, `.names`). The files
    are written into a staging folder inside `out` and moved in once all are written (a failure
    while writing leaves `out` as it was; only the moves, file by file, are not atomic); then
    an earlier result's ``view<j>_*.png`` in `out` that this one did not write are removed, and
    so are `result.metrics`' as-carved figures when ``as_carved_samples`` is 0. `python -m
    jscratch.design` writes its outputs with this call. Returns the metrics added (they are also
    added to `result.metrics`).
    """
    if whole_number(as_carved_samples) is None or as_carved_samples < 0:
        raise DesignError(f"as_carved_samples must be an int >= 0, got {as_carved_samples!r}")
    given, order_time = order_time, real_number(order_time)
    if order_time is None or not (math.isfinite(order_time) and order_time >= 0):
        raise DesignError(f"save_result: order_time must be a finite number of seconds >= 0, got "
                          f"{given!r}")
    out = _folder("save_result", out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise DesignError(f"save_result: {out!r} is a file, not a folder")
    if not isinstance(result, DesignResult):
        raise DesignError(f"save_result needs a DesignResult (what design() returns), got "
                          f"{type(result).__name__}")
    _check_result(result)
    scene = result.scene if scene is None else scene
    names = result.names if names is None else names
    if not (scene is None or isinstance(scene, SceneConfig)):
        raise DesignError(f"save_result: scene must be None or a SceneConfig, got {scene!r}")
    m = int(np.shape(result.targets)[0])
    if names is not None and not (isinstance(names, (list, tuple)) and len(names) == m
                                  and all(isinstance(x, str) for x in names)):
        raise DesignError(f"save_result: names must be None or {m} strings (one per view), got "
                          f"{names!r}")
    made = not os.path.isdir(out)
    os.makedirs(out, exist_ok=True)
    # A command-line run writing in `out` holds it (`lock_folder`); so does this save, unless this
    # process is that run.
    held = None if _held_here(out) else lock_folder(out, refusal=(
        f"save_result: a design run is writing in {out!r}: wait for it to end, or save into "
        "another folder"))
    try:
        return _save_held(out, made, result, scene, names, as_carved_samples, order_time, m)
    finally:
        if held is not None:
            held.release()


def _pictures_of(out: str) -> list[str]:
    """The ``view<j>_*.png`` that the result in folder `out` (its ``metrics.json``) wrote: one
    render and target per view, an as-carved picture per view where it has as-carved figures;
    none where there is no result."""
    try:
        with open(os.path.join(out, "metrics.json")) as f:
            metrics = json.load(f)
        m = len(metrics["ssim"])
    except (OSError, ValueError, KeyError, TypeError):  # (no result there, or not one of ours)
        return []
    kinds = ("render", "target") + ("carved",) * isinstance(metrics.get("as_carved"), dict)
    names = [f"view{j}_{k}.png" for j in range(m) for k in kinds]
    return [n for n in names if os.path.isfile(os.path.join(out, n))]


def _save_held(out, made, result, scene, names, as_carved_samples, order_time, m) -> dict:
    """`save_result`'s writing, into folder `out` held by this process."""
    settle_earlier(out)  # a stopped command-line run's files: settled before a config is written
    wrote = _pictures_of(out)  # what the earlier result there wrote (no one else's files)
    # Everything is written into a staging folder and moved into `out` once complete: a failure
    # part-way leaves `out` as it was, not half of a new result beside half of an old one.
    stage = tempfile.mkdtemp(prefix=".jscratch-save-", dir=out)
    try:
        add = _save_into(stage, result, scene, names, as_carved_samples, order_time)
        new = os.listdir(stage)
        blocked = [n for n in new if os.path.isdir(os.path.join(out, n))]
        if blocked:
            raise DesignError(f"save_result: {os.path.join(out, blocked[0])!r} is a folder; the "
                              "result's file of that name cannot be written")
        # config.json first and metrics.json last: until the last move their run_ids differ,
        # so a folder left half-moved (Ctrl-C, a kill) is refused by `load_result`.
        last = [n for n in ("config.json", "metrics.json") if n in new]
        for name in last[:1] + [n for n in new if n not in last] + last[1:]:
            os.replace(os.path.join(stage, name), os.path.join(out, name))
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if made and not os.listdir(out):
            os.rmdir(out)
        raise
    shutil.rmtree(stage, ignore_errors=True)
    for name in wrote:  # an earlier result's pictures that this one did not replace
        old = re.fullmatch(r"view(\d+)_(render|target|carved)\.png", name)
        if int(old.group(1)) >= m or (old.group(2) == "carved" and not as_carved_samples):
            try:
                os.remove(os.path.join(out, name))
            except FileNotFoundError:
                pass
    if not as_carved_samples:  # an earlier save's as-carved figures no longer have pictures
        result.metrics.pop("as_carved", None)
    result.metrics.update(add)
    return add


#: What a new command-line run moves aside until its own first checkpoint (`settle_earlier`).
EARLIER = ".earlier"


def settle_earlier(out: str) -> None:
    """A new command-line run in folder `out` moves an earlier run's ``checkpoint.npz`` and then
    its ``config.json`` aside (``*.earlier``; an empty ``config.json.earlier`` says there was
    none) before writing its own config, until its first checkpoint. Settle what a run stopped
    in between left, whatever stopped it (a kill too): with this run's checkpoint written, the
    earlier files are removed; without it, they are put back (the config first), so the folder
    is as it was."""
    cfg, ckpt = os.path.join(out, "config.json"), os.path.join(out, "checkpoint.npz")
    e_cfg, e_ckpt = cfg + EARLIER, ckpt + EARLIER
    if os.path.exists(ckpt):
        for path in (e_cfg, e_ckpt):
            if os.path.exists(path):
                os.remove(path)
        return
    if os.path.exists(e_cfg):
        if os.path.getsize(e_cfg):
            os.replace(e_cfg, cfg)
        else:
            if os.path.exists(cfg):
                os.remove(cfg)
            os.remove(e_cfg)
    if os.path.exists(e_ckpt):
        os.replace(e_ckpt, ckpt)


def lock_folder(out: str, *, refusal: str | None = None):
    """Hold folder `out` for one command-line run: an exclusive `fcntl.flock` on the folder itself
    (nothing is written; the lock goes with the process, however it ends). Returns the open
    folder (``.release()`` it when the run ends), or None where there is no folder yet or no
    flock.
    `DesignError` (one line; `refusal` if given) while another run holds it."""
    try:
        import fcntl
    except ImportError:  # (not POSIX: runs are not locked)
        return None
    try:
        fd = os.open(out, os.O_RDONLY)
    except OSError:  # none yet (the run locks it once made), or not a folder: refused later
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:  # (EWOULDBLOCK: held by another process)
        os.close(fd)
        raise DesignError(refusal or f"another design run is writing in {out!r}: wait for it to "
                          "end, or give another --out") from None
    except OSError:  # a file system without flock (some network ones): runs are not locked
        os.close(fd)
        return None
    return _Held(fd)


def _held_here(out: str) -> bool:
    """Whether this process holds folder `out` (`lock_folder`): a second flock on it from here
    would wait for ourselves."""
    try:
        st = os.stat(out)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) in _Held.folders


class _Held:
    """An open folder held by `lock_folder`: `release` closes it, and so releases the lock (as
    does the end of the process)."""

    #: (device, inode) of the folders this process holds.
    folders: set = set()

    def __init__(self, fd: int):
        self.fd = fd
        st = os.fstat(fd)
        self.key = (st.st_dev, st.st_ino)
        _Held.folders.add(self.key)

    def release(self) -> None:
        fd, self.fd = self.fd, None
        if fd is not None:
            _Held.folders.discard(self.key)
            os.close(fd)

    __del__ = release


def remove_partial_writes(out: str) -> None:
    """Remove what a write killed part-way left in folder `out`: a checkpoint's temporary file
    (``.ckpt-*.npz.tmp``, `checkpoint.save_npz`) and `save_result`'s staging folders
    (``.jscratch-save-*``). For the start of a run (none of its own are being written)."""
    for name in os.listdir(out):
        path = os.path.join(out, name)
        if name.startswith(".ckpt-") and name.endswith(".npz.tmp") and os.path.isfile(path):
            os.remove(path)
        elif name.startswith(".jscratch-save-") and os.path.isdir(path):
            shutil.rmtree(path, ignore_errors=True)


def _folder(who: str, out) -> str:
    """`out` as a str; `DesignError` naming `who` for anything that is not a path."""
    if not isinstance(out, (str, os.PathLike)) or not isinstance(os.fspath(out), str) \
            or not os.fspath(out):
        raise DesignError(f"{who}: expected a folder path (str or os.PathLike), got {out!r}")
    return os.fspath(out)


def _check_result(result: DesignResult) -> None:
    """`DesignError` (one line) when a result's images or history do not have the form
    `design` gives them (e.g. a hand-edited result): targets, radiance and display ``(M, H,
    W)`` alike and finite, history ``{"total": [...], "terms": {name: [...]}}``."""
    shapes = {k: np.shape(getattr(result, k)) for k in ("targets", "radiance", "display")}
    if len(shapes["targets"]) != 3 or len(set(shapes.values())) != 1:
        got = ", ".join(f"{k} {v}" for k, v in shapes.items())
        raise DesignError("save_result: the result's targets, radiance and display must share one "
                          f"shape (M, H, W), got {got}")
    bad = [k for k in shapes if not np.all(np.isfinite(np.asarray(getattr(result, k))))]
    if bad:  # (`load_result` refuses them: a folder saved with them could not be read back)
        raise DesignError(f"save_result: the result's {' and '.join(bad)} hold non-finite values")
    h = result.history
    if not (isinstance(h, dict) and isinstance(h.get("total"), (list, tuple))
            and isinstance(h.get("terms"), dict)):
        raise DesignError('save_result: the result\'s history must be {"total": [...], "terms": '
                          '{name: [...]}} as design() gives it')


def _save_into(out, result, scene, names, as_carved_samples, order_time) -> dict:
    """`save_result`'s files, written into folder `out` (its staging folder)."""
    from jscratch.design import maker
    from jscratch.design.checkpoint import save_npz

    s, v, b = result.scratches, result.views, result.board
    profile = result.config.machine_profile()
    plunge = result.params.plunge()
    if plunge is not None:
        plunge = np.asarray(plunge, np.float64)[np.asarray(result.keep)]
    d = designfile.save_design(os.path.join(out, "design.npz"), np.asarray(s.p0), np.asarray(s.p1),
                               np.asarray(s.width), np.asarray(s.depth), np.asarray(s.alpha),
                               np.array([b.Sx, b.Sy]), np.asarray(v.camera), np.asarray(v.light),
                               np.asarray(v.intensity), machine=profile.to_dict(), plunge=plunge,
                               profile=s.profile)
    designfile.write_svg(os.path.join(out, "design.svg"), d)
    add = {"machine": profile.to_dict(), "groove": result.config.groove}
    if as_carved_samples > 0:
        ac = maker.as_carved(d, profile, b.shape, result.display, samples=int(as_carved_samples))
        for j, img in enumerate(ac.pop("display")):
            write_png(os.path.join(out, f"view{j}_carved.png"), img)
        add["as_carved"] = ac
    add["carving"] = maker.carving_estimate(d, profile, time_limit=order_time)
    metrics = {key: val for key, val in result.metrics.items() if key != "as_carved"}  # or new
    metrics.update(add)
    # The same new token in metrics.json and config.json: `load_result` refuses a folder whose
    # config.json a later, unfinished command-line run has replaced.
    metrics["run_id"] = run_id = uuid.uuid4().hex
    p = result.params
    save_npz(os.path.join(out, "result.npz"), {
        "geom": np.asarray(p.geom), "log_width": np.asarray(p.log_width),
        "log_depth": np.asarray(p.log_depth), "logit_alpha": np.asarray(p.logit_alpha),
        "log_intensity": np.asarray(p.log_intensity), "keep": np.asarray(result.keep, bool),
        "targets": np.asarray(result.targets), "radiance": np.asarray(result.radiance),
        "display": np.asarray(result.display),
        "history": np.frombuffer(json.dumps(result.history).encode(), np.uint8)})
    _write_pictures(result, metrics, out)
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(_json_clean(metrics), f, indent=2)
    cfg = {"design": result.config.to_dict(),
           "scene": None if scene is None else scene.to_dict(),
           "targets": names,
           "board": {"Sx": b.Sx, "Sy": b.Sy, "shape": list(b.shape), "F0": b.F0, "a_G": b.a_G,
                     "a_S": b.a_S},
           "camera": np.asarray(v.camera).tolist(), "light": np.asarray(v.light).tolist(),
           "run_id": run_id}
    with open(os.path.join(out, "config.json"), "w") as f:
        json.dump(cfg, f, indent=2)
    return add


def load_result(out: str | os.PathLike) -> DesignResult:
    """The `DesignResult` that `save_result` wrote into folder `out`, in the library's own types
    (`Scratches`, `Views`, `Board`, `DesignParams`, `DesignConfig`; arrays in the config's dtype),
    so that it renders, resumes into notebooks and fabricates as saved.

    **Raises:** `jscratch.DesignFileError` naming the file when one is missing or unreadable.
    """
    from jscratch.design.config import DesignConfig
    from jscratch.errors import DesignFileError

    if (not isinstance(out, (str, os.PathLike)) or not isinstance(os.fspath(out), str)
            or not os.fspath(out)):
        raise DesignFileError(f"load_result: expected a folder path (str or os.PathLike), got "
                              f"{out!r}")
    out = os.fspath(out)
    if not os.path.isdir(out):
        raise DesignFileError(f"{out!r} is not a result folder (save_result writes one)")
    # A new command-line run stopped before its first checkpoint (`settle_earlier` not run since)
    # moved the result's config aside: the config of the metrics' run is read there.
    e_cfg = os.path.join(out, "config.json" + EARLIER)
    earlier = os.path.isfile(e_cfg) and os.path.getsize(e_cfg) > 0
    config_name = ("config.json" + EARLIER
                   if earlier and not os.path.exists(os.path.join(out, "config.json"))
                   else "config.json")
    for name in ("design.npz", "result.npz", "metrics.json", config_name):
        if not os.path.isfile(os.path.join(out, name)):
            raise DesignFileError(f"{out!r} lacks {name}: not a complete result folder")

    def read_json(name):
        try:
            with open(os.path.join(out, name)) as f:
                return json.load(f)
        except (OSError, ValueError) as e:
            raise DesignFileError(f"{os.path.join(out, name)!r}: not readable JSON "
                                  f"({error_line(e)})") from None

    cfg, metrics = read_json(config_name), read_json("metrics.json")
    if (earlier and config_name == "config.json" and isinstance(cfg, dict)
            and isinstance(metrics, dict) and "run_id" in cfg
            and metrics.get("run_id") != cfg["run_id"]):
        aside = read_json("config.json" + EARLIER)
        if isinstance(aside, dict) and aside.get("run_id") == metrics.get("run_id"):
            config_name, cfg = "config.json" + EARLIER, aside
    if not isinstance(cfg, dict) or "design" not in cfg:
        raise DesignFileError(f"{os.path.join(out, config_name)!r}: no 'design' config")
    if not isinstance(metrics, dict):
        raise DesignFileError(f"{os.path.join(out, 'metrics.json')!r}: not a JSON object")
    if "run_id" in cfg and metrics.get("run_id") != cfg["run_id"]:
        raise DesignFileError(
            f"{out!r}: config.json is a later run's, which has not finished (python -m "
            f"jscratch.design --resume --out {out} finishes it), or a save stopped part-way; "
            "the result files are not all of one run")
    try:
        config = DesignConfig.from_dict(cfg["design"])
    except InputError as e:
        raise DesignFileError(f"{os.path.join(out, config_name)!r}: {e}") from None
    d = designfile.load_design(os.path.join(out, "design.npz"))
    try:
        return _result_from(out, cfg, metrics, config, d)
    except DesignFileError:
        raise
    except (InputError, ValueError, TypeError, KeyError) as e:  # a file edited out of step
        raise DesignFileError(f"{out!r}: the result's files do not agree "
                              f"({error_line(e)})") from None


def _result_from(out, cfg, metrics, config, d) -> DesignResult:
    """`load_result`'s assembly of the read files (any inconsistency raises)."""
    import jax.numpy as jnp

    from jscratch.design.params import DesignParams
    from jscratch.errors import DesignFileError
    from jscratch.scene import Scratches

    rpath = os.path.join(out, "result.npz")
    try:
        with np.load(rpath, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - any reader failure is an unreadable file
        raise DesignFileError(f"{rpath!r}: not a readable result file ({error_line(e)})") from None
    need = ("geom", "log_width", "log_depth", "logit_alpha", "log_intensity", "keep", "targets",
            "radiance", "display", "history")
    missing = [k for k in need if k not in arrays]
    if missing:
        raise DesignFileError(f"{rpath!r} lacks {', '.join(missing)}")
    dt = np.dtype(config.dtype)
    bd = cfg.get("board") or {}
    board = Board(shape=tuple(arrays["targets"].shape[1:]), Sx=float(d.board[0]),
                  Sy=float(d.board[1]), **{k: bd[k] for k in ("F0", "a_G", "a_S") if k in bd})
    groove = None
    if config.groove == "carvable":
        from jscratch.design.carvable import groove_map_of

        groove = groove_map_of(config.machine_profile())
    params = DesignParams(*(jnp.asarray(arrays[k], dt) for k in need[:5]),
                          parameterisation=config.parameterisation,
                          board_size=(board.Sx, board.Sy), groove=groove)
    keep = np.asarray(arrays["keep"], bool)
    n = config.n_scratches
    if (keep.shape != (n,) or int(keep.sum()) != d.n
            or any(np.shape(arrays[k])[:1] != (n,) for k in need[:4])):
        raise DesignFileError(f"{rpath!r} does not match {os.path.join(out, 'design.npz')!r} "
                              f"and the config's {n} scratches")
    if (config.groove == "carvable") != (d.plunge is not None):
        raise DesignFileError(f"{os.path.join(out, 'design.npz')!r} does not match the config's "
                              f"{config.groove!r} grooves")
    m, hw = len(d.camera), np.shape(arrays["targets"])[1:]
    bad = [k for k in need[:9] if not np.all(np.isfinite(arrays[k]))]
    bad += [k for k in ("targets", "radiance", "display") if np.shape(arrays[k]) != (m, *hw)]
    bad += ["log_intensity"] * (np.shape(arrays["log_intensity"]) != (m,))
    if bad:
        raise DesignFileError(f"{rpath!r}: {', '.join(bad)} hold non-finite values or do not fit "
                              f"{m} views")
    ends = [np.asarray(e, np.float64)[keep] for e in params.endpoints()]
    tol = 1e-4 * max(board.Sx, board.Sy)  # (design.npz holds the kept ones, clamped to the board)
    if not all(np.allclose(e, np.asarray(f, np.float64), atol=tol)
               for e, f in zip(ends, (d.p0, d.p1))):
        raise DesignFileError(f"{os.path.join(out, 'design.npz')!r} holds other scratches than "
                              f"{rpath!r}: the files come from different runs")
    scratches = Scratches(*(np.asarray(a, dt) for a in (d.p0, d.p1, d.width, d.depth, d.alpha)),
                          profile=d.profile)
    views = Views(np.asarray(d.camera, dt), np.asarray(d.light, dt), np.asarray(d.intensity, dt))
    history = json.loads(bytes(arrays["history"]).decode())
    scene = cfg.get("scene")
    scene = None if scene is None else SceneConfig.from_dict(scene)
    names = cfg.get("targets")
    if names is not None and not (isinstance(names, list) and len(names) == m
                                  and all(isinstance(x, str) for x in names)):
        raise DesignFileError(f"{os.path.join(out, 'config.json')!r}: 'targets' is not {m} names")
    return DesignResult(scratches, views, board, params, keep, arrays["radiance"],
                        arrays["display"], arrays["targets"], history, _json_floats(metrics),
                        config, scene, names)


def _json_floats(x, key=None):
    """`_json_clean` undone for the per-view image metrics (``ssim``, ``psnr``, ``ghosting``,
    at any depth): None back as NaN, "inf"/"-inf" as floats (a one-view run's ghosting is NaN,
    saved as None). Other values are left as read."""
    if isinstance(x, dict):
        return {k: _json_floats(v, k) for k, v in x.items()}
    if isinstance(x, list) and key in _IMAGE_METRICS:
        return [math.nan if v is None else float(v) if v in ("inf", "-inf") else v for v in x]
    return x


_IMAGE_METRICS = ("ssim", "psnr", "ghosting")


def _json_clean(x):
    """`x` with non-finite floats as JSON can hold them (None, "inf", "-inf")."""
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _json_clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_clean(v) for v in x]
    return x


def _write_pictures(result: DesignResult, metrics: dict, out: str) -> None:
    """``view<j>_render.png``, ``view<j>_target.png``, ``comparison.png`` and ``loss.png``."""
    from matplotlib.figure import Figure  # not pyplot: a notebook's backend stays as it is

    m = result.targets.shape[0]
    for j in range(m):
        write_png(os.path.join(out, f"view{j}_render.png"), result.display[j])
        write_png(os.path.join(out, f"view{j}_target.png"), result.targets[j])

    def num(x):
        return "-" if x is None or not math.isfinite(x) else f"{x:.3f}"

    fig = Figure(figsize=(3 * m, 6.4))
    axes = fig.subplots(2, m, squeeze=False)
    for j in range(m):
        axes[0, j].imshow(result.targets[j], cmap="gray", vmin=0, vmax=1)
        axes[0, j].set_title(f"target {j}")
        axes[1, j].imshow(np.clip(result.display[j], 0, 1), cmap="gray", vmin=0, vmax=1)
        mt = metrics
        axes[1, j].set_title(f"render {j}: SSIM {num(mt['ssim'][j])}, "
                             f"ghost {num(mt['ghosting'][j])}", fontsize=8)
        for a in axes[:, j]:
            a.axis("off")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "comparison.png"), dpi=100)
    fig = Figure(figsize=(5, 3.5))
    ax = fig.subplots()
    ax.plot(np.arange(len(result.history["total"])), result.history["total"], label="total")
    for k, vals in result.history["terms"].items():
        ax.plot(np.arange(len(vals)), vals, "--", label=k)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out, "loss.png"), dpi=100)
