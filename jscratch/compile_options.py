"""XLA compiler options for jscratch's compiled functions, and `few_calls_jit`, the jit of a
function that a run calls only a few times (docs/architecture.md, "Compilation").

On the CPU, XLA's fusion emitters (its default) make forward passes a few per cent faster but
compile slower. With ``xla_cpu_use_fusion_emitters=False`` (`grad_compiler_options`):

- a render's value and gradient, the design step, compiles ~35 % faster and runs faster too;
- a forward pass runs 3-8 % slower (the default design's render and loss terms: 96.6 against
  93.4 ms; its discard scores: 77.5 against 71.8 ms) but compiles 25-50 % faster (the same: 1.53
  against 2.35 s, 0.24 against 0.32 s).

So the step (`jscratch.design.solver`) is compiled with these options, and so are the functions a
run calls once or a handful of times (`few_calls_jit`: the targets' Gram matrices and ghosting
baseline, the pair list's measurement, the evaluation and the discard scores), where the
compilation is most of their cost. Results differ from the default compilation by float32
rounding (other fusions, other orders of the same sums). Measured on 2 CPU cores, jax 0.10.1:
``benchmarks/RESULTS.md`` ("Compilation").

XLA takes compiler options only at the top level: a `few_calls_jit` function called inside
another jitted function (its arguments traced, or XLA refusing the options there) is compiled
there as a plain jit.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np

__all__ = ["FewCallsJit", "few_calls_jit", "grad_compiler_options", "record_calls"]


@functools.lru_cache(maxsize=None)
def grad_compiler_options() -> dict:
    """XLA compiler options for a jitted function that differentiates `render.render_pairs`, or
    that a run calls only a few times (pass them as ``jax.jit(f,
    compiler_options=grad_compiler_options())``; `few_calls_jit` does).

    On the CPU: ``xla_cpu_use_fusion_emitters=False`` (measured in the module docstring). Elsewhere,
    or where this XLA does not know the option (checked once by compiling a trivial function),
    ``{}``.
    """
    if jax.default_backend() != "cpu":
        return {}
    opts = {"xla_cpu_use_fusion_emitters": False}
    try:
        jax.jit(lambda x: x + 1).lower(np.float32(0)).compile(opts)
    except Exception:  # an XLA without this option: compile with the defaults
        return {}
    return opts


class FewCallsJit:
    """`few_calls_jit`'s callable: the jit with `grad_compiler_options` at the top level (made on
    first use: the options depend on the backend), the plain jit inside another trace."""

    def __init__(self, fn: Callable, jit: Callable):
        self._fn, self._jit = fn, jit
        self._made: dict[str, Callable] = {}  # "plain", "fast": one jit each, made once
        self._lock = threading.Lock()  # (a design calls and lowers from several threads)
        functools.update_wrapper(self, fn)

    def jitted(self, compiler_options: dict | None = None) -> Callable:
        """``fn`` jitted with these compiler options (none: the plain jit)."""
        if not compiler_options:
            return self._plain
        return self._jit(self._fn, compiler_options=compiler_options)

    def _get(self, which: str) -> Callable:
        """The ``"plain"`` jit, or the ``"fast"`` one (the plain one where there are no options)."""
        with self._lock:
            if which not in self._made:
                opts = grad_compiler_options() if which == "fast" else {}
                self._made[which] = (self._jit(self._fn, compiler_options=opts) if opts
                                     else self._made.get("plain") or self._jit(self._fn))
            return self._made[which]

    @property
    def _plain(self):
        return self._get("plain")

    @property
    def _fast(self):
        return self._get("fast")

    def __call__(self, *args, **kwargs):
        if _recording is not None:
            _recording.append((self, args, kwargs))
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs))):
            return self._plain(*args, **kwargs)
        try:
            return self._fast(*args, **kwargs)
        except ValueError as e:  # called inside a trace on constants only
            if "top-level" not in str(e):
                raise
            return self._plain(*args, **kwargs)

    def lower(self, *args, **kwargs):
        """The top-level jit's ``lower`` (``.compile()`` then fills its cache)."""
        return self._fast.lower(*args, **kwargs)


_recording: list | None = None


@contextlib.contextmanager
def record_calls():
    """Within the block, every call of a `few_calls_jit` function is appended to the list this
    yields as ``(function, args, kwargs)`` (`benchmarks/bench_compile.py` compiles them again)."""
    global _recording
    outer, _recording = _recording, []
    try:
        yield _recording
    finally:
        _recording = outer


def few_calls_jit(fn: Callable | None = None, *, filter: bool = False, **jit_kwargs):
    """``jax.jit(fn, **jit_kwargs)`` (or ``eqx.filter_jit(fn)`` with ``filter=True``) compiled
    with `grad_compiler_options` when called at the top level: for functions a run calls a few
    times, whose compilation costs more than their runs. Usable as a decorator, with or without
    arguments; the result has ``lower`` as a jitted function does."""
    if fn is None:
        return functools.partial(few_calls_jit, filter=filter, **jit_kwargs)
    if filter:
        if jit_kwargs:
            raise TypeError("few_calls_jit(filter=True) takes no jax.jit arguments")
        return FewCallsJit(fn, eqx.filter_jit)
    return FewCallsJit(fn, functools.partial(jax.jit, **jit_kwargs))
