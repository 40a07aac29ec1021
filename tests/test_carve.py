"""Tests of jscratch.carve: streaming a program to a simulated GRBL 1.1 controller (tests/grbl_sim.py)
on a real pty, with fault injection (errors, alarms, a vanishing device, Ctrl-C, garbage, a slow
device, a lost ok), the journal and resume, work offsets, the safe-Z retract and the spindle's
dwell. Every job is checked against the simulated workpiece: every scratch carved completely
exactly once (but the one in progress at a fault), in program order, within the board."""

import json
import os
import re
import sys
import threading
import time

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

from grbl_sim import GrblSim, Workpiece  # noqa: E402

from jscratch import carve as carve_mod  # noqa: E402
from jscratch.designfile import demo_design, save_design  # noqa: E402
from jscratch.fabricate import (  # noqa: E402
    CarveError, MachineConfig, carve, main, make_program, read_program, write_program,
)
from jscratch.grbl import Grbl  # noqa: E402
from jscratch.journal import Journal, JournalError, sha256_file  # noqa: E402

FAST = dict(quiet=True, banner_timeout=1.0, poll_interval=0.05, stall_timeout=5.0)


@pytest.fixture(scope="module")
def small():
    d = demo_design(24, seed=2)
    prog = make_program(d, MachineConfig(plunge_mm=0.1, safe_z_mm=1.0), time_limit=5)
    return d, prog


def _program_cuts(prog):
    """Per k: entry (x, y), exit (x, y), plunge depth, from the G-code text."""
    out = {}
    for text, k, role in zip(prog.lines, prog.k.tolist(), prog.role):
        if k < 0:
            continue
        w = {t[0]: float(t[1:]) for t in text.split()[1:]}
        if role == "travel":
            out[k] = [(w["X"], w["Y"]), None, None]
        elif role == "plunge":
            out[k][2] = w["Z"]
        elif role == "cut":
            out[k][1] = (w["X"], w["Y"])
    return out



def _verify(prog, wp, in_progress=(), origin=(0.0, 0.0, 0.0)):
    """Every scratch carved completely exactly once, except the ones in progress at a fault (at most
    twice); plunges and cuts in program order; everything in bounds of the board whose corner is at
    machine `origin`; the host never overflowed RX nor cut with the spindle not up to speed."""
    assert wp.faults == []
    cuts = _program_cuts(prog)
    by_entry = {tuple(np.round(v[0], 3)): k for k, v in cuts.items()}
    n = len(cuts)
    o = np.asarray(origin, float)
    moves = [(kind, tuple(np.round(np.subtract(s, o), 9)), tuple(np.round(np.subtract(e, o), 9)), f)
             for kind, s, e, f in wp.moves]
    xs = np.array([m[2] for m in moves] + [m[1] for m in moves])
    zmin = min(v[2] for v in cuts.values())
    assert np.all(xs[:, 0] >= -1e-9) and np.all(xs[:, 0] <= 300 + 1e-9)
    assert np.all(xs[:, 1] >= -1e-9) and np.all(xs[:, 1] <= 300 + 1e-9)
    assert np.all(xs[:, 2] >= zmin - 1e-9) and np.all(xs[:, 2] <= 5 + 1e-9)
    complete, touched = [], []
    for kind, s, e, f in moves:
        if s[2] < 0 and e[2] >= s[2] and s[:2] == e[:2]:
            continue  # a vertical retract, from wherever the tool stopped
        if e[2] < 0 or s[2] < 0:  # any other move with the tool below the surface
            k = by_entry.get(tuple(np.round(s[:2], 3)))
            assert k is not None, ("material removed away from any scratch entry", s, e)
            if s[:2] == e[:2]:
                touched.append(k)  # plunge
            else:
                assert kind == "G1"
                if f == 1.0:
                    assert np.allclose(e[:2], cuts[k][1], atol=1e-6) and np.isclose(e[2], cuts[k][2])
                    complete.append(k)
                touched.append(k)
    counts = np.bincount(complete, minlength=n)
    again = set(np.flatnonzero(counts != 1).tolist())
    assert np.all(counts >= 1), f"never carved: {np.flatnonzero(counts == 0)}"
    assert again <= set(in_progress) and np.all(counts <= 2), (again, in_progress)
    # Order: the sequence of scratches touched never goes back, except to re-cut one in progress.
    seq = [k for i, k in enumerate(touched) if i == 0 or k != touched[i - 1]]
    backs = [(a, b) for a, b in zip(seq, seq[1:]) if b < a]
    assert all(b in in_progress for _, b in backs), backs
    assert len(backs) <= len(in_progress)



@pytest.fixture
def job(tmp_path, small):
    d, prog = small
    path = tmp_path / "job.gcode"
    write_program(prog, path)
    return str(path), prog



@pytest.mark.parametrize("counting", [False, True])
def test_clean_job_and_check_mode(job, counting):
    path, prog = job
    sim = GrblSim()
    try:
        r = carve(path, sim.port, counting=counting, check=True, **FAST)
    finally:
        sim.close()
    assert r["done"] == r["total"] == 24
    _verify(prog, sim.wp)
    # check mode ran every line once before the real pass, and moved nothing
    code = [t for t in prog.lines if not t.startswith("(")]
    assert sim.wp.received == code + code
    header, done = Journal.read(path + ".journal")
    assert done == 24 and header["gcode_sha256"] == sha256_file(path)



def _resume(path, sim, **kw):
    return carve(path, sim.port, resume=True, **FAST, **kw)



def test_error_mid_job_then_resume(job):
    path, prog = job
    wp = Workpiece()
    # line 2 + 5*9 + 3 is the cut of scratch position 9
    sim = GrblSim(wp, error_at=(2 + 5 * 9 + 3, 33))
    with pytest.raises(CarveError, match=r"error:33 .* G-code line \d+ 'G1 X.*scratch position 9 .*retracted"):
        carve(path, sim.port, **FAST)
    assert Journal.read(path + ".journal")[1] == 9
    assert sim.pos[2] == 1.0  # retracted to safe Z
    sim.error_at = None
    r = _resume(path, sim)
    sim.close()
    assert r["done"] == 24
    _verify(prog, wp, in_progress={9})



def test_alarm_mid_job_needs_home_then_resume(job):
    path, prog = job
    wp = Workpiece()
    sim = GrblSim(wp, alarm_at=(1 + 4 * 12 + 3, 1))  # during the cut of position 12
    with pytest.raises(CarveError, match=r"ALARM:1 .*--resume"):
        carve(path, sim.port, counting=True, **FAST)
    assert Journal.read(path + ".journal")[1] == 12
    sim.alarm_at = None
    n_recv = len(wp.received)
    with pytest.raises(CarveError, match="Alarm state .* --home"):
        _resume(path, sim)
    assert len(wp.received) == n_recv  # refused: nothing sent
    r = _resume(path, sim, home=True, counting=True)
    sim.close()
    assert r["done"] == 24
    _verify(prog, wp, in_progress={12})



class _GarbledAlarm(GrblSim):
    """A simulator whose `ALARM:N` lines arrive garbled by noise on the wire."""

    def _send(self, data):
        if data.startswith(b"ALARM:"):
            data = b"AL\xffRM:1\r\n" + data.split(b"\r\n", 1)[1]
        super()._send(data)


class _LocksOnError(GrblSim):
    """A simulator whose status reports say Alarm from its first error on (as after a limit
    switch or a lockout) until `$X` or `$H`."""

    locked = False

    def _answer(self, text):
        self.locked |= text.startswith("error")
        super()._answer(text)

    def _execute_line(self, line):
        self.locked &= line not in ("$X", "$H")
        return super()._execute_line(line)

    def _status(self):
        report = super()._status()
        return "<Alarm|" + report.split("|", 1)[1] if self.locked else report


def test_an_error_that_leaves_the_controller_in_alarm_needs_home_to_resume(job):
    path, prog = job
    wp = Workpiece()
    sim = _LocksOnError(wp, error_at=(2 + 5 * 7 + 3, 9))  # the cut of position 7
    try:
        with pytest.raises(CarveError, match=r"error:9 .*in Alarm: no retract sent.*re-home "
                                             r"\(--home\) or re-zero") as e:
            carve(path, sim.port, **FAST)
        assert "\n" not in str(e.value) and Journal.read(path + ".journal")[1] == 7
        sim.error_at = None
        with pytest.raises(CarveError, match=r"position may be lost \(an alarm since the job"):
            _resume(path, sim, unlock=True)
        assert _resume(path, sim, home=True)["done"] == 24
    finally:
        sim.close()
    _verify(prog, wp, in_progress={7})


def test_an_alarm_whose_line_was_lost_stops_the_job(job):
    """The controller stops in Alarm but its `ALARM:N` line never arrives whole: the status
    reports' `Alarm` stops the stream (it does not wait forever), and the resume needs --home."""
    path, prog = job
    wp = Workpiece()
    sim = _GarbledAlarm(wp, alarm_at=(1 + 4 * 6 + 3, 1))  # during the cut of position 6
    t = time.monotonic()
    with pytest.raises(CarveError, match=r"reports Alarm \(its ALARM:N line was lost\).*position "
                                         r"likely lost.*--home") as e:
        carve(path, sim.port, **FAST)
    assert time.monotonic() - t < 10 and "\n" not in str(e.value)
    assert Journal.read(path + ".journal")[1] == 6
    sim.alarm_at = None
    with pytest.raises(CarveError, match="Alarm state .* --home"):
        _resume(path, sim)
    r = _resume(path, sim, home=True)
    sim.close()
    assert r["done"] == 24
    _verify(prog, wp, in_progress={6})


def test_a_controller_that_just_started_without_homing_is_refused(job):
    """An Arduino-style board restarts when its port opens: without homing it then counts machine
    positions from wherever the tool stands (0, 0, 0), and the G54 zero kept in EEPROM from the
    session that zeroed the board no longer points at it (here the first Z move would drive the
    tool 19 mm down). Refused before any motion; with --home the job runs."""
    path, prog = job
    started = r"has just started without homing \(machine position 0, 0, 0\).*--home.*-hupcl"
    wp = Workpiece()
    wp.wcs[54] = [50.0, 40.0, -20.0]  # zeroed at the board's corner in an earlier session
    sim = GrblSim(wp, start_alarm=True)  # started up locked: reset, banner, then $X
    sim.pos = [0.0, 0.0, 0.0]
    try:
        with pytest.raises(CarveError, match=started + ".*no motion was sent") as e:
            carve(path, sim.port, unlock=True, **FAST)
        assert wp.moves == [] and "\n" not in str(e.value)
        assert not os.path.exists(path + ".journal")
        assert carve(path, sim.port, home=True, **FAST)["done"] == 24
    finally:
        sim.close()

    class Restarted:  # what `Grbl.connect` leaves after a restart on opening: status by $10
        port, banner, homed = "/dev/ttyUSB0", "Grbl 1.1h ['$' for help]", False
        settings, options, state_at_connect, unlocked = {}, "V", "Idle", False
        offsets = {"G54": (50.0, 40.0, -20.0), "G92": (0.0, 0.0, 0.0), "TLO": (0.0,)}
        status = {"state": "Idle", "MPos": "0.000,0.000,0.000"}

        def query_status(self):
            return self.status

    untouched = lambda: "(no motion was sent)"  # noqa: E731
    for field, value in (("MPos", "0.000,0.000,0.000"), ("WPos", "-50.000,-40.000,20.000")):
        g = Restarted()
        g.status = {"state": "Idle", field: value}
        with pytest.raises(CarveError, match=started):
            carve_mod._check_work_zero(g, "G54", None, False, untouched)
    # Refused too when it started before the port opened (no banner this session); not refused:
    # homed now, the tool elsewhere, the zero at the origin.
    g = Restarted()
    g.banner = None
    with pytest.raises(CarveError, match=started):
        carve_mod._check_work_zero(g, "G54", None, False, untouched)
    for change in (dict(homed=True),
                   dict(status={"state": "Idle", "MPos": "50.000,40.000,-19.000"}),
                   dict(offsets=dict(Restarted.offsets, G54=(0.0, 0.0, 0.0)))):
        g = Restarted()
        g.__dict__.update(change)
        carve_mod._check_work_zero(g, "G54", None, False, untouched)
    # With homing on ($22=1) GRBL starts locked in Alarm: found Idle, it was homed since, and
    # 0, 0, 0 is its home on firmware built with HOMING_FORCE_SET_ORIGIN (`Z`): not refused.
    # Refused still: built without the lock (`L`), found in Alarm, or unlocked ($X) now.
    homed = dict(settings={22: 1.0}, options="VZ")
    carve_mod._check_work_zero(type("Homed", (Restarted,), homed)(), "G54", None, False, untouched)
    carve_mod._check_work_zero(type("Homed", (Restarted,), dict(settings={22: 1.0, 27: 0.0}))(),
                               "G54", None, False, untouched)  # no pull-off: home is 0, 0, 0
    # Refused: without `Z` homing leaves the machine at -$27 (pull-off), so 0, 0, 0 is a restart
    # (unlocked by another sender).
    for change in (dict(options="VZL"), dict(state_at_connect="Alarm"), dict(unlocked=True),
                   dict(settings={22: 0.0}), dict(options="V"),
                   dict(options="V", settings={22: 1.0, 27: 1.0})):
        g = type("NotHomed", (Restarted,), {**homed, **change})()
        with pytest.raises(CarveError, match=started):
            carve_mod._check_work_zero(g, "G54", None, False, untouched)
    wp = Workpiece()
    wp.wcs[54] = [50.0, 40.0, -20.0]
    sim = GrblSim(wp, options="VZ", settings={22: 1, 23: 7})  # homed earlier, parked at home
    sim.pos = [0.0, 0.0, 0.0]
    try:
        os.remove(path + ".journal")
        assert carve(path, sim.port, **FAST)["done"] == 24
    finally:
        sim.close()
    assert wp.faults == [] and len(wp.moves) > 24


def test_device_vanishes_then_resume_after_power_cycle(job):
    path, prog = job
    wp = Workpiece()
    sim = GrblSim(wp, vanish_at=1 + 4 * 5 + 2)  # during the plunge of position 5
    with pytest.raises(CarveError, match=r"lost.*position is lost: re-home it \(--home\) or re-zero the board") as e:
        carve(path, sim.port, **FAST)
    assert "\n" not in str(e.value)
    assert Journal.read(path + ".journal")[1] == 5
    sim.close()
    # Powered up again without a homing lock: Idle, its position unknown. A resume that neither
    # homes nor says the board was re-zeroed is refused before anything is sent.
    sim2 = GrblSim(wp)
    n_recv = len(wp.received)
    lost = r"position may be lost \(a lost device since the job last ran\): re-home it \(--home\)"
    with pytest.raises(CarveError, match=lost + ".*--rezeroed.*no motion") as e:
        _resume(path, sim2)
    assert "\n" not in str(e.value) and len(wp.received) == n_recv
    sim2.close()
    sim2 = GrblSim(wp, start_alarm=True)  # powered up again with a homing lock
    with pytest.raises(CarveError, match=r"position may be lost \(a lost device"):
        _resume(path, sim2, unlock=True)  # $X does not restore the position
    assert len(wp.received) == n_recv
    sim2.close()
    sim2 = GrblSim(wp, start_alarm=True)
    r = _resume(path, sim2, home=True)
    sim2.close()
    assert r["done"] == 24
    _verify(prog, wp, in_progress={5})



def _ctrl_c_at(position):
    """An `on_scratch` that raises KeyboardInterrupt once scratch `position` is journalled."""
    def stop(k, s):
        if k == position:
            raise KeyboardInterrupt
    return stop


def test_ctrl_c_holds_retracts_and_resumes(job):
    path, prog = job
    wp = Workpiece()
    sim = GrblSim(wp)
    with pytest.raises(KeyboardInterrupt):
        carve(path, sim.port, on_scratch=_ctrl_c_at(6), **FAST)
    assert Journal.read(path + ".journal")[1] == 7 and sim.pos[2] == 1.0 and sim.state == "Idle"
    r = _resume(path, sim, counting=True)
    sim.close()
    assert r["done"] == 24
    _verify(prog, wp)



def test_sigterm_holds_and_retracts_as_ctrl_c_does(job):
    """``kill`` (SIGTERM) of a carving job stops it as Ctrl-C does: held, lifted to safe Z, the
    interrupt journalled, exit 130; the resume finishes the job."""
    import signal
    import subprocess

    path, prog = job
    wp = Workpiece()
    sim = GrblSim(wp, block_time=0.004)  # slow enough to be stopped part-way
    child = subprocess.Popen([sys.executable, "-m", "jscratch.fabricate", "--gcode", path,
                              "--port", sim.port, "--banner-timeout", "2"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end and (not os.path.exists(path + ".journal")
                                            or Journal.read(path + ".journal")[1] < 3):
            time.sleep(0.02)
        child.send_signal(signal.SIGTERM)
        out, err = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 130, err[-2000:]
    recs = Journal.records(path + ".journal")
    assert [r["event"] for r in recs if r["type"] == "event"][-1] == "interrupt", recs[-3:]
    assert "interrupted: held, reset and retracted to Z1.000" in err, err
    assert sim.pos[2] == 1.0
    done = Journal.read(path + ".journal")[1]
    assert 3 <= done < 24
    assert _resume(path, sim)["done"] == 24
    sim.close()
    _verify(prog, wp, in_progress={done})


def test_a_second_ctrl_c_during_the_hold_resets_and_journals(job, monkeypatch):
    """Ctrl-C holds and retracts; a second one while the hold settles sends a soft reset at once
    (motion and spindle stop), and the journal keeps the interrupt and the reset, so a resume
    asks for the position to be restored first."""
    path, prog = job
    wp = Workpiece()
    sim = GrblSim(wp)

    def second_ctrl_c(self, accept, timeout):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(Grbl, "wait_state", second_ctrl_c)
        with pytest.raises(KeyboardInterrupt):
            carve(path, sim.port, on_scratch=_ctrl_c_at(6), **FAST)
    recs = Journal.records(path + ".journal")
    assert [r["event"] for r in recs if r["type"] == "event"][-2:] == ["interrupt", "reset"]
    assert Journal.read(path + ".journal")[1] == 7
    time.sleep(0.2)
    assert sim.state.startswith("Alarm") or sim.state == "Idle"
    assert sim.spindle_on is None and sim.planner == type(sim.planner)()  # stopped, flushed
    with pytest.raises(CarveError, match=r"position may be lost \(a soft reset on a second "
                                         r"interrupt since the job last ran\)"):
        _resume(path, sim, unlock=True)
    r = _resume(path, sim, home=True)
    sim.close()
    assert r["done"] == 24
    _verify(prog, wp, in_progress={7})


def test_the_spindle_starts_with_the_tool_off_the_board(tmp_path, small):
    """Zeroed by touching the tool to the board, a job with a spindle lifts to safe Z before
    ``M3``: a spinning cutter on the surface would mark the corner (the simulator records it)."""
    d, _ = small
    prog = make_program(d, MachineConfig(plunge_mm=0.1, spindle_rpm=12000, spinup_s=0.1),
                        time_limit=2)
    assert prog.lines.index("G0 Z1.000") < prog.lines.index("M3 S12000")
    path = tmp_path / "spin.gcode"
    write_program(prog, path)
    wp = Workpiece()
    sim = GrblSim(wp, spinup_s=0.05)
    sim.pos = [0.0, 0.0, 0.0]  # the tool on the board's corner, the work zero there
    try:
        assert carve(str(path), sim.port, **FAST)["done"] == 24
    finally:
        sim.close()
    _verify(prog, wp)


def test_a_journal_torn_in_its_header_blocks_nothing(job):
    """Power lost while the header was written (before any motion): a fresh run replaces it;
    a resume says so and what to do, in one line."""
    path, prog = job
    with open(path + ".journal", "w") as f:
        f.write('{"type": "header", "gcode_sha')
    sim = GrblSim()
    try:
        with pytest.raises(CarveError, match=r"^--resume: journal .* holds only a torn header .*"
                                             r"without --resume") as e:
            carve(path, sim.port, resume=True, **FAST)
        assert "\n" not in str(e.value) and sim.wp.moves == []
        assert carve(path, sim.port, **FAST)["done"] == 24
    finally:
        sim.close()
    _verify(prog, sim.wp)
    assert Journal.read(path + ".journal")[1] == 24
    assert Journal.torn_header(path + ".journal") is False
    for text, torn in (('{"type": "header", "n_scratches": 24}', False),  # whole, no newline
                       ('{"type": "header", "n_scr', True),
                       ('{"type": "header"}\n{"type": "do', False),  # a torn later record
                       ('{"type": "head', True), ("{", True), ("\0" * 4096, True),
                       ('{"type": "header", "gc' + "\0" * 100, True),  # zeros of a power cut
                       ('{"kind": "header"', False)):  # not the header as the carver writes it
        with open(path + ".journal", "w") as f:
            f.write(text)
        assert Journal.torn_header(path + ".journal") is torn, text


def test_garbage_and_slow_device(job):
    path, prog = job
    sim = GrblSim(garbage_every=3, reply_delay=0.002, block_time=0.003)
    try:
        r = carve(path, sim.port, counting=True, **FAST)
    finally:
        sim.close()
    assert r["done"] == 24
    _verify(prog, sim.wp)



def test_bad_port_non_grbl_device_and_journal_rules(job, tmp_path):
    path, prog = job
    with pytest.raises(CarveError, match="does not exist"):
        carve(path, str(tmp_path / "ttyNOPE"), **FAST)
    assert not os.path.exists(path + ".journal")  # no journal before motion is about to be sent
    sim = GrblSim(not_grbl=True)
    try:
        with pytest.raises(CarveError, match=r"did not answer like GRBL.*no motion was sent"):
            carve(path, sim.port, **FAST)
    finally:
        sim.close()
    assert sim.wp.received == [] and sim.wp.moves == []
    assert not os.path.exists(path + ".journal")
    with pytest.raises(JournalError, match="does not exist; nothing to resume"):
        carve(path, str(tmp_path / "ttyNOPE"), resume=True, **FAST)
    # A journal from another G-code is refused; an existing (started) journal needs --resume.
    j = Journal(path + ".journal", sha256_file(path), 24, resume=False)
    j.event("start", k=0)
    j.close()
    other = tmp_path / "other.gcode"
    other.write_text("G0 X1\n")
    with pytest.raises(JournalError, match="belongs to G-code"):
        Journal(path + ".journal", sha256_file(other), 24, resume=True)
    with pytest.raises(JournalError, match="already exists"):
        Journal(path + ".journal", sha256_file(path), 24, resume=False)
    # A torn final record (power lost mid-write) is ignored.
    j = Journal(path + ".journal", sha256_file(path), 24, resume=True)
    j.confirm(0, int(prog.scratch[prog.k == 0][0]))
    j.close()
    with open(path + ".journal", "a") as f:
        f.write('{"type": "done", "k": 1, "scr')
    assert Journal.read(path + ".journal")[1] == 1



def test_character_counting_respects_rx_buffer_and_overflow_is_caught():
    from jscratch.grbl import Grbl

    lines = [f"G1 X{i % 50 + 0.5:.3f} Y{(7 * i) % 50 + 0.25:.3f} F900" for i in range(60)]
    for rx_size, overflow in ((None, False), (400, True)):
        sim = GrblSim(block_time=0.004)
        try:
            with Grbl(sim.port, banner_timeout=1.0, poll_interval=0.05, stall_timeout=5.0) as grbl:
                grbl.connect()
                assert grbl.rx_size == 128 and grbl.version.startswith("1.1h")
                if rx_size:
                    grbl.rx_size = rx_size  # a host that believes in a bigger buffer
                grbl.stream(lines, counting=True)
                assert grbl.command("G4 P0").kind == "ok"
        finally:
            sim.close()
        assert bool(sim.wp.faults) == overflow, sim.wp.faults[:1]
        assert sim.wp.received == lines + ["G4 P0"] or overflow



def _operator(sim, *lines):
    """What an operator does at the machine before a job: `lines` sent on a session of their own."""
    with Grbl(sim.port, banner_timeout=1.0, poll_interval=0.05, stall_timeout=5.0) as g:
        g.connect()
        for line in lines:
            assert g.command(line).kind == "ok", line



def test_work_zero_g92_refused_g54_kept_across_reset_and_resume(job):
    path, prog = job
    wp = Workpiece()
    sim = GrblSim(wp)
    corner = (5.0, 4.0, 2.0)  # machine position of the board corner, on its surface
    _operator(sim, "G0 X5.000 Y4.000 Z2.000", "G92 X0 Y0 Z0", "G4 P0.000")
    wp.moves.clear()
    n_recv = len(wp.received)
    # A G92 zero would be cleared by any reset (connect, fault, check mode): refused, untouched.
    with pytest.raises(CarveError, match=r"G92 offset \(X5\.000 Y4\.000 Z2\.000\).*G10 L20 P1.*no motion was sent"):
        carve(path, sim.port, **FAST)
    assert wp.moves == [] and len(wp.received) == n_recv and sim.g92 == list(corner)
    assert not os.path.exists(path + ".journal")
    # The documented way: G10 L20 P1 (G54, kept in EEPROM). A fault resets the controller; the
    # retract and the resume still land on the board.
    _operator(sim, "G92.1", "G10 L20 P1 X0 Y0 Z0")
    assert wp.wcs[54] == list(corner)
    sim.error_at = (sim.gcode_lines + 2 + 5 * 9 + 3, 33)  # the cut of position 9
    with pytest.raises(CarveError, match="error:33"):
        carve(path, sim.port, **FAST)
    assert sim.pos[2] == pytest.approx(3.0)  # work Z1 in G54 (machine 2 + 1) after the reset
    sim.error_at = None
    # Resume re-checks the work zero: a changed G54 is refused, naming how to restore it.
    wp.wcs[54][0] += 1.0
    n_moves = len(wp.moves)
    with pytest.raises(CarveError, match=r"G54 work zero is X6\.000 .* was X5\.000 Y4\.000 Z2\.000.*"
                                         r"G10 L2 P1 X5\.000 Y4\.000 Z2\.000.*--rezeroed"):
        _resume(path, sim)
    assert len(wp.moves) == n_moves
    wp.wcs[54][0] -= 1.0
    assert _resume(path, sim)["done"] == 24
    sim.close()
    _verify(prog, wp, in_progress={9}, origin=corner)



#: A homed machine with soft limits on: travel 400 x 350 x 60 mm, machine space [-$13N, 0].
TRAVEL = {20: 1, 22: 1, 23: 0, 130: 400.0, 131: 350.0, 132: 60.0}


def _carve_at(path, zero, settings, options="V", **kw):
    """Carve on a fresh simulated controller whose G54 zero is `zero` (the tool above it)."""
    wp = Workpiece()
    wp.wcs[54] = list(zero)
    sim = GrblSim(wp, settings=settings, options=options)
    sim.pos = [zero[0], zero[1], zero[2] + 5.0]
    try:
        return carve(path, sim.port, **FAST, **kw), wp
    finally:
        sim.close()


def test_a_program_outside_the_machines_travel_is_refused_when_soft_limits_are_on(job, monkeypatch):
    """With soft limits on ($20=1) GRBL stops a job part-way with ALARM:2 at the first move
    outside the machine's travel. The program's extent plus the work zero (and the safe Z) is
    checked against the travel ($130-$132, read with $$) before any motion. Reference: the
    simulated firmware's own per-move check, with the pre-check switched off, stops exactly the
    jobs the pre-check refuses."""
    path, prog = job  # X 0..293.716, Y 0..278.608, Z -0.1..1 (work mm)
    fits = (-380.0, -320.0, -40.0)
    r, wp = _carve_at(path, fits, TRAVEL)
    assert r["done"] == 24
    _verify(prog, wp, origin=fits)
    os.remove(path + ".journal")
    cases = {"X": (-100.0, -320.0, -40.0),   # X reaches +193.716 > 0
             "Y": (-380.0, -200.0, -40.0),   # Y reaches +78.608 > 0
             "Z": (-380.0, -320.0, -0.5),    # the safe Z (work 1) is machine +0.5 > 0
             "Y ": (-380.0, -360.0, -40.0)}  # Y starts at -360 < -350
    for axis, zero in cases.items():
        refused = (rf"program moves {axis[0]} from .* outside the machine's travel "
                   r".*\$20=1.*ALARM:2.*no motion was sent")
        with pytest.raises(CarveError, match=refused) as e:
            _carve_at(path, zero, TRAVEL)
        assert "\n" not in str(e.value) and not os.path.exists(path + ".journal")
    with monkeypatch.context() as m:  # the firmware alone: each of these jobs stops part-way
        m.setattr(carve_mod, "_check_travel", lambda *a: None)
        for axis, zero in cases.items():
            with pytest.raises(CarveError, match="ALARM:2"):
                _carve_at(path, zero, TRAVEL)
            _, done = Journal.read(path + ".journal")
            assert done < 24
            os.remove(path + ".journal")
    # A controller reporting inches ($13=1): the zero comes in mm (`_check_work_zero` converts
    # it: `test_a_work_zero_reported_in_inches_is_named_in_mm`) and is not converted again.
    class Inches:
        settings, options = {**TRAVEL, 13: 1}, "V"

    lines = [t for t in prog.lines if not t.startswith("(")]
    carve_mod._check_travel(Inches(), lines, 1.0, list(fits), "G54", lambda: "", print)
    with pytest.raises(CarveError, match="program moves X from -100.000 to 193.716 mm"):
        carve_mod._check_travel(Inches(), lines, 1.0, list(cases["X"]), "G54", lambda: "", print)
    # Without homing, machine coordinates count from wherever the machine started: not checked.
    r, _ = _carve_at(path, cases["X"], {**TRAVEL, 20: 0, 22: 0})
    assert r["done"] == 24


def test_travel_follows_the_firmwares_homing_origin_and_warns_without_soft_limits(job, capsys):
    """Built with HOMING_FORCE_SET_ORIGIN (`Z` among `$I`'s options), an axis homed towards its
    minimum ($23 bit set) has the travel [0, $13N]; with homing on but soft limits off ($20=0) a
    program outside the travel is streamed with a warning (nothing enforces the travel)."""
    path, prog = job
    assert carve_mod._travel(TRAVEL, "V") == [(-400.0, 0.0), (-350.0, 0.0), (-60.0, 0.0)]
    assert carve_mod._travel({**TRAVEL, 23: 3}, "VZ") == [(0.0, 400.0), (0.0, 350.0), (-60.0, 0.0)]
    assert carve_mod._travel({**TRAVEL, 23: 3}, "V")[0] == (-400.0, 0.0)
    assert carve_mod._travel({130: 0.0}, "V") == [None, None, None]
    origin = (10.0, 20.0, -40.0)
    r, wp = _carve_at(path, origin, {**TRAVEL, 23: 3}, options="VZ")
    assert r["done"] == 24
    _verify(prog, wp, origin=origin)
    os.remove(path + ".journal")
    with pytest.raises(CarveError, match=r"program moves X from 10\.000 to 303\.716 mm"):
        _carve_at(path, origin, TRAVEL)  # the same zero in the default machine space
    capsys.readouterr()
    r, _ = _carve_at(path, origin, {**TRAVEL, 20: 0})
    assert r["done"] == 24
    err = capsys.readouterr().err
    assert re.search(r"warning: the program moves X from 10\.000 to 303\.716 mm .*\$20=0", err), err
    assert "warning: the program moves Y from 20.000 to 298.608" in err
    assert err.count("warning:") == 2  # X and Y; Z (-40.1 to -39) fits


def _design_file(tmp_path, n=24, seed=2):
    d = demo_design(n, seed=seed)
    f = tmp_path / "d.npz"
    save_design(f, d.p0, d.p1, d.width, d.depth, d.alpha, d.board)
    return str(f)



def test_plain_rerun_keeps_the_program_of_an_unfinished_job(tmp_path, capsys):
    design = _design_file(tmp_path)
    gcode = tmp_path / "d.gcode"
    wp = Workpiece()
    sim = GrblSim(wp, error_at=(2 + 5 * 4 + 3, 33))
    base = [design, "--plunge", "0.1", "--order-time", "1", "--quiet", "--banner-timeout", "1"]
    assert main(base + ["--port", sim.port]) == 4
    before = gcode.read_bytes()
    capsys.readouterr()
    # A plain re-run (here with another feed) or a dry run must not replace the job's program.
    for extra in (["--feed", "600", "--port", sim.port], ["--feed", "600", "--dry-run"]):
        assert main(base + extra) == 2
        err = capsys.readouterr().err
        assert re.fullmatch(r"error: .*unfinished job .*4 of 24 scratches carved.*--resume.*\n", err), err
        assert gcode.read_bytes() == before
    sim.error_at = None
    # The resume streams the program as written, and says which options given now it ignores.
    loud = [a for a in base if a != "--quiet"] + ["--port", sim.port, "--resume", "--feed", "600",
                                                  "--spindle", "1000", "--offset", "1", "2"]
    assert main(loud) == 0
    err = capsys.readouterr().err
    assert ("not applied: feed_mm_min = 600.0 (the program has F900.0), board_offset_mm = "
            "[1.0, 2.0] (the program has X0.000 Y0.000), spindle_rpm = 1000.0") in err
    assert "using the given values" not in err and "plunge_mm" not in err  # (the program's own)
    sim.close()
    _verify(read_program(gcode), wp, in_progress={4})
    assert main(base + ["--dry-run"]) == 2
    assert "finished job" in capsys.readouterr().err and gcode.read_bytes() == before



def test_lost_ok_while_idle_stops_with_resume_advice(job):
    path, prog = job
    wp = Workpiece()
    sim = GrblSim(wp, drop_ok_at=2 + 5 * 4 + 2)  # the plunge of position 4: executed, never answered
    out = {}

    def run():
        try:
            carve(path, sim.port, idle_timeout=0.5, **FAST)
        except BaseException as exc:  # noqa: BLE001 (reported below)
            out["exc"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(20.0)
    hung = t.is_alive()
    if hung:
        sim.vanish()
        t.join(5.0)
    assert not hung, "the streamer still waits for the lost ok after 20 s"
    msg = str(out.get("exc"))
    assert isinstance(out.get("exc"), CarveError), msg
    assert re.fullmatch(r"controller on \S+ reports Idle but has not answered 'G1 Z-0\.100 F300\.0' for 0\.5 s "
                        r"\(a lost 'ok'\) at G-code line 28 .*scratch position 4 .*retracted to Z1\.000\. "
                        r"4 of 24 scratches are journalled; .*--resume", msg), msg
    assert sim.pos[2] == 1.0 and Journal.read(path + ".journal")[1] == 4
    sim.drop_ok_at = None
    assert _resume(path, sim)["done"] == 24
    sim.close()
    _verify(prog, wp, in_progress={4})
    # Character counting: the 'ok's that follow answer the lines after it, so the stall can only
    # name the lines in flight since every earlier one was answered (from the plunge on).
    os.remove(path + ".journal")
    wp = Workpiece()
    sim = GrblSim(wp, drop_ok_at=2 + 5 * 4 + 2)
    try:
        with pytest.raises(CarveError) as e:
            carve(path, sim.port, idle_timeout=0.5, counting=True, **FAST)
    finally:
        sim.close()
    assert re.fullmatch(r"controller on \S+ reports Idle but has not answered one of the 4 lines "
                        r"from 'G1 Z-0\.100 F300\.0' to 'G4 P0\.000' for 0\.5 s \(a lost 'ok'; "
                        r"character counting cannot tell which\) at G-code line 28 .*scratch "
                        r"position 4 .*4 of 24 scratches are journalled; .*--resume",
                        str(e.value)), str(e.value)



def test_failed_connection_leaves_no_journal_and_the_next_run_starts(job, tmp_path):
    path, prog = job
    for port in (str(tmp_path / "ttyNOPE"), None):
        sim = None if port else GrblSim(start_alarm=True)  # Alarm and no --home: refused
        with pytest.raises(CarveError) as e:
            carve(path, port or sim.port, **FAST)
        if sim:
            sim.close()
        assert not os.path.exists(path + ".journal")
        assert "no motion was sent" in str(e.value)
    # A header-only journal (a session that never connected) does not block.
    with open(path + ".journal", "w") as f:
        f.write(json.dumps({"type": "header", "gcode_sha256": "0" * 64, "n_scratches": 24}) + "\n")
    sim = GrblSim()
    try:
        assert carve(path, sim.port, **FAST)["done"] == 24
    finally:
        sim.close()
    _verify(prog, sim.wp)



def test_emergency_retract_goes_to_the_programs_safe_z(tmp_path, small):
    d, _ = small
    prog = make_program(d, MachineConfig(plunge_mm=0.1, safe_z_mm=3.0), time_limit=2)
    path = tmp_path / "z3.gcode"
    write_program(prog, path)
    sim = GrblSim(error_at=(2 + 5 * 3 + 3, 33))  # mid-cut of position 3
    try:
        # Streamed with the CLI, whose --safe-z default (1 mm) is below the program's 3 mm.
        assert main(["--gcode", str(path), "--port", sim.port, "--quiet", "--banner-timeout", "1"]) == 4
        assert sim.pos[2] == 3.0
        # An explicit lower safe_z_mm never retracts below the program's travel height.
        sim.error_at = (sim.gcode_lines + 2 + 3, 33)
        with pytest.raises(CarveError, match=r"retracted to Z3\.000"):
            carve(path, sim.port, resume=True, safe_z_mm=0.5, **FAST)
    finally:
        sim.close()



def test_failure_after_homing_does_not_say_no_motion_was_sent(job):
    path, _ = job
    # `--home` homes whatever the controller's state (an Idle one too: after a power cycle of a
    # controller without homing lock, Idle says nothing about its position).
    for alarm, home in ((True, True), (False, True), (False, False)):
        sim = GrblSim(start_alarm=alarm, error_at=(2 + 5 * 2 + 3, 20))  # found by check mode
        try:
            with pytest.raises(CarveError, match=r"check mode \(\$C\): error:20") as e:
                carve(path, sim.port, home=home, check=True, **FAST)
        finally:
            sim.close()
        msg = str(e.value)
        assert ("no motion was sent" in msg) != home, msg
        assert ("homing cycle $H ran" in msg) == home, msg
        assert sim.wp.moves == []



def test_not_grbl_error_is_one_short_line(job):
    path, _ = job
    sim = GrblSim(not_grbl=(bytes(range(128, 256)) * 4 + b"\r\n") * 3 + b"x" * 2000 + b"\r\n")
    try:
        with pytest.raises(CarveError, match="did not answer like GRBL") as e:
            carve(path, sim.port, **FAST)
    finally:
        sim.close()
    msg = str(e.value)
    assert len(msg) <= 400 and msg.isprintable() and msg.isascii(), (len(msg), msg[:200])



def test_spinup_dwell_after_m3_also_on_resume(tmp_path, small):
    d, _ = small
    prog = make_program(d, MachineConfig(plunge_mm=0.1, spindle_rpm=12000, spinup_s=0.6), time_limit=2)
    i = prog.lines.index("M3 S12000")
    assert prog.lines[i + 1] == "G4 P0.600" and prog.role[i + 1] == "pre"
    path = tmp_path / "spin.gcode"
    write_program(prog, path)
    wp = Workpiece()
    sim = GrblSim(wp, spinup_s=0.5, error_at=(4 + 5 * 6 + 3, 33))  # the cut of position 6
    with pytest.raises(CarveError, match="error:33"):
        carve(str(path), sim.port, **FAST)  # the retract's reset stops the spindle
    sim.error_at = None
    assert _resume(str(path), sim)["done"] == 24
    sim.close()
    _verify(prog, wp, in_progress={6})  # no cut with the spindle off or still spinning up


def _carve_in_thread(path, sim, wait=20.0, **kw):
    """`carve` on a thread: its exception (None if it returned) and whether it still ran after
    `wait` s (the port is then closed under it)."""
    out = {}

    def run():
        try:
            carve(path, sim.port, **{**FAST, **kw})
        except BaseException as exc:  # noqa: BLE001 (returned to the test)
            out["exc"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(wait)
    hung = t.is_alive()
    if hung:
        sim.vanish()
        t.join(5.0)
    return out.get("exc"), hung


class _NoiseFrom(GrblSim):
    """Everything it sends from its `start`-th G-code line on arrives as noise (a baud rate gone
    wrong): whole lines, none of them GRBL's."""

    start = 2 + 5 * 3 + 3  # the cut of scratch position 3

    def _send(self, data):
        if self.gcode_lines >= self.start:
            data = bytes((b ^ 0x55) & 0x7F for b in data).replace(b"\n", b"") + b"\r\n"
        super()._send(data)


@pytest.mark.parametrize("block_time", [0.5, 0.0004])  # the last good status: Run, Idle
def test_a_controller_that_turns_to_noise_is_lost_after_the_stall_timeout(job, block_time):
    """Lines of noise are not answers, nor status reports: when nothing GRBL sends has come for
    `stall_timeout` s the device counts as lost (one line, the count journalled), however much
    noise arrives, and a lost `ok` is not inferred from the last report."""
    path, _ = job
    sim = _NoiseFrom(Workpiece(), block_time=block_time)
    exc, hung = _carve_in_thread(path, sim, stall_timeout=3.0, idle_timeout=2.0)
    sim.close()
    assert not hung, "the streamer still waits after 20 s of noise"
    assert isinstance(exc, CarveError), exc
    assert re.fullmatch(r"device on \S+ sent nothing GRBL sends for 3 s, only \d+ unexpected "
                        r"lines \(the latest '.*': a wrong baud rate, noise on the line\?\)\. 3 of "
                        r"24 scratches are journalled; .*--resume.*", str(exc)), str(exc)


class _RestartsUnheard(GrblSim):
    """Restarts (a brown-out) at its `restart_at`-th G-code line: machine position 0, 0, 0, the
    G54 zero kept; its banner arrives garbled, so the host does not see the restart."""

    restart_at = 2 + 5 * 4 + 3  # the cut of scratch position 4
    moves_at_restart = None

    def _execute_line(self, line):
        if self.restart_at and self.gcode_lines + 1 == self.restart_at and not line.startswith("$"):
            self.restart_at = None
            with self.lock:
                if self.executing is not None:
                    self.executing["abort"] = True
                self.planner.clear()
                self.rx.clear()
                self.pos, self.state = [0.0, 0.0, 0.0], "Idle"
                self.modal = {"distance": 90, "units": 21}
                self.moves_at_restart = len(self.wp.moves)
            self._send(b"\r\nGr\xffl 1.1h ['$' for help]\r\n")
            return True
        return super()._execute_line(line)


def test_an_unheard_restart_sends_no_retract_and_blocks_a_plain_resume(job):
    """After a restart whose banner did not come through, the lost `ok` looks like a stall: a
    retract in the G54 zero would now drive the tool 19 mm down. No retract is sent, the lost
    position is journalled, and a resume needs --home or --rezeroed."""
    path, _ = job
    wp = Workpiece()
    wp.wcs[54] = [50.0, 40.0, -20.0]
    sim = _RestartsUnheard(wp)
    sim.pos = [50.0, 40.0, -15.0]
    try:
        exc, hung = _carve_in_thread(path, sim, idle_timeout=0.5)
        assert not hung and isinstance(exc, CarveError), exc
        assert re.search(r"the controller has restarted \(machine position 0, 0, 0, its G54 zero "
                         r"elsewhere\): position lost, no retract sent\. 4 of 24 scratches are "
                         r"journalled; re-home \(--home\)", str(exc)), str(exc)
        after = wp.moves[sim.moves_at_restart:]  # (the move it was making, cut short)
        assert not [m for m in after if np.allclose(m[1], 0.0)]  # none from where it restarted
        events = [r.get("event") for r in Journal.records(path + ".journal")]
        assert events[-2:] == ["fault", "restarted"]
        with pytest.raises(CarveError, match=r"position may be lost \(a restart of the "
                                             r"controller since the job last ran\)"):
            _resume(path, sim)
        assert wp.moves[sim.moves_at_restart:] == after
    finally:
        sim.close()


def test_a_journal_that_cannot_be_written_stops_the_job_in_one_line(job, monkeypatch):
    """A `done` record that cannot be written (a full disk) stops the job at once: hold, reset,
    retract; one line naming the scratch, the journal and how to resume; the resume cuts that
    scratch again and finishes."""
    import errno

    path, prog = job
    append, dones = Journal._append, []

    def full_disk(self, rec):
        if rec.get("type") == "done":
            dones.append(rec["k"])
            if len(dones) == 4:
                raise OSError(errno.ENOSPC, "No space left on device")
        return append(self, rec)

    monkeypatch.setattr(Journal, "_append", full_disk)
    wp = Workpiece()
    sim = GrblSim(wp)
    try:
        with pytest.raises(CarveError) as e:
            carve(path, sim.port, **FAST)
        assert re.fullmatch(r"could not journal scratch position 3 \(design scratch \d+\), which "
                            r"was cut, in '.*job\.gcode\.journal': OSError: \[Errno 28\] No space "
                            r"left on device; held, reset and retracted to Z1\.000\. 3 of 24 "
                            r"scratches are journalled; .*--resume \(it cuts that scratch again, "
                            r"in its own groove\)", str(e.value)), str(e.value)
        assert sim.pos[2] == 1.0 and sim.spindle_on is None
        monkeypatch.setattr(Journal, "_append", append)
        assert _resume(path, sim)["done"] == 24
    finally:
        sim.close()
    _verify(prog, wp, in_progress={3})


class _NoHoming(GrblSim):
    """Homing not enabled (`$22=0`): GRBL 1.1 answers `$H` with `error:5`."""

    def _dollar(self, line):
        if line == "$H":
            self._answer("error:5")
            return True
        return super()._dollar(line)


def test_a_refused_homing_cycle_says_it_did_not_run(job):
    path, _ = job
    sim = _NoHoming(Workpiece(), settings={22: 0})
    try:
        with pytest.raises(CarveError) as e:
            carve(path, sim.port, home=True, **FAST)
    finally:
        sim.close()
    msg = str(e.value)
    assert re.fullmatch(r"the homing cycle \$H was answered error:5 \(homing is not enabled: "
                        r"\$22=0\); run again without --home .* \(the homing cycle \$H was sent; "
                        r"no G-code line was sent\)", msg), msg
    assert sim.wp.moves == []


def test_oks_owed_to_an_earlier_host_are_not_taken_for_the_answer_to_i(job):
    """A host that died during a dwell leaves GRBL Idle (so not reset) with an `ok` to come: it
    is not the answer to `$I`, whose own answer follows, and the job runs."""
    path, prog = job
    sim = GrblSim()
    try:
        g = Grbl(sim.port, banner_timeout=1.0, poll_interval=0.05).connect()
        g._write(b"G4 P1.500\n")
        time.sleep(0.2)
        g.close()
        assert carve(path, sim.port, **FAST)["done"] == 24
    finally:
        sim.close()
    _verify(prog, sim.wp)


@pytest.mark.parametrize("counting", [False, True])
def test_an_ok_that_answers_no_line_never_journals_a_scratch_early(job, counting):
    """Noise that reads `ok` would be taken for the oldest unanswered line's answer, and every
    later line's answer one line early: a scratch journalled while it is still being cut (lost
    if the job then stops). Each scratch is journalled only once it is carved and the tool is
    up, whether the stray `ok` comes at a plunge, a dwell or a travel, or before a line."""
    path, prog = job
    cuts = _program_cuts(prog)
    sim = GrblSim(block_time=0.02, stray_ok_at={2 + 5 * 3 + 2, 2 + 5 * 10 + 5, 2 + 5 * 15 + 1})
    early = []

    def on_scratch(k, s):
        done = any(f == 1.0 and np.allclose(e[:2], cuts[k][1], atol=1e-6)
                   for _, e, f in sim.wp.cuts())
        if not (done and sim.pos[2] > 0 and sim.state == "Idle"):
            early.append((k, done, tuple(sim.pos), sim.state))

    try:
        r = carve(path, sim.port, counting=counting, on_scratch=on_scratch, **FAST)
        assert early == [] and r["done"] == 24
        assert Journal.read(path + ".journal")[1] == 24
        g = Grbl(sim.port, banner_timeout=1.0, poll_interval=0.05).connect()
        sim._reply("ok")  # unasked, before the next line is written
        time.sleep(0.1)
        assert g.command("G4 P0").text == "ok" and g.stray_oks == 1
        g.close()
    finally:
        sim.close()
    _verify(prog, sim.wp)


def test_a_work_zero_reported_in_inches_is_named_in_mm():
    """With `$13=1` GRBL reports `$#` in inches; the work zero is compared and named in mm."""
    class Inches:  # what `Grbl.connect` leaves on such a controller
        port, homed, unlocked, state_at_connect, options = "/dev/ttyUSB0", True, False, "Idle", "V"
        settings = {13: 1.0}
        offsets = {"G54": (50 / 25.4, 40 / 25.4, -20 / 25.4), "G92": (0.0, 0.0, 0.0),
                   "TLO": (0.0,)}

    untouched = lambda: "(no motion was sent)"  # noqa: E731
    zero = carve_mod._check_work_zero(Inches(), "G54", None, False, untouched)
    np.testing.assert_allclose(zero, [50.0, 40.0, -20.0])
    with pytest.raises(CarveError, match=r"the G54 work zero is X50\.000 Y40\.000 Z-20\.000 "
                                         r"\(machine mm\) but was X50\.000 Y40\.000 Z-19\.000 .*"
                                         r"G10 L2 P1 X50\.000 Y40\.000 Z-19\.000"):
        carve_mod._check_work_zero(Inches(), "G54", {"G54": [50.0, 40.0, -19.0]}, False,
                                   untouched)
