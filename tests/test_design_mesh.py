"""jscratch.design.mesh: a design on several devices (4 forced CPU devices) and on several
processes (2 on localhost, joined by jax.distributed) equals the one-device design.

The multi-device runs are subprocesses: the forced device count must be set before JAX starts,
and a process joins at most one distributed run. Tolerance: the parameters agree to 1e-5 (absolute
on the unconstrained parameters, which are O(1)): on a mesh every pixel strip sums its own pairs
and the gradients are summed over the strips (a psum), so float32 sums run in another order than
on one device; three Adam steps of that rounding (~1e-7 relative per sum) stay far below 1e-5,
while a wrong shard (a missing or doubled strip) changes the loss and the parameters at 1e-2.
"""

import json
import os
import socket
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from jscratch.design import DesignConfig, mesh
from jscratch.errors import InputError
from jscratch.scene import Board

pytestmark = pytest.mark.slow

TOL = 1e-5

_SCRIPT = textwrap.dedent("""
    import os, sys, json
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=4"
    import jax, numpy as np
    jax.config.update("jax_platforms", "cpu")
    from jscratch.design import design, DesignConfig
    from jscratch.design.mesh import sub_mesh
    from jscratch.errors import InputError

    out = sys.argv[1]
    rng = np.random.default_rng(0)
    t = rng.uniform(0.2, 0.8, (2, 32, 32)).astype(np.float32)
    cfg = DesignConfig(n_scratches=200, iterations=3, prune_every=2)
    ck4, ck1 = os.path.join(out, "c4.npz"), os.path.join(out, "c1.npz")
    runs = {
        "one": lambda: design(t, config=cfg, mesh=sub_mesh(1)),
        "four": lambda: design(t, config=cfg, mesh=sub_mesh(4)),
        # interrupted on 4 devices, resumed on 1; and the other way round
        "four_to_one": lambda: (design(t, config=cfg, mesh=sub_mesh(4), checkpoint=ck4,
                                       stop_after=2),
                                design(t, config=cfg, mesh=sub_mesh(1), checkpoint=ck4,
                                       resume=True))[1],
        "one_to_four": lambda: (design(t, config=cfg, mesh=sub_mesh(1), checkpoint=ck1,
                                       stop_after=2),
                                design(t, config=cfg, mesh=sub_mesh(4), checkpoint=ck1,
                                       resume=True))[1],
    }
    res = {}
    for name, run in runs.items():
        r = run()
        leaves = jax.tree_util.tree_leaves(r.params)
        np.savez(os.path.join(out, name + ".npz"), keep=r.keep,
                 **{f"p{i}": np.asarray(x) for i, x in enumerate(leaves)})
        res[name] = {"mesh": r.metrics["mesh"], "loss": r.metrics["loss"],
                     "iterations": r.metrics["iterations"], "prune": r.metrics["prune"]}
    try:  # 30 rows do not split over 4 devices
        design(t[:, :30], config=cfg, mesh=sub_mesh(4))
    except InputError as e:
        res["error"] = str(e)
    json.dump(res, open(os.path.join(out, "res.json"), "w"))
""")


def _env():
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    return env


@pytest.fixture(scope="module")
def four_devices(tmp_path_factory):
    out = tmp_path_factory.mktemp("mesh4")
    p = subprocess.run([sys.executable, "-c", _SCRIPT, str(out)], capture_output=True, text=True,
                       timeout=900, env=_env())
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads((out / "res.json").read_text())
    return out, res


def _params(path):
    with np.load(path) as z:
        return z["keep"], [z[f"p{i}"] for i in range(len(z.files) - 1)]


def _same(a, b):
    (ka, pa), (kb, pb) = _params(a), _params(b)
    assert np.array_equal(ka, kb)  # the same scratches kept by the discard
    for x, y in zip(pa, pb):
        np.testing.assert_allclose(x, y, rtol=0, atol=TOL)


def test_four_devices_equal_one(four_devices):
    out, res = four_devices
    assert res["one"]["mesh"] == {"devices": 1, "processes": 1, "axes": {"pixels": 1},
                                  "platform": "cpu", "device_kind": "cpu"}
    assert res["four"]["mesh"]["devices"] == 4 and res["four"]["mesh"]["axes"] == {"pixels": 4}
    assert res["four"]["prune"] == res["one"]["prune"]  # the same prune rounds, same moves
    assert res["four"]["loss"] == pytest.approx(res["one"]["loss"], rel=1e-4)
    _same(out / "one.npz", out / "four.npz")


@pytest.mark.parametrize("name", ["four_to_one", "one_to_four"])
def test_resume_across_device_counts(four_devices, name):
    out, res = four_devices
    assert res[name]["iterations"] == 3
    _same(out / "one.npz", out / f"{name}.npz")


def test_mesh_must_divide_the_rows(four_devices):
    _, res = four_devices
    assert "does not divide the image's 30 rows" in res["error"]


def test_one_device_is_the_single_device_path():
    board = Board(shape=(32, 32))
    one = jax.sharding.Mesh(np.asarray(jax.devices()[:1]), (mesh.AXIS,))
    assert mesh.resolve(one, board, DesignConfig()) is None
    assert mesh.describe(None)["devices"] == 1
    # one process on the CPU: forced host devices split the same cores, so not used unasked
    assert mesh.default_mesh() is None and mesh.sub_mesh(0) is None
    n = len(jax.devices())
    assert mesh.sub_mesh(n).size == n
    with pytest.raises(InputError, match=rf"--devices must be an int in \[0, {n}\]"):
        mesh.sub_mesh(n + 1)
    with pytest.raises(InputError, match="mesh must be a jax.sharding.Mesh"):
        mesh.resolve("cpu", board, DesignConfig())


def test_culled_lists_refused_on_a_mesh():
    devs = jax.devices()
    if len(devs) < 2:
        pytest.skip("needs the suite's forced CPU devices")
    two = jax.sharding.Mesh(np.asarray(devs[:2]), (mesh.AXIS,))
    with pytest.raises(InputError, match="cull_eps > 0 .* not on a mesh of 2"):
        mesh.resolve(two, Board(shape=(32, 32)), DesignConfig(cull_eps=1e-3))


@pytest.mark.parametrize("args, match", [
    ((None, 2, 0), "need --coordinator"),
    (("localhost:1234", None, 0), "needs --num-processes N and --process-id I"),
    (("localhost:1234", 2, 2), r"--process-id must be an int in \[0, 2\)"),
    (("localhost", 2, 0), "--coordinator must be HOST:PORT"),
])
def test_initialize_refuses_bad_values(args, match):
    with pytest.raises(InputError, match=match):
        mesh.initialize(*args)


def test_the_coordinator_may_come_from_the_environment(monkeypatch):
    """``JAX_COORDINATOR_ADDRESS`` stands for ``--coordinator`` beside ``--num-processes`` and
    ``--process-id`` (checked as the option is: this one has no port)."""
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "localhost")
    with pytest.raises(InputError, match="--coordinator must be HOST:PORT .*got 'localhost'"):
        mesh.initialize(None, 2, 0)


def test_one_process_needs_no_agreement():
    mesh.agree({"config": {"a": 1}})  # one process: nothing to compare, no collective
    assert mesh.is_writer()


# --------------------------------------------------------------------------------------------
# Two processes on localhost (jax.distributed, gloo CPU collectives)

_ARGS = ["--size", "32", "--scratches", "200", "--iterations", "3", "--prune-every", "2",
         "--views", "2", "--quiet"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _cli(args):
    return [sys.executable, "-m", "jscratch.design", *_ARGS, *args]


def _two(out0, out1, extra0=(), extra1=(), timeout=600, cli=_cli, env=None):
    port = _free_port()
    common = ["--coordinator", f"localhost:{port}", "--num-processes", "2", "--join-timeout", "60"]
    procs = [subprocess.Popen(cli(["--out", str(o), *common, "--process-id", str(i), *extra]),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              env={**_env(), **(env or {})})
             for i, (o, extra) in enumerate([(out0, extra0), (out1, extra1)])]
    try:
        return [p.communicate(timeout=timeout) + (p.returncode,) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()


# The command line with the host's free memory read from FREE_BYTES (bytes), JAX's shutdown
# barrier timing out after 5 s, and process 0's outputs written SLOW_SAVE seconds late (a long
# as-carved render).
_PATCHED_CLI = ("import functools, os, sys, time; import jax; "
                "import jscratch.design.run as r; "
                "r.free_memory = lambda: int(os.environ['FREE_BYTES']); "
                "jax.distributed.initialize = functools.partial(jax.distributed.initialize, "
                "shutdown_timeout_seconds=5); import jscratch.design.cli as c; "
                "save = c.save_result; c.save_result = lambda *a, **k: "
                "(time.sleep(float(os.environ['SLOW_SAVE'])), save(*a, **k))[1]; "
                "sys.exit(c.main(sys.argv[1:]))")


def _patched_cli(args):
    return [sys.executable, "-c", _PATCHED_CLI, *_ARGS, *args]


def test_two_processes_equal_one_and_check_their_memory_together(tmp_path):
    """Two processes on this machine design what one process designs (process 0 writes the
    outputs). Process 1 ends its part when the design is done, but not the run: it waits for
    process 0's outputs, so that JAX's shutdown barrier (here 5 s) does not time out and abort
    process 0 while it writes them (10 s late here).

    Their steps' memory is summed before it is compared with the machine's free memory
    (`run.check_step_memory`, `mesh.per_host_total`): with 1.5x one process's need free, each
    process alone would fit, both together do not, so both refuse."""
    ref = subprocess.run(_cli(["--out", str(tmp_path / "one")]), capture_output=True, text=True,
                         timeout=600, env=_env())
    assert ref.returncode == 0, ref.stderr[-3000:]
    (_, e0, r0), (_, e1, r1) = _two(tmp_path / "two", tmp_path / "other", cli=_patched_cli,
                                    env={"FREE_BYTES": str(10 ** 12), "SLOW_SAVE": "10"})
    assert (r0, r1) == (0, 0), (e0[-3000:], e1[-3000:])
    assert not (tmp_path / "other").exists()  # process 0 writes the outputs
    assert (tmp_path / "two" / "design.npz").exists()
    m1 = json.loads((tmp_path / "one" / "metrics.json").read_text())
    m2 = json.loads((tmp_path / "two" / "metrics.json").read_text())
    assert m2["mesh"]["processes"] == 2 and m2["mesh"]["devices"] == 2
    assert m2["prune"] == m1["prune"] and m2["kept"] == m1["kept"]
    one, two = tmp_path / "one" / "result.npz", tmp_path / "two" / "result.npz"
    with np.load(one) as a, np.load(two) as b:
        assert np.array_equal(a["keep"], b["keep"])
        for k in ("geom", "log_width", "log_depth", "logit_alpha", "log_intensity"):
            np.testing.assert_allclose(a[k], b[k], rtol=0, atol=TOL)

    need = m2["step_memory_bytes"]
    assert need > 0
    (_, e0, r0), (_, e1, r1) = _two(tmp_path / "c", tmp_path / "d", cli=_patched_cli,
                                    env={"FREE_BYTES": str(int(1.5 * need)), "SLOW_SAVE": "0"})
    assert (r0, r1) == (2, 2), (e0[-3000:], e1[-3000:])
    assert "this machine (running 2 processes) has" in e0
    assert not (tmp_path / "c").exists() and not (tmp_path / "d").exists()


def test_same_host_sums_add_the_processes_of_one_machine():
    hosts = ["m1/boot", "m2/boot", "m1/boot", "m1/other"]
    values = np.array([5, 7, 11, 13], np.int64)
    assert mesh.same_host_sums(values, hosts, 0) == (16, 2)
    assert mesh.same_host_sums(values, hosts, 2) == (16, 2)
    assert mesh.same_host_sums(values, hosts, 1) == (7, 1)
    assert mesh.same_host_sums(values, hosts, 3) == (13, 1)
    assert mesh.per_host_total(123) == (123, 1)  # one process: no collective
    assert mesh.host_identity() == mesh.host_identity() != ""


def test_two_processes_that_disagree_refuse(tmp_path):
    (_, e0, r0), (_, e1, r1) = _two(tmp_path / "a", tmp_path / "b", extra1=("--seed", "1"))
    assert (r0, r1) == (2, 2)
    for err in (e0, e1):
        assert "error: process 1 and process 0 disagree on the design option --seed" in err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()  # nothing written


def test_a_missing_process_is_one_line(tmp_path):
    port = _free_port()
    p = subprocess.run(_cli(["--out", str(tmp_path / "a"), "--coordinator", f"localhost:{port}",
                             "--num-processes", "2", "--process-id", "0", "--join-timeout", "3"]),
                       capture_output=True, text=True, timeout=300, env=_env())
    assert p.returncode == 2
    # (XLA's coordination service logs in C++ beside the one line; no Python traceback follows)
    assert "\nerror: jax.distributed: process 0 of 2 could not join the run" in "\n" + p.stderr
    assert "Traceback" not in p.stderr
    assert not (tmp_path / "a").exists()


def test_a_coordinator_port_in_use_is_named(tmp_path):
    with socket.socket() as busy:
        busy.bind(("localhost", 0))
        busy.listen()
        port = busy.getsockname()[1]
        p = subprocess.run(_cli(["--out", str(tmp_path / "a"), "--coordinator",
                                 f"localhost:{port}", "--num-processes", "2", "--process-id", "0",
                                 "--join-timeout", "3"]),
                           capture_output=True, text=True, timeout=300, env=_env())
    assert p.returncode == 2
    assert f"error: --coordinator localhost:{port}: port {port} cannot be served here (" in \
        p.stderr and "Traceback" not in p.stderr, p.stderr[-2000:]  # (XLA's service crashed)
    assert not (tmp_path / "a").exists()


def test_a_refusal_on_one_process_stops_every_process(tmp_path):
    # 33 rows do not split over the 2 devices: process 1 refuses, process 0 (32 rows) would not
    (_, e0, r0), (_, e1, r1) = _two(tmp_path / "a", tmp_path / "b", extra1=("--size", "33"))
    assert (r0, r1) == (2, 2)
    assert "error: mesh of 2 devices does not divide the image's 33 rows" in e1
    assert "error: process 1 refused: mesh of 2 devices does not divide the image's 33 rows" in e0
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_devices_that_leave_a_process_out_are_refused_by_every_process(tmp_path):
    """``--devices 1`` over two processes of one device each leaves process 1 without a device
    in the mesh (it crashed, then hung): every process refuses in one line, nothing written."""
    (_, e0, r0), (_, e1, r1) = _two(tmp_path / "a", tmp_path / "b", extra0=("--devices", "1"),
                                    extra1=("--devices", "1"))
    assert (r0, r1) == (2, 2), (e0[-3000:], e1[-3000:])
    says = ("--devices 1 leaves a process of the run without a device in the mesh: every "
            "process needs one (at least --devices 2), or start fewer processes")
    assert f"error: {says}\n" in e0 and f"refused: {says}\n" in e1, (e0[-3000:], e1[-3000:])
    assert "Traceback" not in e0 + e1
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_process_killed_mid_run_stops_the_other_in_one_line(tmp_path):
    """Process 1 killed after the first checkpoint: process 0's next collective fails, and it
    stops with one line (exit 1, no traceback, no C++ abort at the shutdown barrier's timeout);
    its checkpoint is kept for --resume."""
    import time

    port = _free_port()
    common = ["--coordinator", f"localhost:{port}", "--num-processes", "2", "--join-timeout", "60",
              "--iterations", "100000", "--checkpoint-every", "5"]
    procs = [subprocess.Popen(_cli(["--out", str(tmp_path / f"p{i}"), *common, "--process-id",
                                    str(i)]), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env=_env()) for i in range(2)]
    try:
        for _ in range(600):
            if (tmp_path / "p0" / "checkpoint.npz").exists() or procs[0].poll() is not None:
                break
            time.sleep(0.5)
        procs[1].kill()
        _, err = procs[0].communicate(timeout=600)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    assert procs[0].returncode == 1, err[-3000:]
    assert "error: another process of the run stopped (" in err and "Traceback" not in err
    assert (tmp_path / "p0" / "checkpoint.npz").exists()


def test_ctrl_c_while_joining_stops_at_once(tmp_path):
    """Ctrl-C while a process waits for the others to join: it stops then, in one line (blocked
    in XLA's join it went on waiting for the whole --join-timeout)."""
    import signal
    import time

    port = _free_port()
    cmd = _cli(["--out", str(tmp_path / "a"), "--coordinator", f"localhost:{port}",
                "--num-processes", "2", "--process-id", "0", "--join-timeout", "600"])
    # Ctrl-C's default, whatever this process inherited (a shell's background job ignores
    # SIGINT), set by a small parent that then becomes the command (no fork of this process).
    default_sigint = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
                      "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])")
    p = subprocess.Popen([sys.executable, "-c", default_sigint]
                         + [a for a in cmd[1:] if a != "--quiet"],  # (it says when it waits)
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        import queue
        import threading

        lines: queue.Queue = queue.Queue()  # stderr's lines, read on a thread
        threading.Thread(target=lambda: [lines.put(t) for t in p.stderr] + [lines.put("")],
                         daemon=True).start()
        want = f"process 0 of 2: waiting up to 600 s for every process to join at localhost:{port}"
        seen = []  # (the imports and the checks come first)
        while not (seen and seen[-1].startswith(want)):
            seen.append(lines.get(timeout=300))
            assert seen[-1], f"it ended before the join: {seen}"
        time.sleep(1)  # (into XLA's join)
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=120) is not None  # (not the 600 s join timeout)
        err = "".join(iter(lambda: lines.get(timeout=10), ""))
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130 and "error: interrupted" in err and "Traceback" not in err, err
