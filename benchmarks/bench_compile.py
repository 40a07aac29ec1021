"""What a default design compiles before its first step, and what the CPU compiler options of
`jscratch.compile_options` save there.

1. The default design's setup and initial state (`run.setup`, `run.initial_state` with its
   compile threads), wall and CPU time: run it under two code trees to compare them
   (``PYTHONPATH=DIR``, from a folder other than the repository's).
2. Every `few_calls_jit` function the setup, the first evaluation and the discard scores call:
   each lowered with the arguments of the run, then compiled alternately with XLA's defaults and
   with `grad_compiler_options`; medians of wall and CPU time. Then their run times with each
   (medians, after a first call that compiles).

    python benchmarks/bench_compile.py [--repeats 3]
"""

import argparse
import contextlib
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import native

try:
    from jscratch import compile_options
except ImportError:  # code from before `compile_options`: part 1 only
    compile_options = None
from jscratch.design import DesignConfig, default_targets
from jscratch.design import discard, run, solver


def clocks():
    return time.perf_counter(), time.process_time()


def since(start):
    w, c = clocks()
    return w - start[0], c - start[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    native.keep_freed_memory()
    native.prepare()
    cfg = DesignConfig()
    targets, _ = default_targets(3, (256, 256))
    recorder = compile_options.record_calls() if compile_options else contextlib.nullcontext([])
    with recorder as calls:  # (function, args, kwargs) as the run calls
        start = clocks()
        tnp, views, board = run.check_inputs(targets, None, None, cfg)
        params, adam, ctx = run.setup(tnp, views, board, cfg)
        setup = since(start)
        start = clocks()
        state, warm = run.initial_state(params, adam, ctx, tnp, cfg)
        warm.join()
        initial = since(start)
        keep = jnp.ones((cfg.n_scratches,), bool)
        jax.block_until_ready(solver.evaluate(state.params, state.lists, keep, ctx))
        discard.scores(state.params, state.lists, ctx)
    print(f"jscratch {run.__file__.rsplit('/jscratch/', 1)[0]}")
    print(f"setup: wall {setup[0]:.2f} s, CPU {setup[1]:.2f} s; initial state (compile threads "
          f"joined): wall {initial[0]:.2f} s, CPU {initial[1]:.2f} s")

    opts = compile_options.grad_compiler_options() if compile_options else {}
    if not opts:
        print("no compiler options here (backend or code): nothing to compare")
        return
    lowerings = {}
    for fn, a, k in calls:
        if fn.__name__ not in lowerings:
            lowerings[fn.__name__] = functools.partial(
                lambda fn, a, k: getattr(low := fn.jitted().lower(*a, **k), "lowered", low),
                fn, a, k)
    if not lowerings:
        print("no few_calls_jit function was called (code from before them): nothing to compare")
        return
    print(f"| function | compile, XLA defaults (wall / CPU s) | compile, {opts} (wall / CPU s) |")
    print("|---|---|---|")
    for name, lower in lowerings.items():
        t = {"default": [], "options": []}
        for _ in range(args.repeats):
            for key, o in (("default", {}), ("options", opts)):
                low = lower()
                jax.clear_caches()  # else jax hands back the executable it compiled before
                start = clocks()
                low.compile(o)
                t[key].append(since(start))
        d, o = (np.median(np.asarray(t[key]), axis=0) for key in ("default", "options"))
        print(f"| `{name}` | {d[0]:.2f} / {d[1]:.2f} | {o[0]:.2f} / {o[1]:.2f} |")
    print(f"\n| function | run, XLA defaults (ms) | run, {opts} (ms) |")
    print("|---|---|---|")
    seen = set()
    for fn, a, k in calls:
        if fn.__name__ in seen:
            continue
        seen.add(fn.__name__)
        jitted = {"default": fn.jitted(), "options": fn.jitted(opts)}
        t = {key: [] for key in jitted}
        for _ in range(args.repeats + 1):  # the first round compiles
            for key, f in jitted.items():
                start = time.perf_counter()
                jax.block_until_ready(f(*a, **k))
                t[key].append(time.perf_counter() - start)
        d, o = (1e3 * np.median(t[key][1:]) for key in ("default", "options"))
        print(f"| `{fn.__name__}` | {d:.1f} | {o:.1f} |")


if __name__ == "__main__":
    main()
