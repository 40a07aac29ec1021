#!/usr/bin/env bash
# One GPU, the jnp pair kernel (the native kernel is CPU-only): the default design, the paper's five
# views x 80,000 scratches, and `python -m jscratch.bench --quick` (kernel accuracy in float32 and
# float64 against the independent reference, the stability sweep's non-finite counts), each under
# its own time limit. Logs and each design's metrics.json go to OUT (default ./gpu_out), with the
# GPU's peak memory per design.
#
#   bash benchmarks/bench_gpu.sh [OUT]
#
# Needs jscratch importable (installed, or PYTHONPATH at the repository root) and a JAX that sees
# the GPU.
set -u
OUT=${1:-${OUT:-gpu_out}}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
PY=${PYTHON:-python3}
WORK=$(mktemp -d)

nvidia-smi -L 2>&1 | tee "$OUT/machine.txt"
$PY - <<'EOF' 2>&1 | tee -a "$OUT/machine.txt"
import jax, equinox, optax, numpy, platform
print("python", platform.python_version(), "jax", jax.__version__, "equinox", equinox.__version__,
      "optax", optax.__version__, "numpy", numpy.__version__)
print("devices", jax.devices(), "backend", jax.default_backend())
EOF

design() {  # design NAME LIMIT_S ARGS...: one design, its metrics.json and the GPU's peak memory
  local name=$1 limit=$2; shift 2
  /usr/bin/time -f "wall %e s, host peak %M kB" timeout "$limit" $PY - "$WORK/$name" "$@" <<'EOF' \
      2>&1 | tee "$OUT/$name.log"
import sys, time
import jax
from jscratch.design.cli import main
t = time.perf_counter()
rc = main(["--out", sys.argv[1], "--quiet", *sys.argv[2:]])
stats = jax.devices()[0].memory_stats() or {}
print(f"rc {rc}, main {time.perf_counter() - t:.1f} s, device peak "
      f"{stats.get('peak_bytes_in_use', 0) / 2**30:.2f} GiB")
EOF
  cp "$WORK/$name/metrics.json" "$OUT/$name.metrics.json" 2>/dev/null
}

design default 170
design paper5x80k 230 --views 5 --scratches 80000
timeout 170 $PY -m jscratch.bench --quick --out "$WORK/bench" 2>&1 | tail -80 >"$OUT/bench.log"
cp "$WORK/bench/bench.json" "$OUT/bench.json" 2>/dev/null
tail -40 "$OUT/bench.log"
