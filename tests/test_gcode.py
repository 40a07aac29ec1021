"""Tests of jscratch.gcode (with the program `fabricate.make_program` writes): every line in the strict
GRBL 1.1 grammar of the simulator's checker (tests/grbl_sim.py, itself checked on bad lines), in
bounds, the line map (scratch and role of every line) surviving the write/read round trip, and
`check_program_lines`' refusals."""

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

from grbl_sim import GcodeError, check_line  # noqa: E402

from jscratch import gcode  # noqa: E402
from jscratch.designfile import DesignError, demo_design  # noqa: E402
from jscratch.errors import DesignFileError  # noqa: E402
from jscratch.fabricate import MachineConfig, make_program, read_program, write_program  # noqa: E402


@pytest.fixture(scope="module")
def small():
    d = demo_design(24, seed=2)
    prog = make_program(d, MachineConfig(plunge_mm=0.1, safe_z_mm=1.0), time_limit=5)
    return d, prog


def _check_program(d, prog, cfg):
    state = {}
    n = d.n
    seen = []
    for ln, (text, k, s, role) in enumerate(zip(prog.lines, prog.k, prog.scratch, prog.role), start=1):
        words = check_line(text, state)  # strict GRBL 1.1 grammar, modal state carried
        assert len(text) < 80
        for a, lo, hi in (("X", 0, 1000 * d.board[0]), ("Y", 0, 1000 * d.board[1]), ("Z", -cfg.cutter_radius_mm, cfg.safe_z_mm)):
            if a in words:
                assert lo - 1e-9 <= words[a] <= hi + 1e-9, (ln, text)
        if role == "travel":
            entry = (words["X"], words["Y"])
            seen.append(s)
            ends = 1000 * np.array([d.p0[s], d.p1[s]])
            side = int(np.argmin(np.linalg.norm(ends - entry, axis=1)))
            assert np.allclose(ends[side], entry, atol=6e-4), (ln, text)
        if role == "cut":
            assert np.allclose(ends[1 - side], (words["X"], words["Y"]), atol=6e-4), (ln, text)
        if role in ("travel", "plunge", "cut", "retract", "sync"):
            assert k == len(seen) - 1 and s == seen[-1]
        if role == "plunge":
            assert words["Z"] < 0 and set(words) >= {"Z", "F"}
        if role == "sync":
            assert text == "G4 P0.000"  # fixed decimals (jscratch.grbl.gword)
    assert sorted(seen) == list(range(n))
    assert state["units"] == 21 and state["distance"] == 90



def test_gcode_grammar_bounds_and_line_map(tmp_path, small):
    d, prog = small
    _check_program(d, prog, MachineConfig(plunge_mm=0.1))
    write_program(prog, tmp_path / "p.gcode")
    back = read_program(tmp_path / "p.gcode")
    assert back.lines == prog.lines and np.array_equal(back.k, prog.k) and back.role == prog.role
    # Fitted plunge, offset board and a margin: still in grammar and bounds.
    cfg = MachineConfig(board_offset_mm=(10.0, 20.0), cutter_radius_mm=0.125, fit="global")
    p2 = make_program(d, cfg, time_limit=2)
    xs = [float(w[1:]) for t in p2.lines if not t.startswith("(") for w in t.split() if w[0] == "X"]
    assert min(xs) >= 10.0 and max(xs) <= 310.0
    assert p2.info["fit"]["mode"] == "global"



def test_grammar_checker_rejects_bad_lines():
    bad = {"G1 X1 Y2": 22, "G0 X1 X2": 25, "G0 G1 X1": 21, "G4": 26, "G4 P-1": 4, "g0 x1": 1, "G0  X1": 1,
           "G0 X1.2.3": 2, "G7 X1": 20, "Q1": 20, "G0 X" + "1" * 80: 14, "G0 (X1": 1, "X1": 31}
    for line, code in bad.items():
        with pytest.raises(GcodeError) as e:
            check_line(line, {})
        assert e.value.code == code, line
    check_line("G1 X1 Y2 F900 (comment) ; more", {})


def test_check_program_lines_extents_and_refusals(small):
    d, prog = small
    lo, hi = (0.0, 0.0, -1.0), (300.0, 300.0, 5.0)
    ext = gcode.check_program_lines(prog.lines, lo, hi)
    # the extents by hand: every X, Y, Z word of the program
    words = [w for t in prog.lines if not t.startswith("(") for w in t.split()]
    for axis in "XYZ":
        vals = [float(w[1:]) for w in words if w[0] == axis]
        assert ext[axis.lower()] == [min(vals), max(vals)]
    assert gcode.check_program_lines(["(only a comment)"], lo, hi) == {"x": None, "y": None, "z": None}
    with pytest.raises(ValueError, match=r"G-code line 2 .*X = 301.0 outside \[0.000, 300.000\] mm"):
        gcode.check_program_lines(["G0 Z1.000", "G0 X301.000 Y0.000"], lo, hi)
    with pytest.raises(ValueError, match=r"G-code line 1 is 80 characters \(> 79\)"):
        gcode.check_program_lines(["(" + "x" * 78 + ")"], lo, hi)
    with pytest.raises(ValueError, match="G-code line 1 'G0 X1e2 Y0.000'"):
        gcode.check_program_lines(["G0 X1e2 Y0.000"], lo, hi)


@pytest.mark.parametrize("edit, words", [
    (("G1 Z-0.100 F300.0", "G1 Z-9.000 F300.0"), "Z = -9.0 outside [-0.100, 1.000]"),
    (("G0 Z1.000", "G0 Z25.000"), "Z = 25.0 outside [-0.100, 1.000]"),
    ("travel", "Y = 99999.0 outside [0.000, 300.000]"),
    (("(limits ", "(bounds "), "has no '(limits X..:.. Y..:.. Z..:.. mm)' line"),
    # Edits within the limits, and limits widened to let an edit through, break the digest.
    (("F900.0", "F100.0"), "was changed after jscratch wrote and checked it"),
    ((("Z-0.100:", "Z-9.000:"), ("G1 Z-0.100 F300.0", "G1 Z-9.000 F300.0")), "was changed"),
    (("(sha256 ", "(sha-256 "), "has 0 '(sha256 ..)' lines, not one"),
])
def test_read_program_refuses_coordinates_outside_its_limits(tmp_path, small, edit, words):
    """A program read back (what `--gcode` streams) is checked against the limits comment that
    `make_program` wrote: a hand-edited plunge, height or move off the board is refused in one
    line naming the line; a program without the comment cannot be checked and is refused; and
    a program edited in any other way no longer matches its digest line and is refused."""
    _, prog = small
    path = tmp_path / "p.gcode"
    gcode.write_program(prog, path)
    assert gcode.limits_comment((0, 0, -0.1), (300, 300, 1)) in prog.lines
    text = path.read_text()
    if edit == "travel":
        i = prog.role.index("travel") + 5 * 3
        old = prog.lines[i]
        text = text.replace(old + "\n", old.split(" Y")[0] + " Y99999.000\n", 1)
    else:
        for a, b in edit if isinstance(edit[0], tuple) else (edit,):
            assert a in text
            text = text.replace(a, b, 1)
    path.write_text(text)
    with pytest.raises(DesignFileError) as e:
        gcode.read_program(path)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_read_program_refuses_a_missing_or_mismatched_map(tmp_path, small):
    _, prog = small
    path = tmp_path / "p.gcode"
    with pytest.raises(DesignFileError, match="does not exist"):
        gcode.read_program(path)
    map_path = gcode.write_program(prog, path)
    os.remove(map_path)
    with pytest.raises(DesignFileError, match="line map .* does not exist"):
        gcode.read_program(path)
    gcode.write_program(prog, path)
    rows = open(map_path).read().splitlines()
    open(map_path, "w").write("\n".join(rows[:-1]) + "\n")
    with pytest.raises(ValueError, match=f"has {len(rows) - 2} rows for {len(rows) - 1} G-code lines"):
        gcode.read_program(path)


def test_options_not_in_program_reads_every_line_of_their_role():
    """An option counts as the program's only when every line of its role carries its word: a
    program of ten depths has no single plunge, and says how many it has and their range."""
    d = demo_design(10, seed=4)
    d = d._replace(depth=np.linspace(2e-5, 9e-5, 10))
    prog = make_program(d, MachineConfig(), time_limit=0.5)
    z = sorted({w for t, r in zip(prog.lines, prog.role) if r == "plunge"
                for w in t.split() if w[0] == "Z"}, key=lambda w: float(w[1:]))
    assert len(z) == 10
    deepest = -float(z[0][1:])
    got = gcode.options_not_in_program(prog, {"plunge_mm": deepest, "rapid_mm_min": 1.0})
    assert got == [f"plunge_mm = {deepest!r} (the program has 10 values, {z[0]} to {z[-1]})"]
    one = make_program(d, MachineConfig(plunge_mm=0.05), time_limit=0.5)
    assert gcode.options_not_in_program(one, {"plunge_mm": 0.05}) == []
    assert gcode.options_not_in_program(one, {"plunge_mm": 0.06}) == [
        "plunge_mm = 0.06 (the program has Z-0.050)"]


def test_make_program_refuses_an_endpoint_off_the_board():
    """A design built in Python is checked as a loaded one is: an endpoint 50 mm off the board is
    refused, not clipped onto its edge (which would cut another scratch)."""
    d = demo_design(5, seed=1)
    p1 = d.p1.copy()
    p1[0] = [d.board[0] + 0.05, 0.1]
    with pytest.raises(DesignError, match=r"^make_program: design: scratch 0: p1 = \(0.35, 0.1\) m "
                                          r"lies off the board"):
        make_program(d._replace(p1=p1), MachineConfig(plunge_mm=0.05), time_limit=0.5)
