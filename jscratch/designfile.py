"""The design file (docs/model.md §9): what an optimisation saves and what ``fabricate`` reads.

A design is one ``.npz`` file holding

- ``p0``, ``p1``: ``(N, 2)`` scratch endpoints, board metres;
- ``width``, ``depth``, ``alpha``: ``(N,)`` profile width ``w``, depth ``d`` (metres) and GGX roughness;
- ``board``: ``(2,)`` board size ``(Sx, Sy)``, metres;
- optionally ``camera``, ``light`` (``(M, 3)``, metres, above the board) and ``intensity`` (``(M,)``, W/sr),
  when the design came from an optimisation;
- optionally ``machine``: the machine profile it was designed for (`jscratch.machine`), a 0-d
  string array holding its JSON, and ``plunge`` (``(N,)``, metres): the cutter plunge of each
  scratch of a carvable design (within the profile's ``[plunge_min_mm, plunge_max_mm]``);
- optionally ``profile``: a 0-d string array, the grooves' cross-section
  (`jscratch.scene.PROFILES`): ``"paper"`` (also when absent) or ``"arc"``, the ball's circular arc
  of docs/model.md §13 stored as ``width = 2R``, ``depth = -2R log(1 - p/R)``.

The ``.npz`` is the source of truth; `write_svg` exports the same scratches for people and plotter
tools. Loading checks shapes, finiteness, ranges and that every endpoint lies on the board, and names
the first bad scratch and field.
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
import zipfile
from typing import NamedTuple
from xml.sax.saxutils import quoteattr

import numpy as np

from jscratch.errors import DesignFileError, InputError, error_line, instance_arg, real_number
from jscratch.scene import PROFILES, check_scratches, check_views

__all__ = [
    "Design",
    "DesignError",
    "DesignFileError",
    "save_design",
    "load_design",
    "validate_design",
    "write_svg",
    "demo_design",
    "groove_half_width",
]

_REQUIRED = ("p0", "p1", "width", "depth", "alpha", "board")
_VIEWS = ("camera", "light", "intensity")
_MAKER = ("machine", "plunge", "profile")


class DesignError(InputError):
    """A design, or a design run's input, that breaks the rules (docs/model.md §9; `jscratch.scene`):
    the message names the array and the scratch, view or file. Shared by `jscratch.design`.
    A design *file* that cannot be read or breaks the rules is a `DesignFileError` instead
    (`load_design`); both are `InputError`s (and `ValueError`s)."""


class Design(NamedTuple):
    """A scratch design, all arrays float64 numpy, SI units (docs/model.md §9).

    **Fields:**

    - `p0`, `p1`: `(N, 2)` endpoints, board metres.
    - `width`, `depth`: `(N,)` profile parameters `w`, `d` of docs/model.md §2, metres.
    - `alpha`: `(N,)` GGX roughness.
    - `board`: `(2,)` board size `(Sx, Sy)`, metres.
    - `camera`, `light`: `(M, 3)` view positions, metres, or `None`.
    - `intensity`: `(M,)` light intensities, W/sr, or `None`.
    - `machine`: the machine profile (a dict, `jscratch.machine.MachineProfile.to_dict`) the
      design was made for, or `None`.
    - `plunge`: `(N,)` cutter plunge per scratch, metres (carvable designs), or `None`.
    - `profile`: the grooves' cross-section, ``"paper"`` or ``"arc"`` (`jscratch.scene.Scratches`).
    """

    p0: np.ndarray
    p1: np.ndarray
    width: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    board: np.ndarray
    camera: np.ndarray | None = None
    light: np.ndarray | None = None
    intensity: np.ndarray | None = None
    machine: dict | None = None
    plunge: np.ndarray | None = None
    profile: str = "paper"

    @property
    def n(self) -> int:
        """Number of scratches."""
        return int(self.p0.shape[0])

    @property
    def length(self) -> np.ndarray:
        """`(N,)` scratch lengths, metres."""
        return np.hypot(*(self.p1 - self.p0).T)

    def digest(self) -> str:
        """The first 16 hex digits of a SHA-256 of what a carving program is made from (the
        scratches, their plunges, the board and the profile): equal for the same design read
        again, different for another (what `python -m jscratch.fabricate` records in a program)."""
        h = hashlib.sha256(self.profile.encode())
        for a in (self.p0, self.p1, self.width, self.depth, self.alpha, self.board, self.plunge):
            h.update(b"-" if a is None else np.ascontiguousarray(a, np.float64).tobytes())
        return h.hexdigest()[:16]


def groove_half_width(width, depth):
    """Half width `x_max = (w/2) sqrt(1 - exp(-2d/w))` of the groove (docs/model.md §2), numpy, metres."""
    width = np.asarray(width, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    return 0.5 * width * np.sqrt(-np.expm1(-2.0 * depth / width))


def _as_float_array(name, value, source):
    try:
        arr = np.asarray(value)
    except Exception as exc:  # jax arrays, lists, ... all go through np.asarray
        raise DesignError(f"{source}: {name} cannot be read as an array ({error_line(exc)})") from None
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise DesignError(f"{source}: {name} must hold real numbers, got dtype {arr.dtype}")
    return np.array(arr, dtype=np.float64)



def validate_design(p0, p1, width, depth, alpha, board, camera=None, light=None, intensity=None,
                    machine=None, plunge=None, profile="paper", *, source="design") -> Design:
    """Check a design against docs/model.md §9 and return it as a float64 `Design`.

    **Arguments:** the design arrays (anything `np.asarray` reads, e.g. jax arrays), see
    `Design`; `source` names the design in messages (a file name).

    **Returns:** the `Design`.

    **Raises:** `DesignError` naming the array and the first bad scratch (or view) when a
    shape is wrong, a value is not finite, `width`, `depth` or `alpha` is out of range
    (`w > 0`, `d > 0`, alpha in `scene.ALPHA_RANGE`: the rules of
    `jscratch.scene.check_scratches`, the same the renderer applies), or an endpoint lies off
    the board.
    """
    arrays = {
        "p0": _as_float_array("p0", p0, source),
        "p1": _as_float_array("p1", p1, source),
        "width": _as_float_array("width", width, source),
        "depth": _as_float_array("depth", depth, source),
        "alpha": _as_float_array("alpha", alpha, source),
        "board": _as_float_array("board", board, source),
    }
    b = arrays["board"]
    if b.shape != (2,):
        raise DesignError(f"{source}: board must have shape (2,) (Sx, Sy in metres), got {b.shape}")
    if not np.all(np.isfinite(b)) or np.any(b <= 0):
        raise DesignError(f"{source}: board must be two finite positive sizes in metres, got {b.tolist()}")
    P0 = arrays["p0"]
    if P0.ndim != 2 or P0.shape[1] != 2:
        raise DesignError(f"{source}: p0 must have shape (N, 2), got {P0.shape}")
    n = P0.shape[0]
    expected = {"p1": (n, 2), "width": (n,), "depth": (n,), "alpha": (n,)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise DesignError(
                f"{source}: {name} must have shape {shape} to match p0 {P0.shape}, got {arrays[name].shape}"
            )
    check_scratches(arrays["p0"], arrays["p1"], arrays["width"], arrays["depth"],
                    arrays["alpha"], board=b, source=source, error=DesignError)

    views = {"camera": camera, "light": light, "intensity": intensity}
    given = [k for k, v in views.items() if v is not None]
    if given and len(given) != 3:
        missing = [k for k in _VIEWS if k not in given]
        raise DesignError(f"{source}: camera, light and intensity go together; missing {missing}")
    if given:
        cam = _as_float_array("camera", camera, source)
        lig = _as_float_array("light", light, source)
        inten = _as_float_array("intensity", intensity, source)
        if cam.ndim != 2 or cam.shape[1] != 3:
            raise DesignError(f"{source}: camera must have shape (M, 3), got {cam.shape}")
        m = cam.shape[0]
        if lig.shape != (m, 3):
            raise DesignError(f"{source}: light must have shape ({m}, 3) to match camera, got {lig.shape}")
        if inten.shape != (m,):
            raise DesignError(f"{source}: intensity must have shape ({m},) to match camera, got {inten.shape}")
        check_views(cam, lig, inten, source=source, error=DesignError)
        views = {"camera": cam, "light": lig, "intensity": inten}
    else:
        views = {"camera": None, "light": None, "intensity": None}
    if isinstance(profile, np.ndarray) and profile.shape == ():
        profile = profile.item()
    if not isinstance(profile, str) or profile not in PROFILES:
        raise DesignError(f"{source}: profile must be one of {PROFILES}, got {profile!r}")
    return Design(**arrays, **views, **_check_maker(machine, plunge, n, source), profile=profile)


def _check_maker(machine, plunge, n, source):
    """The checked ``machine`` (dict) and ``plunge`` (``(N,)`` metres in the profile's range)."""
    from jscratch.machine import MachineProfile

    prof = None
    if machine is not None:
        if isinstance(machine, np.ndarray):
            machine = machine.item() if machine.shape == () else None
        if isinstance(machine, (str, bytes)):
            import json

            try:
                machine = json.loads(machine)
            except ValueError as exc:
                raise DesignError(f"{source}: machine is not a JSON machine profile ({error_line(exc)})") from None
        try:
            prof = MachineProfile.from_dict(machine, source=f"{source}: machine")
        except (TypeError, ValueError) as exc:
            raise DesignError(str(exc)) from None
    if plunge is not None:
        pl = _as_float_array("plunge", plunge, source)
        if pl.shape != (n,):
            raise DesignError(f"{source}: plunge must have shape ({n},) to match p0, got {pl.shape}")
        bad = ~np.isfinite(pl) | (pl <= 0)
        if prof is not None:
            lo, hi = prof.plunge_range
            bad |= (pl < lo * (1 - 1e-6)) | (pl > hi * (1 + 1e-6))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            rng = "" if prof is None else f" within the machine's [{prof.plunge_min_mm}, {prof.plunge_max_mm}] mm"
            raise DesignError(f"{source}: plunge of scratch {i} is {pl[i]!r} m; must be finite, > 0{rng}")
        plunge = pl
    return {"machine": None if prof is None else prof.to_dict(), "plunge": plunge}


def _umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def save_design(path, p0, p1, width, depth, alpha, board, camera=None, light=None, intensity=None,
                machine=None, plunge=None, profile="paper") -> Design:
    """Validate and write a design to a `.npz` file (docs/model.md §9), atomically.

    **Arguments:** `path` (the file; written as given, no suffix added), then the arrays of
    `Design` (numpy or jax, float32 or float64; stored as float64).

    **Returns:** the validated `Design`.

    **Raises:** `DesignError` for an invalid design; nothing is written then.
    """
    path = _file_path(path, "save_design")
    if os.path.isdir(path):
        raise DesignFileError(f"save_design: {path!r} is a folder; give the design file's path")
    design = validate_design(p0, p1, width, depth, alpha, board, camera, light, intensity, machine, plunge,
                             profile, source=path)
    payload = {k: v for k, v in design._asdict().items() if v is not None}
    payload["profile"] = np.array(design.profile)
    if design.machine is not None:
        import json

        payload["machine"] = np.array(json.dumps(design.machine, sort_keys=True))
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".design-", suffix=".npz.tmp", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; a design is an ordinary file
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return design


def _file_path(path, who: str) -> str:
    """`path` as a str; `DesignFileError` naming `who` for anything that is not a path."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise DesignFileError(f"{who}: expected a file path (str or os.PathLike), got {path!r}")
    path = os.fspath(path)
    if not isinstance(path, str):
        raise DesignFileError(f"{who}: expected a file path (str or os.PathLike), got {path!r}")
    return path


def load_design(path) -> Design:
    """Read and check a design `.npz` (docs/model.md §9).

    **Arguments:** `path` to the file.

    **Returns:** a `Design` of float64 numpy arrays.

    **Raises:** `DesignFileError` (one line naming the file, and the array and first bad scratch
    where there is one) for a missing or unreadable file, or one that is not a valid design.
    """
    path = _file_path(path, "load_design")
    if not os.path.exists(path):
        raise DesignFileError(f"design file {path!r} does not exist")
    if os.path.isdir(path):
        raise DesignFileError(f"design file {path!r} is a folder, not an .npz design file")
    if not zipfile.is_zipfile(path):
        raise DesignFileError(f"{path}: not a readable .npz design file (not a zip archive of arrays)")
    try:
        npz = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise DesignFileError(f"{path}: not a readable .npz design file ({error_line(exc)})") from None
    with npz:
        if not hasattr(npz, "files"):
            raise DesignFileError(f"{path}: expected an .npz archive of arrays, got a single array")
        missing = [k for k in _REQUIRED if k not in npz.files]
        if missing:
            raise DesignFileError(f"{path}: missing array(s) {missing}; a design holds {list(_REQUIRED)}")
        try:
            arrays = {k: npz[k] for k in _REQUIRED + _VIEWS + _MAKER if k in npz.files}
        except Exception as exc:
            raise DesignFileError(f"{path}: cannot read arrays ({error_line(exc)})") from None
    try:
        return validate_design(**arrays, source=path)
    except DesignError as exc:
        raise DesignFileError(str(exc)) from None


def _fmt(v):
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def write_svg(path, design: Design, *, min_stroke_mm: float = 0.02) -> None:
    """Write the scratches as an SVG: one `<line>` per scratch, board millimetres.

    The page is the board, `Sx x Sy` mm (`width="...mm"` with a matching `viewBox`, so Inkscape and
    vpype read true sizes). SVG's y axis points down, so board point `(x, y)` is drawn at
    `(1000 x, 1000 (Sy - y))`: the picture looks like the board seen from above, with the edge
    `y = Sy` at the top (docs/model.md §1). Each line's stroke width is the groove width `2 x_max`
    (at least `min_stroke_mm`, to stay visible) and its `id` is `s<index>`.

    **Arguments:** `path` of the SVG; `design` a `Design`; `min_stroke_mm` the thinnest stroke.
    """
    instance_arg("write_svg", "design", design, Design)
    given, min_stroke_mm = min_stroke_mm, real_number(min_stroke_mm)
    if min_stroke_mm is None or not (math.isfinite(min_stroke_mm) and min_stroke_mm >= 0):
        raise DesignError(f"write_svg: min_stroke_mm must be a finite width >= 0 in mm, got "
                          f"{given!r}")
    sx, sy = (1000.0 * design.board).tolist()
    stroke = np.maximum(2000.0 * groove_half_width(design.width, design.depth), min_stroke_mm)
    x0, x1 = 1000.0 * design.p0[:, 0], 1000.0 * design.p1[:, 0]
    y0, y1 = 1000.0 * (design.board[1] - design.p0[:, 1]), 1000.0 * (design.board[1] - design.p1[:, 1])
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{_fmt(sx)}mm" '
        f'height="{_fmt(sy)}mm" viewBox="0 0 {_fmt(sx)} {_fmt(sy)}">',
        f"<title>{quoteattr('jscratch design: %d scratches' % design.n)[1:-1]}</title>",
        '<g id="scratches" fill="none" stroke="black" stroke-linecap="round">',
    ]
    for i in range(design.n):
        lines.append(
            f'<line id="s{i}" x1="{_fmt(x0[i])}" y1="{_fmt(y0[i])}" x2="{_fmt(x1[i])}" '
            f'y2="{_fmt(y1[i])}" stroke-width="{_fmt(stroke[i])}"/>'
        )
    lines += ["</g>", "</svg>", ""]
    text = "\n".join(lines)
    path = os.fspath(path)
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)


def demo_design(n: int = 400, seed: int = 0, board=(0.3, 0.3), depth: float = 1.28e-4) -> Design:
    """A small built-in design: `n` brushed scratches on rings around the board centre.

    Lengths are uniform in `[5, 25]` mm and the profile is the optimisation start of docs/model.md §5
    (`w = 2.5e-4`, `d = 1.28e-4` m, `alpha = 0.04`; `depth` gives another `d`); each scratch runs
    tangent to the circle through its midpoint (a brushed-ring look) with a little random tilt.
    Every endpoint lies on the board.

    **Arguments:** `n` scratches (>= 1), `seed` for `numpy.random.default_rng`, `board`
    `(Sx, Sy)` m, `depth` the grooves' `d`, m.

    **Returns:** a `Design` without views.
    """
    if int(n) < 1:
        raise InputError(f"demo_design: n (the number of scratches) must be >= 1, got {n}")
    n = int(n)
    rng = np.random.default_rng(seed)
    b = np.asarray(board, dtype=np.float64)
    centre = 0.5 * b
    out = np.empty((0, 2, 2))
    while out.shape[0] < n:
        k = 2 * (n - out.shape[0]) + 8
        mid = rng.uniform([0.0, 0.0], b, size=(k, 2))
        rel = mid - centre
        theta = np.arctan2(rel[:, 1], rel[:, 0]) + 0.5 * np.pi + rng.normal(0.0, 0.15, k)
        half = 0.5 * rng.uniform(0.005, 0.025, k)
        d = half[:, None] * np.stack([np.cos(theta), np.sin(theta)], axis=1)
        seg = np.stack([mid - d, mid + d], axis=1)
        ok = np.all((seg >= 0.0) & (seg <= b), axis=(1, 2))
        out = np.concatenate([out, seg[ok]], axis=0)
    out = out[:n]
    return validate_design(
        out[:, 0], out[:, 1], np.full(n, 2.5e-4), np.full(n, float(depth)), np.full(n, 0.04), b,
        source="demo design"
    )
