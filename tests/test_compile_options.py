"""`jscratch.compile_options`: the options, and `few_calls_jit` at the top level, nested in
another jit (where XLA refuses compiler options) and lowered ahead of time."""

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
