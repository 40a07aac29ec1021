"""A simulated GRBL 1.1 controller on a real pseudo-terminal, for the fabrication tests.

The host opens ``sim.port`` (the pty's slave) with pyserial exactly like a USB serial port. The
simulator models what a host can get wrong:

- a 128-byte receive buffer (127 usable). A line's bytes occupy it until the line is answered (stricter
  than the real ISR, so a host that streams past the buffer always shows up): overflowing it is
  recorded in ``Workpiece.faults`` and the test fails;
- a 15-block planner executed by a motion thread (tiny sleeps), ``G4`` waiting for the planner and
  then dwelling ``P`` seconds while reporting ``Idle`` (as GRBL 1.1 does), ``M3``/``M5`` waiting for
  the planner too;
- the reply grammar ``ok``/``error:N``/``ALARM:N``/``[MSG:...]``/``<status>``, the banner on reset,
  ``$I`` with ``[OPT:V,15,128]``, ``$C`` check mode, ``$X``, ``$H``, ``$#`` (``[G54:x,y,z]`` ..
  ``[G92:..]``, ``[TLO:..]``) and ``$G`` (``[GC:...]``);
- work offsets as the firmware keeps them: ``G54``-``G59`` set by ``G10 L2``/``L20`` live in the
  :class:`Workpiece` (EEPROM: kept across resets and power cycles), the ``G92`` offset (``G92``,
  ``G92.1``) is cleared by a soft reset; targets are work coordinates, positions machine ones;
- real-time bytes ``?``, ``!``, ``~`` and ``0x18`` (reset in motion raises ALARM:3);
- settings (``$$``) as given, and GRBL 1.1h's soft limits: with ``$20=1`` a motion target outside
  the machine's travel (``[-$13N, 0]`` per axis; ``[0, $13N]`` for an axis homed towards its
  minimum, ``$23``, when ``options`` holds ``Z``, HOMING_FORCE_SET_ORIGIN) raises ``ALARM:2`` and
  stops motion, the position kept;
- faults: ``error:N`` on the n-th G-code line, ``ALARM:N`` in the n-th block, the device vanishing
  in the n-th block, the n-th line's ``ok`` lost, an ``ok`` that answers no line, garbage lines,
  a slow device, a non-GRBL device (optionally spewing given bytes), start in Alarm, cutting
  before the spindle is up to speed, starting the spindle with the tool on the board.

Every executed move is recorded in a :class:`Workpiece` (shared across simulator instances so a
"power cycle" keeps the board). :func:`check_line` is a strict GRBL 1.1 grammar checker.
"""

from __future__ import annotations

import os
import re
import select
import threading
import time
import tty
from collections import deque

RX_SIZE = 128
PLANNER = 15
BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"

# --- strict GRBL 1.1 line grammar -------------------------------------------------------------

_WORD = re.compile(r"([A-Z])([+-]?(?:\d+\.?\d*|\.\d+))")
_MODAL = {  # modal groups of the G-codes GRBL 1.1 supports
    "motion": {0, 1, 2, 3, 38.2, 38.3, 38.4, 38.5, 80},
    "plane": {17, 18, 19},
    "distance": {90, 91},
    "arc_distance": {91.1},
    "feed": {93, 94},
    "units": {20, 21},
    "cutter_comp": {40},
    "tool_length": {43.1, 49},
    "coord": {54, 55, 56, 57, 58, 59},
    "control": {61},
    "nonmodal": {4, 10, 28, 28.1, 30, 30.1, 53, 92, 92.1},
}
_MGROUP = {"stop": {0, 1, 2, 30}, "spindle": {3, 4, 5}, "coolant": {7, 8, 9}}
_LETTERS = set("FGHIJKLMNPRSTXYZ")


class GcodeError(ValueError):
    def __init__(self, code, msg):
        super().__init__(f"error:{code}: {msg}")
        self.code = code


def strip_comments(line: str) -> str:
    out, depth = [], 0
    for ch in line:
        if ch == ";" and depth == 0:
            break
        if ch == "(":
            if depth:
                raise GcodeError(1, "nested comment")
            depth = 1
        elif ch == ")":
            if not depth:
                raise GcodeError(1, "unbalanced ')'")
            depth = 0
        elif not depth:
            out.append(ch)
    if depth:
        raise GcodeError(1, "unterminated comment")
    return "".join(out)


def check_line(line: str, state: dict | None = None) -> dict:
    """Parse one G-code line under a strict GRBL 1.1 grammar; return its words.

    Strict: upper case, words separated by single spaces, each letter at most once (G and M once
    per modal group), numbers as GRBL reads them, at most 79 characters, G1 needs a feed rate (in
    the line or modal `state['F']`), G4 needs `P >= 0`, axis words need a motion mode. Raises
    :class:`GcodeError` with GRBL's error number.

    **Returns:** dict with `G` (list), `M` (list) and single letters -> float.
    """
    if state is None:
        state = {}
    if len(line) > 79:
        raise GcodeError(14, "line longer than 79 characters")
    if any(ord(c) < 32 or ord(c) > 126 for c in line):
        raise GcodeError(1, "non-printable character")
    body = strip_comments(line)
    if body != line:  # the text around a comment may keep its spaces
        body = " ".join(body.split())
    if body != body.strip() or "  " in body:
        raise GcodeError(1, "stray whitespace")
    words = {"G": [], "M": []}
    groups = set()
    if not body:
        return words
    for tok in body.split(" "):
        m = _WORD.fullmatch(tok)
        if not m:
            if tok[:1].isalpha() and tok[0].isupper():
                raise GcodeError(2, f"bad number format in {tok!r}")
            raise GcodeError(1, f"expected command letter in {tok!r}")
        letter, num = m.group(1), float(m.group(2))
        if letter not in _LETTERS:
            raise GcodeError(20, f"unsupported word {letter}")
        if letter in "GM":
            table = _MODAL if letter == "G" else _MGROUP
            grp = next((g for g, vals in table.items() if num in vals), None)
            if grp is None:
                raise GcodeError(20, f"unsupported command {tok}")
            if (letter, grp) in groups:
                raise GcodeError(21, f"modal group violation at {tok}")
            groups.add((letter, grp))
            words[letter].append(num)
        else:
            if letter in words:
                raise GcodeError(25, f"repeated word {letter}")
            words[letter] = num
    g = words["G"]
    axes = [a for a in "XYZ" if a in words]
    if "F" in words and words["F"] <= 0:
        raise GcodeError(4, "F must be > 0")
    if "S" in words and words["S"] < 0:
        raise GcodeError(4, "S must be >= 0")
    if 4 in g:
        if "P" not in words:
            raise GcodeError(26, "G4 without P")
        if words["P"] < 0:
            raise GcodeError(4, "negative P")
        if axes:
            raise GcodeError(24, "G4 with axis words")
    motion = next((c for c in g if c in _MODAL["motion"]), state.get("motion"))
    if axes and motion is None and not (set(g) & {10, 28, 30, 53, 92}):
        raise GcodeError(31, "axis words without a motion mode")
    if motion == 1 and axes:
        if "F" not in words and "F" not in state:
            raise GcodeError(22, "undefined feed rate")
    if any(c in (2, 3, 38.2, 38.3, 38.4, 38.5) for c in g):
        raise GcodeError(20, "arcs and probing are not used by jscratch")
    # update modal state
    if motion is not None:
        state["motion"] = motion
    if "F" in words:
        state["F"] = words["F"]
    for c in g:
        if c in (90, 91):
            state["distance"] = c
        if c in (20, 21):
            state["units"] = c
    return words


# --- the workpiece -----------------------------------------------------------------------------


class Workpiece:
    """What happened to the board: executed moves and protocol faults, shared across power cycles.

    `moves`: list of `(kind, start, end, fraction)` with `kind` `G0`/`G1`, `start`/`end` `(x, y, z)`
    machine mm and the executed fraction (1 for a complete move). `faults`: violations by the host
    (RX overflow, cutting with the spindle not up to speed). `received`: every G-code line received.
    `wcs`: the `G54`..`G59` work offsets (machine mm), kept like GRBL's EEPROM.
    """

    def __init__(self):
        self.moves = []
        self.faults = []
        self.received = []
        self.wcs = {c: [0.0, 0.0, 0.0] for c in range(54, 60)}
        self.lock = threading.Lock()

    def cuts(self):
        """Executed XY moves below the surface: `(start, end, fraction)`."""
        return [(s, e, f) for kind, s, e, f in self.moves
                if kind == "G1" and s[2] < 0 and e[2] < 0 and (s[0], s[1]) != (e[0], e[1])]


# --- the controller ----------------------------------------------------------------------------


class GrblSim:
    """A GRBL 1.1 controller on a pty. See the module docstring.

    **Arguments:** `workpiece` (new if None); `block_time` seconds per planner block; `reply_delay`
    seconds before each answer; `error_at` `(n, code)`: answer the n-th G-code line (1-based) with
    `error:code` instead of running it; `alarm_at` `(n, code)`: raise `ALARM:code` half-way through
    the n-th executed block; `vanish_at` n: close the device half-way through the n-th block;
    `garbage_every` n: a garbage line before every n-th answer; `drop_ok_at` n: run the n-th G-code
    line but never send its `ok`; `stray_ok_at` a collection of n: an `ok` that answers no line,
    sent as the n-th G-code line is received (before its own answer); `start_alarm`;
    `not_grbl`: answer like some other firmware, or with these bytes; `spinup_s`: a cut below
    Z = 0 (work) sooner than this after `M3`, or with the spindle off, is a fault;
    `banner_on_open`; `settings` the `$$` settings (number -> value; `$20=1` turns soft limits
    on); `options` the build option letters of `$I`'s `[OPT:...]`.
    """

    def __init__(self, workpiece=None, *, block_time=0.0004, reply_delay=0.0, error_at=None, alarm_at=None,
                 vanish_at=None, garbage_every=None, drop_ok_at=None, stray_ok_at=(),
                 start_alarm=False, not_grbl=False,
                 spinup_s=None, banner_on_open=True, settings=None, options="V"):
        self.wp = workpiece or Workpiece()
        self.settings = dict(settings or {})
        self.options = options
        self.drop_ok_at = drop_ok_at
        self.stray_ok_at = set(stray_ok_at)
        self.spinup_s = spinup_s
        self.g92 = [0.0, 0.0, 0.0]
        self.spindle_on = None  # time.monotonic() of the M3 that started the spindle
        self._dwell_end = None
        self.block_time = block_time
        self.reply_delay = reply_delay
        self.error_at = error_at
        self.alarm_at = alarm_at
        self.vanish_at = vanish_at
        self.garbage_every = garbage_every
        self.not_grbl = not_grbl
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        self.port = os.ttyname(self.slave)
        self.lock = threading.RLock()
        self.rx = bytearray()  # bytes of unanswered lines
        self.planner = deque()
        self.pos = [0.0, 0.0, 5.0]
        self.state = "Alarm" if start_alarm else "Idle"
        self.hold = False
        self.check = False
        self.modal = {"distance": 90, "units": 21}
        self.gcode_lines = 0
        self.blocks_run = 0
        self.replies = 0
        self.executing = None
        self.critical = False
        self.alive = True
        self._stop = threading.Event()
        self._io = threading.Thread(target=self._io_loop, daemon=True)
        self._motion = threading.Thread(target=self._motion_loop, daemon=True)
        if banner_on_open:
            self._send(b"\x00\xff" if garbage_every else b"")
            self._banner()
        self._io.start()
        self._motion.start()

    # -- output --
    def _send(self, data: bytes):
        if not self.alive or not data:
            return
        try:
            os.write(self.master, data)
        except OSError:
            pass

    def _reply(self, text: str):
        if self.reply_delay:
            time.sleep(self.reply_delay)
        self.replies += 1
        if self.garbage_every and self.replies % self.garbage_every == 0:
            self._send(b"\xfe\x80#garbage%\x01\r\n")
        self._send(text.encode() + b"\r\n")

    def _banner(self):
        if self.not_grbl:
            self._send(self.not_grbl if isinstance(self.not_grbl, bytes) else b"start\r\nMarlin 2.1\r\necho: Unknown command\r\n")
            return
        self._send(BANNER)
        if self.state == "Alarm":
            self._send(b"[MSG:'$H'|'$X' to unlock]\r\n")

    def close(self):
        self._stop.set()
        self.alive = False
        for t in (self._io, self._motion):
            if t.is_alive() and t is not threading.current_thread():
                t.join(timeout=1.0)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def vanish(self):
        """The device disappears (USB unplugged): the pty closes."""
        self.alive = False
        self._stop.set()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    # -- input --
    def _status(self):
        x, y, z = self.pos
        st = self.state
        bf = f"Bf:{PLANNER - len(self.planner)},{RX_SIZE - 1 - len(self.rx)}"
        return f"<{st}|MPos:{x:.3f},{y:.3f},{z:.3f}|{bf}|FS:0,0>"

    def _reset(self):
        with self.lock:
            moving = self.executing is not None and not (self.hold and self.state == "Hold:0")
            if self.executing is not None:
                self.executing["abort"] = True
            self.planner.clear()
            self.rx.clear()
            self.hold = False
            self.critical = False
            self.check = False
            self.modal = {"distance": 90, "units": 21}
            self.g92 = [0.0, 0.0, 0.0]  # the firmware's gc_init clears the G92 offset
            self.spindle_on = None
            self._dwell_end = None
            if moving:
                self.state = "Alarm"
                self._send(b"ALARM:3\r\n")
            elif self.state != "Alarm":
                self.state = "Idle"
        self._banner()

    def _io_loop(self):
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self.master], [], [], 0.001)
            except (OSError, ValueError):
                return
            if r:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    return
                for b in data:
                    self._byte(b)
            self._parse_lines()

    def _byte(self, b):
        c = bytes([b])
        if self.not_grbl:
            if c == b"\n":
                self._send(self.not_grbl if isinstance(self.not_grbl, bytes) else b"echo: Unknown command\r\n")
            self.rx.clear()
            return
        if c == b"?":
            self._send(self._status().encode() + b"\r\n")
        elif c == b"!":
            with self.lock:
                if self.state == "Run" or self.executing is not None:
                    self.hold = True
                    self.state = "Hold:1"
                elif self.state == "Idle":
                    self.hold = True
                    self.state = "Hold:0"
        elif c == b"~":
            with self.lock:
                if self.hold:
                    self.hold = False
                    self.state = "Run" if (self.planner or self.executing) else "Idle"
        elif c == b"\x18":
            self._reset()
        else:
            if b >= 0x80:
                return
            self.rx.append(b)
            if len(self.rx) > RX_SIZE - 1:
                with self.wp.lock:
                    self.wp.faults.append(f"RX buffer overflow: {len(self.rx)} bytes > {RX_SIZE - 1}")

    def _parse_lines(self):
        while self.alive and not self.critical:
            i = self.rx.find(b"\n")
            if i < 0:
                return
            line = self.rx[:i].decode("ascii", "replace").strip("\r ").strip()
            done = self._execute_line(line)
            if not done:
                return  # waits for planner space / drain
            del self.rx[:i + 1]
            # (the answer has been sent by _execute_line, after which the bytes are freed)

    def _answer(self, text):
        self._reply(text)

    def _execute_line(self, line: str) -> bool:
        """Run one line; False when it must wait (planner full, G4 draining). Answers it when done."""
        if not line:
            self._answer("ok")
            return True
        if line.startswith("$"):
            return self._dollar(line)
        if self.state == "Alarm":
            self._answer("error:9")
            return True
        # Planner space / dwell synchronisation before parsing side effects.
        try:
            words = check_line(line, dict(self.modal))
        except GcodeError as exc:
            self.wp.received.append(line)
            self._answer(f"error:{exc.code}")
            return True
        g, mc = words["G"], words["M"]
        offset_cmd = set(g) & {10, 92}
        is_motion = any(a in words for a in "XYZ") and not offset_cmd
        if is_motion and len(self.planner) >= PLANNER:
            return False
        if (4 in g or set(mc) & {2, 3, 5}) and not self.check:
            if self.planner or self.executing is not None:
                return False  # G4 and spindle changes wait for the planner to drain
            if 4 in g:
                if self._dwell_end is None:
                    self._dwell_end = time.monotonic() + words["P"]
                if time.monotonic() < self._dwell_end:
                    return False  # dwelling: status says Idle
                self._dwell_end = None
        self.gcode_lines += 1
        self.wp.received.append(line)
        if self.gcode_lines in self.stray_ok_at:
            self._answer("ok")  # noise: an answer to no line
        if self.error_at and self.gcode_lines == self.error_at[0]:
            self._answer(f"error:{self.error_at[1]}")
            return True
        check_line(line, self.modal)  # update modal state
        for c in g:
            if c in (54, 55, 56, 57, 58, 59):
                self.modal["coord"] = int(c)
        if not self.check:
            self._offsets_and_spindle(words)
        if is_motion:
            target = list(self.pos_after_planner())
            off = self.work_offset()
            for j, a in enumerate("XYZ"):
                if a in words:
                    target[j] = words[a] + off[j] if self.modal.get("distance", 90) == 90 else target[j] + words[a]
            kind = "G0" if self.modal.get("motion") == 0 else "G1"
            if self.settings.get(20) and not self._within_travel(target):
                # GRBL 1.1h (limits_soft_check): feed hold, reset, ALARM:2; position kept
                with self.lock:
                    if self.executing is not None:
                        self.executing["abort"] = True
                    self.planner.clear()
                    self.state = "Alarm"
                    self.critical = True
                self._send(b"ALARM:2\r\n[MSG:Reset to continue]\r\n")
                return True
            if not self.check:
                with self.lock:
                    self.planner.append({"kind": kind, "target": target, "abort": False,
                                         "below": target[2] - off[2] < -1e-9})
                    if not self.hold:
                        self.state = "Run"
            else:
                self._check_pos = target
        if self.drop_ok_at and self.gcode_lines == self.drop_ok_at:
            return True  # the ok is lost on the wire
        self._answer("ok")
        return True

    def _within_travel(self, target):
        """GRBL 1.1h's `system_check_travel_limits` for a machine target (mm)."""
        for j in range(3):
            t = self.settings.get(130 + j, 0.0)
            if "Z" in self.options and int(self.settings.get(23, 0)) >> j & 1:
                lo, hi = 0.0, t
            else:
                lo, hi = -t, 0.0
            if not lo <= target[j] <= hi:
                return False
        return True

    def work_offset(self):
        """Machine minus work coordinates: the active G54..G59 offset plus G92 (mm)."""
        wcs = self.wp.wcs[self.modal.get("coord", 54)]
        return [a + b for a, b in zip(wcs, self.g92)]

    def _offsets_and_spindle(self, words):
        g, mc = words["G"], words["M"]
        pos = self.pos_after_planner()
        if 10 in g:  # G10 L2 Pn: offset = value; G10 L20 Pn: offset such that here = value
            coord = 53 + int(words.get("P", 1)) if words.get("P", 0) else self.modal.get("coord", 54)
            for j, a in enumerate("XYZ"):
                if a in words:
                    v = words[a] if words.get("L") == 2 else pos[j] - self.g92[j] - words[a]
                    with self.wp.lock:
                        self.wp.wcs[coord][j] = v
        if 92 in g:
            wcs = self.wp.wcs[self.modal.get("coord", 54)]
            for j, a in enumerate("XYZ"):
                if a in words:
                    self.g92[j] = pos[j] - wcs[j] - words[a]
        if 92.1 in g:
            self.g92 = [0.0, 0.0, 0.0]
        if 3 in mc:
            z_work = pos[2] - self.work_offset()[2]
            if self.spindle_on is None and z_work <= 1e-6:  # a spinning cutter marks the board
                with self.wp.lock:
                    self.wp.faults.append(f"spindle started with the tool on the board (work Z "
                                          f"{z_work:.3f})")
            self.spindle_on = time.monotonic()
        if 5 in mc or 2 in mc:
            self.spindle_on = None

    def pos_after_planner(self):
        if self.check:
            return getattr(self, "_check_pos", self.pos)
        if self.planner:
            return self.planner[-1]["target"]
        if self.executing is not None:
            return self.executing["target"]
        return self.pos

    def _dollar(self, line):
        if line == "$I":
            self._send(f"[VER:1.1h.20190825:]\r\n[OPT:{self.options},15,128]\r\n".encode())
            self._answer("ok")
        elif line == "$C":
            if self.check:
                self.check = False
                self._send(b"[MSG:Disabled]\r\n")
                self._answer("ok")
                self._reset()
            else:
                if self.state not in ("Idle",):
                    self._answer("error:8")
                    return True
                self.check = True
                self._check_pos = list(self.pos)
                self._send(b"[MSG:Enabled]\r\n")
                self._answer("ok")
        elif line == "$X":
            if self.state == "Alarm":
                self.state = "Idle"
                self._send(b"[MSG:Caution: Unlocked]\r\n")
            self._answer("ok")
        elif line == "$H":
            if self.planner or self.executing is not None:
                return False
            time.sleep(self.block_time * 5)
            self.pos = [0.0, 0.0, 5.0]
            self.state = "Idle"
            self._answer("ok")
        elif line == "$#":
            rows = [f"G{c}:" + ",".join(f"{v:.3f}" for v in self.wp.wcs[c]) for c in range(54, 60)]
            rows += ["G28:0.000,0.000,0.000", "G30:0.000,0.000,0.000",
                     "G92:" + ",".join(f"{v:.3f}" for v in self.g92), "TLO:0.000", "PRB:0.000,0.000,0.000:0"]
            self._send("".join(f"[{r}]\r\n" for r in rows).encode())
            self._answer("ok")
        elif line == "$G":
            dist = self.modal.get("distance", 90)
            units = self.modal.get("units", 21)
            spindle = "M5" if self.spindle_on is None else "M3"
            self._send(f"[GC:G0 G{self.modal.get('coord', 54)} G17 G{units} G{dist} G94 {spindle} M9 T0 F0 S0]\r\n".encode())
            self._answer("ok")
        elif line == "$$":
            self._send("".join(f"${k}={v:.3f}\r\n" if k >= 100 else f"${k}={int(v)}\r\n"
                               for k, v in sorted(self.settings.items())).encode())
            self._answer("ok")
        else:
            self._answer("error:3")
        return True

    # -- motion --
    def _motion_loop(self):
        steps = 4
        while not self._stop.is_set():
            with self.lock:
                if self.hold or not self.planner or self.state == "Alarm":
                    blk = None
                    if self.hold and self.executing is None and self.state == "Hold:1":
                        self.state = "Hold:0"
                else:
                    blk = self.planner.popleft()
                    self.executing = blk
                    self.state = "Run"
            if blk is None:
                time.sleep(self.block_time / steps)
                continue
            if self.spinup_s is not None and blk["below"]:
                on = self.spindle_on
                if on is None or time.monotonic() - on < self.spinup_s:
                    with self.wp.lock:
                        self.wp.faults.append(f"cut below the surface to {blk['target']} with the spindle "
                                              + ("off" if on is None else f"on for only {time.monotonic() - on:.3f} s"))
            self.blocks_run += 1
            start = list(self.pos)
            frac = 0.0
            aborted = False
            for step in range(1, steps + 1):
                time.sleep(self.block_time / steps)
                while True:  # feed hold pauses mid-block
                    with self.lock:
                        if blk["abort"]:
                            aborted = True
                            break
                        if not self.hold:
                            break
                        self.state = "Hold:0"
                    time.sleep(self.block_time / steps)
                    if self._stop.is_set():
                        aborted = True
                        break
                if aborted:
                    break
                frac = step / steps
                self.pos = [s + frac * (t - s) for s, t in zip(start, blk["target"])]
                self._bounds_hook(self.pos)
                if step == steps // 2:
                    if self.alarm_at and self.blocks_run == self.alarm_at[0]:
                        self._record(blk, start, frac)
                        with self.lock:
                            self.planner.clear()
                            self.executing = None
                            self.state = "Alarm"
                            self.critical = True
                        self._send(f"ALARM:{self.alarm_at[1]}\r\n".encode() + b"[MSG:Reset to continue]\r\n")
                        blk = None
                        break
                    if self.vanish_at and self.blocks_run == self.vanish_at:
                        self._record(blk, start, frac)
                        self.vanish()
                        return
            if blk is None:
                continue
            self._record(blk, start, frac)
            with self.lock:
                self.executing = None
                if not self.planner and not self.hold and self.state == "Run":
                    self.state = "Idle"
                if self.hold:
                    self.state = "Hold:0"

    def _bounds_hook(self, pos):
        pass

    def _record(self, blk, start, frac):
        end = [s + frac * (t - s) for s, t in zip(start, blk["target"])]
        with self.wp.lock:
            self.wp.moves.append((blk["kind"], tuple(start), tuple(end), frac))
