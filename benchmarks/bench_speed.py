"""The pair kernel, the renderer and the design step against an earlier commit, in one run on the
same pairs: how much faster (or slower) the working tree is than a given commit.

    python benchmarks/bench_speed.py [--base b8f83e0] [--sections kernel render design]
                                     [--iterations 12] [--design-args "--groove free"]
                                     [--out benchmarks/results/speed]

The base commit's package is exported with `git archive` into a temporary folder; each
measurement runs in a fresh worker process (this script with ``--worker``) whose ``PYTHONPATH``
selects the code: the base export or the installed package. Workers of the two codes alternate,
and every input (kernel pairs, half vectors) is drawn once by this process and handed to both
in a file, so both codes see the same pairs.

- ``kernel``: `ndf.pair_integral` on 16,384 random float32 pairs (`ndf_cases.random_cases`),
  vmapped over M = 1, 3, 5 views with the scratch and footprint shared by the views (as the
  renderer calls it): ns per pair-view forward (``D + A``) and forward + backward (gradient with
  respect to the half vectors, endpoints, width, depth and alpha; compiled with
  `render.grad_compiler_options`), XLA cost-analysis flops and bytes per pair-view.
- ``render``: `render.render_pairs` on the default scene (20,000 scratches, 256x256, views on a
  circle at 50 degrees, unculled `bin_pairs` list): forward and value + VJP, ns per pair-view.
- ``design``: ``python -m jscratch.design --iterations N --no-discard`` (the command line's
  defaults, plus ``--design-args`` for both codes): median step, first step, the loss after N
  iterations and the shared list's rebuilds.

Medians of repeated `block_until_ready` runs after a warm-up, compile time apart. Writes
``speed.json`` and ``speed.md`` to ``--out`` and prints the Markdown.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

N_PAIRS = 16384
VIEWS = (1, 3, 5)


# ---------------------------------------------------------------------------------------------
# Workers (run in a subprocess; the code under test is whatever `import jscratch` finds).


def _median_ns(fn, args, per: int, repeats: int) -> float:
    """Median ns per item (`per` items a call) of `repeats` timed calls after a warm-up."""
    from jscratch.bench import median_time  # (in the base code too)

    return 1e9 * median_time(lambda: fn(*args), repeats)[0] / per


def _cost(compiled, per: int) -> dict:
    ca = compiled.cost_analysis()
    ca = ca[0] if isinstance(ca, list) else ca
    return {"flops": ca["flops"] / per, "bytes": ca["bytes accessed"] / per}


def worker_kernel(inputs: str, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jscratch import ndf
    from jscratch import render

    data = np.load(inputs)
    fp, p0, p1, w, d, a = (jnp.asarray(data[k]) for k in ("fp", "p0", "p1", "w", "d", "a"))
    rows = {}
    for m in VIEWS:
        H = jnp.asarray(data[f"h{m}"])

        def total(H, p0, p1, w, d, a):
            pairs = jax.vmap(ndf.pair_integral)
            views = jax.vmap(pairs, in_axes=(0, None, None, None, None, None, None))
            D, A = views(H, fp, p0, p1, w, d, a)
            return jnp.sum(D) + jnp.sum(A[0])

        args = (H, p0, p1, w, d, a)
        per = N_PAIRS * m
        fwd = jax.jit(total).lower(*args).compile()
        grad = jax.jit(jax.grad(total, argnums=tuple(range(6))),
                       compiler_options=render.grad_compiler_options()).lower(*args).compile()
        rows[m] = {"fwd_ns": _median_ns(fwd, args, per, repeats),
                   "fwd_bwd_ns": _median_ns(grad, args, per, repeats),
                   "fwd_cost": _cost(fwd, per), "fwd_bwd_cost": _cost(grad, per)}
    return rows


def worker_render(repeats: int) -> dict:
    import math

    import jax
    import jax.numpy as jnp

    from jscratch import render

    board = render.Board(shape=(256, 256))
    s = render.Scratches.random(jax.random.PRNGKey(0), 20000, board, length=(0.005, 0.025),
                           width=2.5e-4, depth=1.28e-4, alpha=0.04, dtype=jnp.float32)
    pairs = render.bin_pairs(s, board)
    n_pairs = int(pairs.valid.sum())
    rows = {}
    for m in VIEWS:
        v = render.views_on_circle(m, math.radians(50), 1.0, None, board)

        def rend(s, v, pairs):
            return render.render_pairs(s, v, board, pairs)

        def vjp(s, v, pairs):
            out, back = jax.vjp(lambda s, v: rend(s, v, pairs), s, v)
            return back(jnp.ones_like(out))

        args = (s, v, pairs)
        per = n_pairs * m
        fwd = jax.jit(rend).lower(*args).compile()
        grad = jax.jit(vjp, compiler_options=render.grad_compiler_options()).lower(*args).compile()
        rows[m] = {"pairs": n_pairs, "fwd_ns": _median_ns(fwd, args, per, repeats),
                   "value_vjp_ns": _median_ns(grad, args, per, repeats)}
    return rows


def worker_design(iterations: int) -> dict:
    from jscratch import design  # in this process: the code this worker's PYTHONPATH selects

    # The same scene for both codes: the command line's defaults (a base older than `--groove`
    # ran free grooves by default: pass `--design-args "--groove free"` to compare like with like).
    with tempfile.TemporaryDirectory() as out:
        args = ["--iterations", str(iterations), "--no-discard", "--quiet", "--out", out]
        extra = os.environ.get("JSCRATCH_BENCH_DESIGN_ARGS", "").split()
        try:
            design.main(args + extra)
        except SystemExit as e:
            if e.code not in (0, None):
                raise
        m = json.loads(Path(out, "metrics.json").read_text())
    return {"step_median_s": m["time_step_median"], "first_step_s": m["time_first_step"],
            "loss": m["loss"], "rebins": m.get("rebins")}


# ---------------------------------------------------------------------------------------------
# Driver.


def _inputs(path: Path) -> None:
    """The kernel's pairs and per-view half vectors, float32, drawn once for both codes."""
    import numpy as np

    from jscratch.bench.ndf_cases import random_cases

    C = random_cases(N_PAIRS).astype(np.float32)
    rng = np.random.default_rng(1)
    arrays = {"fp": C.footprint, "p0": C.p0, "p1": C.p1, "w": C.width, "d": C.depth, "a": C.alpha}
    for m in VIEWS:
        h = rng.normal(size=(m, N_PAIRS, 3))
        h[..., 2] = np.abs(h[..., 2]) + 0.5
        arrays[f"h{m}"] = (h / np.linalg.norm(h, axis=-1, keepdims=True)).astype(np.float32)
    np.savez(path, **arrays)


def _run_worker(code: str | None, args: list[str]) -> dict:
    env = dict(os.environ)
    if code is not None:  # the exported base package shadows the installed one
        env["PYTHONPATH"] = code + os.pathsep + env.get("PYTHONPATH", "")
    # (run from a temporary folder: a working directory holding a `jscratch` folder would shadow)
    with tempfile.TemporaryDirectory() as cwd:
        res = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", *args],
                             env=env, check=True, capture_output=True, text=True, cwd=cwd)
    return json.loads(res.stdout.strip().splitlines()[-1])


def _export(base: str, into: str) -> None:
    top = subprocess.run(["git", "rev-parse", "--show-toplevel"], check=True, capture_output=True,
                         text=True, cwd=os.path.dirname(os.path.abspath(__file__))).stdout.strip()
    archive = subprocess.run(["git", "archive", base, "jscratch"], check=True,
                             capture_output=True, cwd=top).stdout
    subprocess.run(["tar", "-x", "-C", into], input=archive, check=True)


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}x" if b > 0 else "-"


def _markdown(res: dict) -> str:
    base = res["base"]
    lines = [f"Base: commit `{base}`; current: the working tree. Machine: {res['machine']}; "
             f"load average before/after: {res['load_before']} / {res['load_after']}.", ""]
    if "kernel" in res:
        lines += ["| kernel, views | fwd ns/pv base | now | speed-up | fwd+bwd ns/pv base | now |"
                  " speed-up | fwd+bwd flop/pv base | now | fwd+bwd bytes/pv base | now |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for m in VIEWS:
            b, c = res["kernel"]["base"][str(m)], res["kernel"]["current"][str(m)]
            lines.append(
                f"| {m} | {b['fwd_ns']:.0f} | {c['fwd_ns']:.0f} | {_ratio(b['fwd_ns'], c['fwd_ns'])}"
                f" | {b['fwd_bwd_ns']:.0f} | {c['fwd_bwd_ns']:.0f} |"
                f" {_ratio(b['fwd_bwd_ns'], c['fwd_bwd_ns'])} |"
                f" {b['fwd_bwd_cost']['flops']:,.0f} | {c['fwd_bwd_cost']['flops']:,.0f} |"
                f" {b['fwd_bwd_cost']['bytes']:,.0f} | {c['fwd_bwd_cost']['bytes']:,.0f} |")
        lines.append("")
    if "render" in res:
        lines += ["| render_pairs, views | pairs | fwd ns/pv base | now | speed-up |"
                  " value+VJP ns/pv base | now | speed-up |", "|---|---|---|---|---|---|---|---|"]
        for m in VIEWS:
            b, c = res["render"]["base"][str(m)], res["render"]["current"][str(m)]
            lines.append(
                f"| {m} | {c['pairs']} | {b['fwd_ns']:.0f} | {c['fwd_ns']:.0f} |"
                f" {_ratio(b['fwd_ns'], c['fwd_ns'])} | {b['value_vjp_ns']:.0f} |"
                f" {c['value_vjp_ns']:.0f} | {_ratio(b['value_vjp_ns'], c['value_vjp_ns'])} |")
        lines.append("")
    if "design" in res:
        b, c = res["design"]["base"], res["design"]["current"]
        it = res["design"]["iterations"]
        lines += [f"| default design{res['design']['args']}, {it} iterations | base | now |"
                  " speed-up |", "|---|---|---|---|",
                  f"| median step (s) | {b['step_median_s']:.2f} | {c['step_median_s']:.2f} |"
                  f" {_ratio(b['step_median_s'], c['step_median_s'])} |",
                  f"| first step (s) | {b['first_step_s']:.2f} | {c['first_step_s']:.2f} |"
                  f" {_ratio(b['first_step_s'], c['first_step_s'])} |",
                  f"| loss after {it} iterations | {b['loss']!r} | {c['loss']!r} | |",
                  f"| shared-list rebuilds | {b.get('rebins')} | {c.get('rebins')} | |", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="b8f83e0", help="commit to compare with (default b8f83e0)")
    ap.add_argument("--iterations", type=int, default=12, help="design section: iterations")
    ap.add_argument("--design-args", default="",
                    help='design section: extra options for both codes, e.g. "--groove free"')
    ap.add_argument("--sections", nargs="+", default=["kernel", "render", "design"],
                    choices=["kernel", "render", "design"])
    ap.add_argument("--repeats", type=int, default=7, help="timed runs per measurement")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                                  "results", "speed"))
    ap.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        what, *rest = a.worker
        res = {"kernel": lambda: worker_kernel(rest[0], a.repeats),
               "render": lambda: worker_render(max(3, a.repeats // 2)),
               "design": lambda: worker_design(a.iterations)}[what]()
        import jscratch

        res["code"] = os.path.dirname(jscratch.__file__)  # which package was measured
        print(json.dumps(res))
        return 0

    from jscratch.bench import machine_line  # the working tree's (the parent measures nothing)

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = {"base": a.base, "load_before": " ".join(f"{x:.2f}" for x in os.getloadavg()),
           "machine": machine_line()}
    with tempfile.TemporaryDirectory() as tmp:
        _export(a.base, tmp)
        inputs = Path(tmp, "kernel_inputs.npz")
        _inputs(inputs)
        codes = {"base": tmp, "current": None}
        for section in a.sections:
            args = {"kernel": ["kernel", str(inputs)], "render": ["render"],
                    "design": ["design", "--iterations", str(a.iterations)]}[section] + [
                "--repeats", str(a.repeats)]
            os.environ["JSCRATCH_BENCH_DESIGN_ARGS"] = a.design_args
            res[section] = {}
            for name, code in codes.items():
                print(f"{section}: {name} ...", file=sys.stderr, flush=True)
                res[section][name] = _run_worker(code, args)
                # (the worker reports which package it imported: checked, then named by its role)
                got = res[section][name].pop("code")
                assert (code is None) != got.startswith(tmp), (name, got)
            if section == "design":
                res["design"].update(iterations=a.iterations,
                                     args=f" `{a.design_args}`" if a.design_args else "")
    res["load_after"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    md = _markdown(json.loads(json.dumps(res)))
    (out / "speed.json").write_text(json.dumps(res, indent=1))
    (out / "speed.md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
