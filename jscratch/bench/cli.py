"""The driver of `python -m jscratch.bench`: `run_bench(sections, quick, out)` and `main`."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax

from jscratch.bench import kernel, rendering
from jscratch.bench.timing import machine_info

DESCRIPTION = ("`python -m jscratch.bench`: run time against error, numerical stress, and the"
               " recorded results.")
SECTIONS = ("kernel", "stability", "render", "brute", "design")


def run_bench(sections=SECTIONS, quick: bool = False, out: str | Path = "bench_out") -> dict:
    """Run the chosen sections; write `bench.json`, `bench.md` and plots to `out`; return the
    results dict (`machine`, one entry per section, each with a `markdown` table)."""
    # float64 rows and references need x64; float32 paths build float32 arrays explicitly.
    jax.config.update("jax_enable_x64", True)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        raise ValueError(f"unknown bench sections {sorted(unknown)}; choose from {SECTIONS}")
    runners = {"kernel": kernel.bench_kernel, "stability": kernel.bench_stability,
               **rendering.RUNNERS}
    res = {"machine": machine_info(), "quick": quick, "command": " ".join(sys.argv)}
    for s in sections:
        if s not in runners:
            res[s] = {"skipped": "not available in this build", "markdown": "(skipped)"}
            continue
        t0 = time.perf_counter()
        res[s] = runners[s](quick, out)
        res[s]["section_wall_s"] = time.perf_counter() - t0
    md = [f"# jscratch bench ({'quick' if quick else 'full'})\n",
          "Machine: " + ", ".join(f"{k} {v}" for k, v in res["machine"].items()) + "\n"]
    for s in sections:
        md.append(f"\n## {s}\n\n{res[s].get('markdown', '')}\n")
        if "note" in res[s]:
            md.append(f"\n{res[s]['note']}\n")
    text = "".join(md)
    (out / "bench.md").write_text(text)
    (out / "bench.json").write_text(json.dumps(res, indent=1, default=float))
    return res


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m jscratch.bench", description=DESCRIPTION)
    p.add_argument("--quick", action="store_true", help="small sizes (about 50 s on 2 CPU cores)")
    p.add_argument("--out", default="bench_out", help="output folder (default: bench_out)")
    p.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS,
                   help="sections to run (default: all)")
    a = p.parse_args(argv)
    res = run_bench(a.sections, a.quick, a.out)
    print((Path(a.out) / "bench.md").read_text())
    return res


if __name__ == "__main__":
    main()
