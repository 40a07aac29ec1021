"""Where one step of the default design goes: the render forward, the render value + VJP, the loss
value + gradient and a host rebin, timed apart on the default scene (3 views, 20k scratches,
256x256, unculled, initial layout). Medians of 3 after a warm-up.

    python benchmarks/bench_design_step.py
"""

import math
import os
import sys
import time

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from jscratch import loss as L  # noqa: E402
from jscratch import render as R  # noqa: E402
from jscratch.bench_render import _median_time  # noqa: E402
from jscratch.design import default_targets  # noqa: E402

board = R.Board(shape=(256, 256))
s = R.Scratches.random(jax.random.PRNGKey(0), 20000, board, length=(0.005, 0.025),
                       width=2.5e-4, depth=1.28e-4, alpha=0.04, dtype=jnp.float32)
v = R.views_on_circle(3, math.radians(50), 1.0, None, board)
pairs = R.bin_pairs(s, board)
print("pairs", int(pairs.valid.sum()))
t, _ = default_targets(3, (256, 256))
bound = L.make_loss(L.LossConfig()).bind(jnp.asarray(t, jnp.float32))


def rend(s, v):
    return R.render_pairs(s, v, board, pairs)


f_fwd = jax.jit(rend)
f_vjp = jax.jit(lambda s, v: jax.vjp(rend, s, v)[1](jnp.ones((3, 256, 256), jnp.float32)))
disp = jnp.asarray(R.display(f_fwd(s, v)))
f_loss = jax.jit(jax.value_and_grad(lambda d: bound.terms(d)["total"]))
for name, fn in (("render forward", lambda: f_fwd(s, v)),
                 ("render value + VJP", lambda: f_vjp(s, v)),
                 ("loss value + gradient", lambda: f_loss(disp))):
    print(f"{name}: {_median_time(fn, 3):.3f} s")
t0 = time.perf_counter()
R.bin_pairs(s, board)
print(f"rebin (host): {time.perf_counter() - t0:.3f} s")
