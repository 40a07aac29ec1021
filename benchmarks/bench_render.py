"""Benchmark the multi-view renderer: sections ``render`` and ``brute`` of `jscratch.bench`
(`jscratch.bench.rendering`), in full mode, written as a Markdown fragment for RESULTS.md.

    python benchmarks/bench_render.py                 # both sections, full size
    python benchmarks/bench_render.py --sections render

Writes ``benchmarks/results/render.md`` and the JSON/plots under ``benchmarks/results/render/``.
"""

from __future__ import annotations

import argparse
import os
import sys


from jscratch.bench import run_bench

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sections", nargs="+", default=["render", "brute"],
                    choices=["render", "brute"])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    out = os.path.join(HERE, "results", "render")
    res = run_bench(args.sections, args.quick, out)
    m = res["machine"]
    text = ["# Renderer benchmark (`python benchmarks/bench_render.py "
            + " ".join(sys.argv[1:]) + "`)", "",
            "Machine: " + ", ".join(f"{k} {v}" for k, v in m.items()), ""]
    for s in args.sections:
        text += [f"## {s}", "", res[s]["markdown"], ""]
    text = "\n".join(text)
    print(text)
    with open(os.path.join(HERE, "results", "render.md"), "w") as f:
        f.write(text + "\n")


if __name__ == "__main__":
    main()
