"""Design file (docs/model.md §9): round trip, validation messages naming the bad scratch, SVG export."""

import os
import stat
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from jscratch.designfile import DesignError, DesignFileError, demo_design, groove_half_width, load_design, save_design, write_svg


def _arrays(n=5, seed=0, dtype=np.float64):
    rng = np.random.default_rng(seed)
    p0 = rng.uniform(0.01, 0.29, (n, 2)).astype(dtype)
    p1 = rng.uniform(0.01, 0.29, (n, 2)).astype(dtype)
    return dict(p0=p0, p1=p1, width=np.full(n, 2.5e-4, dtype), depth=np.full(n, 1.28e-4, dtype),
                alpha=np.full(n, 0.04, dtype), board=np.array([0.3, 0.3], dtype))


def test_round_trip_float32_and_views(tmp_path):
    a = _arrays(dtype=np.float32)
    views = dict(camera=np.array([[0.1, 0.2, 1.0], [0.3, 0.1, 0.9]]), light=np.array([[0.0, 0.0, 1.0]] * 2),
                 intensity=np.array([1.0, 2.0]))
    path = tmp_path / "d.npz"
    save_design(path, **a, **views)
    d = load_design(path)
    assert d.p0.dtype == np.float64 and d.n == 5
    np.testing.assert_array_equal(d.p0, a["p0"].astype(np.float64))
    np.testing.assert_array_equal(d.intensity, views["intensity"])
    np.testing.assert_allclose(d.length, np.linalg.norm(a["p1"] - a["p0"], axis=1).astype(np.float64), rtol=1e-6)
    d2 = load_design(save_design(tmp_path / "e.npz", **a) and tmp_path / "e.npz")
    assert d2.camera is None and d2.light is None


@pytest.mark.parametrize(
    "field,index,value,match",
    [
        ("p1", 3, np.nan, r"scratch 3: p1 .* not finite"),
        ("p0", 2, 0.31, r"scratch 2: p0 = .* lies off the board"),
        ("p0", 1, -1e-3, r"scratch 1: p0 = .* lies off the board"),
        ("width", 4, 0.0, r"scratch 4: width .* must be >= 1e-12 m"),
        ("alpha", 0, 1.5, r"scratch 0: alpha .* must lie in \[0.0001, 0.99\]"),
        ("alpha", 3, 1.0, r"scratch 3: alpha = 1.0 must lie in \[0.0001, 0.99\]"),
        ("depth", 2, np.inf, r"scratch 2: depth .* not finite"),
    ],
)
def test_bad_values_name_the_scratch(tmp_path, field, index, value, match):
    a = _arrays()
    if a[field].ndim == 2:
        a[field][index, 0] = value
    else:
        a[field][index] = value
    # A file written by someone else (np.savez directly) is caught on load ...
    path = tmp_path / "bad.npz"
    np.savez(path, **a)
    with pytest.raises(DesignFileError, match=match):
        load_design(path)
    # ... and save_design refuses to write it.
    with pytest.raises(DesignError, match=match):
        save_design(tmp_path / "never.npz", **a)
    assert not (tmp_path / "never.npz").exists()


def test_bad_shapes_and_files(tmp_path):
    a = _arrays()
    a["p1"] = a["p1"][:4]
    with pytest.raises(DesignError, match=r"p1 must have shape \(5, 2\)"):
        save_design(tmp_path / "x.npz", **a)
    a = _arrays()
    del a["alpha"]
    np.savez(tmp_path / "m.npz", **a)
    with pytest.raises(DesignFileError, match=r"missing array\(s\) \['alpha'\]"):
        load_design(tmp_path / "m.npz")
    with pytest.raises(DesignFileError, match="does not exist"):
        load_design(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DesignFileError, match="not a readable .npz"):
        load_design(tmp_path / "junk.npz")
    with pytest.raises(DesignError, match="camera, light and intensity go together"):
        save_design(tmp_path / "v.npz", **_arrays(), camera=np.ones((2, 3)))


def test_svg_lines_in_board_millimetres(tmp_path):
    d = demo_design(25, seed=3)
    write_svg(tmp_path / "d.svg", d)
    root = ET.parse(tmp_path / "d.svg").getroot()
    ns = {"s": "http://www.w3.org/2000/svg"}
    assert root.get("viewBox") == "0 0 300 300" and root.get("width") == "300mm"
    lines = root.findall(".//s:line", ns)
    assert len(lines) == 25
    for i, ln in enumerate(lines):
        assert ln.get("id") == f"s{i}"
        x1, y1, x2, y2 = (float(ln.get(k)) for k in ("x1", "y1", "x2", "y2"))
        # y flipped: the board edge y = Sy is the top of the page (docs/model.md §1).
        np.testing.assert_allclose([x1, 300 - y1, x2, 300 - y2], 1000 * np.r_[d.p0[i], d.p1[i]], atol=1e-4)
        np.testing.assert_allclose(float(ln.get("stroke-width")),
                                   2000 * groove_half_width(d.width[i], d.depth[i]), atol=1e-4)


def test_groove_half_width_and_demo():
    # x_max solves h(x_max) = 0 for the profile of docs/model.md §2.
    w, dd = 2.5e-4, 1.28e-4
    xm = groove_half_width(w, dd)
    assert abs(-(w / 2) * np.log(1 - 4 * xm**2 / w**2) - dd) < 1e-15
    d = demo_design(300, seed=1)
    assert d.n == 300 and np.all(d.p0 >= 0) and np.all(d.p1 <= 0.3)
    assert np.all((d.length >= 0.005 - 1e-12) & (d.length <= 0.025 + 1e-12))
    with pytest.raises(ValueError, match=r"n \(the number of scratches\) must be >= 1"):
        demo_design(0)


def test_save_design_respects_the_umask(tmp_path):
    d = demo_design(5, seed=0)
    old = os.umask(0o022)
    try:
        for mask, mode in ((0o022, 0o644), (0o077, 0o600), (0o002, 0o664)):
            os.umask(mask)
            f = tmp_path / f"d{mask:o}.npz"
            save_design(f, d.p0, d.p1, d.width, d.depth, d.alpha, d.board)
            assert stat.S_IMODE(os.stat(f).st_mode) == mode, (oct(mask), oct(os.stat(f).st_mode))
    finally:
        os.umask(old)


def test_groove_profile_round_trip(tmp_path):
    """``profile`` is stored and read back; a file without it is the paper's profile; anything
    else is refused in one line naming the field."""
    a = _arrays()
    path = tmp_path / "arc.npz"
    assert save_design(path, **a, profile="arc").profile == "arc"
    assert load_design(path).profile == "arc"
    with np.load(path) as z:
        plain = {k: z[k] for k in z.files if k != "profile"}
    np.savez(tmp_path / "old.npz", **plain)
    assert load_design(tmp_path / "old.npz").profile == "paper"
    with pytest.raises(DesignError, match="profile must be one of"):
        save_design(tmp_path / "bad.npz", **a, profile="ball")
    assert not (tmp_path / "bad.npz").exists()


def test_paths_profiles_and_stroke_widths_that_are_not_are_refused_in_one_line(tmp_path):
    """`save_design` / `load_design` given something that is not a file path, or a folder; a
    profile array that is not one name; a stroke width that is not a width."""
    d = demo_design(4)
    arrays = (d.p0, d.p1, d.width, d.depth, d.alpha, d.board)
    for bad in (None, 3, ""):
        with pytest.raises(DesignFileError, match="^save_design: expected a file path"):
            save_design(bad, *arrays)
        with pytest.raises(DesignFileError, match="^load_design: expected a file path"):
            load_design(bad)
    with pytest.raises(DesignFileError, match="^save_design: .* is a folder"):
        save_design(tmp_path, *arrays)
    assert list(tmp_path.iterdir()) == []  # nothing left behind
    save_design(tmp_path / "d.npz", *arrays)
    with np.load(tmp_path / "d.npz") as z:
        two = {**z, "profile": np.array(["arc", "paper"])}
    np.savez(tmp_path / "two.npz", **two)
    with pytest.raises(DesignFileError, match=r"profile must be one of \('paper', 'arc'\), got "
                                              r"array\(\['arc', 'paper'\]"):
        load_design(tmp_path / "two.npz")
    for bad in (float("nan"), -1.0, "a", True):
        with pytest.raises(DesignError, match="^write_svg: min_stroke_mm must be a finite width"):
            write_svg(tmp_path / "d.svg", d, min_stroke_mm=bad)
    assert not (tmp_path / "d.svg").exists()
    write_svg(tmp_path / "d.svg", d, min_stroke_mm=np.array(0.02))  # a 0-d array is a number
    assert (tmp_path / "d.svg").exists()
