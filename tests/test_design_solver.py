"""Tests of the learning-rate schedule (``DesignConfig.lr_schedule``, `solver.make_adam`): the
cosine schedule scales Adam's steps by the closed-form cosine factor written out here, the constant
one is plain Adam, and the options reach ``--help`` and the errors."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jscratch.design import DesignConfig, DesignError, solver
from jscratch.design.cli import main


def _cosine(k, steps, final):
    """The factor at update ``k`` (0-based), written out (not optax)."""
    k = min(k, steps)
    return final + (1 - final) * 0.5 * (1 + math.cos(math.pi * k / steps))


def test_cosine_schedule_scales_adam_steps():
    plain = solver.make_adam(0.9, 0.999, 1e-12)
    sched = solver.make_adam(0.9, 0.999, 1e-12, 10, 0.1)
    assert solver.make_adam(0.9, 0.999, 1e-12, 10, 0.1) is sched  # cached
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=5))
    sp, ss = plain.init(x), sched.init(x)
    for k in range(13):
        g = jnp.asarray(rng.normal(size=5))
        up, sp = plain.update(g, sp, x)
        us, ss = sched.update(g, ss, x)
        np.testing.assert_allclose(np.asarray(us), _cosine(k, 10, 0.1) * np.asarray(up),
                                   rtol=1e-5)
    # the last scheduled step is at a tenth of the first's scale
    assert _cosine(10, 10, 0.1) == pytest.approx(0.1)


def test_schedule_config_and_cli(capsys):
    with pytest.raises(DesignError, match="lr_schedule"):
        DesignConfig(lr_schedule="linear")
    with pytest.raises(DesignError, match="lr_final"):
        DesignConfig(lr_final=1.5)
    assert main(["--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for opt in ("--lr-schedule", "--lr-final", "--target-ssim", "--prune-every", "--lambda-x"):
        assert opt in out
    assert "default: constant" in out and "default: 0.1" in out


def _kept(p):
    v = np.asarray(p.valid)
    return sorted(zip(np.asarray(p.pixel)[v].tolist(), np.asarray(p.scratch)[v].tolist()))


@pytest.mark.parametrize("skin", [0.0, 2e-3])
def test_step_rebuilds_the_shared_list_only_when_a_groove_left_its_envelope(skin):
    """The pair list the step returns for the new parameters is the one `bvh.build_pairs` bins
    for them (at the same capacities) whenever `bvh.needs_rebin` says the old one may miss a
    pair, and the old list itself (no binning) otherwise; with a skin most steps keep it."""
    import math

    from jscratch import bvh
    from jscratch.design.run import initial_state, setup
    from jscratch.scene import Board, views_on_circle

    board = Board(shape=(16, 16))
    views = views_on_circle(2, math.radians(50), board=board)
    targets = np.random.default_rng(0).random((2, 16, 16))
    cfg = DesignConfig(n_scratches=60, iterations=6, seed=3, groove="free", skin=skin,
                       lr_endpoints=3e-3)
    params, opt, ctx = setup(targets, views, board, cfg)
    state, warm = initial_state(params, opt, ctx, targets, cfg)
    warm.join()
    p, o, lists = state.params, state.opt_state, state.lists
    flags = []
    for _ in range(cfg.iterations):
        new, o, _, new_lists, rebinned, *_ = solver.step(p, o, lists, ctx, opt)
        s = new.scratches()
        needed = bool(bvh.needs_rebin(lists.shared, s.p0, s.p1, s.width, s.depth))
        assert bool(rebinned) == needed and not bool(new_lists.shared.overflow)
        if needed:
            ref, _ = bvh.build_pairs(s.p0, s.p1, s.width, s.depth, board=(board.Sx, board.Sy),
                                     shape=board.shape, spec=lists.spec)
            assert _kept(new_lists.shared) == _kept(ref)
            np.testing.assert_array_equal(np.asarray(new_lists.shared.bin_p0), np.asarray(s.p0))
        else:
            for f in ("pixel", "scratch", "valid", "bin_p0", "bin_p1"):
                np.testing.assert_array_equal(np.asarray(getattr(new_lists.shared, f)),
                                              np.asarray(getattr(lists.shared, f)))
        flags.append(needed)
        p, lists = new, new_lists
    # without a skin every moving step rebuilds; a skin of ~2 px outlasts several steps
    assert all(flags) if skin == 0 else (0 < flags.count(False))


def test_health_names_the_first_bad_scratch_under_jit():
    """`solver._health` inside jit: every check passes on a good state (a gradient that is a
    constant zero included, as autodiff gives the jnp path for the depth of carvable grooves), and
    a non-finite gradient or value at scratch k reports ``(False, k)``, the first bad one."""
    import jax

    from jscratch.design.params import DesignParams
    from jscratch.scene import Board, Scratches

    board = Board(shape=(16, 16))
    n, rng = 50, np.random.default_rng(1)
    p0 = rng.uniform(0.1, 0.9, (n, 2)) * board.Sx
    p1 = np.clip(p0 + rng.normal(0, 1e-3, (n, 2)), 0, board.Sx)
    s = Scratches(jnp.asarray(p0, jnp.float32), jnp.asarray(p1, jnp.float32),
                  jnp.full((n,), 2e-4, jnp.float32), jnp.full((n,), 1e-4, jnp.float32),
                  jnp.full((n,), 0.05, jnp.float32))
    params = DesignParams.from_physical(s, np.ones(2), board)

    @jax.jit
    def health(grads, new):
        zero_depth = grads.log_depth * 0  # a constant for XLA to fold, as autodiff's zeros are
        grads = DesignParams(grads.geom, grads.log_width, jnp.zeros_like(zero_depth),
                             grads.logit_alpha, grads.log_intensity, grads.parameterisation,
                             grads.board_size, grads.groove)
        return solver._health(jnp.float32(1.0), grads, new)

    good = health(params, params)
    assert all(bool(ok) for ok, _ in good.values())
    bad_grad = DesignParams(params.geom.at[17, 2].set(jnp.nan), *(
        getattr(params, k) for k in ("log_width", "log_depth", "logit_alpha", "log_intensity",
                                     "parameterisation", "board_size", "groove")))
    out = health(bad_grad, params)
    assert not bool(out["gradient of endpoints"][0])
    assert int(out["gradient of endpoints"][1]) == 17
    bad_width = DesignParams(params.geom, params.log_width.at[33].set(jnp.inf).at[40].set(
        jnp.nan), *(getattr(params, k) for k in ("log_depth", "logit_alpha", "log_intensity",
                                                  "parameterisation", "board_size", "groove")))
    out = health(params, bad_width)
    assert not bool(out["updated width"][0]) and int(out["updated width"][1]) == 33
    assert all(bool(ok) for key, (ok, _) in out.items() if key != "updated width")


@pytest.mark.float64
def test_setup_threads_follow_the_callers_float64_context(caplog):
    """`setup` binds the loss, and `initial_state` compiles the step, on other threads; inside a
    `jax.enable_x64` block (thread-local) they still work in float64: the bound loss holds float64
    arrays and the first step compiles nothing more."""
    import jax

    from jscratch.design import default_targets
    from jscratch.design.run import initial_state, setup
    from jscratch.scene import Board, views_on_circle

    board = Board(shape=(16, 16))
    targets, _ = default_targets(2, (16, 16))
    views = views_on_circle(2, math.radians(50), board=board)
    cfg = DesignConfig(n_scratches=50, iterations=2, dtype="float64", groove="free")
    params, opt, ctx = setup(targets, views, board, cfg)
    leaves = [x for x in jax.tree_util.tree_leaves(ctx.loss) if hasattr(x, "dtype")]
    assert leaves and all(x.dtype == jnp.float64 for x in leaves if jnp.issubdtype(
        x.dtype, jnp.floating))
    state, warm = initial_state(params, opt, ctx, targets, cfg)
    warm.join()
    with jax.log_compiles(True), caplog.at_level("WARNING"):
        out = solver.step(state.params, state.opt_state, state.lists, ctx, opt)
    assert out[2]["total"].dtype == jnp.float64
    assert not [r for r in caplog.records if "_step_impl" in r.getMessage()]
