"""Tests of the learning-rate schedule (``DesignConfig.lr_schedule``, `solver.make_adam`): the
cosine schedule scales Adam's steps by the closed-form cosine factor written out here, the constant
one is plain Adam, and the options reach ``--help`` and the errors."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jscratch.design import DesignConfig, DesignError, solver
from jscratch.design.cli import main


def _cosine(k, steps, final):
    """The factor at update ``k`` (0-based), written out (not optax)."""
    k = min(k, steps)
    return final + (1 - final) * 0.5 * (1 + math.cos(math.pi * k / steps))


def test_cosine_schedule_scales_adam_steps():
    plain = solver.make_adam(0.9, 0.999, 1e-12)
    sched = solver.make_adam(0.9, 0.999, 1e-12, 10, 0.1)
    assert solver.make_adam(0.9, 0.999, 1e-12, 10, 0.1) is sched  # cached
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=5))
    sp, ss = plain.init(x), sched.init(x)
    for k in range(13):
        g = jnp.asarray(rng.normal(size=5))
        up, sp = plain.update(g, sp, x)
        us, ss = sched.update(g, ss, x)
        np.testing.assert_allclose(np.asarray(us), _cosine(k, 10, 0.1) * np.asarray(up),
                                   rtol=1e-5)
    # the last scheduled step is at a tenth of the first's scale
    assert _cosine(10, 10, 0.1) == pytest.approx(0.1)


def test_schedule_config_and_cli(capsys):
    with pytest.raises(DesignError, match="lr_schedule"):
        DesignConfig(lr_schedule="linear")
    with pytest.raises(DesignError, match="lr_final"):
        DesignConfig(lr_final=1.5)
    assert main(["--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for opt in ("--lr-schedule", "--lr-final", "--target-ssim", "--prune-every", "--lambda-x"):
        assert opt in out
    assert "default: constant" in out and "default: 0.1" in out
