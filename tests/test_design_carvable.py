"""Tests of jscratch.design.carvable: the groove map is the least-squares optimum of an independent
scipy quadrature of the misfit between the paper's profile and the ball's arc, its bounds hold for
any parameter, and the real jitted design step never leaves them, however large the step."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy import integrate

from jscratch import render
from jscratch.design import DesignConfig
from jscratch.design.carvable import groove_map
from jscratch.designfile import groove_half_width

SIZE = 16
_MINE = dict(name="mine", cutter_radius_mm=0.2, plunge_min_mm=0.01, plunge_max_mm=0.08, feed_mm_min=600.0,
             overhead_s=0.5)


def _fit_error_reference(w, p, R_, criterion):
    """Mean squared misfit over the cut (scipy quadrature, float64) of the paper profile of width
    `w` and half width `a` (its depth from x_max = a) against the ball's arc at plunge `p`:
    wall angles (rad^2) or heights (m^2)."""
    a = math.sqrt(2 * R_ * p - p * p)
    d = -0.5 * w * math.log1p(-((2 * a / w) ** 2))
    if criterion == "slope":
        f = lambda x: (2 * math.atan(2 * x / w) - math.asin(x / R_)) ** 2  # noqa: E731
    else:
        f = lambda x: (-0.5 * w * math.log1p(-((2 * x / w) ** 2)) - d  # noqa: E731
                       - (R_ - p - math.sqrt(R_ * R_ - x * x))) ** 2
    return integrate.quad(f, 0, a, limit=200)[0] / a



@pytest.mark.float64
@pytest.mark.parametrize("criterion", ["height", "slope"])
def test_groove_map_is_the_least_squares_optimum(criterion):
    R_, lo, hi = 1.25e-4, 5e-6, 1e-4
    g = groove_map(R_, lo, hi, criterion)
    for p in (5e-6, 3e-5, 7e-5, 1e-4):
        w, d = (float(v) for v in g.profile_of_plunge(jnp.float64(p)))
        a = math.sqrt(2 * R_ * p - p * p)
        assert groove_half_width(w, d) == pytest.approx(a, rel=1e-6)
        best = _fit_error_reference(w, p, R_, criterion)
        # The fitted w is the optimum of an independent float64 quadrature of the same misfit.
        for f in (0.97, 1.03):
            if f * w > 2 * a:
                assert _fit_error_reference(f * w, p, R_, criterion) >= best * (1 - 1e-3)
        if criterion == "slope":
            assert math.degrees(math.sqrt(best)) <= g.rms_deg + 0.05



@settings(max_examples=25, deadline=None)
@given(r=st.floats(0.05, 1.0), lo=st.floats(0.01, 0.4), hi=st.floats(0.45, 0.95),
       z=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=16))
def test_carvable_bounds_for_any_parameter(r, lo, hi, z):
    R_ = r * 1e-3
    g = groove_map(R_, lo * R_, hi * R_)  # the default criterion
    z = jnp.asarray(z, jnp.float32)
    p = np.asarray(g.plunge(z), np.float64)
    w, d = (np.asarray(v, np.float64) for v in g.profile(z))
    assert np.all((p >= lo * R_ * (1 - 1e-6)) & (p <= hi * R_ * (1 + 1e-6)))
    assert np.all(np.isfinite(w) & np.isfinite(d) & (w > 0) & (d > 0))
    np.testing.assert_allclose(groove_half_width(w, d), np.sqrt(2 * R_ * p - p * p), rtol=2e-3)



_OPT = {}



def _tiny_optimisation():
    """A tiny carvable design problem, built once (the jitted step compiles once)."""
    if not _OPT:
        from jscratch.design.io import default_targets
        from jscratch.design.run import pair_lists, setup

        board = render.Board(shape=(SIZE, SIZE))
        views = render.views_on_circle(2, math.radians(50), board=board)
        targets, _ = default_targets(2, (SIZE, SIZE))
        # The round trip's scene and machine, so that the jitted step is compiled once for both.
        cfg = DesignConfig(n_scratches=150, iterations=1, groove="carvable", machine=_MINE)
        params, opt, ctx = setup(targets, views, board, cfg)
        pairs = pair_lists(params, ctx, cfg)  # unculled: the shared list serves every view
        _OPT.update(params=params, pairs=pairs, opt=opt, ctx=ctx)
    return _OPT["params"], _OPT["pairs"], _OPT["opt"], _OPT["ctx"]



@settings(max_examples=6, deadline=None)
@given(lr=st.sampled_from([1e-2, 1.0, 1e2, 1e4]), start=st.floats(-30.0, 30.0), seed=st.integers(0, 9))
def test_carvable_bounds_never_violated_during_optimisation(lr, start, seed):
    """Adam steps of the real jitted design step, from plunges anywhere in (and pressed against)
    the range, with learning rates up to absurd: every iterate's plunge stays in the range and
    its groove is the cut's width."""
    import equinox as eqx
    from jscratch.design.params import group_tree
    from jscratch.design.solver import step

    params, pairs, opt, ctx = _tiny_optimisation()
    z0 = params.log_width
    z = z0 + start + np.random.default_rng(seed).normal(0.0, 3.0, z0.shape).astype(np.float32)
    p_ = eqx.tree_at(lambda q: q.log_width, params, jnp.asarray(z, z0.dtype))
    lrs = group_tree(p_, {g: jnp.asarray(lr if g == "width" else 1e-3, jnp.float32)
                          for g in ("endpoints", "width", "depth", "alpha", "intensity")})
    ctx = eqx.tree_at(lambda c: c.lrs, ctx, lrs)
    o_ = opt.init(p_)
    moved = 0.0
    for _ in range(3):
        new, o_, terms, *_ = step(p_, o_, pairs, ctx, opt)
        pl = np.asarray(new.plunge(), np.float64)
        s = new.scratches()
        assert np.all((pl >= 1e-5 * (1 - 1e-6)) & (pl <= 8e-5 * (1 + 1e-6)))
        np.testing.assert_allclose(groove_half_width(np.asarray(s.width, np.float64), np.asarray(s.depth, np.float64)),
                                   np.sqrt(2 * 2e-4 * pl - pl**2), rtol=2e-3)
        moved = max(moved, float(np.abs(np.asarray(new.log_width) - np.asarray(p_.log_width)).max()))
        p_ = new
    if abs(start) <= 10:  # the plunges are optimised, not frozen (past ~17 the float32 map is
        assert moved > 0  # saturated against its bound: a zero gradient, which Adam leaves alone)


def test_arc_map_renders_the_ball_itself():
    """`groove_fit = "arc"` (the default): no fit; a plunge maps to ``w = 2R``,
    ``d = -2R log(1 - p/R)`` (written out here), rendered with the arc profile; the fitted maps
    render the paper's profile."""
    R_, lo, hi = 1.25e-4, 5e-6, 1e-4
    g = groove_map(R_, lo, hi)
    assert g.fit == "arc" and g.scratch_profile == "arc" and g.rms_deg == 0.0 and g.t_grid == ()
    assert groove_map(R_, lo, hi, "height").scratch_profile == "paper"
    p = np.linspace(lo, hi, 7)
    w, d = (np.asarray(v, np.float64) for v in g.profile_of_plunge(jnp.asarray(p, jnp.float32)))
    np.testing.assert_allclose(w, 2 * R_, rtol=1e-7)
    np.testing.assert_allclose(d, -2 * R_ * np.log1p(-p / R_), rtol=1e-5)
    np.testing.assert_allclose(g.plunge_of_profile(w, d), p, rtol=1e-4)
    assert DesignConfig().machine_profile().groove_fit == "arc"
