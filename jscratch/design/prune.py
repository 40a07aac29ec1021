"""Prune and re-seed during the optimisation: the scratch budget goes where it helps.

Every ``config.prune_every`` iterations (until ``config.prune_until`` of the run), the
``config.prune_fraction`` of the scratches (at most ``config.prune_per_pixel`` per image pixel,
`moved_count`) that send the least light to any view (the discard's
score: largest over the views of a scratch's contribution relative to the view's mean scratch) are
moved: each is re-seeded where a view is most *too dark* and oriented so that it lights up in that
view. Then the pair list is rebuilt and the per-view capacities re-measured, and the Adam moments of
the moved scratches are zeroed (a new scratch starts with a fresh optimiser state; the step count
is shared). The parameter tree keeps its shapes (``N`` fixed), so jitted steps are reused.

Where: the positive part of the blurred error ``g * (T_j - display(I_j))`` over all views and
pixels, squared, is the sampling density (a scratch can only add light, and covering the board
darkens it by a negligible amount away from the light's mirror direction). A sample ``(j, pixel)``
puts a scratch's midpoint uniformly in that pixel's footprint, its direction perpendicular to the
board-plane part of view ``j``'s half vector there (a groove's normals are perpendicular to its
direction, so it reflects the light into camera ``j`` only when ``h_j . t = 0``) plus a small random
turn, its length uniform in ``config.init_length``, and the initial width, depth and roughness.

Deterministic: the random numbers come from ``(config.seed, iteration)``, and the round runs at the
top of an iteration, after the checkpoint of the previous one, so a resumed run repeats it exactly.
(The last round is at ``prune_until * iterations``: resuming with a larger ``--iterations`` than the
interrupted run had can add rounds that run would not have made, like any schedule.)

Measured (benchmarks/RESULTS.md): 128 px / 5k scratches, ``E_p``: mean SSIM 0.739 ->
0.768 at equal wall time; 256 px / 20k: 0.801 -> 0.813; with carvable grooves and ``E_p + 200 E_g``
0.746 -> 0.758. The moved scratches end up useful, so the final discard keeps more of them
(+9-20 %), which is part of the price. On by default (every 10 iterations) below
``config.dense_from`` scratches per image pixel (0.4); off above it, where rounds were
measured to cost 0.03-0.04 mean SSIM.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jscratch.scene import Scratches
from jscratch.shading import display
from jscratch.design import solver
from jscratch.design.discard import scores
from jscratch.design.params import DesignParams

#: Standard deviation (radians) of the random turn of a re-seeded scratch's direction.
RESEED_TURN = np.radians(5.0)

_SCRATCH_LEAVES = ("geom", "log_width", "log_depth", "logit_alpha")


def due(iteration: int, config) -> bool:
    """Whether a prune/re-seed round runs at the top of ``iteration``."""
    every = config.prune_every
    return (every > 0 and iteration > 0 and iteration % every == 0
            and iteration <= config.prune_until * config.iterations)


def moves_at(iteration: int, n: int, pixels: int, config) -> bool:
    """Whether a round at the top of ``iteration`` moves any of ``n`` scratches (`due` and
    `moved_count` > 0; ``pixels`` per view)."""
    return due(iteration, config) and moved_count(n, pixels, config) > 0


def moved_count(n: int, pixels: int, config) -> int:
    """Scratches moved per round: ``prune_fraction * n``, at most ``prune_per_pixel * pixels``
    (``pixels`` per view), and none at ``dense_from * pixels`` scratches or more. The
    re-seeded scratches go where a view is too dark, which is a matter of image area, not of the
    scratch count: above about 0.3 scratches per pixel a fixed fraction moves more scratches than
    the dark areas need and costs picture; and a dense design is close to its targets, where any
    round costs more than it brings (docs/model.md §6)."""
    if config.is_dense(pixels, n):
        return 0
    k = int(round(config.prune_fraction * n))
    if config.prune_per_pixel > 0:
        k = min(k, int(round(config.prune_per_pixel * pixels)))
    return k


def error_density(disp: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``(M, H, W)`` sampling density: ``max(0, g * (T - I))^2`` (g: sigma 1 px Gaussian)."""
    from skimage.filters import gaussian

    e = np.stack([gaussian(t - d, sigma=1.0, mode="nearest", preserve_range=True)
                  for t, d in zip(np.asarray(target, np.float64), np.asarray(disp, np.float64))])
    return np.maximum(e, 0.0) ** 2


def new_scratches(density, hs, board, n, config, rng) -> tuple[np.ndarray, np.ndarray]:
    """``n`` re-seeded scratches' endpoints ``(n, 2), (n, 2)`` (m) from a density ``(M, H, W)``
    and the half vectors ``hs`` ``(M, H*W, 3)`` (see the module docstring)."""
    m, h, w = density.shape
    p = density.ravel()
    if not np.isfinite(p).all() or p.sum() <= 0:
        p = np.ones_like(p)
    pick = rng.choice(p.size, size=n, p=p / p.sum())
    j, pix = np.divmod(pick, h * w)
    r, c = np.divmod(pix, w)
    sx, sy = board.Sx, board.Sy
    x = (c + rng.uniform(size=n)) * sx / w
    y = sy - (r + rng.uniform(size=n)) * sy / h
    hv = np.asarray(hs, np.float64)[j, pix]
    ang = np.arctan2(hv[:, 1], hv[:, 0]) + 0.5 * np.pi + rng.normal(scale=RESEED_TURN, size=n)
    half = 0.5 * rng.uniform(config.init_length[0], config.init_length[1], size=n)
    t = np.stack([np.cos(ang), np.sin(ang)], -1) * half[:, None]
    mid = np.stack([x, y], -1)
    size = np.array([sx, sy])
    return np.clip(mid - t, 0, size), np.clip(mid + t, 0, size)


def _put(tree, idx, values: dict):
    """``tree`` with rows ``idx`` of the scratch leaves replaced by ``values[name]`` (or 0)."""
    for name in _SCRATCH_LEAVES:
        leaf = getattr(tree, name)
        v = values.get(name)
        v = jnp.zeros((len(idx),) + leaf.shape[1:], leaf.dtype) if v is None else v.astype(leaf.dtype)
        tree = eqx.tree_at(lambda t, name=name: getattr(t, name), tree, leaf.at[idx].set(v))
    return tree


def reset_moments(opt_state, idx):
    """Adam state with the first and second moments of scratches ``idx`` zeroed (any optax state
    whose `DesignParams`-shaped entries are its moments; the step count is kept)."""
    is_params = lambda x: isinstance(x, DesignParams)  # noqa: E731
    return jax.tree_util.tree_map(lambda x: _put(x, idx, {}) if is_params(x) else x, opt_state,
                                  is_leaf=is_params)


def prune_reseed(params, opt_state, lists, ctx, config, iteration: int):
    """One round. Returns ``(params, opt_state, moved indices (k,))``; the caller rebuilds the
    pair list and the capacities for the new parameters."""
    n = params.log_width.shape[0]
    k = moved_count(n, ctx.board.n_pixels, config)
    if k == 0:
        return params, opt_state, np.zeros((0,), np.int64)
    sc = scores(params, lists, ctx)
    idx = np.sort(np.argsort(sc, kind="stable")[:k])
    keep = jnp.ones((n,), bool)
    rad, _, _ = solver.evaluate(params, lists, keep, ctx)
    dens = error_density(np.asarray(display(rad)), np.asarray(ctx.loss.target))
    rng = np.random.default_rng([config.seed, iteration, 17])
    p0, p1 = new_scratches(dens, ctx.hs, ctx.board, k, config, rng)
    dt = params.geom.dtype
    s = Scratches(jnp.asarray(p0, dt), jnp.asarray(p1, dt), jnp.full((k,), config.init_width, dt),
                  jnp.full((k,), config.init_depth, dt), jnp.full((k,), config.init_alpha, dt))
    fresh = DesignParams.from_physical(s, np.ones(1), ctx.board, params.parameterisation,
                                       params.groove)
    params, opt_state = _reseeded(params, opt_state, jnp.asarray(idx), fresh)
    return params, opt_state, idx


@eqx.filter_jit
def _reseeded(params, opt_state, idx, fresh):
    """``params`` with rows ``idx`` (k,) of the scratch leaves taken from ``fresh`` (k rows), and
    those rows' Adam moments zeroed (`reset_moments`): one compiled call a round, not a dozen
    scatters dispatched one by one."""
    params = _put(params, idx, {name: getattr(fresh, name) for name in _SCRATCH_LEAVES})
    return params, reset_moments(opt_state, idx)
