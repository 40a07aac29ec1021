"""Test configuration: float32 by default, float64 per test, 4 forced CPU devices for sharding
tests, XLA's CPU fusion emitters off, one JAX compilation cache per run.

The tests compile with ``--xla_cpu_use_fusion_emitters=false`` (unless ``XLA_FLAGS`` already sets
it): the design's step and `jscratch.compile_options.few_calls_jit` compile so anyway, and the
suite's compilations, most of its time, are about a third faster.
``tests/test_compile_options.py`` renders values and gradients in a process with XLA's default
flags and checks they are the suite's to float32 rounding.

Tests run in JAX's default float32 (what users run). A test that needs float64 (a float64
reference, ``jnp.float64`` arrays) is marked ``@pytest.mark.float64`` (or its module sets
``pytestmark = pytest.mark.float64``); its setup, call and teardown then run inside
``jax.enable_x64(True)``. Library code follows the dtype of its inputs; tests build their arrays
with an explicit dtype. Requesting float64 from JAX outside a marked test is an error (the
``filterwarnings`` entry in pyproject.toml), so a missing mark fails instead of silently testing
float32.
"""

import atexit
import contextlib
import os
import shutil
import tempfile

# One JAX compilation cache for the whole run: the xdist workers and the command lines the tests
# start inherit it, so a program that several of them compile alike (a small design's step) is
# compiled once. It lives as long as the process that made it (the controller).
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="jscratch-tests-xla-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.3")

os.environ.setdefault("XLA_FLAGS", "")
if "xla_force_host_platform_device_count" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_force_host_platform_device_count=4"
if "xla_cpu_use_fusion_emitters" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_cpu_use_fusion_emitters=false"

import jax  # noqa: E402

jax.config.update("jax_enable_x64", False)
jax.config.update("jax_platforms", "cpu")


import pytest  # noqa: E402


def _x64(item):
    """The x64 context of one test phase: on for tests marked ``float64``, none otherwise."""
    if item.get_closest_marker("float64") is not None:
        return jax.enable_x64(True)
    return contextlib.nullcontext()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item):
    # Fixtures are built in setup: a marked test's fixtures (any scope) get x64 too.
    with _x64(item):
        return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item):
    with _x64(item):
        return (yield)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item, nextitem):
    try:
        with _x64(item):
            return (yield)
    finally:
        # A test that switched x64 on globally (jax.config.update) does not leak it to the next.
        jax.config.update("jax_enable_x64", False)


@pytest.fixture(scope="session")
def two_view_scene():
    """The small design scene of the prune and target-quality tests: two default targets at
    32 x 32 px and two views on a 50-degree circle, ``(targets, views, board)``."""
    import math

    from jscratch.design.io import default_targets
    from jscratch.scene import Board, views_on_circle

    targets, _ = default_targets(2, (32, 32))
    board = Board(shape=(32, 32))
    return targets, views_on_circle(2, math.radians(50), board=board), board


@pytest.fixture(scope="session")
def random_layout():
    """``layout(rng, n, lo, hi) -> (mid (n, 2), u (n, 2))``: scratch midpoints uniform in
    ``[lo, hi]^2`` (m) and unit directions of uniform angle, drawn in that order from `rng` (the
    random scenes of the binning and culling tests)."""
    import numpy as np

    def layout(rng, n, lo, hi):
        mid = rng.uniform(lo, hi, (n, 2))
        ang = rng.uniform(0, 2 * np.pi, n)
        return mid, np.stack([np.cos(ang), np.sin(ang)], -1)

    return layout


@pytest.fixture(scope="session")
def smooth_images():
    """``images(m, h, w, seed) -> (m, h, w)``: smooth random images in [0, 1] (float64 numpy;
    a Gaussian blur of uniform noise, stretched to the full range), for the SSIM and ghosting
    tests."""
    import numpy as np
    from skimage.filters import gaussian

    def images(m=3, h=24, w=20, seed=0):
        base = gaussian(np.random.default_rng(seed).uniform(size=(m, h, w)), sigma=(0, 1.5, 1.5))
        return (base - base.min()) / (base.max() - base.min())

    return images
