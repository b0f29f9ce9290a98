"""The refusal tally: counts per source and reason, one log line per pair per interval."""

from __future__ import annotations

import logging
import threading

from racecar_hw.runtime.refusals import OTHER_SOURCES, Refusals


class _Clock:
    def __init__(self) -> None:
        self.ns = 0

    def __call__(self) -> int:
        return self.ns


def test_first_refusal_logged_then_summaries_per_interval(caplog):
    clock = _Clock()
    refusals = Refusals(10.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="racecar_hw.refusals"):
        for _ in range(10_000):
            refusals.note("web", "127.0.0.1", "bad token")
        assert len(caplog.records) == 1
        assert "127.0.0.1" in caplog.records[0].getMessage()
        clock.ns = 10_000_000_000
        refusals.note("web", "127.0.0.1", "bad token")
        assert len(caplog.records) == 2
        assert "10000 times in the last 10 s (10001 in all)" in caplog.records[1].getMessage()
    assert refusals.total() == 10_001
    assert refusals.counts() == {("web", "bad token"): 10_001}


def test_each_source_and_reason_has_its_own_line(caplog):
    refusals = Refusals(10.0, clock=_Clock())
    with caplog.at_level(logging.WARNING, logger="racecar_hw.refusals"):
        refusals.note("mavlink", "10.0.0.1:14550", "bad signature")
        refusals.note("mavlink", "10.0.0.2:14550", "bad signature")
        refusals.note("mavlink", "10.0.0.1:14550", "unsigned")
    assert len(caplog.records) == 3
    assert refusals.counts() == {("mavlink", "bad signature"): 2, ("mavlink", "unsigned"): 1}
    assert refusals.total("mavlink", "unsigned") == 1
    assert refusals.lines() == ["mavlink: bad signature: 2", "mavlink: unsigned: 1"]


def test_flush_writes_what_is_pending_once(caplog):
    refusals = Refusals(10.0, clock=_Clock())
    with caplog.at_level(logging.WARNING, logger="racecar_hw.refusals"):
        for _ in range(5):
            refusals.note("zenoh", "127.0.0.1:7447", "authentication failed")
        refusals.flush()
        refusals.flush()
    assert len(caplog.records) == 2
    assert "4 times" in caplog.records[1].getMessage()


def test_sources_are_bounded():
    refusals = Refusals(10.0, max_sources=4, clock=_Clock(), logger=logging.getLogger("quiet"))
    for i in range(100):
        refusals.note("mavlink", f"10.0.0.{i}:1", "forged")
    sources = {source for (_, source, _) in refusals.by_source()}
    assert len(sources) == 5 and OTHER_SOURCES in sources
    assert refusals.total() == 100


def test_counts_from_many_threads():
    refusals = Refusals(10.0, logger=logging.getLogger("quiet"))

    def flood() -> None:
        for _ in range(2000):
            refusals.note("zenoh", "127.0.0.1", "flood")

    threads = [threading.Thread(target=flood) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert refusals.total("zenoh") == 8000


def test_reasons_per_source_are_bounded_and_cut_short():
    """A reason may quote the sender (a Zenoh sample's type and hash): varying it grows nothing."""
    from racecar_hw.runtime.refusals import MAX_REASON_CHARS, OTHER_REASONS

    refusals = Refusals(10.0, max_reasons=4, clock=_Clock(), logger=logging.getLogger("quiet"))
    for i in range(1000):
        refusals.note("zenoh", "/cmd_vel", f"wrong type pkg{i}/msg/T (it takes geometry_msgs/msg/Twist)")
    refusals.note("zenoh", "/cmd_vel", "x" * 10_000)
    refusals.note("zenoh", "/drive", "y" * 10_000)
    by = refusals.by_source()
    assert len([k for k in by if k[1] == "/cmd_vel"]) == 5
    assert by[("zenoh", "/cmd_vel", OTHER_REASONS)] == 1000 - 4 + 1
    assert refusals.total() == 1002
    assert all(len(reason) <= MAX_REASON_CHARS for _, _, reason in by)
    assert ("zenoh", "/drive", "y" * (MAX_REASON_CHARS - 1) + "\u2026") in by


def test_sources_and_reasons_are_logged_as_one_printable_line(caplog):
    """A sender's text in a reason (a Zenoh type name) forges no log line and paints no terminal."""
    refusals = Refusals(10.0, clock=_Clock())
    with caplog.at_level(logging.WARNING, logger="racecar_hw.refusals"):
        refusals.note("zenoh", "/cmd_vel\r\nFORGED", "wrong type evil\nERROR forged line\x1b[2J (it takes T)")
    (record,) = caplog.records
    text = record.getMessage()
    assert "\n" not in text and "\r" not in text and "\x1b" not in text
    assert "refused /cmd_vel FORGED: wrong type evil ERROR forged line [2J (it takes T)" in text
    reason = "wrong type evil ERROR forged line [2J (it takes T)"
    assert refusals.by_source() == {("zenoh", "/cmd_vel FORGED", reason): 1}
