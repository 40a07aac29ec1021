"""Multi-view scratch design: optimise scratches and light intensities so that the board shows each
target image from its view (paper sections 3.4 and 4.1, SPEC section 6).

**Library:** `design(targets, views, board=None, config=DesignConfig()) -> DesignResult`.
**Command line:** ``python -m jscratch.design [TARGET ...] [options]`` (``--help`` lists every
option; with no targets it uses three images bundled with scikit-image).

**Parameters** (`DesignParams`, an equinox module) live in unconstrained coordinates:

- endpoints: ``p = S * sigmoid(4 z)`` per coordinate (``S`` the board size), i.e. board-normalised
  ``u = p / S`` through a sigmoid of unit slope at the centre, so an Adam step of ``lr`` moves an
  endpoint by at most about ``lr`` board widths and never off the board. The ablation
  parameterisation ``"midpoint"`` uses the midpoint (same map), the direction angle (rad) and the
  log length (log m); its endpoints are clipped to the board.
- ``log width``, ``log depth`` (log m), ``logit alpha``, ``log intensity`` (log W/sr).

Each group (``"endpoints"``, ``"width"``, ``"depth"``, ``"alpha"``, ``"intensity"``) has its own
learning rate and can be frozen (the paper freezes ``alpha = 0.04`` for fabrication; so does our
default). The optimiser is optax's Adam (``optax.scale_by_adam``) followed by a per-group scale
``-lr_g``; a frozen group gets a zero gradient and a zero step.

**Light intensities** start in closed form: with ``R_j`` the view-``j`` radiance at ``I_j = 1``,
``I_j = (mean(T_j) / mean(display(R_j)))^2.2``, which makes the mean display value equal the
target's mean wherever the render is above the display knee (``display`` is a pure power there).

**Each iteration** (one jitted step): the shared pair list (`bvh.build_pairs`) is rendered for
every view; with ``cull_eps > 0`` each view's list is first culled with `bvh.cull` (pairs whose NDF
bound is below ``cull_eps`` of their possible maximum) and compacted to a per-view capacity, and
with ``coverage_eps > 0`` the coverage pass keeps only the pairs `bvh.cull_coverage` keeps. Both
are off by default: culling bounds the forward error but removes the small gradients that turn
unlit grooves towards a view, and Adam's per-parameter scaling makes those matter (measured on the
default run: loss 0.0136 unculled vs 0.0323 at ``cull_eps = 1e-3``, 1.9x slower; see
`benchmarks/RESULTS.md`). The renderer (`render.render_pairs`) gives radiance, `render.display`
gives display values, and the loss (`loss.make_loss`) its value and gradient; Adam updates the
parameters; `bvh.needs_rebin` says whether the pair list still holds every pair. The list is
rebuilt on the host (outside the jitted step, same capacities, so no recompilation) only when it
says so. Capacity overflows (pair list or
per-view lists) re-allocate and recompile; they are rare (margins 1.25).

**Discard** (paper Fig. 21): after the optimisation each scratch gets a score, the largest over
views of its share of the view's scratch radiance relative to the mean scratch's
(``sum over its pairs of D_hat * shading / S_P``); scratches are dropped in increasing score order,
as many as bisection finds while the loss stays within ``(1 + discard_tol)`` of the loss with all
scratches (default ``discard_tol = 0.01``: at most 1 % higher).

**Failures** raise `DesignError` (a `ValueError`) for bad input (targets, views) and
`NonFiniteError` (a `RuntimeError`) when the loss, a gradient or an updated parameter becomes NaN or
infinite: the message names the iteration, the parameter group and the first bad scratch or view,
and the last good state stays in the checkpoint.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Bool, Float

from jscratch import bvh
from jscratch import loss as loss_mod
from jscratch import render as R
from jscratch.metrics import image_metrics

__all__ = [
    "DEFAULT_IMAGES",
    "GROUPS",
    "PARAMETERISATIONS",
    "DesignConfig",
    "DesignError",
    "DesignParams",
    "DesignResult",
    "NonFiniteError",
    "design",
    "load_target",
    "default_targets",
    "main",
    "write_outputs",
]

#: Parameter groups (learning rates and freezing are per group).
GROUPS = ("endpoints", "width", "depth", "alpha", "intensity")
#: Scratch position parameterisations: two endpoints (paper) or midpoint + direction + length.
PARAMETERISATIONS = ("endpoints", "midpoint")
#: Default targets from ``skimage.data`` (bundled with scikit-image; nothing is downloaded).
DEFAULT_IMAGES = ("camera", "astronaut", "chelsea", "coffee", "rocket", "moon")

_SIG = 4.0  # endpoint map u = sigmoid(_SIG z): unit slope du/dz = 1 at the board centre
_U_EPS = 1e-6  # initial board-normalised coordinates are kept this far inside [0, 1]
_CAP_ROUND = 1024  # per-view pair capacities are rounded up to a multiple of this
_CAP_MARGIN = 1.25


class DesignError(ValueError):
    """Bad input to a design: unreadable or mismatched targets, impossible views, bad config."""


class NonFiniteError(RuntimeError):
    """The loss, a gradient or a parameter became NaN or infinite during the optimisation."""


# ----------------------------------------------------------------------------------------------
# Configuration


@dataclasses.dataclass(frozen=True)
class DesignConfig:
    """Everything that controls an optimisation (JSON-friendly: `to_dict` / `from_dict`).

    **Fields** (units in brackets):

    - `n_scratches`: number of scratches ``N``. Default 20000.
    - `iterations`: Adam iterations. Default 100 (paper).
    - `seed`: seed of the initial layout (SPEC section 5).
    - `parameterisation`: ``"endpoints"`` (default, paper) or ``"midpoint"`` (ablation).
    - `init_width`, `init_depth` [m]: initial profile (paper Fig. 15: 2.5e-4, 1.28e-4).
    - `init_alpha`: initial GGX roughness. Default 0.04.
    - `init_length` [m]: initial lengths uniform in this range. Default (0.005, 0.025).
    - `lr_endpoints` [board widths per step] 1e-3 (paper); `lr_width`, `lr_depth` [log m],
      `lr_alpha` [logit], `lr_intensity` [log W/sr]: 1e-2 each.
    - `freeze`: groups not optimised (subset of `GROUPS`). Default ``("alpha",)``.
    - `loss`: a `loss.LossConfig` (default ``E_p + LAMBDA_G E_g``, filter bank).
    - `cull_eps`: per-view culling tolerance of `bvh.cull` (0 keeps every pair). Default 0:
      measured on the default run, 1e-3 is 1.9x faster (295 s vs 546 s) but ends at 2.4x the loss
      (0.0323 vs 0.0136; SSIM 0.46/0.76/0.74 vs 0.69/0.75/0.82), 1e-2 far worse (module docstring).
    - `coverage_eps`: culling tolerance of the coverage pass (`bvh.cull_coverage`, same error
      bound; only with ``cull_eps > 0``). Default 0 (every pair): measured with
      ``cull_eps = 1e-3``, 1e-3 saved 22% of the time (229 s vs 295 s) but lowered SSIM
      (0.463/0.738/0.707 vs 0.463/0.758/0.736): in dark regions the board term ``(1 - c) D_S``
      is the pixel's whole brightness, which the display gamma magnifies, and covering the board
      is how the optimiser darkens it.
    - `skin` [m]: groove inflation for binning (`bvh.allocate`); 0 rebins whenever a groove
      leaves its binned rectangle (about every step; cheaper than the extra pairs of a skin).
    - `discard`: run the discard step. `discard_tol`: allowed relative loss increase (0.01).
    - `init_intensity`: ``"match_mean"`` (closed form, default) or ``"given"`` (keep the views').
    - `adam_b1`, `adam_b2`, `adam_eps`: Adam constants. ``adam_eps = 1e-12`` because our losses
      are means over pixels (the paper's are sums), so gradients are ``H W`` times smaller.
    - `checkpoint_every`: iterations between checkpoints (when a checkpoint path is given).
    - `chunk`: pairs per chunk in the renderer (memory knob).
    - `dtype`: ``"float32"`` (default) or ``"float64"`` (needs ``jax_enable_x64``).
    """

    n_scratches: int = 20000
    iterations: int = 100
    seed: int = 0
    parameterisation: str = "endpoints"
    init_width: float = 2.5e-4
    init_depth: float = 1.28e-4
    init_alpha: float = 0.04
    init_length: tuple[float, float] = (0.005, 0.025)
    lr_endpoints: float = 1e-3
    lr_width: float = 1e-2
    lr_depth: float = 1e-2
    lr_alpha: float = 1e-2
    lr_intensity: float = 1e-2
    freeze: tuple[str, ...] = ("alpha",)
    loss: loss_mod.LossConfig = dataclasses.field(default_factory=loss_mod.LossConfig)
    cull_eps: float = 0.0
    coverage_eps: float = 0.0
    skin: float = 0.0
    discard: bool = True
    discard_tol: float = 0.01
    init_intensity: str = "match_mean"
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    adam_eps: float = 1e-12
    checkpoint_every: int = 10
    chunk: int = R.DEFAULT_CHUNK
    dtype: str = "float32"

    def __post_init__(self):
        def bad(name, what):
            raise DesignError(f"DesignConfig.{name} must be {what}, got {getattr(self, name)!r}")

        for name in ("n_scratches", "chunk", "checkpoint_every"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                bad(name, "a positive int")
        if not (isinstance(self.iterations, (int, np.integer)) and self.iterations >= 0):
            bad("iterations", "an int >= 0")
        if self.parameterisation not in PARAMETERISATIONS:
            bad("parameterisation", f"one of {PARAMETERISATIONS}")
        for name in ("init_width", "init_depth"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                bad(name, "a positive length in metres")
        if not (0 < self.init_alpha < 1):
            bad("init_alpha", "in (0, 1)")
        lo, hi = self.init_length
        if not (0 < lo <= hi and math.isfinite(hi)):
            bad("init_length", "(min, max) metres with 0 < min <= max")
        object.__setattr__(self, "init_length", (float(lo), float(hi)))
        for g in GROUPS:
            v = getattr(self, f"lr_{g}")
            if not (math.isfinite(v) and v >= 0):
                bad(f"lr_{g}", "a finite learning rate >= 0")
        freeze = tuple(self.freeze)
        for g in freeze:
            if g not in GROUPS:
                bad("freeze", f"a subset of {GROUPS}")
        object.__setattr__(self, "freeze", tuple(g for g in GROUPS if g in freeze))
        if isinstance(self.loss, dict):
            object.__setattr__(self, "loss", loss_mod.LossConfig(**self.loss))
        if not isinstance(self.loss, loss_mod.LossConfig):
            bad("loss", "a jscratch.loss.LossConfig")
        for name in ("cull_eps", "coverage_eps", "skin", "discard_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                bad(name, "finite and >= 0")
        if self.init_intensity not in ("match_mean", "given"):
            bad("init_intensity", "'match_mean' or 'given'")
        if self.dtype not in ("float32", "float64"):
            bad("dtype", "'float32' or 'float64'")

    def learning_rates(self) -> dict[str, float]:
        """Per-group learning rate, 0 for frozen groups."""
        return {g: 0.0 if g in self.freeze else float(getattr(self, f"lr_{g}")) for g in GROUPS}

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (``from_dict`` inverts it)."""
        d = dataclasses.asdict(self)
        d["init_length"] = list(self.init_length)
        d["freeze"] = list(self.freeze)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "DesignConfig":
        d = dict(d)
        if "loss" in d and isinstance(d["loss"], dict):
            d["loss"] = loss_mod.LossConfig(**d["loss"])
        if "init_length" in d:
            d["init_length"] = tuple(d["init_length"])
        if "freeze" in d:
            d["freeze"] = tuple(d["freeze"])
        return cls(**d)


# ----------------------------------------------------------------------------------------------
# Parameters in unconstrained coordinates


def _logit(u):
    return np.log(u) - np.log1p(-u)


class DesignParams(eqx.Module):
    """Optimised parameters in unconstrained coordinates (see the module docstring).

    **Fields:**

    - `geom`: ``(N, 4)``: ``"endpoints"``: ``(z0x, z0y, z1x, z1y)`` with ``p = S sigmoid(4 z)``;
      ``"midpoint"``: ``(zmx, zmy, angle [rad], log length [log m])``.
    - `log_width`, `log_depth` ``(N,)`` (log m); `logit_alpha` ``(N,)``;
      `log_intensity` ``(M,)`` (log W/sr).
    - `parameterisation` (static) and `board_size` ``(Sx, Sy)`` m (static).
    """

    geom: Float[Array, "n 4"]
    log_width: Float[Array, " n"]
    log_depth: Float[Array, " n"]
    logit_alpha: Float[Array, " n"]
    log_intensity: Float[Array, " m"]
    parameterisation: str = eqx.field(static=True, default="endpoints")
    board_size: tuple[float, float] = eqx.field(static=True, default=(0.3, 0.3))

    @staticmethod
    def from_physical(scratches: R.Scratches, intensity: ArrayLike, board: R.Board,
                      parameterisation: str = "endpoints") -> "DesignParams":
        """Unconstrained coordinates of concrete scratches and intensities (host side).

        Endpoints are first moved ``1e-6`` board widths inside the board (the sigmoid never
        reaches its ends). Returns arrays in ``scratches.dtype``.
        """
        dt = scratches.dtype
        size = np.array([board.Sx, board.Sy])
        p0 = np.asarray(scratches.p0, np.float64)
        p1 = np.asarray(scratches.p1, np.float64)
        if parameterisation == "endpoints":
            u = np.clip(np.concatenate([p0, p1], 1) / np.tile(size, 2), _U_EPS, 1 - _U_EPS)
            geom = _logit(u) / _SIG
        elif parameterisation == "midpoint":
            um = np.clip(0.5 * (p0 + p1) / size, _U_EPS, 1 - _U_EPS)
            d = p1 - p0
            length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-6)
            geom = np.concatenate(
                [_logit(um) / _SIG, np.arctan2(d[:, 1], d[:, 0])[:, None], np.log(length)[:, None]], 1
            )
        else:
            raise DesignError(f"parameterisation must be one of {PARAMETERISATIONS}, got {parameterisation!r}")
        a = np.asarray(scratches.alpha, np.float64)
        inten = np.broadcast_to(np.asarray(intensity, np.float64), np.shape(intensity) or (1,))
        return DesignParams(
            geom=jnp.asarray(geom, dt),
            log_width=jnp.asarray(np.log(np.asarray(scratches.width, np.float64)), dt),
            log_depth=jnp.asarray(np.log(np.asarray(scratches.depth, np.float64)), dt),
            logit_alpha=jnp.asarray(_logit(a), dt),
            log_intensity=jnp.asarray(np.log(np.maximum(inten, 1e-300)), dt),
            parameterisation=parameterisation,
            board_size=(float(board.Sx), float(board.Sy)),
        )

    def endpoints(self) -> tuple[Array, Array]:
        """``(p0, p1)``, each ``(N, 2)`` board metres, on the board."""
        size = jnp.asarray(self.board_size, self.geom.dtype)
        if self.parameterisation == "endpoints":
            u = jax.nn.sigmoid(_SIG * self.geom)
            return u[:, :2] * size, u[:, 2:] * size
        m = jax.nn.sigmoid(_SIG * self.geom[:, :2]) * size
        ang, half = self.geom[:, 2], 0.5 * jnp.exp(self.geom[:, 3])
        t = jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1) * half[:, None]
        return jnp.clip(m - t, 0, size), jnp.clip(m + t, 0, size)

    def scratches(self) -> R.Scratches:
        """The physical `render.Scratches` (jittable)."""
        p0, p1 = self.endpoints()
        return R.Scratches(p0, p1, jnp.exp(self.log_width), jnp.exp(self.log_depth),
                           jax.nn.sigmoid(self.logit_alpha))

    def intensity(self) -> Array:
        """Light intensities ``(M,)`` (W/sr)."""
        return jnp.exp(self.log_intensity)

    def group(self, name: str) -> Array:
        """The unconstrained array of a parameter group."""
        return {"endpoints": self.geom, "width": self.log_width, "depth": self.log_depth,
                "alpha": self.logit_alpha, "intensity": self.log_intensity}[name]


def _group_tree(params: DesignParams, values: dict[str, Any]) -> DesignParams:
    """A `DesignParams`-shaped pytree with ``values[group]`` at each group's leaf."""
    return DesignParams(values["endpoints"], values["width"], values["depth"], values["alpha"],
                        values["intensity"], params.parameterisation, params.board_size)


# ----------------------------------------------------------------------------------------------
# Jitted pieces (module level, so that repeated designs of the same shapes reuse compilations)


class _Ctx(eqx.Module):
    """Per-design constants of the jitted functions."""

    camera: Array
    light: Array
    hs: Array  # (M, P, 3) half vectors
    board_ndf: Array  # (P,) flat board's GGX at each pixel, largest over the views (1/sr)
    loss: loss_mod.BoundLoss
    lrs: DesignParams  # per-group learning rate (0 = frozen), scalar leaves
    cull_eps: float = eqx.field(static=True)
    coverage_eps: float = eqx.field(static=True)
    board: R.Board = eqx.field(static=True)
    chunk: int = eqx.field(static=True)


@functools.lru_cache(maxsize=None)
def _adam(b1: float, b2: float, eps: float) -> optax.GradientTransformation:
    # Cached: the same object for the same constants, so jit caches hit across designs.
    return optax.scale_by_adam(b1=b1, b2=b2, eps=eps)


def _culled(params: DesignParams, pairs: bvh.Pairs, ctx: _Ctx) -> list[bvh.Pairs]:
    """The ``M`` per-view culled lists (`bvh.cull`, same capacity as ``pairs``) and the coverage
    list (`bvh.cull_coverage` when ``coverage_eps > 0``, else ``pairs`` itself). Needs
    ``cull_eps > 0``."""
    s = jax.lax.stop_gradient(params).scratches()
    culled = [bvh.cull(pairs, s.p0, s.p1, s.width, s.depth, s.alpha, ctx.hs[j], ctx.cull_eps)
              for j in range(ctx.hs.shape[0])]
    if ctx.coverage_eps > 0:
        return culled + [bvh.cull_coverage(pairs, s.alpha, ctx.board_ndf, ctx.coverage_eps)]
    return culled + [pairs]


def _view_lists(params: DesignParams, pairs: bvh.Pairs, ctx: _Ctx, caps: tuple[int, ...]):
    """``(lists, coverage list, counts)``: per-view culled, compacted pair lists, the coverage
    list (compacted when culled by `bvh.cull_coverage`) and the ``M + 1`` counts of kept pairs
    (views, then coverage); see `_culled`. Unculled (``cull_eps == 0``): the shared list, ``None``
    (coverage from the same list) and ``M`` counts."""
    m = ctx.hs.shape[0]
    if ctx.cull_eps == 0:
        n = jnp.sum(pairs.valid)
        return pairs, None, jnp.stack([n] * m)
    culled = _culled(params, pairs, ctx)
    counts = jnp.stack([jnp.sum(c.valid) for c in culled])
    # An overflowing list is incomplete: the host sees ``counts > caps``, throws the result away
    # and retries with larger capacities. The flag is cleared so that the renderer's own overflow
    # check does not abort the step first.
    compacted = lambda c, cap: eqx.tree_at(lambda q: q.overflow, bvh.compact(c, cap),
                                           jnp.zeros((), bool))
    lists = [compacted(c, cap) for c, cap in zip(culled[:m], caps)]
    cov = compacted(culled[m], caps[m]) if ctx.coverage_eps > 0 else pairs
    return lists, cov, counts


def _radiance(params: DesignParams, lists, cov, ctx: _Ctx) -> Array:
    """Radiance ``(M, H, W)`` from `_view_lists`' pair lists."""
    views = R.Views(ctx.camera, ctx.light, params.intensity())
    return R.render_pairs(params.scratches(), views, ctx.board, lists, cov, chunk=ctx.chunk)


def _masked(p: bvh.Pairs, keep_ext: Array) -> bvh.Pairs:
    return eqx.tree_at(lambda q: q.valid, p, p.valid & keep_ext[p.scratch])


@eqx.filter_jit
def _evaluate(params: DesignParams, pairs: bvh.Pairs, keep: Array, ctx: _Ctx, caps):
    """Forward only: ``(radiance (M,H,W), loss terms, per-view counts)`` with scratches outside
    ``keep`` removed (their pairs masked, so they neither shine nor cover)."""
    keep_ext = jnp.concatenate([keep, jnp.zeros((1,), bool)])
    lists, cov, counts = _view_lists(params, pairs, ctx, caps)
    if isinstance(lists, list):
        lists = [_masked(p, keep_ext) for p in lists]
    else:
        lists = _masked(lists, keep_ext)
    cov = None if cov is None else _masked(cov, keep_ext)
    rad = _radiance(params, lists, cov, ctx)
    return rad, ctx.loss.terms(R.display(rad)), counts


def _health(loss, grads: DesignParams, new: DesignParams) -> dict[str, Array]:
    """Per check: ``(ok, first bad index)``; names the parameter group that went wrong."""
    out = {"loss": (jnp.isfinite(loss), jnp.asarray(-1))}
    s = new.scratches()
    phys = {"endpoints": jnp.concatenate([s.p0, s.p1], 1), "width": s.width, "depth": s.depth,
            "alpha": s.alpha, "intensity": new.intensity()}
    ranges = {"width": lambda x: x > 0, "depth": lambda x: x > 0,
              "alpha": lambda x: (x > 0) & (x <= 1), "intensity": lambda x: x >= 0}
    for g in GROUPS:
        gr, val = grads.group(g), phys[g]
        good_g = jnp.isfinite(gr).reshape(gr.shape[0], -1).all(-1)
        good_v = jnp.isfinite(val).reshape(val.shape[0], -1).all(-1) & jnp.isfinite(
            new.group(g)).reshape(val.shape[0], -1).all(-1)
        if g in ranges:
            good_v = good_v & ranges[g](val)
        out[f"gradient of {g}"] = (jnp.all(good_g), jnp.argmin(good_g))
        out[f"updated {g}"] = (jnp.all(good_v), jnp.argmin(good_v))
    return out


def _step(params: DesignParams, opt_state, pairs: bvh.Pairs, ctx: _Ctx, caps, adam):
    """`_step_impl`, jitted with `render.grad_compiler_options` (faster compile and step)."""
    return _jitted_step()(params, opt_state, pairs, ctx, caps, adam)


@functools.lru_cache(maxsize=None)
def _jitted_step():
    return eqx.filter_jit(_step_impl, compiler_options=R.grad_compiler_options())


def _step_impl(params: DesignParams, opt_state, pairs: bvh.Pairs, ctx: _Ctx, caps, adam):
    """One Adam iteration. Returns the new state, the loss terms at ``params``, whether the pair
    list must be rebuilt for the new parameters, per-view counts (to detect capacity overflow) and
    the health report."""
    lists, cov, counts = _view_lists(params, pairs, ctx, caps)

    def f(p):
        terms = ctx.loss.terms(R.display(_radiance(p, lists, cov, ctx)))
        return terms["total"], terms

    (value, terms), grads = eqx.filter_value_and_grad(f, has_aux=True)(params)
    frozen = jax.tree_util.tree_map(lambda lr: lr == 0, ctx.lrs)
    grads = jax.tree_util.tree_map(lambda g, fr: jnp.where(fr, 0, g), grads, frozen)
    updates, opt_state = adam.update(grads, opt_state, params)
    updates = jax.tree_util.tree_map(lambda u, lr: (-lr * u).astype(u.dtype), updates, ctx.lrs)
    new = eqx.apply_updates(params, updates)
    s = new.scratches()
    # Non-finite or out-of-range values are reported by the health check (and the host stops);
    # here they are replaced so that needs_rebin's own checks do not fire first.
    ok = lambda x: jnp.isfinite(x) & (x > 0)
    p0 = jnp.where(jnp.isfinite(s.p0), s.p0, 0)
    p1 = jnp.where(jnp.isfinite(s.p1), s.p1, 0)
    rebin = bvh.needs_rebin(pairs, p0, p1, jnp.where(ok(s.width), s.width, 1e-4),
                            jnp.where(ok(s.depth), s.depth, 1e-4))
    return new, opt_state, terms, rebin, counts, _health(value, grads, new)


@eqx.filter_jit
def _physical(params: DesignParams):
    s = params.scratches()
    return s.p0, s.p1, s.width, s.depth, s.alpha, params.intensity()


@eqx.filter_jit
def _contributions(params: DesignParams, lists, ctx: _Ctx, fps: Array) -> Array:
    """Per view and scratch, the scratch term of the view's total radiance
    ``sum_pairs D_hat * shade(1, 1) / S_P`` (W/(sr m^2) summed over pixels), ``(M, N)``."""
    from jscratch import ndf

    s = params.scratches()
    n = s.n
    m = ctx.hs.shape[0]
    views = R.Views(ctx.camera, ctx.light, params.intensity())
    dt = s.dtype
    ones = jnp.ones((m, ctx.board.n_pixels), dt)
    k = R.shade(ones, ones, views, ctx.board) / ctx.board.pixel_area  # (M, P), board term is 0
    if not isinstance(lists, list):
        lists = [lists] * m
    out = []
    for j, p in enumerate(lists):
        i = jnp.clip(p.scratch, 0, n - 1)
        pix = jnp.clip(p.pixel, 0, ctx.board.n_pixels - 1)

        def one(args):
            ii, px = args
            d, _ = ndf.pair_integral(ctx.hs[j, px], fps[px], s.p0[ii], s.p1[ii], s.width[ii],
                                     s.depth[ii], s.alpha[ii])
            return d

        d = jax.lax.map(one, (i, pix), batch_size=ctx.chunk)
        d = jnp.where(p.valid, d * k[j, pix], 0)
        out.append(jax.ops.segment_sum(d, i, num_segments=n))
    return jnp.stack(out)


# ----------------------------------------------------------------------------------------------
# Checks of the inputs


def _check_targets(targets, m: int | None) -> np.ndarray:
    t = np.asarray(targets)
    if t.dtype == object or not (np.issubdtype(t.dtype, np.floating) or np.issubdtype(t.dtype, np.integer)):
        raise DesignError(f"targets must be a numeric (M, H, W) array of display values, got dtype {t.dtype}")
    if t.ndim != 3:
        raise DesignError(f"targets must have shape (M, H, W) (one grayscale image per view), got {t.shape}")
    if m is not None and t.shape[0] != m:
        raise DesignError(f"got {t.shape[0]} target images for {m} views: give one target per view")
    if np.issubdtype(t.dtype, np.integer):
        raise DesignError("targets must be floating display values in [0, 1]; convert integer images "
                          "(e.g. uint8 / 255) or use load_target")
    if not np.all(np.isfinite(t)):
        j = int(np.argwhere(~np.isfinite(t))[0, 0])
        raise DesignError(f"target {j} has non-finite values")
    if t.min() < 0 or t.max() > 1:
        j = int(np.argmax(((t < 0) | (t > 1)).reshape(t.shape[0], -1).any(-1)))
        raise DesignError(f"target {j} has values outside [0, 1] (range [{t[j].min()}, {t[j].max()}])")
    if min(t.shape[1:]) < 16:
        raise DesignError(f"targets must be at least 16x16 px, got {t.shape[1]}x{t.shape[2]}")
    return t


def _check_views(views: R.Views, board: R.Board) -> None:
    cam = np.asarray(views.camera, np.float64)
    lig = np.asarray(views.light, np.float64)
    for name, pos in (("camera", cam), ("light", lig)):
        bad = ~(np.isfinite(pos).all(-1) & (pos[:, 2] > 0))
        if bad.any():
            j = int(np.argmax(bad))
            raise DesignError(f"view {j}: the {name} at {pos[j].tolist()} m is not above the board "
                              "(it needs z > 0)")
    spot = R.flat_highlight(cam, lig)
    on = (spot[:, 0] >= 0) & (spot[:, 0] <= board.Sx) & (spot[:, 1] >= 0) & (spot[:, 1] <= board.Sy)
    if on.any():
        j = int(np.argmax(on))
        raise DesignError(
            f"view {j}: the camera is at the light's mirror direction (the flat board reflects the "
            f"light into it at board point ({spot[j, 0]:.4f}, {spot[j, 1]:.4f}) m), so the board's "
            "own highlight would dominate that view; move the camera or the light")


def _targets_hash(t: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(t, np.float64).tobytes()).hexdigest()[:16]


# ----------------------------------------------------------------------------------------------
# Checkpoints


def _save_npz(path: str, arrays: dict[str, np.ndarray]) -> None:
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".ckpt-", suffix=".npz.tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


_PAIR_FIELDS = ("pixel", "scratch", "valid", "overflow", "bin_p0", "bin_p1", "bin_half_width",
                "bin_extend", "bin_tol")
_SPEC_FIELDS = ("board", "shape", "strip_capacity", "rows_per_strip", "pair_capacity", "skin",
                "margin")


@dataclasses.dataclass
class _State:
    """Everything the loop carries between iterations (what a checkpoint holds)."""

    iteration: int
    params: DesignParams
    opt_state: Any
    pairs: bvh.Pairs | None
    spec: bvh.GridSpec | None
    caps: tuple[int, ...]
    history: dict[str, Any]
    rebins: int


def _save_checkpoint(path: str, state: _State, config: DesignConfig, thash: str) -> None:
    arrays: dict[str, np.ndarray] = {}
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state.params)):
        arrays[f"params/{i}"] = np.asarray(leaf)
    for i, leaf in enumerate(jax.tree_util.tree_leaves(state.opt_state)):
        arrays[f"opt/{i}"] = np.asarray(leaf)
    for f in _PAIR_FIELDS:
        arrays[f"pairs/{f}"] = np.asarray(getattr(state.pairs, f))
    meta = {
        "iteration": state.iteration,
        "spec": {f: getattr(state.spec, f) for f in _SPEC_FIELDS},
        "caps": list(state.caps),
        "history": state.history,
        "rebins": state.rebins,
        "config": config.to_dict(),
        "targets_hash": thash,
    }
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    _save_npz(path, arrays)


def _load_checkpoint(path: str, like: _State, config: DesignConfig, thash: str) -> _State:
    if not os.path.isfile(path):
        raise DesignError(f"--resume: no checkpoint at {path!r}")
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    meta = json.loads(bytes(data["meta"]).decode())
    if meta["targets_hash"] != thash:
        raise DesignError(f"checkpoint {path!r} was made for different target images")
    saved = DesignConfig.from_dict(meta["config"])
    keys = ("n_scratches", "seed", "parameterisation", "freeze", "dtype", "cull_eps",
            "coverage_eps", "skin")
    for k in keys:
        if getattr(saved, k) != getattr(config, k):
            raise DesignError(f"checkpoint {path!r} was made with {k} = {getattr(saved, k)!r}, "
                              f"not {getattr(config, k)!r}")

    def restore(tree, prefix):
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        new = []
        for i, leaf in enumerate(leaves):
            a = data.get(f"{prefix}/{i}")
            if a is None or a.shape != np.shape(leaf):
                raise DesignError(f"checkpoint {path!r} does not match this design ({prefix} leaf {i})")
            new.append(jnp.asarray(a, dtype=jnp.asarray(leaf).dtype))
        return jax.tree_util.tree_unflatten(treedef, new)

    params = restore(like.params, "params")
    opt_state = restore(like.opt_state, "opt")
    pairs = bvh.Pairs(**{f: jnp.asarray(data[f"pairs/{f}"]) for f in _PAIR_FIELDS})
    sp = meta["spec"]
    spec = bvh.GridSpec(board=tuple(sp["board"]), shape=tuple(sp["shape"]),
                        strip_capacity=sp["strip_capacity"], rows_per_strip=sp["rows_per_strip"],
                        pair_capacity=sp["pair_capacity"], skin=sp["skin"], margin=sp["margin"])
    return _State(meta["iteration"], params, opt_state, pairs, spec, tuple(meta["caps"]),
                  meta["history"], meta["rebins"])


# ----------------------------------------------------------------------------------------------
# The optimisation


@dataclasses.dataclass
class DesignResult:
    """What `design` returns.

    **Fields:**

    - `scratches`: the final `render.Scratches` after the discard step (``N_kept`` scratches).
    - `views`: `render.Views` with the optimised intensities.
    - `board`: the `render.Board`.
    - `params`: final `DesignParams` (all ``N`` scratches, before the discard).
    - `keep`: ``(N,)`` bool, the scratches kept by the discard.
    - `radiance`, `display`: ``(M, H, W)`` final renders (after the discard).
    - `targets`: ``(M, H, W)`` the targets.
    - `history`: per-iteration lists ``"total"`` and the loss terms (loss at the parameters the
      iteration started from).
    - `metrics`: SPEC section 7 metrics (`metrics.image_metrics`) plus ``loss``,
      ``loss_before_discard``, ``metrics_before_discard`` (SPEC 7 metrics with every scratch),
      ``discarded``, ``kept``, ``pairs_total``, ``pairs_per_view``, ``coverage_pairs`` (pairs in
      the coverage pass after `bvh.cull_coverage`), ``rebins``,
      timing (s): ``time_total``, ``time_first_step`` (includes compilation),
      ``time_step_median``, ``time_discard``.
    - `config`: the `DesignConfig`.
    """

    scratches: R.Scratches
    views: R.Views
    board: R.Board
    params: DesignParams
    keep: np.ndarray
    radiance: np.ndarray
    display: np.ndarray
    targets: np.ndarray
    history: dict[str, list]
    metrics: dict[str, Any]
    config: DesignConfig


def _round_cap(x: float) -> int:
    return max(_CAP_ROUND, int(math.ceil(x / _CAP_ROUND)) * _CAP_ROUND)


@eqx.filter_jit
def _cull_counts(params: DesignParams, pairs: bvh.Pairs, ctx: _Ctx) -> Array:
    return jnp.stack([jnp.sum(c.valid) for c in _culled(params, pairs, ctx)])


def _measure_caps(params, pairs, ctx, m) -> tuple[int, ...]:
    """Capacities of the ``M`` view lists and the coverage list: the culled pair counts times a
    margin (``M`` ones when not culling)."""
    if ctx.cull_eps == 0:
        return (1,) * m
    counts = np.asarray(_cull_counts(params, pairs, ctx))
    return tuple(_round_cap(_CAP_MARGIN * int(c)) for c in counts)


def design(
    targets: Float[ArrayLike, "M H W"],
    views: R.Views,
    board: R.Board | None = None,
    config: DesignConfig | None = None,
    *,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    progress: bool = False,
    stop_after: int | None = None,
) -> DesignResult:
    """Optimise scratches and light intensities so that view ``j`` shows ``targets[j]``.

    **Arguments:**

    - `targets`: ``(M, H, W)`` display values in ``[0, 1]``, row 0 at the top (SPEC section 1).
    - `views`: `render.Views` with ``M`` cameras and lights (m, above the board); the intensities
      are the starting values when ``config.init_intensity == "given"``.
    - `board`: `render.Board`; its ``shape`` must be ``(H, W)``. Default ``Board(shape=(H, W))``.
    - `config`: `DesignConfig` (default ``DesignConfig()``).
    - `checkpoint`: path of a checkpoint file, written every ``config.checkpoint_every``
      iterations, at the end, and with the last good state when a NaN stops the run.
    - `resume`: continue from `checkpoint` (same targets and config); the continued run is
      identical to an uninterrupted one.
    - `progress`: show a tqdm progress bar with the loss.
    - `stop_after`: stop after this many iterations in total (for tests of resuming); the
      checkpoint is written and the result describes the state at that point.

    **Returns:** a `DesignResult`.

    **Raises:** `DesignError` for bad targets, views or config; `NonFiniteError` when the loss, a
    gradient or a parameter becomes non-finite (after saving the last good state to `checkpoint`).
    """
    t_start = time.perf_counter()
    config = DesignConfig() if config is None else config
    if not isinstance(config, DesignConfig):
        raise DesignError(f"config must be a DesignConfig, got {type(config).__name__}")
    if not isinstance(views, R.Views):
        raise DesignError(f"views must be a jscratch.render.Views, got {type(views).__name__}")
    m = views.m
    tnp = _check_targets(targets, m)
    h, w = tnp.shape[1:]
    board = R.Board(shape=(h, w)) if board is None else board
    if board.shape != (h, w):
        raise DesignError(f"targets are {h}x{w} px but the board's image shape is {board.shape}")
    _check_views(views, board)
    if config.dtype == "float64" and jax.dtypes.canonicalize_dtype(jnp.float64) != jnp.float64:
        raise DesignError("dtype float64 needs jax_enable_x64 (jax.config.update('jax_enable_x64', True))")
    if resume and checkpoint is None:
        raise DesignError("resume=True needs a checkpoint path")
    dt = jnp.dtype(config.dtype)
    checkpoint = None if checkpoint is None else os.fspath(checkpoint)
    thash = _targets_hash(tnp)

    # Initial state (also the structure a checkpoint is restored into).
    scratches = R.Scratches.random(
        jax.random.PRNGKey(config.seed), config.n_scratches, board, length=config.init_length,
        width=config.init_width, depth=config.init_depth, alpha=config.init_alpha, dtype=dt)
    params = DesignParams.from_physical(scratches, np.asarray(views.intensity), board,
                                        config.parameterisation)
    adam = _adam(config.adam_b1, config.adam_b2, config.adam_eps)
    lrs = _group_tree(params, {g: jnp.asarray(v, dt) for g, v in config.learning_rates().items()})
    cam = jnp.asarray(views.camera, dt)
    lig = jnp.asarray(views.light, dt)
    hs = R.half_vectors(R.Views(cam, lig), board, dt)
    bound = loss_mod.make_loss(config.loss).bind(jnp.asarray(tnp, dt))
    board_ndf = jnp.max(R.board_ndf(R.Views(cam, lig), board, dt), axis=0)  # (P,)
    ctx = _Ctx(cam, lig, hs, board_ndf, bound, lrs, float(config.cull_eps),
               float(config.coverage_eps), board, int(config.chunk))
    all_keep = jnp.ones((config.n_scratches,), bool)

    def bin_pairs(params, spec):
        p0, p1, wd, dp, _, _ = _physical(params)
        return bvh.build_pairs(p0, p1, wd, dp, board=(board.Sx, board.Sy), shape=board.shape,
                               spec=spec, skin=config.skin)

    if resume:
        like = _State(0, params, adam.init(params), None, None, (1,) * m, {}, 0)
        state = _load_checkpoint(checkpoint, like, config, thash)
    else:
        pairs, spec = bin_pairs(params, None)
        caps = _measure_caps(params, pairs, ctx, m)
        if config.init_intensity == "match_mean":
            unit = eqx.tree_at(lambda p: p.log_intensity, params, jnp.zeros((m,), dt))
            rad = np.asarray(_evaluate(unit, pairs, all_keep, ctx, caps)[0], np.float64)
            mean_disp = np.asarray(R.display(rad)).mean(axis=(1, 2))
            tmean = tnp.mean(axis=(1, 2))
            if np.any(mean_disp <= 0):
                j = int(np.argmax(mean_disp <= 0))
                raise DesignError(f"view {j} renders black at intensity 1: cannot set its light")
            log_i = R.DISPLAY_GAMMA * (np.log(np.maximum(tmean, 1e-6)) - np.log(mean_disp))
            params = eqx.tree_at(lambda p: p.log_intensity, params, jnp.asarray(log_i, dt))
        state = _State(0, params, adam.init(params), pairs, spec, caps,
                       {"total": [], "terms": {}}, 0)

    n_iter = config.iterations if stop_after is None else min(config.iterations, stop_after)
    step_times: list[float] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.iterations, initial=state.iteration, desc="design", unit="it",
                   dynamic_ncols=True)
    try:
        while state.iteration < n_iter:
            t0 = time.perf_counter()
            new, opt_state, terms, rebin, counts, health = _step(
                state.params, state.opt_state, state.pairs, ctx, state.caps, adam)
            counts = np.asarray(counts)
            if ctx.cull_eps > 0 and np.any(counts > np.asarray(state.caps)):
                caps = tuple(max(c, _round_cap(_CAP_MARGIN * int(n)))
                             for c, n in zip(state.caps, counts))
                state = dataclasses.replace(state, caps=caps)
                continue  # retry the same iteration with larger per-view lists
            for what, (ok, idx) in health.items():
                if not bool(ok):
                    if checkpoint is not None:
                        _save_checkpoint(checkpoint, state, config, thash)
                    unit = "view" if what.endswith("intensity") else "scratch"
                    where = "" if what == "loss" else f" (first bad {unit}: {int(idx)})"
                    saved = f"; the last good state is in {checkpoint!r}" if checkpoint else ""
                    raise NonFiniteError(
                        f"non-finite or out-of-range {what} at iteration {state.iteration}{where}: "
                        f"the optimisation stopped{saved}. Lower the learning rate of that group "
                        "or freeze it.")
            hist = state.history
            hist["total"].append(float(terms["total"]))
            for k, v in terms.items():
                if k != "total":
                    hist["terms"].setdefault(k, []).append(float(v))
            pairs, spec, rebins = state.pairs, state.spec, state.rebins
            if bool(rebin):
                pairs, spec = bin_pairs(new, spec)
                rebins += 1
            state = _State(state.iteration + 1, new, opt_state, pairs, spec, state.caps, hist,
                           rebins)
            step_times.append(time.perf_counter() - t0)
            if bar is not None:
                bar.set_postfix(loss=f"{hist['total'][-1]:.5g}")
                bar.update(1)
            if checkpoint is not None and (state.iteration % config.checkpoint_every == 0
                                           or state.iteration == n_iter):
                _save_checkpoint(checkpoint, state, config, thash)
    finally:
        if bar is not None:
            bar.close()

    # Final render, discard, metrics.
    params, pairs = state.params, state.pairs
    caps = state.caps
    t_d = time.perf_counter()
    rad, terms, counts = _evaluate(params, pairs, all_keep, ctx, caps)
    if ctx.cull_eps > 0 and np.any(np.asarray(counts) > np.asarray(caps)):
        caps = _measure_caps(params, pairs, ctx, m)
        rad, terms, counts = _evaluate(params, pairs, all_keep, ctx, caps)
    loss_all = float(terms["total"])
    metrics_all = image_metrics(np.asarray(R.display(rad)), tnp)
    keep = np.ones(config.n_scratches, bool)
    if config.discard and stop_after is None:
        keep, rad, terms = _discard(params, pairs, ctx, caps, loss_all, config.discard_tol,
                                    rad, terms)
    t_discard = time.perf_counter() - t_d
    rad = np.asarray(rad)
    disp = np.asarray(R.display(rad))
    p0, p1, wd, dp, al, inten = (np.asarray(a) for a in _physical(params))
    k = keep
    result_scratches = R.Scratches(p0[k], p1[k], wd[k], dp[k], al[k])
    result_views = R.Views(np.asarray(cam), np.asarray(lig), inten)
    mets = image_metrics(disp, tnp)
    mets.update({
        "loss": float(terms["total"]),
        "loss_terms": {k2: float(v) for k2, v in terms.items()},
        "loss_before_discard": loss_all,
        "metrics_before_discard": metrics_all,
        "discarded": int((~keep).sum()),
        "kept": int(keep.sum()),
        "pairs_total": int(np.asarray(pairs.valid).sum()),
        "pairs_per_view": [int(c) for c in np.asarray(counts)[:m]],
        "coverage_pairs": (int(np.asarray(counts)[m]) if len(counts) > m
                           else int(np.asarray(pairs.valid).sum())),
        "rebins": state.rebins,
        "iterations": state.iteration,
        "time_total": time.perf_counter() - t_start,
        "time_first_step": step_times[0] if step_times else None,
        "time_step_median": float(np.median(step_times[1:])) if len(step_times) > 1 else None,
        "time_discard": t_discard,
        "intensity": [float(x) for x in inten],
    })
    return DesignResult(result_scratches, result_views, board, params, keep, rad, disp, tnp,
                        state.history, mets, config)


def _discard(params, pairs, ctx, caps, loss_all, tol, rad_all, terms_all):
    """Drop the lowest-scoring scratches while the loss stays within ``(1 + tol) loss_all``."""
    n = params.log_width.shape[0]
    lists, _, _ = _view_lists(params, pairs, ctx, caps)
    fps = R.pixel_footprints(ctx.board, params.geom.dtype)
    contrib = np.asarray(_contributions(params, lists, ctx, fps), np.float64)  # (M, N)
    mean = contrib.mean(axis=1, keepdims=True)
    score = (contrib / np.where(mean > 0, mean, 1.0)).max(axis=0)
    order = np.argsort(score, kind="stable")
    limit = loss_all * (1 + tol)

    def evaluate(k):
        keep = np.ones(n, bool)
        keep[order[:k]] = False
        rad, terms, _ = _evaluate(params, pairs, jnp.asarray(keep), ctx, caps)
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


# ----------------------------------------------------------------------------------------------
# Targets and outputs


def _to_gray01(img: np.ndarray, name: str) -> np.ndarray:
    from skimage.color import rgb2gray

    img = np.asarray(img)
    if img.ndim == 3 and img.shape[-1] == 4:
        img = img[..., :3]
    if img.ndim == 3 and img.shape[-1] == 3:
        if np.issubdtype(img.dtype, np.integer):
            img = img / float(np.iinfo(img.dtype).max)
        img = rgb2gray(img)
    elif img.ndim != 2:
        raise DesignError(f"target {name}: expected a grayscale or RGB(A) image, got shape {img.shape}")
    if img.dtype == bool:
        img = img.astype(np.float64)
    elif np.issubdtype(img.dtype, np.integer):
        img = img / float(np.iinfo(img.dtype).max)
    img = np.asarray(img, np.float64)
    if not np.all(np.isfinite(img)) or img.min() < 0 or img.max() > 1:
        raise DesignError(f"target {name}: float images must hold values in [0, 1]")
    return img


def _fit(img: np.ndarray, shape: tuple[int, int], name: str, crop: bool) -> np.ndarray:
    from skimage.transform import resize

    h, w = img.shape
    want = shape[1] / shape[0]
    if crop:
        if w / h > want:
            cw = int(round(h * want))
            img = img[:, (w - cw) // 2:(w - cw) // 2 + cw]
        else:
            ch = int(round(w / want))
            img = img[(h - ch) // 2:(h - ch) // 2 + ch]
    elif abs((w / h) / want - 1) > 0.02:
        raise DesignError(f"target {name} is {w}x{h} px (aspect {w / h:.3f}) but the board image is "
                          f"{shape[1]}x{shape[0]} (aspect {want:.3f}): crop it first")
    return np.clip(resize(img, shape, anti_aliasing=True), 0.0, 1.0)


def load_target(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """Read an image file as display values ``(H, W)`` in ``[0, 1]`` (grayscale, resized).

    RGB is converted with `skimage.color.rgb2gray`; an alpha channel is dropped; integer images
    are scaled by their dtype's maximum. The aspect ratio must match ``shape`` within 2 %.

    **Raises:** `DesignError` naming the file when it is missing, unreadable or mismatched.
    """
    from skimage import io

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise DesignError(f"target image {path!r} does not exist")
    try:
        img = io.imread(path)
    except Exception as e:  # noqa: BLE001 - any reader failure is an unreadable image
        raise DesignError(f"cannot read target image {path!r}: {type(e).__name__}: {e}") from None
    return _fit(_to_gray01(img, repr(path)), shape, repr(path), crop=False)


def default_targets(m: int, shape: tuple[int, int]) -> tuple[np.ndarray, list[str]]:
    """``m`` targets from `DEFAULT_IMAGES` (cycled), centre-cropped and resized to ``shape``."""
    from skimage import data

    names = [DEFAULT_IMAGES[j % len(DEFAULT_IMAGES)] for j in range(m)]
    imgs = [_fit(_to_gray01(getattr(data, n)(), n), shape, n, crop=True) for n in names]
    return np.stack(imgs), [f"skimage.data.{n}" for n in names]


def _png(path: str, img: np.ndarray) -> None:
    from skimage import io

    io.imsave(path, (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8), check_contrast=False)


def write_outputs(result: DesignResult, out: str | os.PathLike, extra_config: dict | None = None) -> None:
    """Write a result: ``design.npz`` + ``design.svg`` (SPEC section 9), ``view<j>_render.png``
    and ``view<j>_target.png``, ``comparison.png``, ``loss.png``, ``metrics.json`` and
    ``config.json`` (the `DesignConfig` plus `extra_config`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jscratch import designfile

    out = os.fspath(out)
    os.makedirs(out, exist_ok=True)
    s, v, b = result.scratches, result.views, result.board
    d = designfile.save_design(os.path.join(out, "design.npz"), np.asarray(s.p0), np.asarray(s.p1),
                               np.asarray(s.width), np.asarray(s.depth), np.asarray(s.alpha),
                               np.array([b.Sx, b.Sy]), np.asarray(v.camera), np.asarray(v.light),
                               np.asarray(v.intensity))
    designfile.write_svg(os.path.join(out, "design.svg"), d)
    m = result.targets.shape[0]
    for j in range(m):
        _png(os.path.join(out, f"view{j}_render.png"), result.display[j])
        _png(os.path.join(out, f"view{j}_target.png"), result.targets[j])
    fig, axes = plt.subplots(2, m, figsize=(3 * m, 6.4), squeeze=False)
    for j in range(m):
        axes[0, j].imshow(result.targets[j], cmap="gray", vmin=0, vmax=1)
        axes[0, j].set_title(f"target {j}")
        axes[1, j].imshow(np.clip(result.display[j], 0, 1), cmap="gray", vmin=0, vmax=1)
        mt = result.metrics
        axes[1, j].set_title(f"render {j}: SSIM {mt['ssim'][j]:.3f}, ghost {mt['ghosting'][j]:.3f}",
                             fontsize=8)
        for a in axes[:, j]:
            a.axis("off")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "comparison.png"), dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(np.arange(len(result.history["total"])), result.history["total"], label="total")
    for k, vals in result.history["terms"].items():
        ax.plot(np.arange(len(vals)), vals, "--", label=k)
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out, "loss.png"), dpi=100)
    plt.close(fig)

    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        return x

    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(clean(result.metrics), f, indent=2)
    cfg = {"design": result.config.to_dict(), "board": {"Sx": b.Sx, "Sy": b.Sy, "shape": list(b.shape)},
           "camera": np.asarray(v.camera).tolist(), "light": np.asarray(v.light).tolist(),
           **(extra_config or {})}
    with open(os.path.join(out, "config.json"), "w") as f:
        json.dump(cfg, f, indent=2)


# ----------------------------------------------------------------------------------------------
# Command line


def _parser() -> argparse.ArgumentParser:
    d = DesignConfig()
    p = argparse.ArgumentParser(
        prog="python -m jscratch.design",
        description="Optimise a scratch design so that a board shows one target image per view "
                    "(Shen et al. 2023). With no TARGET it uses skimage.data images "
                    f"({', '.join(DEFAULT_IMAGES)}).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("targets", nargs="*", metavar="TARGET",
                   help="target image files, one per view (grayscale or RGB; same aspect as the board)")
    p.add_argument("--views", type=int, default=None,
                   help="number of views M (default: number of targets, or 3)")
    p.add_argument("--theta-deg", type=float, default=50.0,
                   help="polar angle of the light and cameras from the board normal (degrees)")
    p.add_argument("--camera-theta-deg", type=float, default=None,
                   help="polar angle of the cameras (degrees; default --theta-deg)")
    p.add_argument("--distance", type=float, default=1.0, help="distance of light and cameras from the board centre (m)")
    p.add_argument("--offset-deg", type=float, default=None,
                   help="azimuth of camera 0 relative to the light (degrees; default keeps cameras away from the light's mirror direction)")
    p.add_argument("--board", type=float, default=0.3, help="board side (m), square board")
    p.add_argument("--size", type=int, default=256, help="image size (pixels per side)")
    p.add_argument("--scratches", type=int, default=d.n_scratches, help="number of scratches")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"Adam iterations (default {d.iterations}; with --resume, the saved value)")
    p.add_argument("--loss", choices=loss_mod.LOSS_KINDS, default=d.loss.kind, help="loss")
    p.add_argument("--lambda-p", type=float, default=1.0, help="weight of E_p (or of L2)")
    p.add_argument("--lambda-g", type=float, default=None,
                   help=f"weight of E_g (default {loss_mod.LAMBDA_G} for the filter bank)")
    p.add_argument("--vgg-weights", default=None, help="local VGG-19 .npz for E_g (scripts/convert_vgg19.py)")
    p.add_argument("--freeze", default=",".join(d.freeze),
                   help=f"comma-separated groups not optimised, from {','.join(GROUPS)}; 'none' for none")
    for g in GROUPS:
        p.add_argument(f"--lr-{g}", type=float, default=getattr(d, f"lr_{g}"),
                       help=f"learning rate of {g}")
    p.add_argument("--parameterisation", choices=PARAMETERISATIONS, default=d.parameterisation,
                   help="scratch position parameters")
    p.add_argument("--init-width", type=float, default=d.init_width, help="initial width w (m)")
    p.add_argument("--init-depth", type=float, default=d.init_depth, help="initial depth d (m)")
    p.add_argument("--init-alpha", type=float, default=d.init_alpha, help="initial roughness alpha")
    p.add_argument("--cull-eps", type=float, default=d.cull_eps, help="per-view pair culling tolerance (0: none, default; 1e-3 is ~2x faster but optimises worse)")
    p.add_argument("--coverage-eps", type=float, default=d.coverage_eps,
                   help="coverage-pass culling tolerance (0: none; faster but can lose contrast in dark regions)")
    p.add_argument("--no-discard", action="store_true", help="skip the discard step")
    p.add_argument("--discard-tol", type=float, default=d.discard_tol,
                   help="discard: allowed relative loss increase")
    p.add_argument("--seed", type=int, default=0, help="seed of the initial layout")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="working precision")
    p.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                   help="iterations between checkpoints")
    p.add_argument("--out", default="design_out", help="output folder")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.npz with OUT/config.json (other options ignored except --iterations, --quiet)")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    return p


def _run_cli(args) -> int:
    out = args.out
    cfg_path = os.path.join(out, "config.json")
    if args.resume:
        if not os.path.isfile(cfg_path):
            raise DesignError(f"--resume: no {cfg_path!r} (run without --resume first)")
        with open(cfg_path) as f:
            saved = json.load(f)
        cli = saved["cli"]
        config = DesignConfig.from_dict(saved["design"])
        if args.iterations is not None:
            config = dataclasses.replace(config, iterations=args.iterations)
    else:
        cli = {k: getattr(args, k) for k in ("targets", "views", "theta_deg", "camera_theta_deg",
                                              "distance", "offset_deg", "board", "size")}
        freeze = () if args.freeze.strip().lower() in ("", "none") else tuple(
            g.strip() for g in args.freeze.split(","))
        config = DesignConfig(
            n_scratches=args.scratches,
            iterations=100 if args.iterations is None else args.iterations,
            seed=args.seed, parameterisation=args.parameterisation,
            init_width=args.init_width, init_depth=args.init_depth, init_alpha=args.init_alpha,
            freeze=freeze, cull_eps=args.cull_eps, coverage_eps=args.coverage_eps,
            discard=not args.no_discard,
            discard_tol=args.discard_tol, checkpoint_every=args.checkpoint_every, dtype=args.dtype,
            loss=loss_mod.LossConfig(kind=args.loss, lambda_p=args.lambda_p, lambda_g=args.lambda_g,
                                     vgg_weights=args.vgg_weights),
            **{f"lr_{g}": getattr(args, f"lr_{g}") for g in GROUPS})
    if config.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    size = int(cli["size"])
    if size < 16:
        raise DesignError(f"--size must be at least 16 px, got {size}")
    shape = (size, size)
    if cli["targets"]:
        m = len(cli["targets"]) if cli["views"] is None else cli["views"]
        if m != len(cli["targets"]):
            raise DesignError(f"got {len(cli['targets'])} target images for --views {m}: give one per view")
        targets = np.stack([load_target(t, shape) for t in cli["targets"]])
        names = list(cli["targets"])
    else:
        m = 3 if cli["views"] is None else cli["views"]
        if m < 1:
            raise DesignError(f"--views must be >= 1, got {m}")
        targets, names = default_targets(m, shape)
    board = R.Board(shape=shape, Sx=cli["board"], Sy=cli["board"])
    ct = cli["camera_theta_deg"]
    try:
        views = R.views_on_circle(
            m, math.radians(cli["theta_deg"]), cli["distance"],
            None if cli["offset_deg"] is None else math.radians(cli["offset_deg"]), board,
            camera_theta=None if ct is None else math.radians(ct))
    except ValueError as e:
        raise DesignError(f"impossible view set-up: {e}") from None
    os.makedirs(out, exist_ok=True)
    if not args.resume:
        with open(cfg_path, "w") as f:
            json.dump({"design": config.to_dict(), "cli": cli, "targets": names}, f, indent=2)
    result = design(targets, views, board, config, checkpoint=os.path.join(out, "checkpoint.npz"),
                    resume=args.resume, progress=not args.quiet)
    write_outputs(result, out, {"cli": cli, "targets": names})
    if not args.quiet:
        mt = result.metrics
        print(f"wrote {out}: {mt['kept']} scratches ({mt['discarded']} discarded), loss "
              f"{mt['loss']:.5g}, SSIM {[round(x, 3) for x in mt['ssim']]}, PSNR "
              f"{[round(x, 2) for x in mt['psnr']]} dB, {mt['time_total']:.1f} s")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status (0 ok, 2 bad input, 3 non-finite)."""
    args = _parser().parse_args(argv)
    try:
        return _run_cli(args)
    except (ValueError, FileNotFoundError) as e:  # DesignError, and config errors (LossConfig)
        print(f"error: {e}", file=sys.stderr)
        return 2
    except NonFiniteError as e:
        print(f"error: {e}", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
