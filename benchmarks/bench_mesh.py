"""A design step on a mesh of 1, 2 and 4 forced CPU devices: step time and the bytes its
collectives move, against the number of devices.

The bytes are read from the compiled step (XLA's HLO): every all-reduce, all-gather,
reduce-scatter, all-to-all and collective-permute with the size of its result, and the model's
per-device traffic of a ring (all-reduce ``2 (D-1)/D`` of the payload, all-gather ``(D-1)/D``).
Forced CPU devices share this machine's cores: the times show the overhead of the mesh, not a
speed-up (one CPU device already runs on every core); the GPU figures of `benchmarks/RESULTS.md`
come from the model, not from a run.

    python benchmarks/bench_mesh.py [N_SCRATCHES] [RES] [VIEWS]     (default 5000 128 3)
"""

import argparse
import os
import re
import time

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=4")

import jax  # noqa: E402
import numpy as np  # noqa: E402

from jscratch.design import DesignConfig, solver  # noqa: E402
from jscratch.design import mesh as mesh_mod  # noqa: E402
from jscratch.design.run import check_inputs, pair_lists, setup  # noqa: E402

_BYTES = {"f32": 4, "s32": 4, "u32": 4, "pred": 1, "s8": 1, "u8": 1, "f64": 8, "s64": 8}
_COLL = re.compile(r"=\s+(.+?)\s+(all-reduce|all-gather|reduce-scatter|all-to-all|"
                   r"collective-permute)(?:-start)?\(")
_HEAD = re.compile(r"^(?:ENTRY\s+)?%([\w.\-]+)\s.*\{\s*$")
_CALLS = re.compile(r"(?:calls|to_apply|body|condition|true_computation|false_computation)"
                    r"=%([\w.\-]+)")


def collective_bytes(hlo: str) -> dict[str, int]:
    """Result bytes of each kind of collective a step runs, from its HLO module's text: those of
    the computations reachable from the entry, leaving out the branches of ``error_if`` checks
    (they run only when a check fails). Counted once each (a collective inside a loop body would
    run once per trip: the step has none)."""
    comps: dict[str, list[str]] = {}
    entry, name = None, None
    for line in hlo.splitlines():
        m = _HEAD.match(line)
        if m:
            name = m.group(1)
            comps[name] = []
            if line.startswith("ENTRY"):
                entry = name
        elif name is not None:
            comps[name].append(line)
    seen, todo = set(), [entry]
    while todo:
        c = todo.pop()
        if c in seen or c not in comps:
            continue
        seen.add(c)
        for line in comps[c]:
            if "conditional(" in line and "error_if" in line:
                continue  # a failed check's branch
            todo.extend(_CALLS.findall(line))
    out: dict[str, int] = {}
    for c in seen:
        for line in comps[c]:
            for shapes, kind in _COLL.findall(line.split(", metadata=")[0]):
                size = 0
                for dt, dims in re.findall(r"(\w+)\[([\d,]*)\]", shapes):
                    size += _BYTES.get(dt, 4) * int(np.prod([int(d) for d in dims.split(",")
                                                             if d]))
                out[kind] = out.get(kind, 0) + size
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("n", nargs="?", type=int, default=5000, help="scratches (default 5000)")
    parser.add_argument("res", nargs="?", type=int, default=128, help="image side (default 128)")
    parser.add_argument("m", nargs="?", type=int, default=3, help="views (default 3)")
    args = parser.parse_args()
    n, res, m = args.n, args.res, args.m
    rng = np.random.default_rng(0)
    targets = rng.uniform(0.2, 0.8, (m, res, res)).astype(np.float32)
    config = DesignConfig(n_scratches=n, iterations=10, prune_every=0, discard=False)
    tnp, views, board = check_inputs(targets, None, None, config)
    print(f"{n} scratches, {res}x{res}, {m} views, float32; jax {jax.__version__}, "
          f"{os.cpu_count()} CPU cores")
    print("| devices | step s (median of 5) | all-reduce B | all-gather B | other B "
          "| ring traffic per device B |")
    print("|---|---|---|---|---|---|")
    for d in (1, 2, 4):
        mesh = mesh_mod.resolve(mesh_mod.sub_mesh(d), board, config)
        params, optimizer, ctx = setup(tnp, views, board, config, mesh)
        lists = pair_lists(params, ctx, config)
        p, o = mesh_mod.place((params, optimizer.init(params)), mesh)
        hlo = solver.lower_step(p, o, lists, ctx, optimizer).compile().compiled.as_text()
        coll = collective_bytes(hlo) if mesh is not None else {}
        times = []
        for i in range(6):
            t0 = time.perf_counter()
            new, o2, terms, *_ = solver.step(p, o, lists, ctx, optimizer)
            jax.block_until_ready(new)
            times.append(time.perf_counter() - t0)
        ar, ag = coll.get("all-reduce", 0), coll.get("all-gather", 0)
        other = sum(coll.values()) - ar - ag
        ring = (2 * ar + ag + other) * (d - 1) / d
        print(f"| {d} | {np.median(times[1:]):.3f} | {ar:,} | {ag:,} | {other:,} | {ring:,.0f} |",
              flush=True)


if __name__ == "__main__":
    main()
