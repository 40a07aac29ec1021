"""Smoke test of `python -m jscratch.bench --quick`: structure and finiteness of what it writes
(not its speed)."""

import json
import math
import shlex

import jax.numpy as jnp

from jscratch import bench, native


def test_quick_bench_writes_finite_results(tmp_path):
    bench.main(["--quick", "--out", str(tmp_path)])
    def strict(constant):  # NaN or Infinity: not JSON (a strict reader refuses the file)
        raise AssertionError(f"bench.json holds {constant}")

    res = json.loads((tmp_path / "bench.json").read_text(), parse_constant=strict)
    assert res["quick"] is True and res["machine"]["jax"]
    command = shlex.join(["python", "-m", "jscratch.bench", "--quick", "--out", str(tmp_path)])
    assert res["command"] == command  # the command line as typed, not the module's path
    assert f"Command: `{command}`" in (tmp_path / "bench.md").read_text()
    rows = res["kernel"]["rows"]
    methods = {r["method"] for r in rows}
    assert "closed form" in methods and any(m.startswith("GL n=") for m in methods)
    for r in rows:
        for k in ("ns_per_pair_fwd", "max_rel", "median_rel", "max_abs_scaled", "compile_s"):
            assert math.isfinite(r[k]) and r[k] >= 0, (r["method"], k)
        bwd = r["ns_per_pair_fwd_bwd"]  # quick mode times only the closed form's backward
        assert (bwd is None) == (r["method"] != "closed form") and (bwd is None or bwd > 0)
        assert r["nonfinite"] == 0
    closed = next(r for r in rows if r["method"] == "closed form")
    assert closed["max_rel"] < 1e-3  # float32 closed form against the independent reference
    st = res["stability"]
    assert st["n_cases"] >= 1000
    assert st["nonfinite_values_f32"] == 0 and st["cases_with_nonfinite_gradients_f32"] == 0
    assert st["worst_f32_err_over_tol"] <= 1.0
    # Every pair kernel a render can run, float32 against the float64 closed form of its groove.
    paths = {p["kernel"]: p for p in st["paths"]}
    assert set(paths) == {"ndf.pair_integral, paper profile", "arc.arc_lit_integral, arc",
                          "native, paper profile", "native, arc"}
    for name, p in paths.items():
        if "skipped" in p:
            assert name.startswith("native") and not native.available(jnp.float32), name
            continue
        assert p["nonfinite_values"] == 0 and p["cases_with_nonfinite_gradients"] == 0, name
        assert p["worst_err_over_tol"] <= 1.0 and p["cases_over_tol"] == 0, name
        assert p["worst_err_over_pixel_peak"] < 1e-4, name
    assert "| native, arc |" in (tmp_path / "bench.md").read_text() or "skipped" in paths[
        "native, arc"]
    assert (tmp_path / "kernel_pareto.png").stat().st_size > 1000
    assert "| closed form |" in (tmp_path / "bench.md").read_text()
    # Renderer, brute force and optimiser sections.
    for r in res["render"]["cases"]:
        assert r["pairs"] > 0
        for k in ("fwd_ms_per_view", "fwd_bwd_ms_per_view", "fwd_pairs_per_s", "bin_share_of_step"):
            assert math.isfinite(r[k]) and r[k] > 0, k
    cull = res["render"]["culling"]
    assert cull[0]["eps"] == 0 and cull[0]["max_err_over_peak"] == 0
    assert all(0 < c["pairs_kept"] <= 1 and 0 <= c["max_err_over_peak"] < 0.05 for c in cull)
    br = res["brute"]
    assert br["analytic_rel_rms_error"] < 1e-3  # float32 analytic vs float64 analytic
    assert all(math.isfinite(r["rel_rms_error"]) and r["time_ms"] > 0 for r in br["rows"])
    rows = res["design"]["rows"]
    assert [r["iteration"] for r in rows] == sorted(r["iteration"] for r in rows)
    assert all(len(r["ssim"]) == res["design"]["views"] for r in rows)
    assert rows[-1]["loss"] < rows[0]["loss"]  # resumed stages continue one optimisation
    for name in ("render_culling.png", "brute_vs_analytic.png", "design_ssim.png"):
        assert (tmp_path / name).stat().st_size > 1000, name


def test_cpu_model_reads_the_first_model_name(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: X\nmodel name\t: Some  CPU   @ 2.0GHz\n\n"
                    "processor\t: 1\nmodel name\t: Other CPU\n")
    assert bench.cpu_model(info) == "Some CPU @ 2.0GHz"
    # No model name line, or no file: the platform's own answer, never empty.
    (tmp_path / "bare").write_text("processor\t: 0\nmodel name\t:\n")
    for path in (tmp_path / "bare", tmp_path / "missing"):
        assert bench.cpu_model(path).strip()


def test_machine_line_names_date_cpu_and_load():
    import datetime

    info = bench.machine_info()
    today = datetime.datetime.now(datetime.timezone.utc).date().isoformat()
    assert info["date"] == today and info["cpu_model"] == bench.cpu_model()
    line = bench.machine_line(info)
    assert line.startswith(f"{today} {info['time_utc']} UTC; {info['cpu_model']}, ")
    assert f"{info['cpu_count']} CPUs" in line and "load " in line and "\n" not in line
