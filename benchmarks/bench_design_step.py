"""Where one step of the default design goes, on the design's own state: `run.setup` and
`run.initial_state` with the command line's defaults (3 views, 20,000 scratches, 256 px, carvable
grooves rendered as the ball's arc, no culling), then after ``--warm`` chained steps (the grooves
have grown a little, as in a design):

- the whole step (`solver.step`: render, loss, gradient, Adam, the in-step rebin check), chained;
- the render forward and its value + gradient with respect to the parameters (the pair kernel);
- the loss's value + gradient on the rendered image, whole and per term;
- a rebuild of the shared pair list (`run.rebin`, what a step that moved a groove runs).

Medians of ``--repeats`` calls after a first call that compiles. One process: the parts are timed
apart, so they do not add up to the step exactly (XLA fuses across them inside the step).

    python benchmarks/bench_design_step.py [--scratches N] [--views M] [--size PX]
        [--groove-fit arc|height] [--warm 10] [--repeats 9]

``--groove-fit height`` renders the grooves as the paper's profile fitted to the ball's arc;
``JSCRATCH_NATIVE=0`` times the jnp path (what runs where the native kernel cannot be built).
"""

import argparse
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jscratch import native
from jscratch.bench import machine_line
from jscratch.bench.rendering import design_step_state
from jscratch.design import DesignConfig
from jscratch.design import run, solver
from jscratch.machine import MachineProfile
from jscratch.render import display


def median_s(fn, repeats):
    """Median wall time [s] of ``fn()`` over ``repeats`` calls, after one call that compiles."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scratches", type=int, default=20000)
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--groove-fit", choices=("arc", "height"), default="arc",
                    help="the groove a carvable design renders (docs/model.md §13)")
    ap.add_argument("--warm", type=int, default=10, help="steps taken before the timing")
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    print(machine_line())
    machine = dict(MachineProfile().to_dict(), groove_fit=args.groove_fit)
    cfg = DesignConfig(n_scratches=args.scratches, machine=machine)
    p, opt, lists, ctx, adam = design_step_state(cfg, args.views, args.size, args.warm)
    pairs = int(np.asarray(lists.shared.valid).sum())
    print(f"{args.views} views, {args.scratches} scratches, {args.size} px, {cfg.groove} grooves "
          f"({cfg.machine_profile().groove_fit}), after {args.warm} steps: {pairs:,} pairs, "
          f"kernel {native.status()['kernel']}; medians of {args.repeats} [ms]")

    chain = {"p": p, "opt": opt, "lists": lists}

    def one_step():  # chained, as the design runs them
        out = solver.step(chain["p"], chain["opt"], chain["lists"], ctx, adam)
        chain["p"], chain["opt"] = out[0], out[1]
        chain["lists"] = out[3] if out[3] is not None else chain["lists"]
        return out[2]["total"]

    fwd = eqx.filter_jit(lambda q: solver.radiance(q, lists, ctx))
    cot = jnp.ones_like(fwd(p))
    vjp = eqx.filter_jit(lambda q: jax.vjp(lambda r: solver.radiance(r, lists, ctx), q)[1](cot))
    disp = display(fwd(p))
    loss_vg = {t: eqx.filter_jit(lambda b, d, t=t: jax.value_and_grad(
        lambda d: b.terms(d)[t])(d)) for t in ("total", "E_p", "E_g", "E_x")}
    rows = [("the whole step (solver.step)", one_step),
            ("render forward", lambda: fwd(p)),
            ("render value + gradient (parameters)", lambda: vjp(p)),
            ("loss value + gradient", lambda: loss_vg["total"](ctx.loss, disp))]
    rows += [(f"  its {t} alone", lambda t=t: loss_vg[t](ctx.loss, disp))
             for t in ("E_p", "E_g", "E_x")]
    rows.append(("rebuild of the shared list (run.rebin)",
                 lambda: run.rebin(lists, p, ctx).shared.valid))
    for name, fn in rows:
        print(f"{name}: {1e3 * median_s(fn, args.repeats):.1f}")


if __name__ == "__main__":
    main()
