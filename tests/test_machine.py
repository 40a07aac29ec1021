"""Tests of jscratch.machine: the profile's TOML round trip, bad values refused in one line naming
the key (by the profile, by fabricate and by the design CLI), the shipped default printed and read
back, and the carving-time estimate by hand."""

import dataclasses
import json
import math
import re

import pytest

from jscratch import fabricate, machine
from jscratch.design import main as design_main
from jscratch.errors import DesignFileError, InputError
from jscratch.machine import MachineProfile, carving_seconds


@pytest.mark.parametrize("key,value", [
    ("cutter_radius_mm", -1.0), ("plunge_max_mm", 0.2), ("plunge_min_mm", 0.2), ("feed_mm_min", "fast"),
    ("cutter", "flat"), ("holder", "glue"), ("board_offset_mm", [1.0]), ("overhead_s", float("nan")),
    ("drop_short", 3), ("spindle_rpm", -5.0), ("typo_mm", 1.0), ("board_offset_mm", [1e300, 0]),
    # Values G-code would write as zero: no groove, travel on the surface, a still spindle.
    ("safe_z_mm", 0.0004), ("plunge_mm", 0.0004), ("plunge_min_mm", 0.0001), ("spindle_rpm", 0.3),
    ("plunge_mm", 0.11),  # deeper than plunge_max_mm
])
def test_bad_profile_values_one_line_naming_the_key(tmp_path, key, value, capsys):
    path = tmp_path / "bad.toml"
    v = "nan" if isinstance(value, float) and math.isnan(value) else json.dumps(value)
    path.write_text(f"[machine]\n{key} = {v}\n")
    with pytest.raises(ValueError) as e:
        MachineProfile.from_toml(path)
    msg = str(e.value)
    assert f"machine.{key}" in msg and str(path) in msg and "\n" not in msg
    capsys.readouterr()
    assert fabricate.main(["--dry-run", "--machine", str(path), "--out", str(tmp_path / "o" / "j")]) == 2
    err = capsys.readouterr().err
    assert f"machine.{key}" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()
    assert design_main(["--machine", str(path), "--out", str(tmp_path / "d"), "--quiet"]) == 2



def test_profile_toml_round_trip_and_the_config_option(tmp_path):
    p = MachineProfile(name="x", cutter_radius_mm=0.3, plunge_max_mm=0.2, board_offset_mm=(1.0, 2.0), spindle_rpm=1e4)
    path = tmp_path / "p.toml"
    path.write_text(p.to_toml())
    assert MachineProfile.from_toml(path) == p
    assert fabricate.MachineConfig is MachineProfile
    # `--config` reads the same file (MachineConfig is the same class).
    assert fabricate.main(["--dry-run", "--config", str(path), "--demo-n", "5", "--out", str(tmp_path / "o" / "j"),
                           "--quiet", "--order-time", "0.1"]) == 0
    assert "S10000" in (tmp_path / "o" / "j.gcode").read_text()


def test_default_profile_printed_and_read_back(tmp_path, capsys):
    assert machine.main([]) == 0
    text = capsys.readouterr().out
    path = tmp_path / "default.toml"
    path.write_text(text)
    assert machine.load_machine(path) == machine.load_machine() == MachineProfile()
    assert machine.main([str(tmp_path / "missing.toml")]) == 2
    assert "missing.toml" in capsys.readouterr().err


def test_carving_seconds_by_hand():
    prof = MachineProfile(feed_mm_min=600.0, rapid_mm_min=1200.0, plunge_mm_min=60.0, safe_z_mm=2.0,
                          overhead_s=3.0, spindle_rpm=0.0)
    # 3 scratches: 30 mm cut at 10 mm/s, 12 mm travel at 20 mm/s, 0.3 mm plunged at 1 mm/s, per
    # scratch a 2 mm rapid up and down (0.2 s) and 2 mm at the plunge feed (2 s), 3 s overhead.
    t = carving_seconds(prof, n=3, cut_mm=30.0, travel_mm=12.0, plunge_mm_total=0.3)
    assert t == pytest.approx(3.0 + 0.6 + 0.3 + 3 * (0.2 + 2.0) + 3 * 3.0)
    spun = dataclasses.replace(prof, spindle_rpm=1e4, spinup_s=4.0)
    assert carving_seconds(spun, n=3, cut_mm=30.0, travel_mm=12.0, plunge_mm_total=0.3) == pytest.approx(t + 4.0)


def test_a_spin_up_dwell_written_as_zero_is_refused():
    with pytest.raises(ValueError, match=r"machine.spinup_s must be written as at least P0.001 .*"
                                         r"or 0 for no dwell"):
        MachineProfile(spindle_rpm=1000, spinup_s=0.0001)
    assert MachineProfile(spindle_rpm=1000, spinup_s=0).spinup_s == 0.0  # (no dwell, asked for)
    assert MachineProfile(spindle_rpm=0, spinup_s=0.0001).spinup_s == 0.0001  # (no spindle)


@pytest.mark.parametrize("text,what", [
    ("feed_mm_min = 5\n[machine]\ncutter_radius_mm = 0.2\n", "feed_mm_min outside the [machine]"),
    ("[machine]\ncutter_radius_mm = 0.2\n[other]\nx = 1\n", "other outside the [machine] table"),
    ("machine = 3\n", "'machine' is not a table"),
])
def test_settings_outside_the_machine_table_are_refused_not_dropped(tmp_path, text, what):
    """A file with a ``[machine]`` table and settings beside it would lose those settings:
    refused in one line naming them."""
    path = tmp_path / "mixed.toml"
    path.write_text(text)
    with pytest.raises(DesignFileError, match=re.escape(what)):
        MachineProfile.from_toml(path)
    bare = tmp_path / "bare.toml"
    bare.write_text("feed_mm_min = 500.0\ncutter_radius_mm = 0.2\n")
    assert MachineProfile.from_toml(bare).feed_mm_min == 500.0


@pytest.mark.parametrize("name", ["n", "cut_mm", "travel_mm", "plunge_mm_total"])
@pytest.mark.parametrize("value", [-1, float("nan"), float("inf"), None])
def test_carving_seconds_refuses_negative_or_non_finite_amounts(name, value):
    kw = dict(n=3, cut_mm=30.0, travel_mm=12.0, plunge_mm_total=0.3) | {name: value}
    with pytest.raises(InputError, match=rf"^carving_seconds: `{name}` must be a finite number "
                                         rf">= 0, got {value}$"):
        carving_seconds(MachineProfile(), **kw)


def test_unknown_keywords_are_refused_like_unknown_keys(tmp_path):
    """`load_machine(foo=1)` and `MachineProfile(foo=1)` refuse the name in one line, as
    `from_dict` refuses an unknown key, not with a TypeError."""
    known = r"\(known: board_offset_mm, cutter, .*\)$"
    with pytest.raises(InputError,
                       match=rf"^load_machine: unknown machine setting machine.foo {known}"):
        machine.load_machine(foo=1)
    path = tmp_path / "m.toml"
    path.write_text(MachineProfile().to_toml())
    with pytest.raises(InputError, match=r"^load_machine: unknown machine setting machine.foo "):
        machine.load_machine(path, foo=None)
    with pytest.raises(InputError,
                       match=rf"^MachineProfile: unknown machine setting machine.foo {known}"):
        MachineProfile(foo=1)
    with pytest.raises(InputError, match=r"^src: unknown machine setting machine.bar "):
        MachineProfile.from_dict({}, source="src", bar=2.0)
    assert machine.load_machine(path, feed_mm_min=800.0).feed_mm_min == 800.0
    assert MachineProfile(feed_mm_min=800).feed_mm_min == 800.0
