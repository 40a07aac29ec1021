"""The discard step (paper Fig. 21): drop the dimmest scratches while the loss allows."""

from __future__ import annotations


import jax.numpy as jnp
import numpy as np

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
