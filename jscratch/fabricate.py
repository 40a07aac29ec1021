"""Fabrication: order a design's scratches, fit the cutter, write GRBL 1.1 G-code, stream it.

A separate, imperative stage (docs/model.md §8): it reads a design file (docs/model.md §9) and drives a
3-axis carver with a ball-end cutter for hours, so every step is checked before any motion and the
progress survives crashes.

- `jscratch.machine.MachineProfile` (also ``MachineConfig``): the machine profile, read
  from ``--machine FILE`` (TOML; ``--config`` is an alias) or recorded in the design file;
  `machine_for_design` reconciles the two (a different cutter is refused).
- Carvable designs (``plunge`` in the design file) are cut at their recorded plunges; other
  designs get a fitted plunge:
- `fit_plunge`: plunge depth of a ball-end cutter of radius `R` that best matches each
  scratch's groove profile (least squares with optimistix), with the fit error.
- `make_program`: ordered G-code (mm, absolute) with a line map (line -> scratch).
- `carve`: stream a G-code file to GRBL over a serial port with a journal and resume.
- ``python -m jscratch.fabricate --help``: the command line.

G-code layout (four comment lines: what it carves, the cutter, the design's digest
``(design ..)`` and the limits the program was checked against, ``(limits X..:.. Y..:.. Z..:..
mm)``; preamble ``G21 G90 G94 G17 G54`` and ``G0 Z<safe>`` (the
tool off the board), then, with a spindle, ``M3 S..`` and a spin-up dwell ``G4 P..``; one block
per scratch, at most 79 characters a line;
last, after ``M2``, a comment with the SHA-256 of every other line, ``(sha256 ..)``)::

    G0 X.. Y..        travel, at safe Z          (role "travel")
    G1 Z-p F..        plunge                     (role "plunge")
    G1 X.. Y.. F..    cut                        (role "cut")
    G0 Z..            retract to safe Z          (role "retract")
    G4 P0.000         sync: its ok means the scratch is carved (role "sync")

GRBL answers ``G4 P0.000`` only once the planner is empty, so the journal records a scratch as
carved when that ``ok`` arrives; at a fault, only the scratch after the last confirmed one can be
partly cut.

Work zero: the board corner on its surface is the origin of the ``G54`` work system, set on the
machine with ``G10 L20 P1 X0 Y0 Z0`` (stored in GRBL's EEPROM, kept across resets and power
cycles). `carve` refuses a ``G92`` offset or a tool length offset (GRBL clears both at every
reset, so a job relying on them would shift after a fault or on resume), journals the ``G54``
offset and refuses to resume when it has changed (unless `rezeroed`).

Numbers: every word is written by `jscratch.grbl.gword` (fixed decimals, no exponent, within
GRBL's 8-digit reader); `make_program` re-reads each line with
`jscratch.grbl.check_words` and checks the bounds: every X/Y in ``[offset - margin, offset + S
+ margin]`` mm (``margin_mm``, default 0: design endpoints within the load tolerance are clamped
onto the board), every Z in ``[-plunge_max_mm, safe_z]``: no plunge is deeper than the profile's
``plunge_max_mm`` (a deeper recorded plunge is refused, a fitted one is cut at that depth and
counted unreachable).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import stat
import sys
from typing import NamedTuple

import numpy as np

from jscratch.designfile import (Design, DesignError, demo_design, groove_half_width,
                                 load_design, validate_design)
from jscratch.options import OneLineParser, check_out_prefix, signals_interrupt
from jscratch.errors import EXIT_STATUS_HELP, InputError, JscratchError, real_number, report
from jscratch.grbl import WORD_FORMAT, clip, gword
from jscratch.carve import CarveError, carve
from jscratch.gcode import (Program, check_program_lines, design_comment, digest_comment,
                            limits_comment, options_not_in_program, program_design, read_program,
                            write_program)
from jscratch.machine import CUT_KEYS, MachineConfig, MachineProfile, carving_seconds
from jscratch.toolpath import order_scratches

__all__ = [
    "MachineConfig", "MachineProfile", "machine_for_design", "CutterFit", "fit_plunge", "Program", "make_program", "write_program",
    "read_program", "write_preview", "summarize", "carve", "CarveError", "main",
]


# ----------------------------------------------------------------------------------------------
# Cutter fit.


class CutterFit(NamedTuple):
    """Plunge fit of a ball-end cutter to the design's groove profiles (all lengths metres).

    - `plunge`: `(N,)` plunge depth per scratch.
    - `rms`: `(N,)` RMS height error between the cut and the design profile over `|x| <= 1.25 x_max`.
    - `rel_rms`: `(N,)` `rms / depth`.
    - `groove_width`, `cut_width`: `(N,)` design groove width `2 x_max` and the cut's `2 sqrt(2Rp - p^2)`.
    - `unreachable`: `(N,)` bool, the cutter cannot make this groove well (`rel_rms > 0.25` or the
      plunge hit the cutter's radius).
    """

    plunge: np.ndarray
    rms: np.ndarray
    rel_rms: np.ndarray
    groove_width: np.ndarray
    cut_width: np.ndarray
    unreachable: np.ndarray


_FIT_SAMPLES = 64
_fit_cache = {}


def _fit_solver():
    """The jitted, vmapped optimistix least-squares plunge fit (built once)."""
    if "f" in _fit_cache:
        return _fit_cache["f"]
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    s = jnp.linspace(-1.0, 1.0, _FIT_SAMPLES)

    def residual(theta, args):
        # Units of R: groove w, d, x_max; plunge p = sigmoid(theta) in (0, 1).
        w, d, xm, weight = (jnp.asarray(a)[..., None] for a in args)
        x = 1.25 * xm * s
        p = jax.nn.sigmoid(theta)
        inside = jnp.abs(x) < xm
        xs = jnp.where(inside, x, 0.0)
        h = jnp.where(inside, -0.5 * w * jnp.log1p(-4.0 * xs**2 / w**2) - d, 0.0)
        ball = 1.0 - p - jnp.sqrt(jnp.maximum(1.0 - x**2, 1e-12))
        cut = jnp.minimum(ball, 0.0)
        return weight * (cut - jnp.minimum(h, 0.0))

    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10)

    def one(theta0, args):
        sol = optx.least_squares(residual, solver, theta0, args=args, max_steps=200, throw=False)
        r = residual(sol.value, args)
        return jax.nn.sigmoid(sol.value), jnp.sqrt(jnp.mean((r / args[3][..., None]) ** 2, axis=-1))

    per = jax.jit(jax.vmap(one))
    glob = jax.jit(one)
    _fit_cache["f"] = (per, glob)
    return per, glob


def fit_plunge(width, depth, radius: float, *, mode: str = "per-scratch") -> CutterFit:
    """Fit the plunge depth `p` of a ball-end cutter of radius `radius` to groove profiles.

    The cut of a ball plunged to `p` has height `min(0, R - p - sqrt(R^2 - x^2))` (surface width
    `2 sqrt(2Rp - p^2)`, docs/model.md §8); the design groove is `min(0, h(x))` of docs/model.md §2. The
    plunge minimises the squared height difference over `|x| <= 1.25 x_max` (optimistix
    Levenberg-Marquardt on `p = R sigmoid(theta)`, so `0 < p < R`); `"global"` fits one plunge for all
    scratches. Unique `(w, d)` pairs are fitted once.

    **Arguments:** `width`, `depth` `(N,)` metres; `radius` metres; `mode` `"per-scratch"` or `"global"`.

    **Returns:** a `CutterFit`.
    """
    import jax.numpy as jnp

    try:
        width = np.asarray(width, np.float64)
        depth = np.asarray(depth, np.float64)
    except (TypeError, ValueError):
        raise InputError("fit_plunge: width and depth must be arrays of lengths in metres"
                         ) from None
    if width.ndim != 1 or depth.shape != width.shape:
        raise InputError(f"fit_plunge: width and depth must have one shape (N,), got {width.shape} "
                         f"and {depth.shape}")
    for name, v in (("width", width), ("depth", depth)):
        if v.size and not (np.all(np.isfinite(v)) and np.all(v > 0)):
            i = int(np.flatnonzero(~(np.isfinite(v) & (v > 0)))[0])
            raise InputError(f"fit_plunge: {name}[{i}] = {float(v[i])!r} is not a finite length "
                             "> 0 (m)")
    given, radius = radius, real_number(radius)
    if radius is None or not (math.isfinite(radius) and radius > 0):
        raise InputError(f"fit_plunge: radius must be a finite length > 0 in metres, got {given!r}")
    if mode not in ("per-scratch", "global"):
        raise InputError(f"fit_plunge: mode must be 'per-scratch' or 'global', got {mode!r}")
    n = width.shape[0]
    xm_all = groove_half_width(width, depth)
    if n == 0:
        z = np.zeros(0)
        return CutterFit(z, z, z, z, z, np.zeros(0, bool))
    pairs, inv, counts = np.unique(np.stack([width, depth], 1), axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    w, d = pairs[:, 0] / radius, pairs[:, 1] / radius
    xm = groove_half_width(w, d)
    a = np.minimum(xm, 0.999)
    p0 = np.clip(1.0 - np.sqrt(1.0 - a**2), 1e-4, 0.999)
    theta0 = np.log(p0 / (1.0 - p0))
    per, glob = _fit_solver()
    dt = jnp.float64 if jnp.zeros(()).dtype == jnp.float64 else jnp.float32
    if mode == "per-scratch":
        args = tuple(jnp.asarray(v, dt) for v in (w, d, xm, np.ones_like(w)))
        p, rms = per(jnp.asarray(theta0, dt), args)
        p_u, rms_u = np.asarray(p, np.float64), np.asarray(rms, np.float64)
    else:
        wt = np.sqrt(counts / counts.sum())
        args = tuple(jnp.asarray(v, dt) for v in (w, d, xm, wt))
        theta_g = float(np.average(theta0, weights=counts))
        pg, _ = glob(jnp.asarray(theta_g, dt), args)
        p_u = np.full(len(w), float(pg))
        # Per-groove RMS at the shared plunge (no extra solve: evaluate with max_steps=0 equivalent).
        theta = np.full(len(w), math.log(float(pg) / (1 - float(pg))))
        _, rms = per(jnp.asarray(theta, dt), tuple(jnp.asarray(v, dt) for v in (w, d, xm, np.ones_like(w))))
        rms_u = np.asarray(rms, np.float64)
        p_u = np.full(len(w), float(pg))
    plunge = p_u[inv] * radius
    rms_m = rms_u[inv] * radius
    rel = rms_m / depth
    cut_w = 2.0 * np.sqrt(np.maximum(2.0 * radius * plunge - plunge**2, 0.0))
    unreachable = (rel > 0.25) | (plunge > 0.98 * radius)
    return CutterFit(plunge, rms_m, rel, 2.0 * xm_all, cut_w, unreachable)


def _design_fit(design: Design, idx, cfg: MachineProfile) -> dict:
    """The fit report of a carvable design's recorded plunges: the groove map's wall-angle error,
    the cut width against the design groove width, and the plunges outside the cutter's range."""
    from jscratch.design.carvable import groove_map_of

    gmap = groove_map_of(cfg)
    R = cfg.cutter_radius_mm
    p = 1000.0 * design.plunge[idx]
    cut_w = 2.0 * np.sqrt(np.maximum(2.0 * R * p - p * p, 0.0))
    groove_w = 2000.0 * groove_half_width(design.width[idx], design.depth[idx])
    out = (p < cfg.plunge_min_mm * (1 - 1e-6)) | (p > cfg.plunge_max_mm * (1 + 1e-6))
    return {
        "mode": "design",
        "groove": design.profile,  # "arc": the design rendered the ball's own cut
        "slope_rms_deg_max": 0.0 if design.profile == "arc" else gmap.rms_deg,
        "width_rel_err_max": float(np.max(np.abs(cut_w / groove_w - 1.0))) if len(p) else 0.0,
        "groove_width_mm": [float(groove_w.min()), float(groove_w.max())] if len(p) else [0.0, 0.0],
        "cut_width_mm": [float(cut_w.min()), float(cut_w.max())] if len(p) else [0.0, 0.0],
        "unreachable": int(out.sum()),
    }


def machine_for_design(design: Design, file_profile: MachineProfile | None, overrides: dict, *,
                       override: bool = False, warn=None) -> MachineProfile:
    """The profile to fabricate `design` with.

    A design that records its machine (docs/model.md §9) is cut with that profile. A `file_profile`
    (``--machine``) or `overrides` (options) that change the cutter (`jscratch.machine.CUT_KEYS`)
    are refused, since the grooves would not be the designed ones, unless `override`; other
    differences (feeds, offsets: the machine on the day) are taken from the file and options, with
    a `warn` line. Without a recorded machine: `file_profile` (or the default) plus `overrides`.

    **Raises:** `InputError`, one line naming the keys that differ.
    """
    if not isinstance(design, Design):
        raise InputError(f"machine_for_design: design must be a jscratch Design (load_design), got "
                         f"{type(design).__name__}")
    if file_profile is not None and not isinstance(file_profile, MachineProfile):
        raise InputError(f"machine_for_design: file_profile must be a MachineProfile or None, got "
                         f"{type(file_profile).__name__}")
    overrides = {} if overrides is None else overrides
    if not isinstance(overrides, dict):
        raise InputError(f"machine_for_design: overrides must be a dict of profile fields, got "
                         f"{type(overrides).__name__}")
    if design.machine is None:
        base = file_profile.to_dict() if file_profile is not None else {}
        return MachineProfile.from_dict(base, **overrides)
    rec = MachineProfile.from_dict(design.machine, source="the design's recorded machine")
    want = (file_profile.to_dict() if file_profile is not None else rec.to_dict())
    want.update({k: v for k, v in overrides.items() if v is not None})
    new = MachineProfile.from_dict(want)
    cut = rec.cut_mismatch(new)
    if cut and not override:
        diffs = ", ".join(f"{k} {getattr(rec, k)!r} (design) vs {getattr(new, k)!r}" for k in cut)
        raise InputError(f"machine mismatch: the design was made for another cutter: {diffs}; use the "
                         "design's profile (drop --machine), re-design with this one, or pass --override-machine")
    other = [k for k in rec.to_dict() if k not in CUT_KEYS and getattr(rec, k) != getattr(new, k)]
    if (cut or other) and warn is not None:
        warn(f"warning: machine settings differ from the design's recorded profile {rec.name!r}: "
             f"{', '.join(cut + other)}; using " + ("the given values (--override-machine)" if cut else "the given values"))
    return new


# ----------------------------------------------------------------------------------------------
# G-code.


def check_design_for_cutting(design: Design, cfg: MachineConfig):
    """Scratches long enough to cut; raises `DesignError` naming the first too-short scratch.

    **Returns:** `(N,)` bool mask of scratches to cut (all True unless `cfg.drop_short`).
    """
    length_mm = 1000.0 * design.length
    short = length_mm < cfg.min_length_mm
    if short.size and short.all():
        raise DesignError(f"every scratch ({short.size}) is shorter than min_length_mm = "
                          f"{cfg.min_length_mm:g} mm: nothing to cut")
    if short.any() and not cfg.drop_short:
        i = int(np.flatnonzero(short)[0])
        raise DesignError(
            f"scratch {i} has length {length_mm[i]:.4g} mm (< min_length_mm = {cfg.min_length_mm:g} mm; "
            f"{int(short.sum())} such scratches): a zero-length scratch cannot be cut; pass --drop-short to skip them"
        )
    return ~short


def make_program(design: Design, cfg: MachineConfig, *, improve: bool = True, time_limit: float | None = 40.0,
                 quiet: bool = True, override_machine: bool = False) -> Program:
    """Order the scratches, fit the plunge and write GRBL 1.1 G-code with its line map.

    **Arguments:** `design` a `jscratch.designfile.Design`; `cfg` machine settings (a
    `MachineProfile`; for a design that records its machine, `machine_for_design` gives it);
    `improve`/`time_limit` for `jscratch.toolpath.order_scratches`; `quiet`; `override_machine`
    cuts a design that records its machine with another cutter (`CUT_KEYS`) all the same.

    **Returns:** a `Program`. **Raises:** `DesignError` for scratches too short to cut or breaking
    `validate_design` (an endpoint off the board, ...); `InputError` if `cfg`'s cutter is not the
    one the design records (its grooves would not be the designed ones), unless `override_machine`.
    """
    if not isinstance(design, Design):
        raise InputError(f"make_program: design must be a jscratch Design (load_design), got "
                         f"{type(design).__name__}")
    if not isinstance(cfg, MachineProfile):
        raise InputError(f"make_program: cfg must be a MachineProfile (machine_for_design or "
                         f"load_machine), got {type(cfg).__name__}")
    design = validate_design(**design._asdict(), source="make_program: design")
    if design.machine is not None and not override_machine:
        rec = MachineProfile.from_dict(design.machine, source="the design's recorded machine")
        cut = rec.cut_mismatch(cfg)
        if cut:
            diffs = ", ".join(f"{k} {getattr(rec, k)!r} (design) vs {getattr(cfg, k)!r}"
                              for k in cut)
            raise InputError(f"make_program: the design was made for another cutter: {diffs}; "
                             "use machine_for_design(design, None, {}), or override_machine=True")
    keep = check_design_for_cutting(design, cfg)
    idx = np.flatnonzero(keep)
    board_mm = 1000.0 * design.board
    p0 = np.clip(1000.0 * design.p0[idx], 0.0, board_mm)
    p1 = np.clip(1000.0 * design.p1[idx], 0.0, board_mm)
    ordering = order_scratches(p0, p1, (0.0, 0.0), improve=improve, time_limit=time_limit)
    design_fit = clamped = None
    if cfg.plunge_mm is not None:
        plunge = np.full(len(idx), cfg.plunge_mm)
        fit = None
    elif design.plunge is not None:
        plunge = 1000.0 * design.plunge[idx]
        fit = None
        design_fit = _design_fit(design, idx, cfg)
        # A plunge shallower than the profile's range would be written as (about) Z0.000: the
        # scratch would not be cut; one deeper than it, deeper than the profile allows.
        for out, what, bound, key in (
                (plunge > cfg.plunge_max_mm * (1 + 1e-6), "deeper", cfg.plunge_max_mm, "max"),
                (plunge < cfg.plunge_min_mm * (1 - 1e-6), "shallower", cfg.plunge_min_mm, "min")):
            bad = np.flatnonzero(out)
            if len(bad):
                j = int(bad[0])
                raise DesignError(
                    f"scratch {int(idx[j])} has a recorded plunge of {plunge[j]:.4g} mm, {what} "
                    f"than machine.plunge_{key}_mm = {bound:g} mm ({len(bad)} such scratches): "
                    "refusing to cut outside the profile's plunge range; fabricate with the "
                    "design's own profile, or pass --plunge")
    else:
        fit = fit_plunge(design.width[idx], design.depth[idx], cfg.cutter_radius_mm / 1000.0, mode=cfg.fit)
        # A fitted plunge is cut within the profile's range (and so never written as Z0.000).
        plunge = np.clip(1000.0 * fit.plunge, cfg.plunge_min_mm, cfg.plunge_max_mm)
        clamped = plunge != 1000.0 * fit.plunge
    ox, oy = cfg.board_offset_mm
    safe = cfg.safe_z_mm
    lines, ks, ss, roles = [], [], [], []

    def emit(text, k=-1, s=-1, role="pre"):
        lines.append(text)
        ks.append(k)
        ss.append(s)
        roles.append(role)

    n = len(idx)
    g = gword
    emit(f"(jscratch: {n} scratches, board {board_mm[0]:.3f} x {board_mm[1]:.3f} mm, work zero G54)", role="comment")
    emit(f"(ball R {cfg.cutter_radius_mm:.3f} mm, feed {cfg.feed_mm_min:.1f} mm/min)", role="comment")
    emit(design_comment(design), role="comment")  # (`--gcode` checks it against the design beside)
    # The bounds checked below, in the file: reading the program back (`--gcode`) checks them again.
    lo = (ox - cfg.margin_mm, oy - cfg.margin_mm, -cfg.plunge_max_mm)
    hi = (ox + board_mm[0] + cfg.margin_mm, oy + board_mm[1] + cfg.margin_mm, safe)
    for axis, a, b in zip("XY", lo, hi):
        w_lo, w_hi = WORD_FORMAT[axis][1:]
        if a < w_lo or b > w_hi:
            raise InputError(f"make_program: the board at board_offset_mm (--offset) = "
                             f"{list(cfg.board_offset_mm)}, plus margin_mm = {cfg.margin_mm:g}, "
                             f"spans {axis} {a:.3f} to {b:.3f} mm, beyond GRBL's [{w_lo}, {w_hi}]")
    emit(limits_comment(lo, hi), role="comment")
    emit("G21 G90 G94 G17 G54")
    emit(f"G0 {g('Z', safe)}")  # first: the tool may stand on the board, where it was zeroed
    if cfg.spindle_rpm > 0:
        emit(f"M3 {g('S', cfg.spindle_rpm)}")
        emit(f"G4 {g('P', cfg.spinup_s)}")  # spin-up: GRBL starts cutting as soon as M3 is parsed
    for k, j in enumerate(ordering.order.tolist()):
        a, b = (p1[j], p0[j]) if ordering.flipped[j] else (p0[j], p1[j])
        s = int(idx[j])
        emit(f"G0 {g('X', a[0] + ox)} {g('Y', a[1] + oy)}", k, s, "travel")
        emit(f"G1 {g('Z', -plunge[j])} {g('F', cfg.plunge_mm_min)}", k, s, "plunge")
        emit(f"G1 {g('X', b[0] + ox)} {g('Y', b[1] + oy)} {g('F', cfg.feed_mm_min)}", k, s, "cut")
        emit(f"G0 {g('Z', safe)}", k, s, "retract")
        emit(f"G4 {g('P', 0)}", k, s, "sync")
    emit(f"G0 {g('Z', safe)}", role="post")
    emit(f"G0 {g('X', ox)} {g('Y', oy)}", role="post")
    if cfg.spindle_rpm > 0:
        emit("M5", role="post")
    emit("M2", role="post")
    emit(digest_comment(lines), role="comment")  # reading the program back checks it is unchanged

    # Every word, re-read from the text, must be strictly formatted and every coordinate in bounds.
    ext = check_program_lines(lines, lo, hi)
    cut_len = float(np.hypot(*(p1 - p0).T).sum())
    est = carving_seconds(cfg, n=n, cut_mm=cut_len, travel_mm=ordering.travel, plunge_mm_total=float(plunge.sum()))
    info = {
        "scratches": n,
        "dropped_short": int((~keep).sum()),
        "cut_length_mm": cut_len,
        "travel_input_mm": ordering.travel_input,
        "travel_greedy_mm": ordering.travel_greedy,
        "travel_mm": ordering.travel,
        "travel_reduction": 1.0 - ordering.travel / ordering.travel_input if ordering.travel_input > 0 else 0.0,
        "ordering_seconds": ordering.seconds,
        "estimated_seconds": est,
        "bounds_mm": ext,
        "limits_mm": {"x": [lo[0], hi[0]], "y": [lo[1], hi[1]], "z": [lo[2], hi[2]]},
        "plunge_mm": [float(plunge.min()) if n else 0.0, float(plunge.max()) if n else 0.0],
        "cutter_radius_mm": cfg.cutter_radius_mm,
    }
    if fit is not None and n:
        info["fit"] = {
            "mode": cfg.fit,
            "rms_um_max": 1e6 * float(fit.rms.max()),
            "rel_rms_max": float(fit.rel_rms.max()),
            "groove_width_mm": [1e3 * float(fit.groove_width.min()), 1e3 * float(fit.groove_width.max())],
            "cut_width_mm": [1e3 * float(fit.cut_width.min()), 1e3 * float(fit.cut_width.max())],
            "unreachable": int((fit.unreachable | clamped).sum()),
            "clamped": int(clamped.sum()),
        }
    if design_fit is not None:
        info["fit"] = design_fit
    if design.machine is not None:
        info["machine"] = design.machine.get("name", "?")
    return Program(lines, np.asarray(ks), np.asarray(ss), roles, info)


# ----------------------------------------------------------------------------------------------
# Preview and summary.


def write_preview(prog: Program, path, board_mm, offset_mm=(0.0, 0.0)):
    """Toolpath preview PNG: cuts in dark blue, rapid travels in light red, board outline in grey."""
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure  # not pyplot: a notebook's backend stays as it is

    cuts, travels = [], []
    pos = (0.0, 0.0)
    for text, role in zip(prog.lines, prog.role):
        if role in ("travel", "cut") or (role == "post" and "X" in text):
            w = dict((t[0], float(t[1:])) for t in text.split() if t[0] in "XY")
            new = (w["X"] - offset_mm[0], w["Y"] - offset_mm[1])
            (cuts if role == "cut" else travels).append([pos, new])
            pos = new
    fig = Figure(figsize=(7, 7), dpi=120)
    ax = fig.subplots()
    ax.add_collection(LineCollection(travels, colors="#e8a0a0", linewidths=0.4, label="travel"))
    ax.add_collection(LineCollection(cuts, colors="#1f3b73", linewidths=0.8, label="cut"))
    ax.plot([0, board_mm[0], board_mm[0], 0, 0], [0, 0, board_mm[1], board_mm[1], 0], color="0.6", lw=0.8)
    ax.set_xlim(-0.02 * board_mm[0], 1.02 * board_mm[0])
    ax.set_ylim(-0.02 * board_mm[1], 1.02 * board_mm[1])
    ax.set_aspect("equal")
    ax.set_xlabel("X (mm)")
    ax.set_ylabel("Y (mm)")
    ax.set_title(f"{len(cuts)} cuts (blue), travels (red)")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(os.fspath(path))


def summarize(info: dict) -> str:
    """Human-readable summary of `Program.info`."""
    t = info["estimated_seconds"]

    def box(b):
        return "  ".join(f"{a.upper()} [{b[a][0]:.3f}, {b[a][1]:.3f}]" if b.get(a) else f"{a.upper()} -" for a in "xyz")

    out = [
        f"scratches        {info['scratches']}" + (f" ({info['dropped_short']} too short, dropped)" if info.get("dropped_short") else ""),
        f"cut length       {info['cut_length_mm'] / 1000:.3f} m",
        f"travel           {info['travel_mm'] / 1000:.3f} m (input order {info['travel_input_mm'] / 1000:.3f} m, "
        f"greedy {info['travel_greedy_mm'] / 1000:.3f} m; reduction {100 * info['travel_reduction']:.1f}%, "
        f"ordering {info['ordering_seconds']:.1f} s)",
        f"estimated time   {t / 3600:.2f} h ({t:.0f} s)",
        f"bounds (mm)      {box(info['bounds_mm'])}  (the program's extents)",
        f"plunge           {info['plunge_mm'][0]:.4f}-{info['plunge_mm'][1]:.4f} mm (ball R {info['cutter_radius_mm']} mm)",
    ]
    if info.get("limits_mm"):
        out.insert(5, f"limits (mm)      {box(info['limits_mm'])}  "
                      "(allowed: board + margin, -plunge_max_mm to safe Z)")
    f = info.get("fit")
    if f and f.get("mode") == "design":
        out.append(
            f"cutter fit       carvable design (machine profile {info.get('machine', '?')!r}): "
            "recorded plunges, 0 fitted; "
            + ("designed with the ball's own arc; " if f.get("groove") == "arc" else
               f"wall-slope RMS error of the groove map <= {f['slope_rms_deg_max']:.2f} deg; ")
            + f"cut width {f['cut_width_mm'][0]:.4f}-{f['cut_width_mm'][1]:.4f} mm "
            f"(groove width error {100 * f['width_rel_err_max']:.4f}%); {f['unreachable']} unreachable grooves")
        if f["unreachable"]:
            out.append(f"WARNING          {f['unreachable']} recorded plunges lie outside the cutter's range")
    elif f:
        out.append(
            f"cutter fit       {f['mode']}: RMS error <= {f['rms_um_max']:.2f} um ({100 * f['rel_rms_max']:.1f}% of depth); "
            f"groove width {f['groove_width_mm'][0]:.4f}-{f['groove_width_mm'][1]:.4f} mm, "
            f"cut width {f['cut_width_mm'][0]:.4f}-{f['cut_width_mm'][1]:.4f} mm"
        )
        if f["unreachable"]:
            out.append(f"WARNING          {f['unreachable']} grooves are unreachable with this cutter "
                       "(fit error > 25% of depth, or a plunge outside the profile's range: "
                       f"{f.get('clamped', 0)} cut at its nearest end); consider a smaller ball")
    ac = info.get("as_carved")
    if ac:
        out.append(f"as carved        SSIM vs the design render per view {[round(x, 3) for x in ac['ssim']]} "
                   f"(ball profile, brute force; from {ac.get('source', 'the design run')})")
    elif "as_carved" in info:
        out.append("as carved        not computed: run the design with --as-carved-samples 32 to "
                   "preview the board the ball will cut")
    return "\n".join(out)


# ----------------------------------------------------------------------------------------------
# Command line.


def _parser():
    p = OneLineParser(
        prog="python -m jscratch.fabricate",
        description="Order a scratch design, write GRBL 1.1 G-code (mm, absolute) with a line map and a toolpath "
                    "preview, and optionally stream it to a GRBL controller with a crash-safe journal.",
        epilog="Every option and input file is checked before anything is written or sent; a refusal is one "
               "line 'error: ...' on stderr. " + EXIT_STATUS_HELP,
    )
    p.add_argument("design", nargs="?", help="design .npz (docs/model.md §9), or a design run's "
                   "output folder (its design.npz); default: a built-in demo design")
    p.add_argument("--dry-run", action="store_true", help="write G-code, preview and summary; never open a port")
    p.add_argument("--out", help="output prefix (default: the design path without .npz, or ./jscratch_demo); "
                                 "writes PREFIX.gcode, PREFIX.gcode.map.csv, PREFIX.preview.png, PREFIX.summary.json")
    p.add_argument("--gcode", help="stream this existing G-code file (with its .map.csv) instead of generating one; "
                                   "without --port it is only read and checked")
    p.add_argument("--machine", "--config", dest="machine",
                   help="machine profile, TOML (keys as the options below, underscores; see python -m "
                        "jscratch.machine); a design that records its profile is cut with that one, and a "
                        "different cutter here is refused (--config is an alias)")
    p.add_argument("--override-machine", action="store_true",
                   help="cut even when --machine or the options change the cutter the design was made for")
    p.add_argument("--demo-n", type=int, default=400, help="scratches in the demo design (default 400)")
    m = p.add_argument_group("machine (defaults from MachineConfig)")
    m.add_argument("--feed", dest="feed_mm_min", type=float, help="cutting feed, mm/min (default 900 = 1.5 cm/s)")
    m.add_argument("--plunge-feed", dest="plunge_mm_min", type=float, help="plunge feed, mm/min (default 300)")
    m.add_argument("--rapid", dest="rapid_mm_min", type=float, help="rapid rate for estimates, mm/min (default 3000)")
    m.add_argument("--safe-z", dest="safe_z_mm", type=float, help="travel height, mm above the surface (default 1)")
    m.add_argument("--cutter-radius", dest="cutter_radius_mm", type=float, help="ball-end radius R, mm (default 0.125)")
    m.add_argument("--plunge", dest="plunge_mm", type=float, help="fixed plunge depth, mm (default: fitted)")
    m.add_argument("--fit", choices=["per-scratch", "global"], help="plunge fit (default per-scratch)")
    m.add_argument("--offset", dest="board_offset_mm", type=float, nargs=2, metavar=("X", "Y"),
                   help="work coordinates of the board corner, mm (default 0 0)")
    m.add_argument("--margin", dest="margin_mm", type=float, help="allowed excursion outside the board, mm (default 0)")
    m.add_argument("--min-length", dest="min_length_mm", type=float, help="shortest cuttable scratch, mm (default 0.01)")
    m.add_argument("--drop-short", dest="drop_short", action="store_const", const=True,
                   help="skip scratches shorter than --min-length instead of failing")
    m.add_argument("--spindle", dest="spindle_rpm", type=float, help="spindle rpm, 0 for none (default 0)")
    m.add_argument("--spinup", dest="spinup_s", type=float,
                   help="dwell after M3 for the spindle to reach speed, s (default 3; sent again on --resume)")
    m.add_argument("--no-improve", action="store_true", help="greedy ordering only (no 2-opt/Or-opt)")
    m.add_argument("--order-time", type=float, default=40.0, help="time limit for the ordering's local search, s (default 40)")
    s = p.add_argument_group("streaming")
    s.add_argument("--port", help="serial device of the GRBL controller, e.g. /dev/ttyUSB0")
    s.add_argument("--baud", type=int, default=115200, help="baud rate (default 115200)")
    s.add_argument("--resume", action="store_true", help="continue the job recorded in the G-code's journal")
    s.add_argument("--counting", action="store_true", help="character-counting streaming (default: send-and-wait)")
    s.add_argument("--check", action="store_true", help="run the G-code through GRBL's $C check mode first")
    s.add_argument("--home", action="store_true",
                   help="run the homing cycle ($H) first, whatever the controller's state")
    s.add_argument("--unlock", action="store_true", help="clear an Alarm with $X (position may be wrong!)")
    s.add_argument("--rezeroed", action="store_true",
                   help="with --resume: the board was re-zeroed (G10 L20 P1): accept a G54 work "
                   "zero other than the journalled one, and a position lost since the job last ran")
    s.add_argument("--banner-timeout", type=float, default=5.0, help="seconds to wait for the GRBL banner (default 5)")
    s.add_argument("--idle-timeout", type=float, default=10.0,
                   help="stop when a line stays unanswered this long while the controller reports Idle "
                        "(a lost 'ok'), s, plus any dwell in flight (default 10)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return p


def _refuse_overwrite(gcode: str):
    """Refuse to write `gcode` while its journal exists: the program belongs to that job."""
    from jscratch.journal import Journal

    jp = gcode + ".journal"
    if not os.path.exists(jp) or Journal.torn_header(jp):  # (torn: nothing was carved)
        return
    try:
        header, done = Journal.read(jp)
        what = f"{done} of {header.get('n_scratches', '?')} scratches carved"
        finished = done == header.get("n_scratches")
    except (JscratchError, OSError) as exc:
        what, finished = f"unreadable: {clip(exc, 80)}", False
    if finished:
        raise InputError(f"{gcode!r} is the program of a finished job (journal {jp!r}: {what}); choose another "
                         "--out, or move the G-code and its journal away, to write a new program")
    raise InputError(f"{gcode!r} is the program of an unfinished job (journal {jp!r}: {what}); continue it with "
                     "--resume, or move the G-code and its journal away to start a new one; nothing was written")


def _refuse_another_design(gcode: str):
    """Refuse a program written from a design other than the one beside it now (``X.gcode`` is
    written from ``X.npz`` by default): made again since, the program would carve the old one."""
    beside = os.path.splitext(gcode)[0] + ".npz"
    try:
        now = load_design(beside).digest() if os.path.isfile(beside) else None
        with open(gcode, encoding="ascii") as f:
            was = program_design(f.read().split("\n"))
    except (JscratchError, OSError, UnicodeDecodeError):  # (no design there; read_program says)
        return
    if now is not None and was is not None and now != was:
        raise InputError(f"{gcode!r} carves another design than {beside!r} beside it (made again "
                         f"since?): write the program again with python -m jscratch.fabricate "
                         f"{beside}, or move one of them away")


def _attach_as_carved(info: dict, design_path: str):
    """Copy the design run's "as carved" SSIM (``metrics.json`` next to the design) into `info`."""
    mpath = os.path.join(os.path.dirname(os.path.abspath(design_path)), "metrics.json")
    try:
        with open(mpath) as f:
            metrics = json.load(f)
    except (OSError, ValueError):  # (UnicodeDecodeError is a ValueError)
        return
    ac = metrics.get("as_carved") if isinstance(metrics, dict) else None
    # (None: a design run's metrics without it, or not in the design run's form: the summary says
    # how to get it)
    ssim = ac.get("ssim") if isinstance(ac, dict) else None
    good = (isinstance(ssim, list) and ssim
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in ssim))
    info["as_carved"] = {"ssim": ssim, "source": mpath} if good else None


def _check_options(args) -> None:
    """Refuse option values and combinations before any work (`InputError`, one line). A design
    run's folder given as the design stands for its ``design.npz``."""
    for opt, value in (("the design", args.design), ("--gcode", args.gcode),
                       ("--machine", args.machine), ("--out", args.out), ("--port", args.port)):
        if value is not None and not value.strip():
            raise InputError(f"{opt} is an empty path ({value!r}; an unset shell variable?): "
                             "give a file, or leave the option out")
    if args.design and os.path.isdir(args.design):
        inside = os.path.join(args.design, "design.npz")
        if not os.path.isfile(inside):
            raise InputError(f"design {args.design!r} is a folder without a design.npz (give a "
                             "design .npz, or a design run's output folder)")
        args.design = inside
    if args.dry_run and args.port:
        raise InputError("--dry-run never opens a port; drop --port or --dry-run")
    if args.gcode and args.design:
        raise InputError(f"give a design or --gcode, not both (got {args.design!r} and --gcode {args.gcode!r})")
    if args.gcode and args.out:
        raise InputError("--out names the files written from a design; --gcode streams an existing program")
    if args.resume and not args.port:
        raise InputError("--resume continues carving a job: give --port")
    if args.port is not None and "://" not in args.port:
        if not os.path.exists(args.port):
            raise InputError(f"--port {args.port!r} does not exist (is the controller plugged in?)")
        if not stat.S_ISCHR(os.stat(args.port).st_mode):
            raise InputError(f"--port {args.port!r} is not a serial device (a character device "
                             "such as /dev/ttyUSB0)")
    if args.rezeroed and not args.resume:
        raise InputError("--rezeroed accepts a changed work zero when resuming: it needs --resume")
    if args.demo_n < 1:
        raise InputError(f"--demo-n must be an int >= 1 (scratches in the demo design), got {args.demo_n}")
    if not (math.isfinite(args.order_time) and args.order_time >= 0):
        raise InputError(f"--order-time must be a finite number of seconds >= 0, got {args.order_time}")
    if args.baud < 1:
        raise InputError(f"--baud must be a positive int (e.g. 115200), got {args.baud}")
    for opt, v in (("--banner-timeout", args.banner_timeout), ("--idle-timeout", args.idle_timeout)):
        if not (math.isfinite(v) and v > 0):
            raise InputError(f"{opt} must be a finite number of seconds > 0, got {v}")
    if args.out is not None:
        check_out_prefix("--out", args.out, "DIR/job")


def _warn_unused_options(gcode: str, over: dict, args) -> None:
    """Warn about the options given now that shape a program, not its streaming, when `--resume`
    or `--gcode` streams an existing program as written: those whose value differs from the
    program's own words (`options_not_in_program`), and the others (a `--machine` file, ...)."""
    out = options_not_in_program(read_program(gcode), over)
    out += [f"--machine {args.machine}"] * bool(args.machine) + ["--no-improve"] * args.no_improve
    if out and not args.quiet:
        print(f"warning: the program {gcode!r} is streamed as written; not applied: "
              f"{', '.join(out)}", file=sys.stderr)


def main(argv=None) -> int:
    """Command line entry point; returns the exit status (`jscratch.errors.EXIT_STATUS_HELP`: 0 ok,
    1 a file could not be written, 2 refused input, 4 carving or the device stopped, 130
    interrupted: Ctrl-C, or SIGTERM / SIGHUP, `jscratch.options.signals_interrupt`)."""
    try:
        with signals_interrupt():
            return _main(argv)
    except KeyboardInterrupt:
        return 130


def _main(argv) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    flags = {a.dest: a.option_strings[0] for a in parser._actions if a.option_strings}
    names = [f.name for f in dataclasses.fields(MachineConfig)]
    over = {k: getattr(args, k) for k in names if hasattr(args, k) and getattr(args, k) is not None}
    try:
        _check_options(args)
        # Read and check everything (profile, design, program) before anything is written.
        file_prof = MachineProfile.from_toml(args.machine) if args.machine else None
        cfg = MachineProfile.from_dict(file_prof.to_dict() if file_prof else {}, source="the machine options",
                                       flags=flags, **over)
        prog = None
        if args.gcode:
            gcode = args.gcode
            _warn_unused_options(gcode, over, args)
            if not args.resume:  # (a resumed job goes on with its program, whatever changed)
                _refuse_another_design(gcode)
            if not args.port:
                n = read_program(gcode).info["scratches"]  # check it, as the carver would
                if not args.quiet:
                    print(f"{gcode}: a checked program of {n} scratches; give --port to carve it")
        else:
            if args.design:
                design = load_design(args.design)
                prefix = args.out or os.path.splitext(args.design)[0]
                # (a resumed job streams its program as written: `_warn_unused_options` says so)
                warn = None if args.quiet or args.resume else (lambda m: print(m, file=sys.stderr))
                cfg = machine_for_design(design, file_prof, over, override=args.override_machine, warn=warn)
            else:
                design = demo_design(args.demo_n, depth=6e-5)  # (the shipped ball reaches it)
                prefix = args.out or "jscratch_demo"
            gcode = prefix + ".gcode"
            if args.resume:
                if not os.path.exists(gcode):
                    raise InputError(f"--resume: G-code {gcode!r} does not exist (no job to resume there)")
                _warn_unused_options(gcode, over, args)
            else:
                _refuse_overwrite(gcode)
                prog = make_program(design, cfg, improve=not args.no_improve,
                                    time_limit=args.order_time,
                                    override_machine=args.override_machine)
        if prog is not None:
            folder = os.path.dirname(gcode)
            if folder:  # `--out NEWDIR/job`: the folder is made, as the design command does
                os.makedirs(folder, exist_ok=True)
            if args.design:
                _attach_as_carved(prog.info, args.design)
            write_program(prog, gcode)
            write_preview(prog, prefix + ".preview.png", 1000.0 * design.board, cfg.board_offset_mm)
            with open(prefix + ".summary.json", "w") as f:
                json.dump(prog.info, f, indent=1)
            if not args.quiet:
                print(summarize(prog.info))
                print(f"wrote {gcode}, {gcode}.map.csv, {prefix}.preview.png, {prefix}.summary.json")
        if args.port:
            res = carve(gcode, args.port, baud=args.baud, resume=args.resume, counting=args.counting,
                        check=args.check, home=args.home, unlock=args.unlock, rezeroed=args.rezeroed,
                        quiet=args.quiet, banner_timeout=args.banner_timeout, idle_timeout=args.idle_timeout)
            if not args.quiet:
                print(f"carved {res['done']} of {res['total']} scratches")
    except KeyboardInterrupt:
        return 130
    except (JscratchError, OSError) as exc:
        return report(exc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
