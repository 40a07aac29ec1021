"""Same small design, three paths (unculled, culled, prune/re-seed): the final losses as exact
reprs, to compare two checkouts bit for bit (a refactor must not change results).

    PYTHONPATH=/path/to/old/checkout python benchmarks/compare_design.py > old.json
    python benchmarks/compare_design.py > new.json && diff old.json new.json

3 views of `views_on_circle(3, 50 deg)`, 96 px, 3,000 scratches, 12 iterations, seed 0, discard on,
carvable grooves (the command line's default, named so that older checkouts run the same).
``--machine FILE`` designs for that machine profile (TOML; `DesignConfig.machine`), e.g. the
shipped one with ``groove_fit = "height"`` to compare with a checkout whose default groove was the
fitted paper profile.
"""

from __future__ import annotations

import json
import argparse
import math
import sys
import tomllib

import jscratch
from jscratch.design import DesignConfig
from jscratch.design.io import default_targets
from jscratch.design.run import design
from jscratch.scene import Board, views_on_circle

PATHS = {
    "unculled": {},
    "culled": dict(cull_eps=1e-3, coverage_eps=1e-3),
    "prune": dict(prune_every=4, prune_fraction=0.05),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machine", metavar="FILE", help="machine profile TOML (default: shipped)")
    args = ap.parse_args()
    machine = {}
    if args.machine:
        with open(args.machine, "rb") as f:
            machine = {"machine": tomllib.load(f)["machine"]}
    print(f"jscratch from {jscratch.__file__}", file=sys.stderr)
    out = {}
    for name, kw in PATHS.items():
        targets, _ = default_targets(3, (96, 96))
        board = Board(shape=(96, 96))
        views = views_on_circle(3, math.radians(50), board=board)
        r = design(targets, views, board, DesignConfig(n_scratches=3000, iterations=12,
                                                       groove="carvable", **machine, **kw))
        out[name] = [repr(float(r.metrics["loss"])), r.metrics["kept"],
                     r.metrics["pairs_per_view"]]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
