"""Smoke test of `python -m jscratch.bench --quick`: structure and finiteness of what it writes
(not its speed)."""

import json
import math

from jscratch import bench


def test_quick_bench_writes_finite_results(tmp_path):
    bench.main(["--quick", "--out", str(tmp_path), "--sections", "kernel", "stability"])
    res = json.loads((tmp_path / "bench.json").read_text())
    assert res["quick"] is True and res["machine"]["jax"]
    rows = res["kernel"]["rows"]
    methods = {r["method"] for r in rows}
    assert "closed form" in methods and any(m.startswith("GL n=") for m in methods)
    for r in rows:
        for k in ("ns_per_pair_fwd", "max_rel", "median_rel", "max_abs_scaled", "compile_s"):
            assert math.isfinite(r[k]) and r[k] >= 0, (r["method"], k)
        assert r["nonfinite"] == 0
    closed = next(r for r in rows if r["method"] == "closed form")
    assert closed["max_rel"] < 1e-3  # float32 closed form against the independent reference
    st = res["stability"]
    assert st["n_cases"] >= 1000
    assert st["nonfinite_values_f32"] == 0 and st["cases_with_nonfinite_gradients_f32"] == 0
    assert st["worst_f32_err_over_tol"] <= 1.0
    assert (tmp_path / "kernel_pareto.png").stat().st_size > 1000
    assert "| closed form |" in (tmp_path / "bench.md").read_text()
