"""The discard step (paper Fig. 21): drop the dimmest scratches while the loss allows; and its
target-quality variant: drop them while the mean SSIM stays at a requested value."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jscratch.compile_options import few_calls_jit
from jscratch.metrics import image_metrics
from jscratch.shading import display
from jscratch.design import solver


@few_calls_jit(filter=True)
def _contributions(params, lists, ctx):
    """`solver.contributions` over `solver.view_lists`' lists, one compiled call."""
    return solver.contributions(params, solver.view_lists(params, lists, ctx), ctx)


def compile_scores(params, lists, ctx) -> None:
    """Compile `scores`' per-scratch contributions for these arguments' shapes without running
    them (the jit cache is then warm); the design does it on a thread beside the step's
    compilation."""
    _contributions.lower(params, lists, ctx).compile()


def scores(params, lists, ctx) -> np.ndarray:
    """``(N,)`` each scratch's score: ``max_j contribution[j, i] / mean_i contribution[j, i]``
    (`solver.contributions` over the `bvh.PairLists` ``lists``); the discard and the
    prune/re-seed rounds drop the lowest."""
    contrib = np.asarray(_contributions(params, lists, ctx), np.float64)  # (M, N)
    mean = contrib.mean(axis=1, keepdims=True)
    return (contrib / np.where(mean > 0, mean, 1.0)).max(axis=0)


def _largest_drop(params, lists, ctx, accept, resolution: int, best):
    """Bisection over how many of the lowest-scoring scratches (`scores`) to drop: the largest
    count, to within `resolution`, whose render ``accept(keep, radiance, terms)`` accepts
    (assumed to fail from some count on). Returns the accepted ``(keep, radiance, terms)`` with
    the most dropped, or `best` (nothing dropped) when none was."""
    n = params.log_width.shape[0]
    order = np.argsort(scores(params, lists, ctx), kind="stable")
    lo, hi = 0, n  # dropping lo is accepted; dropping hi is assumed not to be
    while hi - lo > resolution:
        mid = (lo + hi) // 2
        keep = np.ones(n, bool)
        keep[order[:mid]] = False
        rad, terms, _ = solver.evaluate(params, lists, jnp.asarray(keep), ctx)
        if accept(keep, rad, terms):
            lo, best = mid, (keep, rad, terms)
        else:
            hi = mid
    return best


def discard(params, lists, ctx, loss_all, tol, rad_all, terms_all):
    """Drop the lowest-scoring scratches (`scores`) while the loss stays within
    ``(1 + tol) loss_all``."""
    n = params.log_width.shape[0]
    limit = loss_all * (1 + tol)
    return _largest_drop(params, lists, ctx, lambda k, r, t: float(t["total"]) <= limit,
                         max(1, n // 256), (np.ones(n, bool), rad_all, terms_all))


def fewest_for_ssim(params, lists, ctx, targets, target_ssim, rad_all, terms_all):
    """The fewest scratches whose mean SSIM (docs/model.md §7, `jscratch.metrics.image_metrics`,
    mean over views) stays ``>= target_ssim``: scratches are dropped in increasing `scores` order
    (the discard's), and bisection over the number dropped finds the largest count, to within
    ``max(1, N // 1024)`` scratches, whose render still meets the target. Every accepted count
    was rendered and measured, so the returned set meets the target whenever the full design
    does (bisection assumes the SSIM falls as more are dropped; where it does not, it still
    returns a measured, target-meeting set, possibly not the smallest).

    **Arguments:** the design's state as for `discard`; `targets` ``(M, H, W)`` display values;
    `target_ssim` the requested mean SSIM; `rad_all`, `terms_all` the render and loss terms with
    every scratch.

    **Returns:** ``(keep (N,) bool, radiance, loss terms, report)``; ``report`` is
    ``{"ssim": target_ssim, "reached": bool, "mean_ssim": float (of the kept set), "search":
    [[kept, mean SSIM], ...] in evaluation order}``. When the full design is below the target,
    every scratch is kept and ``reached`` is False.
    """
    n = params.log_width.shape[0]
    targets = np.asarray(targets)

    def mean_ssim(rad):
        return float(np.mean(image_metrics(np.asarray(display(rad)), targets)["ssim"]))

    full = mean_ssim(rad_all)
    search = [[n, full]]
    if full < target_ssim:
        return np.ones(n, bool), rad_all, terms_all, {"ssim": float(target_ssim), "reached": False,
                                                      "mean_ssim": full, "search": search}

    def accept(keep, rad, terms):
        search.append([int(keep.sum()), mean_ssim(rad)])
        return search[-1][1] >= target_ssim

    keep, rad, terms = _largest_drop(params, lists, ctx, accept, max(1, n // 1024),
                                     (np.ones(n, bool), rad_all, terms_all))
    kept_ssim = dict(map(tuple, search))[int(keep.sum())]
    return keep, rad, terms, {"ssim": float(target_ssim), "reached": True,
                              "mean_ssim": kept_ssim, "search": search}
