"""GRBL protocol pieces against the simulated controller on a real pty: feedback tags with digits,
the strict number formatter, bounded messages, connecting without a reset, the lost-ok watchdog."""

import os
import re
import sys
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, os.path.dirname(__file__))

from grbl_sim import BANNER, GrblSim  # noqa: E402

from jscratch.grbl import WORD_FORMAT, Grbl, Stalled, check_words, classify, clip, gword  # noqa: E402

OPEN = dict(banner_timeout=1.0, poll_interval=0.05, stall_timeout=5.0)


def test_feedback_tags_with_digits_are_feedback():
    for line in ("[G54:1.000,2.000,0.000]", "[G92:5.000,4.000,2.000]", "[G28:0.000,0.000,0.000]",
                 "[G30:0.000,0.000,0.000]", "[TLO:0.000]", "[PRB:0.000,0.000,0.000:0]",
                 "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "[VER:1.1h.20190825:]", "[MSG:Reset to continue]"):
        assert classify(line).kind == "msg", line
    for junk in ("[g54:1.000]", "[54:1.000]", "[G54 1.000]", "G54:1.000]", "[G54:1.000"):
        assert classify(junk).kind == "unknown", junk


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(WORD_FORMAT)), st.floats(allow_nan=True, allow_infinity=True))
def test_gword_is_fixed_point_in_range_or_refuses(letter, value):
    dec, lo, hi = WORD_FORMAT[letter]
    try:
        word = gword(letter, value)
    except ValueError as exc:
        assert f"G-code word {letter}" in str(exc)
        assert not (lo - 0.5 * 10.0**-dec < value < hi + 0.5 * 10.0**-dec) or value != value
        return
    assert re.fullmatch(rf"{letter}-?\d{{1,8}}" + (rf"\.\d{{{dec}}}" if dec else ""), word), word
    assert len(word.replace("-", "").replace(".", "")) <= 9  # letter + at most 8 digits GRBL reads
    assert abs(float(word[1:]) - value) <= 0.5 * 10.0**-dec * (1 + 1e-9) + 1e-9 * abs(value)
    check_words(word)


def test_clip_is_one_bounded_printable_line():
    s = clip("a\r\nb\x00" + "\ufffd" * 500, 60)
    assert len(s) == 60 and s.isprintable() and s.isascii() and s.startswith("a\\r\\nb\\x00") and s.endswith("...")
    assert clip("short") == "short"


def test_connect_keeps_an_idle_controllers_g92_and_reads_offsets():
    sim = GrblSim()
    try:
        with Grbl(sim.port, **OPEN) as g:
            g.connect()
            for line in ("G0 X5.000 Y4.000 Z2.000", "G92 X0 Y0 Z0", "G10 L2 P2 X1.500 Y-2.000 Z0.250"):
                assert g.command(line).kind == "ok"
        with Grbl(sim.port, **OPEN) as g:  # a new session, as the carver opens one
            g.connect()
            assert sim.g92 == [5.0, 4.0, 2.0] and not g.reset_sent
            assert g.offsets["G92"] == (5.0, 4.0, 2.0) and g.offsets["G55"] == (1.5, -2.0, 0.25)
            assert g.offsets["G54"] == (0.0, 0.0, 0.0) and g.offsets["TLO"] == (0.0,)
            assert "G54" in g.modes and g.unknown == []
        sim._reset()  # what the firmware does at a reset: G92 cleared, G54..G59 kept
        assert sim.g92 == [0.0, 0.0, 0.0] and sim.wp.wcs[55] == [1.5, -2.0, 0.25]
    finally:
        sim.close()
    sim = GrblSim(start_alarm=True, settings={20: 1, 22: 1, 23: 3, 130: 400.5, 132: 60.0},
                  options="VNMZ")  # not Idle: reset, banner, then homing
    try:
        with Grbl(sim.port, **OPEN) as g:
            g.connect(home=True)
            assert g.reset_sent and g.homed and g.banner == BANNER.decode().strip()
            assert g.settings == {20: 1.0, 22: 1.0, 23: 3.0, 130: 400.5, 132: 60.0}
            assert g.options == "VNMZ" and g.unknown == []
    finally:
        sim.close()


def test_a_noisy_port_logs_a_few_unexpected_lines_and_keeps_the_latest():
    """A controller that sends garbage line after line: the first ten are logged (the tenth
    saying no more follow), every one is counted, and only the latest ten are kept."""
    sim = GrblSim()
    logs = []
    try:
        with Grbl(sim.port, **dict(OPEN, log=logs.append)) as g:
            g.connect()
            for i in range(500):
                g._handle(f"noise {i}")
            assert g.n_unknown == 500 and g.unknown == [f"noise {i}" for i in range(490, 500)]
    finally:
        sim.close()
    noise = [m for m in logs if "unexpected line" in m]
    assert len(noise) == 10 and noise[-1].endswith("(no more such lines are shown)")


def test_watchdog_allows_dwells_and_stops_a_lost_ok():
    sim = GrblSim()
    try:
        with Grbl(sim.port, idle_timeout=0.2, **OPEN) as g:
            g.connect()
            t0 = time.monotonic()
            g.stream(["G4 P0.600", "G0 X1.000"])  # Idle for 0.6 s while dwelling: not a stall
            assert time.monotonic() - t0 >= 0.6
            sim.drop_ok_at = sim.gcode_lines + 2
            t0 = time.monotonic()
            with pytest.raises(Stalled, match=r"reports Idle but has not answered 'G0 X3\.000' for 0\.2 s") as e:
                g.stream(["G0 X2.000", "G0 X3.000", "G0 X4.000"])
            assert e.value.index == 1 and time.monotonic() - t0 < 3.0
            assert sim.wp.received[-1] == "G0 X3.000"  # nothing after the line owed its ok
    finally:
        sim.close()


def test_reply_grammar():
    assert classify("ok").kind == "ok"
    assert classify("error:20")[:3] == ("error", 20, "error:20")
    assert classify("ALARM:1").code == 1
    assert classify("<Hold:0|MPos:1.000,2.000,3.000|FS:0,0>").kind == "status"
    assert classify("[MSG:Reset to continue]").kind == "msg"
    assert classify("Grbl 1.1h ['$' for help]").kind == "banner"
    assert classify("$130=400.000").kind == classify("$20=1").kind == "setting"
    for junk in ("okay", "error:", "\ufffd#garbage%", "<Idle", "Marlin 2.1", "$130=", "$N0=G54"):
        assert classify(junk).kind == "unknown"
