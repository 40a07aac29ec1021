"""The carve journal: an append-only, fsynced record of the scratches a carving job has confirmed
cut, keyed to its G-code's SHA-256, so that a stopped job resumes exactly where it stopped
(`jscratch.carve` writes it, `jscratch.fabricate` reads it). No serial I/O here.
"""

from __future__ import annotations

import hashlib
import json
import os
import time

from jscratch.errors import CarveError

__all__ = ["Journal", "JournalError", "sha256_file"]


def sha256_file(path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class JournalError(CarveError):
    """A journal that does not belong to this G-code, or cannot be continued (a `CarveError`)."""


class Journal:
    """Append-only record of scratches confirmed carved, keyed to the G-code's SHA-256.

    One JSON object per line: a `header` (`gcode_sha256`, `n_scratches`, `work_zero`), then `done`
    records (`k` the position in the cutting order, `scratch` the design index) and `event` records
    (a `start` event per session, with its `work_zero`). Each record is flushed and fsynced before
    the call returns. A torn last line (power lost mid-write) is ignored on reading and cut off
    before a resumed session appends (recorded as a `repaired` event). The carver
    creates a journal only once motion is about to be sent.

    **Arguments:** `path`; `gcode_sha256`; `n_scratches`; `resume`: continue an existing journal
    (it must exist and match); otherwise there must be no journal, or only a header, whole or
    torn (a leftover of a session that never started: it is replaced); `header`: extra header
    fields.
    """

    def __init__(self, path, gcode_sha256: str, n_scratches: int, *, resume: bool, header: dict | None = None):
        self.path = os.fspath(path)
        self.done = self.check(self.path, gcode_sha256, resume=resume)["done"]
        torn = self._end_last_record() if resume else 0
        self._f = open(self.path, "a" if resume else "w", encoding="utf-8")
        if torn:
            self.event("repaired", dropped_bytes=torn)
        if not resume:
            self._append({"type": "header", "gcode_sha256": gcode_sha256, "n_scratches": int(n_scratches),
                          "time": time.time(), **(header or {})})

    @classmethod
    def check(cls, path, gcode_sha256: str, *, resume: bool) -> dict:
        """Whether a session may start (before anything is sent); raises `JournalError` if not.

        **Returns:** dict with `done` (scratches journalled), `n_scratches`, `work_zero` (that of
        the latest session, or None) and, on `resume`, `position_lost` (how the latest session lost
        the machine's position, or None).
        """
        path = os.fspath(path)
        exists = os.path.exists(path) and os.path.getsize(path) > 0
        if exists and cls.torn_header(path):
            if resume:
                raise JournalError(
                    f"--resume: journal {path!r} holds only a torn header (the power was lost as "
                    "the job started, before any scratch was carved): run the same command "
                    "without --resume to start the job; it replaces the journal")
            exists = False  # nothing was carved: replaced, as a header-only journal is
        if not exists:
            if resume:
                raise JournalError(f"--resume: journal {path!r} does not exist; nothing to resume")
            return {"done": 0, "n_scratches": None, "work_zero": None, "position_lost": None}
        recs = cls.records(path)
        header, done = recs[0], cls._count(path, recs)
        starts = [r for r in recs if r.get("type") == "event" and r.get("event") == "start"]
        if resume and header.get("gcode_sha256") != gcode_sha256:
            raise JournalError(
                f"journal {path!r} belongs to G-code {str(header.get('gcode_sha256', '?'))[:12]}..., not to "
                f"this G-code ({gcode_sha256[:12]}...); refusing to resume a different job"
            )
        if not resume and (starts or done):
            raise JournalError(
                f"journal {path!r} already exists ({done} of {header.get('n_scratches', '?')} scratches done); "
                "pass --resume to continue that job, or move the journal away to start again"
            )
        zero = next((r["work_zero"] for r in reversed(starts) if r.get("work_zero")), header.get("work_zero"))
        return {"done": done if resume else 0, "n_scratches": header.get("n_scratches"),
                "work_zero": zero, "position_lost": cls._position_lost(recs) if resume else None}

    @staticmethod
    def _position_lost(recs) -> str | None:
        """How the latest session lost the machine's position (a lost device, an alarm, a reset of
        the controller), or None: the events after its `start`."""
        last = max((i for i, r in enumerate(recs) if r.get("event") == "start"), default=0)
        for r in recs[last + 1:]:
            reply = str(r.get("reply", ""))
            if r.get("event") == "lost":
                return "a lost device"
            if r.get("event") == "alarm":
                return "an alarm"
            if r.get("event") == "reset":
                return "a soft reset on a second interrupt"
            if r.get("event") == "restarted":
                return "a restart of the controller"
            if r.get("event") == "fault" and reply.startswith("ALARM"):
                return reply
            if r.get("event") == "fault" and reply.startswith("Grbl"):
                return "a reset of the controller"
        return None

    @staticmethod
    def torn_header(path) -> bool:
        """Whether the journal holds nothing but a torn header record (the power was lost while
        the carver wrote it, just before the first motion): nothing was carved."""
        try:
            with open(path, "rb") as f:
                data = f.read(1 << 16)
        except OSError:
            return False
        start = b'{"type": "header"'  # how the carver's header begins (`json.dumps`)
        data = data.rstrip(b"\0")  # (a power cut can leave a file's last block as zeros)
        if b"\n" in data or not (data.startswith(start) or start.startswith(data)):
            return False  # a whole record ends with its newline
        try:
            json.loads(data)
        except ValueError:  # json.JSONDecodeError, UnicodeDecodeError
            return True
        return False

    @staticmethod
    def records(path) -> list:
        """All records of a journal (a torn final line dropped); the first is the header."""
        try:
            with open(path, encoding="utf-8") as f:
                lines = f.read().split("\n")
        except UnicodeDecodeError:
            raise JournalError(f"journal {path!r} is not a jscratch journal (not UTF-8 text)") from None
        recs = []
        for n, line in enumerate(lines):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                if not isinstance(rec, dict):
                    raise ValueError("not a JSON object")
                recs.append(rec)
            except ValueError:  # json.JSONDecodeError, or a record that is not an object
                if any(x.strip() for x in lines[n + 1:]):
                    raise JournalError(f"journal {path!r}: line {n + 1} is corrupt") from None
                break  # torn final record
        if not recs or recs[0].get("type") != "header":
            raise JournalError(f"journal {path!r} has no header record")
        return recs

    @staticmethod
    def _count(path, recs) -> int:
        done = 0
        for r in recs[1:]:
            if r.get("type") == "done":
                if r.get("k") != done:
                    raise JournalError(f"journal {path!r}: done record k={r.get('k')} out of order (expected {done})")
                done += 1
        return done

    @classmethod
    def read(cls, path):
        """Parse a journal: returns `(header dict, number of consecutive done records from k = 0)`."""
        recs = cls.records(path)
        return recs[0], cls._count(path, recs)

    def _end_last_record(self) -> int:
        """Before appending to a journal: a final record that a power cut left without its newline
        is ended with one if it is whole (`records` counted it), or cut off if torn (`records`
        ignored it), so that the next record starts a line of its own.

        **Returns:** the number of torn bytes removed (0 if none).
        """
        with open(self.path, "rb+") as f:
            data = f.read()
            if not data or data.endswith(b"\n"):
                return 0
            start = data.rfind(b"\n") + 1
            try:
                whole = isinstance(json.loads(data[start:].decode("utf-8")), dict)
            except ValueError:  # json.JSONDecodeError, UnicodeDecodeError
                whole = False
            if whole:
                f.write(b"\n")
            else:
                f.truncate(start)
            f.flush()
            os.fsync(f.fileno())
            return 0 if whole else len(data) - start

    def _append(self, rec):
        self._f.write(json.dumps(rec) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())

    def confirm(self, k: int, scratch: int):
        """Record that order position `k` (design scratch `scratch`) is carved."""
        if k != self.done:
            raise JournalError(f"confirming scratch position {k} but {self.done} is next")
        self._append({"type": "done", "k": int(k), "scratch": int(scratch), "time": time.time()})
        self.done += 1

    def event(self, kind: str, **info):
        """Record a session event (start, fault, interrupt)."""
        self._append({"type": "event", "event": kind, "time": time.time(), **info})

    def close(self):
        try:
            self._f.close()
        except OSError:  # (a full disk: every record that returned is already fsynced)
            pass
