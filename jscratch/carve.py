"""Carving: stream a G-code program written by `jscratch.fabricate` to a GRBL 1.1 controller over a
serial port, journalling every confirmed scratch so that a job survives a fault, a lost device or an
interrupt and resumes where it stopped (`carve`, `CarveError`). The journal is
`jscratch.journal`'s (`Journal`), the protocol `jscratch.grbl`'s (`Grbl`); see
`jscratch.fabricate`'s docstring for the program's roles and the work-zero rules.

Imports: `jscratch.grbl`, `jscratch.journal`, `jscratch.gcode` (the `Program` it reads).
"""

from __future__ import annotations

import os
import sys

from jscratch.errors import CarveError, DesignFileError, error_line
from jscratch.grbl import clip
from jscratch.gcode import Program, check_program_lines, read_program

__all__ = ["CarveError", "carve"]


# ----------------------------------------------------------------------------------------------
# Streaming with a journal.


def _strip(text: str) -> str:
    if "(" in text or ";" in text:
        out, depth = [], 0
        for ch in text:
            if ch == ";" and depth == 0:
                break
            if ch == "(":
                depth += 1
            elif ch == ")":
                depth -= 1
            elif depth == 0:
                out.append(ch)
        text = "".join(out)
    return text.strip()


def _program_setup(prog: Program, path) -> tuple:
    """The program's safe Z (the highest `G0 Z`, mm) and the work system its preamble selects (or None)."""
    zs, coord = [], None
    for text, role in zip(prog.lines, prog.role):
        words = _strip(text).split()
        if words[:1] == ["G0"]:
            zs += [float(w[1:]) for w in words if w[0] == "Z"]
        if role == "pre":
            coord = next((w for w in words if w in ("G54", "G55", "G56", "G57", "G58", "G59")), coord)
    if not zs:
        raise DesignFileError(f"G-code {clip(path, 60)!r} has no 'G0 Z' line (safe height): refusing to carve, "
                              "an emergency retract would not know where to go")
    return max(zs), coord


class _JournalFailed(Exception):
    """A scratch cut whose `done` record could not be written (`error` the `OSError`)."""

    def __init__(self, k: int, s: int, error: OSError):
        super().__init__(k, s, error)
        self.k, self.s, self.error = k, s, error


def _xyz(v) -> str:
    return " ".join(f"{a}{x:.3f}" for a, x in zip("XYZ", v))


def carve(gcode_path, port: str, *, baud: int = 115200, resume: bool = False, counting: bool = False,
          check: bool = False, home: bool = False, unlock: bool = False, rezeroed: bool = False,
          safe_z_mm: float | None = None, journal_path=None, quiet: bool = False, banner_timeout: float = 5.0,
          stall_timeout: float = 30.0, idle_timeout: float = 10.0, poll_interval: float = 0.25,
          on_scratch=None) -> dict:
    """Stream a G-code file (with its line map) to GRBL, journalling carved scratches.

    Before any motion: the G-code and map are read and checked (a bad program: `DesignFileError`,
    before any port is opened), the journal checked (none, or on
    `resume` matching the G-code's SHA-256), the port opened and GRBL 1.1 recognised (no reset
    when it reports `Idle`); an Alarm state stops the run unless `home` (`$H`, run in any state)
    or `unlock` (`$X`). A `resume` after a session that lost the position (a lost device, an alarm,
    a reset of the controller, or an Alarm cleared now with `unlock`) needs `home` or `rezeroed`.
    The work zero is checked (`$#`): no `G92` or tool length offset (GRBL clears both at reset),
    no controller that has just started without homing (machine position 0, 0, 0 and the work
    zero elsewhere: it no longer points at the board), and on `resume` the work
    system's offset equal to the one journalled (unless `rezeroed`). On a controller with homing
    on (`$22=1`), the program's extent plus the work zero is checked against the travel
    (`$130`-`$132`): refused when soft limits are on (`$20=1`: GRBL would stop the job part-way
    with ALARM:2), a warning on stderr otherwise. With
    `check`, the lines first run through GRBL's `$C` check mode. Only then is the journal written
    and the preamble and the scratches from the first unconfirmed one sent; each scratch is
    journalled when its `G4 P0.000` is answered `ok`.

    On `error:N`, a lost `ok` (no answer for `idle_timeout` s while the controller reports `Idle`)
    or Ctrl-C: feed hold, soft reset, retract to the program's safe Z. On `ALARM:N` or a lost
    device: stop. Each raises `CarveError` (one line; `KeyboardInterrupt` after Ctrl-C) naming
    the G-code line and scratch and how to resume.

    **Arguments:** `gcode_path`; `port`; `baud`; `resume`; `counting` (character counting instead of
    send-and-wait); `check`; `home`; `unlock`; `rezeroed` (accept a changed work zero on resume);
    `safe_z_mm` retract height, mm (default and lowest: the program's highest `G0 Z`);
    `journal_path` (default `gcode_path + '.journal'`); `quiet`; timeouts in seconds;
    `on_scratch(k, scratch)` called after each journalled scratch.

    **Returns:** dict with `done`, `total`, `sent_lines`.
    """
    from jscratch.grbl import DeviceLost, Grbl, GrblError, JobFault, Stalled
    from jscratch.journal import Journal, sha256_file

    prog = read_program(gcode_path)
    digest = sha256_file(gcode_path)
    n = prog.info["scratches"]
    journal_path = os.fspath(journal_path or os.fspath(gcode_path) + ".journal")
    retract_z, coord = _program_setup(prog, gcode_path)
    if safe_z_mm is not None:
        retract_z = max(retract_z, float(safe_z_mm))  # never retract below the program's travel height
    state = Journal.check(journal_path, digest, resume=resume)  # refuses before any port is opened
    k0 = state["done"]
    if k0 >= n:
        return {"done": n, "total": n, "sent_lines": 0}
    first = next((i for i, k in enumerate(prog.k.tolist()) if k >= 0), len(prog.lines))
    sel = [i for i, (k, r) in enumerate(zip(prog.k.tolist(), prog.role))
           if (r != "comment") and (i < first or k >= k0 or r == "post")]
    sel = [i for i in sel if _strip(prog.lines[i])]
    items = [_strip(prog.lines[i]) for i in sel]
    roles = [prog.role[i] for i in sel]
    barrier = [r == "plunge" or (j > 0 and roles[j - 1] == "sync") for j, r in enumerate(roles)]

    def say(msg):
        if not quiet:
            print(msg, file=sys.stderr)

    try:
        grbl = Grbl(port, baud, banner_timeout=banner_timeout, stall_timeout=stall_timeout,
                    idle_timeout=idle_timeout, poll_interval=poll_interval, log=say)
    except GrblError as exc:
        raise CarveError(f"{exc} (no motion was sent)") from None

    def untouched():
        if grbl.homing_tried:
            done = "ran" if grbl.homed else "was sent"
            return f"(the homing cycle $H {done}; no G-code line was sent)"
        return "(no motion was sent)"

    journal = bar = None
    try:
        try:
            grbl.connect(home=home, unlock=unlock)
        except GrblError as exc:
            raise CarveError(f"{exc} {untouched()}") from None
        lost = state["position_lost"] or ("an Alarm cleared with $X" if grbl.unlocked else None)
        if resume and lost and not (grbl.homed or rezeroed):
            raise CarveError(
                f"the machine position may be lost ({lost} since the job last ran): re-home "
                f"it (--home) or re-zero the board (G10 L20 P1 X0 Y0 Z0) and pass --rezeroed, "
                f"then run again with --resume {untouched()}")
        coord = coord or next((w for w in grbl.modes if w in ("G54", "G55", "G56", "G57", "G58", "G59")), "G54")
        zero = _check_work_zero(grbl, coord, state["work_zero"] if resume else None, rezeroed, untouched)
        _check_travel(grbl, items, retract_z, zero, coord, untouched,
                      lambda m: print(m, file=sys.stderr))  # a warning even when quiet
        if check:
            try:
                grbl.check_mode(items, counting=counting)
            except JobFault as exc:
                i = sel[exc.index] if exc.index >= 0 else -1
                raise CarveError(f"check mode ($C): {exc} at G-code line {i + 1}: {clip(prog.lines[i], 60)!r} "
                                 f"{untouched()}") from None
        # Motion is about to be sent: only now is the journal written.
        journal = Journal(journal_path, digest, n, resume=resume, header={"work_zero": {coord: zero}})
        journal.event("start", k=k0, port=port, counting=counting, work_zero={coord: zero})
        from tqdm.auto import tqdm

        bar = tqdm(total=n, initial=k0, unit="scratch", disable=quiet, desc="carving", dynamic_ncols=True)

        def on_ok(j):
            if roles[j] == "sync":
                i = sel[j]
                k, s = int(prog.k[i]), int(prog.scratch[i])
                try:
                    journal.confirm(k, s)
                except OSError as exc:
                    raise _JournalFailed(k, s, exc) from None
                bar.update(1)
                if on_scratch is not None:
                    on_scratch(k, s)

        def where(j):
            i = sel[j] if 0 <= j < len(sel) else -1
            k = int(prog.k[i]) if i >= 0 else -1
            what = f"scratch position {k} (design scratch {int(prog.scratch[i])})" if k >= 0 else "outside scratches"
            return i, f"G-code line {i + 1} {clip(prog.lines[i], 40)!r}, {what}" if i >= 0 else "no line"

        def retract():
            try:
                if _restarted(grbl, coord):  # a retract in its zero would go to the wrong place
                    return (f"; the controller has restarted (machine position 0, 0, 0, its "
                            f"{coord} zero elsewhere): position lost, no retract sent")
                return "; " + grbl.hold_and_retract(retract_z, coord=coord)
            except GrblError as e2:
                return f"; hold/retract failed: {clip(e2, 80)}"

        try:
            grbl.stream(items, barrier=barrier, counting=counting, on_ok=on_ok)
        except JobFault as exc:
            i, loc = where(exc.index)
            journal.event("fault", reply=exc.reply, line=i + 1, done=journal.done)
            if isinstance(exc, Stalled):
                action, advice = retract(), "check the machine, then run again with --resume"
            elif exc.reply.startswith("error"):
                action, advice = retract(), "fix the cause and run again with --resume"
            elif exc.reply.startswith("ALARM"):
                action = "; machine stopped by the controller, position likely lost"
                advice = "re-home (--home) or re-zero the board (G10 L20 P1, then --rezeroed), then run again with --resume"
            else:
                action = "; the controller reset itself, position may be lost"
                advice = "re-home (--home) or re-zero the board (G10 L20 P1, then --rezeroed), then run again with --resume"
            if "in Alarm" in action or "restarted" in action:  # the position is lost
                journal.event("alarm" if "in Alarm" in action else "restarted", done=journal.done)
                advice = ("re-home (--home) or re-zero the board (G10 L20 P1, then --rezeroed), "
                          "then run again with --resume")
            raise CarveError(f"{exc} at {loc}{action}. {journal.done} of {n} scratches are journalled; {advice}") from None
        except _JournalFailed as exc:  # stop: a scratch cut but not journalled is cut again
            raise CarveError(
                f"could not journal scratch position {exc.k} (design scratch {exc.s}), which was "
                f"cut, in {journal_path!r}: {error_line(exc.error)}{retract()}. {journal.done} of "
                f"{n} scratches are journalled; fix the journal's disk, then run again with "
                "--resume (it cuts that scratch again, in its own groove)") from None
        except DeviceLost as exc:
            journal.event("lost", error=clip(exc, 200), done=journal.done)
            raise CarveError(
                f"{exc}. {journal.done} of {n} scratches are journalled; reconnect, and if the controller was reset or "
                "power-cycled its position is lost: re-home it (--home) or re-zero the board (G10 L20 P1, then "
                "--rezeroed); then run again with --resume (the scratch in progress will be cut again)") from None
        except KeyboardInterrupt:
            journal.event("interrupt", done=journal.done)  # first: a second Ctrl-C keeps it
            try:
                msg = "interrupted" + retract().replace(";", ":", 1)
            except KeyboardInterrupt:  # a second Ctrl-C during the hold: stop now
                try:
                    grbl.realtime(b"\x18")  # soft reset: motion and spindle stop at once
                except Exception:  # noqa: BLE001 (the port may be gone: nothing more to send)
                    pass
                journal.event("reset", done=journal.done)
                msg = ("interrupted twice: soft reset sent, no retract (the position may be lost: "
                       "re-home (--home) or re-zero (--rezeroed) before --resume)")
            say(f"{msg}. {journal.done} of {n} scratches are journalled; run again with --resume")
            raise
        journal.event("finished", done=journal.done)
        return {"done": journal.done, "total": n, "sent_lines": len(grbl.lines_sent)}
    finally:
        if bar is not None:
            bar.close()
        grbl.close()
        if journal is not None:
            journal.close()


def _check_work_zero(grbl, coord: str, journalled: dict | None, rezeroed: bool, untouched) -> list:
    """Refuse offsets a reset would clear and, on resume, a work zero that changed; returns it (mm)."""
    inch = 25.4 if grbl.settings.get(13, 0) == 1 else 1.0  # `$#` reports inches when $13=1
    g92 = [inch * v for v in grbl.offsets["G92"]]
    tlo = [inch * v for v in grbl.offsets.get("TLO", (0.0,))]
    if any(abs(v) > 5e-4 for v in g92):
        raise CarveError(
            f"a G92 offset ({_xyz(g92)}) is active, and GRBL clears G92 at every reset, so the job would shift after "
            f"a fault or on resume; set the board zero with G10 L20 P1 X0 Y0 Z0 (kept in G54), clear G92 with G92.1, "
            f"and run again {untouched()}")
    if any(abs(v) > 5e-4 for v in tlo):
        raise CarveError(f"a tool length offset (TLO {tlo[0]:.3f}) is active, and GRBL clears it at every reset; "
                         f"cancel it with G49 and zero Z in G54 (G10 L20 P1 Z0), then run again {untouched()}")
    if coord not in grbl.offsets:
        raise CarveError(f"the controller did not report the {coord} offset ($#) {untouched()}")
    zero = [inch * float(v) for v in grbl.offsets[coord]]
    # With homing on ($22=1) GRBL starts locked in Alarm (unless built without that lock: `L`
    # among `$I`'s options): found unlocked and not unlocked now, it was homed since it started
    # (or unlocked by another sender), and a machine position of 0, 0, 0 is where homing leaves
    # it on firmware built with HOMING_FORCE_SET_ORIGIN (`Z`), or with no pull-off ($27=0);
    # elsewhere homing leaves it at -$27, and 0, 0, 0 says a restart.
    homed_before = (grbl.settings.get(22) == 1 and "L" not in grbl.options
                    and ("Z" in grbl.options or grbl.settings.get(27) == 0)
                    and not grbl.state_at_connect.startswith("Alarm") and not grbl.unlocked)
    if not (grbl.homed or homed_before) and any(abs(v) > 5e-4 for v in zero):
        # Started without homing (on opening the port, or before it): GRBL then counts machine
        # positions from wherever the tool stood, so a machine position of exactly 0, 0, 0 says
        # it has just started, and the zero stored in EEPROM no longer points at the board.
        mpos = _machine_position(grbl.query_status(), grbl.offsets, coord)
        if mpos is not None and all(abs(v) < 5e-4 for v in mpos):
            raise CarveError(
                f"the controller on {grbl.port} has just started without homing (machine position "
                f"0, 0, 0), so its {coord} zero ({_xyz(zero)}) no longer points at the board; many "
                f"Arduino-based boards restart when the port opens: home it (--home, with homing "
                f"enabled: $22=1), or stop the restart on open (stty -F {grbl.port} -hupcl), zero "
                f"the board again (G10 L20 P1 X0 Y0 Z0) and run again {untouched()}")
    old = (journalled or {}).get(coord)
    if old is not None and not rezeroed and max(abs(a - b) for a, b in zip(zero, old)) > 2e-3:
        raise CarveError(
            f"the {coord} work zero is {_xyz(zero)} (machine mm) but was {_xyz(old)} when this job last ran; "
            f"restore it with G10 L2 P{int(coord[1:]) - 53} {_xyz(old)}, or pass --rezeroed if you re-zeroed the same "
            f"board at its corner {untouched()}")
    return zero


def _travel(settings: dict, options: str) -> list:
    """Per axis, the `(lo, hi)` machine mm that GRBL 1.1's soft limits allow: `[-$13N, 0]`, or
    `[0, $13N]` for an axis homed towards its minimum (`$23`) when the firmware was built with
    HOMING_FORCE_SET_ORIGIN (`Z` among `$I`'s options); None where `$13N` is unknown or 0."""
    out = []
    for a in range(3):
        t = settings.get(130 + a, 0.0)
        if t <= 0:
            out.append(None)
        elif "Z" in options and int(settings.get(23, 0)) >> a & 1:
            out.append((0.0, t))
        else:
            out.append((-t, 0.0))
    return out


def _check_travel(grbl, items, retract_z: float, zero, coord: str, untouched, warn) -> None:
    """Refuse a program that leaves the machine's travel when GRBL's soft limits are on (`$20=1`:
    GRBL would stop the job part-way with ALARM:2); warn when only homing is on (`$22=1`: the
    travel settings `$130`-`$132` are then the machine's measure, but nothing enforces them)."""
    soft, homing = grbl.settings.get(20, 0) == 1, grbl.settings.get(22, 0) == 1
    if not (soft or homing):
        return  # without homing, machine coordinates count from wherever the machine started
    ext = check_program_lines(items)
    z = ext["z"] or [retract_z, retract_z]
    ext["z"] = [min(z[0], retract_z), max(z[1], retract_z)]
    for a, (name, limits) in enumerate(zip("XYZ", _travel(grbl.settings, grbl.options))):
        e = ext[name.lower()]
        if limits is None or e is None:
            continue
        lo, hi = e[0] + zero[a], e[1] + zero[a]
        if limits[0] - 1e-6 <= lo and hi <= limits[1] + 1e-6:
            continue
        what = (f"the program moves {name} from {lo:.3f} to {hi:.3f} mm in machine coordinates "
                f"(work {e[0]:.3f} to {e[1]:.3f} plus the {coord} zero {zero[a]:.3f}), outside the "
                f"machine's travel {limits[0]:.3f} to {limits[1]:.3f} "
                f"(${130 + a}={limits[1] - limits[0]:g})")
        if soft:
            raise CarveError(
                f"{what}: with soft limits on ($20=1) GRBL would stop the job part-way with "
                f"ALARM:2; zero the board where the whole program fits (G10 L20 P1 X0 Y0 Z0), or "
                f"write the program with a lower --safe-z, then run again {untouched()}")
        warn(f"warning: {what}; soft limits are off ($20=0), so nothing stops the tool at the "
             f"end of its travel: check ${130 + a} and the board's zero before the job reaches it")


def _restarted(grbl, coord: str) -> bool:
    """Whether the controller has restarted since `connect` without a banner that came through:
    its machine position is exactly 0, 0, 0 while the `coord` zero lies elsewhere."""
    mpos = _machine_position(grbl.query_status(), grbl.offsets, coord)
    return (mpos is not None and all(abs(v) < 5e-4 for v in mpos)
            and any(abs(v) > 5e-4 for v in grbl.offsets[coord]))


def _machine_position(status: dict, offsets: dict, coord: str) -> list | None:
    """The machine position (mm) of a status report: its `MPos`, or its `WPos` plus the work
    offsets (`coord`'s, `G92`, the tool length offset on Z); None when it has neither."""
    if "MPos" in status:
        return [float(v) for v in status["MPos"].split(",")]
    if "WPos" in status:
        wco = [a + b for a, b in zip(offsets[coord], offsets["G92"])]
        wco[2] += offsets.get("TLO", (0.0,))[0]
        return [float(v) + o for v, o in zip(status["WPos"].split(","), wco)]
    return None
