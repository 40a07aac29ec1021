"""A design on a `jax.sharding.Mesh`: one process with several devices, or several processes
joined by JAX's own distributed runtime (`jax.distributed`).

The design runs the same program on every process (JAX's multi-controller model). The image
work is split over the mesh's one axis, ``"pixels"``: `render.render_pairs` renders strips of
rows under `jax.shard_map` and sums the parameters' gradients with a ``psum``; the scratch
parameters, the Adam state and the small per-design constants (`solver.Context`) are replicated.
The jitted functions of `jscratch.design.solver` return replicated arrays (`replicated`), so the
host code between steps (rebinning, capacity retries, health checks, prune/re-seed, discard,
stopping rules) reads the same values on every process and makes the same decisions there.

This module holds what that needs beside the solver: building and checking the mesh
(`resolve`, `initialize`), the check that every process runs the same design (`agree`), the
shared pair list laid out per pixel shard (`shard_lists`), placing per-design constants on the
mesh (`place`), reading a file on process 0 for every process (`read_on_zero`) and the record of
the mesh for ``metrics.json`` (`describe`). Process 0 writes the outputs and the checkpoint
(`is_writer`). A checkpoint holds the device-count-independent shared list (not its layout), so
it resumes on any mesh.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import json
import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jscratch import bvh
from jscratch.errors import DesignFileError, InputError

__all__ = ["AXIS", "abandoned_join", "agree", "all_or_none", "checkpoint_bytes", "default_mesh",
           "describe", "initialize", "is_writer", "joined", "outputs_written", "place",
           "read_on_zero", "replicated", "resolve", "shard_lists", "sub_mesh", "versions"]

#: The mesh axis the pixels (rows of the image) are split over.
AXIS = "pixels"


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, timeout: int = 300, say=None) -> bool:
    """Join the processes of a run with `jax.distributed.initialize` (before any JAX work).

    With `coordinator` (``HOST:PORT``) the three values are given; without it, when the
    environment names a coordinator (``JAX_COORDINATOR_ADDRESS``, or a cluster JAX detects:
    SLURM, Open MPI, ...) JAX reads the rest from there. Otherwise nothing is done (one process).
    `timeout`: seconds to wait for every process; `say(line)`, when given, is told that the
    process waits for the others. Returns whether the runtime was started.
    Raises `InputError` (one line) for inconsistent values or a process that did not join."""
    if coordinator is None and (num_processes is not None or process_id is not None):
        coordinator = os.environ.get("JAX_COORDINATOR_ADDRESS") or None  # (its equivalent)
        if coordinator is None:
            raise InputError("--num-processes and --process-id need --coordinator HOST:PORT (or "
                             "JAX_COORDINATOR_ADDRESS)")
    if coordinator is None and not os.environ.get("JAX_COORDINATOR_ADDRESS"):
        return False
    if coordinator is not None:
        if num_processes is None or process_id is None:
            raise InputError("--coordinator needs --num-processes N and --process-id I")
        if not (isinstance(num_processes, int) and num_processes >= 1):
            raise InputError(f"--num-processes must be an int >= 1, got {num_processes!r}")
        if not (isinstance(process_id, int) and 0 <= process_id < num_processes):
            raise InputError(f"--process-id must be an int in [0, {num_processes}), "
                             f"got {process_id!r}")
        host, _, port = coordinator.rpartition(":")
        if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise InputError(f"--coordinator must be HOST:PORT (a port in 1-65535), got "
                             f"{coordinator!r}")
    if not (isinstance(timeout, int) and not isinstance(timeout, bool) and timeout >= 1):
        raise InputError(f"--join-timeout must be an int >= 1 (seconds), got {timeout!r}")
    if process_id == 0 and coordinator is not None:
        _check_port_free(coordinator)
    if say is not None:
        say(f"process {process_id} of {num_processes}: waiting up to {timeout} s for every "
            f"process to join at {coordinator or os.environ.get('JAX_COORDINATOR_ADDRESS')}")
    try:
        _join_interruptibly(lambda: jax.distributed.initialize(
            coordinator, num_processes, process_id, initialization_timeout=int(timeout)))
    except Exception as exc:  # XLA's errors are long; the one line names what happened
        _forget_failed_client()
        where = coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS")
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        first = "" if "bad_cast" in first else f": {first}"  # (the callback's own failure)
        raise InputError(f"jax.distributed: process {process_id} of {num_processes} could not "
                         f"join the run at {where} within {timeout} s (is every process started,"
                         f" with the same --coordinator and --num-processes?){first}") from None
    global _JOINED
    _JOINED = jax.process_count() > 1
    return True


_ABANDONED: list = []  # a join left behind by Ctrl-C (`abandoned_join`)


def abandoned_join() -> bool:
    """Whether a Ctrl-C left this process's join of a run behind (blocked in XLA's client): the
    process then ends without JAX's shutdown, which would wait for the join."""
    return bool(_ABANDONED)


def _join_interruptibly(join) -> None:
    """Run `join` (XLA's blocking connect) on a thread and wait for it here, where Ctrl-C is
    delivered (blocked in XLA it would wait for the join's timeout): `KeyboardInterrupt` then,
    the join left behind (`abandoned_join`); its own error is raised here."""
    import threading

    box = []

    def run():
        try:
            with _join_errors_raise():
                join()
        except BaseException as exc:  # (handed to the waiting thread)
            box.append(exc)

    thread = threading.Thread(target=run, name="jscratch-join", daemon=True)
    thread.start()
    try:
        while thread.is_alive():
            thread.join(0.1)
    except KeyboardInterrupt:
        _ABANDONED.append(thread)
        raise
    if box:
        raise box[0]


def _check_port_free(coordinator: str) -> None:
    """Process 0 serves the coordinator on every address at the port of ``HOST:PORT``: refuse
    a port that cannot be bound there (in use), which XLA's service answers with a crash."""
    import socket

    port = int(coordinator.rpartition(":")[2])
    for family, address in ((socket.AF_INET6, "::"), (socket.AF_INET, "0.0.0.0")):
        try:
            with socket.socket(family) as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # (a closed run's port)
                s.bind((address, port))
            return
        except OSError as exc:
            if family == socket.AF_INET6 and exc.errno != errno.EADDRINUSE:
                continue  # (no IPv6 here: the IPv4 address instead)
            raise InputError(f"--coordinator {coordinator}: port {port} cannot be served here "
                             f"({exc.strerror}): is it in use by another program? Give another "
                             "port") from None


def default_mesh() -> Mesh | None:
    """The mesh a design runs on when none is given: every device JAX sees (all processes'),
    axis `AXIS`, when several processes are joined or the devices are accelerators; `None` (one
    device) for one process on the CPU, whose one device already runs on every core (forced
    host devices, ``--xla_force_host_platform_device_count``, split the same cores: a test
    setting, asked for with an explicit mesh or ``--devices``)."""
    devs = jax.devices()
    if jax.process_count() > 1 or devs[0].platform != "cpu":
        return Mesh(np.asarray(devs), (AXIS,))
    return None


_FAILED: list = []
_JOINED = False  # whether this process has joined a run of several (`initialize`)


def joined() -> bool:
    """Whether this process joined a run of several processes (`initialize`)."""
    return _JOINED


def _forget_failed_client():
    """Drop the client of a join that failed: it cannot shut down, and JAX's exit hook would
    try and print a traceback and a C++ log after the one-line error. Where this JAX keeps its
    state elsewhere, nothing is changed."""
    try:
        from jax._src import distributed
        state = distributed.global_state
        _FAILED.append(state.client)  # (its destructor logs the failure again: kept to the end)
        state.preemption_sync_manager = state.client = state.service = None
    except (ImportError, AttributeError):
        pass


@contextlib.contextmanager
def _join_errors_raise():
    """While joining: XLA's distributed client given a callback for the service's fatal errors,
    so that a process that does not join within the timeout makes `connect` raise (caught and
    reported in one line) instead of the client's default, aborting the process with a C++ log.
    Where this JAX's private client factory differs, nothing is changed (JAX then aborts)."""
    try:
        from jax._src.lib import _jax
        factory = _jax.get_distributed_runtime_client
        if "missed_heartbeat_callback" not in (factory.__doc__ or ""):
            raise AttributeError
    except (ImportError, AttributeError):
        yield
        return

    def failed(*_):
        raise RuntimeError("a process of the run failed or did not join")

    def client(*args, **kw):
        kw.setdefault("missed_heartbeat_callback", failed)
        return factory(*args, **kw)

    _jax.get_distributed_runtime_client = client
    try:
        yield
    finally:
        _jax.get_distributed_runtime_client = factory


def resolve(mesh: Mesh | None, board, config) -> Mesh | None:
    """The mesh a design runs on: `mesh`, or `default_mesh`; `None` (the single-device path, no
    `shard_map`) when that is one device. Raises `InputError` when the mesh does not divide the
    work: its devices must split the image's ``H`` rows evenly, and per-view culled lists
    (``cull_eps > 0``) are laid out for one device only."""
    if mesh is None:
        mesh = default_mesh()
        if mesh is None:
            return None
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a jax.sharding.Mesh, got {type(mesh).__name__}")
    n = int(mesh.size)
    if n == 1:
        return None
    if board.H % n:
        raise InputError(f"mesh of {n} devices does not divide the image's {board.H} rows "
                         f"(each device renders H/{n} rows): use a device count that divides "
                         f"{board.H} (--devices)")
    if config.cull_eps > 0:
        raise InputError(f"cull_eps > 0 (per-view culled lists) runs on one device, not on a "
                         f"mesh of {n}: use --cull-eps 0 or --devices 1")
    return mesh


def sub_mesh(devices: int) -> Mesh | None:
    """A mesh over the first `devices` devices JAX sees (0: `default_mesh`)."""
    devs = jax.devices()
    if not (isinstance(devices, int) and 0 <= devices <= len(devs)):
        raise InputError(f"--devices must be an int in [0, {len(devs)}] (the devices JAX sees), "
                         f"got {devices!r}")
    if devices == 0:
        return default_mesh()
    first = {}  # each process's first device, in JAX's order
    for i, d in enumerate(devs):
        first.setdefault(d.process_index, i)
    if max(first.values()) >= devices:
        raise InputError(f"--devices {devices} leaves a process of the run without a device in "
                         f"the mesh: every process needs one (at least --devices "
                         f"{max(first.values()) + 1}), or start fewer processes")
    return Mesh(np.asarray(devs[:devices]), (AXIS,))


#: How long the processes of a run wait for process 0 to write the outputs (ms, `outputs_written`).
WRITE_WAIT_MS = 24 * 3600 * 1000


def outputs_written(done: bool) -> None:
    """With several processes: process 0 (``done=True``) says it has written the outputs, or
    stopped; the others (``done=False``) wait for it (up to `WRITE_WAIT_MS`), so that none ends
    the run, and JAX's shutdown barrier does not time out and abort process 0, while it writes.
    Nothing for one process."""
    if jax.process_count() == 1:
        return
    from jax._src import distributed

    client = distributed.global_state.client
    if done:
        client.key_value_set("jscratch/outputs_written", "1", allow_overwrite=True)
    else:
        client.blocking_key_value_get("jscratch/outputs_written", WRITE_WAIT_MS)


def describe(mesh: Mesh | None) -> dict[str, Any]:
    """The mesh a run used, for ``metrics.json``: device count, process count, axis sizes and
    the devices' platform and kind."""
    devs = [jax.devices()[0]] if mesh is None else list(mesh.devices.flat)
    return {"devices": len(devs), "processes": len({d.process_index for d in devs}),
            "axes": {AXIS: 1} if mesh is None else {k: int(v) for k, v in mesh.shape.items()},
            "platform": devs[0].platform, "device_kind": devs[0].device_kind}


def is_writer() -> bool:
    """Whether this process writes the outputs and the checkpoint (process 0)."""
    return jax.process_index() == 0


def _rep(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def _put(x, sharding: NamedSharding):
    """``x`` as a global array with `sharding`, built from this process's host copy
    (`jax.make_array_from_callback`: no collective, unlike `jax.device_put`, which checks that
    every process passed the same value and so must not run beside another thread's collective)."""
    if isinstance(x, jax.Array) and x.sharding == sharding:
        return x
    host = np.asarray(x)
    return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])


def place(tree, mesh: Mesh | None):
    """`tree`'s array leaves replicated on every device of `mesh` (unchanged without a mesh):
    per-design constants are put there once instead of at every call."""
    if mesh is None:
        return tree
    return jax.tree_util.tree_map(
        lambda x: _put(x, _rep(mesh)) if isinstance(x, (jax.Array, np.ndarray)) else x,
        tree)


def replicated(tree, mesh: Mesh | None):
    """Inside jit: `tree`'s arrays constrained to be replicated over `mesh`, so that every
    process can read them (`np.asarray`) and the host makes the same decisions everywhere."""
    if mesh is None:
        return tree
    return jax.tree_util.tree_map(
        lambda x: jax.lax.with_sharding_constraint(x, _rep(mesh)) if isinstance(x, jax.Array)
        else x, tree)


# The last layout made, by the shared list it was made from (rebuilt only when that changes).
_LAST: list = [None, None, None]


def shard_lists(lists: bvh.PairLists, mesh: Mesh | None, board, chunk: int,
                n: int) -> bvh.PairLists:
    """`lists` with the shared list laid out for the mesh's pixel shards (`bvh.layout`: equal
    segments, segment ``s`` holding the pairs of rows ``[s H/k, (s+1) H/k)`` of a ``k``-device
    mesh, placed on device ``s``), the layout `render.render_pairs` checks; its binning record
    (``bin_*``, what `bvh.needs_rebin` compares) is kept, replicated. ``n``: the number of
    scratches (the padding's sentinel). Lists already laid out, and any lists without a mesh,
    are returned as they are. The layout is a function of the shared list alone, so a resumed
    run lays out the same. Host code; the last layout is kept until the shared list changes."""
    if mesh is None or lists is _LAST[2]:
        return lists
    shared = lists.shared
    if _LAST[0] is shared and _LAST[1] == (mesh, board, chunk, n):
        return _LAST[2]
    pix, scr, val = bvh.layout(np.asarray(shared.pixel).reshape(-1),
                               np.asarray(shared.scratch).reshape(-1),
                               [np.asarray(shared.valid).reshape(-1)], n, board, int(mesh.size),
                               chunk)
    split = NamedSharding(mesh, PartitionSpec(AXIS))
    record = place(dataclasses.replace(shared, pixel=None, scratch=None, valid=None), mesh)
    laid = dataclasses.replace(record, pixel=_put(pix[0], split), scratch=_put(scr[0], split),
                               valid=_put(val[0], split))
    out = dataclasses.replace(lists, shared=laid, counts=place(lists.counts, mesh))
    _LAST[:] = [shared, (mesh, board, chunk, n), out]
    return out


def _digest(value) -> np.ndarray:
    """32 bytes of SHA-256 of a JSON-able value (or bytes)."""
    raw = value if isinstance(value, bytes) else json.dumps(value, sort_keys=True,
                                                            default=str).encode()
    return np.frombuffer(hashlib.sha256(raw).digest(), np.uint8)


def agree(items: dict[str, Any]) -> None:
    """Check that every process of the run has the same `items` (name -> JSON-able value or
    bytes: inputs, config, versions). One process: nothing to check. Raises `InputError` naming
    the first item and process that differ from process 0 (on every process: the verdict is
    computed from the digests all of them gathered)."""
    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils

    names = list(items)
    mine = np.stack([_digest(items[k]) for k in names])  # (k, 32)
    everyone = np.asarray(multihost_utils.process_allgather(mine))  # (processes, k, 32)
    for i, name in enumerate(names):
        for p in range(1, everyone.shape[0]):
            if not np.array_equal(everyone[p, i], everyone[0, i]):
                raise InputError(f"process {p} and process 0 disagree on the {name}: run the same "
                                 "command, inputs and jscratch/JAX versions on every process")


def host_identity() -> str:
    """This machine's name and the running kernel's boot id: equal for the processes that share
    one machine's memory, different across machines (and across containers, which have their
    own names and memory limits)."""
    import socket

    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip()
    except OSError:
        boot = ""
    return f"{socket.gethostname()}/{boot}"


def same_host_sums(values: np.ndarray, hosts: list[str], me: int) -> tuple[int, int]:
    """The sum of `values` (one per process) over the processes whose `hosts` entry equals
    process `me`'s, and their count."""
    here = [i for i, h in enumerate(hosts) if h == hosts[me]]
    return int(sum(int(values[i]) for i in here)), len(here)


def per_host_total(value: int) -> tuple[int, int]:
    """``value`` (a non-negative int, such as bytes this process needs) summed over every process
    running on this machine (`host_identity`), and the number of those processes. A collective:
    every process of the run calls it. One process: ``(value, 1)``."""
    if jax.process_count() == 1:
        return int(value), 1
    from jax.experimental import multihost_utils

    # bytes, which every dtype setting carries unchanged (ints would be cut to 32 bits)
    mine = np.concatenate([_digest(host_identity()),
                           np.frombuffer(np.int64(value).tobytes(), np.uint8)])
    everyone = np.asarray(multihost_utils.process_allgather(mine))  # (processes, 40)
    hosts = [bytes(row[:32]).hex() for row in everyone]
    values = np.frombuffer(np.ascontiguousarray(everyone[:, 32:]).tobytes(), np.int64)
    return same_host_sums(values, hosts, jax.process_index())


def all_or_none(checks):
    """``checks()`` (a function that raises a `JscratchError` or `OSError` to refuse) on every
    process, and its verdict shared: when it refused on any process, every process raises the
    refusal of the first that refused (its one line, prefixed with the process on the others),
    so no process is left waiting in a collective for one that stopped. Returns ``checks()``'s
    value. One process: just ``checks()``."""
    from jscratch.errors import JscratchError

    if jax.process_count() == 1:
        return checks()
    from jax.experimental import multihost_utils

    try:
        value, refusal = checks(), None
    except (JscratchError, OSError) as exc:  # (an unreadable input file: OSError)
        value, refusal = None, exc
    failed = np.asarray(multihost_utils.process_allgather(np.int32(refusal is not None)))
    if not failed.any():
        return value
    first = int(np.argmax(failed))
    me = jax.process_index() == first
    text = np.zeros(400, np.uint8)
    if me:
        raw = str(refusal).encode()[:400]
        text[:len(raw)] = np.frombuffer(raw, np.uint8)
    text = bytes(np.asarray(multihost_utils.broadcast_one_to_all(text, is_source=me)))
    if me:
        raise refusal
    cls = type(refusal) if refusal is not None else InputError
    raise cls(f"process {first} refused: {text.rstrip(bytes(1)).decode(errors='replace')}")


def versions() -> dict[str, str]:
    """The versions every process must share (jscratch, JAX, jaxlib)."""
    import jaxlib

    import jscratch

    return {"jscratch": getattr(jscratch, "__version__", "?"), "jax": jax.__version__,
            "jaxlib": jaxlib.__version__}


def read_on_zero(path: str) -> bytes | None:
    """The bytes of file `path` as process 0 reads them, on every process (`None` when process 0
    has no such file): hosts without a shared file system resume from process 0's checkpoint."""
    if jax.process_count() == 1:
        if not os.path.isfile(path):
            return None
        with open(path, "rb") as f:
            return f.read()
    from jax.experimental import multihost_utils

    data = b""
    if is_writer() and os.path.isfile(path):
        with open(path, "rb") as f:
            data = f.read()
    size = -1 if is_writer() and not os.path.isfile(path) else len(data)
    size = int(multihost_utils.broadcast_one_to_all(np.int64(size)))
    if size < 0:
        return None
    buf = np.zeros(size, np.uint8)
    if is_writer():
        buf[:] = np.frombuffer(data, np.uint8)
    return bytes(np.asarray(multihost_utils.broadcast_one_to_all(buf)).tobytes())


def checkpoint_bytes(path: str) -> bytes:
    """`read_on_zero` for ``--resume``: refuses (on every process) when process 0 has none."""
    raw = read_on_zero(path)
    if raw is None:
        raise DesignFileError(f"resume: no checkpoint at {path!r}")
    return raw
