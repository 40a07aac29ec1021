"""Tests of the target-quality mode (`discard.fewest_for_ssim`, ``DesignConfig.target_ssim``,
``--target-ssim``): the kept set meets the requested mean SSIM when rendered independently (the
public renderer on the kept scratches alone, SSIM from scikit-image), a higher target never keeps
fewer scratches, dropping a few more in the same order falls below the target, an unreachable
target keeps everything, and the design's result stays consistent.

One tiny configuration (2 views, 32x32 px, 300 scratches), as in test_design_prune.
"""


import jax.numpy as jnp
import numpy as np
import pytest
from skimage.filters import gaussian
from skimage.metrics import structural_similarity

from jscratch import render
from jscratch.design import DesignConfig, DesignError, design, discard, solver
from jscratch.design.run import initial_state, rebin, setup
from jscratch.shading import display

N = 300


def _mean_ssim_reference(disp, targets):
    """The mean SSIM of docs/model.md §7 written out with scikit-image (not `jscratch.metrics`)."""
    out = []
    for d, t in zip(np.clip(np.asarray(disp, np.float64), 0, 1), np.asarray(targets, np.float64)):
        g = lambda x: gaussian(x, sigma=1.0, mode="nearest", preserve_range=True)  # noqa: E731
        out.append(structural_similarity(g(d), g(t), data_range=1.0))
    return float(np.mean(out))


def _render_kept(params, keep, views, board):
    """Display images of the kept scratches alone, through the public renderer."""
    p0, p1, w, d, a, inten = (np.asarray(x) for x in solver.physical(params))
    k = np.asarray(keep)
    s = render.Scratches(p0[k], p1[k], w[k], d[k], a[k], profile=params.scratches().profile)
    v = render.Views(np.asarray(views.camera), np.asarray(views.light), inten)
    return np.asarray(display(render.render(s, v, board)))


@pytest.fixture(scope="module")
def optimised(two_view_scene):
    targets, views, board = two_view_scene
    cfg = DesignConfig(n_scratches=N, iterations=8, cull_eps=0.0, groove="carvable")
    params, opt, ctx = setup(targets, views, board, cfg)
    st, warm = initial_state(params, opt, ctx, targets, cfg)
    warm.join()
    p, o, lists = st.params, st.opt_state, st.lists
    for _ in range(cfg.iterations):
        p_old, lists_old = p, lists
        p, o, _, lists, *_ = solver.step(p, o, lists, ctx, opt)
        if bool(lists.shared.overflow):
            lists = rebin(lists_old, p, ctx)
    rad, terms, _ = solver.evaluate(p, lists, jnp.ones((N,), bool), ctx)
    return targets, views, board, p, lists, ctx, rad, terms


def test_kept_set_meets_target_and_is_nearly_minimal(optimised):
    targets, views, board, p, lists, ctx, rad, terms = optimised
    full = _mean_ssim_reference(display(rad), targets)
    kept = []
    for frac in (0.6, 0.8, 0.95):
        s = frac * full
        keep, rad_k, _, rep = discard.fewest_for_ssim(p, lists, ctx, targets, s, rad, terms)
        n_kept = int(keep.sum())
        assert rep["reached"] and rep["ssim"] == s
        assert 0 < n_kept < N  # below the full design's SSIM, something can go
        # independent: the kept scratches alone, public renderer, scikit-image SSIM
        ref = _mean_ssim_reference(_render_kept(p, keep, views, board), targets)
        assert ref >= s - 1e-4
        assert rep["mean_ssim"] == pytest.approx(ref, abs=1e-4)
        # nearly minimal: the search measured a set at most `resolution` smaller below the target
        res = max(1, N // 1024)
        assert any(k < n_kept and k >= n_kept - res and m < s for k, m in rep["search"])
        # the kept set is the complement of the lowest scores' prefix
        sc = discard.scores(p, lists, ctx)
        assert sc[~keep].max(initial=-np.inf) <= sc[keep].min()
        kept.append(n_kept)
    assert kept == sorted(kept) and kept[0] < kept[-1]  # monotone in the target


def test_unreachable_target_keeps_everything(optimised):
    targets, views, board, p, lists, ctx, rad, terms = optimised
    full = _mean_ssim_reference(display(rad), targets)
    keep, _, _, rep = discard.fewest_for_ssim(p, lists, ctx, targets, min(1.0, full + 0.05),
                                              rad, terms)
    assert keep.all() and not rep["reached"]
    assert rep["mean_ssim"] == pytest.approx(full, abs=1e-6)


def test_design_with_target_ssim_is_consistent(two_view_scene):
    targets, views, board = two_view_scene
    base = dict(n_scratches=N, iterations=3, cull_eps=0.0)
    full = design(targets, views, board, DesignConfig(**base, discard=False))
    s = 0.9 * float(np.mean(full.metrics["ssim"]))
    res = design(targets, views, board, DesignConfig(**base, target_ssim=s))
    m = res.metrics
    assert m["target"]["reached"] and m["kept"] == int(res.keep.sum()) == res.scratches.p0.shape[0]
    assert m["kept"] + m["discarded"] == N and m["kept"] < N
    assert np.mean(m["ssim"]) >= s
    assert m["target"]["mean_ssim"] == pytest.approx(np.mean(m["ssim"]), abs=1e-9)
    assert res.params.log_width.shape == (N,)  # the parameter tree keeps every scratch
    # same optimisation as without the target: only the selection differs
    np.testing.assert_array_equal(np.asarray(res.params.geom), np.asarray(full.params.geom))


def test_target_ssim_errors():
    for bad in (0.0, 1.5, float("nan"), -0.2):
        with pytest.raises(DesignError, match="target_ssim"):
            DesignConfig(target_ssim=bad)
