"""`jscratch.options`: a dataclass declares each option once; the generated parser has one flag
per field (nested dataclasses flattened, clashes refused), fills in nothing the user did not give,
and `overlay` lays what was given over defaults or a file's settings."""

import argparse
import dataclasses

import pytest

from jscratch.errors import InputError
from jscratch.options import add_arguments, check_out_prefix, flags, given, option, overlay


@dataclasses.dataclass(frozen=True)
class Inner:
    rate: float = option(0.5, "a rate", unit="1/s")
    mode: str = option("a", "a mode", choices=("a", "b"), flag="--kind")


@dataclasses.dataclass(frozen=True)
class Outer:
    files: tuple[str, ...] = option((), "input files", flag="files")
    count: int = option(3, "how many")
    pair: tuple[float, float] = option((1.0, 2.0), "two numbers", unit="m")
    on: bool = option(True, "switch")
    cap: float | None = option(None, "an optional cap")
    names: tuple[str, ...] = option(("x",), "names", parse=lambda t: tuple(t.split(",")))
    inner: Inner = option(default_factory=Inner, nested=True, help="inner options")


def _parse(argv):
    p = argparse.ArgumentParser()
    add_arguments(p, Outer)
    return p.parse_args(argv)


def test_flags_one_per_field_nested_flattened():
    assert flags(Outer) == {"files": "files", "count": "--count", "pair": "--pair", "on": "--on",
                            "cap": "--cap", "names": "--names", "inner.rate": "--rate",
                            "inner.mode": "--kind"}


def test_nothing_given_nothing_filled():
    assert given(_parse([]), Outer) == {}
    assert overlay(Outer(), given(_parse([]), Outer)) == Outer()


def test_given_values_typed_and_laid_over():
    args = _parse(["f1", "f2", "--count", "7", "--pair", "3", "4.5", "--no-on", "--cap", "none",
                   "--names", "a,b", "--rate", "0.25", "--kind", "b"])
    g = given(args, Outer)
    assert g == {"files": ("f1", "f2"), "count": 7, "pair": (3.0, 4.5), "on": False, "cap": None,
                 "names": ("a", "b"), "inner": {"rate": 0.25, "mode": "b"}}
    base = Outer(count=1, inner=Inner(rate=9.0))
    out = overlay(base, {"inner": {"mode": "b"}})
    assert out.inner == Inner(rate=9.0, mode="b") and out.count == 1


def test_bad_values_refused_by_the_parser(capsys):
    with pytest.raises(SystemExit):
        _parse(["--count", "x"])
    with pytest.raises(SystemExit):
        _parse(["--kind", "c"])
    assert "--kind" in capsys.readouterr().err


def test_clashing_flags_refused():
    @dataclasses.dataclass(frozen=True)
    class Clash:
        rate: int = option(1, "outer rate")
        inner: Inner = option(default_factory=Inner, nested=True, help="x")

    with pytest.raises(TypeError, match="clash"):
        flags(Clash)


def test_help_has_unit_and_one_default(capsys):
    p = argparse.ArgumentParser()
    add_arguments(p, Outer)
    p.print_help()
    text = capsys.readouterr().out
    assert "two numbers [m] (default: 1.0 2.0)" in " ".join(text.split())
    assert text.count("(default: 3)") == 1


@pytest.mark.parametrize("value", ["", "dir/", "dir/.."])
def test_out_prefix_needs_a_name(value):
    with pytest.raises(InputError, match="--out is a prefix"):
        check_out_prefix("--out", value, "DIR/job")


def test_out_prefix_folder_must_be_a_folder(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        check_out_prefix("--out", str(tmp_path / "f" / "job"), "DIR/job")
    check_out_prefix("--out", str(tmp_path / "new" / "job"), "DIR/job")  # a new folder is fine
