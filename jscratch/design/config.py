"""The configuration of a design run: `DesignConfig`, the parameter groups and the errors."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from jscratch import loss as loss_mod
from jscratch.designfile import DesignError
from jscratch.render import DEFAULT_CHUNK
#: Parameter groups (learning rates and freezing are per group).
GROUPS = ("endpoints", "width", "depth", "alpha", "intensity")


#: Scratch position parameterisations: two endpoints (paper) or midpoint + direction + length.
PARAMETERISATIONS = ("endpoints", "midpoint")


#: Default weight of the ghosting term ``E_x`` in a design, against a zero baseline (the raw
#: cross-view SSIM, SPEC section 7's ghosting). Measured (benchmarks/RESULTS.md, issue 17,
#: session 9; 256 px, 20k scratches, 3 views, carvable grooves, seed 0): with ``lambda_g = 20``
#: and prune/re-seed every 10 iterations, 0.001 gave mean SSIM 0.802 and ghosting 0.211 against
#: the old defaults' 0.746 / 0.235 (camera / astronaut / chelsea), 0.746 / 0.328 vs 0.683 / 0.336
#: (coins / clock / line art), 0.781 / 0.241 vs 0.712 / 0.271 (text / brick / page); seed 1
#: (after the grid fix of session 9): 0.803 / 0.211 vs 0.746 / 0.236. At 60k scratches it gives
#: 0.880 / 0.201 vs 0.913 / 0.258 (less SSIM, less ghosting: there ``--lambda-g 200 --lambda-x 0
#: --prune-every 0`` keeps the old SSIM). 0.01 cut
#: ghosting to 0.077 but SSIM to 0.679; the excess-only baseline (``"targets"``) at 0.03 raised
#: the ghosting on the other two sets.
DESIGN_LAMBDA_X = 1e-3


#: Learning-rate schedules (`DesignConfig.lr_schedule`).
LR_SCHEDULES = ("constant", "cosine")


#: Default targets from ``skimage.data`` (bundled with scikit-image; nothing is downloaded).
DEFAULT_IMAGES = ("camera", "astronaut", "chelsea", "coffee", "rocket", "moon")


from jscratch.errors import NonFiniteError as NonFiniteError  # noqa: E402 (defined with its family)


@dataclasses.dataclass(frozen=True)
class DesignConfig:
    """Everything that controls an optimisation (JSON-friendly: `to_dict` / `from_dict`).

    **Fields** (units in brackets):

    - `n_scratches`: number of scratches ``N``. Default 20000.
    - `iterations`: Adam iterations. Default 100 (paper).
    - `seed`: seed of the initial layout (SPEC section 5).
    - `parameterisation`: ``"endpoints"`` (default, paper) or ``"midpoint"`` (ablation).
    - `init_width`, `init_depth` [m]: initial profile (paper Fig. 15: 2.5e-4, 1.28e-4).
    - `init_alpha`: initial GGX roughness. Default 0.04.
    - `init_length` [m]: initial lengths uniform in this range. Default (0.005, 0.025).
    - `lr_endpoints` [board widths per step] 1e-3 (paper); `lr_width`, `lr_depth` [log m],
      `lr_alpha` [logit], `lr_intensity` [log W/sr]: 1e-2 each.
    - `freeze`: groups not optimised (subset of `GROUPS`). Default ``("alpha",)``.
    - `loss`: a `loss.LossConfig`. Default ``E_p + LAMBDA_G E_g + DESIGN_LAMBDA_X E_x`` (filter
      bank, ``LAMBDA_G = 20``; ``E_x`` with ``ghost_baseline = "zero"``: the raw cross-view SSIM),
      issue 17's measured defaults (see `DESIGN_LAMBDA_X`). A `LossConfig` built by hand has no
      ``E_x`` unless it asks (``LossConfig.lambda_x`` defaults to 0).
    - `cull_eps`: per-view culling tolerance of `cull.cull` (0 keeps every pair). Default 0:
      measured on the default run, 1e-3 is 1.9x faster (295 s vs 546 s) but ends at 2.4x the loss
      (0.0323 vs 0.0136; SSIM 0.46/0.76/0.74 vs 0.69/0.75/0.82), 1e-2 far worse (module docstring).
    - `coverage_eps`: culling tolerance of the coverage pass (`cull.cull_coverage`, same error
      bound; only with ``cull_eps > 0``). Default 0 (every pair): measured with
      ``cull_eps = 1e-3``, 1e-3 saved 22% of the time (229 s vs 295 s) but lowered SSIM
      (0.463/0.738/0.707 vs 0.463/0.758/0.736): in dark regions the board term ``(1 - c) D_S``
      is the pixel's whole brightness, which the display gamma magnifies, and covering the board
      is how the optimiser darkens it.
    - `skin` [m]: groove inflation for binning (`bvh.allocate`); 0 rebins whenever a groove
      leaves its binned rectangle (about every step; cheaper than the extra pairs of a skin).
    - `discard`: run the discard step. `discard_tol`: allowed relative loss increase (0.01).
    - `init_intensity`: ``"match_mean"`` (closed form, default) or ``"given"`` (keep the views').
    - `adam_b1`, `adam_b2`, `adam_eps`: Adam constants. ``adam_eps = 1e-12`` because our losses
      are means over pixels (the paper's are sums), so gradients are ``H W`` times smaller.
    - `checkpoint_every`: iterations between checkpoints (when a checkpoint path is given).
    - `chunk`: pairs per chunk in the renderer (memory knob).
    - `dtype`: ``"float32"`` (default) or ``"float64"`` (needs ``jax_enable_x64``).
    - `groove`: ``"free"`` (default here: ``w, d`` optimised freely, as before issue 15) or
      ``"carvable"`` (one plunge per scratch within the machine's range, mapped to ``(w, d)`` by
      `jscratch.design.carvable`; the command line's default).
    - `machine`: the machine profile as a dict (`jscratch.machine.MachineProfile.to_dict`), or
      None for the shipped default; its cutter fixes the carvable grooves.
    - `prune_every` [iterations]: every this many iterations, move the least useful scratches
      to where the image is most too dark (`design.prune`); 0 never. Default 10 (issue 17,
      session 9: part of the measured defaults, see `DESIGN_LAMBDA_X`). The moved scratches end
      up useful, so the discard keeps more of them (+9-20 % scratches and carving time;
      ``target_ssim`` trades quality back for scratches).
    - `prune_fraction`: fraction of the ``N`` scratches moved per round. Default 0.05.
    - `prune_until`: no round after this fraction of ``iterations`` (moved scratches need
      iterations to settle). Default 0.6.
    - `target_ssim`: None (default: the discard's loss tolerance decides what is kept) or a mean
      SSIM (SPEC section 7, mean over views) in ``(0, 1]``: instead of the discard, keep the
      fewest scratches (dropped in the discard's score order) whose render still reaches it
      (`discard.fewest_for_ssim`; all are kept when the full design is below it). Reported in
      ``metrics["target"]``.
    - `lr_schedule`: ``"constant"`` (default, paper) or ``"cosine"``: every group's learning rate
      follows ``optax.cosine_decay_schedule`` from its value down to ``lr_final`` of it at
      ``iterations`` (resuming with a larger ``--iterations`` stretches the schedule).
    - `lr_final`: the cosine schedule's final fraction, in ``[0, 1]``. Default 0.1.
    """

    n_scratches: int = 20000
    iterations: int = 100
    seed: int = 0
    parameterisation: str = "endpoints"
    init_width: float = 2.5e-4
    init_depth: float = 1.28e-4
    init_alpha: float = 0.04
    init_length: tuple[float, float] = (0.005, 0.025)
    lr_endpoints: float = 1e-3
    lr_width: float = 1e-2
    lr_depth: float = 1e-2
    lr_alpha: float = 1e-2
    lr_intensity: float = 1e-2
    freeze: tuple[str, ...] = ("alpha",)
    loss: loss_mod.LossConfig = dataclasses.field(default_factory=lambda: loss_mod.LossConfig(
        lambda_x=DESIGN_LAMBDA_X, ghost_baseline="zero"))
    cull_eps: float = 0.0
    coverage_eps: float = 0.0
    skin: float = 0.0
    discard: bool = True
    discard_tol: float = 0.01
    init_intensity: str = "match_mean"
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    adam_eps: float = 1e-12
    checkpoint_every: int = 10
    chunk: int = DEFAULT_CHUNK
    dtype: str = "float32"
    groove: str = "free"
    machine: dict | None = None
    prune_every: int = 10
    prune_fraction: float = 0.05
    prune_until: float = 0.6
    target_ssim: float | None = None
    lr_schedule: str = "constant"
    lr_final: float = 0.1

    def __post_init__(self):
        def bad(name, what):
            raise DesignError(f"DesignConfig.{name} must be {what}, got {getattr(self, name)!r}")

        for name in ("n_scratches", "chunk", "checkpoint_every"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                bad(name, "a positive int")
        if not (isinstance(self.iterations, (int, np.integer)) and self.iterations >= 0):
            bad("iterations", "an int >= 0")
        if self.parameterisation not in PARAMETERISATIONS:
            bad("parameterisation", f"one of {PARAMETERISATIONS}")
        for name in ("init_width", "init_depth"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                bad(name, "a positive length in metres")
        if not (0 < self.init_alpha < 1):
            bad("init_alpha", "in (0, 1)")
        lo, hi = self.init_length
        if not (0 < lo <= hi and math.isfinite(hi)):
            bad("init_length", "(min, max) metres with 0 < min <= max")
        object.__setattr__(self, "init_length", (float(lo), float(hi)))
        for g in GROUPS:
            v = getattr(self, f"lr_{g}")
            if not (math.isfinite(v) and v >= 0):
                bad(f"lr_{g}", "a finite learning rate >= 0")
        freeze = tuple(self.freeze)
        for g in freeze:
            if g not in GROUPS:
                bad("freeze", f"a subset of {GROUPS}")
        object.__setattr__(self, "freeze", tuple(g for g in GROUPS if g in freeze))
        if isinstance(self.loss, dict):
            object.__setattr__(self, "loss", loss_mod.LossConfig(**self.loss))
        if not isinstance(self.loss, loss_mod.LossConfig):
            bad("loss", "a jscratch.loss.LossConfig")
        for name in ("cull_eps", "coverage_eps", "skin", "discard_tol"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                bad(name, "finite and >= 0")
        if self.init_intensity not in ("match_mean", "given"):
            bad("init_intensity", "'match_mean' or 'given'")
        if self.dtype not in ("float32", "float64"):
            bad("dtype", "'float32' or 'float64'")
        from jscratch.design.carvable import GROOVE_MODES

        if self.groove not in GROOVE_MODES:
            bad("groove", f"one of {GROOVE_MODES}")
        if self.machine is not None:
            from jscratch.machine import MachineProfile

            try:
                prof = MachineProfile.from_dict(dict(self.machine), source="DesignConfig.machine")
            except (TypeError, ValueError) as e:
                raise DesignError(str(e)) from None
            object.__setattr__(self, "machine", prof.to_dict())
        if not (isinstance(self.prune_every, (int, np.integer)) and self.prune_every >= 0):
            bad("prune_every", "an int >= 0 (iterations; 0 = never)")
        if self.lr_schedule not in LR_SCHEDULES:
            bad("lr_schedule", f"one of {LR_SCHEDULES}")
        for name in ("prune_fraction", "prune_until", "lr_final"):
            if not (math.isfinite(getattr(self, name)) and 0 <= getattr(self, name) <= 1):
                bad(name, "in [0, 1]")
        if self.target_ssim is not None and not (
                isinstance(self.target_ssim, (int, float)) and 0 < self.target_ssim <= 1):
            bad("target_ssim", "None or a mean SSIM in (0, 1]")

    def machine_profile(self):
        """The `jscratch.machine.MachineProfile` of `machine` (the shipped default when None)."""
        from jscratch.machine import MachineProfile

        return MachineProfile.from_dict(self.machine or {})

    def learning_rates(self) -> dict[str, float]:
        """Per-group learning rate, 0 for frozen groups."""
        return {g: 0.0 if g in self.freeze else float(getattr(self, f"lr_{g}")) for g in GROUPS}

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (``from_dict`` inverts it)."""
        d = dataclasses.asdict(self)
        d["init_length"] = list(self.init_length)
        d["freeze"] = list(self.freeze)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "DesignConfig":
        d = dict(d)
        if "loss" in d and isinstance(d["loss"], dict):
            d["loss"] = loss_mod.LossConfig(**d["loss"])
        if "init_length" in d:
            d["init_length"] = tuple(d["init_length"])
        if "freeze" in d:
            d["freeze"] = tuple(d["freeze"])
        return cls(**d)
