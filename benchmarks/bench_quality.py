"""Quality per scratch: run design rows (loss weights, ghosting term, prune/re-seed) and write a
markdown table.

Each row is one `jscratch.design.design` run in its own Python process (so that its wall time
includes its own compilation, like a user's run), on one of the target sets below, with the same
seed and scene. The table reports per-view SSIM, PSNR, ghosting (docs/model.md §7), the texture
distance (`metrics.texture_distance`), scratches kept, the ghosting in excess of the targets' own
(`excess`), the carving estimate and the wall time of ``design`` (compilation included; the
carving estimate is not timed).

Carving estimate: the machine profile's (`jscratch.design.maker.carving_estimate`: the kept
scratches ordered with 1 s of 2-opt, then `jscratch.machine.carving_seconds` with the shipped
profile's feeds, plunges and overheads), the number ``python -m jscratch.design`` writes to
``metrics.json`` ("carving"). The rule of docs/model.md §8 (one second per scratch plus the cutting
length at 1.5 cm/s) is kept in the ``.jsonl`` as ``hours_spec8``, a machine-independent figure.

Every row uses the command line's groove model (``--groove carvable``, one plunge per scratch)
unless ``--groove free`` is given; ``--iterations`` sets the Adam iterations of every row,
``--extra JSON`` merges `DesignConfig` overrides into every row (e.g. ``'{"target_ssim": 0.75}'``).

    python benchmarks/bench_quality.py --suite lambda --size 128 --scratches 5000 \
        --out /tmp/w17/lambda128.md

Suites: ``lambda`` (the ``lambda_g`` sweep), ``ghost`` (``lambda_x``), ``prune`` (re-seed
rounds), ``pieces`` (the baseline ``E_p + 200 E_g`` without prune or ``E_x``, each piece of
the shipped defaults alone, then ``E_p + 20 E_g`` with prune), ``s9`` (the shipped defaults built up
from that baseline: ``lambda_g`` 20 alone, prune alone, both, both with ``E_x`` at the ``--lx``
values, and with the raw-ghosting ``E_x`` (``ghost_baseline = "zero"``) at the ``--lx`` values;
the shipped defaults are ``--lx 0.001 --only 4``: that row leaves ``lambda_g`` to the design, 20 or,
for a dense design, ``DesignConfig.dense_lambda_g``). ``--sets`` picks target sets (``default``: camera/astronaut/chelsea; ``other``:
coins/clock/line art; ``other2``: text/brick/page).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from jscratch.bench.timing import cpu_model

SETS = {
    "default": ("camera", "astronaut", "chelsea"),
    "other": ("coins", "clock", "lineart"),
    "other2": ("text", "brick", "page"),
}

#: docs/model.md §8: about one second per scratch (moves, plunge) plus cutting at 1.5 cm/s.
SECONDS_PER_SCRATCH = 1.0
CUT_SPEED = 0.015  # m/s


def lineart(shape, seed=0):
    """A synthetic line-art target: dark strokes (lines, circles, a polygon) on white, [0, 1]."""
    from skimage.draw import circle_perimeter_aa, line_aa, polygon_perimeter
    from skimage.filters import gaussian

    h, w = shape
    img = np.ones((h, w))
    rng = np.random.default_rng(seed)
    for _ in range(10):
        r0, c0, r1, c1 = (rng.integers(0, h), rng.integers(0, w), rng.integers(0, h),
                          rng.integers(0, w))
        rr, cc, val = line_aa(r0, c0, r1, c1)
        img[rr, cc] = np.minimum(img[rr, cc], 1 - val)
    for k in range(4):
        rr, cc, val = circle_perimeter_aa(h // 2, w // 2, (k + 1) * min(h, w) // 10, shape=shape)
        img[rr, cc] = np.minimum(img[rr, cc], 1 - val)
    rr, cc = polygon_perimeter([h // 8, h // 3, h // 5], [w // 8, w // 6, w // 3], shape=shape)
    img[rr, cc] = 0
    # strokes about 2 px wide at 256 px
    return np.clip(gaussian(img, sigma=0.6 * h / 256, preserve_range=True), 0, 1)


def targets(names, size):
    from skimage import data

    from jscratch.design.io import prepare_target

    out = []
    for n in names:
        if n == "lineart":
            out.append(lineart((size, size)))
        else:
            out.append(prepare_target(getattr(data, n)(), (size, size), n))
    return np.stack(out)


def carving_hours_spec8(p0, p1):
    length = np.hypot(*(np.asarray(p1) - np.asarray(p0)).T).sum()
    return (SECONDS_PER_SCRATCH * len(p0) + length / CUT_SPEED) / 3600.0


def run_one(spec: dict) -> dict:
    """One row in this process: returns the metrics (called in a child process)."""
    import jax

    from jscratch.design import DesignConfig, design
    from jscratch.metrics import texture_distance
    from jscratch.scene import Board, views_on_circle

    size = spec["size"]
    t = targets(SETS[spec["set"]], size)
    board = Board(shape=(size, size))
    views = views_on_circle(3, np.radians(50.0), 1.0, None, board)
    over = dict(spec["config"])
    if over.pop("raw_ghost", False):  # E_x against a zero baseline: the raw cross-view SSIM
        over["loss"] = {**over.get("loss", {}), "ghost_baseline": "zero"}
    cfg = DesignConfig.from_dict({"n_scratches": spec["scratches"], "groove": spec["groove"],
                                  "iterations": spec["iterations"], **over})
    t0 = time.perf_counter()
    res = design(t, views, board, cfg)
    wall = time.perf_counter() - t0
    m = res.metrics
    s = res.scratches
    from jscratch.metrics import image_metrics

    base = image_metrics(t, t)["ghosting"]  # what a perfect render would show
    from jscratch import designfile
    from jscratch.design.maker import carving_estimate

    plunge = None
    if res.params.groove is not None:
        plunge = np.asarray(res.params.plunge(), np.float64)[np.asarray(res.keep)]
    v = res.views
    d = designfile.Design(np.asarray(s.p0, np.float64), np.asarray(s.p1, np.float64),
                          np.asarray(s.width, np.float64), np.asarray(s.depth, np.float64),
                          np.asarray(s.alpha, np.float64), np.array([board.Sx, board.Sy]),
                          np.asarray(v.camera), np.asarray(v.light), np.asarray(v.intensity),
                          plunge=plunge, profile=s.profile)
    carve = carving_estimate(d, cfg.machine_profile(), time_limit=1.0, plunge=plunge)
    return {
        "ssim": m["ssim"], "psnr": m["psnr"], "ghosting": m["ghosting"],
        "texture": texture_distance(np.asarray(res.display), t),
        "kept": int(m["kept"]), "hours": carve["estimated_hours"],
        "hours_spec8": float(carving_hours_spec8(s.p0, s.p1)), "iterations": cfg.iterations,
        "groove": cfg.groove, "target": m.get("target"),
        "step_median": m["time_step_median"], "time_select": m["time_discard"],
        "loss_terms": m["loss_terms"], "wall": wall, "jax": jax.__version__,
        "prune": m.get("prune"), "ghost_base": base,
    }


def suite(name: str, lx=(0.003, 0.01, 0.03), prune=((10, 0.05), (20, 0.1)), lg_new=0.0
          ) -> list[tuple[str, dict]]:
    """``(row label, DesignConfig overrides)`` of a suite (``lx``: ``lambda_x`` values;
    ``prune``: ``(prune_every, prune_fraction)`` settings; ``lg_new``: the new ``lambda_g``)."""
    # (each row names the loss terms it has: `lambda_x` 0 where its label has no E_x, and the
    # E_x rows their baseline, so that a suite does not move with the defaults)
    if name == "lambda":
        rows = [("E_p alone (lambda_g 0)", {"loss": {"kind": "perceptual", "lambda_x": 0.0}})]
        for lg in (20, 50, 100, 200, 400):
            rows.append((f"E_p + {lg} E_g", {"loss": {"kind": "perceptual+gram", "lambda_g": lg,
                                                      "lambda_x": 0.0}}))
        return rows
    if name == "ghost":
        return [(f"E_p + {lx} E_x (zero baseline)",
                 {"loss": {"kind": "perceptual", "lambda_x": lx, "ghost_baseline": "zero"}})
                for lx in lx]
    if name == "prune":
        return [(f"E_p, prune every {e}, {f:.0%}", {"loss": {"kind": "perceptual", "lambda_x": 0.0},
                                                     "prune_every": e, "prune_fraction": f})
                for e, f in prune]
    if name == "pieces":
        old = {"loss": {"kind": "perceptual+gram", "lambda_g": 200.0, "lambda_x": 0.0},
               "prune_every": 0}
        ep = {"loss": {"kind": "perceptual", "lambda_x": 0.0}, "prune_every": 0}
        (pe, pf), x = prune[0], lx[0]
        return [
            ("baseline (E_p + 200 E_g, no prune, no E_x)", old),
            ("E_p alone (lambda_g 0)", ep),
            ("E_p + 20 E_g", {**ep, "loss": {**ep["loss"], "kind": "perceptual+gram",
                                              "lambda_g": 20.0}}),
            (f"E_p + {x} E_x (ghosting term)", {**ep, "loss": {**ep["loss"], "lambda_x": x}}),
            (f"E_p + prune every {pe}, {pf:.0%}", {**ep, "prune_every": pe, "prune_fraction": pf}),
            ("E_p + 20 E_g, prune every 10, 5%",
             {"loss": {"kind": "perceptual+gram", "lambda_g": 20.0, "lambda_x": 0.0},
              "prune_every": 10, "prune_fraction": 0.05}),
        ]
    if name == "s9":
        # the baseline (E_p + 200 E_g, no prune, no E_x) and every other row name their weights
        # explicitly, so that the suite does not move with the defaults
        old = {"loss": {"kind": "perceptual+gram", "lambda_g": 200.0, "lambda_x": 0.0},
               "prune_every": 0}
        g20 = {"kind": "perceptual+gram", "lambda_g": 20.0, "lambda_x": 0.0}
        (pe, pf) = prune[0]
        pr = {"prune_every": pe, "prune_fraction": pf}
        rows = [
            ("baseline (E_p + 200 E_g, no prune, no E_x)", old),
            ("E_p + 20 E_g alone", {**old, "loss": g20}),
            (f"prune every {pe}, {pf:.0%} alone (E_p + 200 E_g)", {**old, **pr}),
            (f"proposal: E_p + 20 E_g, prune every {pe}, {pf:.0%}", {"loss": g20, **pr}),
        ]
        for x in lx:  # the current defaults but lambda_x (lambda_g: 20, or `dense_lambda_g`)
            rows.append((f"current defaults with {x} E_x", {"loss": {"kind": "perceptual+gram",
                                                                      "lambda_x": x}, **pr}))
        for x in lx:
            rows.append((f"proposal + {x} E_x raw (zero baseline, lambda_g 20)",
                         {"loss": {**g20, "lambda_x": x, "ghost_baseline": "zero"}, **pr}))
        return rows
    raise SystemExit(f"unknown suite {name!r}")


def excess(r: dict) -> float:
    """Mean over views of the ghosting beyond the targets' own: ``max(0, ghosting - baseline)``,
    the baseline being the ghosting of a perfect render (the targets against each other)."""
    return float(np.mean(np.maximum(0.0, np.asarray(r["ghosting"]) - np.asarray(r["ghost_base"]))))


def fmt(r: dict) -> str:
    f3 = lambda xs: "/".join(f"{x:.3f}" for x in xs)  # noqa: E731
    f2 = lambda xs: "/".join(f"{x:.2f}" for x in xs)  # noqa: E731
    return (f"{f3(r['ssim'])} ({np.mean(r['ssim']):.3f}) | {f2(r['psnr'])} | "
            f"{f3(r['ghosting'])} ({np.mean(r['ghosting']):.3f}) | {excess(r):.3f} | "
            f"{np.mean(r['texture']):.4f} | "
            f"{r['kept']} | {r['hours']:.2f} | {r['wall']:.0f}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--suite", default="lambda")
    p.add_argument("--sets", default="default,other")
    p.add_argument("--size", type=int, default=128, help="image side (px)")
    p.add_argument("--scratches", type=int, default=5000)
    p.add_argument("--only", default=None, help="comma-separated row indices to run")
    p.add_argument("--lx", default="0.003,0.01,0.03", help="lambda_x values (ghost suite; "
                   "pieces: the first)")
    p.add_argument("--prune", default="10:0.05,20:0.1", help="EVERY:FRACTION settings (prune "
                   "suite; pieces: the first)")
    p.add_argument("--groove", choices=("carvable", "free"), default="carvable",
                   help="groove model of every row (the command line's default: carvable)")
    p.add_argument("--iterations", type=int, default=100, help="Adam iterations of every row")
    p.add_argument("--extra", default="{}", help="JSON DesignConfig overrides merged into every "
                   "row (e.g. '{\"target_ssim\": 0.75}')")
    p.add_argument("--label", default="", help="suffix of every row's label")
    p.add_argument("--out", default="/tmp/jscratch-quality.md", help="markdown table (appended)")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # child: JSON spec
    a = p.parse_args(argv)
    if a.one is not None:
        print("RESULT " + json.dumps(run_one(json.loads(a.one))))
        return
    rows = suite(a.suite, tuple(float(x) for x in a.lx.split(",")),
                 tuple((int(x.split(":")[0]), float(x.split(":")[1])) for x in a.prune.split(",")))
    if a.only:
        rows = [rows[int(i)] for i in a.only.split(",")]
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    load = os.getloadavg()
    with open(a.out, "a") as f:
        f.write(f"\n### suite {a.suite}, {a.size} px, {a.scratches} scratches, 3 views, "
                f"{a.iterations} it., {a.groove} grooves, extra {a.extra}, "
                f"seed 0 ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
                f"{cpu_model()}, load at start {load[0]:.2f}/{load[1]:.2f}/{load[2]:.2f})\n\n"
                "| targets | run | SSIM per view (mean) | PSNR (dB) | ghosting (mean) | excess "
                "ghosting | texture | kept | carve (h) | wall (s) | load |\n"
                "|---|---|---|---|---|---|---|---|---|---|---|\n")
    for set_name in a.sets.split(","):
        for label, cfg in rows:
            extra = json.loads(a.extra)
            if "loss" in extra:
                extra["loss"] = {**cfg.get("loss", {}), **extra["loss"]}
            label = label + a.label
            spec = {"set": set_name, "size": a.size, "scratches": a.scratches,
                    "groove": a.groove, "iterations": a.iterations, "config": {**cfg, **extra}}
            load0 = os.getloadavg()[0]
            proc = subprocess.run([sys.executable, __file__, "--one", json.dumps(spec)],
                                  capture_output=True, text=True)
            line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
            if proc.returncode != 0 or not line:
                row = f"| {set_name} | {label} | failed: {proc.stderr.strip().splitlines()[-1:]} |"
            else:
                r = json.loads(line[0][7:])
                row = (f"| {set_name} | {label} | {fmt(r)} | "
                       f"{load0:.1f}-{os.getloadavg()[0]:.1f} |")
                with open(a.out + ".jsonl", "a") as g:
                    g.write(json.dumps({"set": set_name, "label": label, "size": a.size,
                                        "scratches": a.scratches, "config": spec["config"],
                                        "load": os.getloadavg(), **r}) + "\n")
            print(row, flush=True)
            with open(a.out, "a") as f:
                f.write(row + "\n")
    with open(a.out, "a") as f:
        load = os.getloadavg()
        f.write(f"\nload at end {load[0]:.2f}/{load[1]:.2f}/{load[2]:.2f}\n")


if __name__ == "__main__":
    main()
