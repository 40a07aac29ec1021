"""The optimised parameters: `DesignParams` in unconstrained coordinates and `group_tree`."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jscratch.designfile import DesignError
from jscratch.scene import ALPHA_RANGE, Board, Scratches
from jscratch.design.config import PARAMETERISATIONS


_SIG = 4.0  # endpoint map u = sigmoid(_SIG z): unit slope du/dz = 1 at the board centre


_U_EPS = 1e-6  # initial board-normalised coordinates are kept this far inside [0, 1]


def _logit(u):
    return np.log(u) - np.log1p(-u)


class DesignParams(eqx.Module):
    """Optimised parameters in unconstrained coordinates (see the module docstring).

    **Fields:**

    - `geom`: ``(N, 4)``: ``"endpoints"``: ``(z0x, z0y, z1x, z1y)`` with ``p = S sigmoid(4 z)``;
      ``"midpoint"``: ``(zmx, zmy, angle [rad], log length [log m])``.
    - `log_width`, `log_depth` ``(N,)`` (log m); `logit_alpha` ``(N,)``;
      `log_intensity` ``(M,)`` (log W/sr).
    - `parameterisation` (static) and `board_size` ``(Sx, Sy)`` m (static).
    - `groove` (static): None (free ``w, d``) or a `jscratch.design.carvable.GrooveMap`; then
      `log_width` holds the plunge logit ``z`` (``p = p_min + (p_max - p_min) sigmoid(z)``),
      ``(w, d)`` follow from ``p`` and `log_depth` is unused (its gradient is zero).
    """

    geom: Float[Array, "n 4"]
    log_width: Float[Array, " n"]
    log_depth: Float[Array, " n"]
    logit_alpha: Float[Array, " n"]
    log_intensity: Float[Array, " m"]
    parameterisation: str = eqx.field(static=True, default="endpoints")
    board_size: tuple[float, float] = eqx.field(static=True, default=(0.3, 0.3))
    groove: Any = eqx.field(static=True, default=None)

    @staticmethod
    def from_physical(scratches: Scratches, intensity: ArrayLike, board: Board,
                      parameterisation: str = "endpoints", groove=None) -> "DesignParams":
        """Unconstrained coordinates of concrete scratches and intensities (host side).

        Endpoints are first moved ``1e-6`` board widths inside the board (the sigmoid never
        reaches its ends). Returns arrays in ``scratches.dtype``. With a `groove` map the
        plunge is the one whose cut has the scratch's groove width (clipped to the range).
        """
        dt = scratches.dtype
        size = np.array([board.Sx, board.Sy])
        p0 = np.asarray(scratches.p0, np.float64)
        p1 = np.asarray(scratches.p1, np.float64)
        if parameterisation == "endpoints":
            u = np.clip(np.concatenate([p0, p1], 1) / np.tile(size, 2), _U_EPS, 1 - _U_EPS)
            geom = _logit(u) / _SIG
        elif parameterisation == "midpoint":
            um = np.clip(0.5 * (p0 + p1) / size, _U_EPS, 1 - _U_EPS)
            d = p1 - p0
            length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-6)
            geom = np.concatenate(
                [_logit(um) / _SIG, np.arctan2(d[:, 1], d[:, 0])[:, None], np.log(length)[:, None]], 1
            )
        else:
            raise DesignError(f"parameterisation must be one of {PARAMETERISATIONS}, got {parameterisation!r}")
        a = np.asarray(scratches.alpha, np.float64)
        inten = np.broadcast_to(np.asarray(intensity, np.float64), np.shape(intensity) or (1,))
        log_w = np.log(np.asarray(scratches.width, np.float64))
        log_d = np.log(np.asarray(scratches.depth, np.float64))
        if groove is not None:
            log_w = groove.z_of_plunge(groove.plunge_of_profile(np.exp(log_w), np.exp(log_d)))
            log_d = np.zeros_like(log_w)
        return DesignParams(
            geom=jnp.asarray(geom, dt),
            log_width=jnp.asarray(log_w, dt),
            log_depth=jnp.asarray(log_d, dt),
            logit_alpha=jnp.asarray(_logit(a), dt),
            log_intensity=jnp.asarray(np.log(np.maximum(inten, 1e-300)), dt),
            parameterisation=parameterisation,
            board_size=(float(board.Sx), float(board.Sy)),
            groove=groove,
        )

    def endpoints(self) -> tuple[Array, Array]:
        """``(p0, p1)``, each ``(N, 2)`` board metres, on the board."""
        size = jnp.asarray(self.board_size, self.geom.dtype)
        if self.parameterisation == "endpoints":
            u = jax.nn.sigmoid(_SIG * self.geom)
            return u[:, :2] * size, u[:, 2:] * size
        m = jax.nn.sigmoid(_SIG * self.geom[:, :2]) * size
        ang, half = self.geom[:, 2], 0.5 * jnp.exp(self.geom[:, 3])
        t = jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1) * half[:, None]
        return jnp.clip(m - t, 0, size), jnp.clip(m + t, 0, size)

    def alpha(self) -> Array:
        """Roughness ``(N,)``: ``sigmoid(logit_alpha)`` held in the scene's `ALPHA_RANGE` (an
        optimised alpha stops at the range's ends instead of leaving it)."""
        return jnp.clip(jax.nn.sigmoid(self.logit_alpha), *ALPHA_RANGE)

    def scratches(self) -> Scratches:
        """The physical `render.Scratches` (jittable)."""
        p0, p1 = self.endpoints()
        if self.groove is not None:
            w, d = self.groove.profile(self.log_width)
            return Scratches(p0, p1, w, d, self.alpha(), profile=self.groove.scratch_profile)
        return Scratches(p0, p1, jnp.exp(self.log_width), jnp.exp(self.log_depth), self.alpha())

    def plunge(self) -> Array | None:
        """Per-scratch plunge ``(N,)`` (m) with a `groove` map, else None."""
        return None if self.groove is None else self.groove.plunge(self.log_width)

    def intensity(self) -> Array:
        """Light intensities ``(M,)`` (W/sr)."""
        return jnp.exp(self.log_intensity)

    def group(self, name: str) -> Array:
        """The unconstrained array of a parameter group."""
        return {"endpoints": self.geom, "width": self.log_width, "depth": self.log_depth,
                "alpha": self.logit_alpha, "intensity": self.log_intensity}[name]


def group_tree(params: DesignParams, values: dict[str, Any]) -> DesignParams:
    """A `DesignParams`-shaped pytree with ``values[group]`` at each group's leaf."""
    return DesignParams(values["endpoints"], values["width"], values["depth"], values["alpha"],
                        values["intensity"], params.parameterisation, params.board_size,
                        params.groove)
