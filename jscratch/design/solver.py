"""The jitted pieces of the optimisation: the per-design `Context`, the pair lists culled for the
current parameters (`view_lists`, a `bvh.PairLists`), the forward `evaluate`, one Adam `step`
with its health report and the per-scratch `contributions`. Module level, so that repeated designs
of the same shapes reuse compilations. Tests drive a step through these names."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
import optax
from jaxtyping import Array

from jscratch import bvh
from jscratch import loss as loss_mod
from jscratch.compile_options import few_calls_jit, grad_compiler_options
from jscratch.contributions import scratch_contributions
from jscratch.render import render_pairs
from jscratch.scene import SCRATCH_RULES, Board, Views
from jscratch.shading import display
from jscratch.design.config import GROUPS
from jscratch.design.params import DesignParams
from jscratch.design import mesh as mesh_mod


class Context(eqx.Module):
    """Per-design constants of the jitted functions."""

    camera: Array
    light: Array
    hs: Array  # (M, P, 3) half vectors
    board_ndf: Array  # (P,) flat board's GGX at each pixel, largest over the views (1/sr)
    loss: loss_mod.BoundLoss
    lrs: DesignParams  # per-group learning rate (0 = frozen), scalar leaves
    board: Board = eqx.field(static=True)
    chunk: int = eqx.field(static=True)
    # The `jax.sharding.Mesh` the image work is split over (`jscratch.design.mesh`), or None.
    mesh: Any = eqx.field(static=True, default=None)
    # The step's pair-view skipping tolerance (`render.render_pairs`' ``skip_eps``).
    skip_eps: float = eqx.field(static=True, default=0.0)


@functools.lru_cache(maxsize=None)
def make_adam(b1: float, b2: float, eps: float, decay_steps: int = 0,
              final_fraction: float = 1.0) -> optax.GradientTransformation:
    """Adam's scaling (``optax.scale_by_adam``); `_step_impl` then scales each group by its own
    ``-lr`` (``Context.lrs``, 0 for a frozen group, whose gradient is zeroed first). Cached: the
    same object for the same constants, so jit caches hit across designs. With ``decay_steps > 0``
    the steps are also scaled by ``optax.cosine_decay_schedule(1, decay_steps, final_fraction)``
    (every group's learning rate falls from its value to ``final_fraction`` of it).

    (``optax.multi_transform`` with ``optax.set_to_zero()`` computes the same update, but its
    different compiled step changes the default design's loss by ~1e-7 relative after a few
    iterations and ~3e-3 after 100: kept as is so that results stay identical.)"""
    adam = optax.scale_by_adam(b1=b1, b2=b2, eps=eps)
    if decay_steps > 0:
        sched = optax.cosine_decay_schedule(1.0, decay_steps, alpha=final_fraction)
        return optax.chain(adam, optax.scale_by_schedule(sched))
    return adam


def view_lists(params: DesignParams, lists: bvh.PairLists, ctx: Context) -> bvh.PairLists:
    """`lists` culled for ``params`` (`bvh.update_lists` at the lists' fixed capacities; its
    ``overflow`` / ``counts > caps`` means the caller retries after `bvh.grow_lists`)."""
    s = jax.lax.stop_gradient(params).scratches()
    return bvh.update_lists(lists, s, ctx.hs, ctx.board_ndf)


#: One pair in this many is counted for the pair-views a skipping step evaluates.
COUNT_STRIDE = 16


def _kept_counts(params: DesignParams, lists: bvh.PairLists, ctx: Context) -> Array:
    """Per view, the pair-views of the shared list that ``ctx.skip_eps`` keeps (`cull.view_keep`:
    what the step's renderer evaluates), ``(M,)`` int32, estimated from every `COUNT_STRIDE`-th
    slot (counting them all took ~5 % of a default step)."""
    s = jax.lax.stop_gradient(params).scratches()
    pix, scr, valid = (x[::COUNT_STRIDE] for x in (lists.shared.pixel, lists.shared.scratch,
                                                   lists.shared.valid))
    i = jnp.clip(scr, 0, s.n - 1)
    h = ctx.hs[:, jnp.clip(pix, 0, ctx.hs.shape[1] - 1)]
    keep = bvh.view_keep(h, s.p0[i], s.p1[i], s.width[i], s.depth[i], s.alpha[i], ctx.skip_eps,
                          s.profile)
    share = jnp.sum(keep & valid[None], axis=1) / jnp.maximum(jnp.sum(valid), 1)
    return jnp.round(share * jnp.sum(lists.shared.valid)).astype(jnp.int32)


def radiance(params: DesignParams, lists: bvh.PairLists, ctx: Context, *,
             skip: bool = False) -> Array:
    """Radiance ``(M, H, W)`` from `view_lists`' culled lists; with `skip`, the pair-views below
    ``ctx.skip_eps`` skipped (shared lists only: per-view lists are culled already). Without the
    renderer's traced checks (``checked=False``): the setup draws valid scratches, a resumed
    checkpoint is checked when it is read, and every step checks what it updates (`_health`)."""
    views = Views(ctx.camera, ctx.light, params.intensity())
    skip_eps = ctx.skip_eps if skip and not lists.culled else 0.0
    rad = render_pairs(params.scratches(), views, ctx.board, *lists.for_render(), chunk=ctx.chunk,
                       mesh=ctx.mesh, checked=False, skip_eps=skip_eps)
    # (on a mesh: the small images gathered, so the loss runs replicated, not split into strips)
    return mesh_mod.replicated(rad, ctx.mesh)


def _masked(lists: bvh.PairLists, keep_ext: Array) -> bvh.PairLists:
    """`lists` without the pairs of scratches outside ``keep_ext`` (``(N + 1,)``)."""
    mask = lambda p: eqx.tree_at(lambda q: q.valid, p, p.valid & keep_ext[p.scratch])  # noqa: E731
    return dataclasses.replace(
        lists, shared=mask(lists.shared),
        views=None if lists.views is None else tuple(mask(p) for p in lists.views),
        coverage=None if lists.coverage is None else mask(lists.coverage))


def _on_mesh(params: DesignParams, lists: bvh.PairLists, ctx: Context) -> bvh.PairLists:
    """`lists` laid out for ``ctx.mesh`` (`mesh.shard_lists`; as they are without a mesh). On a
    mesh every argument of the jitted functions is put there (`mesh.place`) so that one
    compilation serves every call."""
    return mesh_mod.shard_lists(lists, ctx.mesh, ctx.board, ctx.chunk, params.log_width.shape[0])


def evaluate(params: DesignParams, lists: bvh.PairLists, keep: Array, ctx: Context):
    """Forward only: ``(radiance (M,H,W), loss terms, per-list counts)`` with scratches outside
    ``keep`` removed (their pairs masked, so they neither shine nor cover). On a mesh the lists
    are laid out for it first and the results are replicated."""
    params, keep = mesh_mod.place((params, keep), ctx.mesh)
    return _evaluate(params, _on_mesh(params, lists, ctx), keep, ctx)


@few_calls_jit(filter=True)
def _evaluate(params: DesignParams, lists: bvh.PairLists, keep: Array, ctx: Context):
    keep_ext = jnp.concatenate([keep, jnp.zeros((1,), bool)])
    culled = view_lists(params, lists, ctx)
    rad = radiance(params, _masked(culled, keep_ext), ctx)
    return mesh_mod.replicated((rad, ctx.loss.terms(display(rad)), culled.counts), ctx.mesh)


def _health(loss, grads: DesignParams, new: DesignParams) -> dict[str, Array]:
    """Per check: ``(ok, first bad index)``; names the parameter group that went wrong."""
    out = {"loss": (jnp.isfinite(loss), jnp.asarray(-1))}
    s = new.scratches()
    phys = {"endpoints": jnp.concatenate([s.p0, s.p1], 1), "width": s.width, "depth": s.depth,
            "alpha": s.alpha, "intensity": new.intensity()}
    ranges = {name: ok for name, (ok, _) in SCRATCH_RULES.items()}
    ranges["intensity"] = lambda x: x >= 0
    for g in GROUPS:
        gr, val = grads.group(g), phys[g]
        good_g = jnp.isfinite(gr).reshape(gr.shape[0], -1).all(-1)
        good_v = jnp.isfinite(val).reshape(val.shape[0], -1).all(-1) & jnp.isfinite(
            new.group(g)).reshape(val.shape[0], -1).all(-1)
        if g in ranges:
            good_v = good_v & ranges[g](val)
        # The barrier keeps XLA from folding the check of a gradient that autodiff made a
        # constant zero (on the jnp path: the depth of carvable grooves) at compile time: on a
        # GPU, folding that argmin took 1.5 s of the step's compilation at 80,000 scratches.
        good_g, good_v = lax.optimization_barrier((good_g, good_v))
        out[f"gradient of {g}"] = (jnp.all(good_g), jnp.argmin(good_g))
        out[f"updated {g}"] = (jnp.all(good_v), jnp.argmin(good_v))
    return out


def step(params: DesignParams, opt_state, lists: bvh.PairLists, ctx: Context, adam):
    """`_step_impl`, jitted with `compile_options.grad_compiler_options` (faster compile and
    step)."""
    params, opt_state = mesh_mod.place((params, opt_state), ctx.mesh)  # (once: then in place)
    return _jitted_step()(params, opt_state, _on_mesh(params, lists, ctx), ctx, adam)


def compile_step(params: DesignParams, opt_state, lists: bvh.PairLists, ctx: Context, adam):
    """Compile `step` for these arguments' shapes without running it: the jit cache is then warm
    and the first `step` call only runs. The design calls it on a second thread while the setup
    renders (XLA compiles without holding the GIL), so the two compilations overlap. Returns
    the compiled step (its ``memory_analysis`` sizes the run: `jscratch.design.run`)."""
    return lower_step(params, opt_state, lists, ctx, adam).compile()


def lower_step(params: DesignParams, opt_state, lists: bvh.PairLists, ctx: Context, adam):
    """`step` lowered for these arguments (on ``ctx.mesh`` as `step` runs it): ``.compile()``
    gives equinox's executable, whose ``.compiled.as_text()`` shows the collectives of a step."""
    params, opt_state = mesh_mod.place((params, opt_state), ctx.mesh)
    return _jitted_step().lower(params, opt_state, _on_mesh(params, lists, ctx), ctx, adam)


@functools.lru_cache(maxsize=None)
def _jitted_step():
    return eqx.filter_jit(_step_impl, compiler_options=grad_compiler_options())


def _step_impl(params: DesignParams, opt_state, lists: bvh.PairLists, ctx: Context, adam):
    """One Adam iteration (`make_adam`, then ``-lr`` per group). Returns the new parameters and
    Adam state, the loss terms at ``params``, the pair lists for the new parameters, whether their
    shared list was rebuilt, the per-list counts (to detect capacity overflow) and the health
    report.

    The shared list is rebuilt inside the step, only when a groove left the envelope it was binned
    with (`bvh.needs_rebin`, then `grid.update` at the same capacities under a `lax.cond`): no
    host round trip, and a step that needs no rebuild does no binning. When the rebuilt list
    overflows its capacities (``lists.shared.overflow``), the host rebuilds it with larger ones
    (`bvh.rebin_lists`)."""
    culled = view_lists(params, lists, ctx)
    if ctx.skip_eps > 0 and not culled.culled:  # (the counts: the pair-views evaluated)
        culled = dataclasses.replace(culled, counts=_kept_counts(params, culled, ctx))

    def f(p):
        terms = ctx.loss.terms(display(radiance(p, culled, ctx, skip=True)))
        return terms["total"], terms

    (value, terms), grads = eqx.filter_value_and_grad(f, has_aux=True)(params)
    frozen = jax.tree_util.tree_map(lambda lr: lr == 0, ctx.lrs)
    grads = jax.tree_util.tree_map(lambda g, fr: jnp.where(fr, 0, g), grads, frozen)
    updates, opt_state = adam.update(grads, opt_state, params)
    updates = jax.tree_util.tree_map(lambda u, lr: (-lr * u).astype(u.dtype), updates, ctx.lrs)
    new = eqx.apply_updates(params, updates)
    s = new.scratches()
    # Non-finite or out-of-range values are reported by the health check (and the host stops);
    # here they are replaced, so the binning's own runtime checks are left out (``checked``):
    # the step then holds no host callback, and a persistent compilation cache can keep it.
    ok = lambda x: jnp.isfinite(x) & (x > 0)
    p0 = jnp.where(jnp.isfinite(s.p0), s.p0, 0)
    p1 = jnp.where(jnp.isfinite(s.p1), s.p1, 0)
    w = jnp.where(ok(s.width), s.width, 1e-4)
    d = jnp.where(ok(s.depth), s.depth, 1e-4)
    rebin = bvh.needs_rebin(lists.shared, p0, p1, w, d, checked=False)
    new_lists = None  # on a mesh the host rebuilds and lays out the list (`mesh.shard_lists`)
    if ctx.mesh is None:
        shared = jax.lax.cond(rebin, lambda: bvh.update(lists.spec, p0, p1, w, d, checked=False),
                              lambda: lists.shared)
        new_lists = dataclasses.replace(lists, shared=shared, views=None, coverage=None)
    return mesh_mod.replicated((new, opt_state, terms, new_lists, rebin, culled.counts,
                                _health(value, grads, new)), ctx.mesh)


@eqx.filter_jit
def physical(params: DesignParams):
    s = params.scratches()
    return s.p0, s.p1, s.width, s.depth, s.alpha, params.intensity()


@eqx.filter_jit
def contributions(params: DesignParams, lists: bvh.PairLists, ctx: Context) -> Array:
    """`contributions.scratch_contributions` of the design's scene, ``(M, N)``, from `view_lists`'
    culled lists."""
    views = Views(ctx.camera, ctx.light, params.intensity())
    return mesh_mod.replicated(
        scratch_contributions(params.scratches(), views, ctx.board, lists.for_render()[0],
                              chunk=ctx.chunk, h=ctx.hs), ctx.mesh)
