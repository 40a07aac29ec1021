"""Issue 15: the machine profile (file -> design -> npz -> fabricate), carvable grooves (bounds never
violated while optimising; the map against an independent slope integral), the as-carved brute
render against a 1-D quadrature, the carving-time estimate by hand, and the orbit preview."""

import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy import integrate

from jscratch import designfile
from jscratch import fabricate
from jscratch import render
from jscratch.design import DesignConfig
from jscratch.design import main as design_main
from jscratch.design.carvable import groove_map
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


@pytest.mark.parametrize("key,value", [
    ("cutter_radius_mm", -1.0), ("plunge_max_mm", 0.2), ("plunge_min_mm", 0.2), ("feed_mm_min", "fast"),
    ("cutter", "flat"), ("holder", "glue"), ("board_offset_mm", [1.0]), ("overhead_s", float("nan")),
    ("drop_short", 3), ("spindle_rpm", -5.0), ("typo_mm", 1.0),
])
def test_bad_profile_values_one_line_naming_the_key(tmp_path, key, value, capsys):
    path = tmp_path / "bad.toml"
    v = "nan" if isinstance(value, float) and math.isnan(value) else json.dumps(value)
    path.write_text(f"[machine]\n{key} = {v}\n")
    with pytest.raises(ValueError) as e:
        MachineProfile.from_toml(path)
    msg = str(e.value)
    assert f"machine.{key}" in msg and str(path) in msg and "\n" not in msg
    capsys.readouterr()
    assert fabricate.main(["--dry-run", "--machine", str(path), "--out", str(tmp_path / "o" / "j")]) == 2
    err = capsys.readouterr().err
    assert f"machine.{key}" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()
    assert design_main(["--machine", str(path), "--out", str(tmp_path / "d"), "--quiet"]) == 2


def test_profile_toml_round_trip_and_old_config_name(tmp_path):
    p = MachineProfile(name="x", cutter_radius_mm=0.3, plunge_max_mm=0.2, board_offset_mm=(1.0, 2.0), spindle_rpm=1e4)
    path = tmp_path / "p.toml"
    path.write_text(p.to_toml())
    assert MachineProfile.from_toml(path) == p
    assert fabricate.MachineConfig is MachineProfile
    # `--config` still reads the same file.
    assert fabricate.main(["--dry-run", "--config", str(path), "--demo-n", "5", "--out", str(tmp_path / "o" / "j"),
                           "--quiet", "--order-time", "0.1"]) == 0
    assert "S10000" in (tmp_path / "o" / "j.gcode").read_text()


# ----------------------------------------------------------------------------------------------
# Carvable grooves.


def _fit_error_reference(w, p, R_, criterion):
    """Mean squared misfit over the cut (scipy quadrature, float64) of the paper profile of width
    `w` and half width `a` (its depth from x_max = a) against the ball's arc at plunge `p`:
    wall angles (rad^2) or heights (m^2)."""
    a = math.sqrt(2 * R_ * p - p * p)
    d = -0.5 * w * math.log1p(-((2 * a / w) ** 2))
    if criterion == "slope":
        f = lambda x: (2 * math.atan(2 * x / w) - math.asin(x / R_)) ** 2  # noqa: E731
    else:
        f = lambda x: (-0.5 * w * math.log1p(-((2 * x / w) ** 2)) - d  # noqa: E731
                       - (R_ - p - math.sqrt(R_ * R_ - x * x))) ** 2
    return integrate.quad(f, 0, a, limit=200)[0] / a


@pytest.mark.parametrize("criterion", ["height", "slope"])
def test_groove_map_is_the_least_squares_optimum(criterion):
    R_, lo, hi = 1.25e-4, 5e-6, 1e-4
    g = groove_map(R_, lo, hi, criterion)
    for p in (5e-6, 3e-5, 7e-5, 1e-4):
        w, d = (float(v) for v in g.profile_of_plunge(jnp.float64(p)))
        a = math.sqrt(2 * R_ * p - p * p)
        assert groove_half_width(w, d) == pytest.approx(a, rel=1e-6)
        best = _fit_error_reference(w, p, R_, criterion)
        # The fitted w is the optimum of an independent float64 quadrature of the same misfit.
        for f in (0.97, 1.03):
            if f * w > 2 * a:
                assert _fit_error_reference(f * w, p, R_, criterion) >= best * (1 - 1e-3)
        if criterion == "slope":
            assert math.degrees(math.sqrt(best)) <= g.rms_deg + 0.05


@settings(max_examples=25, deadline=None)
@given(r=st.floats(0.05, 1.0), lo=st.floats(0.01, 0.4), hi=st.floats(0.45, 0.95),
       z=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=16))
def test_carvable_bounds_for_any_parameter(r, lo, hi, z):
    R_ = r * 1e-3
    g = groove_map(R_, lo * R_, hi * R_)  # the default criterion
    z = jnp.asarray(z, jnp.float32)
    p = np.asarray(g.plunge(z), np.float64)
    w, d = (np.asarray(v, np.float64) for v in g.profile(z))
    assert np.all((p >= lo * R_ * (1 - 1e-6)) & (p <= hi * R_ * (1 + 1e-6)))
    assert np.all(np.isfinite(w) & np.isfinite(d) & (w > 0) & (d > 0))
    np.testing.assert_allclose(groove_half_width(w, d), np.sqrt(2 * R_ * p - p * p), rtol=2e-3)


_OPT = {}


def _tiny_optimisation():
    """A tiny carvable design problem, built once (the jitted step compiles once)."""
    if not _OPT:
        from jscratch.design.io import default_targets
        from jscratch.design.run import pair_lists, setup

        board = render.Board(shape=(SIZE, SIZE))
        views = render.views_on_circle(2, math.radians(50), board=board)
        targets, _ = default_targets(2, (SIZE, SIZE))
        # The round trip's scene and machine, so that the jitted step is compiled once for both.
        cfg = DesignConfig(n_scratches=150, iterations=1, groove="carvable", machine=_MINE)
        params, opt, ctx = setup(targets, views, board, cfg)
        pairs = pair_lists(params, ctx, cfg)  # unculled: the shared list serves every view
        _OPT.update(params=params, pairs=pairs, opt=opt, ctx=ctx)
    return _OPT["params"], _OPT["pairs"], _OPT["opt"], _OPT["ctx"]


@settings(max_examples=6, deadline=None)
@given(lr=st.sampled_from([1e-2, 1.0, 1e2, 1e4]), start=st.floats(-30.0, 30.0), seed=st.integers(0, 9))
def test_carvable_bounds_never_violated_during_optimisation(lr, start, seed):
    """Adam steps of the real jitted design step, from plunges anywhere in (and pressed against)
    the range, with learning rates up to absurd: every iterate's plunge stays in the range and
    its groove is the cut's width."""
    import equinox as eqx
    from jscratch.design.params import group_tree
    from jscratch.design.solver import step

    params, pairs, opt, ctx = _tiny_optimisation()
    z0 = params.log_width
    z = z0 + start + np.random.default_rng(seed).normal(0.0, 3.0, z0.shape).astype(np.float32)
    p_ = eqx.tree_at(lambda q: q.log_width, params, jnp.asarray(z, z0.dtype))
    lrs = group_tree(p_, {g: jnp.asarray(lr if g == "width" else 1e-3, jnp.float32)
                          for g in ("endpoints", "width", "depth", "alpha", "intensity")})
    ctx = eqx.tree_at(lambda c: c.lrs, ctx, lrs)
    o_ = opt.init(p_)
    moved = 0.0
    for _ in range(3):
        new, o_, terms, _, _, _ = step(p_, o_, pairs, ctx, opt)
        pl = np.asarray(new.plunge(), np.float64)
        s = new.scratches()
        assert np.all((pl >= 1e-5 * (1 - 1e-6)) & (pl <= 8e-5 * (1 + 1e-6)))
        np.testing.assert_allclose(groove_half_width(np.asarray(s.width, np.float64), np.asarray(s.depth, np.float64)),
                                   np.sqrt(2 * 2e-4 * pl - pl**2), rtol=2e-3)
        moved = max(moved, float(np.abs(np.asarray(new.log_width) - np.asarray(p_.log_width)).max()))
        p_ = new
    if abs(start) <= 10:  # the plunges are optimised, not frozen (past ~17 the float32 map is
        assert moved > 0  # saturated against its bound: a zero gradient, which Adam leaves alone)


# ----------------------------------------------------------------------------------------------
# As carved, estimate, preview.


def test_ball_brute_render_against_quadrature():
    """One scratch across a pixel, the ball's groove: D_P S_P = L * integral of GGX(n(x).h) dx."""
    from jscratch.brute import brute_sums

    Rb, p, alpha = 2e-3, 6e-4, 0.3
    board = render.Board(shape=(1, 1), Sx=0.01, Sy=0.01)
    views = render.Views(jnp.array([[0.004, 0.005, 0.05]]), jnp.array([[0.008, 0.005, 0.04]]), 1.0)
    sc = render.Scratches(jnp.array([[0.005, 0.0]]), jnp.array([[0.005, 0.01]]), 1e-3, p, alpha)
    D, c = brute_sums(sc, views, board, n=96, ball_radius=Rb)
    a = math.sqrt(2 * Rb * p - p * p)
    ctr = np.array([0.005, 0.005, 0.0])
    wo = (np.array([0.004, 0.005, 0.05]) - ctr)
    wi = (np.array([0.008, 0.005, 0.04]) - ctr)
    h = wo / np.linalg.norm(wo) + wi / np.linalg.norm(wi)
    h /= np.linalg.norm(h)
    # Local frame: t = +y, b = (t_y, -t_x) = (1, 0): local x is board x.
    def ggx(x):
        n = np.array([-x, 0.0, math.sqrt(Rb * Rb - x * x)]) / Rb
        cth = float(n @ h)
        return 0.0 if cth <= 0 else alpha**2 / (math.pi * (cth * cth * (alpha**2 - 1) + 1) ** 2)
    ref = 0.01 * integrate.quad(ggx, -a, a, limit=200)[0] / 1e-4
    assert float(c[0]) == pytest.approx(2 * a * 0.01 / 1e-4, rel=2e-2)
    assert float(D[0, 0]) == pytest.approx(ref, rel=3e-2)


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


def test_orbit_preview_on_a_tiny_design(tmp_path):
    from PIL import Image
    from jscratch.preview import main, orbit_views

    d = designfile.demo_design(60)
    views = render.views_on_circle(3, math.radians(50))
    path = tmp_path / "tiny.npz"
    designfile.save_design(path, d.p0, d.p1, d.width, d.depth, d.alpha, d.board, np.asarray(views.camera),
                           np.asarray(views.light), np.array([1.0, 2.0, 3.0]))
    d = designfile.load_design(path)
    cams, light, az, marks = orbit_views(d, 10)
    # Every design camera is one of the frames, exactly; all frames at its polar angle and distance.
    for j in range(3):
        k = int(np.flatnonzero(marks == j)[0])
        np.testing.assert_allclose(cams[k], d.camera[j], atol=1e-12)
    ctr = np.array([0.15, 0.15, 0.0])
    np.testing.assert_allclose(np.linalg.norm(cams - ctr, axis=1), 1.0, rtol=1e-9)
    np.testing.assert_allclose(light, d.light[0])
    assert main([str(path), "--frames", "5", "--size", "16", "--batch", "2", "--quiet",
                 "--out", str(tmp_path / "o" / "tiny")]) == 0
    gif = Image.open(tmp_path / "o" / "tiny.orbit.gif")
    assert gif.n_frames == 5 and gif.size == (16, 16)
    assert (tmp_path / "o" / "tiny.orbit_sheet.png").stat().st_size > 0
    assert main([str(tmp_path / "missing.npz"), "--quiet"]) == 2
