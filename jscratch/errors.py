"""One-line errors from loaders: `error_line` turns a reader's exception (imageio, numpy, ...)
into the one line a loader appends to its own message naming the file.

Imports: nothing from jscratch.
"""

from __future__ import annotations

__all__ = ["error_line"]


def error_line(exc: BaseException, limit: int = 160) -> str:
    """The first line of an exception's message (at most `limit` characters), with its type: what
    a loader puts in its own one-line error (readers such as imageio add lines of advice)."""
    lines = str(exc).strip().splitlines()
    text = lines[0].strip() if lines else ""
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
