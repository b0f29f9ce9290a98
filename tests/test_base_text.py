"""racecar_hw.base.text.one_line: a sender's text as one printable log line."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from racecar_hw.base.text import ELLIPSIS, one_line


def test_control_characters_and_whitespace_runs_become_one_space():
    assert one_line("a\nb\r\n\tc\x00\x1b[31md  e", 100) == "a b c [31md e"
    assert one_line("  \n\x00 ", 100) == ""
    assert one_line(ValueError("bad\nbag"), 100) == "bad bag"


def test_long_text_is_cut_to_the_limit_with_an_ellipsis():
    assert one_line("x" * 10, 10) == "x" * 10
    assert one_line("x" * 11, 10) == "x" * 9 + ELLIPSIS


@given(st.text(), st.integers(min_value=1, max_value=300))
def test_any_text_is_one_printable_line_within_the_limit(text, limit):
    shown = one_line(text, limit)
    assert len(shown) <= limit
    assert all(c.isprintable() for c in shown)
    assert shown == shown.strip() and "  " not in shown
