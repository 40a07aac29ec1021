"""`benchmarks/bench_seeds.py`'s paired comparison: its table against the means, paired
differences and standard errors computed here with numpy, on made-up runs (no design is run)."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_seeds.py"


@pytest.fixture(scope="module")
def seeds():
    spec = importlib.util.spec_from_file_location("bench_seeds", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run(arm, seed, rng):
    return {"arm": arm, "seed": seed, "args": [], "ssim": list(rng.uniform(0.7, 0.9, 2)),
            "ghosting": list(rng.uniform(0.1, 0.3, 2)), "loss": rng.uniform(0.009, 0.011),
            "kept": int(rng.integers(18000, 20000)), "time_total": rng.uniform(25, 30),
            "time_step_median": rng.uniform(0.15, 0.2)}


def _cells(md, label):
    line = next(x for x in md.splitlines() if x.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split("|")[1:]]


def test_table_pairs_the_seeds(seeds):
    rng = np.random.default_rng(0)
    rows = [_run(a, s, rng) for s in (3, 5, 9) for a in ("ref", "new")]
    rows.append(_run("new", 11, rng))  # a seed without its reference run is left out
    md = seeds.table(rows, ["ref", "new"])
    assert md.startswith("3 seeds (3, 5, 9)")
    by = {(r["arm"], r["seed"]): r for r in rows}
    ref = [by["ref", s] for s in (3, 5, 9)]
    new = [by["new", s] for s in (3, 5, 9)]
    means, diffs = _cells(md, "new"), _cells(md, "new - ref")
    d = np.array([b["ghosting"][1] - a["ghosting"][1] for a, b in zip(ref, new)])
    assert diffs[3] == f"{d.mean():+.4f} +- {d.std(ddof=1) / np.sqrt(3):.4f}"  # ghosting 2
    rel = np.array([100 * (b["kept"] / a["kept"] - 1) for a, b in zip(ref, new)])
    assert diffs[5] == f"{rel.mean():+.1f} +- {rel.std(ddof=1) / np.sqrt(3):.1f} %"
    assert float(means[0]) == pytest.approx(np.mean([r["ssim"][0] for r in new]), abs=5e-5)
    assert means[5] == f"{np.mean([r['kept'] for r in new]):.0f}"


def test_runs_are_read_back_not_repeated(seeds, tmp_path):
    """A run whose metrics.json exists is read (an interrupted comparison continues)."""
    folder = tmp_path / "a_s4"
    folder.mkdir()
    m = {"ssim": [0.8], "ghosting": [0.2], "loss": 0.01, "kept": 10, "time_total": 1.0,
         "time_step_median": 0.1, "psnr": [20.0]}
    (folder / "metrics.json").write_text(json.dumps(m))
    r = seeds.run("a", ["--no-such-option"], 4, tmp_path)  # (it would fail if it ran)
    assert r["ssim"] == [0.8] and r["seed"] == 4 and r["args"] == ["--no-such-option"]


def test_arms_are_parsed_or_refused(seeds):
    assert seeds.parse_arm('skip=--skip-eps 5e-5 --seed-note "a b"') == (
        "skip", ["--skip-eps", "5e-5", "--seed-note", "a b"])
    assert seeds.parse_arm("full=") == ("full", [])
    assert seeds.parse_seeds("0-2,7") == [0, 1, 2, 7]
    with pytest.raises(Exception, match="NAME=ARGS"):
        seeds.parse_arm("--skip-eps 0")
