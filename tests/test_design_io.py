"""Tests of jscratch.design.io: the target checks and their one-line refusals, the view check
(a camera at the light's mirror direction), image files read as display values (8-bit gray, RGB
by the Rec. 709 luma, RGBA, 16-bit) against hand-made pixels, the aspect refusal, the default
targets, the PNG writer's rounding, the targets' hash, and `save_result` / `load_result` for a
hand-built result (its design file read back)."""

import json
import os
import re

import jax.numpy as jnp
import numpy as np
import pytest
from skimage import io as skio

from jscratch import designfile
from jscratch.design import io
from jscratch.design.config import DesignConfig
from jscratch.design.result import DesignResult
from jscratch.designfile import DesignError
from jscratch.scene import Board, Scratches, Views


@pytest.mark.parametrize(
    "targets, m, match",
    [
        (np.zeros((2, 16, 16), np.uint8), 2, "must be floating display values"),
        (np.zeros((16, 16)), None, r"must have shape \(M, H, W\)"),
        (np.zeros((3, 16, 16)), 2, "got 3 target images for 2 views"),
        (np.full((2, 16, 16), np.nan), 2, "target 0 has non-finite values"),
        (np.concatenate([np.zeros((1, 16, 16)), np.full((1, 16, 16), 1.5)]), 2,
         r"target 1 has values outside \[0, 1\]"),
        (np.zeros((2, 8, 16)), 2, "at least 16x16 px"),
        (np.array([[["a"]]], object), None, "must be a numeric"),
        (np.zeros((0, 32, 32)), None, r"must have shape \(M, H, W\).*got \(0, 32, 32\)"),
    ],
)
def test_check_targets_refusals(targets, m, match):
    with pytest.raises(DesignError, match=match):
        io.check_targets(targets, m)


def test_check_targets_hash_and_views():
    t = np.random.default_rng(0).random((2, 16, 20))
    assert io.check_targets(t, 2) is not None
    assert io.targets_hash(t) == io.targets_hash(t.copy()) != io.targets_hash(t[::-1])
    assert len(io.targets_hash(t)) == 16
    board = Board(shape=(16, 20))
    light = [0.15 - 0.5, 0.15, 0.8]
    ok = Views(jnp.asarray([[0.15, 0.15 + 0.6, 0.8]]), jnp.asarray([light]))
    io.check_design_views(ok, board)
    mirror = Views(jnp.asarray([[0.15 + 0.5, 0.15, 0.8]]), jnp.asarray([light]))
    with pytest.raises(DesignError, match="view 0: the camera is at the light's mirror direction"):
        io.check_design_views(mirror, board)


def test_load_target_files(tmp_path):
    gray = np.tile(np.arange(32, dtype=np.uint8) * 8, (32, 1))
    skio.imsave(tmp_path / "g.png", gray, check_contrast=False)
    got = io.load_target(tmp_path / "g.png", (32, 32))
    np.testing.assert_allclose(got, gray / 255.0, atol=1e-6)
    # RGB: Rec. 709 luma of the 8-bit values scaled to [0, 1]
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50
    skio.imsave(tmp_path / "c.png", rgb, check_contrast=False)
    want = (0.2125 * 200 + 0.7154 * 100 + 0.0721 * 50) / 255
    np.testing.assert_allclose(io.load_target(tmp_path / "c.png", (16, 16)), want, atol=1e-6)
    rgba = np.concatenate([rgb, np.full((32, 32, 1), 7, np.uint8)], -1)
    skio.imsave(tmp_path / "a.png", rgba, check_contrast=False)
    np.testing.assert_allclose(io.load_target(tmp_path / "a.png", (16, 16)), want, atol=1e-6)
    skio.imsave(tmp_path / "w.png", np.full((32, 32), 65535, np.uint16), check_contrast=False)
    np.testing.assert_allclose(io.load_target(tmp_path / "w.png", (16, 16)), 1.0)
    with pytest.raises(DesignError, match="does not exist"):
        io.load_target(tmp_path / "missing.png", (16, 16))
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(DesignError, match="is not a readable image"):
        io.load_target(tmp_path / "bad.png", (16, 16))
    with pytest.raises(DesignError, match=r"is 32x32 px \(aspect 1.000\).*crop it first"):
        io.load_target(tmp_path / "g.png", (16, 32))


def test_load_target_names_a_junk_npz_file_without_numpy_advice(tmp_path):
    """A file that is neither an image nor a .npz archive is refused in one line naming it, not
    with numpy's advice on pickled data; a real .npz array still loads (the reader takes it)."""
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"this is not a zip archive\n" * 10)
    with pytest.raises(DesignError, match=rf"^target image {re.escape(repr(str(junk)))} is not a "
                                          r"valid image or \.npz file$"):
        io.load_target(junk, (16, 16))
    np.savez(tmp_path / "real.npz", np.full((16, 16), 0.25))
    np.testing.assert_allclose(io.load_target(tmp_path / "real.npz", (16, 16)), 0.25, atol=1e-6)


def test_prepare_target_crops_the_centre_and_default_targets():
    img = np.zeros((40, 80))
    img[:, 20:60] = 1.0  # the centre 40 x 40 square is white
    np.testing.assert_allclose(io.prepare_target(img, (16, 16), "x"), 1.0)
    t, names = io.default_targets(3, (16, 24))
    assert t.shape == (3, 16, 24) and t.min() >= 0 and t.max() <= 1
    assert names == ["skimage.data.camera", "skimage.data.astronaut", "skimage.data.chelsea"]


def test_write_png_rounds_to_8_bits(tmp_path):
    img = np.array([[0.0, 0.5, 1.0, 1.7], [-1.0, 0.25, 0.002, 0.998]])
    io.write_png(str(tmp_path / "x.png"), img)
    back = skio.imread(tmp_path / "x.png")
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, [[0, 128, 255, 255], [0, 64, 1, 254]])
    img[1, 1] = np.nan  # a cast would write some grey: refused, nothing written
    with pytest.raises(DesignError, match=r"^write_png: .*y.png': the image holds non-finite"):
        io.write_png(str(tmp_path / "y.png"), img)
    assert not (tmp_path / "y.png").exists()


def test_save_result_refuses_non_finite_images_load_result_would_refuse(tmp_path):
    res = _one_view_result({"ssim": [0.5], "ghosting": [0.1]})
    res.radiance = res.radiance.copy()
    res.radiance[0, 3, 3] = np.inf
    with pytest.raises(DesignError, match="^save_result: the result's radiance hold non-finite "
                                          "values$"):
        io.save_result(res, tmp_path / "r")
    assert not (tmp_path / "r").exists()


def test_save_and_load_a_hand_built_result(tmp_path):
    from jscratch.design.params import DesignParams

    board = Board(shape=(16, 16))
    s = Scratches(np.float32([[0.01, 0.02], [0.1, 0.1]]), np.float32([[0.05, 0.02], [0.2, 0.25]]),
                  np.float32([2.5e-4, 3e-4]), np.float32([1.28e-4, 1e-4]), np.float32([0.04, 0.05]))
    views = Views(np.float32([[0.0, 0.5, 0.8], [0.5, 0.0, 0.8]]), np.float32([[0.3, 0.3, 0.9]] * 2),
                  np.float32([1.0, 2.0]))
    params = DesignParams.from_physical(s, np.asarray(views.intensity), board)
    disp = np.random.default_rng(1).random((2, 16, 16))
    res = DesignResult(s, views, board, params, np.ones(2, bool), disp, disp, disp,
                       {"total": [2.0, 1.0], "terms": {"E_p": [2.0, 1.0]}},
                       {"ssim": [0.5, 0.6], "ghosting": [0.1, 0.2], "loss": float("nan")},
                       DesignConfig(n_scratches=2, groove="free"))
    (tmp_path / "out").mkdir()
    stale = ("view2_render.png", "view2_target.png", "view0_carved.png")  # an earlier 3-view run's
    (tmp_path / "out" / "metrics.json").write_text(json.dumps(
        {"ssim": [0.1, 0.2, 0.3], "as_carved": {"ssim": [0.1, 0.2, 0.3]}}))
    mine = ("notes.txt", "view5_render.png")  # not the earlier result's: left alone
    for f in (*stale, *mine):
        (tmp_path / "out" / f).write_text("x")
    io.save_result(res, tmp_path / "out")
    assert not any((tmp_path / "out" / f).exists() for f in stale)
    assert all((tmp_path / "out" / f).read_text() == "x" for f in mine)
    for kw, words in ((dict(names=np.array(["a", "b"])), "names must be None or 2 strings"),
                      (dict(names=["a"]), "names must be None or 2 strings"),
                      (dict(scene={"size": 24}), "scene must be None or a SceneConfig")):
        with pytest.raises(DesignError, match=words):
            io.save_result(res, tmp_path / "out2", **kw)
    assert not (tmp_path / "out2").exists()
    assert (tmp_path / "out" / "notes.txt").exists()  # (what is not a result's is left alone)
    d = designfile.load_design(tmp_path / "out" / "design.npz")
    np.testing.assert_allclose(d.p0, np.asarray(s.p0), rtol=1e-7)
    np.testing.assert_allclose(d.intensity, [1.0, 2.0])
    assert d.plunge is None and d.machine["name"] == "paper"  # free grooves: no plunges recorded
    for f in ("design.svg", "view0_render.png", "view1_target.png", "comparison.png", "loss.png"):
        assert (tmp_path / "out" / f).stat().st_size > 0
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["loss"] is None and metrics["groove"] == "free" and "carving" in metrics
    cfg = json.loads((tmp_path / "out" / "config.json").read_text())
    assert cfg["board"]["shape"] == [16, 16] and cfg["design"]["n_scratches"] == 2
    back = io.load_result(tmp_path / "out")
    np.testing.assert_array_equal(back.scratches.p1, s.p1)
    np.testing.assert_array_equal(back.display, disp)
    np.testing.assert_array_equal(np.asarray(back.params.geom), np.asarray(params.geom))
    assert back.history == res.history and back.config == res.config


def _one_view_result(metrics, scene=None, names=None):
    """A hand-built one-scratch, one-view `DesignResult` with free grooves on a 16 px board."""
    from jscratch.design.params import DesignParams

    board = Board(shape=(16, 16))
    s = Scratches(np.float32([[0.01, 0.02]]), np.float32([[0.05, 0.02]]), np.float32([2.5e-4]),
                  np.float32([1.28e-4]), np.float32([0.04]))
    views = Views(np.float32([[0.0, 0.5, 0.8]]), np.float32([[0.3, 0.3, 0.9]]), np.float32([1.0]))
    params = DesignParams.from_physical(s, np.asarray(views.intensity), board)
    disp = np.random.default_rng(2).random((1, 16, 16))
    return DesignResult(s, views, board, params, np.ones(1, bool), disp, disp, disp,
                        {"total": [1.0], "terms": {}}, metrics,
                        DesignConfig(n_scratches=1, groove="free"), scene, names)


def test_a_loaded_one_view_result_saves_again_with_its_scene_and_without_stale_figures(tmp_path):
    """A one-view run's ghosting is NaN (saved as null): it loads back as NaN and saves again.
    The scene and target names a run was made from travel with the result, so a re-saved folder
    can be repeated with --config; an as-carved block not recomputed is dropped, not re-saved
    beside no pictures; saving leaves matplotlib's backend as it was (a notebook's inline one)."""
    import math

    import matplotlib

    from jscratch.design.config import SceneConfig

    scene = SceneConfig(views=1, size=16, distance=2.0)
    res = _one_view_result({"ssim": [0.5], "ghosting": [float("nan")],
                            "as_carved": {"ssim": [0.4]}}, scene=scene, names=["mine.png"])
    before = matplotlib.get_backend()
    matplotlib.use("pdf")  # any backend but Agg
    try:
        io.save_result(res, tmp_path / "a")
        assert matplotlib.get_backend() == "pdf"
    finally:
        matplotlib.use(before)
    assert "as_carved" not in res.metrics  # no as-carved render this time: no stale figures
    back = io.load_result(tmp_path / "a")
    assert math.isnan(back.metrics["ghosting"][0]) and back.metrics["ssim"] == [0.5]
    assert back.scene == scene and back.names == ["mine.png"]
    io.save_result(back, tmp_path / "b")
    cfg = json.loads((tmp_path / "b" / "config.json").read_text())
    assert cfg["scene"] == scene.to_dict() and cfg["targets"] == ["mine.png"]
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["ghosting"] == [None]


def test_images_read_as_a_viewer_shows_them(tmp_path):
    """A JPEG with an EXIF orientation is read turned as viewers show it (PIL's
    `ImageOps.exif_transpose`, the reference); CMYK is read as its RGB (not as RGBA); gray with
    alpha drops the alpha like RGBA."""
    from PIL import Image, ImageOps

    a = np.zeros((40, 60), np.uint8)
    a[:10] = 255  # a bright band along the top rows, as stored
    for orientation in (3, 6, 8):
        im = Image.fromarray(a)
        exif = im.getexif()
        exif[0x0112] = orientation
        im.save(tmp_path / "r.jpg", exif=exif.tobytes(), quality=95)
        shown = np.asarray(ImageOps.exif_transpose(Image.open(tmp_path / "r.jpg"))) / 255.0
        got = io.load_target(tmp_path / "r.jpg", shown.shape)
        assert got.shape == shown.shape and np.abs(got - shown).max() < 0.02, orientation
    rgb = np.random.default_rng(0).integers(0, 256, (32, 32, 3)).astype(np.uint8)
    Image.fromarray(rgb).convert("CMYK").save(tmp_path / "c.jpg", quality=95)
    ref = np.asarray(Image.open(tmp_path / "c.jpg").convert("L")) / 255.0
    got = io.load_target(tmp_path / "c.jpg", (32, 32))
    assert np.corrcoef(got.ravel(), ref.ravel())[0, 1] > 0.95  # (not inverted: -0.98 as RGBA)
    # A palette image with an orientation: its colours, not its palette indices.
    red = np.stack([a, 0 * a, 0 * a], -1)
    im = Image.fromarray(red).convert("P", palette=Image.Palette.ADAPTIVE)
    exif = im.getexif()
    exif[0x0112] = 3
    im.save(tmp_path / "p.png", exif=exif.tobytes())
    np.testing.assert_allclose(io.load_target(tmp_path / "p.png", (40, 60)),
                               np.rot90(0.2125 * (a / 255.0), 2), atol=2e-3)  # Rec. 709 red
    Image.fromarray(rgb).save(tmp_path / "one.gif")  # one frame: read as an image, not a movie
    ref = np.asarray(Image.open(tmp_path / "one.gif").convert("L")) / 255.0
    got = io.load_target(tmp_path / "one.gif", (32, 32))
    assert got.shape == (32, 32) and np.corrcoef(got.ravel(), ref.ravel())[0, 1] > 0.95
    Image.fromarray(a).convert("LA").save(tmp_path / "la.png")
    Image.fromarray(a).save(tmp_path / "l.png")
    np.testing.assert_array_equal(io.load_target(tmp_path / "la.png", (40, 60)),
                                  io.load_target(tmp_path / "l.png", (40, 60)))


@pytest.mark.parametrize("call, match", [
    (lambda: io.default_targets(0, (32, 32)), "number of views must be an int >= 1"),
    (lambda: io.default_targets(2, (0, 32)), r"image shape must be \(H, W\)"),
    (lambda: io.default_targets(2, 32), r"image shape must be \(H, W\)"),
    (lambda: io.default_targets(2, (32, 32, 3)), r"image shape must be \(H, W\)"),
    (lambda: io.load_target(None, (32, 32)), "must be a file path"),
    (lambda: io.prepare_target(np.zeros((0, 0)), (32, 32), "x"), "an empty image"),
    (lambda: io.prepare_target(np.zeros((24, 24)), (0, 24), "x"), r"image shape must be \(H, W\)"),
    (lambda: io.default_targets(2, (2, 3000)), "nothing is left of it when cropped"),
])
def test_target_helpers_refuse_bad_arguments_in_one_line(call, match):
    with pytest.raises(DesignError, match=match) as e:
        call()
    assert "\n" not in str(e.value)


def test_a_save_that_fails_part_way_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    """`save_result` writes into a staging folder and moves the files in once all are written:
    a failure while drawing the pictures leaves an earlier result whole (its files unchanged,
    no new ones, no staging folder), and a new folder is not left behind."""
    res = _one_view_result({"ssim": [0.5], "ghosting": [0.1]})
    io.save_result(res, tmp_path / "a")
    before = {f.name: f.read_bytes() for f in (tmp_path / "a").iterdir()}

    def broken(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(io, "_write_pictures", broken)
    res.history["total"].append(0.5)  # a different result
    for out in (tmp_path / "a", tmp_path / "new"):
        with pytest.raises(OSError, match="No space left"):
            io.save_result(res, out)
    assert {f.name: f.read_bytes() for f in (tmp_path / "a").iterdir()} == before
    assert not (tmp_path / "new").exists()
    assert "carving" in res.metrics  # from the first save only


def test_save_and_load_result_refuse_what_is_no_result_or_path_in_one_line(tmp_path):
    """`save_result`, `load_result` and `load_scene` refuse a path, a time, a result whose images
    disagree or whose history is not `design`'s, and a scene of the wrong type, naming them;
    `save_result` then writes nothing."""
    import dataclasses

    from jscratch.errors import DesignFileError

    metrics = {"ssim": [0.5], "psnr": [10.0], "ghosting": [float("nan")], "loss": 1.0}
    res = _one_view_result(metrics)
    out = tmp_path / "r"
    for bad in (None, 3, ""):
        with pytest.raises(DesignError, match="^save_result: expected a folder path"):
            io.save_result(res, bad)
        with pytest.raises(DesignFileError, match="^load_result: expected a folder path"):
            io.load_result(bad)
    for bad in ("a", -1.0, float("nan"), None, True):
        with pytest.raises(DesignError, match="^save_result: order_time must be a finite number"):
            io.save_result(res, out, order_time=bad)
    two = np.concatenate([res.display, res.display])
    with pytest.raises(DesignError, match=r"targets \(1, 16, 16\), radiance \(1, 16, 16\), "
                                          r"display \(2, 16, 16\)"):
        io.save_result(dataclasses.replace(res, display=two), out)
    with pytest.raises(DesignError, match="^save_result: the result's history must be"):
        io.save_result(dataclasses.replace(res, history={"total": [1.0]}), out)
    assert not out.exists()
    with pytest.raises(DesignError, match="^load_scene: scene must be a SceneConfig"):
        io.load_scene({"size": 32})


def test_save_result_is_refused_in_a_folder_another_process_holds(tmp_path):
    """A folder a design run holds (`io.lock_folder`: a command-line run writing there, in
    another process) is not written by a Python `save_result`: one line, nothing changed; once
    the holder ends the save goes through. A folder this process holds (the command line's own
    save) is written."""
    import subprocess
    import sys

    out = tmp_path / "held"
    out.mkdir()
    (out / "checkpoint.npz").write_bytes(b"the run's")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDONLY); "
         "fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); sys.stdin.read()", str(out)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        with pytest.raises(DesignError) as err:
            io.save_result(_one_view_result({"ssim": [0.5], "ghosting": [0.1]}), out)
        assert str(err.value) == (f"save_result: a design run is writing in {str(out)!r}: wait "
                                  "for it to end, or save into another folder")
        assert os.listdir(out) == ["checkpoint.npz"]
    finally:
        holder.communicate("")
    io.save_result(_one_view_result({"ssim": [0.5], "ghosting": [0.1]}), out)
    assert io.load_result(out).metrics["ssim"] == [0.5]
    held = io.lock_folder(str(out))
    try:
        io.save_result(_one_view_result({"ssim": [0.25], "ghosting": [0.1]}), out)
    finally:
        held.release()
    assert io.load_result(out).metrics["ssim"] == [0.25]
    assert io.lock_folder(str(out)) is not None  # released
