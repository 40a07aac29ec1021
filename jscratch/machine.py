"""The machine profile: one small TOML file that both the design and the fabrication read.

A `MachineProfile` (``MachineConfig`` is an alias of the same class) describes the carver:
the cutter (a ball end of radius ``R`` on a spring holder, paper section 5), the plunge range it can
cut well, the feeds, and the G-code settings. ``python -m jscratch.design --machine FILE`` designs
grooves that this cutter can cut (`jscratch.design.carvable`) and records the profile in the design
file; ``python -m jscratch.fabricate`` then uses the recorded profile, and refuses a different cutter.

The file is TOML, one ``[machine]`` table (or bare keys) named as the fields below::

    [machine]
    cutter = "ball"
    cutter_radius_mm = 0.125
    plunge_min_mm = 0.005
    plunge_max_mm = 0.1
    feed_mm_min = 900.0      # 1.5 cm/s (paper)

``python -m jscratch.machine`` prints the shipped default (the paper's setup) as such a file.
A bad value is a one-line `jscratch.errors.InputError` (a `ValueError`) naming the key
(``machine.plunge_max_mm must ...``); a profile file that is missing, unreadable, not TOML or holds
a bad value is a `jscratch.errors.DesignFileError` (an `InputError`) naming the file.

Also here: `carving_seconds`, the carving-time estimate from the profile's feeds and an
ordered toolpath (used by `jscratch.fabricate` and the design's ``metrics.json``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import sys

from jscratch.errors import EXIT_STATUS_HELP, DesignFileError, InputError, JscratchError, report

__all__ = ["MachineProfile", "MachineConfig", "load_machine", "carving_seconds", "CUT_KEYS"]

#: The keys that decide the groove a scratch gets; a design and a fabrication must agree on them.
CUT_KEYS = ("cutter", "cutter_radius_mm", "plunge_min_mm", "plunge_max_mm")

_FLOAT_POS = ("feed_mm_min", "plunge_mm_min", "rapid_mm_min", "safe_z_mm", "cutter_radius_mm",
              "plunge_min_mm", "plunge_max_mm")
_FLOAT_NONNEG = ("margin_mm", "min_length_mm", "spindle_rpm", "spinup_s", "overhead_s")


@dataclasses.dataclass
class MachineProfile:
    """The carver (millimetres, mm/min, seconds). Defaults: the paper's machine (section 5).

    - `name`: a label, recorded with the design.
    - `cutter`: ``"ball"`` (a sphere-headed milling cutter; the only kind supported).
    - `holder`: ``"spring"`` (paper: a spring holder lets the cutter follow the board's height
      within 1-2 mm) or ``"rigid"``; informational.
    - `cutter_radius_mm`: ball radius ``R``.
    - `plunge_min_mm`, `plunge_max_mm`: the plunge range a carvable design uses (``0 < min < max
      < R``): a plunge ``p`` cuts a groove of width ``2 sqrt(2Rp - p^2)`` and steepest wall
      ``asin(sqrt(2Rp - p^2) / R)``.
    - `feed_mm_min`: cutting feed (paper: 1.5 cm/s = 900 mm/min).
    - `plunge_mm_min`: plunge feed. `rapid_mm_min`: rapid rate, for time estimates only (GRBL uses
      its `$110`.. max rates).
    - `safe_z_mm`: travel height above the board surface (Z = 0 on the surface).
    - `plunge_mm`: fixed plunge depth for every scratch of a free design, or None to fit it (`fit`).
    - `fit`: ``"per-scratch"`` or ``"global"`` plunge fit for free designs.
    - `board_offset_mm`: work coordinates of the board corner ``(0, 0)``.
    - `margin_mm`: how far outside the board a coordinate may be, at most 1e4 mm (design endpoints
      are clamped).
    - `min_length_mm`: shorter scratches are an error (or dropped with `drop_short`).
    - `spindle_rpm`: 0 for no spindle commands, else ``M3 S..`` / ``M5``.
    - `spinup_s`: dwell after ``M3`` for the spindle to reach speed (also sent on resume).
    - `groove_fit`: the groove a carvable design renders for a plunge
      (`jscratch.design.carvable`): ``"arc"`` (default: the ball's own circular arc,
      docs/model.md §13), or the paper's profile fitted to it, ``"height"`` (least-squares
      heights) or ``"slope"`` (least-squares wall angles).
    - `overhead_s`: per-scratch acceleration and settling time, for the estimate (with the paper's
      mean 1.5 cm scratch at 1.5 cm/s this makes about one scratch a second plus travel).
    """

    feed_mm_min: float = 900.0
    plunge_mm_min: float = 300.0
    rapid_mm_min: float = 3000.0
    safe_z_mm: float = 1.0
    cutter_radius_mm: float = 0.125
    plunge_mm: float | None = None
    fit: str = "per-scratch"
    board_offset_mm: tuple = (0.0, 0.0)
    margin_mm: float = 0.0
    min_length_mm: float = 0.01
    drop_short: bool = False
    spindle_rpm: float = 0.0
    spinup_s: float = 3.0
    overhead_s: float = 0.2
    name: str = "paper"
    cutter: str = "ball"
    holder: str = "spring"
    plunge_min_mm: float = 0.005
    plunge_max_mm: float = 0.1
    groove_fit: str = "arc"

    def __new__(cls, *args, **kwargs):
        # An unknown keyword is refused as `from_dict` refuses an unknown key (before __init__).
        _check_names(cls, kwargs, "MachineProfile")
        return super().__new__(cls)

    def __post_init__(self):
        from jscratch.grbl import gword

        def bad(name, what):
            raise InputError(f"machine.{name} must be {what}, got {getattr(self, name)!r}")

        def number(v):
            return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

        for name in _FLOAT_POS:
            v = getattr(self, name)
            if not (number(v) and v > 0):
                bad(name, "a finite number > 0")
            setattr(self, name, float(v))
        for name in _FLOAT_NONNEG:
            v = getattr(self, name)
            if not (number(v) and v >= 0):
                bad(name, "a finite number >= 0")
            setattr(self, name, float(v))
        for name in ("name", "cutter", "holder", "fit", "groove_fit"):
            if not isinstance(getattr(self, name), str):
                bad(name, "a string")
        if self.cutter != "ball":
            bad("cutter", "'ball' (the only cutter kind supported)")
        if self.holder not in ("spring", "rigid"):
            bad("holder", "'spring' or 'rigid'")
        if self.groove_fit not in ("arc", "height", "slope"):
            bad("groove_fit", "'arc', 'height' or 'slope'")
        if not isinstance(self.drop_short, bool):
            bad("drop_short", "true or false")
        r = self.cutter_radius_mm
        if not self.plunge_max_mm < r:
            bad("plunge_max_mm", f"< cutter_radius_mm = {r}")
        if not self.plunge_min_mm < self.plunge_max_mm:
            bad("plunge_min_mm", f"< plunge_max_mm = {self.plunge_max_mm}")
        if self.plunge_mm is not None and not (
                number(self.plunge_mm) and 0 < self.plunge_mm <= self.plunge_max_mm):
            bad("plunge_mm", f"in (0, plunge_max_mm = {self.plunge_max_mm}] or absent")
        if self.fit not in ("per-scratch", "global"):
            bad("fit", "'per-scratch' or 'global'")
        try:
            off = tuple(float(v) for v in self.board_offset_mm)
        except (TypeError, ValueError):
            off = ()
        if self.margin_mm > 1e4:  # (the limits comment and every coordinate stay short)
            bad("margin_mm", "a finite number in [0, 1e4] mm")
        if len(off) != 2 or not all(math.isfinite(v) and abs(v) <= 1e5 for v in off):
            bad("board_offset_mm", "two finite numbers [x, y] within +-1e5 mm")
        self.board_offset_mm = off
        for name, letter in (("feed_mm_min", "F"), ("plunge_mm_min", "F"), ("safe_z_mm", "Z"),
                             ("spindle_rpm", "S"), ("spinup_s", "P")):
            try:
                gword(letter, getattr(self, name))
            except InputError as exc:
                raise InputError(f"machine setting {name} = {getattr(self, name)!r} does not fit GRBL: {exc}") from None
        # A depth, height or speed that G-code would write as zero cuts nothing, travels on the
        # surface or runs the job with the spindle still.
        written = [("plunge_min_mm", "Z"), ("safe_z_mm", "Z"), ("plunge_mm", "Z")]
        written += [("spindle_rpm", "S")] if self.spindle_rpm > 0 else []
        written += [("spinup_s", "P")] if self.spindle_rpm > 0 and self.spinup_s > 0 else []
        for name, letter in written:
            v = getattr(self, name)
            if v is not None and float(gword(letter, v)[1:]) == 0.0:
                bad(name, f"written as at least {letter}{gword(letter, 0)[1:-1]}1 in G-code"
                    + {"S": " (or 0 for no spindle commands)", "P": " (or 0 for no dwell)"}.get(
                        letter, ""))

    # ------------------------------------------------------------------------------------------
    # Files and records.

    def to_dict(self) -> dict:
        """Plain-JSON form (`from_dict` inverts it)."""
        d = dataclasses.asdict(self)
        d["board_offset_mm"] = list(self.board_offset_mm)
        return d

    @classmethod
    def from_dict(cls, data: dict, source: str = "machine profile", *, flags: dict | None = None,
                  **overrides) -> "MachineProfile":
        """A profile from a dict (keys as the fields), then `overrides` (those not None).

        **Raises:** `InputError`, one line naming `source` and the key, for an unknown key or a
        bad value (a bad override by its command-line option where `flags` maps its field to one).
        """
        if not isinstance(data, dict):
            raise InputError(f"{source}: expected a table of machine settings, got {type(data).__name__}")
        _check_names(cls, data, source)
        _check_names(cls, overrides, source)
        data = dict(data)
        data.update({k: v for k, v in overrides.items() if v is not None})
        try:
            return cls(**data)
        except InputError as exc:
            bad = re.fullmatch(r"machine\.(\w+) (must be .*)", str(exc))
            if bad and overrides.get(bad.group(1)) is not None and bad.group(1) in (flags or {}):
                raise InputError(f"{flags[bad.group(1)]} {bad.group(2)}") from None
            raise InputError(f"{source}: {exc}") from None

    @classmethod
    def from_toml(cls, path, **overrides) -> "MachineProfile":
        """Read a profile from a TOML file (a ``[machine]`` table or bare keys), then apply
        `overrides` (those not None).

        **Raises:** `DesignFileError`, one line naming the file (and the key), for a missing or
        unreadable file, one that is not TOML, or a bad or unknown key in it; `InputError` for a bad
        override.
        """
        import tomllib

        path = str(path)
        _check_names(cls, overrides, f"{path} with the given options")
        try:
            with open(path, "rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            raise DesignFileError(f"machine profile {path!r} does not exist") from None
        except OSError as exc:
            raise DesignFileError(f"machine profile {path!r} cannot be read ({exc.strerror})") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise DesignFileError(f"{path}: not a valid TOML machine profile ({str(exc).splitlines()[0]})") from None
        if "machine" in data:
            outside = sorted(k for k in data if k != "machine")
            if outside or not isinstance(data["machine"], dict):
                what = (f"{', '.join(outside)} outside the [machine] table" if outside
                        else "'machine' is not a table")
                raise DesignFileError(f"{path}: {what} (give every setting in [machine], or "
                                      "every one bare)")
            data = data["machine"]
        try:
            prof = cls.from_dict(data, source=path)
        except InputError as exc:
            raise DesignFileError(str(exc)) from None
        if not any(v is not None for v in overrides.values()):
            return prof
        return cls.from_dict(prof.to_dict(), source=f"{path} with the given options", **overrides)

    def to_toml(self) -> str:
        """The profile as a TOML ``[machine]`` table (`from_toml` reads it back)."""
        out = ["[machine]"]
        for k, v in self.to_dict().items():
            if v is None:
                continue
            if isinstance(v, bool):
                s = "true" if v else "false"
            elif isinstance(v, str):
                s = json.dumps(v)
            elif isinstance(v, list):
                s = "[" + ", ".join(repr(float(x)) for x in v) + "]"
            else:
                s = repr(float(v))
            out.append(f"{k} = {s}")
        return "\n".join(out) + "\n"

    def cut_mismatch(self, other: "MachineProfile") -> list[str]:
        """The `CUT_KEYS` on which two profiles differ (the groove would not be the designed one)."""
        return [k for k in CUT_KEYS if getattr(self, k) != getattr(other, k)]

    # ------------------------------------------------------------------------------------------
    # Geometry (metres).

    @property
    def radius(self) -> float:
        """Ball radius ``R`` (m)."""
        return self.cutter_radius_mm / 1000.0

    @property
    def plunge_range(self) -> tuple[float, float]:
        """``(p_min, p_max)`` (m)."""
        return self.plunge_min_mm / 1000.0, self.plunge_max_mm / 1000.0


def _check_names(cls, names, source: str) -> None:
    """`InputError`, one line naming `source`, when a name in `names` is no field of `cls`."""
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(str(k) for k in set(names) - fields)
    if unknown:
        raise InputError(f"{source}: unknown machine setting machine.{unknown[0]} "
                         f"(known: {', '.join(sorted(fields))})")


#: An alias, for `jscratch.fabricate`'s callers.
MachineConfig = MachineProfile


def load_machine(path=None, **overrides) -> MachineProfile:
    """The profile in TOML file `path`, or the shipped default when `path` is None, then
    `overrides` (those not None). **Raises:** `InputError` (`DesignFileError` for the file), one
    line, for an unknown override name, an unknown key or a bad value."""
    _check_names(MachineProfile, overrides, "load_machine")
    if path is None:
        return MachineProfile.from_dict({}, **overrides)
    return MachineProfile.from_toml(path, **overrides)


def carving_seconds(profile: MachineProfile, *, n: int, cut_mm: float, travel_mm: float,
                    plunge_mm_total: float) -> float:
    """Estimated carving time (s) of an ordered toolpath with `profile`'s feeds.

    Per scratch: rapid up and down between the surface and safe Z, the plunge at the plunge feed,
    the cut at the cutting feed and `overhead_s`; between scratches the rapid travel; plus the
    spindle's spin-up.

    **Arguments:** `n` scratches; `cut_mm` total cut length; `travel_mm` total rapid travel of the
    ordered path; `plunge_mm_total` sum of plunge depths. Each a finite number >= 0 (else
    `InputError`, one line).
    """
    for name, v in (("n", n), ("cut_mm", cut_mm), ("travel_mm", travel_mm),
                    ("plunge_mm_total", plunge_mm_total)):
        try:
            ok = not isinstance(v, (bool, str)) and math.isfinite(v) and v >= 0
        except TypeError:
            ok = False
        if not ok:
            raise InputError(f"carving_seconds: `{name}` must be a finite number >= 0, got {v!r}")
    p = profile
    minutes = (travel_mm / p.rapid_mm_min + cut_mm / p.feed_mm_min + plunge_mm_total / p.plunge_mm_min
               + n * 2 * p.safe_z_mm / p.rapid_mm_min + n * p.safe_z_mm / p.plunge_mm_min)
    return minutes * 60.0 + n * p.overhead_s + (p.spinup_s if p.spindle_rpm > 0 else 0.0)


def main(argv=None) -> int:
    """``python -m jscratch.machine [FILE]``: check FILE (or print the shipped default) as TOML.

    Returns the exit status (0 ok, 2 a missing or bad profile; `jscratch.errors.EXIT_STATUS_HELP`)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in ("-h", "--help"):
        print("usage: python -m jscratch.machine [FILE]\n\nPrint the machine profile in FILE (checked), "
              f"or the shipped default (the paper's machine), as TOML.\n\n{EXIT_STATUS_HELP}")
        return 0
    if len(argv) > 1 or (argv and argv[0].startswith("-")):
        print(f"error: python -m jscratch.machine [FILE] takes at most one FILE and no options, "
              f"got {' '.join(argv)!r}", file=sys.stderr)
        return 2
    try:
        prof = load_machine(argv[0] if argv else None)
    except JscratchError as exc:
        return report(exc)
    sys.stdout.write(prof.to_toml())
    return 0


if __name__ == "__main__":
    sys.exit(main())
