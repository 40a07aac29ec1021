"""Tests of `jscratch.render` (the multi-view renderer), against independent references.

Independent references: the float64 all-pairs dense sum (`render_reference`, no binning, no custom
VJP), the brute-force supersampler (real groove geometry, no analytic integral), float64 central
finite differences, and the unsharded result for the 4-device run. Compilations are kept few: every
scene of one kind shares its shapes, and the jitted functions are module-level.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import arc, brute, bvh, native, ndf
from jscratch import render
from jscratch.errors import InputError

BOARD = render.Board(shape=(10, 10), Sx=0.01, Sy=0.01)  # 1 mm pixels


def _scene(dtype=jnp.float64, seed=4):
    """12 scratches of mixed width/depth/alpha on a 1 cm board, 3 close views (half vectors vary
    across the board); one scratch runs exactly along a row of pixel edges."""
    rng = np.random.default_rng(seed)
    n = 12
    mid = rng.uniform(0.002, 0.008, (n, 2))
    phi = rng.uniform(0, 2 * np.pi, n)
    half = rng.uniform(0.001, 0.004, n)[:, None]
    t = np.stack([np.cos(phi), np.sin(phi)], -1)
    p0, p1 = np.clip(mid - half * t, 0, 0.01), np.clip(mid + half * t, 0, 0.01)
    p0[0], p1[0] = [0.0015, 0.004], [0.0085, 0.004]  # along the pixel edge y = 4 mm
    width = rng.uniform(1.5e-4, 4e-4, n)
    depth = rng.uniform(0.5e-4, 2e-4, n)
    alpha = rng.uniform(0.05, 0.5, n)
    s = render.Scratches(jnp.asarray(p0, dtype), jnp.asarray(p1, dtype), jnp.asarray(width, dtype),
                    jnp.asarray(depth, dtype), jnp.asarray(alpha, dtype))
    v = render.views_on_circle(3, 0.6, 0.05, board=BOARD, intensity=jnp.asarray([1.0, 1.5, 0.7]),
                          dtype=dtype)
    return s, v


# Test-only compiler options: the pair kernel's compilation dominates this file's run time and
# LLVM optimisation buys nothing on scenes this small (same results, 3x faster compiles).
FAST = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}

# Pairs per chunk of the reference and gradient tests: small enough that the test scene's pairs,
# sorted by class, fill chunks needing different piece budgets (see
# `test_gradient_tests_run_several_piece_budgets`), so every kernel variant is checked.
CHUNK = 32

_ref = jax.jit(lambda s, v: render.render_reference(s, v, BOARD), compiler_options=FAST)
_fwd = jax.jit(lambda s, v, pairs: render.render_pairs(s, v, BOARD, pairs, chunk=CHUNK),
               compiler_options=FAST)


@functools.lru_cache(maxsize=None)
def _reference():
    s, v = _scene()
    return np.asarray(_ref(s, v))


CAPACITY = 1024  # every test scene's pair list is padded to this, so compilations are shared


def _pairs(s):
    """The scene's complete pair list from `bvh.build_pairs`, compacted into CAPACITY slots."""
    full, _ = bvh.build_pairs(s.p0, s.p1, s.width, s.depth, board=(BOARD.Sx, BOARD.Sy),
                              shape=BOARD.shape)
    ok = np.asarray(full.valid)
    k = int(ok.sum())
    assert 0 < k <= CAPACITY
    pix = np.zeros(CAPACITY, np.int32)
    scr = np.full(CAPACITY, s.n, np.int32)
    pix[:k], scr[:k] = np.asarray(full.pixel)[ok], np.asarray(full.scratch)[ok]
    return bvh.Pairs(jnp.asarray(pix), jnp.asarray(scr), jnp.asarray(np.arange(CAPACITY) < k),
                     jnp.asarray(False))


def _rel(out, ref):
    out, ref = np.asarray(out, np.float64), np.asarray(ref, np.float64)
    return float(np.max(np.abs(out - ref) / np.abs(ref)))


# --------------------------------------------------------------------------------------------
# Forward model


@pytest.mark.float64
def test_matches_all_pairs_reference_f64_and_f32():
    ref = _reference()
    assert ref.shape == (3, 10, 10) and np.all(ref > 0)
    s64, v64 = _scene(jnp.float64)
    out64 = _fwd(s64, v64, _pairs(s64))
    assert out64.dtype == jnp.float64
    assert _rel(out64, ref) <= 1e-6
    s32, v32 = _scene(jnp.float32)
    out32 = _fwd(s32, v32, _pairs(s32))
    assert out32.dtype == jnp.float32
    assert _rel(out32, ref) <= 1e-3
    # The scratches matter: the scene without them differs by far more than the tolerance.
    empty = _pairs(s64)
    bare = _fwd(s64, v64, eqx.tree_at(lambda p: p.valid, empty, jnp.zeros_like(empty.valid)))
    assert _rel(bare, ref) > 0.5


@pytest.mark.float64
def test_culled_per_view_lists_within_cull_bound():
    s, v = _scene()
    eps = 0.05
    full = _fwd(s, v, _pairs(s))
    out, pairs, cov_pairs = render.render(s, v, BOARD, eps=eps, return_pairs=True)
    n_full = int(np.asarray(cov_pairs.valid).sum())
    n_kept = np.asarray(pairs.valid).sum(-1)
    assert np.all(n_kept < n_full)  # the culling removed pairs in every view
    # D_P drops by at most eps * sum_i A_i / (pi alpha_i^2 S_P); shading is linear in D_P.
    fps = render.pixel_footprints(BOARD)
    pix = np.asarray(cov_pairs.pixel)[np.asarray(cov_pairs.valid)]
    scr = np.asarray(cov_pairs.scratch)[np.asarray(cov_pairs.valid)]
    _, A = jax.vmap(lambda f, i: ndf.pair_integral(jnp.asarray([0.0, 0.0, 1.0]), f, s.p0[i],
                                                   s.p1[i], s.width[i], s.depth[i], s.alpha[i]))(
        fps[pix], scr)
    bound = np.zeros(BOARD.n_pixels)
    np.add.at(bound, pix, eps * np.asarray(A) / (np.pi * np.asarray(s.alpha)[scr] ** 2))
    bound /= BOARD.pixel_area
    cov = np.zeros((1, BOARD.n_pixels))
    per_D = np.asarray(render.shade(jnp.ones((3, BOARD.n_pixels)), jnp.asarray(cov), v, BOARD)
                       - render.shade(jnp.zeros((3, BOARD.n_pixels)), jnp.asarray(cov), v, BOARD))
    diff = np.asarray(full - out).reshape(3, -1)
    rounding = 1e-12 * np.abs(np.asarray(full)).reshape(3, -1)
    assert np.all(diff >= -rounding)
    assert np.all(diff <= per_D * bound[None] * (1 + 1e-9) + rounding)
    assert np.max(diff) > 0


@pytest.mark.float64
def test_skipped_pair_views_within_the_bound_on_every_path():
    """``skip_eps``: the radiance drops by at most ``skip_eps`` times the pixel's mirror-peak
    term (``sum A / (pi alpha^2 S_P)``, docs/model.md §11) and never rises; the gradient is the
    exact gradient of that skipped radiance (central differences); one device with the native
    kernel, the jnp path and 4 sharded devices give the same values and gradients; per-view
    lists or a tolerance outside [0, 1] are refused in one line."""
    s, v = _scene()
    pairs = _pairs(s)
    wts = _loss_weights(jnp.float64)
    eps = 0.05

    def objective(sv, mesh=None, p=pairs):
        rad = render.render_pairs(*sv, BOARD, p, chunk=CHUNK, mesh=mesh, skip_eps=eps)
        return jnp.sum(wts * rad) / rad.size, rad

    vg = jax.jit(jax.value_and_grad(objective, has_aux=True), static_argnames="mesh",
                 compiler_options=FAST)
    out = {}
    for on in ((True, False) if native.available(jnp.float64) else (False,)):
        with native.override(enabled=on):
            out[on] = vg((s, v))
    (val, rad), grads = out[False]
    for (val1, rad1), grads1 in out.values():
        np.testing.assert_allclose(np.asarray(rad1), np.asarray(rad), rtol=0,
                                   atol=1e-12 * float(np.max(np.abs(rad))))
        for a, b in zip(jax.tree_util.tree_leaves(grads1), jax.tree_util.tree_leaves(grads)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0,
                                       atol=1e-10 * float(np.max(np.abs(b))))
    # The bound, per pixel, over the pixel's pairs.
    full = np.asarray(_fwd(s, v, pairs)).reshape(3, -1)
    ok = np.asarray(pairs.valid)
    pix, scr = np.asarray(pairs.pixel)[ok], np.asarray(pairs.scratch)[ok]
    fps = render.pixel_footprints(BOARD)
    _, A = jax.vmap(lambda f, i: ndf.pair_integral(jnp.asarray([0.0, 0.0, 1.0]), f, s.p0[i],
                                                   s.p1[i], s.width[i], s.depth[i], s.alpha[i]))(
        fps[pix], scr)
    peak = np.bincount(pix, np.asarray(A) / (np.pi * np.asarray(s.alpha)[scr] ** 2),
                       minlength=BOARD.n_pixels) / BOARD.pixel_area
    cov = jnp.zeros((1, BOARD.n_pixels))
    per_D = np.asarray(render.shade(jnp.ones((3, BOARD.n_pixels)), cov, v, BOARD)
                       - render.shade(jnp.zeros((3, BOARD.n_pixels)), cov, v, BOARD))
    diff = full - np.asarray(rad).reshape(3, -1)
    rounding = 1e-12 * np.abs(full)
    assert np.all(diff >= -rounding)
    assert np.all(diff <= eps * per_D * peak[None] * (1 + 1e-9) + rounding)
    assert np.sum(diff > rounding) > 10  # pair-views were skipped
    # The gradient is that of the skipped radiance: central differences in an endpoint direction.
    d = jnp.asarray(np.random.default_rng(1).normal(size=(12, 2)) * 1e-4)
    at = lambda t: float(vg((eqx.tree_at(lambda m: m.p0, s, s.p0 + t * d), v))[0][0])  # noqa
    fd = (at(1e-4) - at(-1e-4)) / 2e-4
    assert abs(float(jnp.sum(grads[0].p0 * d)) - fd) <= 1e-5 * abs(fd)
    # Four devices (the suite's forced CPU devices), the list laid out for them.
    if len(jax.devices()) >= 4:
        mesh = jax.sharding.Mesh(np.array(jax.devices()[:4]), ("p",))
        p4 = render.bin_pairs(s, BOARD, shards=4)
        (_, rad4), grads4 = vg((s, v), mesh=mesh, p=p4)
        np.testing.assert_allclose(np.asarray(rad4), np.asarray(rad), rtol=0,
                                   atol=1e-12 * float(np.max(np.abs(rad))))
        for a, b in zip(jax.tree_util.tree_leaves(grads4), jax.tree_util.tree_leaves(grads)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0,
                                       atol=1e-10 * float(np.max(np.abs(b))))
    with pytest.raises(InputError, match="skip_eps > 0 needs one pair list shared"):
        render.render_pairs(s, v, BOARD, [pairs] * 3, pairs, skip_eps=eps)
    with pytest.raises(InputError, match=r"skip_eps must be a float in \[0, 1\]"):
        render.render_pairs(s, v, BOARD, pairs, skip_eps=1.5)


@pytest.mark.float64
def test_brute_force_agrees_to_sampling_error():
    s, v = _scene()
    ana = np.asarray(_fwd(s, v, _pairs(s))).reshape(3, -1)
    sums = jax.jit(lambda key: brute.brute_sums(s, v, BOARD, n=12, key=key),
                   compiler_options=FAST)
    runs = [sums(jax.random.PRNGKey(k)) for k in range(8)]
    D = np.stack([np.asarray(r[0]) for r in runs])  # (K, M, P)
    c = np.stack([np.asarray(r[1]) for r in runs])  # (K, P)
    rad = np.stack([np.asarray(brute.brute_shade(jnp.asarray(Dk), jnp.asarray(ck)[None], v,
                                                 BOARD)) for Dk, ck in zip(D, c)])
    K = rad.shape[0]
    mean, se = rad.mean(0), rad.std(0, ddof=1) / math.sqrt(K)
    sampled = se > 1e-9 * np.abs(mean)
    assert sampled.sum() > 30  # many pixels see grooves
    z2 = ((mean - ana) / np.where(sampled, se, 1)) ** 2
    # Pooled test: for an unbiased estimator mean(z^2) ~ (K-1)/(K-3) = 1.4; a 2% bias would give >100.
    assert float(z2[sampled].mean()) < 3.0
    # Pixels no sample of any key saw a groove in: the analytic value may add only slivers.
    assert np.allclose(mean[~sampled], ana[~sampled], rtol=1e-3)
    # And the sampling error itself is small, so the agreement means something.
    assert float(np.median((se / ana)[sampled])) < 0.05


# --------------------------------------------------------------------------------------------
# Gradients


def _loss_weights(dtype):
    return jax.random.normal(jax.random.PRNGKey(7), (3, 10, 10), dtype)


def _objective(sv, pairs, weights, mesh=None):
    s, v = sv
    rad = render.render_pairs(s, v, BOARD, pairs, chunk=CHUNK, mesh=mesh)
    return jnp.sum(weights * rad) / rad.size, rad


# One compilation per (dtype, mesh): ((loss, radiance), (d/dscratches, d/dviews)).
_vg = jax.jit(lambda sv, pairs, weights, mesh=None: jax.value_and_grad(
    _objective, has_aux=True)(sv, pairs, weights, mesh), static_argnames="mesh",
    compiler_options=FAST)


def _stress_scene(dtype):
    """Scratches on pixel edges and corners, zero length, board edges and corners, overlapping
    twins, the smallest and largest alpha, very wide/shallow and narrow/deep; a grazing camera,
    a grazing light and a camera straight above."""
    p0 = np.array([[0.001, 0.003], [0.002, 0.002], [0.005, 0.005], [0.0, 0.001], [0.004, 0.0],
                   [0.0031, 0.0062], [0.006, 0.001], [0.007, 0.007], [0.003, 0.008],
                   [0.0005, 0.0005], [0.0, 0.0], [0.0005, 0.0005]])
    p1 = np.array([[0.009, 0.003], [0.006, 0.006], [0.005, 0.005], [0.0, 0.009], [0.004, 0.01],
                   [0.0089, 0.0062], [0.006, 0.009], [0.0072, 0.0071], [0.008, 0.008],
                   [0.0095, 0.0095], [0.003, 0.002], [0.0095, 0.0095]])
    width = np.array([2e-4, 2e-4, 2e-4, 3e-4, 1e-4, 1e-3, 5e-5, 2e-4, 2e-4, 2e-4, 2e-4, 2e-4])
    depth = np.array([1e-4, 1e-4, 1e-4, 2e-4, 1e-4, 1e-6, 5e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4])
    alpha = np.array([0.04, 1e-4, 0.3, 0.04, 0.99, 0.04, 0.04, 1e-3, 0.9, 0.04, 0.04, 0.04])
    s = render.Scratches(*(jnp.asarray(x, dtype) for x in (p0, p1, width, depth, alpha)))
    camera = np.array([[0.005, -1.0, 0.02], [0.005, 0.005, 0.5], [0.8, 0.005, 0.3]])
    light = np.array([[-1.0, 0.005, 0.3], [0.005, 1.0, 0.01], [0.005, -0.8, 0.4]])
    v = render.Views(jnp.asarray(camera, dtype), jnp.asarray(light, dtype), jnp.asarray(1.0, dtype))
    return s, v


def _check_stress(dtype):
    s, v = _stress_scene(dtype)
    (val, rad), (gs, gv) = _vg((s, v), _pairs(s), _loss_weights(dtype))
    assert np.isfinite(float(val)) and bool(jnp.all(jnp.isfinite(rad)))
    for g in jax.tree_util.tree_leaves((gs, gv)):
        assert g.dtype == dtype and bool(jnp.all(jnp.isfinite(g)))
    # The zero-length scratch (index 2) has no groove: zero gradient, not NaN.
    assert float(jnp.abs(gs.width[2]) + jnp.abs(gs.alpha[2]) + jnp.abs(gs.p0[2]).sum()) == 0.0
    # Scratches that do show get nonzero gradients.
    assert float(jnp.abs(gs.p0[0]).sum()) > 0 and float(jnp.abs(gs.alpha[1])) > 0


@pytest.mark.float64
def test_gradients_f64_match_finite_differences():
    """float64: gradients of a scalar loss (through the custom VJP) against central finite
    differences of the forward renderer."""
    s, v = _scene()
    pairs = _pairs(s)
    wts = _loss_weights(jnp.float64)
    (val, rad), (gs, gv) = _vg((s, v), pairs, wts)
    rng = np.random.default_rng(0)
    directions = {  # (which, field, direction), displacements in natural units
        "p0": (0, "p0", rng.normal(size=(12, 2)) * 1e-4),
        "p1": (0, "p1", rng.normal(size=(12, 2)) * 1e-4),
        "width": (0, "width", rng.normal(size=12) * np.asarray(s.width) * 0.3),
        "depth": (0, "depth", rng.normal(size=12) * np.asarray(s.depth) * 0.3),
        "alpha": (0, "alpha", rng.normal(size=12) * np.asarray(s.alpha) * 0.3),
        "intensity": (1, "intensity", rng.normal(size=3)),
        "camera": (1, "camera", rng.normal(size=(3, 3)) * 1e-3),
        "light": (1, "light", rng.normal(size=(3, 3)) * 1e-3),
    }
    step = 1e-4
    for name, (which, field, d) in directions.items():
        d = jnp.asarray(d)

        def at(t):  # the loss by the forward-only renderer (no VJP involved)
            sv = [s, v]
            sv[which] = eqx.tree_at(lambda m: getattr(m, field), sv[which],
                                    getattr(sv[which], field) + t * d)
            return float(jnp.sum(wts * _fwd(*sv, pairs)) / wts.size)

        fd = (at(step) - at(-step)) / (2 * step)
        ad = float(jnp.sum(getattr((gs, gv)[which], field) * d))
        assert abs(fd) > 1e-6 * abs(float(val)), name
        assert abs(ad - fd) <= 1e-5 * abs(fd), (name, ad, fd)


@pytest.mark.float64
def test_sharded_equals_single_device_and_f64_stress_gradients_finite():
    """The pixel axis sharded over 4 (forced CPU) devices: same radiance and gradients as on one
    (the pair list laid out for 4 pixel blocks by `bin_pairs`); and float64 gradients are finite
    on the stress scene (same compilation)."""
    _check_stress(jnp.float64)
    s, v = _scene()
    pairs = _pairs(s)
    wts = _loss_weights(jnp.float64)
    (val, rad), (gs, gv) = _vg((s, v), pairs, wts)
    assert len(jax.devices()) >= 4
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()[:4]), ("d",))
    pairs4 = render.bin_pairs(s, BOARD, shards=4, chunk=64)
    (val4, rad4), g4 = _vg((s, v), pairs4, wts, mesh)
    np.testing.assert_allclose(np.asarray(rad4), np.asarray(rad), rtol=1e-12)
    for a, b in zip(jax.tree_util.tree_leaves(g4), jax.tree_util.tree_leaves((gs, gv))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10,
                                   atol=1e-12 * float(jnp.max(jnp.abs(b))))


@pytest.mark.float64
def test_sharded_per_view_lists_and_layout_check():
    """Culled per-view lists (M, L) with the unculled coverage list, over 2 x 2 devices (10 rows:
    3 per shard, the pixel axis padded) and over 2 devices: equal to the unsharded render, and
    over 2 devices the output comes back split into row strips; a list not laid out for the
    mesh's pixel blocks is refused with an error that says how to build one (NaN under jit)."""
    s, v = _scene()
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()[:4]).reshape(2, 2), ("a", "b"))
    full1 = render.bin_pairs(s, BOARD, chunk=64)
    full4 = render.bin_pairs(s, BOARD, chunk=64, shards=4)
    cull1 = render.cull_pairs(full1, s, v, BOARD, 1e-2, chunk=64)
    cull4 = render.cull_pairs(full4, s, v, BOARD, 1e-2, chunk=64, shards=4)
    # culling removed pairs in some view, so this is not the shared-list path again
    assert int(cull1.valid.sum()) < 3 * int(full1.valid.sum())
    f = jax.jit(lambda s, v, p, c, mesh=None: render.render_pairs(s, v, BOARD, p, c, chunk=64,
                                                            mesh=mesh),
                static_argnames="mesh", compiler_options=FAST)
    rad1 = f(s, v, cull1, full1)
    rad4 = f(s, v, cull4, full4, mesh=mesh)
    np.testing.assert_allclose(np.asarray(rad4), np.asarray(rad1), rtol=1e-12)
    # Over 2 devices (5 rows each) the radiance comes back split into row strips.
    mesh2 = jax.sharding.Mesh(np.asarray(jax.devices()[:2]), ("d",))
    rad2 = f(s, v, render.cull_pairs(full1, s, v, BOARD, 1e-2, chunk=64, shards=2),
             render.bin_pairs(s, BOARD, chunk=64, shards=2), mesh=mesh2)
    np.testing.assert_allclose(np.asarray(rad2), np.asarray(rad1), rtol=1e-12)
    assert sorted(x.data.shape for x in rad2.addressable_shards) == [(3, 5, 10)] * 2
    # A list not laid out for the mesh: eagerly a ValueError; under jit NaN radiance (a runtime
    # error on one device of a multi-device program would hang the others).
    with pytest.raises(ValueError, match=r"not laid out for 4 pixel shards.*shards=4"):
        render.render_pairs(s, v, BOARD, cull1, full4, chunk=64, mesh=mesh)
    assert bool(jnp.all(jnp.isnan(f(s, v, cull1, full4, mesh=mesh))))
    with pytest.raises(ValueError, match="not a multiple of the 4"):
        render.render_pairs(s, v, BOARD, bvh.Pairs(full1.pixel[:-1], full1.scratch[:-1],
                                              full1.valid[:-1], full1.overflow), mesh=mesh)


@pytest.mark.float64
def test_gradient_tests_run_chunks_with_several_piece_budgets():
    """On the jnp path (`test_native_pair_kernel_equals_jnp_path`, and every test where the
    native kernel is unavailable) the scene's pairs, sorted by class (`render._sort_pairs`), fill
    chunks of `CHUNK` with the smallest piece budget (`render.PIECE_BUDGETS`) and chunks with a
    larger one, so every budget's branch is checked."""
    s, v = _scene()
    pairs = _pairs(s)
    cfg = render._Cfg(BOARD.H, BOARD.W, BOARD.Sx, BOARD.Sy, CHUNK, None, (), BOARD.n_pixels, False,
                      True, True, "paper")
    params = (s.p0, s.p1, s.width, s.depth, s.alpha)
    klass = render._pair_classes(cfg, params, pairs.pixel, pairs.scratch, pairs.valid)
    _, _, valid = render._sort_pairs(pairs.pixel, pairs.scratch, pairs.valid, klass, 1)
    klass = np.sort(np.asarray(klass))  # the sorted order: classes 1, 2, 3, then padding (0)
    klass = np.concatenate([klass[klass > 0], klass[klass == 0]])
    assert np.array_equal(klass > 0, np.asarray(valid))
    groups = {int(klass[i:i + CHUNK].max()) for i in range(0, klass.shape[0], CHUNK)}
    assert 1 in groups and len(groups - {0, 1}) >= 1, groups


@pytest.mark.skipif(not native.available(jnp.float32),
                    reason=f"native kernel unavailable: {native.status()['why']}")
@pytest.mark.float64
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_native_pair_kernel_equals_jnp_path(dtype):
    """`render_pairs`' value and VJP with the chunks evaluated by the native whole-pair kernel
    and by the jnp path (``JSCRATCH_NATIVE=0``): a shared pair list, and per-view lists with the
    coverage from the shared one. float64: 1e-12 of the radiance's scale, gradients 1e-10 of
    each gradient's largest entry; float32: 1e-5 and 3e-5 (rounding of the two paths)."""
    s, v = _scene(dtype)
    pairs = _pairs(s)
    wts = _loss_weights(dtype)
    tol_v, tol_g = (1e-12, 1e-10) if dtype == jnp.float64 else (1e-5, 3e-5)

    def objective(sv, per_view):
        p, cov = ([pairs] * 3, pairs) if per_view else (pairs, None)
        rad = render.render_pairs(*sv, BOARD, p, cov, chunk=CHUNK)
        return jnp.sum(wts * rad), rad

    for per_view in (False, True):
        out = {}
        for on in (True, False):
            with native.override(enabled=on):
                f = jax.jit(jax.value_and_grad(lambda sv: objective(sv, per_view), has_aux=True),
                            compiler_options=FAST)
                out[on] = f((s, v))
        (_, r1), g1 = out[True]
        (_, r0), g0 = out[False]
        r1, r0 = np.asarray(r1, np.float64), np.asarray(r0, np.float64)
        assert np.max(np.abs(r1 - r0)) <= tol_v * np.max(np.abs(r0)), per_view
        for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g0)):
            a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
            assert np.max(np.abs(b)) > 0
            assert np.max(np.abs(a - b)) <= tol_g * np.max(np.abs(b)), (per_view, a.shape)


def test_gradients_f32_finite_on_stress_scene():
    _check_stress(jnp.float32)


# --------------------------------------------------------------------------------------------
# Memory


def test_gradient_memory_does_not_grow_with_pairs(monkeypatch):
    """Compiled temp memory of a gradient step at fixed chunk, on the path that re-evaluates
    pairs in the reverse pass (the jnp path; the native kernel does the same on a mesh): 16x the
    pairs may add only the integer pair list (a few bytes per pair), where plain autodiff of an
    all-pairs vmap keeps the kernel's intermediates for every pair. The kernel is swapped for a
    cheap stand-in with many intermediates so the two compilations stay fast; the memory design
    does not depend on it. With the native kernel on one device the step keeps each pair's
    Jacobians instead: ``(10 M + 6)`` floats a pair, and not more."""

    def kernel(cfg, xe, ye, p0, p1, w, d, a, h, pix):
        z = jnp.sum(p1 - p0) * h[2] + w * d / a + xe[pix % 3]
        for _ in range(12):
            z = jnp.sin(z) * w + jnp.exp(-z * z)
        return z, jnp.cos(z)

    class Geometry(NamedTuple):  # the renderer's two kernel stages, with the same stand-in
        area: jax.Array
        z: jax.Array

    def geometry(cfg, xe, ye, pix, valid, p0, p1, w, d):
        z = jnp.sum(p1 - p0, axis=-1) + w * d + xe[pix % 3]
        for _ in range(12):
            z = jnp.sin(z) * w + jnp.exp(-z * z)
        return Geometry(jnp.where(valid, jnp.cos(z), 0), z), jnp.int32(0)

    def lit(profile, pieces, g, valid, a, h):
        z = g.z[None] * h[..., 2] / a
        for _ in range(12):
            z = jnp.sin(z) * a + jnp.exp(-z * z)
        return jnp.where(valid[None], z, 0)

    monkeypatch.setattr(render, "_chunk_geometry", geometry)
    monkeypatch.setattr(render, "_chunk_lit", lit)
    s, v = _scene(jnp.float32)
    wts = _loss_weights(jnp.float32)

    def naive(sv, pix, scr):
        s, _ = sv
        g = lambda x: x[scr]
        D, A = jax.vmap(functools.partial(kernel, None, jnp.ones(3), None))(
            g(s.p0), g(s.p1), g(s.width), g(s.depth), g(s.alpha),
            jnp.ones((pix.shape[0], 3)), pix)
        return jnp.sum(jax.ops.segment_sum(D + A, pix, 100) ** 2)

    def temp_bytes(L, use_native=False):
        rng = np.random.default_rng(L)
        pix = jnp.asarray(rng.integers(0, 100, L), jnp.int32)
        scr = jnp.asarray(rng.integers(0, 12, L), jnp.int32)
        pairs = bvh.Pairs(pix, scr, jnp.ones(L, bool), jnp.asarray(False))
        ours = jax.jit(jax.grad(lambda sv: _objective(sv, pairs, wts)[0]), compiler_options=FAST)
        base = jax.jit(jax.grad(naive), compiler_options=FAST)
        mem = lambda f, *a: f.lower(*a).compile().memory_analysis().temp_size_in_bytes
        with native.override(enabled=use_native):
            return mem(ours, (s, v)), mem(base, (s, v), pix, scr)

    L1, L2 = 2048, 32768
    (o1, n1), (o2, n2) = temp_bytes(L1), temp_bytes(L2)
    per_pair_ours, per_pair_naive = (o2 - o1) / (L2 - L1), (n2 - n1) / (L2 - L1)
    assert per_pair_naive > 100  # the measurement sees per-pair residuals when there are any
    assert per_pair_ours < 40, per_pair_ours
    if native.available(jnp.float32):
        (j1, _), (j2, _) = temp_bytes(L1, True), temp_bytes(L2, True)
        jac = (10 * v.m + 6) * 4
        assert jac <= (j2 - j1) / (L2 - L1) < jac + 40


# --------------------------------------------------------------------------------------------
# Errors


@pytest.mark.float64
def test_errors_name_the_argument():
    with pytest.raises(ValueError, match="`p1` must have shape"):
        render.Scratches(jnp.zeros((3, 2)), jnp.zeros((3, 3)))
    with pytest.raises(ValueError,
                       match=r"Scratches: scratch 1: alpha = 1.0 must lie in \[0.0001, 0.99\]"):
        render.Scratches(jnp.zeros((2, 2)), jnp.ones((2, 2)), alpha=jnp.asarray([0.1, 1.0]))
    with pytest.raises(ValueError, match="Scratches: scratch 1: width = nan is not finite"):
        render.Scratches(jnp.zeros((2, 2)), jnp.ones((2, 2)), width=jnp.asarray([1e-4, jnp.nan]))
    with pytest.raises(ValueError, match="Views: view 0: camera is at z"):
        render.Views(jnp.asarray([[0.0, 0.0, -1.0]]), jnp.asarray([[0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="`shape` must be"):
        render.Board(shape=(0, 4))
    s, v = _scene()
    with pytest.raises(InputError, match="render_pairs: `views` must be a jscratch.Views, got Board"):
        render.render_pairs(s, BOARD, v, _pairs(s))
    with pytest.raises(InputError, match="render: `board` must be a jscratch.Board, got NoneType"):
        render.render(s, v, None)
    with pytest.raises(InputError, match="render_reference: `scratches` must be a jscratch.Scr"):
        render.render_reference(None, v, BOARD)
    bad = eqx.tree_at(lambda p: p.overflow, _pairs(s), jnp.asarray(True))
    with pytest.raises(Exception, match="overflowed its capacity"):
        jax.block_until_ready(_fwd(s, v, bad))


def test_unchecked_render_is_the_checked_one_without_its_errors():
    """``checked=False`` (what the design step runs) gives the checked render's bits on a valid
    scene, and under jit neither a non-finite width nor an overflowed list raises there: the
    NaN reaches the radiance, as the caller's own checks expect."""
    s, v = _scene(jnp.float32)
    pairs = _pairs(s)
    unchecked = jax.jit(lambda s, v, p: render.render_pairs(s, v, BOARD, p, chunk=CHUNK,
                                                            checked=False),
                        compiler_options=FAST)
    np.testing.assert_array_equal(np.asarray(unchecked(s, v, pairs)),
                                  np.asarray(_fwd(s, v, pairs)))
    nan_w = eqx.tree_at(lambda t: t.width, s, s.width.at[3].set(jnp.nan))
    with pytest.raises(Exception, match="scratch width is not finite"):
        jax.block_until_ready(_fwd(nan_w, v, pairs))
    assert np.isnan(np.asarray(unchecked(nan_w, v, pairs))).any()
    bad = eqx.tree_at(lambda p: p.overflow, pairs, jnp.asarray(True))
    assert np.all(np.isfinite(np.asarray(unchecked(s, v, bad))))


# --------------------------------------------------------------------------------------------
# The ball's arc profile (`Scratches.profile == "arc"`, docs/model.md §13)

R_BALL = 1.25e-4  # m


def _arc_scene(dtype=jnp.float64, seed=4):
    """`_scene`'s scratches as ball cuts of radius `R_BALL` at plunges 0.05 R .. 0.95 R."""
    s, v = _scene(dtype, seed)
    plunge = np.random.default_rng(seed + 1).uniform(0.05, 0.95, s.n) * R_BALL
    w, d = arc.arc_groove(jnp.asarray(plunge, dtype), jnp.asarray(R_BALL, dtype))
    return render.Scratches(s.p0, s.p1, jnp.broadcast_to(w, (s.n,)), d, s.alpha,
                            profile="arc"), v


@pytest.mark.float64
def test_arc_profile_matches_reference_and_brute_force():
    """Arc grooves: `render_pairs` (native kernel where built) against the float64 all-pairs
    reference (`arc.arc_lit_integral`, plain jnp), and against the brute-force supersampler of the
    real arc (its normals from ``x / R``; no analytic integral): unbiased to sampling error. The
    paper profile with the same ``(w, d)`` renders visibly differently (the test can fail)."""
    s, v = _arc_scene()
    ref = np.asarray(_ref(s, v))
    out64 = _fwd(s, v, _pairs(s))
    assert _rel(out64, ref) <= 1e-6
    s32, v32 = _arc_scene(jnp.float32)
    assert _rel(_fwd(s32, v32, _pairs(s32)), ref) <= 1e-3
    paper = render.Scratches(s.p0, s.p1, s.width, s.depth, s.alpha)
    assert _rel(_fwd(paper, v, _pairs(paper)), ref) > 0.05
    sums = jax.jit(lambda key: brute.brute_sums(s, v, BOARD, n=12, key=key), compiler_options=FAST)
    rad = []
    for k in range(8):
        D, c = sums(jax.random.PRNGKey(k))
        rad.append(np.asarray(brute.brute_shade(D, c[None], v, BOARD)))
    rad = np.stack(rad)
    mean, se = rad.mean(0), rad.std(0, ddof=1) / math.sqrt(rad.shape[0])
    ana = ref.reshape(3, -1)
    sampled = se > 1e-9 * np.abs(mean)
    assert sampled.sum() > 30
    z2 = ((mean - ana) / np.where(sampled, se, 1)) ** 2
    assert float(z2[sampled].mean()) < 3.0  # (K-1)/(K-3) = 1.4 for an unbiased estimate
    assert float(np.median((se / ana)[sampled])) < 0.05


@pytest.mark.float64
def test_arc_profile_gradients_match_finite_differences_and_jnp_path():
    """Arc grooves, float64: the renderer's gradients (native kernel where built) against central
    finite differences of the forward renderer, and the native kernel against the jnp path."""
    s, v = _arc_scene()
    pairs = _pairs(s)
    wts = _loss_weights(jnp.float64)
    (val, _), (gs, _) = _vg((s, v), pairs, wts)
    rng = np.random.default_rng(1)
    for field, d in (("p0", rng.normal(size=(12, 2)) * 1e-4), ("p1", rng.normal(size=(12, 2)) * 1e-4),
                     ("depth", rng.normal(size=12) * np.asarray(s.depth) * 0.2),
                     ("alpha", rng.normal(size=12) * np.asarray(s.alpha) * 0.3)):
        d = jnp.asarray(d)

        def at(t):
            moved = eqx.tree_at(lambda m: getattr(m, field), s, getattr(s, field) + t * d)
            return float(jnp.sum(wts * _fwd(moved, v, pairs)) / wts.size)

        fd = (at(1e-4) - at(-1e-4)) / 2e-4
        ad = float(jnp.sum(getattr(gs, field) * d))
        assert abs(fd) > 1e-6 * abs(float(val)), field
        assert abs(ad - fd) <= 1e-5 * abs(fd), (field, ad, fd)
    if native.available(jnp.float64):
        with native.override(enabled=False):
            (_, r0), (g0, _) = jax.jit(jax.value_and_grad(_objective, has_aux=True),
                                       compiler_options=FAST)((s, v), pairs, wts)
        (_, r1), (g1, _) = _vg((s, v), pairs, wts)
        assert np.max(np.abs(np.asarray(r1) - np.asarray(r0))) <= 1e-12 * np.max(np.abs(r0))
        for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g0)):
            assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b))


@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_an_end_exactly_on_a_pixel_corner_has_the_gradient_of_its_neighbourhood(profile):
    """A scratch ending exactly on a pixel corner: the pixel beyond the end holds only that
    point of the groove (area 0, no gradient); its clipped boundary is one point whose ends move
    differently, which once gave the end a spurious gradient (about (2/3)(p1 - p0) per pair,
    36 of 460 here). The gradient on the corner equals the one 1e-7 m away (where nothing is
    degenerate), by both kernels."""
    board = render.Board(shape=(16, 16), Sx=0.01, Sy=0.01)
    v = render.Views(np.float32([[0.005, -0.5, 0.8]]), np.float32([[0.5, 0.005, 0.8]]))
    corner = np.array([0.005, 0.00625])  # a pixel corner

    def scratch(p1):
        return render.Scratches(np.float32([[0.0025, 0.0025]]), np.float32([p1]), 2.5e-4,
                                1.28e-4, 0.04, profile=profile)

    # One list for both: the pairs of a slightly longer scratch (the pixel beyond the end too).
    pairs = render.bin_pairs(scratch(corner + [1e-6, 1.5e-6]), board)
    for enabled in (True, False):
        with native.override(enabled=enabled):
            grad = jax.jit(jax.grad(lambda s: jnp.sum(render.render_pairs(s, v, board, pairs))),
                           compiler_options=FAST)
            near = np.asarray(grad(scratch(corner - [1e-7, 0.0])).p1[0], np.float64)
            on = np.asarray(grad(scratch(corner)).p1[0], np.float64)
            np.testing.assert_allclose(on, near, rtol=2e-3)


def test_render_pairs_refuses_a_list_binned_for_other_scratches():
    """Called eagerly, `render_pairs` refuses a `bin_pairs` list binned for another number of
    scratches, or for scratches that have since moved beyond it (its pairs would be wrong, with
    every index in range); the list's own scratches render as `render` does."""
    from jscratch.bvh import bin_pairs
    from jscratch.render import Board, Scratches, render_pairs, views_on_circle

    board = Board(shape=(16, 16))
    views = views_on_circle(2, board=board)
    s50 = Scratches.random(jax.random.PRNGKey(0), 50, board=board)
    s80 = Scratches.random(jax.random.PRNGKey(1), 80, board=board)
    pairs = bin_pairs(s50, board)
    np.testing.assert_allclose(render_pairs(s50, views, board, pairs),
                               render.render(s50, views, board), rtol=1e-5, atol=0)
    with pytest.raises(InputError, match=r"^render_pairs: `pairs` was binned for 50 scratches, "
                                         r"got 80"):
        render_pairs(s80, views, board, pairs)
    moved = eqx.tree_at(lambda s: s.p1, s50, s50.p0 + 0.5 * (s50.p1 - s50.p0))
    moved = eqx.tree_at(lambda s: s.p0, moved, s80.p0[:50])
    with pytest.raises(InputError, match=r"^render_pairs: `pairs` may miss pairs of these"):
        render_pairs(moved, views, board, pairs)
    with pytest.raises(InputError, match=r"^render_pairs: `coverage_pairs` may miss pairs"):
        render_pairs(s50, views, board, pairs, coverage_pairs=bin_pairs(moved, board))
    big = Board(shape=(32, 32))  # the same scratches (in metres) on a finer image
    with pytest.raises(InputError, match=r"^render_pairs: `pairs` was binned for another board: "
                                         r"\d+ of its \d+ pairs lie outside their grooves on "
                                         r"this 32x32 board"):
        render_pairs(s50, views_on_circle(2, board=big), big, pairs)
    np.testing.assert_allclose(render_pairs(s50, views_on_circle(2, board=big), big,
                                            bin_pairs(s50, big)),
                               render.render(s50, views_on_circle(2, board=big), big), rtol=1e-5)
