"""`python -m jscratch.bench`: run time against error, numerical stress, and the recorded results.

A thin CLI over `run_bench(sections, quick, out)`. Every timing compiles first (compile time is
reported apart), then takes the median of repeated `block_until_ready` runs. Results go to
``OUT/bench.json``, ``OUT/bench.md`` (also printed) and PNG plots in ``OUT``.

**Sections:**

1. ``kernel``: the closed form `ndf.pair_integral` against Gauss-Legendre quadrature
   (`ndf.pair_integral_quadrature`, n = 8 ... 128), float32 and float64: time per pair
   (forward and forward+backward) against max and median error on a fixed population (the
   realistic random pairs plus the adversarial families of `jscratch.bench.ndf_cases`), the error taken
   against the independent reference `jscratch.bench.ndf_reference` (exact clipping, adaptive
   quadrature). Pareto plot ``kernel_pareto.png``.
2. ``stability``: a sweep over alpha (1e-4 ... 0.9), grazing ``hz``, ``hy`` near 0, width over
   footprint and depth over width, footprint positions across the groove, through every pair
   kernel a render can run (jnp and native, the paper's profile and the ball cutter's arc);
   worst float32 error (against the float64 closed form of the same groove, itself checked
   against the reference in the test suite) and the count of non-finite values and gradients.
   10^5+ cases in full mode.
3. ``render``: forward and forward+backward time per view, pairs per second, binning share and
   peak memory for the standard scenes, and culling ``eps`` against image error.
4. ``brute``: the analytic renderer against the brute-force supersampled renderer: the time each
   needs to reach the same error, and the speed-up.
5. ``design``: SSIM per view against iterations and time for the default design.

``--quick`` shrinks every section (30-45 s on a 2-core CPU, mostly compilation; the figures
are in benchmarks/RESULTS.md, "Quick bench"); the test suite runs it as a smoke test.

**Modules:** `jscratch.bench.timing` (helpers), `jscratch.bench.kernel` (sections 1-2),
`jscratch.bench.rendering` (sections 3-5), `jscratch.bench.cli` (`run_bench`, `main`), and the
kernel's test and bench fixtures: `jscratch.bench.ndf_cases` (adversarial and random pair cases)
and `jscratch.bench.ndf_reference` (the independent reference: exact clipping, adaptive
quadrature).
"""


from jscratch.bench.cli import SECTIONS as SECTIONS, main as main, run_bench as run_bench
from jscratch.bench.timing import (
    compile_once as compile_once,
    cpu_model as cpu_model,
    machine_info as machine_info,
    machine_line as machine_line,
    md_table as md_table,
    median_time as median_time,
    time_compiled as time_compiled,
)
