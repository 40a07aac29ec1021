"""GRBL 1.1 serial protocol: reply grammar and a streaming client over pyserial (the carve
journal is `jscratch.journal`).

pyserial is imported here (lazily, when a port is opened), never at ``import jscratch``.

Protocol notes (GRBL 1.1 interface documentation):

- every line the host sends is answered by exactly one ``ok`` or ``error:N``, in order;
- ``ALARM:N``, ``[MSG:...]``/``[...]`` feedback, ``<status>`` reports and the ``Grbl 1.1x ['$' for
  help]`` banner (after a reset) arrive unasked;
- the real-time bytes ``?`` (status), ``!`` (feed hold), ``~`` (cycle start) and ``0x18`` (soft
  reset) bypass the receive buffer and are never answered with ``ok``;
- the receive buffer holds ``rx_size - 1`` bytes (``rx_size`` from ``$I``'s ``[OPT:...,blocks,rx]``);
  character counting keeps the bytes of unanswered lines within it;
- a soft reset clears the ``G92`` offset and the tool length offset; the ``G54``..``G59`` work
  offsets (``G10 L2``/``L20``) live in EEPROM and survive resets and power cycles. `Grbl.connect`
  therefore does not reset a controller that reports ``Idle``, and reads ``$#`` so that the caller
  can refuse a ``G92`` zero instead of losing it;
- numbers are read as at most 8 significant digits without exponents: `gword` writes every
  word with fixed decimals inside `WORD_FORMAT`'s ranges, `check_words` checks a line.
"""

from __future__ import annotations

import math
import os
import queue
import re
import threading
import time
from collections import deque
from typing import Callable, NamedTuple, Sequence

from jscratch.errors import CarveError, InputError

__all__ = [
    "Reply", "classify", "GrblError", "PortError", "NotGrblError", "AlarmLocked", "DeviceLost",
    "JobFault", "Stalled", "Grbl", "gword", "check_words",
    "WORD_FORMAT", "clip",
]

BANNER_RE = re.compile(r"^Grbl (\d+)\.(\d+)(\w*) \['\$' for help\]$")
FEEDBACK_RE = re.compile(r"\[[A-Z][A-Z0-9]*:[\x20-\x7e]*\]")  # [MSG:..], [GC:..], [G54:..], [G92:..], [TLO:..]
OFFSET_RE = re.compile(r"\[(G5[4-9]|G28|G30|G92|TLO):(-?\d+\.?\d*(?:,-?\d+\.?\d*)*)\]")
SETTING_RE = re.compile(r"\$(\d+)=(-?\d+\.?\d*)")  # one line of `$$`, e.g. `$130=300.000`


def clip(text, limit: int = 120) -> str:
    """`text` as one printable ASCII line of at most `limit` characters (escaped, cut with `...`)."""
    s = "".join(c if " " <= c <= "~" else ascii(c)[1:-1] for c in str(text))
    return s if len(s) <= limit else s[:max(limit - 3, 0)] + "..."


# Fixed decimals and the range of each word jscratch writes. GRBL reads a number as at most 8
# significant digits (more are dropped silently) and knows no exponent, so every range keeps
# the fixed-decimal text within 8 digits; F must be > 0, S and P >= 0.
WORD_FORMAT = {  # letter: (decimals, lowest, highest)
    "X": (3, -99999.999, 99999.999),
    "Y": (3, -99999.999, 99999.999),
    "Z": (3, -99999.999, 99999.999),
    "F": (1, 0.1, 9999999.9),
    "S": (0, 0.0, 99999999.0),
    "P": (3, 0.0, 99999.999),
}
_COMMANDS = {"G": {0, 1, 4, 17, 21, 49, 54, 55, 56, 57, 58, 59, 90, 94}, "M": {2, 3, 5}}


def gword(letter: str, value: float) -> str:
    """One G-code word, e.g. `gword("F", 900) == "F900.0"`: fixed decimals, no exponent, in range.

    **Raises:** `InputError` (a `ValueError`) naming the word when `value` is not finite or outside
    `WORD_FORMAT`.
    """
    dec, lo, hi = WORD_FORMAT[letter]
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"G-code word {letter}: {value!r} is not a finite number")
    text = f"{v:.{dec}f}"
    if float(text) == 0.0:
        text = text.lstrip("-")
    if not lo <= float(text) <= hi:
        shown = text if len(text) <= 16 else f"{v:.6g}"  # (1e300 in fixed point: 300 digits)
        raise InputError(f"G-code word {letter}{shown} is outside GRBL's range "
                         f"[{lo:.{dec}f}, {hi:.{dec}f}]")
    return letter + text


def check_words(line: str) -> None:
    """Check that every word of a G-code line (comments allowed) is as `gword` writes it.

    Commands `G`/`M` must be whole numbers jscratch uses; `X Y Z F S P` fixed decimals in range.
    **Raises:** `InputError` (a `ValueError`) naming the first bad word.
    """
    body = re.sub(r"\([^()]*\)", " ", line).split(";")[0]
    for tok in body.split():
        letter = tok[:1]
        if letter in _COMMANDS:
            if not (re.fullmatch(r"[GM](0|[1-9]\d*)", tok) and int(tok[1:]) in _COMMANDS[letter]):
                raise InputError(f"G-code word {tok!r} is not a command jscratch writes")
        elif letter in WORD_FORMAT:
            dec = WORD_FORMAT[letter][0]
            frac = rf"\.\d{{{dec}}}" if dec else ""
            if not re.fullmatch(rf"{letter}-?\d{{1,8}}{frac}", tok):
                raise InputError(f"G-code word {tok!r}: not fixed-point with {dec} decimals (no exponent)")
            gword(letter, float(tok[1:]))
        else:
            raise InputError(f"G-code word {tok!r}: letter {letter!r} is not written by jscratch")


class Reply(NamedTuple):
    """One classified line from the controller.

    `kind` is one of `ok`, `error`, `alarm`, `status`, `msg` (any `[...]` feedback), `banner`,
    `setting` (a `$N=value` line of `$$`), `unknown`; `code` the number of `error:N`/`ALARM:N`
    (else None); `text` the line; `msgs` how many `msg` lines came before it and `seq` its place
    among every line the controller sent (both set on the answers `Grbl` queues: which of them
    came after a command's feedback, or before a line was written).
    """

    kind: str
    code: int | None
    text: str
    msgs: int = 0
    seq: int = 0


def classify(line: str) -> Reply:
    """Classify one line (without its line ending) under the GRBL 1.1 reply grammar."""
    if line == "ok":
        return Reply("ok", None, line)
    m = re.fullmatch(r"error:(\d+)", line)
    if m:
        return Reply("error", int(m.group(1)), line)
    m = re.fullmatch(r"ALARM:(\d+)", line)
    if m:
        return Reply("alarm", int(m.group(1)), line)
    if re.fullmatch(r"<[A-Za-z]+(:\d)?(\|[A-Za-z]+:[^|<>]*)*>", line):
        return Reply("status", None, line)
    if FEEDBACK_RE.fullmatch(line):
        return Reply("msg", None, line)
    if BANNER_RE.match(line):
        return Reply("banner", None, line)
    if SETTING_RE.fullmatch(line):
        return Reply("setting", None, line)
    return Reply("unknown", None, line)


def parse_status(line: str) -> dict:
    """Fields of a `<State|Key:val|...>` report: `state` (e.g. `Idle`, `Run`, `Hold:0`, `Alarm`) and the keys."""
    body = line[1:-1].split("|")
    out = {"state": body[0]}
    for field in body[1:]:
        k, _, v = field.partition(":")
        out[k] = v
    return out


class GrblError(CarveError):
    """Base class of controller and streaming errors (a `CarveError`)."""


class PortError(GrblError):
    """The serial port cannot be opened."""


class NotGrblError(GrblError):
    """The device did not answer like GRBL 1.1."""


class AlarmLocked(GrblError):
    """The controller is in Alarm state and neither homing nor unlock was requested."""


class DeviceLost(GrblError):
    """The device vanished or stopped answering."""


class JobFault(GrblError):
    """The controller reported `error:N` or `ALARM:N` (or reset) while streaming.

    `index` is the stream item the fault belongs to (for `ALARM`, the oldest unanswered line), `reply`
    the controller's line.
    """

    def __init__(self, message, index, reply):
        super().__init__(message)
        self.index = index
        self.reply = reply


class Stalled(JobFault):
    """A line owed an answer for longer than the idle bound while every status report said `Idle`
    (an `ok` lost on the wire); `reply` is `"stall"`."""


ERROR_TEXT = {
    1: "expected command letter", 2: "bad number format", 3: "invalid $ statement",
    9: "G-code locked out during alarm or jog", 14: "line too long", 15: "travel exceeds max travel",
    20: "unsupported or invalid g-code command", 21: "modal group violation", 22: "undefined feed rate",
    24: "two G-code commands need axis words", 25: "repeated word", 26: "no axis words",
    33: "invalid motion target",
}
ALARM_TEXT = {
    1: "hard limit triggered, position likely lost", 2: "soft limit: target outside travel",
    3: "reset while in motion, position likely lost", 4: "probe fail", 5: "probe fail",
    6: "homing fail: reset during cycle", 7: "homing fail: door opened", 8: "homing fail: pull-off",
    9: "homing fail: limit switch not found",
}
_DWELL_RE = re.compile(r"\bG4\b.*\bP(\d+\.?\d*)")

#: States in which a dwell cannot have been answered: GRBL answers `G4` only once the planner is
#: empty and the dwell is over, so a report sent after a dwell's `ok`, with nothing sent after
#: the dwell, says `Idle` (`Check` in check mode). A feed hold from the machine's own button
#: (`Hold`) is counted as moving too: the stream then waits for another `ok`.
_MOVING = ("Run", "Jog", "Hold")


#: How many unexpected lines from a controller are logged (a noisy line could send thousands).
_UNKNOWN_LOGGED = 10


class Grbl:
    """A GRBL 1.1 controller on a serial port.

    Opening starts a reader thread that classifies every reply and a poller that sends `?` every
    `poll_interval` s. Use `connect` (status, reset unless `Idle`, `$I`, alarm check, `$#`)
    before `stream`.

    **Arguments:** `port` device path; `baud` rate; `banner_timeout` s to wait for the banner;
    `stall_timeout` s without any byte from the device before it counts as lost; `idle_timeout` s a
    line may stay unanswered while every status report says `Idle` (plus the `P` of dwells in
    flight) before `stream` raises `Stalled`; `poll_interval` s between status polls;
    `log` a callable taking a string (warnings, unknown lines).
    """

    def __init__(self, port: str, baud: int = 115200, *, banner_timeout: float = 5.0,
                 stall_timeout: float = 30.0, idle_timeout: float = 10.0, poll_interval: float = 0.25,
                 log: Callable[[str], None] | None = None):
        import serial  # only here: pyserial is not needed to import jscratch

        self._serial_mod = serial
        self.port = port
        self.banner_timeout = banner_timeout
        self.stall_timeout = stall_timeout
        self.idle_timeout = idle_timeout
        self.poll_interval = poll_interval
        self.log = log or (lambda s: None)
        if not os.path.exists(port) and "://" not in port:
            raise PortError(f"serial port {clip(port)!r} does not exist")
        try:
            self.ser = serial.serial_for_url(port, baud, timeout=0.02, write_timeout=2.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortError(f"cannot open serial port {clip(port)!r}: {clip(exc)}") from None
        self.rx_size = 128
        self.options = ""  # the build option letters of `$I`'s `[OPT:...]` (e.g. "VNMZ")
        self.settings: dict = {}  # from `$$`: setting number -> value, e.g. {130: 300.0}
        self.version = None
        self.banner = None
        self.status: dict = {}
        self.messages: list[str] = []
        self.unknown: list[str] = []  # the latest unexpected lines (`n_unknown` in all)
        self.n_unknown = 0
        self.lines_sent: list[str] = []
        self.offsets: dict = {}  # from `$#`: "G54".."G59", "G28", "G30", "G92" -> (x, y, z); "TLO" -> (z,)
        self.modes: list[str] = []  # from `$G`: the parser state, e.g. ["G0", "G54", "G17", ...]
        self.reset_sent = False  # connect sent a soft reset
        self.homed = False  # connect ran the homing cycle `$H` (the machine moved)
        self.homing_tried = False  # connect sent `$H` (answered ok or not)
        self.state_at_connect = ""  # the state connect found (after its reset, if it sent one)
        self.unlocked = False  # connect cleared an Alarm with `$X` (the position was not restored)
        self._acks: queue.Queue = queue.Queue()
        self._banner_event = threading.Event()
        self._status_event = threading.Event()
        self._last_reply = time.monotonic()  # the latest line GRBL sends (not noise)
        self._unknown_at_reply = 0  # `n_unknown` then
        self._n_msgs = 0  # `msg` lines received
        self._seq = 0  # lines received (each reply's `seq`)
        self._status_seq = 0  # `seq` of the latest status report
        self.stray_oks = 0  # `ok`s that answered no line, ignored (`stream`, `command`)
        self._idle_since: float | None = None  # first of the unbroken run of `Idle` reports
        self._status_at = 0.0  # when the latest status report came
        self._lost: BaseException | None = None
        self._stop = threading.Event()
        self._wlock = threading.Lock()
        self._polling = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, name="grbl-reader", daemon=True)
        self._poller = threading.Thread(target=self._poll_loop, name="grbl-poller", daemon=True)
        self._reader.start()
        self._poller.start()

    # -- low level ---------------------------------------------------------------------------

    def close(self):
        """Stop the threads and close the port."""
        self._stop.set()
        for t in (self._poller, self._reader):
            if t.is_alive() and t is not threading.current_thread():
                t.join(timeout=1.0)
        try:
            self.ser.close()
        except Exception:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _lost_error(self, how: str = "lost") -> DeviceLost:
        return DeviceLost(f"device on {self.port} {how}: {clip(self._lost, 80)}")

    def _write(self, data: bytes):
        if self._lost is not None:
            raise self._lost_error()
        try:
            with self._wlock:
                self.ser.write(data)
        except (self._serial_mod.SerialException, OSError) as exc:
            self._lost = exc
            raise self._lost_error("lost while writing") from None

    def realtime(self, byte: bytes):
        """Send a real-time command byte (`b'?'`, `b'!'`, `b'~'`, `b'\\x18'`)."""
        self._write(byte)

    def _read_loop(self):
        buf = b""
        while not self._stop.is_set():
            try:
                data = self.ser.read(max(1, self.ser.in_waiting))
            except Exception as exc:  # SerialException, OSError (EIO when the device vanishes)
                if not self._stop.is_set():
                    self._lost = exc
                    self._acks.put(Reply("lost", None, str(exc)))
                return
            if not data:
                continue
            buf += data
            while b"\n" in buf:
                raw, buf = buf.split(b"\n", 1)
                self._handle(raw.rstrip(b"\r").decode("ascii", "replace").strip())
            if len(buf) > 1024:
                self._handle(buf.decode("ascii", "replace"))
                buf = b""

    def _handle(self, line: str):
        if not line:
            return
        now = time.monotonic()
        self._seq += 1
        r = classify(line)._replace(seq=self._seq)
        if r.kind != "unknown":  # (noise keeps no device alive: `_check_alive`)
            self._last_reply, self._unknown_at_reply = now, self.n_unknown
        if r.kind in ("ok", "error", "alarm"):
            self._acks.put(r._replace(msgs=self._n_msgs))
        elif r.kind == "status":
            self.status = parse_status(line)
            self._status_at, self._status_seq = now, self._seq
            if self.status["state"] != "Idle":
                self._idle_since = None
            elif self._idle_since is None:
                self._idle_since = now
            self._status_event.set()
        elif r.kind == "banner":
            self.banner = line
            self._banner_event.set()
            self._acks.put(r)
        elif r.kind == "msg":
            self.messages.append(line)
            self._n_msgs += 1
        elif r.kind == "setting":
            m = SETTING_RE.fullmatch(line)
            self.settings[int(m.group(1))] = float(m.group(2))
        else:
            self.unknown = self.unknown[-(_UNKNOWN_LOGGED - 1):] + [line]  # the latest few
            self.n_unknown += 1
            if self.n_unknown <= _UNKNOWN_LOGGED:
                last = self.n_unknown == _UNKNOWN_LOGGED
                self.log(f"ignored unexpected line from controller: {clip(line)!r}"
                         + (" (no more such lines are shown)" if last else ""))

    def _poll_loop(self):
        while not self._stop.wait(self.poll_interval):
            if self._polling.is_set() and self._lost is None:
                try:
                    self._write(b"?")
                except DeviceLost:
                    return

    def _check_alive(self):
        if self._lost is not None:
            raise self._lost_error()
        if time.monotonic() - self._last_reply > self.stall_timeout:
            if self.n_unknown > self._unknown_at_reply:
                raise DeviceLost(
                    f"device on {self.port} sent nothing GRBL sends for {self.stall_timeout:g} s, "
                    f"only {self.n_unknown - self._unknown_at_reply} unexpected lines (the latest "
                    f"{clip(self.unknown[-1], 40)!r}: a wrong baud rate, noise on the line?)")
            raise DeviceLost(f"device on {self.port} sent nothing for {self.stall_timeout:g} s")

    def _next(self, timeout=None, *, idle_limit=None, since=0.0) -> Reply:
        """Next ok/error/alarm/banner reply; raises DeviceLost when the device is gone or silent.

        With `idle_limit`: a `Reply("stall", ...)` once every status report for `idle_limit` s (and
        since `since`, a `time.monotonic()`) said `Idle`, reports still come, and nothing was
        answered; an `alarm` reply without a code once a status report since `since` says
        `Alarm` (its `ALARM:N` line lost).
        """
        t_end = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                r = self._acks.get(timeout=0.02)
            except queue.Empty:
                self._check_alive()
                now = time.monotonic()
                if t_end is not None and now > t_end:
                    raise DeviceLost(f"no reply from {self.port} within {timeout:g} s") from None
                idle = self._idle_since
                fresh = now - self._status_at < max(1.0, 4 * self.poll_interval)  # reports come
                if (idle_limit is not None and idle is not None and fresh
                        and now - max(idle, since) > idle_limit):
                    return Reply("stall", None, "stall")
                alarm = self.status.get("state", "").startswith("Alarm") and self._status_at > since
                if idle_limit is not None and alarm:
                    return Reply("alarm", None, "ALARM (a status report; no ALARM:N line came)")
                continue
            if r.kind == "lost":
                raise DeviceLost(f"device on {self.port} lost: {clip(r.text, 80)}")
            return r

    def query_status(self, timeout: float = 2.0) -> dict:
        """Send `?` and return the next status report's fields."""
        self._status_event.clear()
        self._write(b"?")
        if not self._status_event.wait(timeout):
            self._check_alive()
            raise DeviceLost(f"no status report from {self.port} within {timeout:g} s")
        return dict(self.status)

    def _state_after(self, seq: int, timeout: float = 2.0) -> str:
        """The state in the first status report the controller sent after its reply `seq`
        (`query_status` until one comes; `DeviceLost` when none does within `timeout` s)."""
        while self._status_seq <= seq:
            self.query_status(timeout)
        return self.status.get("state", "")

    def _stray(self, why: str):
        self.stray_oks += 1
        self.log(f"ignored an 'ok' that answered no line ({why}): noise on the line, or another "
                 "program writing to the port?")

    def command(self, line: str, timeout: float = 10.0) -> Reply:
        """Send one line and wait for its `ok`/`error:N` (ALARM raises `JobFault`); an `ok` that
        came before the line was written answers no line of this host's and is ignored."""
        before = self._seq
        self._write((line + "\n").encode("ascii"))
        self.lines_sent.append(line)
        while True:
            r = self._next(timeout)
            if r.kind == "ok" and r.seq <= before:
                self._stray(f"it came before {clip(line, 40)!r} was sent")
                continue
            if r.kind == "banner":
                raise JobFault(f"controller reset while waiting for {line!r}", -1, r.text)
            if r.kind == "alarm":
                raise JobFault(f"ALARM:{r.code} ({ALARM_TEXT.get(r.code, '?')}) after {line!r}", -1, r.text)
            return r

    def _drain(self):
        time.sleep(0.02)
        while not self._acks.empty():
            self._acks.get_nowait()

    # -- session -----------------------------------------------------------------------------

    def _probe(self) -> str | None:
        """The state of one status report (`?` only, no line sent), or None when none comes."""
        try:
            return self.query_status(timeout=min(0.5, self.banner_timeout))["state"]
        except DeviceLost:
            if self._lost is not None:
                raise
            return None

    def _reset(self):
        """Wake bytes, soft reset, wait for the GRBL 1.1 banner."""
        self._banner_event.clear()
        self._write(b"\r\n\r\n")
        time.sleep(0.05)
        self._write(b"\x18")
        self.reset_sent = True
        if not self._banner_event.wait(self.banner_timeout):
            if self._lost is not None:
                raise self._lost_error()
            heard = "; ".join(clip(u, 40) for u in self.unknown[-3:]) or "nothing"
            raise NotGrblError(
                f"device on {self.port} did not answer like GRBL: no \"Grbl 1.1 ['$' for help]\" banner within "
                f"{self.banner_timeout:g} s after a soft reset (heard: {heard})"
            )
        m = BANNER_RE.match(self.banner)
        if (int(m.group(1)), int(m.group(2))) != (1, 1):
            raise NotGrblError(f"device on {self.port} is {clip(self.banner, 40)!r}; this streamer speaks GRBL 1.1")
        self._drain()  # oks to the wake newlines, the banner itself

    def connect(self, *, home: bool = False, unlock: bool = False):
        """Recognise GRBL 1.1, home or handle Alarm, read the work offsets (`$#`), parser state
        (`$G`) and settings (`$$`).

        A controller whose status report says `Idle` is not reset (a reset would clear its `G92`
        offset, which the caller must see to refuse); any other state, or no report, gets a soft
        reset and must answer with the GRBL 1.1 banner. `$I` must report version 1.1. With `home`
        the homing cycle `$H` runs whatever the state; otherwise an Alarm is cleared with `$X`
        when `unlock` is set.

        **Raises:** `NotGrblError` (nothing but `?`, wake bytes and a reset was sent),
        `AlarmLocked` when in Alarm and neither `home` nor `unlock` is set, `GrblError` when `$H`
        or `$X` is refused.
        """
        time.sleep(0.05)
        self._drain()  # stale replies to an earlier session
        if self._probe() != "Idle":
            self._reset()
        self.messages.clear()
        sent_at = self._n_msgs
        r = self.command("$I")
        if r.kind == "error" and not self.reset_sent:  # a partial line left by an earlier host ate it
            self.messages.clear()
            r = self.command("$I")
        for _ in range(self.rx_size):  # `ok`s owed to an earlier host's lines (a dwell, found Idle)
            if r.kind != "ok" or r.msgs > sent_at:  # $I's own `ok` follows its `[VER:..]`
                break
            try:
                r = self._next(self.banner_timeout)  # $I's own answer follows them
            except DeviceLost:
                if self._lost is not None:
                    raise
                break
        if r.kind != "ok":
            raise NotGrblError(f"device on {self.port} answered $I with {clip(r.text, 40)!r}")
        for msg in self.messages:
            if msg.startswith("[VER:"):
                self.version = msg[5:-1]
            if msg.startswith("[OPT:"):
                parts = msg[5:-1].split(",")
                self.options = parts[0]
                if len(parts) >= 3 and parts[2].isdigit():
                    self.rx_size = int(parts[2])
        if self.version is None:
            raise NotGrblError(f"device on {self.port} gave no [VER:...] to $I")
        if not self.version.startswith("1.1"):
            raise NotGrblError(f"device on {self.port} is GRBL {clip(self.version, 30)}; this streamer speaks GRBL 1.1")
        self._polling.set()
        st = self.query_status()
        self.state_at_connect = st["state"]
        if home:  # in any state: the caller asks for a known machine position
            self.homing_tried = True
            r = self.command("$H", timeout=120.0)
            if r.kind != "ok":
                hint = " (homing is not enabled: $22=0)" if r.text == "error:5" else ""
                raise GrblError(f"the homing cycle $H was answered {clip(r.text, 40)}{hint}; run "
                                "again without --home (a job resumed after its position was lost: "
                                "re-zero the board, G10 L20 P1 X0 Y0 Z0, and pass --rezeroed)")
            self.homed = True
        elif st["state"].startswith("Alarm"):
            if not unlock:
                raise AlarmLocked(
                    f"controller on {self.port} is in Alarm state (position may be lost); pass --home to "
                    "run the homing cycle ($H) or --unlock to clear the lock ($X), then run again"
                )
            self.unlocked = True
            r = self.command("$X")
            if r.kind != "ok":
                raise GrblError(f"could not leave Alarm: {clip(r.text, 40)}")
        self.read_offsets()
        self.read_settings()
        return self

    def read_settings(self) -> dict:
        """Send `$$`; fills `settings` (number -> value, e.g. `{20: 1.0, 130: 300.0}`) and returns
        it. A controller that refuses `$$` leaves it empty: the settings only inform checks."""
        self.settings.clear()
        r = self.command("$$")
        if r.kind != "ok":
            self.settings.clear()
        return self.settings

    def read_offsets(self) -> dict:
        """Send `$#` and `$G`; fills `offsets` and `modes` and returns the offsets."""
        self.messages.clear()
        r = self.command("$#")
        if r.kind != "ok":
            raise NotGrblError(f"device on {self.port} answered $# with {clip(r.text, 40)!r}")
        offsets = {}
        for msg in self.messages:
            m = OFFSET_RE.fullmatch(msg)
            if m:
                offsets[m.group(1)] = tuple(float(v) for v in m.group(2).split(","))
        self.messages.clear()
        r = self.command("$G")
        modes = next((m[4:-1].split() for m in self.messages if m.startswith("[GC:")), [])
        if r.kind != "ok" or not modes or "G92" not in offsets:
            raise NotGrblError(f"device on {self.port} did not report its work offsets ($#) and parser state ($G)")
        self.offsets, self.modes = offsets, modes
        return offsets

    def stream(self, items: Sequence[str], *, barrier: Sequence[bool] | None = None,
               counting: bool = False, on_ok: Callable[[int], None] | None = None):
        """Send lines, in order, each answered before the stream moves on.

        Send-and-wait by default; with `counting` the bytes of unanswered lines stay within
        `rx_size - 1`. A line with `barrier[i]` is only sent once every earlier line has been
        answered `ok` (the caller puts barriers before plunges and after sync points, so that an
        `error` can never let a later scratch run).

        An `ok` is taken for the oldest unanswered line, so an `ok` that answers no line (noise)
        would shift every later answer one line early. It is ignored when it came before that
        line was written, or when it is taken for a dwell (`G4`, the only line unanswered, as
        after a barrier) while a status report sent after it says the machine is still moving:
        so a dwell is only ever confirmed once the motion before it is over.

        Watchdog: when lines are owed an answer and every status report for `idle_timeout` s (plus
        the `P` seconds of owed `G4` dwells) has said `Idle`, the answer was lost: `Stalled`; a
        status report that says `Alarm` is an alarm whose `ALARM:N` line was lost: `JobFault`.

        **Arguments:** `items` G-code lines (no comments, no line endings); `barrier` per item;
        `counting` character counting; `on_ok(i)` called for each `ok`, in order.

        **Raises:** `JobFault` on `error:N`, `ALARM:N` or an unexpected reset;
        `Stalled`; `DeviceLost`; `KeyboardInterrupt` passes through (the caller
        holds and retracts).
        """
        cap = self.rx_size - 1
        pending: deque = deque()  # (index, bytes, dwell seconds)
        used = 0
        i = 0
        settled = 0  # the first line sent since every earlier line was answered
        n = len(items)
        progress = time.monotonic()  # last send or answer
        while i < n or pending:
            while i < n:
                data = (items[i] + "\n").encode("ascii")
                if len(data) > cap:
                    raise GrblError(f"line {clip(items[i])!r} is longer than the controller's buffer")
                if pending and (not counting or used + len(data) > cap or (barrier is not None and barrier[i])):
                    break
                before = self._seq
                self._write(data)
                self.lines_sent.append(items[i])
                m = _DWELL_RE.search(items[i])
                pending.append((i, len(data), float(m.group(1)) if m else 0.0, before, bool(m)))
                used += len(data)
                i += 1
                progress = time.monotonic()
            limit = self.idle_timeout + sum(p[2] for p in pending)
            r = self._next(idle_limit=limit, since=progress)
            idx = pending[0][0]
            if r.kind == "ok" and r.seq <= pending[0][3]:
                self._stray(f"it came before {clip(items[idx], 40)!r} was sent")
                continue
            if (r.kind == "ok" and pending[0][4] and len(pending) == 1
                    and self._state_after(r.seq).startswith(_MOVING)):
                self._stray(f"the controller was still moving when it came for "
                            f"{clip(items[idx], 40)!r}, a dwell")
                continue
            if r.kind == "ok":
                _, size, *_ = pending.popleft()
                used -= size
                settled = settled if pending else i
                progress = time.monotonic()
                if on_ok is not None:
                    on_ok(idx)
            elif r.kind == "error":
                raise JobFault(f"error:{r.code} ({ERROR_TEXT.get(r.code, 'see GRBL error codes')})", idx, r.text)
            elif r.kind == "alarm" and r.code is None:
                raise JobFault("the controller reports Alarm (its ALARM:N line was lost)", idx,
                               r.text)
            elif r.kind == "alarm":
                raise JobFault(f"ALARM:{r.code} ({ALARM_TEXT.get(r.code, 'see GRBL alarm codes')})", idx, r.text)
            elif r.kind == "stall" and counting and pending[-1][0] > settled:
                # The 'ok's answer lines in order, so a lost one is taken for the next line's:
                # any of the lines since the stream last settled may be the one not answered.
                last = pending[-1][0]
                what = (f"one of the {last - settled + 1} lines from "
                        f"{clip(items[settled], 40)!r} to {clip(items[last], 40)!r}")
                raise Stalled(f"controller on {self.port} reports Idle but has not answered {what} "
                              f"for {limit:g} s (a lost 'ok'; character counting cannot tell "
                              "which)", settled, r.text)
            elif r.kind == "stall":
                raise Stalled(f"controller on {self.port} reports Idle but has not answered "
                              f"{clip(items[idx], 40)!r} for {limit:g} s (a lost 'ok')", idx,
                              r.text)
            else:
                raise JobFault("controller reset unexpectedly (banner mid-job)", idx, r.text)

    def wait_state(self, accept: Callable[[str], bool], timeout: float) -> str:
        """Poll status until `accept(state)` or `timeout` s; returns the last state."""
        t_end = time.monotonic() + timeout
        state = ""
        while time.monotonic() < t_end:
            state = self.query_status()["state"]
            if accept(state):
                return state
            time.sleep(0.01)
        return state

    def hold_and_retract(self, safe_z_mm: float, *, coord: str = "G54", timeout: float = 10.0) -> str:
        """Feed hold, wait until stopped, soft reset (flushes buffers; no alarm when stopped), retract.

        The retract goes to `Z = safe_z_mm` in work system `coord` (the job's), in mm, absolute.

        **Returns:** a short description of what was done (for the report).
        """
        self.realtime(b"!")
        state = self.wait_state(lambda s: s in ("Hold:0", "Idle") or s.startswith("Alarm"), timeout)
        if state.startswith("Alarm"):
            return "controller in Alarm: no retract sent (clear the alarm, then --resume)"
        self._banner_event.clear()
        self.realtime(b"\x18")
        if not self._banner_event.wait(timeout):
            raise DeviceLost(f"no banner from {self.port} after the soft reset")
        self._drain()
        if self.query_status()["state"].startswith("Alarm"):
            return "controller in Alarm after reset: no retract sent"
        z = gword("Z", safe_z_mm)
        for line in (f"G21 G90 {coord}", f"G0 {z}", "G4 P0.000"):
            r = self.command(line, timeout=60.0)
            if r.kind != "ok":
                return f"retract refused: {line!r} -> {clip(r.text, 40)}"
        return f"held, reset and retracted to {z}"

    def check_mode(self, items: Sequence[str], *, counting: bool = False):
        """Run `items` through GRBL's `$C` check mode (parsed, not moved), then leave check mode.

        **Raises:** `JobFault` at the first `error:N` (check mode is left first).
        """
        r = self.command("$C")
        if r.kind != "ok" or not any("Enabled" in m for m in self.messages[-3:]):
            raise GrblError(f"could not enter check mode: {clip(r.text, 40)}")
        fault = None
        try:
            self.stream(items, counting=counting)
        except JobFault as exc:
            fault = exc
        self._banner_event.clear()
        self.command("$C")
        if not self._banner_event.wait(self.banner_timeout):
            raise DeviceLost("no banner after leaving check mode")
        self._drain()
        if fault is not None:
            raise fault
