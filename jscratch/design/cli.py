"""The command line: ``python -m jscratch.design [TARGET ...] [options]``.

Every option is generated from the fields of `SceneConfig` (targets, views, board),
`DesignConfig` (with its nested `jscratch.loss.LossConfig`) and `RunOptions` (output folder,
resume, progress) by `jscratch.options`: a field's help, unit and default are declared once, with
the field. Settings are laid over one another in this order: the dataclass defaults, then
``--config FILE`` (a ``config.json`` that a run wrote beside its outputs), then the options given.
So ``python -m jscratch.design --config OUT/config.json`` repeats a run bit for bit, and
``jscratch.design.design(targets, views, board, DesignConfig())`` gives what the command with no
options gives.

Everything is checked before any work starts; a refusal prints one line ``error: ...`` and exits
with `jscratch.errors.exit_status` (2 bad input, with nothing written; 3 non-finite optimisation,
the last good state kept; 1 a file that could not be written, or memory that ran out).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import traceback
import uuid
from collections.abc import Sequence

import jax

from jscratch import native
from jscratch.errors import (EXIT_STATUS_HELP, DesignFileError, InputError, JscratchError,
                             error_line, report)
from jscratch.options import (OneLineParser, add_arguments, flags, given, option, overlay,
                              signals_interrupt)
from jscratch.designfile import DesignError
from jscratch.design.config import DEFAULT_IMAGES, DesignConfig, SceneConfig
from jscratch.design import mesh as mesh_mod
from jscratch.design.io import (EARLIER, load_scene, lock_folder, remove_partial_writes,
                                save_result, settle_earlier, targets_hash)
from jscratch.design.run import check_inputs, design

__all__ = ["RunOptions", "main", "parser", "configs"]


@dataclasses.dataclass(frozen=True)
class RunOptions:
    """Options of a command-line run that are not part of the design (where outputs go, how the
    run is reported)."""

    out: str = option("design_out", "output folder", metavar="DIR")
    config: str | None = option(
        None, "settings from a config.json that a run wrote (its design and scene), under the "
        "options given here", metavar="FILE")
    resume: bool = option(False, "continue the run in --out from its checkpoint, with "
                          "OUT/config.json (--iterations may change; other design and scene "
                          "options only repeat the run's own values)")
    quiet: bool = option(False, "no progress bar or summary")
    as_carved_samples: int = option(
        0, "strata per pixel side of the brute-force 'as carved' render, the design with the "
        "ball's real arc, in metrics.json and view<j>_carved.png (0: skip it; 32 is what the "
        "maker's path uses, about 20-25 s more at 256 px and 20k scratches; a render too large "
        "for the memory is left out: the design is saved without it, exit 1)")
    # --- where the design runs (jscratch.design.mesh); not part of the design or its config.json
    devices: int = option(0, "devices the image rows are split over: k the first k JAX sees "
                          "(1: one device); 0 every device (every process's) with several "
                          "processes or on GPUs/TPUs, one device for one process on the CPU")
    coordinator: str | None = option(
        None, "HOST:PORT of process 0 (jax.distributed): run the same command on every host with "
        "--num-processes and --process-id; process 0 writes the outputs. Without it, "
        "JAX_COORDINATOR_ADDRESS (or a cluster JAX detects) joins the processes",
        metavar="HOST:PORT")
    num_processes: int | None = option(None, "processes of the run (with --coordinator)")
    process_id: int | None = option(None, "this process's index in [0, --num-processes)")
    join_timeout: int = option(300, "how long the processes wait for each other to join",
                               unit="s")

    def __post_init__(self):
        if not (isinstance(self.out, str) and self.out):
            raise DesignError(f"--out must be a folder path, got {self.out!r}")
        if os.path.exists(self.out) and not os.path.isdir(self.out):
            raise DesignError(f"--out {self.out!r} is a file, not a folder")
        n = self.as_carved_samples
        if not (isinstance(n, int) and not isinstance(n, bool) and n >= 0):
            raise DesignError(f"--as-carved-samples must be an int >= 0, got {n!r}")
        for name, lo in (("devices", 0), ("join_timeout", 1)):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= lo):
                raise DesignError(f"--{name.replace('_', '-')} must be an int >= {lo}, got {v!r}")
        if self.resume and self.config is not None:
            raise DesignError("--resume reads OUT/config.json: do not give --config with it")


def parser() -> argparse.ArgumentParser:
    """The generated parser (`RunOptions`, `SceneConfig`, `DesignConfig` and its loss)."""
    p = OneLineParser(
        prog="python -m jscratch.design",
        description="Optimise a scratch design so that a board shows one target image per view "
                    "(Shen et al. 2023). With no TARGET it uses images bundled with scikit-image "
                    f"({', '.join(DEFAULT_IMAGES)}).",
        epilog=EXIT_STATUS_HELP + " A non-finite optimisation keeps its last good state in "
               "OUT/checkpoint.npz.")
    add_arguments(p, RunOptions, title="run")
    add_arguments(p, SceneConfig, title="scene (targets, views, board)")
    add_arguments(p, DesignConfig, title="design")
    return p


def _read_config(path: str) -> dict:
    """A run's ``config.json`` as a dict with ``design`` (and ``scene``) objects."""
    if not os.path.isfile(path):
        what = "is a folder, not a file" if os.path.isdir(path) else "does not exist"
        raise DesignFileError(f"config file {path!r} {what}")
    try:
        with open(path) as f:
            saved = json.load(f)
    except (OSError, ValueError) as e:
        raise DesignFileError(f"config file {path!r} is not readable JSON "
                              f"({type(e).__name__})") from None
    if not isinstance(saved, dict) or not isinstance(saved.get("design"), dict):
        raise DesignFileError(f"config file {path!r} has no 'design' object (python -m "
                              "jscratch.design writes one as OUT/config.json)")
    unknown = sorted(set(saved) - CONFIG_KEYS)
    if unknown:
        raise DesignFileError(f"config file {path!r}: unknown key {unknown[0]!r} (known: "
                              f"{', '.join(sorted(CONFIG_KEYS))})")
    return saved


#: The top-level keys of a config.json (docs/model.md §12): the settings, and what the run saved.
CONFIG_KEYS = frozenset({"design", "scene", "targets", "board", "camera", "light", "run_id"})


def configs(argv: Sequence[str] | None = None) -> tuple[RunOptions, SceneConfig, DesignConfig]:
    """The three configs a command line asks for (defaults, then ``--config``, then the options
    given), all checked. Raises `jscratch.InputError` (or `DesignFileError`) naming the option or
    file; argparse's own refusals exit 2."""
    args = parser().parse_args(argv)
    run = RunOptions(**given(args, RunOptions))
    scene_given, design_given = given(args, SceneConfig), given(args, DesignConfig)
    scene, config = SceneConfig(), DesignConfig()
    source = None
    if run.resume:
        source = os.path.join(run.out, "config.json")
        if not os.path.isfile(source):
            raise DesignFileError(f"--resume: no run to continue in {run.out!r} (no {source!r})")
    elif run.config is not None:
        source = run.config
    if source is not None:
        saved = _read_config(source)
        if saved.get("scene") is None and not scene_given:
            raise DesignFileError(
                f"config file {source!r} has no scene (a result saved from Python, whose targets "
                "are arrays): give the targets and view options too, or "
                "save_result(..., scene=...)")
        try:
            config = DesignConfig.from_dict(saved["design"])
            scene = SceneConfig.from_dict(saved.get("scene") or _board_scene(saved))
        except InputError as e:
            raise DesignFileError(f"config file {source!r}: {e}") from None
    if run.resume:
        changed = [*_changed(scene, scene_given, SceneConfig),
                   *_changed(config, {k: v for k, v in design_given.items() if k != "iterations"},
                             DesignConfig)]
        if changed:
            raise DesignError(f"--resume continues the run in {run.out!r} with its own settings; "
                              f"only --iterations may change, got {'; '.join(changed)}")
    return run, _by_flag(overlay, scene, scene_given), _by_flag(overlay, config, design_given)


#: How the configs' checks name a field: ``DesignConfig.n_scratches``, ``scene size``, ...
_FIELD_RE = re.compile(r"(DesignConfig\.|LossConfig\.|scene )(\w+)( must be .*)")


def _by_flag(overlay_, saved, changes: dict):
    """``overlay_(saved, changes)``, its refusal of an option given on the command line naming
    the option's flag (``--scratches must be ...``), not the config's field."""
    try:
        return overlay_(saved, changes)
    except InputError as e:
        m = _FIELD_RE.fullmatch(str(e))
        path = None if m is None else ("loss." if m.group(1) == "LossConfig." else "") + m.group(2)
        given_paths = set()
        for k, v in changes.items():  # (nested: the loss options, "loss.lambda_x")
            given_paths |= {f"{k}.{j}" for j in v} if isinstance(v, dict) else {k}
        if path not in given_paths:  # (a value from a --config file: named as the file has it)
            raise
        raise type(e)(flags(type(saved))[path] + m.group(3)) from None


def _board_scene(saved: dict) -> dict:
    """What a config without a scene (a result saved from Python) says of the scene options: the
    image size and board side of its board where it is square (its views are the options')."""
    board = saved.get("board")
    try:
        (h, w), sx, sy = board["shape"], float(board["Sx"]), float(board["Sy"])
    except (TypeError, KeyError, ValueError):
        return {}
    return {"size": h, "board": sx} if h == w and sx == sy else {}


def _changed(saved, changes: dict, cls) -> list[str]:
    """``"--flag GIVEN (the run's: SAVED)"`` for each option in `changes` (`options.given`) whose
    value, as the config holds it (`overlay`: parsed and normalised), differs from the saved
    config's: options repeated with the run's own values pass. Target paths are compared as the
    files they name, and a scene's ``views`` as the count it gives."""
    names = flags(cls)
    new = overlay(saved, changes)
    out = []

    def walk(a, b, given, prefix):
        for name, v in given.items():
            x, y = getattr(a, name), getattr(b, name)
            if isinstance(v, dict) and dataclasses.is_dataclass(x):
                walk(x, y, v, prefix + name + ".")
            elif isinstance(x, dict) and isinstance(y, dict):  # a machine profile: its fields
                out.extend(f"{names[prefix + name]}: {k} {_show(y.get(k))} (the run's: "
                           f"{_show(x.get(k))})" for k in sorted(set(x) | set(y))
                           if x.get(k) != y.get(k))
            elif _comparable(a, name) != _comparable(b, name):
                out.append(f"{names[prefix + name]} {_show(y)} (the run's: {_show(x)})")

    walk(saved, new, changes, "")
    return out


def _comparable(config, name):
    value = getattr(config, name)
    if isinstance(config, SceneConfig) and name == "targets":
        return tuple(os.path.realpath(t) for t in value)
    if isinstance(config, SceneConfig) and name == "views" and value is None:
        return len(config.targets) or 3  # the default: one view per target, else 3
    return value


def _options_by_flag(scene, config) -> dict:
    """``{"design option --seed": 0, ...}``: each scene and design option by its flag (what the
    processes of a run compare, so that a disagreement names the option)."""
    out = {}
    for cls, cfg, what in ((SceneConfig, scene, "scene option"),
                           (DesignConfig, config, "design option")):
        values = cfg.to_dict()
        for path, flag in flags(cls).items():
            v = values
            for part in path.split("."):
                v = v.get(part) if isinstance(v, dict) else None
            out[f"{what} {flag}"] = v
    return out


def _show(value) -> str:
    if isinstance(value, (tuple, list)):
        return ",".join(map(str, value)) if value else "none"
    return "none" if value is None else str(value)


def _run(argv) -> int:
    early = RunOptions(**given(parser().parse_args(argv), RunOptions))
    held = []  # the folder's lock (`lock_folder`), released when the run ends
    try:
        if not early.process_id:  # process 0 (or the only one) writes the folder: held
            held.append(lock_folder(early.out))
            if held[0] is not None:  # what a run stopped by a kill left, before its config is
                settle_earlier(early.out)  # read (the folder as it was before that run)
                remove_partial_writes(early.out)
        run, scene, config = configs(argv)
        # --- several processes: joined before any JAX work (jax.distributed)
        mesh_mod.initialize(run.coordinator, run.num_processes, run.process_id, run.join_timeout,
                            say=None if run.quiet else lambda s: print(s, file=sys.stderr))
        # --- from here SIGTERM and SIGHUP stop the run as Ctrl-C does (not while blocked in
        # the join)
        with signals_interrupt():
            return _run_joined(run, scene, config, held)
    finally:
        for lock in held:
            if lock is not None:
                lock.release()


def _run_joined(run, scene, config, held: list) -> int:
    native.prepare(config.dtype)  # the native kernel builds (first run only) as inputs load
    if config.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    checkpoint = os.path.join(run.out, "checkpoint.npz")
    writer = mesh_mod.is_writer()
    config_path = os.path.join(run.out, "config.json")

    def checks():  # every refusal before any work (with several processes: all refuse together)
        if writer and os.path.isdir(config_path):
            raise DesignFileError(f"{config_path!r} is a folder: the run's config.json cannot be "
                                  "written")
        targets, names, views, board = load_scene(scene)
        if run.resume and writer and not os.path.isfile(checkpoint):
            raise DesignFileError(f"--resume: no checkpoint {checkpoint!r} to continue from "
                                  "(a run without --resume starts a new one there, replacing "
                                  "any result)")
        check_inputs(targets, views, board, config, checkpoint, run.resume)
        mesh = mesh_mod.sub_mesh(run.devices)
        mesh_mod.resolve(mesh, board, config)  # the mesh divides the work
        return targets, names, views, board, mesh

    targets, names, views, board, mesh = mesh_mod.all_or_none(checks)
    # --- the processes' agreement, checked before anything is written
    mesh_mod.agree({"targets": targets_hash(targets), **_options_by_flag(scene, config),
                    "design options": config.to_dict(), "scene options": scene.to_dict(),
                    "run options (--resume, --devices)": [run.resume, run.devices],
                    "versions": mesh_mod.versions()})
    if not writer:  # process 0 writes the outputs and the checkpoint
        design(targets, views, board, config, checkpoint=checkpoint, resume=run.resume,
               progress=False, mesh=mesh)
        mesh_mod.outputs_written(False)  # (the run ends when they are written)
        return 0
    # ---
    made = _missing_folders(run.out)  # removed again if the run stops before its checkpoint
    os.makedirs(run.out, exist_ok=True)
    if not any(held):  # (a folder made now: held from here)
        held.append(lock_folder(run.out))
    try:
        if not run.resume:  # the settings first, so that an interrupted run can be resumed; an
            # earlier run's checkpoint and config are moved aside until this run's first
            # checkpoint (`settle_earlier` puts them back if it stops before, whatever stops it)
            if os.path.exists(checkpoint):
                os.replace(checkpoint, checkpoint + EARLIER)
            if os.path.isfile(config_path):
                os.replace(config_path, config_path + EARLIER)
            else:
                open(config_path + EARLIER, "wb").close()  # (empty: there was none)
            with open(config_path, "w") as f:  # (its run_id: no result is this run's yet)
                json.dump({"design": config.to_dict(), "scene": scene.to_dict(),
                           "targets": names, "run_id": uuid.uuid4().hex}, f, indent=2)
        result = design(targets, views, board, config, checkpoint=checkpoint, resume=run.resume,
                        progress=not run.quiet, mesh=mesh)
    except BaseException as e:
        own = os.path.exists(checkpoint)  # (a resumed run's, or one this run wrote)
        try:  # (a failing clean-up must not hide why the run stopped)
            settle_earlier(run.out)
            if not own:  # nothing of this run to keep: the folders it made go too
                for folder in made:
                    if not os.listdir(folder):
                        os.rmdir(folder)
        except OSError:
            pass
        if isinstance(e, OSError) and own:  # (a full disk, a folder made read-only)
            return report(e, then=f" (the checkpoint {checkpoint!r} holds the last saved "
                                  "state: --resume once the cause is fixed)")
        if not isinstance(e, KeyboardInterrupt):
            raise
        print("error: interrupted " + (
            "(the checkpoint holds the last saved state: --resume)" if own else
            "before the first checkpoint (the folder is as it was): run again to start over"),
            file=sys.stderr)
        return 130
    try:
        return _write(run, result, scene, names)
    finally:
        mesh_mod.outputs_written(True)


def _write(run, result, scene, names) -> int:
    """Process 0's outputs of a finished design (`save_result`) and its summary; the status."""
    settle_earlier(run.out)
    try:
        save_result(result, run.out, scene=scene, names=names,
                    as_carved_samples=run.as_carved_samples)
    except KeyboardInterrupt:
        print("error: interrupted while writing the outputs (the checkpoint holds the design: "
              "--resume writes them)", file=sys.stderr)
        return 130
    except (MemoryError, jax.errors.JaxRuntimeError) as e:
        if not (run.as_carved_samples and _out_of_memory(e)):
            raise
        # the design is kept; only the as-carved render is too large
        save_result(result, run.out, scene=scene, names=names)
        print(f"error: the as-carved render at --as-carved-samples {run.as_carved_samples} ran out "
              f"of memory ({error_line(e, 80)}); the design is saved without it: ask for fewer "
              "samples", file=sys.stderr)
        return 1
    if not run.quiet:
        _summary(result, run.out)
    return 0


def _peer_stopped(e: BaseException) -> bool:
    """Whether `e` is a collective that failed because another process of the run stopped."""
    return any(s in str(e) for s in ("Gloo", "Connection closed", "Connection reset",
                                     "UNAVAILABLE"))


def _out_of_memory(e: BaseException) -> bool:
    """Whether `e` is an allocation failure (Python's, or XLA's on the host or a device)."""
    return isinstance(e, MemoryError) or any(
        s in str(e) for s in ("RESOURCE_EXHAUSTED", "Out of memory", "out of memory"))


def _missing_folders(path: str) -> list[str]:
    """The folders ``os.makedirs(path)`` would create, innermost first."""
    out, path = [], os.path.abspath(path)
    while not os.path.exists(path):
        out.append(path)
        path = os.path.dirname(path)
    return out


def _summary(result, out) -> None:
    mt = result.metrics
    print(f"wrote {out}: {mt['kept']} scratches ({mt['discarded']} discarded), loss "
          f"{mt['loss']:.5g}, SSIM {[round(x, 3) for x in mt['ssim']]}, PSNR "
          f"{[round(x, 2) for x in mt['psnr']]} dB, {mt['time_total']:.1f} s "
          f"({mt['kernel']['kernel']} kernel)")
    if "target" in mt:
        tg = mt["target"]
        print(f"target mean SSIM {tg['ssim']:.3f}: " + (
            f"reached with {mt['kept']} scratches (mean SSIM {tg['mean_ssim']:.3f})"
            if tg["reached"] else f"not reached (full design: {tg['mean_ssim']:.3f})"))
    ac, cv = mt.get("as_carved"), mt["carving"]
    print(f"machine {mt['machine']['name']!r}, {mt['groove']} grooves: "
          + (f"as-carved SSIM {[round(x, 3) for x in ac['ssim']]}, " if ac else "")
          + f"carving ~{cv['estimated_hours']:.2f} h")


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status (`jscratch.errors.exit_status`),
    printing a refusal as one line (`jscratch.errors.report`)."""
    try:
        status = _main(argv)
    except Exception as e:  # (not a refusal: `_main` reports those)
        if not mesh_mod.joined():
            raise
        if not _peer_stopped(e):  # a failure of this process: its traceback, then as below
            traceback.print_exc()
        print(f"error: {'another process of the run stopped' if _peer_stopped(e) else 'failed'}"
              f" ({error_line(e, 100)}): --resume once every process runs", file=sys.stderr)
        status = 1
    if status and (mesh_mod.joined() or mesh_mod.abandoned_join()):  # one of several
        # processes stops (or was stopped while joining): at once, not after the
        # shutdown barrier, which would wait for the others (blocked in a collective with this
        # one) until its timeout; they see the connection close and stop too
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    return status


def _main(argv) -> int:
    try:
        return _run(argv)
    except SystemExit as e:  # argparse: --help (0) or a refused option, already printed (2)
        return e.code if isinstance(e.code, int) else 2
    except (JscratchError, OSError) as e:
        return report(e)
    except (MemoryError, jax.errors.JaxRuntimeError) as e:
        if not _out_of_memory(e):
            raise
        print(f"error: out of memory ({error_line(e, 100)}): ask for fewer scratches, a smaller "
              "--size or a smaller --chunk", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
