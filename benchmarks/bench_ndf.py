"""Kernel throughput against error: the closed form `ndf.pair_integral` and Gauss-Legendre
quadrature (n = 8 ... 128), float32 and float64, forward and forward+backward, jitted, on the CPU,
with max and median error against the independent reference on the same pairs.

A thin wrapper over section 1 of `python -m jscratch.bench` (same code, same population):

    python benchmarks/bench_ndf.py [--quick] [--out DIR]
"""

import sys

from jscratch import bench

if __name__ == "__main__":
    sys.exit(bench.main(["--sections", "kernel", *sys.argv[1:]]))
