"""Pixel-axis sharding of the renderer on forced CPU devices: per-device compiled memory of a
gradient step and the load balance of the per-strip pair lists, for 1, 2 and 4 shards.

Forced CPU devices share this machine's cores, so times here say nothing about several GPUs; the
memory (XLA's per-device compiled estimate: arguments + outputs + temporaries) and the balance
(valid pairs over padded slots; the slowest device does the longest segment) carry over.

    python benchmarks/bench_shard.py [N_SCRATCHES] [RES]     (default 60000 512)
"""

import argparse
import os

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=4")

import jax
import jax.numpy as jnp
import numpy as np

from jscratch import render
from jscratch.bench.rendering import compiled_mib, scene

_parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
_parser.add_argument("n", nargs="?", type=int, default=60000, help="scratches (default 60000)")
_parser.add_argument("res", nargs="?", type=int, default=512, help="image side, px (default 512)")
_args = _parser.parse_args()
n, res = _args.n, _args.res
views = 4
board, s, v = scene(n, res, views)
target = jnp.full((views, res, res), 0.5, jnp.float32)
print(f"{n} scratches, {res}x{res}, {views} views, float32; jax {jax.__version__}")
print("| shards | pair slots | valid pairs | fill (valid / slots) | value+grad MiB per device |")
print("|---|---|---|---|---|")
for k in (1, 2, 4):
    mesh = None if k == 1 else jax.sharding.Mesh(np.asarray(jax.devices()[:k]), ("p",))
    pairs = render.bin_pairs(s, board, shards=k)

    def loss(s, v, pairs, mesh=mesh):
        return jnp.mean((render.display(render.render_pairs(s, v, board, pairs, mesh=mesh)) - target) ** 2)

    c = jax.jit(jax.value_and_grad(loss, (0, 1))).lower(s, v, pairs).compile(
        render.grad_compiler_options())
    slots = int(pairs.valid.shape[0])
    valid = int(np.asarray(pairs.valid).sum())
    print(f"| {k} | {slots:,} | {valid:,} | {valid / slots:.2f} | {compiled_mib(c):.0f} |",
          flush=True)
