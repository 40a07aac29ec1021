"""Tests of jscratch.preview: the orbit's frames include every design camera exactly, all at its
polar angle and distance, and the CLI writes the GIF and the contact sheet."""

import math

import numpy as np
import pytest

from jscratch import designfile, render


@pytest.mark.float64
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
