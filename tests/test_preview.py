"""Tests of jscratch.preview: the orbit's frames include every design camera exactly, all at its
polar angle and distance, and the CLI writes the GIF and the contact sheet."""

import math
import os

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


def test_preview_writes_both_files_or_neither_and_lights_a_design_with_an_unlit_view(tmp_path,
                                                                                    capsys):
    """A view of intensity 0 (a valid design) does not black out the orbit: the default light is
    the geometric mean of the lit views' intensities, and the orbit's frame at a design view
    equals the design's own render of that view at that intensity. When the sheet cannot be
    written, no GIF is left either (nor an earlier run's files replaced)."""
    from PIL import Image
    from jscratch.preview import main, render_orbit
    from jscratch.scene import Board, Scratches, Views
    from jscratch.shading import display

    d = designfile.demo_design(80, seed=1)
    views = render.views_on_circle(2, math.radians(50))
    path = tmp_path / "d.npz"
    designfile.save_design(path, d.p0, d.p1, d.width, d.depth, d.alpha, d.board,
                           np.asarray(views.camera), np.asarray(views.light), np.array([0.0, 9.0]))
    d = designfile.load_design(path)
    frames, az, marks = render_orbit(d, frames=4, size=16, batch=4, progress=False)
    k = int(np.flatnonzero(marks == 1)[0])
    f32 = np.float32
    s = Scratches(d.p0.astype(f32), d.p1.astype(f32), d.width.astype(f32), d.depth.astype(f32),
                  d.alpha.astype(f32), profile=d.profile)
    own = display(render.render(s, Views(d.camera[1:2].astype(f32), d.light[1:2].astype(f32),
                                         np.full(1, 9.0, f32)),
                                Board(shape=(16, 16), Sx=d.board[0], Sy=d.board[1])))
    np.testing.assert_allclose(frames[k], np.clip(np.asarray(own)[0], 0, 1), atol=1e-5)
    assert frames[k].max() > 0.1

    out = tmp_path / "o"
    out.mkdir()
    (out / "p.orbit_sheet.png").mkdir()  # the sheet cannot be written
    args = [str(path), "--frames", "3", "--size", "8", "--quiet", "--out", str(out / "p")]
    assert main(args) == 1
    assert "error: " in capsys.readouterr().err
    assert sorted(os.listdir(out)) == ["p.orbit_sheet.png"]
    (out / "p.orbit_sheet.png").rmdir()
    import jscratch.preview as preview_mod

    def stopped(*a, **k):
        raise KeyboardInterrupt  # (Ctrl-C, or SIGTERM / SIGHUP through signals_interrupt)

    with pytest.MonkeyPatch.context() as m:
        m.setattr(preview_mod, "render_orbit", stopped)
        assert main(args) == 130
    assert capsys.readouterr().err == "error: interrupted\n" and os.listdir(out) == []
    assert main(args) == 0
    assert sorted(os.listdir(out)) == ["p.orbit.gif", "p.orbit_sheet.png"]
    assert Image.open(out / "p.orbit.gif").n_frames == 3


def test_orbit_and_writers_refuse_bad_arguments_in_one_line(tmp_path):
    """A design without views is refused with the command line's words; `frames`, `batch` and
    `fps` out of range, and writers given no frames, are one-line `InputError`s."""
    from jscratch.errors import InputError
    from jscratch.preview import orbit_views, render_orbit, write_gif, write_sheet

    bare = designfile.demo_design(20)
    assert bare.camera is None
    for call, where in ((lambda: render_orbit(bare, frames=3, size=8, progress=False),
                         "render_orbit"), (lambda: orbit_views(bare, 3), "orbit_views")):
        with pytest.raises(InputError, match=rf"^{where}: the design has no views \(camera, "
                                             r"light, intensity\) to orbit$"):
            call()
    d = designfile.demo_design(20)
    views = render.views_on_circle(2, math.radians(50))
    path = tmp_path / "d.npz"
    designfile.save_design(path, d.p0, d.p1, d.width, d.depth, d.alpha, d.board,
                           np.asarray(views.camera), np.asarray(views.light), np.ones(2))
    d = designfile.load_design(path)
    for kw, match in ((dict(frames=0), "`frames` must be an int >= 1, got 0"),
                      (dict(frames=-1), "`frames` must be an int >= 1, got -1"),
                      (dict(frames=2, batch=0), "`batch` must be an int >= 1, got 0")):
        with pytest.raises(InputError, match=f"^render_orbit: {match}$"):
            render_orbit(d, size=8, progress=False, **kw)
    frames, marks, az = np.zeros((2, 8, 8)), np.array([0, -1]), np.array([0.0, 1.0])
    for fps in (0, -1.0, float("nan"), 0.09, 51.0, 2000.0):  # 2000: a GIF frame time of 0
        with pytest.raises(InputError, match=r"^write_gif: `fps` must be a number in \[0.1, 50\] "
                                             rf"\(frames per second\), got {fps}$"):
            write_gif(tmp_path / "a.gif", frames, marks, az, fps=fps)
    with pytest.raises(InputError, match=r"^write_gif: `frames` is empty"):
        write_gif(tmp_path / "a.gif", [], [], [])
    with pytest.raises(InputError, match=r"^write_sheet: `frames` is empty"):
        write_sheet(tmp_path / "a.png", [], [], [])
    assert not list(tmp_path.glob("a.*"))
    for bad in (str(path), None):  # a path is not a design: named as what it is
        with pytest.raises(InputError, match="^render_orbit: design must be a jscratch Design"):
            render_orbit(bad, frames=2, size=8, progress=False)
    write_gif(tmp_path / "b.gif", frames, marks, az, fps=np.array(8.0))  # a 0-d array is a number
    assert (tmp_path / "b.gif").exists()
    from PIL import Image
    from PIL import ImageSequence
    many = np.linspace(0, 1, 8)[:, None, None] * np.ones((8, 8, 8))  # eight different frames
    many_marks, many_az = -np.ones(8, int), np.linspace(0, 1, 8)
    for fps in (50, 0.1, 3, 7, 8):  # frame times as the GIF stores them, fps kept on average
        write_gif(tmp_path / "c.gif", many, many_marks, many_az, fps=fps)
        with Image.open(tmp_path / "c.gif") as im:
            times = [f.info["duration"] for f in ImageSequence.Iterator(im)]
        assert len(times) == 8 and sum(times) == 10 * round(800 / fps), (fps, times)
        assert all(abs(t - 1000 / fps) < 10 for t in times), (fps, times)
    with pytest.raises(InputError, match="^preview: a frame holds non-finite display values$"):
        write_gif(tmp_path / "d.gif", np.full((2, 8, 8), np.nan), marks, az)
