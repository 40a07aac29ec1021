"""Options declared once: a dataclass field carries its help, unit and command-line flag, and the
command line is generated from the dataclass.

- `option(default, help, ...)`: a `dataclasses.field` with that metadata.
- `add_arguments(parser, cls)`: one argparse flag per field of `cls` (nested option dataclasses
  flattened: their flags carry no prefix, and a clash is an error at generation time).
- `given(args, cls)`: the fields the user gave on the command line, as keyword arguments (nested
  ones as dicts), to lay over defaults or a config file (`overlay`).
- `flags(cls)`: field path -> flag, e.g. ``{"n_scratches": "--scratches", "loss.kind": "--loss"}``.
- `OneLineParser`: the argparse parser of every jscratch command (a refusal is one line);
  `check_out_prefix` refuses an output prefix no file can be written at; `signals_interrupt`:
  SIGTERM and SIGHUP stop a command's run as Ctrl-C does.

Types come from the annotations: ``int``, ``float``, ``str``, ``bool`` (``--x`` / ``--no-x``),
``X | None``, ``tuple[float, float]`` (two values) and ``tuple[str, ...]``; a field may instead name
a ``parse`` function (text -> value) for the flag. Argparse never fills defaults in: the defaults
live in the dataclass alone, so ``--help`` shows each default once, taken from the dataclass.

Imports: `jscratch.errors` only.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import signal
import threading
import types
import typing
from collections.abc import Callable
from typing import Any

from jscratch.errors import InputError

__all__ = ["option", "add_arguments", "given", "flags", "overlay", "field_help", "check_out_prefix",
           "OneLineParser", "KnownFields", "signals_interrupt"]

_NESTED = "nested"


class KnownFields:
    """Base of the option dataclasses (`DesignConfig`, `SceneConfig`, `LossConfig`): a keyword
    that names no field is refused in one line (``_unknown_error``, default `InputError`), as
    their ``from_dict`` refuses an unknown key, rather than with Python's ``TypeError``."""

    _unknown_error = InputError

    def __new__(cls, *args, **kwargs):
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(str(k) for k in set(kwargs) - names)
        if unknown:
            raise cls._unknown_error(f"{cls.__name__}: unknown fields {unknown} (known: "
                                     f"{', '.join(sorted(names))})")
        return super().__new__(cls)


def option(default: Any = dataclasses.MISSING, help: str = "", *, unit: str | None = None,
           flag: str | None = None, choices: tuple | None = None,
           parse: Callable[[str], Any] | None = None, metavar: str | None = None,
           default_factory: Callable[[], Any] | None = None, nested: bool = False,
           cli: bool = True) -> Any:
    """A dataclass field with its one-line `help`, `unit` (shown in brackets), command-line `flag`
    (default ``--field-name``), `choices`, a `parse` function for the flag's text, and `nested`
    (the field is itself an option dataclass whose fields become flags). ``cli=False`` keeps a
    field off the command line (only for values a flag cannot carry; `flags` lists the rest)."""
    meta = {"help": help, "unit": unit, "flag": flag, "choices": choices, "parse": parse,
            "metavar": metavar, _NESTED: nested, "cli": cli}
    if default_factory is not None:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return dataclasses.MISSING


def _fields(cls) -> list[tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls) if f.metadata.get("cli", True)]


def _strip_none(tp) -> tuple[Any, bool]:
    """``(T, optional)`` for ``T | None`` (or ``Optional[T]``), else ``(tp, False)``."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def flags(cls, prefix: str = "") -> dict[str, str]:
    """``{field path: flag}`` for every command-line field of `cls` (nested flattened)."""
    out: dict[str, str] = {}
    for f, tp in _fields(cls):
        if f.metadata.get(_NESTED):
            inner = flags(_strip_none(tp)[0], prefix + f.name + ".")
            clash = set(inner.values()) & set(out.values())
            if clash:
                raise TypeError(f"{cls.__name__}.{f.name}: flags {sorted(clash)} clash")
            out.update(inner)
            continue
        flag = f.metadata.get("flag") or "--" + f.name.replace("_", "-")
        if flag in out.values():
            raise TypeError(f"{cls.__name__}.{f.name}: flag {flag} clashes")
        out[prefix + f.name] = flag
    return out


def _fmt(v: Any) -> str:
    if isinstance(v, tuple):
        return " ".join(map(str, v)) if v else "(none)"
    if isinstance(v, dict):
        return "(given)"
    return str(v)


def field_help(f: dataclasses.Field, default: Any) -> str:
    """The help text of a field: its help, unit and default (once)."""
    text = f.metadata.get("help", "")
    unit = f.metadata.get("unit")
    if unit:
        text += f" [{unit}]"
    if (default is not dataclasses.MISSING and not isinstance(default, bool)
            and "default" not in text and default is not None and default != ()):
        text += f" (default: {_fmt(default)})"
    return text.replace("%", "%%")


def add_arguments(parser: argparse.ArgumentParser | Any, cls, *, title: str | None = None,
                  _dests: dict | None = None) -> None:
    """Add one flag per field of option dataclass `cls` (and of its nested ones) to `parser`;
    nothing is filled in for flags the user does not give (`given` reads what was)."""
    group = parser.add_argument_group(title or cls.__name__) if title is not False else parser
    flag_of = flags(cls)
    for f, tp in _fields(cls):
        default = _default(f)
        if f.metadata.get(_NESTED):
            inner = _strip_none(tp)[0]
            add_arguments(parser, inner, title=f"{f.name} ({inner.__name__})")
            continue
        flag = flag_of[f.name]
        dest = cls.__name__ + "." + f.name
        kw: dict[str, Any] = dict(dest=dest, default=argparse.SUPPRESS,
                                  help=field_help(f, default))
        base, optional = _strip_none(tp)
        parse = f.metadata.get("parse")
        kw["metavar"] = f.metadata.get("metavar") or f.name.upper()
        if parse is not None:
            kw["type"] = parse
        elif base is bool:
            kw["action"] = argparse.BooleanOptionalAction
            kw.pop("metavar")
            kw["help"] += f" (default: {'on' if default else 'off'})"
        elif typing.get_origin(base) is tuple:
            args = typing.get_args(base)
            if len(args) == 2 and args[1] is Ellipsis:
                kw.update(nargs="*", type=args[0])
            else:
                kw.update(nargs=len(args), type=args[0])
        elif base in (int, float, str):
            kw["type"] = base
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: no command-line form for {tp!r}; "
                            "give option(parse=...)")
        if f.metadata.get("choices"):
            kw["choices"] = f.metadata["choices"]
            if not f.metadata.get("metavar"):
                kw.pop("metavar", None)
        if optional and parse is None and base in (int, float):
            inner_type = kw["type"]
            kw["type"] = lambda s, t=inner_type: None if s.lower() == "none" else t(s)
        if not flag.startswith("-"):  # a positional: its name is its dest
            kw.pop("dest")
            kw.setdefault("metavar", flag.upper())
            group.add_argument(dest, **kw)
        else:
            group.add_argument(flag, **kw)


def given(args: argparse.Namespace, cls) -> dict[str, Any]:
    """The fields of `cls` that `args` holds (those the user gave), nested ones as dicts."""
    out: dict[str, Any] = {}
    ns = vars(args)
    for f, tp in _fields(cls):
        if f.metadata.get(_NESTED):
            inner = given(args, _strip_none(tp)[0])
            if inner:
                out[f.name] = inner
            continue
        key = cls.__name__ + "." + f.name
        if key in ns:
            v = ns[key]
            out[f.name] = tuple(v) if isinstance(v, list) else v
    return out


def overlay(base: Any, changes: dict[str, Any]) -> Any:
    """`base` (an option dataclass instance) with `changes` applied (nested dicts into nested
    dataclasses); the dataclass checks the result."""
    kw = {}
    for name, v in changes.items():
        cur = getattr(base, name)
        if isinstance(v, dict) and dataclasses.is_dataclass(cur):
            v = overlay(cur, v)
        kw[name] = v
    return dataclasses.replace(base, **kw)


def check_out_prefix(flag: str, value: str, example: str) -> None:
    """Refuse an output prefix (``DIR/name``, the start of several file names) that names no file,
    lies under an existing file, or whose nearest existing folder cannot be written; `example`
    shows a good one. Raises `InputError` with one line naming `flag`."""
    folder, name = os.path.split(value)
    if not name or name in (".", ".."):
        raise InputError(f"{flag} is a prefix of file names (e.g. {example}), got {value!r}")
    above = os.path.abspath(folder or ".")
    while not os.path.exists(above):
        above = os.path.dirname(above)
    if not os.path.isdir(above):
        raise InputError(f"{flag} {value!r}: {above!r} exists and is not a folder")
    if not os.access(above, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {value!r}: the folder {above!r} cannot be written")


class OneLineParser(argparse.ArgumentParser):
    """argparse whose refusals are one line (``error: ...`` on stderr, exit 2), like the rest of
    jscratch's command-line refusals, instead of a usage block."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # A value such as `-1e-4` is a number, not an option (argparse before 3.13 reads only
        # plain `-1` and `-.5` as numbers).
        self._negative_number_matcher = re.compile(r"-\.?\d")

    def error(self, message):
        self.exit(2, f"error: {message} (see --help)\n")


@contextlib.contextmanager
def signals_interrupt():
    """Within the block, SIGTERM and SIGHUP (``kill``, ``timeout``, a closed terminal, a job
    scheduler) stop a command as Ctrl-C does (a design run leaves its folder as Ctrl-C would, a
    carving job holds and retracts); a signal ignored (``nohup``) or handled by the caller stays
    so. Main thread only (elsewhere Python cannot set handlers: unchanged)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)

    # (only where the default would kill the process: `nohup` ignores SIGHUP, and so do we)
    wanted = [sig for sig in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None))
              if sig is not None and signal.getsignal(sig) is signal.SIG_DFL]
    before = {sig: signal.signal(sig, stop) for sig in wanted}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
