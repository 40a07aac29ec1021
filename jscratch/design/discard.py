"""The discard step (paper Fig. 21): drop the dimmest scratches while the loss allows; and its
target-quality variant (issue 17): drop them while the mean SSIM stays at a requested value."""

from __future__ import annotations


import jax.numpy as jnp
import numpy as np

from jscratch.metrics import image_metrics
from jscratch.shading import display
from jscratch.design import solver


def scores(params, lists, ctx) -> np.ndarray:
    """``(N,)`` each scratch's score: ``max_j contribution[j, i] / mean_i contribution[j, i]``
    (`solver.contributions` over the `bvh.PairLists` ``lists``); the discard and the
    prune/re-seed rounds drop the lowest."""
    culled = solver.view_lists(params, lists, ctx)
    contrib = np.asarray(solver.contributions(params, culled, ctx), np.float64)  # (M, N)
    mean = contrib.mean(axis=1, keepdims=True)
    return (contrib / np.where(mean > 0, mean, 1.0)).max(axis=0)


def discard(params, lists, ctx, loss_all, tol, rad_all, terms_all):
    """Drop the lowest-scoring scratches (`scores`) while the loss stays within
    ``(1 + tol) loss_all``."""
    n = params.log_width.shape[0]
    order = np.argsort(scores(params, lists, ctx), kind="stable")
    limit = loss_all * (1 + tol)

    def evaluate(k):
        keep = np.ones(n, bool)
        keep[order[:k]] = False
        rad, terms, _ = solver.evaluate(params, lists, jnp.asarray(keep), ctx)
        return keep, rad, terms

    best = (np.ones(n, bool), rad_all, terms_all)
    lo, hi = 0, n  # loss(lo) within the limit; search the largest such k
    resolution = max(1, n // 256)
    while hi - lo > resolution:
        mid = (lo + hi) // 2
        cand = evaluate(mid)
        if float(cand[2]["total"]) <= limit:
            lo, best = mid, cand
        else:
            hi = mid
    return best


def fewest_for_ssim(params, lists, ctx, targets, target_ssim, rad_all, terms_all):
    """The fewest scratches whose mean SSIM (SPEC section 7, `jscratch.metrics.image_metrics`,
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
    order = np.argsort(scores(params, lists, ctx), kind="stable")

    def mean_ssim(rad):
        return float(np.mean(image_metrics(np.asarray(display(rad)), targets)["ssim"]))

    full = mean_ssim(rad_all)
    search = [[n, full]]
    best = (np.ones(n, bool), rad_all, terms_all, full)
    if full < target_ssim:
        return best[0], best[1], best[2], {"ssim": float(target_ssim), "reached": False,
                                           "mean_ssim": full, "search": search}
    lo, hi = 0, n  # dropping lo meets the target; dropping hi is assumed not to
    resolution = max(1, n // 1024)
    while hi - lo > resolution:
        mid = (lo + hi) // 2
        keep = np.ones(n, bool)
        keep[order[:mid]] = False
        rad, terms, _ = solver.evaluate(params, lists, jnp.asarray(keep), ctx)
        s = mean_ssim(rad)
        search.append([n - mid, s])
        if s >= target_ssim:
            lo, best = mid, (keep, rad, terms, s)
        else:
            hi = mid
    return best[0], best[1], best[2], {"ssim": float(target_ssim), "reached": True,
                                       "mean_ssim": best[3], "search": search}
