"""Tests of jscratch.design.maker: a machine profile carried from its file through the design and
its npz to fabricate (plunges in range cutting exactly the design's grooves, the recorded feeds,
a different cutter refused), and the carving-time estimate by hand."""

import json

import numpy as np
import pytest

from jscratch import designfile
from jscratch import fabricate
from jscratch.design import main as design_main
from jscratch.designfile import groove_half_width
from jscratch.machine import MachineProfile, carving_seconds

SIZE = 16


def _toml(path, **kw):
    lines = ["[machine]"] + [f"{k} = {json.dumps(v)}" for k, v in kw.items()]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


# ----------------------------------------------------------------------------------------------
# The profile file.


_MINE = dict(name="mine", cutter_radius_mm=0.2, plunge_min_mm=0.01, plunge_max_mm=0.08, feed_mm_min=600.0,
             overhead_s=0.5)


def test_profile_round_trip_file_design_npz_fabricate(tmp_path, capsys):
    prof = _toml(tmp_path / "mine.toml", **_MINE)
    out = tmp_path / "run"
    args = ["--views", "2", "--size", str(SIZE), "--scratches", "150", "--iterations", "1",
            "--no-discard", "--machine", prof, "--as-carved-samples", "0", "--out", str(out), "--quiet"]
    assert design_main(args) == 0
    d = designfile.load_design(out / "design.npz")
    assert d.machine == MachineProfile.from_toml(prof).to_dict()
    # Every recorded plunge lies in the file's range and cuts exactly the design's groove.
    assert d.plunge.shape == (d.n,) and d.plunge.min() >= 1e-5 and d.plunge.max() <= 8e-5
    R_ = 2e-4
    np.testing.assert_allclose(np.sqrt(2 * R_ * d.plunge - d.plunge**2),
                               groove_half_width(d.width, d.depth), rtol=1e-4)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["machine"]["name"] == "mine" and metrics["groove"] == "carvable"
    assert metrics["carving"]["estimated_seconds"] > d.n * 0.5  # overhead_s alone
    # Fabricate uses the recorded profile (feed 600, R 0.2) without being told.
    job = tmp_path / "new" / "job"
    assert fabricate.main([str(out / "design.npz"), "--dry-run", "--out", str(job), "--order-time", "1",
                           "--quiet"]) == 0
    info = json.loads((tmp_path / "new" / "job.summary.json").read_text())
    assert info["fit"]["mode"] == "design" and info["fit"]["unreachable"] == 0
    assert info["cutter_radius_mm"] == 0.2
    code = (tmp_path / "new" / "job.gcode").read_text()
    assert "F600.0" in code and "F900.0" not in code
    zs = [float(w[1:]) for line in code.splitlines() if line.startswith("G1 Z") for w in line.split()[1:2]]
    assert len(zs) == d.n and all(-0.08 - 1e-3 <= z <= -0.01 + 1e-3 for z in zs)
    # A different cutter is refused, naming the key; feeds alone only warn.
    other = _toml(tmp_path / "other.toml", cutter_radius_mm=0.125)
    capsys.readouterr()
    assert fabricate.main([str(out / "design.npz"), "--dry-run", "--out", str(tmp_path / "x" / "j"),
                           "--machine", other]) == 2
    err = capsys.readouterr().err
    assert "machine mismatch" in err and "cutter_radius_mm" in err and err.count("\n") == 1
    assert not (tmp_path / "x").exists()  # refused before anything is written
    assert fabricate.main([str(out / "design.npz"), "--dry-run", "--out", str(tmp_path / "y" / "j"),
                           "--feed", "700", "--order-time", "1"]) == 0
    assert "differ from the design's recorded profile" in capsys.readouterr().err
    assert "F700.0" in (tmp_path / "y" / "j.gcode").read_text()


# ----------------------------------------------------------------------------------------------
# The carving-time estimate.


def test_carving_estimate_by_hand():
    prof = MachineProfile(feed_mm_min=600.0, rapid_mm_min=1200.0, plunge_mm_min=60.0, safe_z_mm=2.0,
                          overhead_s=0.5)
    # Two 10 mm scratches, 5 mm apart, starting 0 mm from the tool: travel 5 mm.
    t = carving_seconds(prof, n=2, cut_mm=20.0, travel_mm=5.0, plunge_mm_total=0.1)
    by_hand = (20 / 10 + 5 / 20 + 0.1 / 1 + 2 * (2 * 2 / 20) + 2 * (2 / 1)) + 2 * 0.5
    assert t == pytest.approx(by_hand)
    from jscratch.design.maker import carving_estimate

    d = designfile.validate_design([[0.0, 0.0], [0.0, 0.015]], [[0.0, 0.01], [0.0, 0.025]],
                                   [2.5e-4] * 2, [1.28e-4] * 2, [0.04] * 2, [0.3, 0.3])
    est = carving_estimate(d, prof, time_limit=0.1, plunge=np.array([5e-5, 5e-5]))
    assert est["travel_m"] == pytest.approx(0.005) and est["cut_length_m"] == pytest.approx(0.02)




def test_the_default_carving_estimate_is_the_greedy_toolpath_on_every_run():
    """With no 2-opt time (`save_result`'s default) the estimate is the greedy order with the best
    directions, the same on every run: its travel equals `toolpath`'s greedy order and
    directions computed here, and its hours are `carving_seconds` of that travel."""
    from jscratch import toolpath
    from jscratch.design.maker import carving_estimate

    rng = np.random.default_rng(3)
    p0 = rng.uniform(0.01, 0.29, (400, 2))
    p1 = p0 + rng.normal(0, 0.004, (400, 2))
    n = len(p0)
    d = designfile.validate_design(p0, p1, [2.5e-4] * n, [1.28e-4] * n, [0.04] * n, [0.3, 0.3])
    prof = MachineProfile()
    plunge = np.full(n, 5e-5)
    a = carving_estimate(d, prof, time_limit=0, plunge=plunge)
    b = carving_estimate(d, prof, time_limit=0, plunge=plunge)
    a.pop("ordering_seconds"), b.pop("ordering_seconds")
    assert a == b
    q0, q1 = 1000 * d.p0, 1000 * d.p1
    order, _ = toolpath.greedy_order(q0, q1, (0.0, 0.0))
    flipped = toolpath.best_directions(q0, q1, order, (0.0, 0.0))
    travel = toolpath.path_travel(q0, q1, order, flipped, (0.0, 0.0))
    assert a["travel_m"] == pytest.approx(travel / 1000, rel=1e-12)
    cut = float(np.hypot(*(q1 - q0).T).sum())
    assert a["estimated_seconds"] == pytest.approx(carving_seconds(
        prof, n=n, cut_mm=cut, travel_mm=travel, plunge_mm_total=1000 * plunge.sum()), rel=1e-12)
    improved = carving_estimate(d, prof, time_limit=5.0, plunge=plunge)
    assert improved["travel_m"] <= a["travel_m"]


def test_as_carved_refuses_bad_arguments_by_their_names():
    """`maker.as_carved`: a sample count, an image shape or a design render that is not one is
    refused in one line naming it (not as non-finite images further on); good ones render."""
    from jscratch.design.maker import as_carved
    from jscratch.scene import Board, views_on_circle

    d = designfile.demo_design(30, seed=4)
    v = views_on_circle(2, board=Board(shape=(SIZE, SIZE), Sx=float(d.board[0]),
                                       Sy=float(d.board[1])))
    d = d._replace(camera=np.asarray(v.camera, np.float64), light=np.asarray(v.light, np.float64),
                   intensity=np.asarray(v.intensity, np.float64))
    prof = MachineProfile()
    for bad in (0, -1, 2.5, True):
        with pytest.raises(designfile.DesignError, match="^as carved: samples must be an int >= 1"):
            as_carved(d, prof, (SIZE, SIZE), samples=bad)
    for bad in ((SIZE,), (SIZE, 0), (SIZE, 2.5), "ab", None, (SIZE, 0, SIZE), (SIZE, 16.5, SIZE)):
        with pytest.raises(designfile.DesignError, match=r"^as carved: shape must be \(H, W\)"):
            as_carved(d, prof, bad, samples=2)
    with pytest.raises(designfile.DesignError,
                       match=r"design_display must have shape \(2, 16, 16\)"):
        as_carved(d, prof, (SIZE, SIZE), np.zeros((SIZE, SIZE)), samples=2)
    out = as_carved(d, prof, (SIZE, SIZE), samples=2)
    assert len(out["ssim"]) == 2 and np.all(np.isfinite(out["display"]))
