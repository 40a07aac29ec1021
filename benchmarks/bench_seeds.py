"""Design settings compared over several seeds, paired: is a change in SSIM or ghosting larger
than what any float32-sized perturbation of the optimisation already does?

    python benchmarks/bench_seeds.py --arm full="--skip-eps 0" --arm skip5e5="--skip-eps 5e-5" \
        [--arm fewer="--skip-eps 0 --iterations 94"] [--seeds 0-7] [--out benchmarks/results/seeds]

A design is chaotic in its details: one seed's per-view SSIM and ghosting move by several
thousandths when anything in the run changes by a rounding error (a learning rate scaled by
1.0001, another CPU's float32 rounding). One run per setting therefore cannot show a change of
that size; the same seeds run under every setting, and the differences paired by seed, can.

Each arm is ``NAME=ARGS``: extra arguments of ``python -m jscratch.design`` (the first arm is the
reference). For every seed the arms run one after the other, each in its own process (``--quiet``,
``--seed S``, output in ``OUT/NAME_sS``; a run whose ``metrics.json`` exists is read, not run
again, so an interrupted comparison continues). Writes ``OUT/seeds.jsonl`` (one line a run) and
``OUT/seeds.md``: per arm the mean over the seeds, and its difference from the reference arm,
paired by seed, as mean +- standard error, of the SSIM and ghosting of each view, the loss and
scratches kept (relative), the median step and the run time of ``design``.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import statistics
import subprocess
import sys
from pathlib import Path


def parse_seeds(text: str) -> list[int]:
    """``"0-7"`` or ``"0,3,5"`` as a list of seeds."""
    out = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def parse_arm(text: str) -> tuple[str, list[str]]:
    name, sep, args = text.partition("=")
    if not sep or not name.isidentifier():
        raise argparse.ArgumentTypeError(f"--arm {text!r}: expected NAME=ARGS, NAME a word")
    return name, shlex.split(args)


def run(name: str, args: list[str], seed: int, out: Path) -> dict:
    """One design run (or its earlier result): the figures this comparison uses."""
    folder = out / f"{name}_s{seed}"
    if not (folder / "metrics.json").exists():
        cmd = [sys.executable, "-m", "jscratch.design", "--quiet", "--out", str(folder),
               "--seed", str(seed), *args]
        subprocess.run(cmd, check=True)
    m = json.loads((folder / "metrics.json").read_text())
    return {"arm": name, "seed": seed, "args": args, "ssim": m["ssim"], "ghosting": m["ghosting"],
            "loss": m["loss"], "kept": m["kept"], "time_total": m["time_total"],
            "time_step_median": m["time_step_median"]}


def _mean_se(values: list[float]) -> tuple[float, float]:
    mean = statistics.fmean(values)
    se = statistics.stdev(values) / math.sqrt(len(values)) if len(values) > 1 else math.nan
    return mean, se


def _figures(r: dict) -> dict:
    """A run's figures by column name (loss and kept as they are; relative differences later)."""
    f = {f"SSIM {j + 1}": s for j, s in enumerate(r["ssim"])}
    f |= {f"ghosting {j + 1}": g for j, g in enumerate(r["ghosting"])}
    return f | {"loss": r["loss"], "kept": r["kept"], "step (ms)": 1e3 * r["time_step_median"],
                "design (s)": r["time_total"]}


def table(rows: list[dict], arms: list[str]) -> str:
    """Markdown: each arm's means, and its paired differences from the first arm."""
    by = {(r["arm"], r["seed"]): _figures(r) for r in rows}
    seeds = sorted({r["seed"] for r in rows if all((a, r["seed"]) in by for a in arms)})
    cols = list(by[(arms[0], seeds[0])])
    lines = [f"{len(seeds)} seeds ({', '.join(map(str, seeds))}); differences from "
             f"`{arms[0]}` paired by seed, mean +- standard error; loss and kept relative.", "",
             "| arm | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for arm in arms:
        means = [statistics.fmean(by[(arm, s)][c] for s in seeds) for c in cols]
        cells = [f"{m:.0f}" if c == "kept" else f"{m:.5f}" if c == "loss" else f"{m:.4g}"
                 for c, m in zip(cols, means)]
        lines.append(f"| {arm} | " + " | ".join(cells) + " |")
        if arm == arms[0]:
            continue
        cells = []
        for c in cols:
            ref = [by[(arms[0], s)][c] for s in seeds]
            new = [by[(arm, s)][c] for s in seeds]
            if c in ("loss", "kept"):
                m, se = _mean_se([100 * (b / a - 1) for a, b in zip(ref, new)])
                cells.append(f"{m:+.1f} +- {se:.1f} %")
            else:
                m, se = _mean_se([b - a for a, b in zip(ref, new)])
                cells.append(f"{m:+.4f} +- {se:.4f}" if c.startswith(("SSIM", "ghost"))
                             else f"{m:+.2f} +- {se:.2f}")
        lines.append(f"| {arm} - {arms[0]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arm", type=parse_arm, action="append", required=True,
                    help="NAME=ARGS: design arguments of one arm (the first is the reference)")
    ap.add_argument("--seeds", type=parse_seeds, default=parse_seeds("0-7"),
                    help="e.g. 0-7 or 0,2,5")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/seeds"))
    a = ap.parse_args(argv)
    names = [n for n, _ in a.arm]
    if len(set(names)) != len(names):
        ap.error(f"--arm names must differ, got {names}")
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    with open(a.out / "seeds.jsonl", "w") as log:
        for seed in a.seeds:
            for name, args in a.arm:
                rows.append(run(name, args, seed, a.out))
                log.write(json.dumps(rows[-1]) + "\n")
                log.flush()
    md = table(rows, names)
    (a.out / "seeds.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
