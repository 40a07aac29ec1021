"""The configuration of a design: `DesignConfig` (the optimisation) and `SceneConfig` (targets,
views and board of the command line), each field declared once with its help, unit and flag
(`jscratch.options`): ``python -m jscratch.design`` is generated from them, and
`jscratch.design.design` with the same configs gives the same result bit for bit."""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

import numpy as np

from jscratch import loss as loss_mod
from jscratch.design.carvable import GROOVE_MODES
from jscratch.designfile import DesignError
from jscratch.errors import InputError, NonFiniteError
from jscratch.options import KnownFields, option
from jscratch.render import DEFAULT_CHUNK
from jscratch.scene import ALPHA_RANGE

__all__ = ["DesignConfig", "SceneConfig", "GROUPS", "PARAMETERISATIONS", "LR_SCHEDULES",
           "DEFAULT_IMAGES", "NonFiniteError"]

#: Parameter groups (learning rates and freezing are per group).
GROUPS = ("endpoints", "width", "depth", "alpha", "intensity")

#: Scratch position parameterisations: two endpoints (paper) or midpoint + direction + length.
PARAMETERISATIONS = ("endpoints", "midpoint")

#: Learning-rate schedules (`DesignConfig.lr_schedule`).
LR_SCHEDULES = ("constant", "cosine")

#: The most scratches and the largest image side a design takes: its scratch and pixel indices
#: are int32.
MAX_SCRATCHES, MAX_SIZE = 2**31 - 1, math.isqrt(2**31 - 1)

#: Default targets from ``skimage.data`` (bundled with scikit-image; nothing is downloaded).
DEFAULT_IMAGES = ("camera", "astronaut", "chelsea", "coffee", "rocket", "moon")


def _freeze_list(text: str) -> tuple[str, ...]:
    """``--freeze`` text: comma-separated groups, or ``none``."""
    text = text.strip()
    if text.lower() in ("", "none"):
        return ()
    return tuple(g.strip() for g in text.split(",") if g.strip())


def _machine_file(path: str) -> dict | None:
    """``--machine`` text: a machine profile TOML file, read into its dict (a refusal is the
    option's one-line error)."""
    import argparse

    from jscratch.machine import MachineProfile

    if path.strip().lower() == "none":
        return None
    try:
        return MachineProfile.from_toml(path).to_dict()
    except (OSError, ValueError, TypeError) as e:
        raise argparse.ArgumentTypeError(str(e).splitlines()[0]) from None


@dataclasses.dataclass(frozen=True)
class DesignConfig(KnownFields):
    """Everything that controls an optimisation (JSON-friendly: `to_dict` / `from_dict`).

    Each field's help, unit and command-line flag are declared with it (``python -m
    jscratch.design --help`` lists them); `docs/model.md` §5-§6 and §10 give the model behind them.
    The defaults are the measured ones of `benchmarks/RESULTS.md` (carvable grooves, ``E_p + 20 E_g
    + 0.001 E_x``, prune/re-seed every 10 iterations). Invalid values raise `DesignError` (an
    `jscratch.InputError`) naming the field and the accepted values.
    """

    _unknown_error = DesignError  # (`KnownFields`: a keyword that names no field)

    n_scratches: int = option(20000, "number of scratches N", flag="--scratches")
    iterations: int = option(100, "Adam iterations (with --resume: the total to reach)")
    seed: int = option(0, "seed of the initial layout (docs/model.md §5)")
    groove: str = option("carvable", "carvable: one plunge per scratch within the machine's range, "
                         "mapped to the groove profile (every groove cuttable); free: width and "
                         "depth optimised freely", choices=GROOVE_MODES)
    machine: dict | None = option(
        None, "machine profile TOML (python -m jscratch.machine prints the default, the paper's "
        "ball-end cutter); recorded in the design file for python -m jscratch.fabricate; none: the "
        "shipped default", parse=_machine_file, metavar="FILE")
    parameterisation: str = option("endpoints", "scratch position parameters",
                                   choices=PARAMETERISATIONS)
    init_width: float = option(2.5e-4, "initial groove width w", unit="m")
    init_depth: float = option(1.28e-4, "initial groove depth d", unit="m")
    init_alpha: float = option(0.04, "initial GGX roughness alpha")
    init_length: tuple[float, float] = option((0.005, 0.025), "initial lengths, uniform in MIN MAX",
                                              unit="m", metavar=("MIN", "MAX"))
    lr_endpoints: float = option(1e-3, "learning rate of the endpoints", unit="board widths/step")
    lr_width: float = option(1e-2, "learning rate of the width; with --groove carvable of the "
                             "plunge logit", unit="log m; logit")
    lr_depth: float = option(1e-2, "learning rate of the depth (unused with --groove carvable, "
                             "whose depth follows from the plunge)", unit="log m")
    lr_alpha: float = option(1e-2, "learning rate of the roughness", unit="logit")
    lr_intensity: float = option(1e-2, "learning rate of the light intensities", unit="log W/sr")
    freeze: tuple[str, ...] = option(("alpha",), f"groups not optimised, comma-separated from "
                                     f"{','.join(GROUPS)}, or none", parse=_freeze_list,
                                     metavar="GROUPS")
    loss: loss_mod.LossConfig = option(default_factory=loss_mod.LossConfig, nested=True,
                                       help="the loss (jscratch.loss.LossConfig)")
    cull_eps: float = option(0.0, "per-view pair culling tolerance, a fraction of a pair's peak "
                             "value (0: every pair; 1e-3 optimises worse and, with the native "
                             "kernel, is not faster: docs/model.md §11)")
    coverage_eps: float = option(0.0, "coverage-pass culling tolerance, with --cull-eps > 0 (0: "
                                 "every pair; fewer coverage pairs, but dark regions can lose "
                                 "contrast)")
    skip_eps: float = option(0.0, "the step skips a pair-view whose NDF bound is below this "
                             "fraction of the pair's peak value, unless it is the pair's "
                             "brightest view (0: every pair-view; 5e-5: a step 6 % faster with "
                             "the native kernel, designs slightly worse, dense ones clearly: "
                             "docs/model.md §11)")
    skin: float = option(0.0, "groove inflation for binning (0: rebin when a groove leaves its "
                         "binned cells)", unit="m")
    discard: bool = option(True, "discard the least useful scratches after the optimisation")
    discard_tol: float = option(0.01, "discard: allowed relative loss increase")
    init_intensity: str = option("match_mean", "initial light intensities: matching the "
                                 "targets' mean display values, or the views' given ones",
                                 choices=("match_mean", "given"))
    adam_b1: float = option(0.9, "Adam beta1")
    adam_b2: float = option(0.999, "Adam beta2")
    adam_eps: float = option(1e-12, "Adam epsilon (losses are pixel means, so gradients are small)")
    checkpoint_every: int = option(10, "iterations between checkpoints")
    chunk: int = option(DEFAULT_CHUNK, "pairs per chunk in the renderer (memory knob)")
    dtype: str = option("float32", "working precision (float64 needs jax_enable_x64)",
                        choices=("float32", "float64"))
    prune_every: int = option(10, "iterations between prune/re-seed rounds that move the least "
                              "useful scratches to where a view is too dark (0: never)")
    prune_fraction: float = option(0.05, "fraction of the scratches moved per prune/re-seed round")
    prune_per_pixel: float = option(0.016, "at most this many scratches per image pixel moved per "
                                    "round (0: no cap); the round's count is the smaller of the two")
    prune_until: float = option(0.6, "no prune/re-seed round after this fraction of the iterations")
    dense_from: float = option(
        0.4, "scratches per image pixel from which a design is dense (0: never): a dense design "
        "comes close to its targets, so it makes no prune/re-seed rounds (they would cost more "
        "picture than they bring) and weighs E_g by dense_lambda_g when lambda_g is not given")
    dense_lambda_g: float = option(60.0, "E_g's weight in a dense design when loss.lambda_g is "
                                   "not given (the filter bank's LAMBDA_G otherwise)")
    target_ssim: float | None = option(
        None, "instead of the discard, keep the fewest scratches whose mean SSIM over the views "
        "(docs/model.md §7, 0-1) stays at least this (all when the full design is below it)")
    lr_schedule: str = option("constant", "learning rates constant (paper) or cosine-decayed to "
                              "--lr-final of their values over the iterations", choices=LR_SCHEDULES)
    lr_final: float = option(0.1, "cosine schedule: final learning rates as a fraction (0-1)")

    def __post_init__(self):
        def bad(name, what):
            raise DesignError(f"DesignConfig.{name} must be {what}, got {getattr(self, name)!r}")

        def number(name, lo=-math.inf, hi=math.inf, what=None):
            v = getattr(self, name)
            ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
            if not (ok and math.isfinite(v) and lo <= v <= hi):
                bad(name, what or f"a finite number in [{lo}, {hi}]")
            object.__setattr__(self, name, float(v))

        def integer(name, lo):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= lo):
                bad(name, f"an int >= {lo}")
            object.__setattr__(self, name, int(v))

        for name in ("n_scratches", "iterations", "chunk", "checkpoint_every"):
            integer(name, 1)
        if self.n_scratches > MAX_SCRATCHES:
            bad("n_scratches", f"an int in [1, {MAX_SCRATCHES}] (scratch indices are 32-bit)")
        integer("seed", 0)
        if self.seed >= 2**63:  # jax.random.PRNGKey takes a signed 64-bit seed
            bad("seed", "an int in [0, 2**63)")
        integer("prune_every", 0)
        if not isinstance(self.discard, (bool, np.bool_)):
            bad("discard", "true or false")
        object.__setattr__(self, "discard", bool(self.discard))
        for name, choices in (("parameterisation", PARAMETERISATIONS), ("groove", GROOVE_MODES),
                              ("init_intensity", ("match_mean", "given")),
                              ("dtype", ("float32", "float64")), ("lr_schedule", LR_SCHEDULES)):
            if getattr(self, name) not in choices:
                bad(name, f"one of {choices}")
        for name in ("init_width", "init_depth"):
            number(name, 0.0, what="a positive length in metres")
            if getattr(self, name) <= 0:
                bad(name, "a positive length in metres")
        a_lo, a_hi = ALPHA_RANGE
        number("init_alpha", a_lo, a_hi, f"in [{a_lo:g}, {a_hi:g}]")
        if not a_lo <= self.init_alpha <= a_hi:
            bad("init_alpha", f"in [{a_lo:g}, {a_hi:g}] (the scene's rule)")
        try:
            lo, hi = (float(x) for x in self.init_length)
        except (TypeError, ValueError, OverflowError):
            bad("init_length", "(min, max) metres with 0 < min <= max")
        if not (0 < lo <= hi and math.isfinite(hi)):
            bad("init_length", "(min, max) metres with 0 < min <= max")
        object.__setattr__(self, "init_length", (lo, hi))
        for g in GROUPS:
            number(f"lr_{g}", 0.0, what="a finite learning rate >= 0")
        if not isinstance(self.freeze, (str, list, tuple)):
            bad("freeze", f"a subset of {GROUPS}")
        freeze = (self.freeze,) if isinstance(self.freeze, str) else tuple(self.freeze)
        if any(g not in GROUPS for g in freeze):
            bad("freeze", f"a subset of {GROUPS}")
        object.__setattr__(self, "freeze", tuple(g for g in GROUPS if g in freeze))
        if isinstance(self.loss, dict):
            if not all(isinstance(k, str) for k in self.loss):
                bad("loss", "a jscratch.loss.LossConfig or its fields (a dict)")
            try:
                object.__setattr__(self, "loss", loss_mod.LossConfig(**self.loss))
            except (TypeError, InputError) as e:
                if not str(e).startswith("LossConfig: unknown fields"):
                    raise
                unknown = sorted(set(self.loss) - {f.name for f in dataclasses.fields(
                    loss_mod.LossConfig)})
                raise DesignError(f"DesignConfig.loss: unknown fields {unknown}") from None
        if not isinstance(self.loss, loss_mod.LossConfig):
            bad("loss", "a jscratch.loss.LossConfig")
        for name in ("cull_eps", "coverage_eps", "skip_eps"):  # 1 would cull every pair (§11)
            number(name, 0.0, 1.0, "in [0, 1) (a fraction of a pair's peak value)")
            if getattr(self, name) >= 1:
                bad(name, "in [0, 1) (a fraction of a pair's peak value)")
        for name in ("skin", "discard_tol", "prune_per_pixel", "dense_from", "dense_lambda_g"):
            number(name, 0.0, what="finite and >= 0")
        for name in ("adam_b1", "adam_b2"):
            number(name, 0.0, 1.0, "in [0, 1)")
            if getattr(self, name) >= 1:
                bad(name, "in [0, 1)")
        number("adam_eps", 0.0, what="finite and > 0")
        if self.adam_eps <= 0:  # 0 divides 0 by 0 in a frozen or flat group
            bad("adam_eps", "finite and > 0")
        from jscratch.machine import MachineProfile

        if not (self.machine is None or isinstance(self.machine, dict)):
            bad("machine", "None or a machine profile's fields (a dict)")
        try:  # None is the shipped default, recorded explicitly so that a run's config says it
            prof = MachineProfile.from_dict(dict(self.machine or {}),
                                            source="DesignConfig.machine")
        except (TypeError, ValueError) as e:
            raise DesignError(str(e)) from None
        object.__setattr__(self, "machine", prof.to_dict())
        for name in ("prune_fraction", "prune_until", "lr_final"):
            number(name, 0.0, 1.0, "in [0, 1]")
        if self.target_ssim is not None:
            number("target_ssim", 0.0, 1.0, "None or a mean SSIM in (0, 1]")
            if self.target_ssim <= 0:
                bad("target_ssim", "None or a mean SSIM in (0, 1]")

    def is_dense(self, pixels: int, n: int | None = None) -> bool:
        """Whether ``n`` scratches (default ``n_scratches``) are at least ``dense_from`` per image
        pixel (``pixels`` per view)."""
        n = self.n_scratches if n is None else n
        return self.dense_from > 0 and n >= self.dense_from * pixels

    def design_loss(self, pixels: int) -> loss_mod.LossConfig:
        """The `loss` a design runs: ``lambda_g`` = ``dense_lambda_g`` for a dense design with the
        filter bank and no ``lambda_g`` given (docs/model.md §6), else `loss` as it is."""
        lc = self.loss
        if (lc.lambda_g is None and lc.vgg_weights is None and lc.kind == "perceptual+gram"
                and self.is_dense(pixels)):
            return dataclasses.replace(lc, lambda_g=float(self.dense_lambda_g))
        return lc

    def machine_profile(self):
        """The `jscratch.machine.MachineProfile` of `machine`."""
        from jscratch.machine import MachineProfile

        return MachineProfile.from_dict(self.machine)

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
        """The config of `to_dict`'s form (missing fields take their defaults; unknown ones are
        refused with `DesignError`)."""
        if not isinstance(d, dict):
            raise DesignError(f"a DesignConfig must be a JSON object, got {type(d).__name__}")
        d = dict(d)
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise DesignError(f"DesignConfig: unknown fields {unknown}")
        for name in ("init_length", "freeze"):  # JSON lists; anything else is refused by the class
            if isinstance(d.get(name), list):
                d[name] = tuple(d[name])
        return cls(**d)


@dataclasses.dataclass(frozen=True)
class SceneConfig(KnownFields):
    """The inputs of a design run that are not optimised: targets, views and board, as the
    command line sets them up (`jscratch.design.io.load_scene` builds them; `design` uses the same
    view and board defaults when none are given).

    Angles are in degrees here (the command line's unit); `jscratch.scene.views_on_circle` takes
    radians. Invalid values raise `DesignError` naming the field.
    """

    _unknown_error = DesignError  # (`KnownFields`: a keyword that names no field)

    targets: tuple[str, ...] = option((), "target image files, one per view (grayscale or RGB, "
                                      "the board's aspect); none: images bundled with "
                                      "scikit-image", flag="targets", metavar="TARGET")
    views: int | None = option(None, "number of views M (default: the number of targets, or 3)")
    theta_deg: float = option(50.0, "polar angle of the light and cameras from the board normal",
                              unit="degrees")
    camera_theta_deg: float | None = option(None, "polar angle of the cameras (default: "
                                            "--theta-deg)", unit="degrees")
    distance: float = option(1.0, "distance of the light and cameras from the board centre",
                             unit="m")
    offset_deg: float | None = option(None, "azimuth of camera 0 relative to the light (default "
                                      "keeps the cameras away from the light's mirror "
                                      "direction)", unit="degrees")
    board: float = option(0.3, "board side (square board)", unit="m")
    size: int = option(256, "image size", unit="pixels per side")

    def __post_init__(self):
        def bad(name, what):
            raise DesignError(f"scene {name} must be {what}, got {getattr(self, name)!r}")

        try:
            targets = (self.targets,) if isinstance(self.targets, str) else tuple(self.targets)
        except TypeError:
            bad("targets", "a list of image file paths")
        if not all(isinstance(t, str) and t for t in targets):
            bad("targets", "a list of image file paths")
        # Absolute: a config.json saved with them repeats (--config) or resumes from any folder.
        object.__setattr__(self, "targets", tuple(os.path.abspath(t) for t in targets))
        if self.views is not None:
            if not (isinstance(self.views, (int, np.integer)) and not isinstance(self.views, bool)
                    and self.views >= 1):
                bad("views", "an int >= 1")
            object.__setattr__(self, "views", int(self.views))
            if targets and self.views != len(targets):
                raise DesignError(f"got {len(targets)} target images for {self.views} views: "
                                  "give one target per view")
        if not (isinstance(self.size, (int, np.integer)) and not isinstance(self.size, bool)
                and 16 <= self.size <= MAX_SIZE):
            bad("size", f"an int in [16, {MAX_SIZE}] (pixels; pixel indices are 32-bit)")
        object.__setattr__(self, "size", int(self.size))
        for name in ("theta_deg", "camera_theta_deg", "offset_deg", "distance", "board"):
            v = getattr(self, name)
            if v is None and name in ("camera_theta_deg", "offset_deg"):
                continue
            if not (isinstance(v, (int, float, np.integer, np.floating))
                    and not isinstance(v, bool) and math.isfinite(v)):
                bad(name, "a finite number")
            object.__setattr__(self, name, float(v))
        for name in ("theta_deg", "camera_theta_deg"):
            v = getattr(self, name)
            if v is not None and not 0 <= v < 90:
                bad(name, "in [0, 90) degrees (above the board)")
        for name in ("distance", "board"):
            if getattr(self, name) <= 0:
                bad(name, "positive (m)")

    @property
    def n_views(self) -> int:
        """The number of views ``M``."""
        return self.views if self.views is not None else (len(self.targets) or 3)

    def make_board(self):
        """The square `jscratch.scene.Board` of side `board` with a `size` x `size` image."""
        from jscratch.scene import Board

        return Board(shape=(self.size, self.size), Sx=self.board, Sy=self.board)

    def make_views(self, m: int | None = None, board=None):
        """`jscratch.scene.views_on_circle` for ``m`` views (default `n_views`) over `board`."""
        from jscratch.scene import views_on_circle

        def rad(v):
            return None if v is None else math.radians(v)

        try:
            return views_on_circle(self.n_views if m is None else m, rad(self.theta_deg),
                                   self.distance, rad(self.offset_deg),
                                   self.make_board() if board is None else board,
                                   camera_theta=rad(self.camera_theta_deg))
        except ValueError as e:
            raise DesignError(f"impossible view set-up: {e}") from None

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (`from_dict` inverts it)."""
        d = dataclasses.asdict(self)
        d["targets"] = list(self.targets)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SceneConfig":
        """The scene of `to_dict`'s form (unknown fields refused with `DesignError`)."""
        if not isinstance(d, dict):
            raise DesignError(f"a SceneConfig must be a JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise DesignError(f"SceneConfig: unknown fields {unknown}")
        return cls(**{k: tuple(v) if k == "targets" and isinstance(v, list) else v
                      for k, v in d.items()})
