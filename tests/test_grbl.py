"""GRBL protocol pieces: feedback tags with digits, the strict number formatter, bounded messages."""

import re

from hypothesis import given, settings
from hypothesis import strategies as st

from jscratch.grbl import WORD_FORMAT, check_words, classify, clip, gword


def test_feedback_tags_with_digits_are_feedback():
    for line in ("[G54:1.000,2.000,0.000]", "[G92:5.000,4.000,2.000]", "[G28:0.000,0.000,0.000]",
                 "[G30:0.000,0.000,0.000]", "[TLO:0.000]", "[PRB:0.000,0.000,0.000:0]",
                 "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "[VER:1.1h.20190825:]", "[MSG:Reset to continue]"):
        assert classify(line).kind == "msg", line
    for junk in ("[g54:1.000]", "[54:1.000]", "[G54 1.000]", "G54:1.000]", "[G54:1.000"):
        assert classify(junk).kind == "unknown", junk


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(WORD_FORMAT)), st.floats(allow_nan=True, allow_infinity=True))
def test_gword_is_fixed_point_in_range_or_refuses(letter, value):
    dec, lo, hi = WORD_FORMAT[letter]
    try:
        word = gword(letter, value)
    except ValueError as exc:
        assert f"G-code word {letter}" in str(exc)
        assert not (lo - 0.5 * 10.0**-dec < value < hi + 0.5 * 10.0**-dec) or value != value
        return
    assert re.fullmatch(rf"{letter}-?\d{{1,8}}" + (rf"\.\d{{{dec}}}" if dec else ""), word), word
    assert len(word.replace("-", "").replace(".", "")) <= 9  # letter + at most 8 digits GRBL reads
    assert abs(float(word[1:]) - value) <= 0.5 * 10.0**-dec * (1 + 1e-9) + 1e-9 * abs(value)
    check_words(word)


def test_clip_is_one_bounded_printable_line():
    s = clip("a\r\nb\x00" + "\ufffd" * 500, 60)
    assert len(s) == 60 and s.isprintable() and s.isascii() and s.startswith("a\\r\\nb\\x00") and s.endswith("...")
    assert clip("short") == "short"
