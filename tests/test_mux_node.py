"""The command mux on the real bus: inputs, locks, e-stop, faults, diagnostics, the 50 Hz loop.

Arbitration tests use an injected clock and explicit ``now_ns``; only the asyncio tests use real
time, and they wait on conditions with generous deadlines.
"""

from __future__ import annotations

import asyncio
import time

import pytest
from conftest import async_wait_for

from mux.arbiter import MuxState
from mux.node import CommandMux, Filter, MuxNode
from mux.params import LockParams, MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns, nanoseconds
from racecar_hw.base.errors import TopicTypeError
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Bool,
    DiagnosticArray,
    DiagnosticStatus,
    String,
    Time,
)
from racecar_hw.runtime.ticker import PeriodicTimer

LOW = "/vesc/low_level/ackermann_cmd_mux"
HIGH = "/vesc/high_level/ackermann_cmd_mux"
SAFETY, TELEOP, NAV0 = f"{LOW}/input/safety", f"{LOW}/input/teleop", f"{HIGH}/input/nav_0"
OUTPUT = f"{LOW}/output"


class FakeClock:
    """Monotonic ns that only moves when told."""

    def __init__(self) -> None:
        self.ns = 5_000_000_000

    def __call__(self) -> int:
        return self.ns

    def advance(self, seconds: float) -> int:
        self.ns += nanoseconds(seconds)
        return self.ns


def _cmd(speed: float, steering: float = 0.0) -> AckermannDriveStamped:
    return AckermannDriveStamped(drive=AckermannDrive(steering_angle=steering, speed=speed))


def _mux(**overrides) -> tuple[Bus, CommandMux, FakeClock]:
    bus, clock = Bus(), FakeClock()
    mux = CommandMux(bus, MuxParams(**overrides), clock=clock, wall_clock=lambda: 1_700_000_000_123_456_789)
    return bus, mux, clock


def test_priorities_expiry_and_fall_through_on_the_bus():
    bus, mux, clock = _mux()
    assert mux.arbitrate().source == "idle"
    bus.publish(NAV0, _cmd(1.0))
    bus.publish(TELEOP, _cmd(2.0, 0.1))
    arb = mux.arbitrate()
    assert (arb.source, arb.drive.speed, arb.drive.steering_angle) == ("teleop", 2.0, 0.1)
    clock.advance(0.1)
    bus.publish(NAV0, _cmd(1.0))
    clock.advance(0.15)  # teleop 0.25 s old: expired; nav_0 0.15 s: fresh
    assert mux.arbitrate().source == "nav_0"
    bus.publish(SAFETY, _cmd(0.0))
    assert mux.arbitrate().source == "safety"
    clock.advance(0.3)
    arb = mux.arbitrate()
    assert arb.source == "idle"
    assert arb.drive == AckermannDrive()
    assert [s for _t, s in mux.switches] == ["idle", "teleop", "nav_0", "safety", "idle"]
    times = [t for t, _s in mux.switches]
    assert times == pytest.approx([0.0, 0.0, 0.25, 0.25, 0.55])


def test_explicit_now_overrides_the_clock():
    bus, mux, clock = _mux()
    bus.publish(TELEOP, _cmd(1.0))
    assert mux.arbitrate(clock.ns + nanoseconds(0.2)).source == "teleop"
    assert mux.arbitrate(clock.ns + nanoseconds(0.2) + 1).source == "idle"


def test_active_source_is_published_on_switches():
    bus, mux, clock = _mux()
    seen: list[str] = []
    bus.subscribe(f"{LOW}/active", lambda msg: seen.append(msg.data))
    mux.arbitrate()
    bus.publish(TELEOP, _cmd(1.0))
    mux.arbitrate()
    mux.arbitrate()
    clock.advance(1.0)
    mux.arbitrate()
    assert seen == ["idle", "teleop", "idle"]
    assert isinstance(bus.latest(f"{LOW}/active"), String)


def test_step_publishes_limited_output_in_base_link():
    bus, mux, clock = _mux()
    outputs: list[AckermannDriveStamped] = []
    bus.subscribe(OUTPUT, outputs.append)
    bus.publish(TELEOP, _cmd(5.0, 0.34))
    for _ in range(5):
        mux.step()
        clock.advance(0.02)
    assert len(outputs) == 5
    assert outputs[-1].header.frame_id == "base_link"
    assert outputs[-1].header.stamp == Time(1_700_000_000, 123_456_789)
    assert outputs[-1].drive.speed == pytest.approx(5 * 2.5 / 50)
    assert outputs[-1].drive.steering_angle == pytest.approx(5 * 3.2 / 50)
    assert outputs[0] is not outputs[1]


def test_idle_output_goes_to_zero_and_never_repeats_the_last_command():
    bus, mux, clock = _mux(limiter_enabled=False)
    bus.publish(TELEOP, _cmd(3.0, 0.3))
    assert mux.step().drive.speed == 3.0
    clock.advance(0.21)
    out = mux.step().drive
    assert (out.speed, out.steering_angle) == (0.0, 0.0)


def test_idle_output_with_hold_steering_keeps_the_last_angle():
    bus, mux, clock = _mux(limiter_enabled=False, hold_steering_when_idle=True)
    bus.publish(TELEOP, _cmd(3.0, 0.3))
    mux.step()
    clock.advance(0.21)
    out = mux.step().drive
    assert (out.speed, out.steering_angle) == (0.0, 0.3)
    assert mux.source == "idle"


def test_idle_output_brakes_at_max_decel_with_the_limiter():
    bus, mux, clock = _mux()
    mux.limiter.reset(speed=4.0)
    speeds = [mux.step().drive.speed for _ in range(3)]
    assert speeds == pytest.approx([4.0 - 0.16, 4.0 - 0.32, 4.0 - 0.48])


def test_an_input_at_the_longest_timeout_still_expires_on_the_bus():
    """No input holds its last command (0, "never", is refused: tests/test_mux_params.py)."""
    from mux.params import MAX_INPUT_TIMEOUT_S, InputParams
    bus, mux, clock = _mux(inputs=[InputParams("bag", "/bag", 10, MAX_INPUT_TIMEOUT_S)])
    bus.publish("/bag", _cmd(1.0))
    clock.advance(MAX_INPUT_TIMEOUT_S)
    assert mux.arbitrate().source == "bag"
    clock.advance(0.001)
    assert mux.arbitrate().source == "idle"


def test_filters_run_between_arbitration_and_limiter():
    bus, mux, clock = _mux()
    calls: list[tuple[float, str, int]] = []

    def cap(drive: AckermannDrive, source: str, now_ns: int) -> AckermannDrive:
        calls.append((drive.speed, source, now_ns))
        return AckermannDrive(steering_angle=drive.steering_angle, speed=min(drive.speed, 0.01))

    bus.publish(TELEOP, _cmd(5.0))
    out = mux.step(filters=[cap]).drive
    assert calls == [(5.0, "teleop", clock.ns)]
    assert out.speed == 0.01
    assert bus.latest(TELEOP).drive.speed == 5.0  # the input message is untouched


def test_locks_and_deadman_on_the_bus():
    locks = [LockParams("pause", "/pause", 95, 0.0), LockParams("deadman", "/deadman", 50, 0.5)]
    bus, mux, clock = _mux(locks=locks)
    bus.publish(NAV0, _cmd(1.0))
    arb = mux.arbitrate()
    assert arb.source == "idle"  # the deadman never spoke
    assert arb.engaged_locks == ("deadman",)
    assert arb.masked == ("nav_0", "nav_1", "nav_2", "nav_3")
    bus.publish("/deadman", Bool(False))
    assert mux.arbitrate().source == "nav_0"
    bus.publish("/pause", Bool(True))
    bus.publish(TELEOP, _cmd(2.0))
    arb = mux.arbitrate()
    assert arb.source == "idle"  # pause masks teleop (90) too; safety (100) would still pass
    bus.publish(SAFETY, _cmd(0.5))
    assert mux.arbitrate().source == "safety"
    bus.publish("/pause", Bool(False))
    clock.advance(0.21)  # safety expired
    bus.publish(TELEOP, _cmd(2.0))
    bus.publish("/deadman", Bool(False))
    assert mux.arbitrate().source == "teleop"
    clock.advance(0.15)
    bus.publish(NAV0, _cmd(1.0))
    clock.advance(0.1)  # teleop expired; deadman 0.25 s silent: still alive
    assert mux.arbitrate().source == "nav_0"
    clock.advance(0.26)  # deadman silent 0.51 s: engaged
    bus.publish(NAV0, _cmd(1.0))
    assert mux.arbitrate().source == "idle"


def test_estop_latches_and_needs_an_explicit_release():
    bus, mux, clock = _mux(limiter_enabled=False)
    bus.publish(SAFETY, _cmd(1.0, 0.2))
    mux.engage_estop("test button")
    assert mux.state is MuxState.ESTOP
    out = mux.step().drive
    assert (out.speed, out.steering_angle) == (0.0, 0.0)
    assert mux.source == "estop"
    # inputs keep coming: still stopped
    for _ in range(3):
        clock.advance(0.05)
        bus.publish(SAFETY, _cmd(1.0, 0.2))
        assert mux.step().drive.speed == 0.0
    assert mux.release_estop()
    assert mux.state is MuxState.RUNNING
    assert mux.step().drive.speed == 1.0
    assert [s for _t, s in mux.switches] == ["estop", "safety"]


def test_estop_brakes_and_centres_at_once_past_the_limiter():
    bus, mux, clock = _mux()  # the limiter on: 8 m/s^2 braking, 3.2 rad/s steering
    outputs: list[AckermannDriveStamped] = []
    bus.subscribe(OUTPUT, outputs.append)
    for _ in range(60):  # up to 1 m/s and 0.2 rad
        bus.publish(TELEOP, _cmd(1.0, 0.2))
        mux.step()
        clock.advance(0.02)
    assert (outputs[-1].drive.speed, outputs[-1].drive.steering_angle) == pytest.approx((1.0, 0.2))
    mux.engage_estop("test button")
    bus.publish(TELEOP, _cmd(1.0, 0.2))
    first = mux.step().drive
    # the first output after the engage is already the stop, not one 0.16 m/s braking step
    assert (first.speed, first.steering_angle) == (0.0, 0.0)
    assert (mux.limiter.speed, mux.limiter.steering_angle) == (0.0, 0.0)
    clock.advance(0.02)
    assert mux.step().drive == AckermannDrive()
    # after the release the limiter starts from standstill: one acceleration step, not 1 m/s
    assert mux.release_estop()
    clock.advance(0.02)
    bus.publish(TELEOP, _cmd(1.0, 0.2))
    again = mux.step().drive
    assert again.speed == pytest.approx(2.5 / 50) and again.steering_angle == pytest.approx(3.2 / 50)


def test_estop_topic_engages_and_release_is_refused_while_it_says_true():
    bus, mux, clock = _mux()
    bus.publish("/estop", Bool(True))
    assert mux.state is MuxState.ESTOP
    bus.publish("/estop_release", Bool(True))
    assert mux.state is MuxState.ESTOP  # the e-stop source still asserts
    assert not mux.release_estop()
    bus.publish("/estop", Bool(False))
    assert mux.state is MuxState.ESTOP  # false does not release by itself
    bus.publish("/estop_release", Bool(False))
    assert mux.state is MuxState.ESTOP  # a false release does nothing
    bus.publish("/estop_release", Bool(True))
    assert mux.state is MuxState.RUNNING
    # every true re-engages
    bus.publish("/estop", Bool(True))
    assert mux.state is MuxState.ESTOP


def test_start_estopped():
    bus, mux, _clock = _mux(start_estopped=True)
    bus.publish(TELEOP, _cmd(1.0))
    assert mux.arbitrate().source == "estop"
    assert mux.release_estop()
    assert mux.arbitrate().source == "teleop"


def test_unexpected_exception_in_a_filter_faults_until_reset(caplog):
    bus, mux, clock = _mux(limiter_enabled=False)
    bus.publish(TELEOP, _cmd(2.0, 0.2))

    def broken(drive: AckermannDrive, source: str, now_ns: int) -> AckermannDrive:
        raise ZeroDivisionError("bug in a filter")

    with caplog.at_level("ERROR", logger="mux.node"):
        out = mux.step(filters=[broken]).drive
    assert "bug in a filter" in caplog.text
    assert (out.speed, out.steering_angle) == (0.0, 0.0)
    assert mux.state is MuxState.FAULT
    assert mux.faults == 1
    # the fault stays: no filter now, fresh input, e-stop release: still zero
    bus.publish(TELEOP, _cmd(2.0, 0.2))
    assert not mux.release_estop()
    assert mux.step().drive == AckermannDrive()
    assert mux.source == "fault"
    assert mux.reset() is MuxState.ESTOP
    assert mux.step().drive.speed == 0.0
    assert mux.release_estop()
    assert mux.step().drive.speed == 2.0


def test_malformed_input_message_faults_the_mux():
    bus, mux, _clock = _mux()
    bus.publish(TELEOP, AckermannDriveStamped(drive=None))  # type: ignore[arg-type]
    assert mux.state is MuxState.FAULT
    assert "input teleop" in mux.machine.reason
    assert mux.step().drive == AckermannDrive()


def test_non_finite_command_counts_as_a_stop_from_that_source():
    bus, mux, _clock = _mux(limiter_enabled=False)
    bus.publish(TELEOP, _cmd(float("nan"), 0.2))
    arb = mux.arbitrate()
    assert arb.source == "teleop"  # it holds the slot, so nav cannot sneak in
    assert arb.drive == AckermannDrive()
    assert mux.rejected["teleop"] == 1
    assert mux.state is MuxState.RUNNING


def test_diagnostics_report_state_inputs_locks():
    locks = [LockParams("deadman", "/deadman", 50, 0.5)]
    bus, mux, clock = _mux(locks=locks)
    got: list[DiagnosticArray] = []
    bus.subscribe("/diagnostics", got.append)
    bus.publish(TELEOP, _cmd(1.0))
    clock.advance(0.05)
    mux.step()
    mux.publish_diagnostics()
    status = got[-1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == DiagnosticStatus.OK
    assert status.message == "active: teleop"
    assert values["active"] == "teleop"
    assert values["input teleop (priority 90)"] == "fresh, age 0.050 s"
    assert values["input safety (priority 100)"] == "never received"
    assert values["input nav_0 (priority 20)"] == "never received, masked"
    assert values["lock deadman (priority 50)"] == "engaged (never heard: deadman)"
    mux.engage_estop("diag test")
    mux.publish_diagnostics()
    status = got[-1].status[0]
    assert status.level == DiagnosticStatus.WARN
    assert "diag test" in status.message
    clock.advance(1.0)
    values = {kv.key: kv.value for kv in mux.diagnostics().status[0].values}
    assert values["input teleop (priority 90)"] == "expired, age 1.050 s"


def test_topic_type_conflict_is_refused_at_construction():
    bus = Bus()
    bus.publish(TELEOP, Bool(True))
    with pytest.raises(TopicTypeError):
        CommandMux(bus, MuxParams())


def test_close_unsubscribes_and_is_safe_twice():
    bus, mux, _clock = _mux()
    mux.close()
    mux.close()
    bus.publish(TELEOP, _cmd(1.0))
    assert mux.arbitrate().source == "idle"


def _control_loop(mux: CommandMux, filters: list[Filter] | tuple[()] = ()) -> PeriodicTimer:
    """The daemon's control loop around ``mux``: a :class:`PeriodicTimer` at ``rate_hz`` calling
    :meth:`CommandMux.step`, diagnostics every ``rate_hz / diagnostics_rate_hz`` ticks."""
    every = max(1, round(mux.params.rate_hz / mux.params.diagnostics_rate_hz))

    def tick(due: int, periods: int) -> None:
        mux.step(due, filters, periods)
        if timer.count % every == 1:
            mux.publish_diagnostics(due)

    timer = PeriodicTimer(mux.params.rate_hz, tick)
    return timer


def test_node_at_50hz_keeps_publishing_while_inputs_are_silent():
    async def scenario() -> None:
        bus = Bus()
        mux = MuxNode(bus, MuxParams())
        outputs: list[tuple[int, AckermannDriveStamped]] = []
        diagnostics: list[DiagnosticArray] = []
        bus.subscribe(OUTPUT, lambda msg: outputs.append((monotonic_ns(), msg)))
        bus.subscribe("/diagnostics", diagnostics.append)
        start = monotonic_ns()
        loop = _control_loop(mux)
        loop.start()
        try:
            await async_wait_for(lambda: len(outputs) >= 3, timeout=20)

            async def teleop_until_moving() -> None:
                while not any(m.drive.speed > 0 for _t, m in outputs):
                    bus.publish(TELEOP, _cmd(1.0))
                    await asyncio.sleep(0.01)

            # teleop until the car moves, then silence
            await asyncio.wait_for(teleop_until_moving(), timeout=20)
            await async_wait_for(lambda: mux.source == "idle" and len(outputs) >= 60, timeout=30)
            silent_from = len(outputs)
            await async_wait_for(lambda: len(outputs) >= silent_from + 25, timeout=30)
            elapsed = monotonic_ns() - start
        finally:
            loop.cancel()
        count = len(outputs)
        # never more than one message per 20 ms deadline (no bursts)
        assert count <= elapsed / nanoseconds(0.02) + 2
        tail = [m for _t, m in outputs[silent_from:]]
        assert all(m.header.frame_id == "base_link" for m in tail)
        assert tail[-1].drive.speed == pytest.approx(0.0, abs=1e-9)  # braked to zero while silent
        assert diagnostics, "diagnostics at ~2 Hz"
        assert mux.state is MuxState.RUNNING

    asyncio.run(scenario())


def test_node_that_falls_behind_skips_deadlines():
    async def scenario() -> None:
        bus = Bus()
        mux = CommandMux(bus, MuxParams())
        ticks: list[int] = []

        def stall_once(drive: AckermannDrive, source: str, now_ns: int) -> AckermannDrive:
            ticks.append(now_ns)
            if len(ticks) == 5:
                time.sleep(0.1)  # the loop falls behind by about 5 periods
            return drive

        loop = _control_loop(mux, [stall_once])
        loop.start()
        try:
            await async_wait_for(lambda: len(ticks) >= 15, timeout=30)
        finally:
            loop.cancel()
        assert mux.overruns >= 3 and mux.overruns == loop.missed
        assert mux.state is MuxState.RUNNING
        # a catch-up burst would run the next 5 ticks back to back; on the grid each waits for its
        # own deadline, so 5 ticks span at least 3 whole periods
        after = ticks[5:10]
        assert len(after) == 5
        assert after[-1] - after[0] > nanoseconds(0.04)

    asyncio.run(scenario())


def test_an_early_step_sends_the_next_ticks_output_now_without_taking_the_limiters_step():
    bus, mux, clock = _mux()
    outputs: list[AckermannDriveStamped] = []
    bus.subscribe(OUTPUT, outputs.append)
    mux.step()
    bus.publish(NAV0, _cmd(2.0, 0.2))
    early = mux.step_early("nav_0")
    assert early is outputs[-1] and early is mux.last_output
    assert early.drive.speed == pytest.approx(2.5 / 50)            # one limiter step, not more
    assert mux.limiter.speed == 0.0                                 # the step is not taken yet
    again = mux.step_early("nav_0")                                 # a second early step: the same
    assert again.drive.speed == pytest.approx(2.5 / 50)
    clock.advance(0.02)
    tick = mux.step()
    assert tick.drive.speed == pytest.approx(2.5 / 50) and mux.limiter.speed == pytest.approx(2.5 / 50)
    bus.publish(TELEOP, _cmd(1.0))
    assert mux.step_early("nav_0") is None                          # nav_0 no longer wins
    mux.engage_estop("test")
    assert mux.step_early("teleop") is None                         # never while e-stopped


def test_decide_publishes_nothing_until_publish_output_which_announces_the_switch_first():
    bus, mux, _clock = _mux(limiter_enabled=False)
    seen: list[str] = []
    bus.subscribe(f"{LOW}/active", lambda msg: seen.append(f"active {msg.data}"))
    bus.subscribe(OUTPUT, lambda msg: seen.append(f"output {msg.drive.speed}"))
    bus.publish(TELEOP, _cmd(1.5))
    msg = mux.decide()
    assert msg.drive.speed == 1.5 and mux.last_output is msg and mux.source == "teleop"
    assert seen == []  # taken (the switch recorded, the limiter stepped), nothing on the bus yet
    mux.publish_output(msg)
    assert seen == ["active teleop", "output 1.5"]
    assert mux.decide_early("nav_0") is None  # not the winner: nothing decided
    early = mux.decide_early("teleop")
    assert early is not None and early.drive.speed == 1.5 and seen == ["active teleop", "output 1.5"]


def test_cut_outputs_the_slower_command_past_arbitration_and_clamps_the_limiter():
    bus, mux, _clock = _mux()
    out: list[float] = []
    bus.subscribe(OUTPUT, lambda msg: out.append(msg.drive.speed))
    mux.limiter.reset(speed=2.0, steering_angle=0.2)
    cut = mux.cut(AckermannDrive(steering_angle=0.2, speed=0.4))
    assert cut.drive.speed == 0.4 and cut.drive.steering_angle == 0.2 and mux.limiter.speed == 0.4
    assert out == [] and mux.last_output is cut  # published by publish_output, after the write
    mux.engage_estop("test")
    assert mux.cut(AckermannDrive(speed=0.2)).drive == AckermannDrive()  # the e-stop still brakes
