"""Orbit preview: the board as a visitor walking around it sees it.

``python -m jscratch.preview DESIGN.npz|RUN_DIR`` renders the design (`jscratch.render.render`) with
the light fixed where the design put it and the camera circling the board centre at the design
views' polar angle and distance, and writes

- ``PREFIX.orbit.gif``: an animated GIF, one frame per camera azimuth (design views framed in
  orange and labelled);
- ``PREFIX.orbit_sheet.png``: a still contact sheet of the same frames.

The frames are ``--frames`` azimuths evenly spaced from design view 0's, with the frame nearest each
design view moved onto that view's exact azimuth. A single light has one intensity: the frames use
the geometric mean of the design's per-view intensities (`--intensity` overrides it), so a
design view whose intensity was optimised higher looks a little darker here than in its render.
Where the camera passes the light's mirror direction, the flat board's own highlight floods the
frame: that is what the visitor sees there too.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

from jscratch.options import OneLineParser, check_out_prefix, signals_interrupt
from jscratch.errors import (EXIT_STATUS_HELP, DesignFileError, InputError, JscratchError,
                             count_arg, error_line, real_number, report, shown)

__all__ = ["orbit_views", "render_orbit", "write_gif", "write_sheet", "main"]


#: What an orbit of a design without views is refused with (after the design's name).
_NO_VIEWS = "the design has no views (camera, light, intensity) to orbit"


def _load(path):
    from jscratch.designfile import load_design

    if os.path.isdir(path):
        path = os.path.join(path, "design.npz")
    d = load_design(path)
    if d.camera is None:
        raise DesignFileError(f"{path}: {_NO_VIEWS}")
    return d, path


def _check_orbit(where: str, design, frames) -> int:
    """`frames` as an int >= 1, and a design with views; `InputError` otherwise."""
    from jscratch.designfile import Design

    if not isinstance(design, Design):
        raise InputError(f"{where}: design must be a jscratch Design (load_design), got "
                         f"{type(design).__name__}")
    if design.camera is None:
        raise InputError(f"{where}: {_NO_VIEWS}")
    return count_arg(where, "frames", frames, 1)


def orbit_views(design, frames: int):
    """Camera positions ``(F, 3)``, the light ``(3,)``, the azimuths ``(F,)`` (rad) and, per frame,
    the design view it shows (or -1), for an orbit at the views' polar angle and distance.
    `InputError` for a design without views or `frames` not an int >= 1."""
    frames = _check_orbit("orbit_views", design, frames)
    centre = np.array([design.board[0] / 2, design.board[1] / 2, 0.0])
    rel = design.camera - centre
    dist = np.linalg.norm(rel, axis=1)
    polar = np.arccos(rel[:, 2] / dist)
    az_views = np.arctan2(rel[:, 1], rel[:, 0])
    az = az_views[0] + 2 * np.pi * np.arange(frames) / frames
    marks = np.full(frames, -1)
    for j, a in enumerate(az_views):
        k = int(np.argmin(np.abs(np.angle(np.exp(1j * (az - a))))))
        if marks[k] == -1:
            az[k], marks[k] = a, j
    th, r = float(np.mean(polar)), float(np.mean(dist))
    cams = centre + r * np.stack([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az),
                                  np.full(frames, np.cos(th))], 1)
    return cams, design.light[0], az, marks


def render_orbit(design, *, frames: int = 36, size: int = 128, batch: int = 6,
                 intensity: float | None = None, progress: bool = True):
    """Display images ``(F, size, size)`` of the orbit, with `orbit_views`' azimuths and marks.

    Frames are rendered `batch` at a time (one compilation: the last batch is padded).
    `InputError`, one line, for a design without views, or `frames` or `batch` not an int >= 1."""
    import jax.numpy as jnp
    from jscratch.render import render
    from jscratch.scene import Board, Scratches, Views
    from jscratch.shading import display

    frames = _check_orbit("render_orbit", design, frames)
    batch = count_arg("render_orbit", "batch", batch, 1)
    cams, light, az, marks = orbit_views(design, frames)
    board = Board(shape=(size, size), Sx=float(design.board[0]), Sy=float(design.board[1]))
    inten = _default_intensity(design) if intensity is None else float(intensity)
    f32 = np.float32
    sc = Scratches(design.p0.astype(f32), design.p1.astype(f32), design.width.astype(f32),
                   design.depth.astype(f32), design.alpha.astype(f32), profile=design.profile)
    out = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=frames, desc="orbit", unit="frame", dynamic_ncols=True)
    try:
        for a in range(0, frames, batch):
            c = cams[a:a + batch]
            n = len(c)
            c = np.concatenate([c, np.repeat(c[-1:], batch - n, 0)])
            views = Views(jnp.asarray(c, f32), jnp.asarray(np.repeat(light[None], batch, 0), f32),
                          jnp.full((batch,), inten, f32))
            out.append(np.asarray(display(render(sc, views, board)))[:n])
            if bar is not None:
                bar.update(n)
    finally:
        if bar is not None:
            bar.close()
    return np.clip(np.concatenate(out), 0.0, 1.0), az, marks


def _frame_rgb(img, mark):
    """uint8 RGB frame; a design view gets an orange border. `InputError` for non-finite values
    (a cast would draw them as arbitrary greys)."""
    img = np.asarray(img)
    if not np.all(np.isfinite(img)):
        raise InputError("preview: a frame holds non-finite display values")
    g = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    rgb = np.repeat(g[..., None], 3, -1)
    if mark >= 0:
        b = max(2, img.shape[0] // 40)
        for sl in ((slice(0, b), slice(None)), (slice(-b, None), slice(None)),
                   (slice(None), slice(0, b)), (slice(None), slice(-b, None))):
            rgb[sl] = (255, 140, 0)
    return rgb


def write_gif(path, frames, marks, az, *, fps: float = 8.0):
    """Animated GIF (Pillow), looping; design views framed in orange and labelled.
    A GIF's frame time is in hundredths of a second: frame ``k`` ends at ``100 (k + 1) / fps``
    of them rounded, so that the frames keep `fps` on average (8 fps: 12 and 13 alternately; a
    frame equal to the one before is merged into it, its time added).
    `InputError` for no frames or an `fps` outside `FPS_RANGE` (viewers slow down frames
    shorter than two hundredths)."""
    from PIL import Image, ImageDraw

    if len(frames) == 0:
        raise InputError("write_gif: `frames` is empty: there is no frame to write")
    given, fps = fps, real_number(fps)
    if fps is None or not (math.isfinite(fps) and FPS_RANGE[0] <= fps <= FPS_RANGE[1]):
        raise InputError(f"write_gif: `fps` must be a number in [{FPS_RANGE[0]:g}, "
                         f"{FPS_RANGE[1]:g}] (frames per second), got {shown(given)}")
    ims = []
    for img, m, a in zip(frames, marks, az):
        im = Image.fromarray(_frame_rgb(img, m))
        d = ImageDraw.Draw(im)
        label = f"{round(math.degrees(a), 1) % 360:5.1f} deg" + (f"  view {m}" if m >= 0 else "")
        d.text((4, 2), label, fill=(255, 140, 0) if m >= 0 else (80, 160, 255))
        ims.append(im)
    ends = [round(100 * (k + 1) / fps) for k in range(len(ims))]
    times = [10 * (e - b) for b, e in zip([0] + ends[:-1], ends)]  # ms, whole hundredths
    ims[0].save(os.fspath(path), save_all=True, append_images=ims[1:], duration=times, loop=0)


def write_sheet(path, frames, marks, az, title=""):
    """Contact sheet PNG of the frames (matplotlib), design views framed in orange.
    `InputError` for no frames."""
    from matplotlib.figure import Figure  # not pyplot: a notebook's backend stays as it is

    f = len(frames)
    if f == 0:
        raise InputError("write_sheet: `frames` is empty: there is no frame to write")
    cols = min(f, 9)
    rows = math.ceil(f / cols)
    fig = Figure(figsize=(1.4 * cols, 1.55 * rows + 0.3))
    axes = fig.subplots(rows, cols, squeeze=False)
    for k, ax in enumerate(axes.flat):
        ax.axis("off")
        if k >= f:
            continue
        ax.imshow(_frame_rgb(frames[k], marks[k]))
        lab = f"{round(math.degrees(az[k])) % 360}°" + (f" view {marks[k]}" if marks[k] >= 0 else "")
        ax.set_title(lab, fontsize=7, color="#d46a00" if marks[k] >= 0 else "black")
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(os.fspath(path), dpi=80)


class _Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Defaults in the help, except a None default (its help says what it means)."""

    def _get_help_string(self, action):
        return action.help if action.default is None else super()._get_help_string(action)


def _parser():
    p = OneLineParser(
        prog="python -m jscratch.preview",
        description="Orbit preview of a design: an animated GIF and a contact sheet PNG of the board as the "
                    "camera circles it at the design views' polar angle, the light fixed, design views marked.",
        epilog="Every option and the design are checked before anything is rendered or written; a refusal "
               "is one line 'error: ...' on stderr. " + EXIT_STATUS_HELP,
        formatter_class=_Formatter)
    p.add_argument("design", help="design .npz, or a design run's output folder (holding design.npz)")
    p.add_argument("--out", default=None,
                   help="output prefix; writes PREFIX.orbit.gif and PREFIX.orbit_sheet.png "
                        "(default: the design path without .npz)")
    p.add_argument("--frames", type=int, default=36, help="camera azimuths around the full circle")
    p.add_argument("--size", type=int, default=128, help="frame size in pixels per side")
    p.add_argument("--fps", type=float, default=8.0, help="GIF frames per second")
    p.add_argument("--batch", type=int, default=6, help="frames rendered together (memory knob)")
    p.add_argument("--intensity", type=float, default=None,
                   help="light intensity, W/sr (default: geometric mean of the design's lit "
                        "views' intensities)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return p


#: Option ranges: a GIF stores its frame delay in 1/100 s, and most viewers slow delays under
#: 2/100 s down to 1/10 s, so frame rates above 50 do not play as asked.
FPS_RANGE = (0.1, 50.0)
MAX_SIZE, MAX_FRAMES = 4096, 3600


def _check_options(args) -> None:
    """Refuse option values before any work (`InputError`, one line)."""
    if not 2 <= args.frames <= MAX_FRAMES:
        raise InputError(f"--frames must be an int in [2, {MAX_FRAMES}], got {args.frames}")
    if not 8 <= args.size <= MAX_SIZE:
        raise InputError(f"--size must be an int in [8, {MAX_SIZE}] (pixels per side), "
                         f"got {args.size}")
    if args.batch < 1:
        raise InputError(f"--batch must be an int >= 1, got {args.batch}")
    if not (math.isfinite(args.fps) and FPS_RANGE[0] <= args.fps <= FPS_RANGE[1]):
        raise InputError(f"--fps must be a number in [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}] "
                         f"(frames per second), got {args.fps}")
    if args.intensity is not None and not (math.isfinite(args.intensity) and args.intensity > 0):
        raise InputError(f"--intensity must be a finite number > 0 (W/sr), got {args.intensity}")
    if args.out is not None:
        check_out_prefix("--out", args.out, "DIR/orbit")


def _default_intensity(design) -> float:
    """The geometric mean of the design's lit views' intensities (W/sr); `InputError` when no
    view is lit."""
    lit = np.asarray(design.intensity, np.float64)
    lit = lit[lit > 0]
    if lit.size == 0:
        raise InputError("every view of the design has intensity 0, so the orbit would be black: "
                         "give the light's intensity with --intensity (W/sr)")
    return float(np.exp(np.mean(np.log(lit))))


def _write_both(prefix, frames, marks, az, fps, title) -> None:
    """Write PREFIX.orbit.gif and PREFIX.orbit_sheet.png, both or neither: each is written to a
    temporary name and renamed once both are complete."""
    folder = os.path.dirname(prefix)
    made = []
    while folder and not os.path.isdir(folder):
        made.append(folder)
        folder = os.path.dirname(folder)
    if made:
        os.makedirs(made[0])
    names = [prefix + ".orbit.gif", prefix + ".orbit_sheet.png"]
    tmp = [os.path.join(os.path.dirname(n), f".jscratch-{os.getpid()}-{k}"
                        + os.path.splitext(n)[1]) for k, n in enumerate(names)]
    try:
        for n in names:
            if os.path.isdir(n):
                raise IsADirectoryError(f"{n!r} is a folder")
        write_gif(tmp[0], frames, marks, az, fps=fps)
        write_sheet(tmp[1], frames, marks, az, title=title)
        for t, n in zip(tmp, names):
            os.replace(t, n)
    except BaseException:
        for t in tmp:
            if os.path.exists(t):
                os.remove(t)
        for f in made:  # the folders made here, deepest first, if still empty
            try:
                os.rmdir(f)
            except OSError:
                break
        raise


def main(argv=None) -> int:
    """Command line entry point; returns the exit status (`jscratch.errors.EXIT_STATUS_HELP`: 0 ok,
    1 a file could not be written, 2 refused input, 130 interrupted)."""
    args = _parser().parse_args(argv)  # SystemExit: --help (0) or a refused option (2, one line)
    try:
        with signals_interrupt():  # (SIGTERM, SIGHUP: as Ctrl-C)
            return _main(args)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130


def _main(args) -> int:
    try:
        _check_options(args)
        t0 = time.perf_counter()
        design, path = _load(args.design)
        prefix = args.out or os.path.splitext(path)[0]
        check_out_prefix("the output prefix", prefix, "DIR/orbit")
        inten = _default_intensity(design) if args.intensity is None else args.intensity
        if len(np.unique(np.asarray(design.light), axis=0)) > 1 and not args.quiet:
            print("note: the design's views have different lights; the orbit keeps view 0's",
                  file=sys.stderr)
        frames, az, marks = render_orbit(design, frames=args.frames, size=args.size,
                                         batch=min(args.batch, args.frames), intensity=inten,
                                         progress=not args.quiet)
        _write_both(prefix, frames, marks, az, args.fps,
                    f"{os.path.basename(path)}: {design.n} scratches, light fixed, camera orbiting")
        if not args.quiet:
            unmarked = sorted(set(range(len(design.camera))) - set(marks.tolist()))
            print(f"wrote {prefix}.orbit.gif and {prefix}.orbit_sheet.png ({args.frames} frames, "
                  f"{args.size} px, {time.perf_counter() - t0:.1f} s)"
                  + (f"; views {unmarked} share a frame with another view and are not marked"
                     if unmarked else ""))
    except (JscratchError, OSError) as exc:
        return report(exc)
    except MemoryError as exc:
        print(f"error: out of memory ({error_line(exc, 100)}): ask for a smaller --size or "
              "--batch", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
