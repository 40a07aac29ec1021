"""Test configuration: float64 available for references, 4 forced CPU devices for sharding tests.

Library code follows the dtype of its inputs; float32 tests build float32 arrays explicitly.
"""

import os

os.environ.setdefault("XLA_FLAGS", "")
if "xla_force_host_platform_device_count" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_force_host_platform_device_count=4"

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_platforms", "cpu")


import pytest  # noqa: E402


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
