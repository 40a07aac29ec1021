"""`jscratch.compile_options`: the options, and `few_calls_jit` at the top level, nested in
another jit (where XLA refuses compiler options) and lowered ahead of time."""

import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch.compile_options import few_calls_jit, grad_compiler_options, record_calls


def _f(x, k):
    return jnp.sin(x) * k + jnp.cumsum(x)


def test_options_on_cpu_turn_the_fusion_emitters_off():
    opts = grad_compiler_options()
    if jax.default_backend() == "cpu":
        assert opts == {"xla_cpu_use_fusion_emitters": False}
        # and this XLA accepts them
        jax.jit(lambda x: x * 2).lower(np.float32(1)).compile(opts)
    else:
        assert opts == {}


@pytest.mark.parametrize("filter", [False, True])
def test_top_level_nested_and_lowered_calls_agree_with_jit(filter):
    x = jnp.linspace(0.0, 3.0, 257, dtype=jnp.float32)
    if filter:
        fast = few_calls_jit(filter=True)(_f)
        ref = eqx.filter_jit(_f)
        k = 2.5  # a Python float: static under filter_jit
    else:
        fast = few_calls_jit(_f, static_argnums=1)
        ref = jax.jit(_f, static_argnums=1)
        k = 2.5
    want = np.asarray(ref(x, k), np.float64)
    # top level: the options; the sums may round differently, nothing else
    np.testing.assert_allclose(np.asarray(fast(x, k)), want, rtol=1e-6, atol=1e-5)
    # nested in a jit with a traced argument, and on a closed-over constant: the plain jit
    nested = jax.jit(lambda y: fast(y, k) + 1.0)
    np.testing.assert_allclose(np.asarray(nested(x)), want + 1.0, rtol=1e-6, atol=1e-5)
    const = jax.jit(lambda y: fast(x, k) + y)
    np.testing.assert_allclose(np.asarray(const(1.0)), want + 1.0, rtol=1e-6, atol=1e-5)
    # ahead of time, as the design warms its caches
    compiled = fast.lower(x, k).compile()
    np.testing.assert_allclose(np.asarray(compiled(x) if not filter else compiled(x, k)), want,
                               rtol=1e-6, atol=1e-5)
    assert fast.__name__ == "_f" and fast.__doc__ == _f.__doc__


def test_filter_variant_refuses_jit_arguments():
    with pytest.raises(TypeError, match="filter=True"):
        few_calls_jit(_f, filter=True, static_argnums=1)


def test_other_errors_pass_through():
    bad = few_calls_jit(lambda x: x.reshape(7))
    with pytest.raises(TypeError):
        bad(jnp.ones(5))


def test_record_calls_lists_the_calls_and_jitted_compiles_them_again():
    fast = few_calls_jit(_f, static_argnums=1)
    x = jnp.arange(4.0)
    with record_calls() as calls:
        fast(x, 3.0)
        with record_calls() as inner:
            fast(x, 4.0)
        fast(x, 5.0)
    fast(x, 6.0)  # outside: not recorded
    assert [c[1][1] for c in calls] == [3.0, 5.0] and [c[1][1] for c in inner] == [4.0]
    fn, a, k = calls[0]
    for opts in (None, grad_compiler_options()):
        out = fn.jitted(opts).lower(*a, **k).compile()(a[0])
        np.testing.assert_allclose(np.asarray(out), np.asarray(_f(x, 3.0)), rtol=1e-6)


# The suite compiles with XLA's fusion emitters off (tests/conftest.py), as the design's step and
# `few_calls_jit` do; a process with XLA's default flags renders the same to float32 rounding.
_RENDER_SCRIPT = r'''
import sys
import jax, jax.numpy as jnp, numpy as np
from jscratch import native, render
from jscratch.scene import Board, Scratches, views_on_circle

rng = np.random.default_rng(5)
board = Board(shape=(24, 24), Sx=0.02, Sy=0.02)
n = 60
mid = rng.uniform(0.004, 0.016, (n, 2))
phi = rng.uniform(0, np.pi, n)
t = np.stack([np.cos(phi), np.sin(phi)], -1) * rng.uniform(0.001, 0.004, (n, 1))
weights = jnp.asarray(rng.uniform(0, 1, (2, 24, 24)), jnp.float32)
views = views_on_circle(2, 0.8, distance=0.3, board=board, dtype=jnp.float32)
out = {}
for profile in ("paper",):
    s = Scratches(jnp.asarray(mid - t, jnp.float32), jnp.asarray(mid + t, jnp.float32),
                  width=jnp.asarray(rng.uniform(1.5e-4, 4e-4, n), jnp.float32),
                  depth=jnp.asarray(rng.uniform(0.5e-4, 2e-4, n), jnp.float32),
                  alpha=jnp.asarray(rng.uniform(0.05, 0.3, n), jnp.float32), profile=profile)
    pairs = render.bin_pairs(s, board)
    for on in (True, False):
        with native.override(enabled=on):
            def f(s):
                rad = render.render_pairs(s, views, board, pairs)
                return jnp.sum(weights * rad), rad
            (_, rad), g = jax.jit(jax.value_and_grad(f, has_aux=True))(s)
        key = f"{profile}_{int(on)}"
        out[key + "_rad"] = np.asarray(rad)
        for name in ("p0", "p1", "width", "depth", "alpha"):
            out[f"{key}_d{name}"] = np.asarray(getattr(g, name))
np.savez(sys.argv[1], **out)
'''


def _render_in_process(path, xla_flags):
    env = dict(os.environ, XLA_FLAGS=xla_flags)
    r = subprocess.run([sys.executable, "-c", _RENDER_SCRIPT, str(path)], env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def test_xla_default_flags_render_what_the_suite_checks(tmp_path):
    """Value and gradient of `render_pairs` (native and jnp paths) compiled with XLA's default
    flags, against the suite's flags: within float32 rounding (1e-5 of each array's largest
    entry; measured: 0 on the native path, 2e-7 on the jnp path)."""
    suite = _render_in_process(tmp_path / "suite.npz", "--xla_cpu_use_fusion_emitters=false")
    default = _render_in_process(tmp_path / "default.npz", "")
    assert sorted(suite) == sorted(default)
    for k, a in suite.items():
        b = default[k]
        scale = np.max(np.abs(b))
        assert scale > 0, k
        assert np.max(np.abs(a - b)) <= 1e-5 * scale, (k, np.max(np.abs(a - b)) / scale)
