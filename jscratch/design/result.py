"""What `design` returns: `DesignResult`."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from jscratch.scene import Board, Scratches, Views
from jscratch.design.config import DesignConfig, SceneConfig
from jscratch.design.params import DesignParams


@dataclasses.dataclass
class DesignResult:
    """What `design` returns.

    **Fields:**

    - `scratches`: the final `render.Scratches` after the discard step (``N_kept`` scratches).
    - `views`: `render.Views` with the optimised intensities.
    - `board`: the `render.Board`.
    - `params`: final `DesignParams` (all ``N`` scratches, before the discard).
    - `keep`: ``(N,)`` bool, the scratches kept by the discard.
    - `radiance`, `display`: ``(M, H, W)`` final renders (after the discard).
    - `targets`: ``(M, H, W)`` the targets.
    - `history`: ``{"total": [...], "terms": {name: [...]}}``, the loss and each loss term per
      iteration (at the parameters the iteration started from).
    - `metrics`: docs/model.md §7 metrics (`metrics.image_metrics`) plus ``loss``,
      ``loss_before_discard``, ``metrics_before_discard`` (the same metrics with every scratch),
      ``discarded``, ``kept``, ``pairs_total`` (pairs binned in the final shared list),
      ``pair_capacity`` (its slots), ``pairs_per_view``, ``coverage_pairs`` (pairs in the
      coverage pass after `cull.cull_coverage`), ``pair_views_evaluated`` (summed over the
      steps), ``skip_eps`` (the steps' pair-view skipping tolerance), ``rebins`` (rebuilds of
      the shared list: in the steps and at prune rounds),
      timing (s): ``time_total``, ``time_first_step`` (the first step's wall time; the step is
      compiled meanwhile on a second thread, whose wall time is ``time_compile_step``),
      ``time_step_median``, ``time_discard``, ``time_parts`` (``setup``, ``initial_state``,
      ``steps``, ``prune``, ``rebuild_overflow``, ``checkpoint``, ``finish``: the final render,
      discard and metrics); ``kernel``: which pair kernel ran
      (`jscratch.native.status`). `jscratch.design.io.save_result` adds the machine, the groove
      mode, the carving estimate and (optionally) the as-carved SSIM.
    - `config`: the `DesignConfig`.
    - `scene`, `names`: the `SceneConfig` and target names the run was made from, when known
      (`load_result` reads them from a run folder; `save_result` writes them unless given others);
      None for a design made by `design` from Python (its targets are arrays, not files;
      ``save_result(..., scene=, names=)`` records them).
    """

    scratches: Scratches
    views: Views
    board: Board
    params: DesignParams
    keep: np.ndarray
    radiance: np.ndarray
    display: np.ndarray
    targets: np.ndarray
    history: dict[str, list]
    metrics: dict[str, Any]
    config: DesignConfig
    scene: SceneConfig | None = None
    names: list[str] | None = None
