"""G-code programs with their line maps: `Program` (the lines and, per line, the scratch and its
role), the dry run's checker (`check_program_lines`), `write_program` and `read_program`.

Imports: `jscratch.grbl`, `jscratch.errors`.
"""

from __future__ import annotations

import csv
import hashlib
import os
import re
from typing import NamedTuple

import numpy as np

from jscratch.errors import DesignFileError, InputError
from jscratch.grbl import check_words, clip, gword

__all__ = ["MAX_LINE", "Program", "check_program_lines", "design_comment", "digest_comment",
           "limits_comment", "options_not_in_program", "program_design", "read_program",
           "write_program"]

MAX_LINE = 79  # characters, without the newline (GRBL's line buffer is 80 bytes)

#: The roles of a program's lines (`Program.role`).
ROLES = ("comment", "pre", "travel", "plunge", "cut", "retract", "sync", "post")

class Program(NamedTuple):
    """G-code with its line map.

    - `lines`: the G-code lines (no line endings); file line `i + 1` is `lines[i]`.
    - `k`: `(L,)` int, position in the cutting order of the scratch a line belongs to, -1 for the
      preamble and postamble.
    - `scratch`: `(L,)` int, design index of that scratch, -1 outside scratches.
    - `role`: `(L,)` str: `comment`, `pre`, `travel`, `plunge`, `cut`, `retract`, `sync`, `post`.
    - `info`: dict of summary numbers (see `summarize`).
    """

    lines: list
    k: np.ndarray
    scratch: np.ndarray
    role: list
    info: dict


def check_program_lines(lines, lo=None, hi=None) -> dict:
    """The dry run's checker: line length, strict words (`jscratch.grbl.check_words`), bounds.

    **Arguments:** `lines` G-code text lines; `lo`, `hi` the allowed `(x, y, z)` limits in mm
    (None: no bounds check).

    **Returns:** the program's extents `{"x": [min, max], "y": .., "z": ..}` in mm (None for an axis
    never written). **Raises:** `InputError` naming the line.
    """
    ext = {a: None for a in "xyz"}
    for ln, text in enumerate(lines, start=1):
        if len(text) > MAX_LINE:
            raise InputError(f"G-code line {ln} is {len(text)} characters (> {MAX_LINE}): {clip(text, 40)!r}")
        try:
            check_words(text)
        except InputError as exc:
            raise InputError(f"G-code line {ln} {clip(text, 40)!r}: {exc}") from None
        if text.startswith("("):
            continue
        for word in text.split():
            axis = "XYZ".find(word[0])
            if axis >= 0:
                v = float(word[1:])
                if lo is not None and not (lo[axis] - 5e-4 <= v <= hi[axis] + 5e-4):
                    raise InputError(f"G-code line {ln} {text!r}: {word[0]} = {v} outside [{lo[axis]:.3f}, {hi[axis]:.3f}] mm")
                e = ext["xyz"[axis]]
                ext["xyz"[axis]] = [v, v] if e is None else [min(e[0], v), max(e[1], v)]
    return ext


_NUM = r"(-?\d+\.\d{3})"
_LIMITS_RE = re.compile(rf"\(limits X{_NUM}:{_NUM} Y{_NUM}:{_NUM} Z{_NUM}:{_NUM} mm\)")


def limits_comment(lo, hi) -> str:
    """The comment line that records a program's allowed `(x, y, z)` ranges in mm, e.g.
    ``(limits X0.000:100.000 Y0.000:100.000 Z-0.100:1.000 mm)``; `read_program` checks every
    coordinate of the program against it."""
    ranges = (f"{a}{lo[i]:.3f}:{hi[i]:.3f}" for i, a in enumerate("XYZ"))
    return "(limits " + " ".join(ranges) + " mm)"


_DESIGN_RE = re.compile(r"\(design ([0-9a-f]{16})\)")


def design_comment(design) -> str:
    """The comment line that records which design a program carves (`Design.digest`), e.g.
    ``(design 0123456789abcdef)``."""
    return f"(design {design.digest()})"


def program_design(lines) -> str | None:
    """The design digest a program's `design_comment` records, or None (a program without one)."""
    for text in lines:
        m = _DESIGN_RE.fullmatch(text)
        if m:
            return m.group(1)
    return None


_DIGEST_RE = re.compile(r"\(sha256 ([0-9a-f]{16})\)")


def digest_comment(lines) -> str:
    """The comment line that records the first 16 hex digits of the SHA-256 of a program's other
    `lines` (joined with newlines); `read_program` refuses a program whose lines no longer match
    it (edited after jscratch checked and wrote it)."""
    return f"(sha256 {hashlib.sha256(chr(10).join(lines).encode('ascii')).hexdigest()[:16]})"


def _check_digest(lines, path):
    """`DesignFileError` unless exactly one line is the digest comment of the others."""
    at = [i for i, text in enumerate(lines) if _DIGEST_RE.fullmatch(text)]
    rest = [text for i, text in enumerate(lines) if i not in at]
    if len(at) != 1:
        raise DesignFileError(f"G-code file {path!r} has {len(at)} '(sha256 ..)' lines, not one: "
                              "write it with python -m jscratch.fabricate")
    if lines[at[0]] != digest_comment(rest):
        raise DesignFileError(f"G-code file {path!r} was changed after jscratch wrote and checked "
                              "it (its lines no longer match its sha256 line): write it again "
                              "with python -m jscratch.fabricate")


def _limits(lines, path):
    """The `(lo, hi)` of the program's limits comment; `DesignFileError` without one."""
    for text in lines:
        m = _LIMITS_RE.fullmatch(text)
        if m:
            v = [float(x) for x in m.groups()]
            return tuple(v[0::2]), tuple(v[1::2])
    raise DesignFileError(f"G-code file {path!r} has no '(limits X..:.. Y..:.. Z..:.. mm)' line, "
                          "so its depths and bounds cannot be checked: write it with "
                          "python -m jscratch.fabricate")


def write_program(prog: Program, gcode_path) -> str:
    """Write `gcode_path` and its line map `gcode_path + '.map.csv'` (line, k, scratch, role).

    **Returns:** the map's path.
    """
    gcode_path = os.fspath(gcode_path)
    with open(gcode_path, "w", encoding="ascii", newline="\n") as f:
        f.write("\n".join(prog.lines) + "\n")
    map_path = gcode_path + ".map.csv"
    with open(map_path, "w", encoding="ascii", newline="") as f:
        w = csv.writer(f)
        w.writerow(["line", "k", "scratch", "role"])
        for ln, (k, s, r) in enumerate(zip(prog.k.tolist(), prog.scratch.tolist(), prog.role), start=1):
            w.writerow([ln, k, s, r])
    return map_path


def read_program(gcode_path) -> Program:
    """Read a G-code file and its line map (as written by `write_program`); checks that every line
    is one `write_program` could write (length, words: `jscratch.grbl.check_words`), that every
    coordinate lies within the program's limits comment (`limits_comment`: no plunge deeper, no
    move off the board), that no line was changed since (`digest_comment`), and that the map
    agrees with the lines.

    **Raises:** `DesignFileError`, one line naming the file and the line or row, for a missing,
    unreadable or inconsistent program.
    """
    gcode_path = os.fspath(gcode_path)
    map_path = gcode_path + ".map.csv"
    for path, what in ((gcode_path, "G-code file"), (map_path, "line map")):
        if os.path.isdir(path):
            raise DesignFileError(f"{what} {path!r} is a folder, not a file")
        if not os.path.isfile(path):
            hint = " (write it with the G-code: python -m jscratch.fabricate)" if path == map_path else ""
            raise DesignFileError(f"{what} {path!r} does not exist{hint}")
    texts = []
    for path, what in ((gcode_path, "G-code file"), (map_path, "line map")):
        try:
            with open(path, encoding="ascii") as f:
                texts.append(f.read())
        except UnicodeDecodeError as exc:
            raise DesignFileError(f"{what} {path!r} is not ASCII text (byte {exc.start}): not a program "
                                  "written by jscratch") from None
    lines = texts[0].split("\n")
    rows = list(csv.reader(texts[1].splitlines()))[1:]
    if lines and lines[-1] == "":
        lines.pop()
    try:
        check_program_lines(lines)  # the words, then every coordinate against the limits comment
        check_program_lines(lines, *_limits(lines, gcode_path))
    except DesignFileError:
        raise
    except InputError as exc:
        raise DesignFileError(f"G-code file {gcode_path!r}: {exc}") from None
    _check_digest(lines, gcode_path)
    if len(rows) != len(lines):
        raise DesignFileError(f"line map {map_path!r} has {len(rows)} rows for {len(lines)} G-code lines")
    ks, ss, roles = [], [], []
    for i, row in enumerate(rows, start=1):
        try:
            if len(row) != 4 or int(row[0]) != i or row[3] not in ROLES:
                raise ValueError
            ks.append(int(row[1]))
            ss.append(int(row[2]))
        except ValueError:
            raise DesignFileError(f"line map {map_path!r}: row {i} {clip(','.join(row), 40)!r} is not "
                                  f"'{i},k,scratch,role' with a role from {ROLES}") from None
        roles.append(row[3])
    k = np.asarray(ks)
    syncs = [i for i, r in enumerate(roles) if r == "sync"]
    if [int(k[i]) for i in syncs] != list(range(len(syncs))):
        raise DesignFileError(f"line map {map_path!r}: scratch blocks are not numbered 0..{len(syncs) - 1} in order")
    return Program(lines, k, np.asarray(ss), roles, {"scratches": len(syncs)})


#: Machine options (`jscratch.machine.MachineProfile` fields) whose value a program writes: the
#: role of its lines and the word's letters (the board offset: the last line of the postamble,
#: the return to the board corner ``G0 X.. Y..``).
WRITTEN_OPTIONS = {"feed_mm_min": ("cut", "F"), "plunge_mm_min": ("plunge", "F"),
                   "safe_z_mm": ("retract", "Z"), "plunge_mm": ("plunge", "Z"),
                   "spindle_rpm": ("pre", "S"), "spinup_s": ("pre", "P"),
                   "board_offset_mm": ("post", "XY")}
#: Machine options that only change the time estimate, never a program's words.
ESTIMATE_ONLY = ("rapid_mm_min", "overhead_s")


def options_not_in_program(prog: Program, over: dict) -> list[str]:
    """The machine options in `over` (field -> value) that `prog` was not written with, each as
    ``"key = value (the program has W)"``: an option it writes (`WRITTEN_OPTIONS`) unless every
    line of its role carries the option's word, or one it does not write; `ESTIMATE_ONLY` never.
    `W` is the program's word, or how many different ones it has and their range."""
    out = []
    for key, value in over.items():
        if key in ESTIMATE_ONLY:
            continue
        role, letters = WRITTEN_OPTIONS.get(key, (None, ""))
        values = value if key == "board_offset_mm" else [-value if key == "plunge_mm" else value]
        lines = [t for t, r in zip(prog.lines, prog.role)
                 if r == role and all(f" {a}" in t for a in letters)]
        if role == "post":
            lines = lines[-1:]
        found = sorted({" ".join(w for w in t.split() if w[0] in letters) for t in lines},
                       key=lambda ws: [float(w[1:]) for w in ws.split()])
        if found and found == [" ".join(gword(a, v) for a, v in zip(letters, values))]:
            continue  # every line already has this value
        if key == "spindle_rpm" and value == 0 and not lines:
            continue  # no spindle, as the program has none
        has = (found[0] if len(found) == 1 else
               f"{len(found)} values, {found[0]} to {found[-1]}" if found else None)
        out.append(f"{key} = {value!r}" + (f" (the program has {has})" if has else ""))
    return out
