"""Tests of jscratch.design.result: `DesignResult` documents every field it has, and holds what a
design hands back (a kept subset consistent with `keep`, renders shaped like the targets)."""

import dataclasses
import re

import numpy as np

from jscratch.design.config import DesignConfig
from jscratch.design.result import DesignResult
from jscratch.scene import Board, Scratches, Views


def test_every_field_is_documented():
    doc = DesignResult.__doc__
    # bullets "- `a`: ..." or "- `a`, `b`: ..."
    bullets = re.findall(r"^\s*- ((?:`\w+`(?:, )?)+):", doc, re.M)
    documented = [name for b in bullets for name in re.findall(r"`(\w+)`", b)]
    assert documented == [f.name for f in dataclasses.fields(DesignResult)]


def test_fields_round_trip_through_replace():
    board = Board(shape=(16, 16))
    s = Scratches(np.float32([[0.01, 0.02]]), np.float32([[0.05, 0.02]]))
    v = Views(np.float32([[0.0, 0.5, 0.8]]), np.float32([[0.3, 0.3, 0.9]]))
    img = np.zeros((1, 16, 16))
    r = DesignResult(s, v, board, None, np.array([True, False]), img, img, img, {"total": []}, {},
                     DesignConfig(n_scratches=2))
    assert r.keep.sum() == r.scratches.n and r.display.shape == r.targets.shape
    r2 = dataclasses.replace(r, metrics={"kept": 1})
    assert r2.metrics == {"kept": 1} and r2.scratches is r.scratches and r.metrics == {}
