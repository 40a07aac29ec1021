"""Public functions refuse a bad argument with a one-line `InputError` that names the function
and the argument (what was given, and what is accepted), and compute what they computed before
for good arguments."""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jscratch
from jscratch import loss, toolpath
from jscratch.designfile import demo_design
from jscratch.errors import InputError

F32 = jnp.float32
BOARD = jscratch.Board(shape=(4, 5))
VIEWS = jscratch.views_on_circle(2, board=BOARD)
P = BOARD.n_pixels

#: One pair of `pair_integral`: a 1 mm footprint crossed by a scratch along x.
PAIR = dict(h=jnp.array([0.1, 0.2, 1.0], F32),
            footprint=jnp.array([[0, 0], [1e-3, 0], [1e-3, 1e-3], [0, 1e-3]], F32),
            p0=jnp.array([0, 5e-4], F32), p1=jnp.array([2e-3, 5e-4], F32),
            width=2.5e-4, depth=1.28e-4, alpha=0.04)


def pair(**changed):
    return jscratch.pair_integral(**(PAIR | changed))


def images():
    """A flat render and a ramp target, ``(1, 16, 16)``."""
    return (jnp.full((1, 16, 16), 0.5, F32),
            jnp.linspace(0, 1, 256, dtype=F32).reshape(1, 16, 16))


def shade_inputs():
    D = jnp.linspace(0, 1, 2 * P, dtype=F32).reshape(2, P)
    return D, jnp.linspace(0, 1, P, dtype=F32)


BAD = {
    "pair_integral h (2,)": (
        lambda tmp: pair(h=jnp.ones(2, F32)),
        r"^pair_integral: `h` must have shape \(3,\), got shape \(2,\)$"),
    "pair_integral footprint (3, 2)": (
        lambda tmp: pair(footprint=PAIR["footprint"][:3]),
        r"^pair_integral: `footprint` must have shape \(4, 2\), got shape \(3, 2\)$"),
    "pair_integral footprint (5, 2)": (
        lambda tmp: pair(footprint=jnp.concatenate([PAIR["footprint"], PAIR["footprint"][:1]])),
        r"^pair_integral: `footprint` must have shape \(4, 2\), got shape \(5, 2\)$"),
    "pair_integral p0 (3,)": (
        lambda tmp: pair(p0=jnp.zeros(3, F32)),
        r"^pair_integral: `p0` must have shape \(2,\), got shape \(3,\)$"),
    "pair_integral alpha 2": (
        lambda tmp: pair(alpha=2.0),
        r"^pair_integral: `alpha` must lie in \(0, 1\), got 2.0$"),
    "shade D_P (2, 5)": (
        lambda tmp: jscratch.shade(jnp.zeros((2, 5)), jnp.zeros((2, 5)), VIEWS, BOARD),
        r"^shade: `D_P` must have shape \(2, 20\) \(M views, H\*W pixels\), got shape \(2, 5\)$"),
    "shade coverage (3,)": (
        lambda tmp: jscratch.shade(jnp.zeros((2, P)), jnp.zeros(3), VIEWS, BOARD),
        r"^shade: `coverage` must have shape \(2, 20\), \(1, 20\) or \(20,\) \(M views, "
        r"H\*W pixels\), got shape \(3,\)$"),
    "flat_highlight": (
        lambda tmp: jscratch.flat_highlight([1, 2], [3]),
        r"^flat_highlight: `camera` must have shape \(\.\.\., 3\) \(m\), got shape \(2,\)$"),
    "display": (
        lambda tmp: jscratch.display("abc"),
        r"^display: `radiance` is not a numeric array \("),
    "half_vectors dtype": (
        lambda tmp: jscratch.half_vectors(VIEWS, BOARD, dtype="foo"),
        r"^half_vectors: `dtype` must be float32 or float64; got 'foo'$"),
    "pixel_footprints": (
        lambda tmp: jscratch.pixel_footprints("x"),
        r"^pixel_footprints: `board` must be a jscratch.Board, got str$"),
    "write_svg": (
        lambda tmp: jscratch.write_svg(tmp / "d.svg", "d"),
        r"^write_svg: `design` must be a jscratch.Design, got str$"),
    "order_scratches": (
        lambda tmp: toolpath.order_scratches("x", "y"),
        r"^order_scratches: `p0` must be an \(N, 2\) array of numbers, got 'x'$"),
    "calibrate_lambda_g ratio": (
        lambda tmp: loss.calibrate_lambda_g(*images(), ratio="a"),
        r"^calibrate_lambda_g: `ratio` must be a finite number > 0, got 'a'$"),
}


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_argument_is_refused_in_one_line_naming_it(name, tmp_path):
    call, match = BAD[name]
    with pytest.raises(InputError, match=match) as exc:
        call(tmp_path)
    assert "\n" not in str(exc.value)
    assert not list(tmp_path.iterdir())  # nothing written


def check_pair_integral(tmp):
    D, A = pair()
    np.testing.assert_allclose([float(D), float(A)], [4.37206e-08, 2.0013194e-07], rtol=1e-4)
    # Batched and traced (shapes are checked per pair, values only where concrete).
    batch = {k: jnp.stack([jnp.asarray(v, F32)] * 2) for k, v in PAIR.items()}
    Db, Ab = jax.jit(jax.vmap(jscratch.pair_integral))(**batch)
    np.testing.assert_allclose(np.asarray(Db), [float(D)] * 2, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(Ab), [float(A)] * 2, rtol=1e-5)
    g = jax.grad(lambda a: pair(alpha=a)[0])(jnp.asarray(0.04, F32))
    assert np.isfinite(float(g))


def check_shade(tmp):
    D, c = shade_inputs()
    r = jscratch.shade(D, c, VIEWS, BOARD)
    assert r.shape == (2, P) and r.dtype == F32
    np.testing.assert_allclose([float(r.sum()), float(r[1, 7])],
                               [7.212867736816406, 0.2520864009857178], rtol=1e-5)
    r2 = jax.jit(jscratch.shade)(D, jnp.broadcast_to(c, (2, P)), VIEWS, BOARD)
    np.testing.assert_allclose(np.asarray(r2), np.asarray(r), rtol=1e-6)


def check_flat_highlight(tmp):
    x = jscratch.flat_highlight([[0.0, 0.0, 2.0]], [1.0, 0.0, 1.0])
    np.testing.assert_allclose(x, [[2 / 3, 0.0]])


def check_display(tmp):
    np.testing.assert_allclose(float(jscratch.display(0.5)), 0.5 ** (1 / 2.2), rtol=1e-6)


def check_half_vectors(tmp):
    h = np.asarray(jscratch.half_vectors(VIEWS, BOARD, dtype="float32"))
    assert h.shape == (2, P, 3) and h.dtype == np.float32
    ctr = np.asarray(jscratch.pixel_centres(BOARD), np.float64)
    p = np.concatenate([ctr, np.zeros((P, 1))], 1)[None]
    wo = np.asarray(VIEWS.camera, np.float64)[:, None] - p
    wi = np.asarray(VIEWS.light, np.float64)[:, None] - p
    ref = (wo / np.linalg.norm(wo, axis=-1, keepdims=True)
           + wi / np.linalg.norm(wi, axis=-1, keepdims=True))
    np.testing.assert_allclose(h, ref / np.linalg.norm(ref, axis=-1, keepdims=True), atol=1e-6)


def check_pixel_footprints(tmp):
    fp = np.asarray(jscratch.pixel_footprints(BOARD))
    dx, dy = BOARD.Sx / BOARD.W, BOARD.Sy / BOARD.H
    assert fp.shape == (P, 4, 2)
    np.testing.assert_allclose(fp[0], [[0, 0.3 - dy], [dx, 0.3 - dy], [dx, 0.3], [0, 0.3]],
                               atol=1e-7)


def check_write_svg(tmp):
    jscratch.write_svg(tmp / "ok.svg", demo_design(3))
    text = (tmp / "ok.svg").read_text()
    assert text.startswith("<?xml") and re.findall(r'<line id="(s\d)"', text) == ["s0", "s1", "s2"]


def check_order_scratches(tmp):
    r = toolpath.order_scratches([[0.0, 0.0], [1.0, 1.0]], [[1.0, 0.0], [2.0, 1.0]])
    assert r.order.tolist() == [0, 1] and r.flipped.tolist() == [False, False]


def check_calibrate_lambda_g(tmp):
    lam = loss.calibrate_lambda_g(*images())
    assert math.isclose(lam, 57.546742328603074, rel_tol=1e-4)
    assert math.isclose(loss.calibrate_lambda_g(*images(), ratio=np.float32(0.5)), 2 * lam,
                        rel_tol=1e-6)


GOOD = [check_pair_integral, check_shade, check_flat_highlight, check_display,
        check_half_vectors, check_pixel_footprints, check_write_svg, check_order_scratches,
        check_calibrate_lambda_g]


@pytest.mark.parametrize("check", GOOD, ids=[c.__name__.removeprefix("check_") for c in GOOD])
def test_a_good_call_gives_what_it_gave(check, tmp_path):
    check(tmp_path)
