"""Benchmark of the multi-view design: the default run end to end, and the paper's ablations.

Usage (from the repository root)::

    python benchmarks/bench_design.py                      # default run + ablations
    python benchmarks/bench_design.py --only default
    python benchmarks/bench_design.py --only ablations --size 128 --scratches 5000

- **default**: ``design`` with the CLI defaults (3 views, 20,000 scratches, 256x256, 100
  iterations, skimage.data targets); wall time end to end (including compilation, binning, the
  discard and the metrics), the step's compilation (on a thread beside the setup), the first and
  the median step apart, and per-view SSIM / PSNR / ghosting (docs/model.md §7).
- **ablations** (paper Figs. 17, 19, 20, 21), each at a reduced size with the same budget:
  loss ``l2`` vs ``perceptual`` (each without the ghosting term) vs the default (perceptual, Gram
  and ghosting terms); two
  endpoints vs midpoint + direction + length; ``alpha = 4e-4`` vs ``0.04`` (frozen); discard on
  vs off (from the default-loss run). Every other setting is the default (prune rounds
  included), so the runs differ in the one thing named.
  ``E_p`` of the final render is reported for every run so that runs trained with different losses
  compare on one scale.

Prints Markdown tables and writes them to ``benchmarks/results/design.md`` (with ``--only X``:
``benchmarks/results/design_X.md``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import jax.numpy as jnp
import numpy as np


from jscratch import loss
from jscratch import render
from jscratch.bench import machine_line
from jscratch.design import DesignConfig, default_targets, design

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "design.md")


def _run(m, size, config, theta_deg=50.0):
    targets, _ = default_targets(m, (size, size))
    board = render.Board(shape=(size, size))
    views = render.views_on_circle(m, math.radians(theta_deg), board=board)
    t0 = time.perf_counter()
    res = design(targets, views, board, config)
    wall = time.perf_counter() - t0
    ep = float(loss.perceptual_loss(jnp.asarray(res.display), jnp.asarray(targets)))
    return res, wall, ep


def _fmt_list(xs, nd=3):
    return "/".join(f"{x:.{nd}f}" for x in xs)


def _num(x, spec) -> str:
    """`x` formatted, or "-" where it was not measured (None)."""
    return "-" if x is None else format(x, spec)


def _row(name, res, wall, ep, before=False):
    """A table row; `ep` None where E_p was not measured (the render before the discard is not
    kept)."""
    mt = res.metrics["metrics_before_discard"] if before else res.metrics
    n = res.metrics["kept"] + (res.metrics["discarded"] if before else 0)
    return (f"| {name} | {n} | {_fmt_list(mt['ssim'])} ({np.mean(mt['ssim']):.3f}) | "
            f"{_fmt_list(mt['psnr'], 2)} | {_fmt_list(mt['ghosting'])} | "
            f"{(res.metrics['loss_before_discard'] if before else res.metrics['loss']):.5g} | "
            f"{_num(ep, '.5g')} | {wall:.0f} |")


HEADER = ("| run | scratches | SSIM per view (mean) | PSNR per view (dB) | ghosting per view | "
          "final loss | E_p | wall (s) |\n|---|---|---|---|---|---|---|---|")


def bench_default(args, out):
    cfg = DesignConfig(iterations=args.iterations)
    res, wall, ep = _run(3, 256, cfg)
    mt = res.metrics
    out.append(f"## Default run (CLI defaults: 3 views, 20,000 scratches, 256x256, "
               f"{args.iterations} iterations)\n")
    out.append(HEADER)
    out.append(_row("default, before discard", res, wall, None, before=True))
    out.append(_row("default (after discard)", res, wall, ep))
    out.append("")
    out.append(f"- wall time end to end: **{wall:.1f} s** (the step compiled beside the setup in "
               f"{_num(mt['time_compile_step'], '.1f')} s; first step "
               f"{_num(mt['time_first_step'], '.2f')} s, median step "
               f"{_num(mt['time_step_median'], '.3f')} s, discard "
               f"{_num(mt['time_discard'], '.1f')} s; {mt['rebins']} rebins)")
    out.append(f"- pairs: {mt['pairs_total']} unculled, per view after culling "
               f"{mt['pairs_per_view']}; discarded {mt['discarded']} of {cfg.n_scratches} "
               f"({100 * mt['discarded'] / cfg.n_scratches:.1f} %)")
    out.append(f"- light intensities (W/sr): {_fmt_list(mt['intensity'], 1)}")
    out.append("")


def bench_ablations(args, out):
    size, n, it = args.size, args.scratches, args.iterations
    out.append(f"## Ablations (3 views, {n} scratches, {size}x{size}, {it} iterations each)\n")
    out.append(HEADER)
    base = dict(n_scratches=n, iterations=it)
    runs = [
        ("loss: squared L2", DesignConfig(**base, loss=loss.LossConfig(kind="l2", lambda_x=0.0))),
        ("loss: E_p", DesignConfig(**base, loss=loss.LossConfig(kind="perceptual",
                                                                lambda_x=0.0))),
        ("loss: the default (E_p + E_g + E_x)", DesignConfig(**base)),
        ("midpoint + direction + length", DesignConfig(**base, parameterisation="midpoint")),
        ("alpha = 4e-4 (frozen)", DesignConfig(**base, init_alpha=4e-4)),
    ]
    for name, cfg in runs:
        res, wall, ep = _run(3, size, cfg)
        if name.startswith("loss: the default"):
            out.append(_row("discard off (the default loss, all scratches)", res, wall,
                            None, before=True))
        out.append(_row(name, res, wall, ep))
        print(out[-1], flush=True)
    out.append("")
    out.append("Each row's wall time includes its own compilation. 'final loss' is the loss the "
               "run optimised (not comparable across loss kinds); E_p of the final display values "
               "is. Discard rows: the same run before and after the discard step "
               "(tolerance: loss at most 1 % higher).")
    out.append("")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", choices=("default", "ablations"), default=None)
    p.add_argument("--size", type=int, default=128, help="ablation image size (px)")
    p.add_argument("--scratches", type=int, default=5000, help="ablation scratch count")
    p.add_argument("--iterations", type=int, default=100)
    args = p.parse_args()
    out = [
        "# Design benchmark\n",
        f"- machine: {machine_line()}; float32",
        f"- command: `python benchmarks/bench_design.py {' '.join(sys.argv[1:])}`".rstrip(),
        "",
    ]
    if args.only in (None, "default"):
        bench_default(args, out)
    if args.only in (None, "ablations"):
        bench_ablations(args, out)
    text = "\n".join(out) + "\n"
    print(text)
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    path = RESULTS if args.only is None else RESULTS.replace(".md", f"_{args.only}.md")
    with open(path, "w") as f:
        f.write(text)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
