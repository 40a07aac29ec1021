"""What `design` returns: `DesignResult`."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from jscratch.scene import Board, Scratches, Views
from jscratch.design.config import DesignConfig
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
    - `history`: per-iteration lists ``"total"`` and the loss terms (loss at the parameters the
      iteration started from).
    - `metrics`: the metrics of docs/model.md §7 (`metrics.image_metrics`) plus ``loss``,
      ``loss_before_discard``, ``metrics_before_discard`` (the same metrics with every
      scratch),
      ``discarded``, ``kept``, ``pairs_total``, ``pairs_per_view``, ``coverage_pairs`` (pairs in
      the coverage pass after `cull.cull_coverage`), ``rebins``,
      timing (s): ``time_total``, ``time_first_step`` (includes compilation),
      ``time_step_median``, ``time_discard``.
    - `config`: the `DesignConfig`.
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
