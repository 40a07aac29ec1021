"""Scratch ordering for fabrication: short rapid travel between cuts (numpy only).

Each scratch is cut in one straight stroke, in either direction. The tool starts at ``start`` (work
zero by default) and the travel of an ordering is

    |start - entry_0| + sum_k |exit_k - entry_{k+1}|

with ``entry_k``/``exit_k`` the endpoints of the k-th scratch in its cutting direction. This is a
travelling-salesman path over ``2N`` points whose scratch edges are forced, so the classic heuristics
carry over unchanged:

1. greedy nearest neighbour with flips: from the tool position go to the nearest free *endpoint*
   (either end of any uncut scratch; a uniform grid with ring search and periodic rebuilds stands in
   for a KD-tree);
2. 2-opt over near neighbours (reversing a run of scratches also flips each one, so only the two
   travel edges at its ends change) and Or-opt (moving a run of 1-3 scratches, either way round,
   next to a near neighbour), driven by a work queue ("don't-look bits");
3. the best direction of every scratch for the final order, exactly, by dynamic programming.

All lengths are in the units of the inputs (metres for a design).
"""

from __future__ import annotations

import math
import time
from collections import deque
from typing import NamedTuple

import numpy as np

from jscratch.errors import InputError, float64_arg, real_number, shape_arg, shown, whole_number

__all__ = ["Ordering", "order_scratches", "path_travel", "greedy_order", "improve_order",
           "best_directions", "knn_grid"]


class Ordering(NamedTuple):
    """A cutting order.

    **Fields:**

    - `order`: `(N,)` int, scratch indices in cutting order.
    - `flipped`: `(N,)` bool indexed by *scratch*: True when the scratch is cut from `p1` to `p0`.
    - `travel_input`, `travel_greedy`, `travel`: rapid travel of the input order (each scratch
      `p0 -> p1`), of the greedy order and of the final order (input units).
    - `seconds`: wall time spent ordering.
    """

    order: np.ndarray
    flipped: np.ndarray
    travel_input: float
    travel_greedy: float
    travel: float
    seconds: float


def _ends(p0, p1, order, flipped):
    f = flipped[order][:, None]
    entry = np.where(f, p1[order], p0[order])
    exit_ = np.where(f, p0[order], p1[order])
    return entry, exit_


def path_travel(p0, p1, order, flipped, start=(0.0, 0.0)) -> float:
    """Rapid travel of cutting scratches `order` (directions `flipped`, indexed by scratch) from `start`.

    **Arguments:** `p0`, `p1` `(N, 2)`; `order` `(N,)` int; `flipped` `(N,)` bool; `start` `(2,)`.

    **Returns:** the travel length (input units), a float.
    """
    p0 = np.asarray(p0, np.float64)
    p1 = np.asarray(p1, np.float64)
    order = np.asarray(order)
    if order.size == 0:
        return 0.0
    entry, exit_ = _ends(p0, p1, order, np.asarray(flipped, bool))
    prev = np.concatenate([np.asarray(start, np.float64)[None], exit_[:-1]])
    return float(np.hypot(*(entry - prev).T).sum())


# ----------------------------------------------------------------------------------------------
# Greedy nearest neighbour on a rebuilt uniform grid.


class _Grid:
    """Uniform grid over the endpoints of live scratches, about two endpoints per cell."""

    def __init__(self, xs, ys, ids):
        x = np.asarray([xs[e] for e in ids]) if ids else np.zeros(0)
        y = np.asarray([ys[e] for e in ids]) if ids else np.zeros(0)
        self.x0, self.y0 = float(x.min()), float(y.min())
        wx, wy = float(x.max()) - self.x0, float(y.max()) - self.y0
        area = max(wx * wy, 1e-300)
        h = math.sqrt(area / max(len(ids) / 2.0, 1.0))
        h = max(h, max(wx, wy) / 2048.0, 1e-12)
        self.h = h
        self.gx = max(1, min(4096, int(wx / h) + 1))
        self.gy = max(1, min(4096, int(wy / h) + 1))
        cx = np.minimum(((x - self.x0) / h).astype(np.int64), self.gx - 1)
        cy = np.minimum(((y - self.y0) / h).astype(np.int64), self.gy - 1)
        cell = cy * self.gx + cx
        ids_arr = np.asarray(ids, dtype=np.int64)
        srt = np.argsort(cell, kind="stable")
        starts = np.searchsorted(cell[srt], np.arange(self.gx * self.gy + 1))
        ids_sorted = ids_arr[srt].tolist()
        st = starts.tolist()
        self.cells = [ids_sorted[st[c]:st[c + 1]] for c in range(self.gx * self.gy)]


def greedy_order(p0, p1, start=(0.0, 0.0)):
    """Greedy nearest-neighbour order with flips.

    **Arguments:** `p0`, `p1` `(N, 2)` endpoints; `start` `(2,)` tool position before the first cut.

    **Returns:** `(order, flipped)`: `(N,)` int scratch indices and `(N,)` bool (by scratch).
    """
    p0 = np.asarray(p0, np.float64)
    p1 = np.asarray(p1, np.float64)
    n = p0.shape[0]
    order = np.empty(n, np.int64)
    flipped = np.zeros(n, bool)
    if n == 0:
        return order, flipped
    pts = np.concatenate([p0, p1])  # endpoint e: scratch e % n, side e // n (0: p0, 1: p1)
    xs, ys = pts[:, 0].tolist(), pts[:, 1].tolist()
    alive = [True] * n
    grid = _Grid(xs, ys, list(range(2 * n)))
    built_with = n
    qx, qy = float(start[0]), float(start[1])
    for k in range(n):
        left = n - k
        if left * 4 < built_with and left > 64:
            grid = _Grid(xs, ys, [e for e in range(2 * n) if alive[e % n]])
            built_with = left
        g = grid
        h, gx, gy, cells = g.h, g.gx, g.gy, g.cells
        cx = min(max(int((qx - g.x0) / h), 0), gx - 1)
        cy = min(max(int((qy - g.y0) / h), 0), gy - 1)
        best, be = math.inf, -1
        r = 0
        rmax = max(gx, gy)
        while True:
            lo_x, hi_x, lo_y, hi_y = cx - r, cx + r, cy - r, cy + r
            if r == 0:
                ring = [(cx, cy)]
            else:
                ring = []
                for i in range(max(lo_x, 0), min(hi_x, gx - 1) + 1):
                    if lo_y >= 0:
                        ring.append((i, lo_y))
                    if hi_y < gy:
                        ring.append((i, hi_y))
                for j in range(max(lo_y + 1, 0), min(hi_y - 1, gy - 1) + 1):
                    if lo_x >= 0:
                        ring.append((lo_x, j))
                    if hi_x < gx:
                        ring.append((hi_x, j))
            for i, j in ring:
                for e in cells[j * gx + i]:
                    if alive[e % n]:
                        dx = xs[e] - qx
                        dy = ys[e] - qy
                        d = dx * dx + dy * dy
                        if d < best:
                            best, be = d, e
            # Distance from the query to the outside of the searched box bounds every unseen point.
            bound = min(qx - (g.x0 + lo_x * h), g.x0 + (hi_x + 1) * h - qx,
                        qy - (g.y0 + lo_y * h), g.y0 + (hi_y + 1) * h - qy)
            if (be >= 0 and bound > 0 and best <= bound * bound) or r > rmax:
                break
            r += 1
        s = be % n
        side = be // n
        alive[s] = False
        order[k] = s
        flipped[s] = side == 1
        other = s if side == 1 else s + n
        qx, qy = xs[other], ys[other]
    return order, flipped


# ----------------------------------------------------------------------------------------------
# Neighbour lists.


def knn_grid(points, k: int, *, max_candidates: int = 4_000_000):
    """Approximate `k` nearest neighbours of every point among the others (uniform grid, 3x3 cells).

    Exact when the `k` nearest lie within the 3x3 block of cells around a point (cells hold about
    three points on average); missing slots are `-1`.

    **Arguments:** `points` `(P, 2)`; `k` neighbours; `max_candidates` caps the temporary array size.

    **Returns:** `(P, k)` int indices, nearest first.
    """
    pts = np.asarray(points, np.float64)
    P = pts.shape[0]
    out = np.full((P, k), -1, np.int64)
    if P < 2:
        return out
    lo = pts.min(axis=0)
    span = np.maximum(pts.max(axis=0) - lo, 1e-12)
    h = max(math.sqrt(span[0] * span[1] / max(P / 3.0, 1.0)), float(span.max()) / 4096.0, 1e-12)
    g = np.minimum((span / h).astype(np.int64) + 1, 4096)
    c = np.minimum(((pts - lo) / h).astype(np.int64), g - 1)
    cell = c[:, 1] * g[0] + c[:, 0]
    srt = np.argsort(cell, kind="stable")
    starts = np.searchsorted(cell[srt], np.arange(g[0] * g[1] + 1))
    occ = np.diff(starts)
    cap = int(occ.max())
    offs = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    chunk = max(1, max_candidates // (9 * cap))
    ar = np.arange(cap)
    for a in range(0, P, chunk):
        b = min(P, a + chunk)
        cc = c[a:b, None, :] + offs[None]  # (B, 9, 2)
        ok = np.all((cc >= 0) & (cc < g), axis=2)
        cid = np.where(ok, cc[..., 1] * g[0] + cc[..., 0], 0)
        s0 = np.where(ok, starts[cid], 0)
        s1 = np.where(ok, starts[cid + 1], 0)
        slot = s0[..., None] + ar  # (B, 9, cap)
        valid = slot < s1[..., None]
        cand = srt[np.where(valid, slot, 0)].reshape(b - a, -1)
        valid = valid.reshape(b - a, -1) & (cand != np.arange(a, b)[:, None])
        d = np.sum((pts[cand] - pts[a:b, None]) ** 2, axis=2)
        d = np.where(valid, d, np.inf)
        kk = min(k, d.shape[1])
        part = np.argpartition(d, kk - 1, axis=1)[:, :kk] if kk < d.shape[1] else np.argsort(d, axis=1)
        dp = np.take_along_axis(d, part, axis=1)
        o = np.argsort(dp, axis=1)
        part = np.take_along_axis(part, o, axis=1)
        dp = np.take_along_axis(dp, o, axis=1)
        idx = np.take_along_axis(cand, part, axis=1)
        out[a:b, :kk] = np.where(np.isfinite(dp), idx, -1)
    return out


# ----------------------------------------------------------------------------------------------
# Local improvement.


def improve_order(p0, p1, order, flipped, start=(0.0, 0.0), *, k: int = 8, max_or: int = 3,
                  max_span: int | None = None, time_limit: float | None = None):
    """Improve an order by 2-opt and Or-opt moves between near neighbours (first improvement).

    **Arguments:** `p0`, `p1` `(N, 2)`; `order` `(N,)`; `flipped` `(N,)` bool by scratch; `start`;
    `k` neighbours per endpoint; `max_or` longest run moved by Or-opt; `max_span` the farthest
    (in positions) a move may reach, which bounds the cost of one move (None: no limit); `time_limit` seconds (None:
    run to a local optimum).

    **Returns:** `(order, flipped)`, new arrays; the travel never increases.
    """
    p0 = np.asarray(p0, np.float64)
    p1 = np.asarray(p1, np.float64)
    n = p0.shape[0]
    order = np.array(order, np.int64)
    flipped = np.array(flipped, bool)
    if n < 2:
        return order, flipped
    span = n if max_span is None else int(max_span)
    t_end = None if time_limit is None else time.perf_counter() + time_limit
    pts = np.concatenate([p0, p1])
    nbr = knn_grid(pts, k).tolist()
    X, Y = pts[:, 0].tolist(), pts[:, 1].tolist()
    sx, sy = float(start[0]), float(start[1])
    fl = flipped.tolist()
    pos = np.empty(n, np.int64)
    pos[order] = np.arange(n)
    posl = pos.tolist()
    ordl = order.tolist()
    hyp = math.hypot

    # Endpoint ids: entry/exit of scratch s is s or s + n depending on its direction.
    def entry(s):
        return s + n if fl[s] else s

    def exit_(s):
        return s if fl[s] else s + n

    def B(i):  # exit point of position i (i = -1: the start)
        if i < 0:
            return sx, sy
        e = exit_(ordl[i])
        return X[e], Y[e]

    def A(i):  # entry point of position i
        e = entry(ordl[i])
        return X[e], Y[e]

    def dist(a, b):
        return hyp(a[0] - b[0], a[1] - b[1])

    def reverse(i, j):  # reverse positions i+1..j, flipping each scratch
        seg = ordl[i + 1:j + 1]
        seg.reverse()
        ordl[i + 1:j + 1] = seg
        for m, s in enumerate(seg, start=i + 1):
            posl[s] = m
            fl[s] = not fl[s]

    def try_2opt(i, j):
        if i > j:
            i, j = j, i
        if i < -1 or j <= i or j >= n:
            return False
        bi, ai1, bj = B(i), A(i + 1), B(j)
        if j < n - 1:
            aj1 = A(j + 1)
            delta = dist(bi, bj) + dist(ai1, aj1) - dist(bi, ai1) - dist(bj, aj1)
        else:
            delta = dist(bi, bj) - dist(bi, ai1)
        if delta < -1e-12:
            reverse(i, j)
            return True
        return False

    def try_oropt(i, L, j):
        """Move positions i..i+L-1 to between j and j+1 (j outside the run), either way round."""
        e = i + L - 1
        if e >= n or (i - 1 <= j <= e) or j < -1 or j >= n:
            return False
        prev, ai, be = B(i - 1), A(i), B(e)
        gain = dist(prev, ai)
        if e < n - 1:
            nxt = A(e + 1)
            gain += dist(be, nxt) - dist(prev, nxt)
        bj = B(j)
        if j < n - 1:
            aj1 = A(j + 1)
            base = dist(bj, aj1)
            fwd = dist(bj, ai) + dist(be, aj1) - base
            rev = dist(bj, be) + dist(ai, aj1) - base
        else:
            fwd = dist(bj, ai)
            rev = dist(bj, be)
        cost = min(fwd, rev)
        if cost - gain < -1e-12:
            run = ordl[i:e + 1]
            if rev < fwd:
                run.reverse()
                for s in run:
                    fl[s] = not fl[s]
            if j > e:
                ordl[i:j + 1] = ordl[e + 1:j + 1] + run
                lo, hi = i, j
            else:
                ordl[j + 1:e + 1] = run + ordl[j + 1:i]
                lo, hi = j + 1, e
            for m in range(lo, hi + 1):
                posl[ordl[m]] = m
            return True
        return False

    def requeue(u):
        p = posl[u]
        for m in range(max(0, p - 1), min(n, p + 2)):
            w = ordl[m]
            if not queued[w]:
                queued[w] = True
                queue.append(w)

    queue = deque(ordl)
    queued = [True] * n
    checks = 0
    while queue:
        s = queue.popleft()
        queued[s] = False
        checks += 1
        if t_end is not None and (checks & 255) == 0 and time.perf_counter() > t_end:
            break
        improved = False
        t = -1
        for own_exit in (True, False):
            i = posl[s]
            if own_exit:
                if i == n - 1:
                    continue
                own = exit_(s)
                edge = dist(B(i), A(i + 1))
            else:
                own = entry(s)
                edge = dist(B(i - 1), A(i))
            ox, oy = X[own], Y[own]
            for q in nbr[own]:
                if q < 0:
                    break
                # Neighbour lists are sorted: once the new edge is no shorter than the travel edge
                # at `own`, no move that adds it gains (the standard 2-opt/Or-opt pruning).
                if hyp(X[q] - ox, Y[q] - oy) >= edge:
                    break
                t = q % n
                if t == s:
                    continue
                j = posl[t]
                if abs(j - i) > span:
                    continue
                q_exit = q == exit_(t)
                if own_exit and q_exit:
                    improved = try_2opt(i, j)
                elif not own_exit and not q_exit:
                    improved = try_2opt(i - 1, j - 1)
                if not improved:
                    jj = j if q_exit else j - 1
                    for L in range(1, max_or + 1):
                        first = i - L + 1 if own_exit else i
                        if first >= 0 and try_oropt(first, L, jj):
                            improved = True
                            break
                if improved:
                    break
            if improved:
                break
        if improved:
            queue.appendleft(s)
            queued[s] = True
            requeue(s)
            requeue(t)
    return np.asarray(ordl, np.int64), np.asarray(fl, bool)


def best_directions(p0, p1, order, start=(0.0, 0.0)):
    """Exact best cutting direction of every scratch for a fixed order (dynamic programming).

    **Arguments:** `p0`, `p1` `(N, 2)`; `order` `(N,)`; `start` `(2,)`.

    **Returns:** `(N,)` bool by scratch, True when cut `p1 -> p0`; minimises `path_travel`.
    """
    p0 = np.asarray(p0, np.float64)
    p1 = np.asarray(p1, np.float64)
    order = np.asarray(order)
    n = order.size
    flipped = np.zeros(p0.shape[0], bool)
    if n == 0:
        return flipped
    a0, a1 = p0[order], p1[order]
    # state 0: cut p0 -> p1 (entry p0, exit p1); state 1: flipped (entry p1, exit p0).
    ent = np.stack([a0, a1], axis=1)  # (n, 2 states, 2)
    ext = np.stack([a1, a0], axis=1)
    # trans[k, a, b]: exit of k in state a to entry of k+1 in state b.
    trans = np.hypot(*(ent[1:, None, :, :] - ext[:-1, :, None, :]).transpose(3, 0, 1, 2)).tolist()
    s = np.asarray(start, np.float64)
    c0 = float(np.hypot(*(ent[0, 0] - s)))
    c1 = float(np.hypot(*(ent[0, 1] - s)))
    back = bytearray(2 * max(n - 1, 0))
    for k in range(n - 1):
        t = trans[k]
        n0a, n0b = c0 + t[0][0], c1 + t[1][0]
        n1a, n1b = c0 + t[0][1], c1 + t[1][1]
        back[2 * k] = 0 if n0a <= n0b else 1
        back[2 * k + 1] = 0 if n1a <= n1b else 1
        c0, c1 = min(n0a, n0b), min(n1a, n1b)
    state = 0 if c0 <= c1 else 1
    states = np.empty(n, bool)
    for k in range(n - 1, -1, -1):
        states[k] = bool(state)
        if k > 0:
            state = back[2 * (k - 1) + state]
    flipped[order] = states
    return flipped


def order_scratches(p0, p1, start=(0.0, 0.0), *, improve: bool = True, k: int = 10,
                    time_limit: float | None = 40.0) -> Ordering:
    """Order scratches for cutting: greedy, then 2-opt/Or-opt, then best directions.

    **Arguments:** `p0`, `p1` `(N, 2)` endpoints (any length unit, e.g. metres); `start` `(2,)` tool
    position before the first scratch; `improve` runs the local search; `k` neighbours per endpoint;
    `time_limit` seconds for the local search (None: to a local optimum).

    **Returns:** an `Ordering`. **Raises:** `InputError`, one line: endpoints not ``(N, 2)`` or not
    finite, `start` not two finite numbers, `k` not an int >= 1.
    """
    t0 = time.perf_counter()
    where = "order_scratches"
    p0, p1 = (float64_arg(where, name, p, "an (N, 2) array of numbers")
              for name, p in (("p0", p0), ("p1", p1)))
    shape_arg(where, "p0", p0, ("N", 2))
    shape_arg(where, "p1", p1, p0.shape, what=" (that of `p0`)")
    for name, p in (("p0", p0), ("p1", p1)):
        bad = ~np.isfinite(p).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"order_scratches: {name} of scratch {i} is not finite "
                             f"({p[i, 0]}, {p[i, 1]}); {int(bad.sum())} such endpoints in {name}")
    try:
        start_xy = np.asarray(start, np.float64)
    except (TypeError, ValueError):
        start_xy = np.full(0, np.nan)
    if start_xy.shape != (2,) or not np.isfinite(start_xy).all():
        raise InputError(f"order_scratches: `start` must be (x, y), two finite numbers; got "
                         f"{shown(start)}")
    if whole_number(k) is None or k < 1:
        raise InputError(f"order_scratches: `k` (neighbours per endpoint) must be an int >= 1, "
                         f"got {k!r}")
    if time_limit is not None:
        seconds = real_number(time_limit)
        if seconds is None or not (math.isfinite(seconds) and seconds >= 0):
            raise InputError(f"order_scratches: `time_limit` must be None or a finite number of "
                             f"seconds >= 0, got {time_limit!r}")
    n = p0.shape[0]
    ident = np.arange(n)
    t_in = path_travel(p0, p1, ident, np.zeros(n, bool), start)
    order, flipped = greedy_order(p0, p1, start)
    t_gr = path_travel(p0, p1, order, flipped, start)
    if improve and n > 1:
        order, flipped = improve_order(p0, p1, order, flipped, start, k=k, time_limit=time_limit)
    flipped = best_directions(p0, p1, order, start)
    t_fin = path_travel(p0, p1, order, flipped, start)
    return Ordering(order, flipped, t_in, t_gr, t_fin, time.perf_counter() - t0)
