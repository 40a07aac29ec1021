"""Tests of jscratch.toolpath: travel of an order against a plain loop, the exact best directions
against exhaustive search, the greedy start, the local search (a permutation, never longer, real
gains), and the k-nearest-neighbour grid against brute force."""

import itertools

import numpy as np
import pytest

from jscratch.designfile import demo_design
from jscratch.errors import InputError
from jscratch.toolpath import (
    best_directions, greedy_order, improve_order, knn_grid, order_scratches, path_travel,
)


def _travel_loop(p0, p1, order, flipped, start):
    pos, t = np.asarray(start, float), 0.0
    for s in order:
        a, b = (p1[s], p0[s]) if flipped[s] else (p0[s], p1[s])
        t += float(np.linalg.norm(a - pos))
        pos = b
    return t



def test_travel_greedy_improve_directions_against_brute_force():
    rng = np.random.default_rng(0)
    p0, p1 = rng.uniform(0, 1, (7, 2)), rng.uniform(0, 1, (7, 2))
    order = rng.permutation(7)
    fl = rng.uniform(size=7) < 0.5
    assert abs(path_travel(p0, p1, order, fl, (0.2, 0.1)) - _travel_loop(p0, p1, order, fl, (0.2, 0.1))) < 1e-12
    # Best directions: exact DP equals exhaustive search over 2^7 direction sets.
    best = min(_travel_loop(p0, p1, order, np.array(f), (0, 0)) for f in itertools.product([0, 1], repeat=7))
    assert abs(path_travel(p0, p1, order, best_directions(p0, p1, order), (0, 0)) - best) < 1e-12
    # Greedy: first pick is the nearest endpoint to the start, entered there.
    o, f = greedy_order(p0, p1, (0.0, 0.0))
    assert sorted(o.tolist()) == list(range(7))
    ends = np.concatenate([p0, p1])
    e = int(np.argmin(np.linalg.norm(ends, axis=1)))
    assert o[0] == e % 7 and f[o[0]] == (e >= 7)



def test_order_improves_and_is_a_permutation():
    d = demo_design(3000, seed=4)
    r = order_scratches(d.p0, d.p1, time_limit=None)
    assert sorted(r.order.tolist()) == list(range(3000))
    assert r.travel <= r.travel_greedy + 1e-12 < r.travel_input
    assert r.travel < 0.97 * r.travel_greedy  # the local search does real work
    assert abs(r.travel - _travel_loop(d.p0, d.p1, r.order, r.flipped, (0, 0))) < 1e-9
    # improve_order never increases travel, also from a bad (input) order.
    o, f = improve_order(d.p0[:500], d.p1[:500], np.arange(500), np.zeros(500, bool), time_limit=None)
    assert sorted(o.tolist()) == list(range(500))
    assert path_travel(d.p0[:500], d.p1[:500], o, f) < 0.5 * path_travel(d.p0[:500], d.p1[:500], np.arange(500), np.zeros(500, bool))



def test_knn_grid_matches_brute_force():
    pts = np.random.default_rng(1).uniform(0, 1, (2000, 2))
    nb = knn_grid(pts, 4)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    ref = np.argsort(d, axis=1)[:, :4]
    assert np.mean(np.all(nb == ref, axis=1)) > 0.98


@pytest.mark.parametrize("kw, match", [
    (dict(p0=[[0.0, 0.0], [np.nan, 1.0]]), r"p0 of scratch 1 is not finite \(nan, 1.0\); 1 such"),
    (dict(p1=[[np.inf, 0.5], [1.5, 1.5]]), r"p1 of scratch 0 is not finite \(inf, 0.5\)"),
    (dict(k=-1), r"`k` \(neighbours per endpoint\) must be an int >= 1, got -1$"),
    (dict(k=2.5), r"`k` \(neighbours per endpoint\) must be an int >= 1, got 2.5$"),
    (dict(start=(0,)), r"`start` must be \(x, y\), two finite numbers; got \(0,\)$"),
    (dict(start=(np.nan, 0.0)), r"`start` must be \(x, y\), two finite numbers; got \(nan, 0.0\)$"),
    (dict(start="ab"), r"`start` must be \(x, y\), two finite numbers; got 'ab'$"),
    (dict(time_limit=-1.0), r"`time_limit` must be None or a finite number of seconds >= 0"),
    (dict(time_limit=float("nan")), r"`time_limit` must be None or a finite number"),
    (dict(time_limit="5"), r"`time_limit` must be None or a finite number"),
])
def test_order_scratches_refuses_bad_arguments_in_one_line(kw, match):
    args = dict(p0=[[0.0, 0.0], [1.0, 1.0]], p1=[[0.5, 0.5], [1.5, 1.5]]) | kw
    with pytest.raises(InputError, match="^order_scratches: " + match):
        order_scratches(args.pop("p0"), args.pop("p1"), **args)
