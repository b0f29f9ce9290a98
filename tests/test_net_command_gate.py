"""racecar_hw.net.command_gate: one offer per control period per command row, the newest, and no
thread of ours woken for a stream at a client's pace."""

from __future__ import annotations

import threading

from conftest import wait_for

from racecar_hw.net.command_gate import CommandGate

PERIOD_S = 0.02


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _recorder() -> tuple[list[tuple[object, int]], object]:
    got: list[tuple[object, int]] = []

    def offer(sample: object) -> None:
        got.append((sample, threading.get_ident()))

    return got, offer


def test_a_stream_at_a_clients_pace_is_offered_in_the_receiving_thread():
    """Samples a period or more apart go at once, in the caller's thread; the gate's own thread is
    not even started, so it cannot have been needed."""
    clock = _Clock()
    gate = CommandGate("test-gate", PERIOD_S, clock)
    got, offer = _recorder()
    arrive = gate.row(offer)
    for n in range(40):
        arrive(n)
        clock.t += 0.025  # a client answering 40 scans a second
    assert got == [(n, threading.get_ident()) for n in range(40)]
    assert gate.deferred_offers == 0


def test_samples_within_a_period_go_as_their_newest_when_it_is_over():
    clock = _Clock()
    gate = CommandGate("test-gate", PERIOD_S, clock)
    got, offer = _recorder()
    arrive = gate.row(offer)
    gate.start()
    try:
        arrive("first")  # nothing offered yet: at once
        for n in range(300):  # a flood within the period
            arrive(n)
        assert len(got) == 1
        clock.t += PERIOD_S  # the period is over: the gate's thread sees it at its next look
        wait_for(lambda: len(got) == 2, timeout=20)
        assert [sample for sample, _ in got] == ["first", 299]
        assert got[0][1] == threading.get_ident() and got[1][1] != threading.get_ident()
        assert gate.deferred_offers == 1
    finally:
        gate.stop()


def test_rows_are_gated_apart_and_one_rows_flood_does_not_hold_another():
    clock = _Clock()
    gate = CommandGate("test-gate", PERIOD_S, clock)
    flooded, offer_a = _recorder()
    quiet, offer_b = _recorder()
    a, b = gate.row(offer_a), gate.row(offer_b)
    a(0)
    for n in range(1, 50):
        a(n)  # the same instant: pending, the newest kept
    b("only")
    assert [s for s, _ in flooded] == [0] and [s for s, _ in quiet] == ["only"]
    assert gate._deferred and gate._deferred[0].pending == 49


def test_stop_ends_the_thread_and_drops_what_is_pending():
    clock = _Clock()
    gate = CommandGate("test-gate", PERIOD_S, clock)  # its clock never moves: the period never ends
    got, offer = _recorder()
    arrive = gate.row(offer)
    gate.start()
    thread = gate._thread
    arrive(1)
    arrive(2)
    gate.stop()
    assert thread is not None and not thread.is_alive()
    assert [s for s, _ in got] == [1]
    gate.stop()  # twice is fine
