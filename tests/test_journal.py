"""Tests of jscratch.journal: the SHA-256 of a file against hashlib on its bytes; a journal written,
read back and resumed; the rules of starting and resuming (wrong G-code, existing job, missing
journal, a header-only leftover replaced); a torn last line ignored and a corrupt middle line
refused; confirmations only in order; the latest session's work zero."""

import hashlib
import json

import pytest

from jscratch.journal import Journal, JournalError, sha256_file


def test_sha256_file(tmp_path):
    path = tmp_path / "f.bin"
    data = bytes(range(256)) * 9000  # more than one 1 MiB read
    path.write_bytes(data)
    assert sha256_file(path) == hashlib.sha256(data).hexdigest()


def test_write_read_resume_and_work_zero(tmp_path):
    path = tmp_path / "job.journal"
    j = Journal(path, "a" * 64, 5, resume=False, header={"work_zero": [1.0, 2.0, 0.0]})
    j.event("start", work_zero=[1.0, 2.0, 0.0])
    for k, s in enumerate((4, 0, 2)):
        j.confirm(k, s)
    with pytest.raises(JournalError, match="confirming scratch position 4 but 3 is next"):
        j.confirm(4, 1)
    j.close()
    header, done = Journal.read(path)
    assert header["gcode_sha256"] == "a" * 64 and header["n_scratches"] == 5 and done == 3
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    assert [r["scratch"] for r in recs if r["type"] == "done"] == [4, 0, 2]
    # resuming continues the count and appends; the latest session's work zero wins
    j = Journal(path, "a" * 64, 5, resume=True)
    assert j.done == 3
    j.event("start", work_zero=[5.0, 6.0, 0.0])
    j.confirm(3, 1)
    j.close()
    info = Journal.check(path, "a" * 64, resume=True)
    assert info == {"done": 4, "n_scratches": 5, "work_zero": [5.0, 6.0, 0.0],
                    "position_lost": None}


@pytest.mark.parametrize("events, lost", [
    ([("fault", "error:33")], None),  # held and retracted: the position is kept
    ([("interrupt", None)], None),
    ([("fault", "ALARM:1")], "ALARM:1"),
    ([("fault", "Grbl 1.1h ['$' for help]")], "a reset of the controller"),
    ([("lost", None)], "a lost device"),
    ([("fault", "error:9"), ("alarm", None)], "an alarm"),  # the retract found it in Alarm
    ([("lost", None), ("start", None), ("fault", "error:33")], None),  # a later session ran
])
def test_a_session_that_lost_the_position_is_reported_on_resume(tmp_path, events, lost):
    path = tmp_path / "job.journal"
    j = Journal(path, "a" * 64, 5, resume=False)
    j.event("start")
    j.confirm(0, 3)
    for kind, reply in events:
        j.event(kind, **({"reply": reply} if reply else {}))
    j.close()
    assert Journal.check(path, "a" * 64, resume=True)["position_lost"] == lost


def test_start_and_resume_rules(tmp_path):
    path = tmp_path / "job.journal"
    with pytest.raises(JournalError, match="does not exist; nothing to resume"):
        Journal.check(path, "a" * 64, resume=True)
    assert Journal.check(path, "a" * 64, resume=False)["done"] == 0
    # a header-only leftover (a session that never started) does not block a new job
    Journal(path, "b" * 64, 5, resume=False).close()
    Journal(path, "a" * 64, 5, resume=False).close()
    assert Journal.read(path)[0]["gcode_sha256"] == "a" * 64
    j = Journal(path, "a" * 64, 5, resume=True)
    j.event("start")
    j.close()
    with pytest.raises(JournalError, match="already exists .*pass --resume"):
        Journal(path, "a" * 64, 5, resume=False)
    with pytest.raises(JournalError, match="belongs to G-code aaaaaaaaaaaa.*refusing to resume"):
        Journal(path, "c" * 64, 5, resume=True)


def test_torn_last_line_ignored_corrupt_line_refused(tmp_path):
    path = tmp_path / "job.journal"
    j = Journal(path, "a" * 64, 3, resume=False)
    j.confirm(0, 2)
    j.close()
    with open(path, "a") as f:
        f.write('{"type": "done", "k": 1, "scr')  # power lost mid-write
    assert Journal.read(path)[1] == 1
    intact = path.read_text()
    # A resumed session cuts the torn record off before it appends, so the journal stays readable
    # for every later session; a whole record that only lost its newline is kept and ended.
    for _ in range(2):
        j = Journal(path, "a" * 64, 3, resume=True)
        j.confirm(j.done, 7)
        j.close()
        with open(path, "a") as f:
            f.write(json.dumps({"type": "event", "event": "fault", "done": j.done}))  # no newline
    recs = Journal.records(path)
    assert Journal.read(path)[1] == 3 and recs[-1]["event"] == "fault"
    assert [r.get("event") for r in recs if r["type"] == "event"] == ["repaired", "fault", "fault"]
    repaired = next(r for r in recs if r.get("event") == "repaired")
    assert repaired["dropped_bytes"] == len('{"type": "done", "k": 1, "scr')
    j = Journal(path, "a" * 64, 3, resume=True)
    j.event("start")
    j.close()
    assert all(json.loads(x) for x in path.read_text().splitlines())
    path.write_text(intact)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], "{not json", lines[1]]) + "\n")
    with pytest.raises(JournalError, match="line 2 is corrupt"):
        Journal.read(path)
    path.write_text(json.dumps({"type": "done", "k": 0}) + "\n")
    with pytest.raises(JournalError, match="has no header record"):
        Journal.read(path)
    path.write_text("\n".join([lines[0], json.dumps({"type": "done", "k": 1, "scratch": 0})]) + "\n")
    with pytest.raises(JournalError, match=r"done record k=1 out of order \(expected 0\)"):
        Journal.read(path)
