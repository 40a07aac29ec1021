"""Tests of jscratch.scene: `Scratches.random` (lengths, board, directions, dtype), the value rules
and their one-line messages (host checks and the traced `scene_checks`), `Board`, `Views`, the
flat-board highlight by hand (mirror geometry), and the `views_on_circle` layout."""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jscratch import scene
from jscratch.errors import InputError
from jscratch.scene import Board, Scratches, Views, flat_highlight, views_on_circle


def test_random_scratches_lie_on_the_board_with_lengths_in_range():
    board = Board(shape=(8, 8), Sx=0.3, Sy=0.2)
    s = Scratches.random(jax.random.PRNGKey(0), 2000, board, length=(0.01, 0.05), dtype=jnp.float32)
    assert s.n == 2000 and s.dtype == jnp.float32 and s.width.shape == (2000,)
    p0, p1 = np.asarray(s.p0, np.float64), np.asarray(s.p1, np.float64)
    for p in (p0, p1):
        # on the board up to float32 rounding of its size
        assert np.all(p >= 0) and np.all(p[:, 0] <= np.float32(0.3)) and np.all(p[:, 1] <= np.float32(0.2))
    length = np.linalg.norm(p1 - p0, axis=1)
    assert np.all(length <= 0.05 + 1e-6)
    # only segments shortened at the board's edge fall below the range, and they touch an edge
    short = length < 0.01 - 1e-6
    ends = np.concatenate([p0[short], p1[short]], 1)
    edge = (np.isclose(ends, 0, atol=1e-6) | np.isclose(ends, [0.3, 0.2, 0.3, 0.2], atol=1e-6))
    assert short.mean() < 0.2 and np.all(edge.any(1))
    # directions uniform: the mean of the doubled angle's unit vector is near zero
    phi = np.arctan2(*(p1 - p0)[:, ::-1].T)
    assert abs(np.mean(np.exp(2j * phi))) < 0.1
    np.testing.assert_allclose(np.mean((p0 + p1) / 2, 0), [0.15, 0.1], atol=0.01)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(width=np.float32([1e-4, 0.0])),
         r"Scratches: scratch 1: width = 0.0 must be >= 1e-12 m"),
        (dict(width=np.float32([1e-4, 1e-13])), r"scratch 1: width = \S+ must be >= 1e-12 m"),
        (dict(depth=np.float32([1e-4, -1.0])), r"scratch 1: depth = -1.0 must be > 0 m"),
        (dict(alpha=np.float32([0.1, 1.0])),
         r"scratch 1: alpha = 1.0 must lie in \[0.0001, 0.99\]"),
        (dict(width=np.float32([np.inf, 1e-4])), r"scratch 0: width = inf is not finite"),
    ],
)
def test_scratch_rules_name_the_scratch(kw, match):
    with pytest.raises(ValueError, match=match):
        Scratches(np.zeros((2, 2), np.float32), np.ones((2, 2), np.float32), **kw)


def test_shapes_board_and_views_errors():
    with pytest.raises(ValueError, match="`p1` must have shape"):
        Scratches(jnp.zeros((3, 2)), jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"`width` must have shape \(N,\) = \(3,\)"):
        Scratches(jnp.zeros((3, 2)), jnp.ones((3, 2)), width=jnp.ones(2))
    with pytest.raises(ValueError, match="`shape` must be positive"):
        Board(shape=(0, 4))
    for bad in (-1.0, 3e-19, 9e-7):
        with pytest.raises(ValueError, match=rf"`Sx` must be a finite length >= 1e-06 m; got {bad}"):
            Board(Sx=bad)
    with pytest.raises(ValueError, match=r"`a_S` must lie in \(0, 1\]"):
        Board(a_S=0.0)
    with pytest.raises(ValueError, match="view 0: camera is at z = -1.0"):
        Views(jnp.asarray([[0.0, 0.0, -1.0]]), jnp.asarray([[0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match="view 1: intensity is negative"):
        Views(jnp.ones((2, 3)), jnp.ones((2, 3)), jnp.asarray([1.0, -2.0]))
    with pytest.raises(ValueError, match="scratch 0: p1 = .* lies off the board"):
        scene.check_scratches(np.zeros((1, 2)), np.full((1, 2), 0.5), 1e-4, 1e-4, board=(0.3, 0.3))
    scene.check_scratches(np.zeros((1, 2)), np.full((1, 2), 0.3), 1e-4, 1e-4, board=(0.3, 0.3))
    b = Board(shape=(4, 5), Sx=0.2, Sy=0.1)
    assert (b.H, b.W, b.n_pixels) == (4, 5, 20) and b.pixel_area == pytest.approx(0.04 * 0.025)


def test_scene_checks_inside_jit():
    s = Scratches(np.zeros((2, 2), np.float32), np.ones((2, 2), np.float32))
    v = Views(np.ones((1, 3), np.float32), np.ones((1, 3), np.float32))
    broken = jax.jit(lambda s, v: jnp.stack([c for c, _ in scene.scene_checks(s, v)]))
    assert not np.any(np.asarray(broken(s, v)))
    bad_v = Views.__new__(Views)
    object.__setattr__(bad_v, "camera", -v.camera)
    object.__setattr__(bad_v, "light", v.light)
    object.__setattr__(bad_v, "intensity", v.intensity)
    flags = np.asarray(broken(s, bad_v))
    msgs = [m for _, m in scene.scene_checks(s, v)]
    assert flags.sum() == 1 and "above the board" in msgs[int(np.argmax(flags))]


def test_flat_highlight_is_the_mirror_point():
    camera = np.array([0.1, 0.0, 1.0])
    light = np.array([0.3, 0.2, 0.5])
    x = flat_highlight(camera, light)
    # equal angles: the reflected ray from x towards the camera comes from the light
    p = np.array([x[0], x[1], 0.0])
    a, b = camera - p, light - p
    h = a / np.linalg.norm(a) + b / np.linalg.norm(b)
    np.testing.assert_allclose(h[:2] / np.linalg.norm(h), 0.0, atol=1e-12)


@pytest.mark.float64
def test_views_on_circle_layout():
    v = views_on_circle(5, math.radians(40), 1.0)
    c = np.asarray(v.camera) - [0.15, 0.15, 0]
    np.testing.assert_allclose(np.linalg.norm(c, axis=-1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.arccos(c[:, 2]), math.radians(40), rtol=1e-12)
    az = np.sort(np.mod(np.arctan2(c[:, 1], c[:, 0]), 2 * np.pi))
    np.testing.assert_allclose(np.diff(az), 2 * np.pi / 5, rtol=1e-9)
    # Light at azimuth 0: no camera within pi/5 of the mirror azimuth pi (flat highlight refused).
    assert np.min(np.abs(az - np.pi)) > np.pi / 5 - 1e-9
    assert np.all(np.asarray(v.light) == np.asarray(v.light)[0]) and v.intensity.shape == (5,)
    with pytest.raises(ValueError, match="sees the light mirrored"):
        views_on_circle(4, math.radians(40), offset=math.pi)
    with pytest.raises(ValueError, match="radians: did you mean"):
        views_on_circle(4, 40.0)


def test_views_on_circle_float32_and_even_count():
    v = views_on_circle(4, math.radians(50), 0.8, dtype=jnp.float32)
    assert v.camera.dtype == jnp.float32 and v.m == 4
    c = np.asarray(v.camera, np.float64) - [0.15, 0.15, 0]
    np.testing.assert_allclose(np.linalg.norm(c, axis=-1), 0.8, rtol=1e-6)
    # even M: the light's mirror azimuth (pi) lies midway between two cameras
    az = np.sort(np.mod(np.arctan2(c[:, 1], c[:, 0]), 2 * np.pi))
    np.testing.assert_allclose(az, np.pi / 4 + np.arange(4) * np.pi / 2, atol=1e-6)


def test_groove_profile_is_checked_and_kept():
    """`Scratches.profile` (static): one of `PROFILES`, kept by pytree maps and through jit."""
    p0, p1 = jnp.zeros((2, 2)), jnp.full((2, 2), 0.01)
    s = Scratches(p0, p1, profile="arc")
    assert s.profile == "arc" and Scratches(p0, p1).profile == "paper"
    assert jax.tree_util.tree_map(lambda x: 2 * x, s).profile == "arc"
    assert jax.jit(lambda t: t)(s).profile == "arc"
    with pytest.raises(InputError, match="profile.*one of"):
        Scratches(p0, p1, profile="ball")


def test_views_and_arrays_outside_the_float32_range_are_refused_in_one_line():
    """What float32 cannot render is refused where it is made, in one line: a light or camera
    closer than `MIN_HEIGHT` to the board (its squared distance to the pixel below underflows)
    or farther than `MAX_DISTANCE` (it overflows), an intensity whose irradiance at the board passes
    `MAX_IRRADIANCE` (float32 overflows), half-precision, complex or non-numeric arrays, a board
    shape that is no int; at the edges of the rules a float32 render and its gradient stay
    finite."""
    from jscratch import render

    up = [[0.005, 0.005, 1.0]]
    for cam, light, inten, words in (
            ([[0.0, 0.0, 1e-30]], up, 1.0, "camera is at z = 1e-30 m: it must be at least 1e-06 m"),
            (up, [[1e20, 0.0, 1e20]], 1.0, "light lies farther than 1e+09 m"),
            (up, up, 1e30, "intensity 1e+30 W/sr at 1 m above the board is 1e+30 W/m^2 there, "
                           "above 1e+20")):
        with pytest.raises(ValueError, match=re.escape(words)):
            Views(np.float32(cam), np.float32(light), np.float32(inten))
    for p0, words in ((np.zeros((1, 2), np.float16), "float16; a scene is float32 or float64"),
                      (jnp.zeros((1, 2), jnp.bfloat16), "bfloat16; a scene is float32 or float64"),
                      (np.zeros((1, 2), np.complex64), "complex"),
                      ([[0.0, 0.0], [1.0]], "`p0` is not a numeric array"),
                      (np.array([["a", "b"]]), "`p0` is not a numeric array|not numbers"),
                      (None, "`p0` is not a numeric array|not numbers")):
        p1 = p0 if hasattr(p0, "dtype") else np.ones((1, 2), np.float32)
        with pytest.raises(ValueError, match=words) as e:
            Scratches(p0, p1)
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match=r"`shape` must be \(H, W\), two positive ints"):
        Board(shape=(16.7, 16))

    board = Board(shape=(8, 8), Sx=0.01, Sy=0.01)
    s = Scratches(np.float32([[0.002, 0.003]]), np.float32([[0.008, 0.006]]), 2e-4, 1e-4,
                  scene.ALPHA_RANGE[0])
    c = 0.01 / 16 + 0.01 / 8 * 3  # a pixel centre
    z = scene.MIN_HEIGHT
    near = Views(np.float32([[c, c, z]]), np.float32([[c, c, z]]), np.float32(1.0))
    bright = Views(np.float32([[c, c, z]]), np.float32([[c, c, z]]),
                   np.float32(0.999 * scene.MAX_IRRADIANCE * z * z))
    far = Views(np.float32([[0.0, scene.MAX_DISTANCE, 1.0]]),
                np.float32([[scene.MAX_DISTANCE, 0.0, scene.MAX_DISTANCE]]), np.float32(1e20))
    for v in (near, bright, far):
        pairs = render.bin_pairs(s, board)
        val, g = jax.value_and_grad(
            lambda s, v: jnp.sum(render.render_pairs(s, v, board, pairs)), argnums=(0, 1))(s, v)
        assert np.isfinite(float(val))
        assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(g))


def test_renderers_check_what_they_are_given(tmp_path):
    """`render` checks the views on the host (a view edited past `Views`' own check is one line,
    not an equinox runtime error), every host entry checks the endpoints against the board and
    `chunk`."""
    import equinox as eqx

    from jscratch import render

    board = Board(shape=(8, 8), Sx=0.01, Sy=0.01)
    s = Scratches(np.float32([[0.002, 0.003]]), np.float32([[0.008, 0.006]]), 2e-4, 1e-4, 0.04)
    v = Views(np.float32([[0.0, 0.0, 1.0]]), np.float32([[0.01, 0.01, 1.0]]))
    below = eqx.tree_at(lambda t: t.camera, v, -v.camera)
    with pytest.raises(ValueError, match="render: view 0: camera is at z = -1.0") as e:
        render.render(s, below, board)
    assert "\n" not in str(e.value)
    for chunk in (0, -5, 2.5):
        with pytest.raises(ValueError, match=r"render: `chunk` \(pairs per block\) must be an int"):
            render.render(s, v, board, chunk=chunk)
    off = Scratches(np.float32([[0.002, 0.003]]), np.float32([[0.02, 0.006]]), 2e-4, 1e-4, 0.04)
    pairs = render.bin_pairs(s, board)
    for call, where in ((lambda: render.bin_pairs(off, board), "bin_pairs"),
                        (lambda: render.render_pairs(off, v, board, pairs), "render_pairs"),
                        (lambda: render.render_reference(off, v, board), "render_reference")):
        with pytest.raises(ValueError,
                           match=rf"{where}: scratch 0: p1 = \(0.02, 0.006\) m lies off"):
            call()


@pytest.mark.parametrize("kw, match", [
    (dict(length=(0.03, 0.01)), r"`length` must be \(min, max\) metres with 0 < min <= max; "
                                r"got \(0.03, 0.01\)"),
    (dict(length=(0, 0)), r"`length` must be \(min, max\) .*; got \(0, 0\)"),
    (dict(length=0.01), r"`length` must be \(min, max\) .*; got 0.01"),
    (dict(n=-1), r"`n` must be an int >= 0, got -1"),
    (dict(n=2.5), r"`n` must be an int >= 0, got 2.5"),
    (dict(n="5"), r"`n` must be an int >= 0, got '5'"),
    (dict(key=0), r"`key` must be one PRNG key .*; got 0"),
    (dict(board=[0.3, 0.3]), r"`board` must be a jscratch.Board or None; got list"),
    (dict(dtype=jnp.int32), r"`dtype` must be float32 or float64; got int32"),
    (dict(dtype="foo"), r"`dtype` must be float32 or float64; got 'foo'"),
])
def test_random_refuses_bad_arguments_in_one_line(kw, match):
    args = dict(key=jax.random.PRNGKey(0), n=5) | kw
    key, n = args.pop("key"), args.pop("n")
    with pytest.raises(InputError, match="^Scratches.random: " + match) as e:
        Scratches.random(key, n, **args)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("kw, match", [
    (dict(M=None), r"`M` must be a positive int; got None"),
    (dict(theta=None), r"`theta` must be a real number \(rad\); got None"),
    (dict(theta="a"), r"`theta` must be a real number \(rad\); got 'a'"),
    (dict(distance=None), r"`distance` must be a real number \(m\); got None"),
    (dict(offset="x"), r"`offset` must be a real number \(rad\); got 'x'"),
    (dict(board=[0.3, 0.3]), r"`board` must be a jscratch.Board or None; got list"),
    (dict(dtype="int32"), r"`dtype` must be float32 or float64; got int32"),
])
def test_views_on_circle_refuses_bad_arguments_in_one_line(kw, match):
    args = dict(M=3) | kw
    with pytest.raises(InputError, match="^views_on_circle: " + match):
        views_on_circle(args.pop("M"), **args)


@pytest.mark.parametrize("value, shown", [("a", "'a'"), (None, "None"),
                                          (np.array([1, 2]), r"array\(\[1, 2\]\)")])
def test_board_refuses_what_is_no_number(value, shown):
    with pytest.raises(InputError, match=rf"^Board: `Sx` must be a real number; got {shown}$"):
        Board(Sx=value)


def test_check_views_refuses_wrong_shapes():
    with pytest.raises(InputError, match=r"^views: `camera` and `light` must have one shape "
                                               r"\(M, 3\); got camera \(3,\), light \(3,\)$"):
        scene.check_views([0, 0, 1.0], [0, 0, 1.0], 1.0)
    with pytest.raises(InputError, match=r"`intensity` must have shape \(M,\) = \(1,\)"):
        scene.check_views([[0, 0, 1.0]], [[0, 0, 1.0]], [1.0, 2.0])
    scene.check_views([[0, 0, 1.0]], [[0, 0, 1.0]], 1.0)  # a scalar intensity is every view's


@pytest.mark.parametrize("profile", ["paper", "arc"])
def test_values_and_gradients_stay_finite_at_the_smallest_width_and_board(profile):
    """At `scene.MIN_WIDTH` (a groove) and `scene.MIN_BOARD` (a board side) the float32 render
    and its gradient with respect to every scratch value are finite (below them, the width
    derivative and a pixel's area underflow: refused by the rules above)."""
    from jscratch import render

    rng = np.random.default_rng(3)
    for side, width in ((0.01, scene.MIN_WIDTH), (scene.MIN_BOARD, 1e-8)):
        board = Board(shape=(16, 16), Sx=side, Sy=side)
        n = 24
        p0 = rng.uniform(0.1, 0.9, (n, 2)) * side
        p1 = rng.uniform(0.1, 0.9, (n, 2)) * side
        views = scene.views_on_circle(2, board=board, distance=10 * side)
        w = np.full(n, width, np.float32)

        def loss(p0, p1, w, d, a):
            s = Scratches(p0, p1, w, d, a, profile=profile)
            return jnp.sum(render.render_pairs(s, views, board, pairs)[0] ** 2)

        s0 = Scratches(jnp.asarray(p0, jnp.float32), jnp.asarray(p1, jnp.float32), w,
                       np.full(n, width, np.float32), np.full(n, 0.04, np.float32), profile=profile)
        pairs = render.bin_pairs(s0, board)
        val, grads = jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4))(
            s0.p0, s0.p1, s0.width, s0.depth, s0.alpha)
        assert np.isfinite(float(val)), (side, width)
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g))), (side, width)
