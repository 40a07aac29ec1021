"""The error family of jscratch, and `error_line` for loaders.

Every refusal that a user can meet is a `JscratchError`, so one ``except jscratch.JscratchError``
in a notebook catches "jscratch refused this"; the kinds beneath it say what was refused:

- `InputError` (also a `ValueError`): a bad argument, option, config field, image or scene (wrong
  shape, NaN, out of range, off the board). The message names the argument and what is accepted.
- `DesignFileError` (an `InputError`): a design file, checkpoint, config file or G-code file that
  is missing, unreadable or breaks the file format (`docs/model.md` §9).
- `NonFiniteError` (also a `RuntimeError`): the optimisation produced a NaN or an infinity; the
  last good state is kept.
- `CarveError` (also a `RuntimeError`): carving or the device stopped (serial port, controller
  fault, journal); the message says where and how to resume.

Each message is one line. The command-line tools print it as ``error: ...`` and exit non-zero
without a traceback.

Imports: nothing from jscratch.
"""

from __future__ import annotations

__all__ = [
    "CarveError",
    "DesignFileError",
    "InputError",
    "JscratchError",
    "NonFiniteError",
    "error_line",
]


class JscratchError(Exception):
    """Base of every error jscratch raises on purpose (a one-line message)."""


class InputError(JscratchError, ValueError):
    """A bad argument, option, config field, image or scene; the message names it and the
    accepted values."""


class DesignFileError(InputError):
    """A design file, checkpoint, config file or program file that is missing, unreadable or
    breaks its format; the message names the file (and the array or line)."""


class NonFiniteError(JscratchError, RuntimeError):
    """The loss, a gradient or a parameter became NaN or infinite during the optimisation."""


class CarveError(JscratchError, RuntimeError):
    """Carving or the carving device stopped (port, controller fault, journal, interrupt); the
    message says where and how to resume."""


def error_line(exc: BaseException, limit: int = 160) -> str:
    """The first line of an exception's message (at most `limit` characters), with its type: what
    a loader puts in its own one-line error (readers such as imageio add lines of advice)."""
    lines = str(exc).strip().splitlines()
    text = lines[0].strip() if lines else ""
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
