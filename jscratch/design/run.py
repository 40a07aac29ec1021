"""The optimisation loop: `design(targets, views, board, config) -> DesignResult`."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import os
import threading
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from jscratch import bvh, native
from jscratch import loss as loss_mod
from jscratch.designfile import DesignError
from jscratch.metrics import image_metrics
from jscratch.scene import Board, Scratches, Views
from jscratch.shading import DISPLAY_GAMMA, board_ndf, display, half_vectors
from jscratch.design.checkpoint import State, load_checkpoint, save_checkpoint
from jscratch.design.config import DesignConfig, NonFiniteError, SceneConfig
from jscratch.design.discard import compile_scores, discard, fewest_for_ssim
from jscratch.design import mesh as mesh_mod
from jscratch.design import prune as prune_mod
from jscratch.design.io import check_design_views, check_targets, inputs_hash
from jscratch.design.params import DesignParams, group_tree
from jscratch.design.result import DesignResult
from jscratch.design.solver import (
    Context,
    compile_step,
    evaluate,
    make_adam,
    physical,
    step,
)


def design(
    targets: Float[ArrayLike, "M H W"],
    views: Views | None = None,
    board: Board | None = None,
    config: DesignConfig | None = None,
    *,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    progress: bool = False,
    stop_after: int | None = None,
    mesh: jax.sharding.Mesh | None = None,
) -> DesignResult:
    """Optimise scratches and light intensities so that view ``j`` shows ``targets[j]``.

    **Arguments:**

    - `targets`: ``(M, H, W)`` display values in ``[0, 1]``, row 0 at the top (docs/model.md §1).
    - `views`: `jscratch.Views` with ``M`` cameras and lights (m, above the board); the
      intensities are the starting values when ``config.init_intensity == "given"``. Default: the
      command line's, ``SceneConfig().make_views(M, board)`` (light and cameras at 50 degrees).
    - `board`: `jscratch.Board`; its ``shape`` must be ``(H, W)``. Default ``Board(shape=(H, W))``
      with square pixels, its longer side 0.3 m (for square targets the command line's board).
    - `config`: `DesignConfig` (default ``DesignConfig()``, the command line's defaults: the same
      inputs and configs give the same result bit for bit).
    - `checkpoint`: path of a checkpoint file, written every ``config.checkpoint_every``
      iterations, at the end, and with the last good state when a NaN stops the run.
    - `resume`: continue from `checkpoint` (same targets and config); the continued run is
      identical to an uninterrupted one.
    - `progress`: show a tqdm progress bar with the loss.
    - `stop_after`: stop after this many iterations in total (for tests of resuming); the
      checkpoint is written and the result describes the state at that point.
    - `mesh`: the `jax.sharding.Mesh` the image work is split over (`jscratch.design.mesh`);
      default `jscratch.design.mesh.default_mesh`: every device JAX sees (all processes' after
      `jax.distributed.initialize`) on accelerators or with several processes, else one device
      (the single-device path, no `shard_map`). Every process calls `design` with the same
      arguments; process 0 writes the checkpoint. The result equals the one-device result to
      float rounding (the sums run in another order).

    **Returns:** a `DesignResult`.

    **Raises:** `DesignError` (an `jscratch.InputError`) for bad targets, views or config, before
    any work; `NonFiniteError` when the loss, a gradient or a parameter becomes non-finite (after
    saving the last good state to `checkpoint`).
    """
    t_start = time.perf_counter()
    parts = {}  # wall time per part of the run (s): `metrics["time_parts"]`
    config = DesignConfig() if config is None else config
    # the native kernel builds (first run only) during the setup
    native.prepare(getattr(config, "dtype", "float32"))
    native.keep_freed_memory()  # the steps reuse their large buffers (`native.keep_freed_memory`)
    for name, flag in (("resume", resume), ("progress", progress)):
        if not isinstance(flag, (bool, np.bool_)):  # ("no" would be true)
            raise DesignError(f"design: `{name}` must be True or False, got {flag!r}")
    tnp, views, board = check_inputs(targets, views, board, config, checkpoint, resume)
    mesh_mod.all_or_none(memory_check_on)  # a bad JSCRATCH_MEMORY_CHECK: refused before any work
    if stop_after is not None and not (isinstance(stop_after, (int, np.integer))
                                       and not isinstance(stop_after, bool) and stop_after >= 1):
        raise DesignError(f"stop_after must be None or an int >= 1, got {stop_after!r}")
    checkpoint = None if checkpoint is None else os.fspath(checkpoint)
    inputs = inputs_hash(tnp, views, board)  # what a checkpoint is keyed to
    # --- mesh: the devices the design runs on, and every process running the same design
    mesh = mesh_mod.resolve(mesh, board, config)
    mesh_mod.agree({"target images": inputs["targets_hash"], "design config": config.to_dict(),
                    "views": [np.asarray(views.camera).tolist(), np.asarray(views.light).tolist(),
                              np.asarray(views.intensity).tolist()],
                    "board": [board.Sx, board.Sy, list(board.shape)],
                    "run (resume, stop_after)": [bool(resume), stop_after],
                    "versions": mesh_mod.versions()})
    raw = mesh_mod.checkpoint_bytes(checkpoint) if resume and mesh is not None else None
    mesh_mod.all_or_none(functools.partial(check_scratch_memory, config, mesh))
    # ---
    phase = _Phase(progress, config.dtype)  # what the run does before its first step, one line
    try:
        phase.show("setting up")
        params, optimizer, ctx = setup(tnp, views, board, config, mesh)
        t = time.perf_counter()
        parts["setup"] = t - t_start
        warm = None
        if resume:
            like = State(0, params, optimizer.init(params), None, {}, 0)
            state = load_checkpoint(checkpoint, like, config, inputs, raw)
        else:
            phase.show("compiling the step; the initial render")
            state, warm = initial_state(params, optimizer, ctx, tnp, config)
        compile_seconds = compiled = None
        if warm is not None:
            phase.show("compiling the step")
            warm.join()
            compile_seconds, compiled = warm.seconds, warm.step
        elif state.iteration < config.iterations:  # resumed: the step compiled here, to check
            phase.show("compiling the step")
            t_c = time.perf_counter()
            try:
                compiled = compile_step(state.params, state.opt_state, state.lists, ctx,
                                        optimizer)
            except Exception:  # the first step compiles again and raises it properly
                pass
            compile_seconds = time.perf_counter() - t_c
        # (every process refuses together: none is left waiting for one that stopped)
        mesh_mod.all_or_none(functools.partial(check_step_memory, compiled, mesh))
        step_bytes = None if compiled is None else step_memory(compiled)
    finally:
        phase.close()
    parts["initial_state"] = time.perf_counter() - t
    n_iter = config.iterations if stop_after is None else min(config.iterations, stop_after)
    state, step_times, loop = _iterate(state, optimizer, ctx, config, n_iter, checkpoint, inputs,
                                       progress)
    parts.update(loop)
    t = time.perf_counter()
    result = _finish(state, ctx, tnp, config, discard_now=(
        config.discard or config.target_ssim is not None) and stop_after is None)
    parts["finish"] = time.perf_counter() - t
    result.metrics["pair_views_evaluated"] = loop.pop("pair_views")
    result.metrics["skip_eps"] = ctx.skip_eps
    result.metrics.update({
        "time_total": time.perf_counter() - t_start,
        "time_first_step": step_times[0] if step_times else None,
        "time_step_median": float(np.median(step_times[1:])) if len(step_times) > 1 else None,
        "time_compile_step": compile_seconds,
        "step_memory_bytes": step_bytes,  # per device, `step_memory`
        "time_parts": {k: v for k, v in parts.items() if k != "pair_views"},
        "kernel": native.status(config.dtype),
        "mesh": mesh_mod.describe(mesh),
    })
    if mesh is not None:  # host copies: what follows (saving, metrics) may run on process 0 alone
        result = dataclasses.replace(result, params=jax.device_get(result.params))
    return result


def check_inputs(targets, views, board, config, checkpoint=None, resume=False):
    """Every check `design` makes before any work: ``(targets (M, H, W) numpy, views, board)``
    with the defaults filled in, the loss built once (a missing VGG file is refused here).
    Raises `DesignError` naming what is wrong."""
    if not isinstance(config, DesignConfig):
        raise DesignError(f"config must be a DesignConfig, got {type(config).__name__}")
    if views is not None and not isinstance(views, Views):
        raise DesignError(f"views must be a jscratch.Views, got {type(views).__name__}")
    tnp = check_targets(targets, None if views is None else views.m)
    h, w = tnp.shape[1:]
    if board is not None and not isinstance(board, Board):
        raise DesignError(f"board must be a jscratch.Board, got {type(board).__name__}")
    scene = SceneConfig()  # the command line's defaults for what is not given
    if board is None:  # square pixels, the longer side the command line's board side
        side = scene.board / max(h, w)
        board = Board(shape=(h, w), Sx=side * w if w < h else scene.board,
                      Sy=side * h if h < w else scene.board)
    if views is None:
        views = scene.make_views(tnp.shape[0], board)
    if board.shape != (h, w):
        raise DesignError(f"targets are {h}x{w} px but the board's image shape is {board.shape}")
    check_design_views(views, board)
    if config.dtype == "float64" and jax.dtypes.canonicalize_dtype(jnp.float64) != jnp.float64:
        raise DesignError("dtype float64 needs jax_enable_x64 (jax.config.update('jax_enable_x64', True))")
    if resume and checkpoint is None:
        raise DesignError("resume=True needs a checkpoint path")
    if checkpoint is not None:
        _check_file_path("checkpoint", checkpoint)
    loss_mod.make_loss(config.loss)  # refuses a missing or bad VGG weights file now
    return tnp, views, board


def _check_file_path(what: str, path) -> None:
    """Refuse (`DesignError`) a path that no file can be written at: not a path, a folder, or
    under a file."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise DesignError(f"{what} must be a file path, got {path!r}")
    path = os.path.abspath(os.fspath(path))
    if os.path.isdir(path):
        raise DesignError(f"{what} {path!r} is a folder; give a file path in it, such as "
                          f"{os.path.join(path, 'checkpoint.npz')!r}")
    above = os.path.dirname(path)
    while not os.path.exists(above):
        above = os.path.dirname(above)
    if not os.path.isdir(above):
        raise DesignError(f"{what} {path!r} cannot be written: {above!r} is a file, not a folder")


def setup(tnp, views, board, config, mesh=None):
    """The initial parameters (the structure a checkpoint is restored into), the optimiser and the
    step's `Context` (on `mesh`, its arrays replicated there: `jscratch.design.mesh`)."""
    dt = jnp.dtype(config.dtype)
    # The loss binds the targets (their Gram matrices and ghosting baseline: two compilations)
    # on a second thread while this one draws the scratches and the views' half vectors.
    with concurrent.futures.ThreadPoolExecutor(1, "jscratch-bind-loss") as pool:
        binding = pool.submit(_in_this_context(loss_mod.make_loss(
            config.design_loss(board.n_pixels)).bind), jnp.asarray(tnp, dt))
        params, optimizer, lrs, cam, lig, hs, ndf_max = _setup_scene(views, board, config, dt)
        bound = binding.result()
    ctx = Context(cam, lig, hs, ndf_max, bound, lrs, board, int(config.chunk), mesh,
                  float(config.skip_eps))
    return mesh_mod.place(params, mesh), optimizer, mesh_mod.place(ctx, mesh)


def _in_this_context(fn):
    """``fn``, to run on another thread in this thread's JAX dtype setting (the
    `jax.enable_x64` context is thread-local: a thread would otherwise trace in float32)."""
    x64 = bool(jax.config.jax_enable_x64)

    def run(*args, **kwargs):
        with jax.enable_x64(x64):
            return fn(*args, **kwargs)
    return run


def _setup_scene(views, board, config, dt):
    """`setup`'s parameters, optimiser, learning rates and views: ``(params, optimizer, lrs,
    camera, light, half vectors, the board's largest GGX per pixel)``."""
    scratches = Scratches.random(
        jax.random.PRNGKey(config.seed), config.n_scratches, board, length=config.init_length,
        width=config.init_width, depth=config.init_depth, alpha=config.init_alpha, dtype=dt)
    groove = None
    if config.groove == "carvable":
        from jscratch.design.carvable import groove_map_of

        groove = groove_map_of(config.machine_profile())
    params = DesignParams.from_physical(scratches, np.asarray(views.intensity), board,
                                        config.parameterisation, groove)
    optimizer = make_adam(config.adam_b1, config.adam_b2, config.adam_eps)
    if config.lr_schedule == "cosine":
        optimizer = make_adam(config.adam_b1, config.adam_b2, config.adam_eps, config.iterations,
                              config.lr_final)
    lrs = group_tree(params, {g: jnp.asarray(v, dt) for g, v in config.learning_rates().items()})
    cam = jnp.asarray(views.camera, dt)
    lig = jnp.asarray(views.light, dt)
    hs = half_vectors(Views(cam, lig), board, dt)
    ndf_max = _board_ndf_max(Views(cam, lig), board, dt)  # (P,)
    return params, optimizer, lrs, cam, lig, hs, ndf_max


@eqx.filter_jit
def _board_ndf_max(views, board, dtype):
    """The flat board's GGX, largest over the views, ``(P,)`` (one compiled call, not an eager op
    per line)."""
    return jnp.max(board_ndf(views, board, dtype), axis=0)


@eqx.filter_jit
def _scratches(params) -> Scratches:
    return params.scratches()


def pair_lists(params, ctx, config) -> bvh.PairLists:
    """The `bvh.PairLists` of ``params`` (`bvh.allocate_lists`: the shared list binned with
    ``config.skin``, the per-view capacities measured when ``config.cull_eps > 0``)."""
    return bvh.allocate_lists(_scratches(params), ctx.board, ctx.hs, ctx.board_ndf,
                              cull_eps=float(config.cull_eps),
                              coverage_eps=float(config.coverage_eps), skin=config.skin)


def rebin(lists, params, ctx) -> bvh.PairLists:
    """``lists`` with the shared list binned again for ``params`` (`bvh.rebin_lists`)."""
    return bvh.rebin_lists(lists, _scratches(params), ctx.board)


def remeasure(lists, params, ctx) -> bvh.PairLists:
    """``lists`` with per-view capacities that hold ``params``' culled lists (never smaller)."""
    return bvh.grow_lists(lists, bvh.list_counts(lists, _scratches(params), ctx.hs,
                                                 ctx.board_ndf))


def initial_state(params, optimizer, ctx, tnp, config):
    """Iteration 0: the pair list, the per-view capacities and (``init_intensity ==
    "match_mean"``) the closed-form light intensities. Returns ``(state, Compiling)``: the
    threads compiling meanwhile what the run will call (`_compile_meanwhile`), the step and,
    when the run scores its scratches (`_scores_needed`), `discard.scores`' contributions."""
    m, dt = tnp.shape[0], params.geom.dtype
    lists = pair_lists(params, ctx, config)
    opt_state = optimizer.init(params)
    threads = [_compile_meanwhile("step", functools.partial(compile_step, params, opt_state,
                                                            lists, ctx, optimizer))]
    if _scores_needed(ctx, config):
        threads.append(_compile_meanwhile("scores", functools.partial(compile_scores, params,
                                                                      lists, ctx)))
    warm = Compiling(threads)
    if config.init_intensity == "match_mean":
        unit = eqx.tree_at(lambda p: p.log_intensity, params, jnp.zeros((m,), dt))
        all_keep = jnp.ones((config.n_scratches,), bool)
        rad = np.asarray(evaluate(unit, lists, all_keep, ctx)[0], np.float64)
        if np.any(np.max(rad, axis=(1, 2)) <= 0):
            j = int(np.argmax(np.max(rad, axis=(1, 2)) <= 0))
            raise DesignError(f"view {j} renders black at intensity 1: cannot set its light")
        log_i = matching_log_intensity(rad, np.maximum(tnp.mean(axis=(1, 2)), 1e-6))
        params = eqx.tree_at(lambda p: p.log_intensity, params, jnp.asarray(log_i, dt))
    history = {"total": [], "terms": {}}
    return State(0, params, opt_state, lists, history, 0), warm


def matching_log_intensity(radiance, target_mean) -> np.ndarray:
    """Per view, the log intensity ``u`` (log W/sr) at which the mean display value of
    ``exp(u) * radiance`` equals ``target_mean``: ``(M,)`` from the radiance at intensity 1
    ``(M, H, W)`` (not all zero) and ``(M,)`` display means in ``(0, 1]``.

    The display curve is a power law only above its knee (`jscratch.shading.display`), and a
    distant light puts most pixels below it at intensity 1, so ``u`` is found by bisection (the
    mean display value grows with ``u``), from the power law's ``u`` as the first guess."""
    rad = np.maximum(np.asarray(radiance, np.float64), 0.0)  # (float32 rounding below 0)
    t = np.asarray(target_mean, np.float64)
    scale = np.max(rad, axis=(1, 2))  # the brightest pixel at intensity 1 / scale is 1
    if not (np.all(np.isfinite(rad)) and np.all(scale > 0)):
        j = int(np.argmax(~np.isfinite(scale) | (scale <= 0)))
        raise DesignError(f"view {j} renders black or non-finite at intensity 1: cannot set "
                          "its light")
    rad = rad / scale[:, None, None]

    def mean_disp(u):
        return np.asarray(display(np.exp(u)[:, None, None] * rad), np.float64).mean(axis=(1, 2))

    guess = DISPLAY_GAMMA * (np.log(t) - np.log(np.maximum(mean_disp(np.zeros_like(t)), 1e-300)))
    lo, hi = guess - 1.0, guess + 1.0
    for _ in range(60):  # widen until the root is bracketed: e**(+-60) is far beyond any image
        low, high = mean_disp(lo) > t, mean_disp(hi) < t
        if not (low.any() or high.any()):
            break
        lo, hi = np.where(low, lo - 2.0, lo), np.where(high, hi + 2.0, hi)
    if np.any(mean_disp(lo) > t) or np.any(mean_disp(hi) < t):
        raise DesignError("the initial light intensities could not be matched to the targets' "
                          "means (the render's mean display value does not reach them)")
    for _ in range(50):  # the bracket's width / 2**50: far below float32's resolution of u
        mid = 0.5 * (lo + hi)
        below = mean_disp(mid) < t
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi) - np.log(scale)


class Compiling:
    """The compilations `initial_state` started (`_compile_meanwhile` threads, the step's first):
    ``join()`` waits for them all; ``seconds`` is the step's compilation wall time."""

    def __init__(self, threads: list[threading.Thread]):
        self.threads = threads

    def join(self) -> None:
        for thread in self.threads:
            thread.join()

    @property
    def seconds(self) -> float | None:
        return self.threads[0].seconds

    @property
    def step(self):
        """The compiled step (None if its compilation failed: the first step raises it)."""
        return self.threads[0].result


#: Turns `check_step_memory` off when ``0`` (read at each design).
MEMORY_CHECK_ENV = "JSCRATCH_MEMORY_CHECK"


def check_step_memory(compiled, mesh=None) -> None:
    """Refuse, before the first step, a run whose step needs more memory than is free.

    The need is the compiled step's temporary and output buffers (XLA's ``memory_analysis``;
    its arguments are already held), on every device of the run; on the CPU their sum over
    every process on this machine (`mesh.per_host_total`) is compared with `free_memory` (the
    host's), on an accelerator each device's with its own free
    memory (``memory_stats``; skipped where a backend has none). At 1024 px and 320,000
    scratches the step needs 6.4 GB, 77 % of the process's peak of 8.4 GB (docs/usage.md). Raises
    `DesignError` naming both sizes; ``JSCRATCH_MEMORY_CHECK=0`` turns the check off."""
    need = step_memory(compiled) if compiled is not None and memory_check_on() else None
    devices = ([d for d in mesh.devices.flat if d.process_index == jax.process_index()]
               if mesh is not None else [jax.devices()[0]])
    if devices[0].platform == "cpu":
        # every process runs this (a collective); one that does not check adds nothing
        total, count = mesh_mod.per_host_total(0 if need is None else need * len(devices))
        where = "this machine" if count == 1 else f"this machine (running {count} processes)"
        hosts = [] if need is None else [(total, free_memory(), where)]
    else:
        hosts = [] if need is None else [(need, _device_free(d), str(d)) for d in devices]
    for need_here, free, where in hosts:
        if free is not None and need_here > free:
            raise DesignError(
                f"the design step needs about {_size(need_here)} of memory and {where} has "
                f"{_size(free)} free: ask for fewer scratches, fewer views or a smaller --size "
                f"({MEMORY_CHECK_ENV}=0 runs it anyway)")


#: Bytes of host memory a design holds per scratch before its step, at the least (float32; the
#: scratches, their optimiser state, the pair list at the smallest size): 370-380 bytes measured
#: at 16 px with 3,000,000 scratches and one or three views, a whole run's peak 950-980 bytes.
SETUP_BYTES_PER_SCRATCH = 300


def check_scratch_memory(config, mesh=None) -> None:
    """Refuse, before anything is allocated, a run whose scratches alone cannot fit in the host's
    free memory (``n_scratches * SETUP_BYTES_PER_SCRATCH``, twice that in float64): such a run
    would be killed by the system while it sets up, before `check_step_memory` can weigh its
    step. CPU runs only (elsewhere the arrays live on the devices); ``JSCRATCH_MEMORY_CHECK=0``
    turns it off. Raises `DesignError` naming both sizes."""
    devices = mesh.devices.flat if mesh is not None else jax.devices()[:1]
    if not memory_check_on() or next(iter(devices)).platform != "cpu":
        return
    itemsize = jnp.dtype(config.dtype).itemsize
    need = int(config.n_scratches) * SETUP_BYTES_PER_SCRATCH * itemsize // 4
    free = free_memory()
    if free is not None and need > free:
        raise DesignError(
            f"{config.n_scratches:,} scratches need at least {_size(need)} of memory before the "
            f"first step and this machine has {_size(free)} free: ask for fewer scratches "
            f"({MEMORY_CHECK_ENV}=0 runs it anyway)")


def memory_check_on() -> bool:
    """Whether `check_step_memory` checks: ``JSCRATCH_MEMORY_CHECK`` ``1`` (or unset) or ``0``;
    another value is refused (`DesignError`)."""
    raw = os.environ.get(MEMORY_CHECK_ENV, "").strip() or "1"
    if raw not in ("0", "1"):
        raise DesignError(f"{MEMORY_CHECK_ENV}={raw!r}: expected 0 (no memory check) or 1 (check "
                          "the step's memory before the first step, the default)")
    return raw == "1"


def _size(n: int) -> str:
    return f"{n / 1e9:.1f} GB" if n >= 1e9 else f"{n / 1e6:.0f} MB"


def step_memory(compiled) -> int | None:
    """Bytes a compiled step allocates on one device beyond its arguments: XLA's temporary and
    output buffers (``memory_analysis``), less those aliased to arguments; None where the
    backend gives no analysis."""
    inner = getattr(compiled, "compiled", compiled)  # equinox's wrapper holds jax's executable
    try:
        ma = inner.memory_analysis()
        return (int(ma.temp_size_in_bytes) + int(ma.output_size_in_bytes)
                - int(ma.alias_size_in_bytes))
    except Exception:
        return None


def free_memory(meminfo: str = "/proc/meminfo", cgroup: str = "/proc/self/cgroup",
                root: str = "/sys/fs/cgroup") -> int | None:
    """Bytes this process can still allocate on the host: ``MemAvailable`` + ``SwapFree`` of
    `meminfo`, or less where this process's memory control group (`cgroup`, v2 or v1 under
    `root`) has a limit that leaves less (the limit less the usage, page cache not counted as
    used); None where neither is readable."""
    free = None
    try:
        with open(meminfo) as f:
            info = {k: int(v.split()[0]) * 1024 for k, v in
                    (line.split(":", 1) for line in f if ":" in line)}
        free = info["MemAvailable"] + info.get("SwapFree", 0)
    except (OSError, KeyError, ValueError):
        pass
    limit = _cgroup_free(cgroup, root)
    if limit is not None:
        free = limit if free is None else min(free, limit)
    return free


def _cgroup_free(cgroup: str, root: str) -> int | None:
    """The least that this process's memory control group and its parents leave free (each
    group's limit less its usage, page cache not counted), cgroup v2 or v1; None without a
    limit, or where the files cannot be read."""
    try:
        with open(cgroup) as f:
            groups = [line.strip().split(":", 2) for line in f if line.count(":") >= 2]
    except (OSError, UnicodeDecodeError):
        return None
    free = None
    for hid, ctrl, path in groups:
        if hid == "0" and ctrl == "":
            mount, files = root, ("memory.max", "memory.current", "file")
        elif "memory" in ctrl.split(","):
            mount = root + "/memory"
            files = ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_cache")
        else:
            continue
        # the group's folder and its parents; a container may mount its own group as the root
        path = path.rstrip("/")
        if not os.path.isdir(mount + path):
            path = ""
        while True:
            here = _group_free(mount + path, files)
            if here is not None:
                free = here if free is None else min(free, here)
            if not path:
                break
            path = path.rsplit("/", 1)[0]
    return free


def _group_free(base: str, files: tuple[str, str, str]) -> int | None:
    """One group's limit less its usage without page cache; None without a limit."""
    try:
        with open(os.path.join(base, files[0])) as f:
            raw = f.read().strip()
        if raw == "max" or int(raw) >= 2 ** 60:
            return None
        with open(os.path.join(base, files[1])) as f:
            used = int(f.read().strip())
        with open(os.path.join(base, "memory.stat")) as f:
            stat = dict(line.split()[:2] for line in f if len(line.split()) >= 2)
        return int(raw) - used + int(stat.get(files[2], 0))
    except (OSError, ValueError, UnicodeDecodeError):
        return None


def _device_free(device) -> int | None:
    """An accelerator's free memory (``memory_stats``); None where the backend gives none."""
    try:
        stats = device.memory_stats() or {}
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    except Exception:
        return None


def _scores_needed(ctx, config) -> bool:
    """Whether a fresh run calls `discard.scores`: a prune round (`prune.due` at iteration
    ``prune_every`` with scratches to move) or a final discard. Single device only: on a mesh
    the placement of the later call is not known here."""
    every = config.prune_every
    rounds = every < config.iterations and prune_mod.moves_at(every, config.n_scratches,
                                                               ctx.board.n_pixels, config)
    ends = config.discard or config.target_ssim is not None
    return ctx.mesh is None and (rounds or ends)


def _compile_meanwhile(name: str, compile_fn) -> threading.Thread:
    """Run ``compile_fn`` (a lowering and compilation for the run's shapes, which warms the jit
    cache) on its own thread, so that it overlaps the setup's render and the other compilations
    (XLA compiles without holding the GIL). Only shapes matter, so the intensities set meanwhile
    do not. A failure here is left to the first real call to report. The thread's ``seconds``
    is its wall time, its ``result`` what ``compile_fn`` returned."""
    compile_fn = _in_this_context(compile_fn)

    def work():
        t0 = time.perf_counter()
        try:
            thread.result = compile_fn()
        except Exception:  # the first real call compiles again and raises it properly
            pass
        thread.seconds = time.perf_counter() - t0

    thread = threading.Thread(target=work, name=f"jscratch-compile-{name}", daemon=True)
    thread.seconds = thread.result = None
    thread.start()
    return thread


def _save(checkpoint, state, config, inputs):
    """`save_checkpoint`, on process 0 only (every process holds the same replicated state)."""
    if mesh_mod.is_writer():
        save_checkpoint(checkpoint, state, config, inputs)


def _check_health(health, state, config, checkpoint, inputs):
    """Raise `NonFiniteError` (after saving ``state``, the last good one) when a check failed."""
    for what, (ok, idx) in health.items():
        if not bool(ok):
            if checkpoint is not None:
                _save(checkpoint, state, config, inputs)
            unit = "view" if what.endswith("intensity") else "scratch"
            where = "" if what == "loss" else f" (first bad {unit}: {int(idx)})"
            saved = f"; the last good state is in {checkpoint!r}" if checkpoint else ""
            raise NonFiniteError(
                f"non-finite or out-of-range {what} at iteration {state.iteration}{where}: "
                f"the optimisation stopped{saved}. Lower the learning rate of that group "
                "or freeze it.")


class _Phase:
    """With `progress`: one status line (tqdm, elapsed seconds) for what the run does before its
    first step, saying when the native kernel is being built (a first run); cleared when the
    progress bar of the steps starts."""

    def __init__(self, progress: bool, dtype: str):
        self.dtype = dtype
        self.bar = None
        if progress:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=None, desc="design: starting", bar_format="{desc} ({elapsed})",
                            leave=False, dynamic_ncols=True)

    def show(self, what: str) -> None:
        if self.bar is not None:
            build = "; building the native kernel (first run only)" if native.building(
                self.dtype) else ""
            self.bar.set_description_str(f"design: {what}{build}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _iterate(state, optimizer, ctx, config, n_iter, checkpoint, inputs, progress):
    """Run `step` until ``n_iter``: capacity retries, health checks, history, rebinning,
    progress bar and checkpoints. Returns the final state, the per-step wall times and the loop's
    parts: wall time (s) in the steps (``steps``), the prune rounds (``prune``), host rebuilds
    after an overflow (``rebuild_overflow``) and checkpoints (``checkpoint``), and the pair-views
    the steps evaluated (``pair_views``)."""
    step_times: list[float] = []
    parts = {"steps": 0.0, "prune": 0.0, "rebuild_overflow": 0.0, "checkpoint": 0.0,
             "pair_views": 0}
    m = ctx.hs.shape[0]
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.iterations, initial=state.iteration, desc="design", unit="it",
                   dynamic_ncols=True)
    try:
        while state.iteration < n_iter:
            t0 = time.perf_counter()
            if prune_mod.moves_at(state.iteration, config.n_scratches, ctx.board.n_pixels,
                                  config) and not any(
                    r[0] == state.iteration for r in state.history.get("prune", [])):
                state = _prune(state, ctx, config)
                parts["prune"] += time.perf_counter() - t0
            t1 = time.perf_counter()
            new, opt_state, terms, new_lists, rebinned, counts, health = step(
                state.params, state.opt_state, state.lists, ctx, optimizer)
            counts = np.asarray(counts)
            parts["steps"] += time.perf_counter() - t1
            if state.lists.culled and np.any(counts > np.asarray(state.lists.caps)):
                state = dataclasses.replace(state, lists=bvh.grow_lists(state.lists, counts))
                continue  # retry the same iteration with larger per-view lists
            _check_health(health, state, config, checkpoint, inputs)
            hist = state.history
            hist["total"].append(float(terms["total"]))
            for k, v in terms.items():
                if k != "total":
                    hist["terms"].setdefault(k, []).append(float(v))
            parts["pair_views"] += int(counts[:m].sum())
            rebins = state.rebins + int(rebinned)
            if new_lists is None:  # on a mesh: rebuilt (and laid out per shard) by the host
                new_lists = rebin(state.lists, new, ctx) if bool(rebinned) else state.lists
            lists = new_lists
            if bool(lists.shared.overflow):  # rebuilt in the step, but the capacities were short
                t1 = time.perf_counter()
                lists = rebin(state.lists, new, ctx)
                parts["rebuild_overflow"] += time.perf_counter() - t1
            state = State(state.iteration + 1, new, opt_state, lists, hist, rebins)
            step_times.append(time.perf_counter() - t0)
            if bar is not None:
                bar.set_postfix(loss=f"{hist['total'][-1]:.5g}")
                bar.update(1)
            if checkpoint is not None and (state.iteration % config.checkpoint_every == 0
                                           or state.iteration == n_iter):
                t1 = time.perf_counter()
                _save(checkpoint, state, config, inputs)
                parts["checkpoint"] += time.perf_counter() - t1
    finally:
        if bar is not None:
            bar.close()
    return state, step_times, parts


def _prune(state, ctx, config):
    """A `prune.prune_reseed` round at ``state.iteration``: new parameters and Adam moments, the
    pair list rebuilt, the capacities re-measured (culled runs), ``history["prune"]`` appended with
    ``[iteration, moved]``."""
    params, opt_state, idx = prune_mod.prune_reseed(state.params, state.opt_state, state.lists,
                                                    ctx, config, state.iteration)
    lists = remeasure(rebin(state.lists, params, ctx), params, ctx)
    hist = state.history
    hist.setdefault("prune", []).append([state.iteration, int(len(idx))])
    return State(state.iteration, params, opt_state, lists, hist, state.rebins + 1)


def _finish(state, ctx, tnp, config, *, discard_now: bool) -> DesignResult:
    """Final render, discard (when ``discard_now``) and metrics (timings of the loop are the
    caller's)."""
    m = tnp.shape[0]
    params, lists = state.params, state.lists
    all_keep = jnp.ones((config.n_scratches,), bool)
    t_d = time.perf_counter()
    rad, terms, counts = evaluate(params, lists, all_keep, ctx)
    if lists.culled and np.any(np.asarray(counts) > np.asarray(lists.caps)):
        lists = remeasure(lists, params, ctx)
        rad, terms, counts = evaluate(params, lists, all_keep, ctx)
    loss_all = float(terms["total"])
    metrics_all = image_metrics(np.asarray(display(rad)), tnp)
    keep = np.ones(config.n_scratches, bool)
    target = None
    if discard_now and config.target_ssim is not None:
        keep, rad, terms, target = fewest_for_ssim(params, lists, ctx, tnp, config.target_ssim,
                                                   rad, terms)
    elif discard_now:
        keep, rad, terms = discard(params, lists, ctx, loss_all, config.discard_tol, rad, terms)
    t_discard = time.perf_counter() - t_d
    rad = np.asarray(rad)
    disp = np.asarray(display(rad))
    p0, p1, wd, dp, al, inten = (np.asarray(a) for a in physical(params))
    k = keep
    result_scratches = Scratches(p0[k], p1[k], wd[k], dp[k], al[k],
                                 profile="paper" if params.groove is None else params.groove.scratch_profile)
    result_views = Views(np.asarray(ctx.camera), np.asarray(ctx.light), inten)
    mets = image_metrics(disp, tnp)
    mets.update({
        "loss": float(terms["total"]),
        "loss_terms": {k2: float(v) for k2, v in terms.items()},
        "loss_before_discard": loss_all,
        "metrics_before_discard": metrics_all,
        "discarded": int((~keep).sum()),
        "kept": int(keep.sum()),
        "pairs_total": int(np.asarray(lists.shared.valid).sum()),
        "pair_capacity": int(lists.shared.valid.shape[0]),
        "pairs_per_view": [int(c) for c in np.asarray(counts)[:m]],
        "coverage_pairs": (int(np.asarray(counts)[m]) if len(counts) > m
                           else int(np.asarray(lists.shared.valid).sum())),
        "rebins": state.rebins,
        "iterations": state.iteration,
        "time_total": None,
        "time_first_step": None,
        "time_step_median": None,
        "time_discard": t_discard,
        "intensity": [float(x) for x in inten],
        "prune": state.history.get("prune", []),
        "dense": config.is_dense(ctx.board.n_pixels),
        "lambda_g": config.design_loss(ctx.board.n_pixels).lambda_g,  # None: the loss's default
    })
    if target is not None:
        mets["target"] = target
    return DesignResult(result_scratches, result_views, ctx.board, params, keep, rad, disp, tnp,
                        state.history, mets, config)
