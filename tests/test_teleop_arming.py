"""The shared armed state and its mux filter."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mux.node import CommandMux
from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped
from racecar_hw.teleop.arming import Arming, ArmingChange, ArmingParams

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


def test_starts_as_configured_and_reports_changes() -> None:
    assert not Arming.from_params(ArmingParams()).armed  # the car starts disarmed
    arming = Arming.from_params(ArmingParams(start_armed=True))  # the simulation starts armed
    assert arming.armed and arming.source == "config"
    seen: list[ArmingChange] = []
    remove = arming.on_change(seen.append)
    assert arming.disarm("gamepad", "BACK")
    assert not arming.disarm("gcs")  # no change, no callback
    assert arming.arm("gcs")
    assert [(c.armed, c.source) for c in seen] == [(False, "gamepad"), (True, "gcs")]
    assert arming.reason == "armed by gcs" and arming.changes == 2
    remove()
    arming.disarm("gamepad")
    assert len(seen) == 2


def test_a_failing_callback_does_not_stop_the_change() -> None:
    arming = Arming()
    arming.on_change(lambda c: 1 / 0)
    assert arming.arm("gcs") and arming.armed


@given(st.floats(allow_nan=True), st.floats(allow_nan=True), st.booleans())
def test_filter_stops_everything_while_disarmed(speed: float, steer: float, armed: bool) -> None:
    arming = Arming(start_armed=armed)
    drive = AckermannDrive(steering_angle=steer, speed=speed)
    out = arming.filter(drive, "teleop", 0)
    if armed:
        assert out is drive
    else:
        assert (out.speed, out.steering_angle) == (0.0, 0.0)


def test_filter_in_the_mux_zeroes_every_source_until_armed() -> None:
    bus = Bus()
    mux = CommandMux(bus, MuxParams(limiter_enabled=False))
    arming = Arming()
    bus.publish("/vesc/high_level/ackermann_cmd_mux/input/nav_0",
                AckermannDriveStamped(drive=AckermannDrive(steering_angle=0.2, speed=1.5)))
    out = mux.step(filters=[arming.filter])
    assert (out.drive.speed, out.drive.steering_angle) == (0.0, 0.0) and arming.blocked == 1
    arming.arm("test")
    out = mux.step(filters=[arming.filter])
    assert (out.drive.speed, out.drive.steering_angle) == (1.5, 0.2)
    mux.close()
