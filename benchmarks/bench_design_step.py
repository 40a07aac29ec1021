"""Where one step of the default design goes: the render forward, the render value + VJP, the loss
value + gradient (and of each of its terms) and a host rebin, timed apart on the default scene
(3 views, 20k scratches, 256x256, unculled, initial layout). Medians of 3 after a warm-up. The
bound loss is an argument of the jitted functions, as in the design step.

    python benchmarks/bench_design_step.py
"""

import math
import time

import jax
import jax.numpy as jnp


from jscratch import loss
from jscratch import render
from jscratch.bench.rendering import time_median
from jscratch.design import default_targets

board = render.Board(shape=(256, 256))
s = render.Scratches.random(jax.random.PRNGKey(0), 20000, board, length=(0.005, 0.025),
                       width=2.5e-4, depth=1.28e-4, alpha=0.04, dtype=jnp.float32)
v = render.views_on_circle(3, math.radians(50), 1.0, None, board)
pairs = render.bin_pairs(s, board)
print("pairs", int(pairs.valid.sum()))
t, _ = default_targets(3, (256, 256))
bound = loss.make_loss(loss.LossConfig()).bind(jnp.asarray(t, jnp.float32))


def rend(s, v):
    return render.render_pairs(s, v, board, pairs)


f_fwd = jax.jit(rend)
f_vjp = jax.jit(lambda s, v: jax.vjp(rend, s, v)[1](jnp.ones((3, 256, 256), jnp.float32)))
disp = jnp.asarray(render.display(f_fwd(s, v)))


def loss_vg(term):
    return jax.jit(lambda b, d: jax.value_and_grad(lambda d: b.terms(d)[term])(d))


f_loss = {term: loss_vg(term) for term in ("total", "E_p", "E_g", "E_x")}
for name, fn in (("render forward", lambda: f_fwd(s, v)),
                 ("render value + VJP", lambda: f_vjp(s, v)),
                 ("loss value + gradient", lambda: f_loss["total"](bound, disp)),
                 *((f"  the loss's {t} alone", lambda t=t: f_loss[t](bound, disp))
                   for t in ("E_p", "E_g", "E_x"))):
    print(f"{name}: {time_median(fn, 3):.3f} s")
t0 = time.perf_counter()
render.bin_pairs(s, board)
print(f"rebin (host): {time.perf_counter() - t0:.3f} s")
