"""Tests of jscratch.fabricate: the cutter fit against a grid search, bad designs refused with
clear errors, the dry-run CLI and its outputs, fixed-point words, the summary's bounds. Ordering is
tested in test_toolpath.py, the G-code in test_gcode.py, streaming to the controller in
test_carve.py."""

import json
import os
import re
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

from grbl_sim import check_line  # noqa: E402

from jscratch.designfile import demo_design, save_design  # noqa: E402
from jscratch.fabricate import (  # noqa: E402
    MachineConfig, fit_plunge, main, make_program, read_program, summarize,
)
from jscratch.grbl import check_words  # noqa: E402


# ----------------------------------------------------------------------------------------------
# Cutter fit.


def _brute_plunge(w, dd, R):
    xm = 0.5 * w * np.sqrt(-np.expm1(-2 * dd / w))
    x = 1.25 * xm * np.linspace(-1, 1, 64)
    inside = np.abs(x) < xm
    h = np.where(inside, -0.5 * w * np.log1p(-4 * np.where(inside, x, 0) ** 2 / w**2) - dd, 0.0)
    ps = np.linspace(1e-4, 0.999, 200001) * R
    cut = np.minimum(R - ps[:, None] - np.sqrt(np.maximum(R**2 - x**2, 0)), 0)
    err = np.sqrt(np.mean((cut - np.minimum(h, 0)) ** 2, axis=1))
    i = int(np.argmin(err))
    return ps[i], err[i]


def test_fit_plunge_matches_grid_search_and_flags_unreachable():
    w = np.array([2.5e-4, 1e-4, 2.5e-4, 3e-4])
    dd = np.array([1.28e-4, 1e-4, 1.28e-4, 0.5e-4])
    R = 1.25e-4
    fit = fit_plunge(w, dd, R)
    for i in range(4):
        p, e = _brute_plunge(w[i], dd[i], R)
        assert abs(fit.plunge[i] - p) < 2e-3 * R, (i, fit.plunge[i], p)
        assert abs(fit.rms[i] - e) < 1e-3 * e + 1e-12
    assert fit.plunge[0] == fit.plunge[2]
    np.testing.assert_allclose(fit.cut_width, 2 * np.sqrt(2 * R * fit.plunge - fit.plunge**2))
    assert not fit.unreachable[0] and fit.unreachable[1]  # w = d = 1e-4: far too narrow for R = 0.125 mm
    g = fit_plunge(w, dd, R, mode="global")
    assert np.all(g.plunge == g.plunge[0]) and fit.plunge.min() <= g.plunge[0] <= fit.plunge.max()
    with pytest.raises(ValueError, match="radius must be"):
        fit_plunge(w, dd, -1.0)


# ----------------------------------------------------------------------------------------------
# G-code.


def _deepest_z(prog) -> float:
    return min(float(w[1:]) for line in prog.lines if not line.startswith("(")
               for w in line.split() if w[0] == "Z")


def test_no_plunge_deeper_than_the_profile_allows():
    """Every `Z` of a program is at least `-plunge_max_mm`: a recorded plunge below it is refused
    in one line naming the scratch; a fitted one is cut at `plunge_max_mm` (or `plunge_min_mm`)
    and counted unreachable."""
    from jscratch.designfile import DesignError

    cfg = MachineConfig()
    d = demo_design(12, seed=5)
    plunge = np.full(12, 0.05e-3)
    plunge[7] = 2e-3  # a hand-made file: 2 mm with a 0.125 mm ball
    deep = d._replace(plunge=plunge)
    with pytest.raises(DesignError, match=r"scratch 7 has a recorded plunge of 2 mm, deeper than "
                                          r"machine.plunge_max_mm = 0.1 mm \(1 such") as e:
        make_program(deep, cfg, time_limit=0.5)
    assert "\n" not in str(e.value)
    fitted = make_program(d, cfg, time_limit=0.5)
    raw = 1000 * fit_plunge(d.width, d.depth, cfg.cutter_radius_mm / 1000).plunge
    assert raw.max() > cfg.plunge_max_mm  # the demo's grooves fit 0.1016 mm: the case is exercised
    assert _deepest_z(fitted) == -cfg.plunge_max_mm
    n_out = int(((raw > cfg.plunge_max_mm) | (raw < cfg.plunge_min_mm)).sum())
    assert fitted.info["fit"]["clamped"] == n_out and fitted.info["fit"]["unreachable"] >= n_out
    assert fitted.info["limits_mm"]["z"][0] == -cfg.plunge_max_mm
    assert "cut at its nearest end" in summarize(fitted.info)
    shallow = d._replace(plunge=np.where(np.arange(12) % 5 == 1, 1e-10, 0.05e-3))
    with pytest.raises(DesignError, match=r"^scratch 1 has a recorded plunge of 1e-07 mm, "
                                          r"shallower than machine.plunge_min_mm = 0.005 mm "
                                          r"\(3 such.*outside the profile's plunge range"):
        make_program(shallow, cfg, time_limit=0.5)  # (written as Z0.000: not cut at all)


def test_a_design_is_not_carved_with_another_cutter_than_it_records():
    """`make_program` on a design that records its machine: another cutter (`CUT_KEYS`) is
    refused in one line, as `machine_for_design` refuses it, unless `override_machine`; the
    recorded profile and a feed change are carved."""
    from jscratch.errors import InputError
    from jscratch.fabricate import machine_for_design
    from jscratch.machine import MachineProfile

    rec = MachineProfile()
    d = demo_design(8, seed=1)
    d = d._replace(machine=rec.to_dict(), plunge=np.full(8, 0.5 * rec.plunge_max_mm / 1000))
    other = MachineProfile.from_dict(rec.to_dict(), cutter_radius_mm=0.5)
    with pytest.raises(InputError, match=r"^make_program: the design was made for another "
                                         r"cutter: cutter_radius_mm 0.125 \(design\) vs 0.5") as e:
        make_program(d, other, time_limit=0.2)
    assert "\n" not in str(e.value)
    assert make_program(d, other, time_limit=0.2, override_machine=True).info["scratches"] == 8
    same = make_program(d, machine_for_design(d, None, {}), time_limit=0.2)
    faster = MachineProfile.from_dict(rec.to_dict(), feed_mm_min=2 * rec.feed_mm_min)
    assert make_program(d, faster, time_limit=0.2).info["scratches"] == same.info["scratches"]
    with pytest.raises(InputError, match="^make_program: cfg must be a MachineProfile"):
        make_program(d, {"cutter_radius_mm": 0.125}, time_limit=0.2)
    with pytest.raises(InputError, match="^make_program: design must be a jscratch Design"):
        make_program("design.npz", rec, time_limit=0.2)


@pytest.fixture(scope="module")
def small():
    d = demo_design(24, seed=2)
    prog = make_program(d, MachineConfig(plunge_mm=0.1, safe_z_mm=1.0), time_limit=5)
    return d, prog


def test_zero_length_and_bad_design_give_clear_errors(tmp_path, capsys):
    d = demo_design(10, seed=1)
    p1 = d.p1.copy()
    p1[6] = d.p0[6]
    save_design(tmp_path / "z.npz", d.p0, p1, d.width, d.depth, d.alpha, d.board)
    assert main([str(tmp_path / "z.npz"), "--dry-run", "--quiet", "--plunge", "0.1"]) == 2
    assert "scratch 6 has length 0 mm" in capsys.readouterr().err
    assert not (tmp_path / "z.gcode").exists()
    # --drop-short skips it.
    assert main([str(tmp_path / "z.npz"), "--dry-run", "--quiet", "--plunge", "0.1", "--drop-short"]) == 0
    assert read_program(tmp_path / "z.gcode").info["scratches"] == 9
    # ... but a length that drops every scratch leaves nothing to cut: refused, nothing written
    capsys.readouterr()
    assert main([str(tmp_path / "z.npz"), "--dry-run", "--quiet", "--plunge", "0.1",
                 "--drop-short", "--min-length", "1e9", "--out", str(tmp_path / "all")]) == 2
    assert "every scratch (10) is shorter than" in capsys.readouterr().err
    assert not list(tmp_path.glob("all*"))
    arr = {k: v for k, v in d._asdict().items() if v is not None}
    arr["p0"] = arr["p0"].copy()
    arr["p0"][3, 1] = np.nan
    np.savez(tmp_path / "nan.npz", **arr)
    assert main([str(tmp_path / "nan.npz"), "--dry-run", "--quiet"]) == 2
    assert "scratch 3: p0" in capsys.readouterr().err
    arr["p0"][3, 1] = 0.5
    np.savez(tmp_path / "off.npz", **arr)
    assert main([str(tmp_path / "off.npz"), "--dry-run", "--quiet"]) == 2
    assert "off the board" in capsys.readouterr().err


def test_cli_dry_run_makes_the_output_folder(tmp_path):
    """`--out NEWDIR/job` with NEWDIR missing (and nested): made, as the design command does."""
    prefix = tmp_path / "new" / "deeper" / "job"
    assert main(["--dry-run", "--quiet", "--demo-n", "12", "--order-time", "1",
                 "--out", str(prefix)]) == 0
    for suffix in (".gcode", ".gcode.map.csv", ".preview.png", ".summary.json"):
        assert (tmp_path / "new" / "deeper" / ("job" + suffix)).stat().st_size > 0


def test_cli_takes_a_design_runs_folder(tmp_path, capsys):
    """A design run's output folder stands for its design.npz (as preview takes it), with the
    same default output prefix; a folder without one is refused in one line."""
    d = demo_design(12, seed=1)
    (tmp_path / "run").mkdir()
    save_design(tmp_path / "run" / "design.npz", d.p0, d.p1, d.width, d.depth, d.alpha, d.board)
    assert main([str(tmp_path / "run"), "--dry-run", "--quiet", "--order-time", "1"]) == 0
    assert (tmp_path / "run" / "design.gcode").stat().st_size > 0
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), "--dry-run", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a folder without a design.npz" in err
    assert os.listdir(tmp_path / "empty") == []


def test_a_program_is_refused_beside_a_design_made_again_since(tmp_path, capsys):
    """A program records the design it carves (``(design ..)``): `--gcode` refuses one whose
    design file beside it (``X.npz`` for ``X.gcode``) is now another design (a design run made
    again in the folder), and takes it beside the same design written again, or alone."""
    run, gcode = tmp_path / "run", str(tmp_path / "run" / "design.gcode")
    run.mkdir()
    first, second = demo_design(12, seed=1), demo_design(14, seed=2)
    for d in (first, second):
        d.p0[0] += 1e-9 * (d is second)  # (another design, even by one coordinate)
    save_design(run / "design.npz", first.p0, first.p1, first.width, first.depth, first.alpha,
                first.board)
    assert main([str(run), "--dry-run", "--quiet", "--order-time", "0"]) == 0
    assert main(["--gcode", gcode, "--dry-run", "--quiet"]) == 0
    save_design(run / "design.npz", second.p0, second.p1, second.width, second.depth,
                second.alpha, second.board)
    assert main(["--gcode", gcode, "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err == (f"error: {gcode!r} carves another design than {str(run / 'design.npz')!r} "
                   "beside it (made again since?): write the program again with python -m "
                   f"jscratch.fabricate {run / 'design.npz'}, or move one of them away\n"), err
    save_design(run / "design.npz", first.p0, first.p1, first.width, first.depth, first.alpha,
                first.board)  # the same design, written again
    assert main(["--gcode", gcode, "--dry-run", "--quiet"]) == 0
    os.remove(run / "design.npz")
    assert main(["--gcode", gcode, "--dry-run", "--quiet"]) == 0


@pytest.mark.parametrize("argv, says", [
    (["--safe-z", "0"], "--safe-z must be a finite number > 0, got 0.0"),
    (["--cutter-radius", "nan"], "--cutter-radius must be a finite number > 0, got nan"),
])
def test_a_refused_machine_option_is_named_by_its_flag(argv, says, tmp_path, capsys):
    assert main(["--dry-run", "--demo-n", "5", "--out", str(tmp_path / "j"), *argv]) == 2
    assert capsys.readouterr().err == f"error: {says}\n"
    assert os.listdir(tmp_path) == []


def test_cli_refuses_an_empty_path_instead_of_carving_the_demo(tmp_path, capsys, monkeypatch):
    """``--gcode "$JOB"`` with JOB unset is an empty path, not "no option": refused in one line,
    nothing written (not the built-in demo design streamed instead)."""
    monkeypatch.chdir(tmp_path)
    for argv, opt in ((["--gcode", ""], "--gcode"), ([""], "the design"),
                      (["--machine", " "], "--machine"), (["--out", ""], "--out"),
                      (["--port", ""], "--port")):
        assert main(argv + ["--dry-run", "--quiet", "--demo-n", "5"]) == 2, argv
        err = capsys.readouterr().err
        assert re.fullmatch(rf"error: {opt} is an empty path .*\n", err), err
    assert os.listdir(tmp_path) == []


def test_cli_refuses_a_huge_feed_a_huge_margin_and_a_folder_in_short_lines(tmp_path, capsys):
    for argv, want in ((["--feed", "1e300"], r"word F1e\+300 is outside GRBL's range"),
                       (["--margin", "1e12"], r"--margin must be a finite number in "
                                              r"\[0, 1e4\] mm"),
                       (["--gcode", str(tmp_path)], r"G-code file .* is a folder, not a file"),
                       (["--offset", "99900", "0"], r"board_offset_mm \(--offset\) = \[99900.0, "
                                                    r"0.0\], plus margin_mm = 0, spans X 99900.000 "
                                                    r"to 10\d{4}.\d{3} mm, beyond GRBL's")):
        out = [] if "--gcode" in argv else ["--out", str(tmp_path / "a")]
        assert main(argv + out + ["--dry-run", "--quiet", "--demo-n", "5"]) == 2, argv
        err = capsys.readouterr().err
        assert re.search(want, err) and err.count("\n") == 1 and len(err) < 200, err
    assert os.listdir(tmp_path) == []


def test_a_malformed_metrics_json_beside_the_design_is_ignored(tmp_path, capsys):
    """The design run's ``metrics.json`` only adds the as-carved SSIM to the summary: one not in
    the design run's form is passed over (the summary says how to get the figure)."""
    d = demo_design(12, seed=1)
    save_design(tmp_path / "design.npz", d.p0, d.p1, d.width, d.depth, d.alpha, d.board)
    for bad in ('{"as_carved": {"ssim": 0.93}}', '{"as_carved": "ssim"}', '[1, 2]',
                '{"as_carved": {"ssim": ["a"]}}', '\u00ff'):
        (tmp_path / "metrics.json").write_text(bad)
        for f in tmp_path.glob("design.*"):
            if f.suffix != ".npz":
                f.unlink()
        assert main([str(tmp_path), "--dry-run", "--order-time", "0.5"]) == 0, bad
        out = capsys.readouterr().out
        if bad.startswith("{"):  # a design run's metrics without the figure
            assert "as carved        not computed" in out, (bad, out)
        summary = json.loads((tmp_path / "design.summary.json").read_text())
        assert summary.get("as_carved") is None, bad
    (tmp_path / "metrics.json").write_text('{"as_carved": {"ssim": [0.9, 0.8]}}')
    for f in tmp_path.glob("design.*"):
        if f.suffix != ".npz":
            f.unlink()
    assert main([str(tmp_path), "--dry-run", "--order-time", "0.5"]) == 0
    assert "SSIM vs the design render per view [0.9, 0.8]" in capsys.readouterr().out


def test_streaming_a_program_warns_only_of_options_it_does_not_have(tmp_path, capsys):
    """``--gcode`` (or ``--resume``) streams a program as written: the options given with it
    that the program has (its feed, offset, spindle, spin-up) pass silently, the others are
    named, and those that only change the time estimate never are."""
    prefix = str(tmp_path / "job")
    made = ["--dry-run", "--quiet", "--demo-n", "6", "--order-time", "0.5", "--out", prefix,
            "--offset", "5", "5", "--spindle", "12000", "--spinup", "0.5", "--feed", "600"]
    assert main(made) == 0
    same = ["--offset", "5", "5", "--spindle", "12000", "--spinup", "0.5", "--feed", "600",
            "--rapid", "2000"]
    assert main(["--gcode", prefix + ".gcode"] + same) == 0
    assert "not applied" not in capsys.readouterr().err
    assert main(["--gcode", prefix + ".gcode", "--offset", "5", "6", "--spinup", "1",
                 "--spindle", "0", "--fit", "global"]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and ("not applied: fit = 'global', board_offset_mm = [5.0, 6.0] "
                                      "(the program has X5.000 Y5.000), spindle_rpm = 0.0 (the "
                                      "program has S12000), spinup_s = 1.0 (the program has "
                                      "P0.500)") in err, err
    assert main(["--dry-run", "--quiet", "--demo-n", "6", "--order-time", "0.5", "--out",
                 prefix + "2"]) == 0
    assert main(["--gcode", prefix + "2.gcode", "--spindle", "0"]) == 0  # none, as it has none
    assert "not applied" not in capsys.readouterr().err


def test_cli_dry_run_demo(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["--dry-run", "--demo-n", "60", "--order-time", "2"]) == 0
    out = capsys.readouterr().out
    assert "unreachable" not in out  # the demo's grooves are ones the shipped machine cuts
    for key in ("scratches        60", "travel", "reduction", "estimated time", "bounds (mm)", "cutter fit"):
        assert key in out
    for f in ("jscratch_demo.gcode", "jscratch_demo.gcode.map.csv", "jscratch_demo.preview.png", "jscratch_demo.summary.json"):
        assert (tmp_path / f).stat().st_size > 0
    import skimage.io

    img = skimage.io.imread(tmp_path / "jscratch_demo.preview.png")
    assert img.ndim == 3 and img.shape[0] > 300
    info = json.loads((tmp_path / "jscratch_demo.summary.json").read_text())
    assert info["travel_mm"] < info["travel_input_mm"]


# ----------------------------------------------------------------------------------------------
# Words as the GRBL 1.1h firmware accepts them; the summary.


def test_words_are_fixed_point_without_exponent_and_the_dry_run_checks_them(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["--dry-run", "--quiet", "--demo-n", "12", "--order-time", "1", "--plunge", "0.1",
                 "--spindle", "1000000", "--feed", "1250000.04", "--plunge-feed", "0.25"]) == 0
    lines = (tmp_path / "jscratch_demo.gcode").read_text().splitlines()
    state = {}
    for text in lines:
        check_line(text, state)  # the strict grammar reads 'S1e+06' as a bad number
    for text in lines:
        check_words(text)
    code = [t for t in lines if not t.startswith("(")]
    assert "M3 S1000000" in code and not any(re.search(r"\d[eE]", t) for t in code)
    assert {w for t in code for w in t.split() if w[0] == "F"} == {"F1250000.0", "F0.2"}
    for bad in ("M3 S1e+06", "G1 X1.5 Y2.000 F900.0", "G1 Z-0.1000 F300.0", "G0 X1e2 Y0.000",
                "G0 Z123456.000", "G4 P-1.000", "G1 X0.000 Y0.000 F0.0", "G1 X0.000 Y0.000 F900", "G0 X+1.000"):
        with pytest.raises(ValueError, match="G-code word"):
            check_words(bad)
    for name, value in (("spindle_rpm", 1e9), ("feed_mm_min", 1e-3), ("spinup_s", 1e6)):
        with pytest.raises(ValueError, match=f"machine setting {name} .* does not fit GRBL"):
            MachineConfig(**{name: value})


def test_summary_bounds_are_the_programs_extents(small):
    d, prog = small
    words = [(w[0], float(w[1:])) for t in prog.lines if not t.startswith("(") for w in t.split() if w[0] in "XYZ"]
    ext = {a.lower(): [min(v for c, v in words if c == a), max(v for c, v in words if c == a)] for a in "XYZ"}
    assert prog.info["bounds_mm"] == ext
    assert prog.info["limits_mm"]["x"] == [0.0, 1000 * d.board[0]] and ext["x"][1] < 1000 * d.board[0]
    text = summarize(prog.info).splitlines()
    bounds = next(t for t in text if t.startswith("bounds (mm)"))
    assert f"X [{ext['x'][0]:.3f}, {ext['x'][1]:.3f}]" in bounds and "extents" in bounds
    assert any(t.startswith("limits (mm)") and "allowed" in t for t in text)




def test_fit_plunge_machine_for_design_and_groove_map_refuse_bad_arguments_by_name():
    from jscratch.design.carvable import groove_map
    from jscratch.errors import InputError
    from jscratch.fabricate import machine_for_design

    d = demo_design(5)
    cases = [
        (lambda: fit_plunge(1e-4, 1e-4, 1e-4), r"^fit_plunge: width and depth must have one shape"),
        (lambda: fit_plunge([1e-4, 2e-4], [1e-4], 1e-4), r"got \(2,\) and \(1,\)"),
        (lambda: fit_plunge([1e-4, -1.0], [1e-4, 1e-4], 1e-4),
         r"^fit_plunge: width\[1\] = -1.0 is not a finite length > 0"),
        (lambda: fit_plunge([1e-4], [float("nan")], 1e-4), r"^fit_plunge: depth\[0\] = nan"),
        (lambda: fit_plunge(["a"], [1e-4], 1e-4), r"^fit_plunge: width and depth must be arrays"),
        (lambda: fit_plunge([1e-4], [1e-4], None), r"^fit_plunge: radius must be a finite length"),
        (lambda: machine_for_design(None, None, {}), r"^machine_for_design: design must be"),
        (lambda: machine_for_design(d, {}, {}), r"^machine_for_design: file_profile must be"),
        (lambda: machine_for_design(d, None, [1]),
         r"^machine_for_design: overrides must be a dict"),
        (lambda: groove_map(1e-4, 1e-5, 5e-5, "x"),
         r"^groove map: criterion must be 'arc', 'slope', 'height' or 'cdf'"),
    ]
    for call, match in cases:
        with pytest.raises(InputError, match=match):
            call()
    assert machine_for_design(d, None, None) == machine_for_design(d, None, {})
    one = fit_plunge([2e-4], [5e-5], 1.25e-4).plunge
    for radius in (np.float32(1.25e-4), np.array(1.25e-4)):  # numbers as numpy scalars / 0-d
        np.testing.assert_allclose(fit_plunge([2e-4], [5e-5], radius).plunge, one, rtol=1e-5)
