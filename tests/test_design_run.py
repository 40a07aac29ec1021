"""Tests of jscratch.design.run without an optimisation step: `design`'s input refusals (one line,
naming what is wrong; float64 without x64 in the default float32 setting), and `setup` /
`pair_lists` / `rebin`: the initial scratches are `Scratches.random` of the config's seed, the
intensities the views', and the pair lists hold exactly the pairs `bvh.build_pairs` finds for
the scratches before and after they move."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import bvh, grid, native
from jscratch.design import DesignConfig, design
from jscratch.design import run as run_mod
from jscratch.design.run import free_memory, pair_lists, rebin, setup, step_memory
from jscratch.design.solver import compile_step, lower_step
from jscratch.designfile import DesignError
from jscratch.errors import InputError
from jscratch.scene import Board, Scratches, views_on_circle

CFG = DesignConfig(n_scratches=60, iterations=1, seed=3, groove="free")  # widths as initialised


def _inputs():
    board = Board(shape=(16, 16))
    views = views_on_circle(2, math.radians(50), board=board, intensity=jnp.asarray([1.0, 2.0]))
    targets = np.random.default_rng(0).random((2, 16, 16))
    return targets, views, board


def test_the_default_board_has_square_pixels():
    """Without a board, `design` takes the command line's 0.3 m square board for square targets
    and, for others, a board of square pixels whose longer side is 0.3 m (not the square board,
    which would stretch the picture)."""
    from jscratch.design.config import SceneConfig

    rng = np.random.default_rng(0)
    for h, w in ((24, 24), (32, 16), (16, 40)):
        _, _, board = run_mod.check_inputs(rng.random((2, h, w)), None, None, CFG)
        assert board.shape == (h, w)
        assert board.Sx / w == pytest.approx(board.Sy / h, rel=1e-12)
        assert max(board.Sx, board.Sy) == SceneConfig().board
    _, _, square = run_mod.check_inputs(rng.random((2, 24, 24)), None, None, CFG)
    assert (square.Sx, square.Sy) == (SceneConfig().board,) * 2


def test_design_refuses_bad_inputs(tmp_path):
    targets, views, board = _inputs()
    with pytest.raises(DesignError, match="config must be a DesignConfig, got dict"):
        design(targets, views, board, {"n_scratches": 5})
    with pytest.raises(DesignError, match="views must be a jscratch.Views, got tuple"):
        design(targets, (views.camera, views.light), board, CFG)
    with pytest.raises(DesignError, match=r"targets are 16x16 px but the board's image shape is \(8, 8\)"):
        design(targets, views, Board(shape=(8, 8)), CFG)
    with pytest.raises(DesignError, match="got 1 target images for 2 views"):
        design(targets[:1], views, board, CFG)
    with pytest.raises(DesignError, match="resume=True needs a checkpoint path"):
        design(targets, views, board, CFG, resume=True)
    for name, bad in (("resume", "no"), ("progress", 1)):  # ("no" is true: it resumed)
        with pytest.raises(DesignError, match=rf"^design: `{name}` must be True or False, got "
                                              rf"{bad!r}$"):
            design(targets, views, board, CFG, checkpoint=str(tmp_path / "c.npz"), **{name: bad})
    # the default float32 setting: a float64 design is refused, saying how to enable it
    assert not jax.config.jax_enable_x64
    with pytest.raises(DesignError, match="dtype float64 needs jax_enable_x64"):
        design(targets, views, board, dataclasses.replace(CFG, dtype="float64"))


def _kept(p):
    v = np.asarray(p.valid)
    return sorted(zip(np.asarray(p.pixel)[v].tolist(), np.asarray(p.scratch)[v].tolist()))


def test_setup_pair_lists_and_rebin():
    targets, views, board = _inputs()
    params, optimizer, ctx = setup(targets, views, board, CFG)
    s = params.scratches()
    ref = Scratches.random(jax.random.PRNGKey(3), 60, board, length=CFG.init_length,
                           width=CFG.init_width, depth=CFG.init_depth, alpha=CFG.init_alpha,
                           dtype=jnp.float32)
    assert s.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(s.p0), np.asarray(ref.p0), atol=3e-6)
    np.testing.assert_allclose(np.asarray(s.width), CFG.init_width, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(params.intensity()), [1.0, 2.0], rtol=1e-6)
    assert ctx.hs.shape == (2, 256, 3) and ctx.board is board
    lists = pair_lists(params, ctx, CFG)
    full, _ = bvh.build_pairs(s.p0, s.p1, s.width, s.depth, board=(0.3, 0.3), shape=(16, 16))
    assert _kept(lists.shared) == _kept(full) and len(_kept(full)) > 60
    moved = eqx.tree_at(lambda p: p.geom, params, params.geom + 0.05)
    m = moved.scratches()
    again, _ = bvh.build_pairs(m.p0, m.p1, m.width, m.depth, board=(0.3, 0.3), shape=(16, 16))
    assert _kept(rebin(lists, moved, ctx).shared) == _kept(again) != _kept(full)


def _display64(x, gamma=2.2, knee=1e-4):
    """The display curve of docs/model.md §4 in float64, written out here as the reference."""
    g = 1 / gamma
    P = knee ** (g - 1)
    return np.where(x < knee, (2 - g) * P * x + (g - 1) * (P / knee) * x * x,
                    np.maximum(x, knee) ** g)


def test_matching_intensities_meet_the_target_means_also_below_the_knee():
    """The initial light of each view makes the mean display value equal the target's mean
    (checked in float64 with the display curve written out), whether the render at intensity 1
    lies above the display's knee or far below it (a distant light); a render 1e7x darker needs
    exactly 1e7x the light; and moving a far light and cameras 10x further away needs 100x the
    light (the render falls as 1/r^2), which the power law's closed form misses there."""
    from jscratch.design.run import matching_log_intensity
    from jscratch.render import render
    from jscratch.shading import DISPLAY_GAMMA

    rng = np.random.default_rng(5)
    rad = rng.lognormal(-6.0, 2.5, (3, 24, 24))  # spans the knee (1e-4) by decades either way
    rad[1] *= 1e-9  # a view far below it
    rad[2, :, :12] = 0.0  # half of a view unlit
    t = np.array([0.3, 0.05, 0.6])
    u = matching_log_intensity(rad, t)
    np.testing.assert_allclose(_display64(np.exp(u)[:, None, None] * rad).mean((1, 2)), t,
                               rtol=2e-5)
    np.testing.assert_allclose(matching_log_intensity(rad * 1e-7, t) - u, math.log(1e7), atol=1e-5)
    # A pixel a float32 rounding below 0 counts as dark; a non-finite render is refused.
    neg, zero = rad.copy(), rad.copy()
    neg[0, 0, 0], zero[0, 0, 0] = -1e-9, 0.0
    np.testing.assert_allclose(matching_log_intensity(neg, t), matching_log_intensity(zero, t),
                               atol=1e-9)
    bad = rad.copy()
    bad[1, 3, 3] = np.nan
    with pytest.raises(DesignError, match="view 1 renders black or non-finite"):
        matching_log_intensity(bad, t)

    # Far from the board the render at intensity 1 falls as 1/r^2 (its directions converge).
    targets, views, board = _inputs()
    s = Scratches.random(jax.random.PRNGKey(1), 200, board, length=(0.01, 0.04), width=2.5e-4,
                         depth=1.28e-4, alpha=0.04)
    tmean = targets.mean(axis=(1, 2))
    u, closed = {}, {}
    for d in (1e3, 1e4):
        r = np.asarray(render(s, views_on_circle(2, math.radians(50), distance=d, board=board),
                              board), np.float64)
        u[d] = matching_log_intensity(r, tmean)
        closed[d] = DISPLAY_GAMMA * (np.log(tmean) - np.log(_display64(r).mean((1, 2))))
    np.testing.assert_allclose(u[1e4] - u[1e3], 2 * math.log(10.0), atol=1e-4)
    assert np.all(np.abs(closed[1e4] - closed[1e3] - 2 * math.log(10.0)) > 1.0)


def test_free_memory_reads_meminfo_and_a_control_groups_limit(tmp_path):
    """`free_memory`: ``MemAvailable + SwapFree``, or a cgroup's (v2 or v1) limit less its usage
    without page cache where that is less; no limit ("max", v1's huge number) leaves meminfo."""
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:  16000000 kB\nMemAvailable:    8000000 kB\n"
                       "SwapFree:  1000000 kB\n")
    sys_fs, cgroup = tmp_path / "sys", tmp_path / "cgroup"
    host = 9_000_000 * 1024
    assert free_memory(str(meminfo), str(tmp_path / "none"), str(sys_fs)) == host
    cgroup.write_text("\n0::/job\n")  # (a blank line is skipped)
    v2 = sys_fs / "job"
    v2.mkdir(parents=True)
    (v2 / "memory.current").write_text("3000000000\n")
    (v2 / "memory.stat").write_text("anon 2000000000\nfile 1000000000\n")
    (v2 / "memory.max").write_text("4000000000\n")
    assert free_memory(str(meminfo), str(cgroup), str(sys_fs)) == 2_000_000_000
    (v2 / "memory.max").write_text("max\n")
    assert free_memory(str(meminfo), str(cgroup), str(sys_fs)) == host
    # a limit on a parent group (a job's, over its steps' groups) holds for the process too
    (v2 / "memory.max").write_text("4000000000\n")
    task = v2 / "step" / "task_0"
    task.mkdir(parents=True)
    (task / "memory.max").write_text("max\n")
    cgroup.write_text("0::/job/step/task_0\n")
    assert free_memory(str(meminfo), str(cgroup), str(sys_fs)) == 2_000_000_000
    (task / "memory.max").write_text("not a number\n")  # unreadable: that group is skipped
    assert free_memory(str(meminfo), str(cgroup), str(sys_fs)) == 2_000_000_000
    (v2 / "memory.max").write_text("max\n")
    cgroup.write_text("5:cpu,cpuacct:/\n4:memory:/job\n")
    v1 = sys_fs / "memory" / "job"
    v1.mkdir(parents=True)
    (v1 / "memory.usage_in_bytes").write_text("4500000000\n")
    (v1 / "memory.stat").write_text("cache 400000000\ntotal_cache 500000000\n")
    (v1 / "memory.limit_in_bytes").write_text("5000000000\n")
    assert free_memory(str(meminfo), str(cgroup), str(sys_fs)) == 1_000_000_000
    assert free_memory(str(tmp_path / "none"), str(cgroup), str(sys_fs)) == 1_000_000_000
    cgroup.write_text("4:memory:/docker/abc\n")  # a container that mounts its own group
    for name in ("memory.usage_in_bytes", "memory.stat", "memory.limit_in_bytes"):
        (sys_fs / "memory" / name).write_bytes((v1 / name).read_bytes())
    assert free_memory(str(meminfo), str(cgroup), str(sys_fs)) == 1_000_000_000
    (sys_fs / "memory" / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    cgroup.write_text("4:memory:/job\n")
    (v1 / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    assert free_memory(str(meminfo), str(cgroup), str(sys_fs)) == host
    assert free_memory(str(tmp_path / "none"), str(cgroup), str(sys_fs)) is None


def test_a_step_larger_than_the_free_memory_is_refused_before_it_runs(tmp_path, monkeypatch):
    """With less memory free than the compiled step needs, `design` refuses in one line before
    its first step (no checkpoint written); ``JSCRATCH_MEMORY_CHECK=0`` runs it anyway."""
    targets, views, board = _inputs()
    monkeypatch.setattr(run_mod, "free_memory", lambda: 100_000)  # (the scratches fit)
    checkpoint = tmp_path / "ck.npz"
    with pytest.raises(DesignError, match=r"^the design step needs about \d+ MB of memory "
                       r"and this machine has 0 MB free: .*JSCRATCH_MEMORY_CHECK=0 runs it"):
        design(targets, views, board, CFG, checkpoint=checkpoint)
    assert not checkpoint.exists()
    monkeypatch.setenv("JSCRATCH_MEMORY_CHECK", "no")
    with pytest.raises(DesignError, match=r"^JSCRATCH_MEMORY_CHECK='no': expected 0 .* or 1"):
        design(targets, views, board, CFG)
    monkeypatch.setenv("JSCRATCH_MEMORY_CHECK", "0")
    metrics = design(targets, views, board, CFG).metrics
    assert metrics["iterations"] == 1 and metrics["step_memory_bytes"] > 0


def test_scratches_that_cannot_fit_are_refused_before_anything_is_allocated(monkeypatch):
    """More scratches than ``SETUP_BYTES_PER_SCRATCH`` each leaves room for: refused in one line
    before the setup allocates them (10^8 scratches were killed by the system while setting up,
    before the step's check); ``JSCRATCH_MEMORY_CHECK=0`` goes on to the setup."""
    targets, views, board = _inputs()

    def no_setup(*args, **kwargs):
        raise AssertionError("set up")

    monkeypatch.setattr(run_mod, "setup", no_setup)
    monkeypatch.setattr(run_mod, "free_memory", lambda: 20 * 10**9)
    n = 20 * 10**9 // run_mod.SETUP_BYTES_PER_SCRATCH + 1
    cfg = dataclasses.replace(CFG, n_scratches=n)
    with pytest.raises(DesignError, match=rf"^{n:,} scratches need at least 20.0 GB of memory "
                       r"before the first step and this machine has 20.0 GB free: ask for "
                       r"fewer scratches \(JSCRATCH_MEMORY_CHECK=0 runs it anyway\)$"):
        design(targets, views, board, cfg)
    with pytest.raises(AssertionError, match="set up"):  # one scratch fewer fits
        design(targets, views, board, dataclasses.replace(cfg, n_scratches=n - 1))
    monkeypatch.setenv("JSCRATCH_MEMORY_CHECK", "0")
    with pytest.raises(AssertionError, match="set up"):
        design(targets, views, board, cfg)


@pytest.mark.skipif(not native.available(jnp.float32),
                    reason=f"native kernel unavailable: {native.status()['why']}")
def test_step_memory_holds_every_pairs_jacobians():
    """On one device with the native kernel the step keeps each pair slot's Jacobians,
    ``10 M + 6`` floats (docs/model.md): `step_memory` is at least that, and it grows with the
    pairs by that much."""
    targets, views, board = _inputs()
    needs = []
    for n in (60, 600):
        cfg = dataclasses.replace(CFG, n_scratches=n)
        params, optimizer, ctx = setup(targets, views, board, cfg)
        lists = pair_lists(params, ctx, cfg)
        compiled = compile_step(params, optimizer.init(params), lists, ctx, optimizer)
        slots = lists.shared.valid.shape[0]
        needs.append((step_memory(compiled), slots))
        assert needs[-1][0] >= (10 * 2 + 6) * 4 * slots
    (small, s_small), (big, s_big) = needs
    assert big - small >= (10 * 2 + 6) * 4 * (s_big - s_small) > 0


def _host_callbacks(lowered) -> int:
    """Custom calls into Python (`eqx.error_if`, `jax.pure_callback`, ...) in a lowered program."""
    text = lowered.as_text()
    return text.count("python_cpu_callback") + text.count("xla_python_gpu_callback")


def test_the_step_holds_no_host_callback():
    """The compiled step calls no Python (the binning's runtime checks are left out: the step
    replaces non-finite values first), so JAX's persistent compilation cache can keep it; the
    binning called from outside still checks (a pure callback there), and bins the same."""
    targets, views, board = _inputs()
    params, optimizer, ctx = setup(targets, views, board, CFG)
    lists = pair_lists(params, ctx, CFG)
    assert _host_callbacks(lower_step(params, optimizer.init(params), lists, ctx,
                                      optimizer)) == 0
    s = params.scratches()
    args = (lists.spec, s.p0, s.p1, s.width, s.depth)
    assert _host_callbacks(bvh.update.lower(*args)) > 0
    assert _host_callbacks(bvh.update.lower(*args, checked=False)) == 0
    shared = bvh.update(*args, checked=False)
    for f in ("pixel", "scratch", "valid"):
        np.testing.assert_array_equal(np.asarray(getattr(shared, f)),
                                      np.asarray(getattr(bvh.update(*args), f)))
    rebin = (shared, s.p0, s.p1 + 1e-3, s.width, s.depth)
    assert _host_callbacks(bvh.needs_rebin.lower(*rebin)) > 0
    assert _host_callbacks(bvh.needs_rebin.lower(*rebin, checked=False)) == 0
    assert bool(bvh.needs_rebin(*rebin, checked=False)) == bool(bvh.needs_rebin(*rebin)) is True
    with pytest.raises(Exception, match="p0 has non-finite entries"):
        bvh.update(lists.spec, s.p0.at[0, 0].set(jnp.nan), s.p1, s.width, s.depth)
    # The host drivers check on the host, then bin without runtime checks.
    assert _host_callbacks(grid._setup_counts.lower(s.p0, s.p1, s.width, s.depth,
                                                    (board.Sx, board.Sy), board.shape, 0.0)) == 0
    with pytest.raises(InputError, match=r"^p0 has non-finite entries \(first at index \(0, 0\)"):
        bvh.build_pairs(s.p0.at[0, 0].set(jnp.nan), s.p1, s.width, s.depth,
                        board=(board.Sx, board.Sy), shape=board.shape)


def test_a_resumed_run_is_checked_too(tmp_path, monkeypatch):
    """Resuming compiles the step before its first step and checks its memory: refused with the
    checkpoint left as it was; with the memory there, it runs on and reports the step's size."""
    targets, views, board = _inputs()
    cfg = dataclasses.replace(CFG, iterations=2)
    checkpoint = tmp_path / "ck.npz"
    design(targets, views, board, cfg, checkpoint=checkpoint, stop_after=1)
    saved = checkpoint.read_bytes()
    with monkeypatch.context() as m:
        m.setattr(run_mod, "free_memory", lambda: 100_000)
        with pytest.raises(DesignError, match="^the design step needs about"):
            design(targets, views, board, cfg, checkpoint=checkpoint, resume=True)
    assert checkpoint.read_bytes() == saved
    metrics = design(targets, views, board, cfg, checkpoint=checkpoint, resume=True).metrics
    assert metrics["iterations"] == 2 and metrics["step_memory_bytes"] > 0
