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

Each message is one line. The command-line tools print it as ``error: ...`` (`report`) and exit
with `exit_status` (`EXIT_STATUS_HELP`), without a traceback.

Imports: nothing from jscratch.
"""

from __future__ import annotations

__all__ = [
    "CarveError",
    "DesignFileError",
    "InputError",
    "JscratchError",
    "EXIT_STATUS_HELP",
    "NonFiniteError",
    "error_line",
    "real_number",
    "whole_number",
    "shown",
    "count_arg",
    "instance_arg",
    "shape_arg",
    "float64_arg",
    "exit_status",
    "report",
]

#: The exit statuses of the command-line tools, as their ``--help`` states them.
EXIT_STATUS_HELP = ("exit status: 0 done; 1 a file could not be written or memory ran out "
                    "(operating-system error); "
                    "2 refused input (option, file or design; nothing is written); 3 a non-finite "
                    "value; 4 carving or the device stopped; 130 interrupted (Ctrl-C).")


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


def exit_status(exc: BaseException) -> int:
    """The command-line exit status of an error (`EXIT_STATUS_HELP`): 2 `InputError`, 3
    `NonFiniteError`, 4 `CarveError`, 1 an `OSError` or any other `JscratchError`."""
    if isinstance(exc, InputError):
        return 2
    if isinstance(exc, NonFiniteError):
        return 3
    if isinstance(exc, CarveError):
        return 4
    return 1


def report(exc: BaseException, stream=None, *, then: str = "") -> int:
    """Print ``error: <message>`` as one line to `stream` (default stderr), `then` appended;
    return `exit_status`.

    An `OSError` is reported by its reason and file name (``error: Permission denied: 'out/x'``)."""
    import sys

    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror + (f": {exc.filename!r}" if exc.filename is not None else "")
    else:
        text = str(exc)
    text = " ".join(text.split()) or type(exc).__name__
    print(f"error: {text}{then}", file=sys.stderr if stream is None else stream)
    return exit_status(exc)


def real_number(value) -> float | None:
    """`value` as a float when it is one real number: a Python or numpy scalar, or a 0-d array
    (numpy or a concrete JAX array); None for anything else (None, a bool, a string, an array of
    several values, a traced value). The argument checks read numbers with it, then test the
    range themselves."""
    import numpy as np

    if value is None or isinstance(value, (bool, str, bytes)):
        return None
    try:
        return float(value) if np.ndim(value) == 0 else None
    except (TypeError, ValueError):  # (a tracer's concretization error is a TypeError)
        return None


def whole_number(value) -> int | None:
    """`value` as an int when it is a Python or numpy integer (not a bool); None otherwise. The
    argument checks read counts with it, then test the range themselves."""
    import numpy as np

    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        return None
    return int(value)


def count_arg(where: str, name: str, value, low: int) -> int:
    """`value` as an int ``>= low`` (`whole_number`); `InputError` naming `where` and `name`,
    one line, otherwise."""
    n = whole_number(value)
    if n is None or n < low:
        raise InputError(f"{where}: `{name}` must be an int >= {low}, got {shown(value)}")
    return n


def instance_arg(where: str, name: str, value, kind: type) -> None:
    """`InputError` naming `where` and `name`, one line, unless `value` is a `kind` (a jscratch
    class such as `Board`: the message calls it ``jscratch.<kind>``)."""
    if not isinstance(value, kind):
        raise InputError(f"{where}: `{name}` must be a jscratch.{kind.__name__}, got "
                         f"{type(value).__name__}")


def float64_arg(where: str, name: str, value, what: str):
    """`value` as a float64 numpy array; `InputError` naming `where` and `name`, one line, for
    what is no array of numbers (`what`: what it must be, e.g. ``"an (N, 2) array of numbers"``)."""
    import numpy as np

    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: `{name}` must be {what}, got {shown(value)}") from None


def shape_arg(where: str, name: str, value, *shapes: tuple, what: str = "") -> None:
    """`InputError` naming `where` and `name`, one line, unless `value` (an array, a tracer, a
    nested list or a number) has one of `shapes`. In a shape a string (``"N"``) matches any
    length and a leading ``...`` any leading axes; `what` (e.g. ``" (views, pixels)"``) follows
    the shapes in the message. Shapes are static, so this works under `jax.jit` too."""
    import numpy as np

    def text(shape):
        axes = ["..." if s is Ellipsis else str(s) for s in shape]
        return "(" + ", ".join(axes) + ("," if len(axes) == 1 else "") + ")"

    def fits(got, shape):
        if shape[:1] == (Ellipsis,):
            shape = shape[1:]
            got = got[len(got) - len(shape):] if len(got) >= len(shape) else None
        return got is not None and len(got) == len(shape) and all(
            isinstance(s, str) or s == g for s, g in zip(shape, got))

    try:
        got = None if isinstance(value, (str, bytes)) else tuple(np.shape(value))
    except (TypeError, ValueError):  # (a ragged nested list)
        got = None
    if got is None or not any(fits(got, tuple(s)) for s in shapes):
        texts = [text(tuple(s)) for s in shapes]
        expected = " or ".join([", ".join(texts[:-1]), texts[-1]] if texts[1:] else texts)
        seen = f"shape {text(got)}" if got is not None else shown(value)
        raise InputError(f"{where}: `{name}` must have shape {expected}{what}, got {seen}")


def shown(value, limit: int = 60) -> str:
    """``repr(value)`` on one line and at most `limit` characters, for a one-line message."""
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."
