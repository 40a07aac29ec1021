"""The error family: every refusal a user can meet is a `jscratch.JscratchError` of the right kind
with a one-line message naming what is wrong, and the command-line tools print it as one line
``error: ...``, exit 2 (input) or 4 (carving), and write nothing."""

import io
import os
import subprocess
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

from grbl_sim import GrblSim  # noqa: E402

import jscratch  # noqa: E402
from jscratch import bench, fabricate, loss, machine, metrics, preview  # noqa: E402
from jscratch.carve import carve  # noqa: E402
from jscratch.design.checkpoint import load_checkpoint  # noqa: E402
from jscratch.designfile import demo_design, load_design, save_design  # noqa: E402
from jscratch.errors import (  # noqa: E402
    CarveError,
    DesignFileError,
    InputError,
    JscratchError,
    NonFiniteError,
    exit_status,
    report,
)
from jscratch.gcode import check_program_lines, read_program, write_program  # noqa: E402
from jscratch.grbl import AlarmLocked, DeviceLost, GrblError, JobFault, NotGrblError, PortError, Stalled  # noqa: E402
from jscratch.journal import Journal, JournalError  # noqa: E402
from jscratch.machine import MachineProfile  # noqa: E402
from jscratch.render import render  # noqa: E402
from jscratch.scene import Board, Scratches, Views, views_on_circle  # noqa: E402

F32 = np.float32


def one_line(exc, *words):
    """The message of `exc`: one non-empty line holding each of `words`."""
    msg = str(exc.value if hasattr(exc, "value") else exc)
    assert msg and "\n" not in msg and len(msg) < 500, msg
    for w in words:
        assert w in msg, (w, msg)
    return msg


# ----------------------------------------------------------------------------------------------
# The family.


def test_the_family_tree():
    assert issubclass(InputError, JscratchError) and issubclass(InputError, ValueError)
    assert issubclass(DesignFileError, InputError)
    assert issubclass(NonFiniteError, JscratchError) and issubclass(NonFiniteError, RuntimeError)
    assert issubclass(CarveError, JscratchError) and issubclass(CarveError, RuntimeError)
    assert issubclass(jscratch.DesignError, InputError) and not issubclass(jscratch.DesignError, DesignFileError)
    for cls in (GrblError, PortError, NotGrblError, AlarmLocked, DeviceLost, JobFault, Stalled, JournalError,
                fabricate.CarveError):
        assert issubclass(cls, CarveError), cls
    # One class each, wherever it is imported from.
    from jscratch.design import DesignError, NonFiniteError as design_nonfinite
    from jscratch.design.config import NonFiniteError as config_nonfinite

    assert DesignError is jscratch.DesignError
    assert design_nonfinite is config_nonfinite is jscratch.NonFiniteError is NonFiniteError
    assert (jscratch.JscratchError, jscratch.InputError, jscratch.DesignFileError, jscratch.CarveError) == (
        JscratchError, InputError, DesignFileError, CarveError)
    assert [exit_status(e("x")) for e in (InputError, DesignFileError, NonFiniteError, CarveError)] == [2, 2, 3, 4]


@pytest.mark.parametrize("cls", [InputError, DesignFileError, NonFiniteError, CarveError, jscratch.DesignError,
                                 GrblError, JournalError, Stalled])
def test_except_jscratch_error_catches_each(cls):
    args = ("stopped", 3, "error:2") if issubclass(cls, JobFault) else ("stopped",)
    try:
        raise cls(*args)
    except jscratch.JscratchError as exc:
        assert str(exc) == "stopped"


def test_report_prints_one_line():
    buf = io.StringIO()
    assert report(CarveError("stopped\n  at line 3"), buf) == 4 and buf.getvalue() == "error: stopped at line 3\n"
    buf = io.StringIO()
    assert report(PermissionError(13, "Permission denied", "/x/job.gcode"), buf) == 1
    assert buf.getvalue() == "error: Permission denied: '/x/job.gcode'\n"


# ----------------------------------------------------------------------------------------------
# The library.


def test_scene_wrong_shapes_nan_and_off_board():
    p = np.full((3, 2), 0.1, F32)
    with pytest.raises(InputError) as e:
        Scratches(np.zeros((3, 3), F32), p)
    one_line(e, "Scratches", "p0", "(N, 2)", "(3, 3)")
    with pytest.raises(InputError) as e:
        Scratches(p, p + 0.01, width=np.ones(2, F32))
    one_line(e, "width", "(3,)", "(2,)")
    with pytest.raises(InputError) as e:
        Scratches(p, p + 0.01, width=np.array([1e-4, np.nan, 1e-4], F32))
    one_line(e, "scratch 1", "width", "not finite")
    with pytest.raises(InputError) as e:
        Views(np.ones((2, 3), F32), np.ones((3, 3), F32))
    one_line(e, "camera", "light", "same shape")
    with pytest.raises(InputError) as e:
        Board(shape=(0, 16))
    one_line(e, "shape")
    with pytest.raises(InputError) as e:
        views_on_circle(3, 50.0)
    one_line(e, "theta", "[0, pi/2)", "radians")
    board = Board(shape=(16, 16))
    views = views_on_circle(3, 0.8, board=board, dtype=F32)
    off = Scratches(np.array([[0.1, 0.1], [0.2, 0.1]], F32), np.array([[0.12, 0.1], [0.5, 0.1]], F32))
    with pytest.raises(InputError) as e:
        render(off, views, board)
    one_line(e, "scratch 1", "p1", "off the board", "[0, 0.3]")


def test_loss_metrics_and_fit_refuse_bad_arguments():
    for kw, words in (({"kind": "vgg"}, ("LossConfig.kind", "one of", "'vgg'")),
                      ({"lambda_p": float("nan")}, ("LossConfig.lambda_p", ">= 0", "nan")),
                      ({"lambda_x": -1.0}, ("LossConfig.lambda_x", ">= 0")),
                      ({"ghost_baseline": "mean"}, ("LossConfig.ghost_baseline", "'targets' or 'zero'"))):
        with pytest.raises(InputError) as e:
            loss.LossConfig(**kw)
        one_line(e, *words)
    with pytest.raises(InputError) as e:
        loss.make_loss({"kind": "l2"})
    one_line(e, "LossConfig", "dict")
    t = np.zeros((2, 16, 16), F32)
    with pytest.raises(InputError) as e:
        loss.l2_loss(t, np.zeros((3, 16, 16), F32))
    one_line(e, "target", "same shape")
    with pytest.raises(InputError) as e:
        metrics.image_metrics(np.full((2, 16, 16), np.nan, F32), t)
    one_line(e, "display_images", "non-finite")
    with pytest.raises(InputError) as e:
        fabricate.fit_plunge(np.ones(2), np.ones(2), -1.0)
    one_line(e, "radius", "> 0")
    with pytest.raises(InputError) as e:
        check_program_lines(["G0 X500.000 Y0.000"], (0, 0, -1), (300, 300, 1))
    one_line(e, "line 1", "X = 500.0", "[0.000, 300.000]")


def test_unreadable_and_malformed_design_files(tmp_path):
    text = tmp_path / "notes.npz"
    text.write_text("this is a text file, not a design\n")
    with pytest.raises(DesignFileError) as e:
        load_design(text)
    msg = one_line(e, str(text), "not a readable .npz design file")
    assert "pickle" not in msg
    with pytest.raises(DesignFileError) as e:
        load_design(tmp_path / "missing.npz")
    one_line(e, "missing.npz", "does not exist")
    with pytest.raises(DesignFileError) as e:
        load_design(tmp_path)
    one_line(e, "folder")
    np.save(tmp_path / "one.npy", np.zeros(3))
    os.replace(tmp_path / "one.npy", tmp_path / "one.npz")
    with pytest.raises(DesignFileError):
        load_design(tmp_path / "one.npz")
    d = demo_design(5)
    arrays = {k: v for k, v in d._asdict().items() if v is not None}
    arrays["width"] = arrays["width"].copy()
    arrays["width"][2] = np.nan
    np.savez(tmp_path / "nan.npz", **arrays)
    with pytest.raises(DesignFileError) as e:
        load_design(tmp_path / "nan.npz")
    one_line(e, "nan.npz", "scratch 2", "width", "not finite")
    # Saving refuses the same arrays as bad input (a DesignError), writing nothing.
    with pytest.raises(jscratch.DesignError) as e:
        save_design(tmp_path / "never.npz", **arrays)
    one_line(e, "scratch 2")
    assert not (tmp_path / "never.npz").exists()


def test_unreadable_checkpoint(tmp_path):
    (tmp_path / "ck.npz").write_text("junk")
    with pytest.raises(DesignFileError) as e:
        load_checkpoint(str(tmp_path / "ck.npz"), None, None, "")
    one_line(e, "ck.npz", "not a readable jscratch checkpoint")
    with pytest.raises(DesignFileError) as e:
        load_checkpoint(str(tmp_path / "none.npz"), None, None, "")
    one_line(e, "resume: no checkpoint", "none.npz")


@pytest.mark.parametrize("content,words", [
    ("cutter_radius_mm = = 1\n", ("not a valid TOML machine profile",)),
    ("[machine]\nfeed_mm_min = -3.0\n", ("machine.feed_mm_min", "> 0", "-3.0")),
    ("[machine]\nfeed = 900.0\n", ("unknown machine setting machine.feed", "known:")),
    (b"\xff\xfe\x00binary", ("not a valid TOML machine profile",)),
])
def test_bad_machine_profile_files(tmp_path, content, words):
    path = tmp_path / "m.toml"
    (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
    with pytest.raises(DesignFileError) as e:
        MachineProfile.from_toml(path)
    one_line(e, str(path), *words)


def test_missing_machine_profile_and_bad_values(tmp_path):
    with pytest.raises(DesignFileError) as e:
        MachineProfile.from_toml(tmp_path / "none.toml")
    one_line(e, "none.toml", "does not exist")
    with pytest.raises(InputError) as e:
        MachineProfile(plunge_min_mm=0.2)
    one_line(e, "machine.plunge_min_mm", "< plunge_max_mm = 0.1", "0.2")


@pytest.fixture(scope="module")
def program(tmp_path_factory):
    """A small valid G-code program with its line map."""
    path = tmp_path_factory.mktemp("prog") / "job.gcode"
    prog = fabricate.make_program(demo_design(6, seed=3), MachineProfile(plunge_mm=0.05), time_limit=0.2)
    write_program(prog, path)
    return path


@pytest.mark.parametrize("mangle,words", [
    ("no_map", ("line map", "does not exist")),
    ("bad_word", ("line 2", "G-code word", "'X1e2'")),
    ("long_line", ("line 1", "characters (> 79)")),
    ("short_map", ("line map", "rows for")),
    ("bad_role", ("row 3", "role")),
    ("binary", ("not ASCII text",)),
])
def test_bad_gcode_files(tmp_path, program, mangle, words):
    path = tmp_path / "bad.gcode"
    lines = program.read_text().splitlines()
    rows = (program.parent / (program.name + ".map.csv")).read_text().splitlines()
    if mangle == "bad_word":
        lines[1] = "G0 X1e2 Y0.000"
    elif mangle == "long_line":
        lines[0] = "(" + "x" * 90 + ")"
    elif mangle == "short_map":
        rows = rows[:-1]
    elif mangle == "bad_role":
        rows[3] = rows[3].rsplit(",", 1)[0] + ",dance"
    path.write_text("\n".join(lines) + "\n") if mangle != "binary" else path.write_bytes(b"\x89PNG\r\n\x00\xff")
    if mangle != "no_map":
        (tmp_path / "bad.gcode.map.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(DesignFileError) as e:
        read_program(path)
    one_line(e, *words)
    # The carver refuses it before it opens any port, and writes no journal.
    with pytest.raises(DesignFileError):
        carve(path, str(tmp_path / "ttyNONE"), quiet=True)
    assert not (tmp_path / "bad.gcode.journal").exists()


def test_corrupt_journal_is_a_carve_error(tmp_path):
    path = tmp_path / "j.journal"
    path.write_text('{"type": "header", "gcode_sha256": "0"}\n[1, 2]\n{"type": "done", "k": 0}\n')
    with pytest.raises(CarveError) as e:
        Journal.check(path, "0", resume=True)
    one_line(e, "line 2 is corrupt")


def test_a_port_that_answers_nonsense(program, tmp_path):
    sim = GrblSim(not_grbl=b"\x00\xffHello, I am a modem\r\nATZ OK\r\n" * 3)
    try:
        with pytest.raises(CarveError) as e:
            carve(program, sim.port, quiet=True, banner_timeout=1.0, poll_interval=0.05)
    finally:
        sim.close()
    msg = one_line(e, "did not answer like GRBL", "no motion was sent")
    assert msg.isprintable() and msg.isascii()
    assert sim.wp.moves == [] and not os.path.exists(str(program) + ".journal")


# ----------------------------------------------------------------------------------------------
# The command lines.


def _cli(module, *args, cwd=None):
    """Run ``python -m module args`` (PYTHONPATH inherited); returns (status, stdout, stderr)."""
    r = subprocess.run([sys.executable, "-m", module, *map(str, args)], capture_output=True, text=True,
                       timeout=300, cwd=cwd)
    return r.returncode, r.stdout, r.stderr


def _one_error_line(err, *words):
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)


def test_cli_processes_print_one_line_and_write_nothing(tmp_path):
    text = tmp_path / "design.npz"
    text.write_text("not a design\n")
    out = tmp_path / "new" / "job"
    code, _, err = _cli("jscratch.fabricate", text, "--dry-run", "--out", out)
    assert code == 2
    _one_error_line(err, "design.npz", "not a readable .npz design file")
    code, _, err = _cli("jscratch.preview", text, "--out", out)
    assert code == 2
    _one_error_line(err, "not a readable .npz design file")
    bad = tmp_path / "bad.toml"
    bad.write_text("[machine]\nplunge_max_mm = 0.5\n")
    code, _, err = _cli("jscratch.machine", bad)
    assert code == 2
    _one_error_line(err, "machine.plunge_max_mm", "cutter_radius_mm")
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    code, _, err = _cli("jscratch.bench", "--quick", "--out", blocker / "bench")
    assert code == 2
    _one_error_line(err, "--out", "not a folder")
    assert not (tmp_path / "new").exists() and sorted(os.listdir(tmp_path)) == ["afile", "bad.toml", "design.npz"]


@pytest.mark.parametrize("args,words", [
    (["--demo-n", "0"], ("--demo-n", ">= 1")),
    (["--order-time", "nan"], ("--order-time", ">= 0")),
    (["--baud", "0"], ("--baud",)),
    (["--idle-timeout", "-1"], ("--idle-timeout", "> 0")),
    (["--port", "/dev/null"], ("--dry-run", "--port")),
    (["--resume"], ("--resume", "--port")),
    (["--feed", "-5"], ("--feed must be a finite number", "> 0")),
    (["--cutter-radius", "0.05"], ("machine.plunge_max_mm", "cutter_radius_mm")),
    (["--out", "{tmp}/new/"], ("--out", "prefix")),
    (["--machine", "{tmp}/none.toml"], ("none.toml", "does not exist")),
    (["--gcode", "{tmp}/none.gcode"], ("give a design or --gcode",)),
])
def test_fabricate_refuses_bad_options_before_any_work(tmp_path, monkeypatch, capsys, args, words):
    monkeypatch.chdir(tmp_path)
    design = tmp_path / "d.npz"
    d = demo_design(8)
    save_design(design, d.p0, d.p1, d.width, d.depth, d.alpha, d.board)
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    base = [str(design)] if "--demo-n" not in args else []
    out = ["--out", str(tmp_path / "new" / "job")] if "--out" not in args else []
    assert fabricate.main(base + ["--dry-run", "--quiet", "--order-time", "0.2"] + out + args) == 2
    _one_error_line(capsys.readouterr().err, *words)
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]


def test_fabricate_with_a_nonsense_port_exits_4(program, tmp_path, capsys, monkeypatch):
    # A port that is not there is refused before the program is written.
    assert fabricate.main(["--demo-n", "5", "--port", str(tmp_path / "ttyNONE"), "--out", str(tmp_path / "new" / "j"),
                           "--quiet"]) == 2
    _one_error_line(capsys.readouterr().err, "--port", "does not exist")
    assert os.listdir(tmp_path) == []
    # So are a relative name that is not there (typed without its /dev/), an empty name and a
    # path that is not a serial device.
    for port, words in (("ttyUSB9", "--port 'ttyUSB9' does not exist"),
                        ("", "--port is an empty path"), (".", "is not a serial device")):
        with monkeypatch.context() as m:
            m.chdir(tmp_path)
            assert fabricate.main(["--demo-n", "5", "--port", port, "--quiet"]) == 2
        _one_error_line(capsys.readouterr().err, words)
        assert os.listdir(tmp_path) == []
    sim = GrblSim(not_grbl=True)
    try:
        code = fabricate.main(["--gcode", str(program), "--port", sim.port, "--quiet", "--banner-timeout", "1"])
    finally:
        sim.close()
    assert code == 4
    _one_error_line(capsys.readouterr().err, "did not answer like GRBL")
    assert not os.path.exists(str(program) + ".journal")


def test_fabricate_gcode_without_port_only_checks_the_program(program, tmp_path, capsys):
    assert fabricate.main(["--gcode", str(program)]) == 0
    assert "checked program of 6 scratches" in capsys.readouterr().out
    bad = tmp_path / "bad.gcode"
    bad.write_text("G0 X1.000 Y1.000\n")
    assert fabricate.main(["--gcode", str(bad)]) == 2
    _one_error_line(capsys.readouterr().err, "line map", "does not exist")


@pytest.mark.parametrize("args,words", [
    (["--frames", "1"], ("--frames", "[2, 3600]")),
    (["--frames", "4000"], ("--frames", "[2, 3600]")),
    (["--size", "4"], ("--size", "[8, 4096]")),
    (["--size", "30000"], ("--size", "[8, 4096]")),
    (["--batch", "0"], ("--batch", ">= 1")),
    (["--fps", "inf"], ("--fps", "[0.1, 50]")),
    (["--fps", "0.001"], ("--fps", "[0.1, 50]")),  # a GIF frame delay past 16 bits
    (["--intensity", "-1"], ("--intensity", "> 0")),
    (["--out", "TMP/d.npz/sub/x"], ("--out", "d.npz' exists and is not a folder")),
])
def test_preview_refuses_bad_options(tmp_path, capsys, args, words):
    d = demo_design(4)
    save_design(tmp_path / "d.npz", d.p0, d.p1, d.width, d.depth, d.alpha, d.board)
    args = [a.replace("TMP", str(tmp_path)) for a in args]
    assert preview.main([str(tmp_path / "d.npz"), "--quiet", "--out", str(tmp_path / "o" / "p")] + args) == 2
    _one_error_line(capsys.readouterr().err, *words)
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]
    # A design without views has nothing to orbit: refused before rendering.
    assert preview.main([str(tmp_path / "d.npz"), "--quiet", "--out", str(tmp_path / "o" / "p")]) == 2
    _one_error_line(capsys.readouterr().err, "no views")
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]


def test_machine_and_bench_usage_errors(tmp_path, capsys):
    assert machine.main(["a.toml", "b.toml"]) == 2
    _one_error_line(capsys.readouterr().err, "at most one FILE")
    assert machine.main([str(tmp_path / "none.toml")]) == 2
    _one_error_line(capsys.readouterr().err, "none.toml", "does not exist")
    with pytest.raises(SystemExit) as e:
        bench.main(["--sections", "everything", "--out", str(tmp_path / "b")])
    assert e.value.code == 2 and not (tmp_path / "b").exists()
    _one_error_line(capsys.readouterr().err, "--sections", "invalid choice", "see --help")
    with pytest.raises(InputError, match=r"unknown bench sections \['everything'\]"):
        bench.run_bench(["everything"], out=tmp_path / "b")
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("main", [fabricate.main, preview.main, bench.main])
def test_help_states_the_exit_statuses(main, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "exit status: 0 done" in text and "2 refused input" in text and "4 carving" in text


def test_machine_help_states_the_exit_statuses(capsys):
    assert machine.main(["--help"]) == 0
    assert "2 refused input" in capsys.readouterr().out


def test_negative_numbers_in_exponent_form_are_values_not_options(capsys):
    """`--offset -1e-4 0` is two numbers (argparse before Python 3.13 read `-1e-4` as an option
    and refused the line); a refused option is one line."""
    args = fabricate._parser().parse_args(["d.npz", "--offset", "-1e-4", "-2.5E+1"])
    assert args.board_offset_mm == [-1e-4, -25.0]
    with pytest.raises(SystemExit) as e:
        fabricate._parser().parse_args(["d.npz", "--offset", "-1e-4"])
    assert e.value.code == 2
    _one_error_line(capsys.readouterr().err, "--offset", "expected 2 arguments", "see --help")


def test_real_number_reads_one_number_in_any_scalar_form():
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jscratch.errors import real_number

    for v, want in ((2, 2.0), (2.5, 2.5), (np.float32(0.5), 0.5), (np.int64(3), 3.0),
                    (jnp.float32(0.25), 0.25), (np.array(4.0), 4.0)):
        assert real_number(v) == want, v
    assert np.isnan(real_number(float("nan")))  # a number: the callers check the range
    for v in (None, True, "1", b"1", [1.0], np.array([1.0]), np.zeros((2, 2)), object()):
        assert real_number(v) is None, v
    assert jax.jit(lambda x: x * (real_number(x) is None))(3.0) == 3.0  # a tracer is no number


def test_whole_number_and_count_arg_read_counts_in_any_integer_form():
    import numpy as np

    from jscratch.errors import count_arg, whole_number

    for v in (3, np.int32(3), np.int64(3)):
        assert whole_number(v) == 3 and count_arg("f", "n", v, 1) == 3
    for v in (True, 3.0, "3", None, np.array(3), [3]):
        assert whole_number(v) is None, v
        with pytest.raises(InputError, match=r"^f: `n` must be an int >= 1, got "):
            count_arg("f", "n", v, 1)
    with pytest.raises(InputError, match=r"^f: `n` must be an int >= 1, got 0$"):
        count_arg("f", "n", 0, 1)
