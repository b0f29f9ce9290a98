"""Arbitration as a pure function and the mux state table, with explicit times (no clocks)."""

from __future__ import annotations

from collections.abc import Sequence

from hypothesis import given
from hypothesis import strategies as st

from mux.arbiter import (
    TRANSITIONS,
    InputSpec,
    LockSpec,
    MuxEvent,
    MuxState,
    MuxStateMachine,
    MuxTable,
    arbitrate,
    is_fresh,
    stopped,
)
from mux.params import MuxParams
from racecar_hw.base.messages import AckermannDrive

MS = 1_000_000
RUN = MuxState.RUNNING


def _table(hold: bool = False, locks: Sequence[LockSpec] = ()) -> MuxTable:
    # listed out of priority order on purpose: the table sorts
    inputs = [InputSpec("nav", 10, 200 * MS), InputSpec("safety", 100, 200 * MS),
              InputSpec("teleop", 50, 200 * MS), InputSpec("forever", 1, 0)]
    return MuxTable(inputs, locks, hold)


class Samples:
    """Per-input and per-lock samples in table order, set by name."""

    def __init__(self, table: MuxTable) -> None:
        self.table = table
        self.drives: list[AckermannDrive | None] = [None] * len(table.inputs)
        self.received: list[int | None] = [None] * len(table.inputs)
        self.lock_values: list[bool | None] = [None] * len(table.locks)
        self.lock_received: list[int | None] = [None] * len(table.locks)

    def send(self, name: str, at_ns: int, speed: float, steering: float = 0.0) -> None:
        i = self.table.index_of[name]
        self.drives[i] = AckermannDrive(steering_angle=steering, speed=speed)
        self.received[i] = at_ns

    def lock(self, name: str, at_ns: int, value: bool) -> None:
        i = self.table.lock_names.index(name)
        self.lock_values[i] = value
        self.lock_received[i] = at_ns

    def at(self, now_ns: int, state: MuxState = RUN, held: float = 0.0):  # noqa: ANN201
        return arbitrate(self.table, state, self.drives, self.received, self.lock_values,
                         self.lock_received, now_ns, held)


def test_table_sorts_inputs_by_priority_highest_first():
    assert _table().names == ("safety", "teleop", "nav", "forever")


def test_default_params_keep_ros_racecar_names_and_order():
    table = MuxTable.from_params(MuxParams())
    assert table.names == ("safety", "teleop", "nav_0", "nav_1", "nav_2", "nav_3")
    assert all(spec.timeout_ns == 200 * MS for spec in table.inputs)


def test_highest_priority_fresh_input_wins():
    s = Samples(_table())
    s.send("nav", 0, 1.0)
    assert s.at(10 * MS).source == "nav"
    s.send("teleop", 20 * MS, 2.0, 0.1)
    arb = s.at(30 * MS)
    assert arb.source == "teleop"
    assert (arb.drive.speed, arb.drive.steering_angle) == (2.0, 0.1)
    s.send("safety", 40 * MS, 0.0)
    assert s.at(50 * MS).source == "safety"
    # a lower-priority message does not steal the slot from a fresh higher one
    s.send("nav", 60 * MS, 3.0)
    assert s.at(60 * MS).source == "safety"


def test_expiry_falls_through_to_next_fresh_input_at_once():
    s = Samples(_table())
    s.send("teleop", 0, 2.0)
    s.send("nav", 150 * MS, 1.0)
    assert s.at(200 * MS).source == "teleop"  # age == timeout: still fresh
    arb = s.at(200 * MS + 1)  # teleop expired one nanosecond later
    assert arb.source == "nav"
    assert arb.drive.speed == 1.0
    assert s.at(350 * MS).source == "nav"
    # then nav expires too: only the timeout-0 input could be left, and it never spoke
    assert s.at(350 * MS + 1).source == "idle"


def test_idle_is_zero_and_centred_never_the_last_command():
    s = Samples(_table())
    s.send("teleop", 0, 3.0, 0.3)
    assert s.at(100 * MS).drive.speed == 3.0
    arb = s.at(201 * MS)
    assert arb.source == "idle"
    assert (arb.drive.speed, arb.drive.steering_angle) == (0.0, 0.0)
    # nothing ever received: idle as well
    empty = Samples(_table()).at(0)
    assert empty.source == "idle"
    assert empty.drive == AckermannDrive()


def test_hold_steering_option_keeps_the_given_angle_with_zero_speed():
    s = Samples(_table(hold=True))
    arb = s.at(0, held=0.25)
    assert arb.source == "idle"
    assert (arb.drive.speed, arb.drive.steering_angle) == (0.0, 0.25)
    # without the option the held angle is ignored
    assert Samples(_table(hold=False)).at(0, held=0.25).drive.steering_angle == 0.0


def test_timeout_zero_never_expires():
    s = Samples(_table())
    s.send("forever", 0, 0.5)
    hour = 3600 * 1000 * MS
    arb = s.at(hour)
    assert arb.source == "forever"
    assert arb.ages_s()["forever"] == 3600.0
    assert is_fresh(0, 0, hour)
    assert not is_fresh(0, None, hour)


def test_ages_are_reported_per_input():
    s = Samples(_table())
    s.send("teleop", 10 * MS, 1.0)
    arb = s.at(25 * MS)
    assert arb.ages_s() == {"safety": None, "teleop": 0.015, "nav": None, "forever": None}


def test_engaged_lock_masks_strictly_lower_priorities():
    s = Samples(_table(locks=[LockSpec("pause", 50, 0)]))
    s.send("teleop", 0, 1.0)
    s.send("nav", 0, 2.0)
    s.lock("pause", 0, True)
    arb = s.at(10 * MS)
    # teleop has the lock's own priority: not masked
    assert arb.source == "teleop"
    assert arb.masked == ("nav", "forever")
    assert arb.engaged_locks == ("pause",)
    # once teleop expires, nav stays masked: idle, not nav
    s.send("nav", 300 * MS, 2.0)
    arb = s.at(310 * MS)
    assert arb.source == "idle"
    assert arb.drive.speed == 0.0


def test_released_lock_unmasks():
    s = Samples(_table(locks=[LockSpec("pause", 60, 0)]))
    s.send("nav", 0, 2.0)
    s.lock("pause", 0, True)
    assert s.at(10 * MS).source == "idle"
    s.lock("pause", 20 * MS, False)
    arb = s.at(30 * MS)
    assert arb.source == "nav"
    assert arb.masked == ()
    assert arb.engaged_locks == ()


def test_lock_without_timeout_that_never_spoke_is_released():
    s = Samples(_table(locks=[LockSpec("pause", 60, 0)]))
    s.send("nav", 0, 2.0)
    assert s.at(10 * MS).source == "nav"


def test_deadman_lock_engages_when_silent_and_before_it_first_speaks():
    s = Samples(_table(locks=[LockSpec("deadman", 60, 100 * MS)]))
    s.send("nav", 0, 2.0)
    # never heard: engaged (a deadman must prove it is alive)
    assert s.at(0).source == "idle"
    s.lock("deadman", 10 * MS, False)
    s.send("nav", 20 * MS, 2.0)
    assert s.at(30 * MS).source == "nav"
    assert s.at(110 * MS).source == "nav"  # age == timeout: still alive
    s.send("nav", 105 * MS, 2.0)
    arb = s.at(111 * MS)  # silent too long: engaged again
    assert arb.source == "idle"
    assert arb.engaged_locks == ("deadman",)
    # a deadman that says true is engaged even while fresh
    s.lock("deadman", 120 * MS, True)
    s.send("nav", 120 * MS, 2.0)
    assert s.at(125 * MS).source == "idle"


def test_highest_engaged_lock_sets_the_mask():
    s = Samples(_table(locks=[LockSpec("low", 20, 0), LockSpec("high", 80, 0)]))
    s.send("teleop", 0, 1.0)
    s.lock("low", 0, True)
    s.lock("high", 0, True)
    arb = s.at(1 * MS)
    assert arb.source == "idle"
    assert arb.masked == ("teleop", "nav", "forever")
    s.lock("high", 2 * MS, False)
    assert s.at(3 * MS).source == "teleop"


def test_estop_and_fault_states_output_zero_whatever_the_inputs():
    s = Samples(_table(hold=True))
    s.send("safety", 0, 1.0, 0.2)
    for state, source in ((MuxState.ESTOP, "estop"), (MuxState.FAULT, "fault")):
        arb = s.at(1 * MS, state, held=0.3)
        assert arb.source == source
        assert arb.drive == AckermannDrive()
        assert arb.ages_s()["safety"] == 0.001
    arb = stopped(_table(), MuxState.FAULT)
    assert (arb.source, arb.drive) == ("fault", AckermannDrive())


def test_state_table_is_complete_and_fault_only_leaves_on_reset():
    for state in MuxState:
        assert set(TRANSITIONS[state]) == set(MuxEvent)
    for event in (MuxEvent.ENGAGE_ESTOP, MuxEvent.RELEASE_ESTOP, MuxEvent.ERROR):
        assert TRANSITIONS[MuxState.FAULT][event] is MuxState.FAULT
    assert TRANSITIONS[MuxState.FAULT][MuxEvent.RESET] is MuxState.ESTOP


def test_state_machine_records_reasons():
    m = MuxStateMachine()
    assert m.process(MuxEvent.ENGAGE_ESTOP, "button") is MuxState.ESTOP
    assert m.reason == "button"
    m.process(MuxEvent.ENGAGE_ESTOP, "again")
    assert m.reason == "button"  # no move, first reason kept
    assert m.process(MuxEvent.RELEASE_ESTOP) is MuxState.RUNNING
    assert m.reason == ""
    m.process(MuxEvent.ERROR, "boom")
    assert (m.state, m.reason) == (MuxState.FAULT, "boom")
    assert m.process(MuxEvent.RELEASE_ESTOP) is MuxState.FAULT
    assert m.process(MuxEvent.RESET) is MuxState.ESTOP
    assert "boom" in m.reason
    assert m.process(MuxEvent.RELEASE_ESTOP) is MuxState.RUNNING


_NAMES = ("safety", "teleop", "nav", "forever")
_sample = st.one_of(st.none(), st.integers(min_value=0, max_value=1000 * MS))


@given(received=st.tuples(*[_sample] * 4), lock_value=st.one_of(st.none(), st.booleans()),
       lock_at=_sample, lock_priority=st.integers(0, 120), lock_timeout=st.sampled_from([0, 100 * MS]),
       now=st.integers(min_value=0, max_value=1200 * MS))
def test_winner_is_the_highest_fresh_unmasked_input(received, lock_value, lock_at, lock_priority,
                                                    lock_timeout, now):
    table = _table(locks=[LockSpec("lock", lock_priority, lock_timeout)])
    s = Samples(table)
    for name, at in zip(_NAMES, received, strict=True):
        if at is not None:
            s.send(name, at, 1.0 + table.index_of[name])
    if lock_value is not None and lock_at is not None:
        s.lock("lock", lock_at, lock_value)
    arb = s.at(now)
    engaged = bool(arb.engaged_locks)
    candidates = [spec for i, spec in enumerate(table.inputs)
                  if is_fresh(spec.timeout_ns, s.received[i], now)
                  and not (engaged and spec.priority < lock_priority)]
    if candidates:
        best = max(candidates, key=lambda spec: spec.priority)
        assert arb.source == best.name
        assert arb.drive.speed == 1.0 + table.index_of[best.name]
    else:
        assert arb.source == "idle"
        assert arb.drive == AckermannDrive()
    assert set(arb.masked) == ({spec.name for spec in table.inputs if spec.priority < lock_priority}
                               if engaged else set())
