"""`python -m jscratch.design` against the library: the same tiny design through the command line
and through `jscratch.design.design` from Python (each in its own process, as a user runs them)
gives identical files; ``--config`` repeats a run bit for bit; a saved result loads back into the
library's types and renders identically; a carvable one is carved as designed; bad options are
refused in one line with nothing written."""

import json
import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from jscratch.design import cli
from jscratch.design.io import (RESULT_FILES, load_result, remove_partial_writes, save_result,
                               settle_earlier)
from jscratch.design.config import DesignConfig, SceneConfig
from jscratch.designfile import DesignError
from jscratch.errors import DesignFileError

TINY = ["--size", "24", "--scratches", "150", "--iterations", "3", "--views", "2"]


def _run(args, cwd=None):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=cwd,
                          env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=600)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "out"
    proc = _run(["-m", "jscratch.design", *TINY, "--out", str(out), "--quiet"])
    assert proc.returncode == 0, proc.stderr
    return out


def _arrays(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _assert_same_files(a, b):
    for name in ("design.npz", "result.npz"):
        x, y = _arrays(a / name), _arrays(b / name)
        assert sorted(x) == sorted(y), name
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=f"{name}:{k}")
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert sorted(ma) == sorted(mb)
    for k in ("ssim", "kept", "loss", "pairs_total", "machine", "groove"):
        assert ma[k] == mb[k], k
    assert ma["carving"]["estimated_seconds"] == mb["carving"]["estimated_seconds"]


def test_cli_equals_python_defaults(cli_run, tmp_path):
    """The command line's defaults and `design()`'s are one: a notebook user who passes only the
    same sizes gets the same board, and `save_result` writes the same fields as the CLI."""
    out = tmp_path / "py"
    code = textwrap.dedent(f"""
        from jscratch.design import DesignConfig, SceneConfig, default_targets, design, save_result
        targets, _ = default_targets(2, (24, 24))
        result = design(targets, config=DesignConfig(n_scratches=150, iterations=3))
        save_result(result, {str(out)!r})
    """)
    proc = _run(["-c", code])
    assert proc.returncode == 0, proc.stderr
    _assert_same_files(cli_run, out)
    assert sorted(os.listdir(cli_run)) == sorted(os.listdir(out) + ["checkpoint.npz"])
    for name in RESULT_FILES:
        assert (out / name).is_file()


def test_config_file_repeats_the_run(cli_run, tmp_path):
    out = tmp_path / "again"
    proc = _run(["-m", "jscratch.design", "--config", str(cli_run / "config.json"), "--out",
                 str(out), "--quiet"])
    assert proc.returncode == 0, proc.stderr
    _assert_same_files(cli_run, out)
    saved = json.loads((out / "config.json").read_text())
    assert saved["design"] == json.loads((cli_run / "config.json").read_text())["design"]


def test_config_file_under_given_options(cli_run):
    """Options given on the command line win over the config file's."""
    _, scene, config = cli.configs(["--config", str(cli_run / "config.json"), "--seed", "7"])
    assert config.seed == 7 and config.n_scratches == 150 and scene.size == 24


def test_config_file_with_an_unknown_key_is_refused(cli_run, tmp_path):
    """A top-level key that no run writes (a typo, another tool's file) is refused, naming it, as
    unknown keys under ``design`` and ``scene`` are; every key a run writes is read."""
    saved = json.loads((cli_run / "config.json").read_text())
    assert set(saved) <= cli.CONFIG_KEYS and "run_id" in saved
    path = tmp_path / "config.json"
    path.write_text(json.dumps({**saved, "desing": {}}))
    with pytest.raises(DesignFileError, match="unknown key 'desing'"):
        cli.configs(["--config", str(path)])


def test_config_file_without_a_scene_needs_scene_options(cli_run, tmp_path, capsys):
    saved = json.loads((cli_run / "config.json").read_text())
    saved["scene"] = None  # as save_result writes it for a design made by design() in Python
    path = tmp_path / "config.json"
    path.write_text(json.dumps(saved))
    assert cli.main(["--config", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "has no scene" in capsys.readouterr().err and not (tmp_path / "o").exists()
    _, scene, config = cli.configs(["--config", str(path), "--size", "24", "--views", "2"])
    assert scene.size == 24 and config.n_scratches == 150
    # the image size and board side come from the saved board where it is square, unless given
    saved["board"] = {**saved["board"], "shape": [48, 48], "Sx": 0.2, "Sy": 0.2}
    path.write_text(json.dumps(saved))
    _, scene, _ = cli.configs(["--config", str(path), "--views", "2"])
    assert (scene.size, scene.board) == (48, 0.2)
    _, scene, _ = cli.configs(["--config", str(path), "--views", "2", "--size", "32"])
    assert (scene.size, scene.board) == (32, 0.2)
    saved["board"]["shape"] = [48, 24]  # not one the command line makes: its own defaults
    path.write_text(json.dumps(saved))
    _, scene, _ = cli.configs(["--config", str(path), "--views", "2"])
    assert (scene.size, scene.board) == (SceneConfig().size, SceneConfig().board)


def test_result_round_trip_and_rerender(cli_run):
    import jax.numpy as jnp

    from jscratch.render import render
    from jscratch.scene import Board, Scratches, Views

    res = load_result(cli_run)
    assert isinstance(res.scratches, Scratches) and isinstance(res.views, Views)
    assert isinstance(res.board, Board) and res.board.shape == (24, 24)
    assert res.config.n_scratches == 150 and res.config.groove == "carvable"
    assert res.scratches.p0.dtype == np.float32
    assert int(res.keep.sum()) == res.scratches.p0.shape[0] == res.metrics["kept"]
    # The saved parameters give the saved scratches (the kept ones), exactly as the run did.
    from jscratch.design.solver import physical

    p0, _, width, depth, _, inten = (np.asarray(a) for a in physical(res.params))
    np.testing.assert_array_equal(p0[res.keep], res.scratches.p0)
    np.testing.assert_array_equal(width[res.keep], res.scratches.width)
    np.testing.assert_array_equal(depth[res.keep], res.scratches.depth)
    np.testing.assert_array_equal(inten, res.views.intensity)
    # Re-rendering the loaded result gives the saved render (float32 rounding of another path).
    rad = np.asarray(render(res.scratches, res.views, res.board))
    np.testing.assert_allclose(rad, res.radiance, rtol=2e-4, atol=1e-6 * float(rad.max()))
    again = load_result(cli_run)
    rad2 = np.asarray(render(again.scratches, again.views, again.board))
    np.testing.assert_array_equal(rad, rad2)
    assert jnp.asarray(res.params.geom).dtype == jnp.float32


def test_carvable_result_fabricates_as_carved(cli_run, tmp_path):
    proc = _run(["-m", "jscratch.fabricate", str(cli_run / "design.npz"), "--dry-run", "--out",
                 str(tmp_path / "job" / "board")])
    assert proc.returncode == 0, proc.stderr
    assert "recorded plunges, 0 fitted" in proc.stdout
    assert "0 unreachable grooves" in proc.stdout
    summary = json.loads((tmp_path / "job" / "board.summary.json").read_text())
    assert summary["scratches"] == json.loads((cli_run / "metrics.json").read_text())["kept"]


def test_paths_of_the_wrong_kind_are_named(tmp_path, capsys):
    """An --out that is a file, and a folder given as a target or config file, are refused in
    one line that says so."""
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    for argv, words in ((["--out", str(tmp_path / "afile")], "--out"),
                        ([str(tmp_path / "adir"), "--views", "1"], "is a folder, not an image"),
                        (["--config", str(tmp_path / "adir")], "is a folder, not a file")):
        out = [] if "--out" in argv else ["--out", str(tmp_path / "o")]
        assert cli.main([*argv, *out, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
    assert (tmp_path / "afile").read_text() == "x" and not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, words", [
    (["--as-carved-samples", "-3"], "as-carved-samples"),
    (["--iterations", "0"], "iterations"),
    (["--vgg-weights", "nosuch.npz", "--lambda-g", "1"], "nosuch.npz"),
    (["--machine", "nosuch.toml"], "nosuch.toml"),
    (["--groove", "deep"], "groove"),
    (["--config", "nosuch.json"], "nosuch.json"),
    (["--resume"], "resume"),
    (["--theta-deg", "120"], "--theta-deg must be in"),
    (["--size", "8"], "size"),
    (["--freeze", "legs"], "freeze"),
    (["notanimage.png"], "notanimage.png"),
    (["--scratches", "ten"], "scratches"),
    (["--seed", str(2**64)], "seed must be an int in [0, 2**63)"),
    (["--adam-eps", "0"], "--adam-eps must be finite and > 0"),
    (["--join-timeout", "0"], "--join-timeout must be an int >= 1"),
    (["--coordinator", "localhost:99999", "--num-processes", "2", "--process-id", "1"],
     "a port in 1-65535"),
])
def test_bad_options_one_line_nothing_written(tmp_path, capsys, argv, words):
    out = tmp_path / "out"
    code = cli.main([*argv, "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert words in err
    assert not out.exists()


def test_bad_cli_arguments_exit_2_one_line(tmp_path):
    """Argparse's own refusals (unknown flag, bad number) are one line too, from a real
    process."""
    proc = _run(["-m", "jscratch.design", "--scratchez", "5", "--out", str(tmp_path / "o")])
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1, proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "o").exists()


def test_resume_refuses_other_settings(cli_run, capsys):
    code = cli.main(["--resume", "--out", str(cli_run), "--scratches", "10"])
    assert code == 2 and "only --iterations" in capsys.readouterr().err


def test_a_new_run_stopped_before_its_first_checkpoint_leaves_the_folder_as_it_was(
        tmp_path, monkeypatch, capsys):
    """A new run interrupted, or failing, before its first checkpoint puts back what it had
    replaced (an earlier run's checkpoint and config.json) and removes what it added."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.npz").write_bytes(b"an earlier run's")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "design", interrupted)
    assert cli.main([*TINY, "--out", str(out), "--quiet"]) == 130
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.npz"]
    assert (out / "checkpoint.npz").read_bytes() == b"an earlier run's"
    assert "before the first checkpoint (the folder is as it was)" in capsys.readouterr().err

    def failing(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(cli, "design", failing)
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main([*TINY, "--out", str(tmp_path / "new" / "out"), "--quiet"])
    assert not (tmp_path / "new").exists()


def test_an_unfinished_run_over_an_earlier_result_is_not_loaded_as_it(cli_run, tmp_path,
                                                                     monkeypatch, capsys):
    """A new run interrupted after its first checkpoint, in the folder of an earlier result:
    config.json is the new run's (so that --resume finishes it), and `load_result` refuses the
    folder instead of pairing the new settings with the earlier design; resumed, it loads."""
    out = tmp_path / "run"
    shutil.copytree(cli_run, out)
    run_design = cli.design

    def stopped(*args, checkpoint, **kwargs):
        run_design(*args, checkpoint=checkpoint, stop_after=1, **kwargs)  # its checkpoint
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "design", stopped)
    assert cli.main([*TINY, "--seed", "5", "--out", str(out), "--quiet"]) == 130
    assert "the checkpoint holds the last saved state: --resume" in capsys.readouterr().err
    assert json.loads((out / "config.json").read_text())["design"]["seed"] == 5
    with pytest.raises(DesignFileError, match="config.json is a later run's, which has not "
                                              "finished"):
        load_result(out)
    monkeypatch.setattr(cli, "design", run_design)
    assert cli.main(["--resume", "--out", str(out), "--quiet"]) == 0
    assert load_result(out).config.seed == 5


def test_out_of_memory_is_one_line(tmp_path, monkeypatch, capsys):
    def too_big(*args, **kwargs):
        raise MemoryError("Unable to allocate 298. GiB for an array")

    monkeypatch.setattr(cli, "design", too_big)
    assert cli.main([*TINY, "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: out of memory (MemoryError: Unable to allocate 298. GiB")
    assert err.count("\n") == 1


def _edit_config(key, value):
    def edit(folder):
        c = json.loads((folder / "config.json").read_text())
        c["design"][key] = value
        (folder / "config.json").write_text(json.dumps(c))
    return edit


def _edit_result(key, fn):
    def edit(folder):
        z = _arrays(folder / "result.npz")
        z[key] = fn(z[key])
        np.savez(folder / "result.npz", **z)
    return edit


@pytest.mark.parametrize("edit, words", [
    (_edit_config("init_length", 3), "config.json': DesignConfig.init_length must be"),
    (_edit_config("groove", "free"), "does not match the config's 'free' grooves"),
    (_edit_result("geom", lambda a: a[:10]), "and the config's 150 scratches"),
    (_edit_result("history", lambda a: np.frombuffer(b"\xff\xfe", np.uint8)), "do not agree"),
    (lambda f: (f / "metrics.json").write_text("[1]"), "metrics.json': not a JSON object"),
    (_edit_result("log_intensity", lambda a: a[:1]), "do not fit 2 views"),
    (_edit_result("geom", lambda a: np.full_like(a, np.nan)), "hold non-finite values"),
    (_edit_result("geom", lambda a: a[::-1]), "holds other scratches than"),  # another run's
])
def test_a_result_folder_edited_out_of_step_is_refused(cli_run, tmp_path, edit, words):
    import shutil

    folder = tmp_path / "r"
    shutil.copytree(cli_run, folder)
    edit(folder)
    with pytest.raises(DesignFileError) as e:
        load_result(folder)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_text_file_is_not_a_result(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(DesignFileError, match="lacks design.npz"):
        load_result(tmp_path / "x")
    for name in ("design.npz", "result.npz", "metrics.json", "config.json"):
        (tmp_path / "x" / name).write_text("hello")
    with pytest.raises(DesignFileError) as e:
        load_result(tmp_path / "x")
    assert "\n" not in str(e.value) and "allow_pickle" not in str(e.value)


def test_without_quiet_the_run_says_what_it_does_before_its_first_step(tmp_path):
    """Without ``--quiet`` (a fresh process, as a user runs it): a status line names each phase
    before the first step (setting up, compiling), then the steps' progress bar counts the
    iterations, then the summary; on a first run (an empty kernel cache, where a compiler is
    found) the status line says that the native kernel is being built."""
    import shutil

    env_cache = {"JSCRATCH_CACHE": str(tmp_path / "cache")}
    proc = subprocess.run([sys.executable, "-m", "jscratch.design", *TINY, "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "JAX_PLATFORMS": "cpu", **env_cache})
    assert proc.returncode == 0, proc.stderr
    err = proc.stderr.replace("\r", "\n")
    phases = ["design: setting up", "design: compiling the step", "design: 100%|"]
    at = [err.find(p) for p in phases]
    assert all(i >= 0 for i in at) and at == sorted(at), (at, err[-2000:])
    assert "3/3" in err and proc.stdout.startswith("wrote ")
    if shutil.which("g++") or shutil.which("c++") or shutil.which("clang++"):
        assert "building the native kernel (first run only)" in err, err[-2000:]


def test_resume_accepts_the_runs_own_command_and_names_what_differs(cli_run):
    """The run's own command with ``--resume`` added gives the run's configs; an option with
    another value is refused, naming the option, the value given and the run's."""
    run, scene, config = cli.configs([*TINY, "--out", str(cli_run), "--resume"])
    saved = json.loads((cli_run / "config.json").read_text())
    assert config.to_dict() == DesignConfig.from_dict(saved["design"]).to_dict()
    assert scene == SceneConfig.from_dict(saved["scene"]) and run.resume
    run, scene, config = cli.configs([*TINY, "--out", str(cli_run), "--resume",
                                      "--iterations", "7"])
    assert config.iterations == 7
    with pytest.raises(DesignError, match=r"--scratches 10 \(the run's: 150\)$"):
        cli.configs([*TINY, "--out", str(cli_run), "--resume", "--scratches", "10"])
    with pytest.raises(DesignError, match=r"--views 3 \(the run's: 2\)"):
        cli.configs(["--views", "3", "--out", str(cli_run), "--resume"])


def test_resume_compares_options_as_the_config_holds_them(tmp_path):
    """Other spellings of the run's own values pass: groups in another order, the default
    machine as ``none``, numbers written otherwise, target paths absolute or relative, a view
    count equal to the targets'; another machine profile is refused field by field."""
    import skimage.io

    for name in ("t0.png", "t1.png"):
        skimage.io.imsave(tmp_path / name, np.zeros((8, 8), np.uint8), check_contrast=False)
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch = pytest.MonkeyPatch()
    with monkeypatch.context() as m:
        m.chdir(tmp_path)
        run, scene, config = cli.configs(["t0.png", "t1.png", "--freeze", "width,alpha",
                                          "--lr-endpoints", "0.001", "--out", str(out)])
    (out / "config.json").write_text(json.dumps({"design": config.to_dict(),
                                                 "scene": scene.to_dict()}))
    with monkeypatch.context() as m:
        m.chdir(tmp_path)
        same = [str(tmp_path / "t0.png"), "t1.png", "--views", "2", "--freeze", "alpha,width",
                "--lr-endpoints", "1e-3", "--machine", "none", "--out", str(out), "--resume"]
        _, scene2, config2 = cli.configs(same)
        assert config2.to_dict() == config.to_dict()
        machine = tmp_path / "m.toml"
        machine.write_text("feed_mm_min = 123.0\n")
        with pytest.raises(DesignError, match=r"--machine: feed_mm_min 123\.0 \(the run's: "):
            cli.configs([*same, "--machine", str(machine)])


def test_a_run_with_relative_target_paths_resumes_and_repeats_from_another_folder(
        tmp_path, monkeypatch):
    """Target paths are recorded absolute (as the files they name when the run started), so
    ``--resume`` and ``--config`` work from any folder, with the paths given either way."""
    import skimage.io

    from jscratch.design.io import load_scene

    (tmp_path / "img").mkdir()
    for name in ("t0.png", "t1.png"):
        skimage.io.imsave(tmp_path / "img" / name, np.zeros((24, 24), np.uint8),
                          check_contrast=False)
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    monkeypatch.chdir(tmp_path)
    _, scene, config = cli.configs(["img/t0.png", "img/t1.png", "--out", str(out)])
    (out / "config.json").write_text(json.dumps({"design": config.to_dict(),
                                                 "scene": scene.to_dict()}))
    monkeypatch.chdir(elsewhere)
    for argv in (["--out", str(out), "--resume"],
                 ["--out", str(out), "--resume", str(tmp_path / "img" / "t0.png"),
                  "../img/t1.png"],
                 ["--config", str(out / "config.json"), "--out", "again"]):
        _, again, _ = cli.configs(argv)
        assert again.targets == (str(tmp_path / "img" / "t0.png"), str(tmp_path / "img" / "t1.png"))
        assert load_scene(again)[1] == list(again.targets)


def test_a_run_too_large_for_the_free_memory_is_refused_and_leaves_no_folder(
        tmp_path, monkeypatch, capsys):
    """The step's memory check (`jscratch.design.run.check_step_memory`) from the command line:
    exit 2, one line naming both sizes; the output folder it made is gone again, and in an
    existing folder the config.json it wrote is removed."""
    from jscratch.design import run as run_mod

    monkeypatch.setattr(run_mod, "free_memory", lambda: 100_000)
    out = tmp_path / "out"
    assert cli.main([*TINY, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: the design step needs about ") and err.count("\n") == 1
    assert "this machine has 0 MB free" in err and not out.exists()
    deep = tmp_path / "new" / "a" / "b"
    assert cli.main([*TINY, "--out", str(deep), "--quiet"]) == 2
    assert not (tmp_path / "new").exists()
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert cli.main([*TINY, "--out", str(out), "--quiet"]) == 2
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_a_refused_run_leaves_an_earlier_run_in_its_folder_as_it_was(cli_run, tmp_path,
                                                                     monkeypatch):
    """A new run refused before its first step (here by the memory check) puts back the earlier
    run's config.json and checkpoint it had replaced; every other file is untouched."""
    from jscratch.design import run as run_mod

    out = tmp_path / "run"
    shutil.copytree(cli_run, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert "checkpoint.npz" in before and "config.json" in before
    monkeypatch.setattr(run_mod, "free_memory", lambda: 100_000)
    assert cli.main([*TINY, "--seed", "5", "--out", str(out), "--quiet"]) == 2
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_an_as_carved_render_out_of_memory_keeps_the_design(tmp_path, monkeypatch, capsys):
    """The as-carved render (after the optimisation) running out of memory: the design is saved
    without it, one line says so, exit 1; another error is not swallowed."""
    import jax

    from jscratch.design import maker

    def too_big(*args, **kwargs):
        raise jax.errors.JaxRuntimeError("INTERNAL: Out of memory allocating 92330000023000 "
                                         "bytes.")

    monkeypatch.setattr(maker, "as_carved", too_big)
    out = tmp_path / "out"
    assert cli.main([*TINY, "--as-carved-samples", "4", "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: the as-carved render at --as-carved-samples 4 ran out of "
                          "memory") and err.count("\n") == 1
    assert "as_carved" not in json.loads((out / "metrics.json").read_text())
    assert load_result(out).params is not None

    def broken(*args, **kwargs):
        raise jax.errors.JaxRuntimeError("INTERNAL: something else")

    monkeypatch.setattr(maker, "as_carved", broken)
    with pytest.raises(jax.errors.JaxRuntimeError, match="something else"):
        cli.main([*TINY, "--as-carved-samples", "4", "--out", str(tmp_path / "o2"), "--quiet"])


def _files(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


_SIGTERM_RUN = """
import os, signal, sys, time
from jscratch.design import cli
def terminated(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGTERM)  # as `kill`, `timeout` or a scheduler sends it
    time.sleep(30)
cli.design = terminated
sys.exit(cli.main(sys.argv[1:]))
"""


def test_sigterm_and_a_kill_before_the_first_checkpoint_leave_the_earlier_result(cli_run,
                                                                                 tmp_path):
    """SIGTERM stops a new run as Ctrl-C does: the earlier result's files as they were. A kill
    (SIGKILL: nothing runs) between the moves aside and the first checkpoint leaves the earlier
    files as ``*.earlier``: `load_result` reads the earlier result, and the next run puts them
    back first (`settle_earlier`); a kill after the first checkpoint leaves them stale, removed."""
    out = tmp_path / "run"
    shutil.copytree(cli_run, out)
    before = _files(out)
    proc = _run(["-c", _SIGTERM_RUN, *TINY, "--seed", "7", "--out", str(out), "--quiet"])
    assert proc.returncode == 130, proc.stderr[-2000:]
    assert "before the first checkpoint (the folder is as it was)" in proc.stderr
    assert _files(out) == before
    seed = load_result(out).config.seed
    # What a kill leaves at each point of the moves (checkpoint aside, config aside, new config):
    for moved in (1, 2, 3):
        shutil.rmtree(out)
        shutil.copytree(cli_run, out)
        os.replace(out / "checkpoint.npz", out / "checkpoint.npz.earlier")
        if moved >= 2:
            os.replace(out / "config.json", out / "config.json.earlier")
        if moved == 3:
            (out / "config.json").write_text(json.dumps({"design": {"seed": 7}, "run_id": "x"}))
        (out / ".ckpt-abc.npz.tmp").write_bytes(b"torn")  # a checkpoint write killed part-way
        (out / ".jscratch-save-abc").mkdir()
        if moved >= 2:
            assert load_result(out).config.seed == seed  # the earlier result, read as it was
        settle_earlier(str(out))
        remove_partial_writes(str(out))
        assert _files(out) == before and sorted(os.listdir(out)) == sorted(before), moved
    # Killed after its first checkpoint: the earlier files are stale, removed by the next run.
    for name in ("config.json", "checkpoint.npz"):
        shutil.copy(out / name, out / (name + ".earlier"))
    assert cli.main(["--resume", "--out", str(out), "--quiet"]) == 0
    assert not list(out.glob("*.earlier"))


def test_a_save_stopped_part_way_is_refused_not_loaded_as_one_run(cli_run, tmp_path,
                                                                  monkeypatch):
    """`save_result` moves config.json first and metrics.json last, so a folder left by a save
    stopped after any move holds a config and metrics of different runs: refused, whatever
    order the file system lists the staged files in."""
    result = load_result(cli_run)
    real_replace, real_listdir = os.replace, os.listdir

    def listdir(path):  # the order that would put the run-id pair first
        names = real_listdir(path)
        first = [n for n in ("config.json", "metrics.json") if n in names]
        return first + [n for n in names if n not in first]

    monkeypatch.setattr(os, "listdir", listdir)
    for stop_at in range(1, 6):
        out = tmp_path / f"save{stop_at}"
        shutil.copytree(cli_run, out)
        calls = []

        def replace(src, dst):  # the moves from the staging folder into `out`, counted
            if os.path.dirname(os.fspath(dst)) == str(out):
                calls.append(dst)
                if len(calls) == stop_at + 1:
                    raise KeyboardInterrupt
            return real_replace(src, dst)

        monkeypatch.setattr(os, "replace", replace)
        with pytest.raises(KeyboardInterrupt):
            save_result(result, out)
        monkeypatch.setattr(os, "replace", real_replace)
        assert len(calls) == stop_at + 1  # stopped with `stop_at` files moved
        with pytest.raises(DesignFileError, match="not all of one run"):
            load_result(out)


def test_checkpoint_and_result_files_are_as_readable_as_the_others(tmp_path):
    """`checkpoint.save_npz` writes through a temporary file, with the mode `open` would give
    (0644 under umask 022), not the owner-only mode of `tempfile.mkstemp`."""
    from jscratch.design.checkpoint import save_npz

    old = os.umask(0o022)
    try:
        save_npz(str(tmp_path / "a.npz"), {"x": np.zeros(3)})
        (tmp_path / "b.txt").write_text("x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.npz").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "b.txt").stat().st_mode & 0o777 == 0o644


def test_a_full_disk_mid_run_names_the_checkpoint_kept(tmp_path, monkeypatch, capsys):
    """A write that fails mid-run (a full disk) after a checkpoint: one line naming the file
    meant (not its temporary) and saying the checkpoint holds the last saved state."""
    import errno

    from jscratch.design import checkpoint as ckpt_mod

    out = tmp_path / "out"

    def full_disk(*args, checkpoint, **kwargs):
        ckpt_mod.save_npz(checkpoint, {"x": np.zeros(2)})  # the first checkpoint

        def no_space(*a, **k):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(np, "savez", no_space)
        ckpt_mod.save_npz(checkpoint, {"x": np.zeros(2)})

    monkeypatch.setattr(cli, "design", full_disk)
    assert cli.main([*TINY, "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    ck = str(out / "checkpoint.npz")
    assert err == (f"error: No space left on device: {ck!r} (the checkpoint {ck!r} holds the "
                   "last saved state: --resume once the cause is fixed)\n"), err
    assert not [p for p in os.listdir(out) if p.startswith(".ckpt-")]


def test_nohup_still_ignores_sighup(tmp_path):
    """Under ``nohup`` (SIGHUP ignored) a closed terminal does not stop the run: the command line
    turns SIGTERM and SIGHUP into an interrupt only where they would kill the process."""
    script = ("import os, signal, sys, time\n"
              "signal.signal(signal.SIGHUP, signal.SIG_IGN)  # what nohup does\n"
              "from jscratch.design import cli\n"
              "real = cli.design\n"
              "def hup(*a, **k):\n"
              "    os.kill(os.getpid(), signal.SIGHUP)\n"
              "    time.sleep(0.2)\n"
              "    return real(*a, **k)\n"
              "cli.design = hup\n"
              "sys.exit(cli.main(sys.argv[1:]))\n")
    proc = _run(["-c", script, *TINY, "--out", str(tmp_path / "o"), "--quiet"])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "o" / "design.npz").exists()


def _killed_before_its_checkpoint(src, out):
    """The folder a new run killed (SIGKILL) after moving the earlier files aside leaves."""
    shutil.copytree(src, out)
    os.replace(out / "checkpoint.npz", out / "checkpoint.npz.earlier")
    os.replace(out / "config.json", out / "config.json.earlier")
    (out / "config.json").write_text(json.dumps({"design": {"seed": 7}, "run_id": "killed"}))


def test_after_a_killed_run_resume_save_and_load_see_the_earlier_result(cli_run, tmp_path):
    """A run killed before its first checkpoint: `--resume` settles the folder before it reads
    the run's config (the earlier run's, resumed); a Python `save_result` into the folder
    settles it too, so its own config is not shadowed by the one set aside."""
    out = tmp_path / "run"
    _killed_before_its_checkpoint(cli_run, out)
    assert cli.main(["--resume", "--out", str(out), "--quiet"]) == 0
    assert not list(out.glob("*.earlier")) and load_result(out).config.seed == 0
    shutil.rmtree(out)
    _killed_before_its_checkpoint(cli_run, out)
    result = load_result(out)  # the earlier result, its config read where it was set aside
    save_result(result, out)
    assert not list(out.glob("*.earlier"))
    assert load_result(out).config.seed == 0 and (out / "checkpoint.npz").exists()


def test_a_second_run_in_a_folder_being_written_is_refused_and_changes_nothing(cli_run,
                                                                               tmp_path, capsys):
    """The writing process holds its folder (`io.lock_folder`, flock) for the run: a second
    command there is refused in one line before it settles or cleans anything; a folder named
    config.json is refused before anything is moved."""
    from jscratch.design.io import lock_folder

    out = tmp_path / "run"
    _killed_before_its_checkpoint(cli_run, out)  # what only the holder may settle
    (out / ".ckpt-x.npz.tmp").write_bytes(b"being written")
    before = _files(out)
    held = lock_folder(str(out))
    try:
        for argv in ([*TINY, "--out", str(out), "--quiet"], ["--resume", "--out", str(out)]):
            assert cli.main(argv) == 2
            err = capsys.readouterr().err
            assert err == (f"error: another design run is writing in {str(out)!r}: wait for it "
                           "to end, or give another --out\n"), err
            assert _files(out) == before
    finally:
        del held
    assert lock_folder(str(out)) is not None  # released with its holder
    shutil.rmtree(out)
    shutil.copytree(cli_run, out)
    os.remove(out / "config.json")
    (out / "config.json").mkdir()
    before = _files(out)
    assert cli.main([*TINY, "--out", str(out), "--quiet"]) == 2
    assert "config.json' is a folder" in capsys.readouterr().err
    assert _files(out) == before


@pytest.mark.parametrize("argv, says", [
    (["--scratches", "0"], "--scratches must be an int >= 1, got 0"),
    (["--size", "0"], "--size must be an int in [16, 46340] (pixels; pixel indices are 32-bit), "
                      "got 0"),
    (["--lambda-x", "-1"], "--lambda-x must be a finite number >= 0, got -1.0"),
    (["--theta-deg", "100"], "--theta-deg must be in [0, 90) degrees (above the board), got 100.0"),
])
def test_a_refused_option_is_named_by_its_flag(argv, says, tmp_path, capsys):
    """A value the configs refuse is named as the user typed it (the flag, not the field)."""
    assert cli.main([*argv, "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert capsys.readouterr().err == f"error: {says}\n"
    assert not (tmp_path / "o").exists()
