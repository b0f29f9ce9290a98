"""The lab 0 set-point relay: pose parsing, set-points, limits, streaming on the bus, and the ticker."""

from __future__ import annotations

import asyncio
import math

import pytest
from conftest import async_wait_for
from hypothesis import given, settings
from hypothesis import strategies as st

from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDriveStamped, Float64, String
from racecar_hw.base.params import build
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.sources.setpoint import NAV0_TOPIC, Pose2D, SetpointParams, SetpointRelay, parse_pose

finite = st.floats(-1e6, 1e6, allow_nan=False)


def test_parse_pose() -> None:
    assert parse_pose("0,0,0") == Pose2D(0.0, 0.0, 0.0)
    assert parse_pose(" 1.5, -2 ,3.14159") == Pose2D(1.5, -2.0, 3.14159)
    pose = parse_pose("1,2,1.5707963").to_pose()
    assert (pose.position.x, pose.position.y, pose.position.z) == (1.0, 2.0, 0.0)
    assert pose.orientation.yaw() == pytest.approx(1.5707963)


@pytest.mark.parametrize("text", ["", "1,2", "1,2,3,4", "a,0,0", "0,0,nan", "0,inf,0", "1;2;3", "0,,0"])
def test_parse_pose_refuses(text: str) -> None:
    with pytest.raises(ValueError):
        parse_pose(text)


@settings(deadline=None)
@given(finite, finite, finite)
def test_parse_pose_round_trip(x: float, y: float, theta: float) -> None:
    assert parse_pose(f"{x!r},{y!r},{theta!r}") == Pose2D(x, y, theta)


@settings(deadline=None)
@given(st.text(max_size=30))
def test_parse_pose_only_raises_value_error(text: str) -> None:
    try:
        pose = parse_pose(text)
    except ValueError:
        return
    assert all(math.isfinite(v) for v in (pose.x, pose.y, pose.theta))


def test_params() -> None:
    p = build(SetpointParams, {}, "setpoint")
    assert (p.topic, p.rate_hz) == (NAV0_TOPIC, 20.0)
    with pytest.raises(ConfigError) as info:
        build(SetpointParams, {"initial_pose": "0,0"}, "setpoint")
    assert "initial_pose" in str(info.value)
    with pytest.raises(ConfigError) as info:
        build(SetpointParams, {"rate_hz": 0.5}, "setpoint")
    assert info.value.key == "setpoint.rate_hz"


def test_set_points_limits_and_reset() -> None:
    poses: list[Pose2D] = []
    relay = SetpointRelay(Bus(), SetpointParams(initial_pose="1,2,0.5"), on_initial_pose=poses.append)
    assert poses == [Pose2D(1.0, 2.0, 0.5)] and relay.initial_pose == poses[0]
    relay.set_velocity(2.0)
    relay.set_steering_angle(-0.09)
    cmd = relay.command(stamp_ns=1_500_000_000)
    assert (cmd.drive.speed, cmd.drive.steering_angle) == (2.0, -0.09)
    assert cmd.header.frame_id == "base_link" and cmd.header.stamp.sec == 1
    for bad in (math.nan, math.inf, 2.5, -3.0):
        with pytest.raises(ValueError):
            relay.set_velocity(bad)
    with pytest.raises(ValueError):
        relay.set_steering_angle(0.5)
    assert (relay.velocity, relay.steering_angle) == (2.0, -0.09)  # refused values change nothing
    relay.reset()
    assert (relay.velocity, relay.steering_angle) == (0.0, 0.0)
    relay.set_initial_pose(Pose2D(0.0, 0.0, 0.0))
    assert len(poses) == 2


def test_relay_streams_set_points_from_the_bus() -> None:
    """The seed's publishing trace: pose, 2 m/s, 0.09 rad, then -0.09 rad, then stop."""
    bus = Bus()
    got: list[AckermannDriveStamped] = []
    bus.subscribe(NAV0_TOPIC, got.append)
    poses: list[Pose2D] = []
    relay = SetpointRelay(bus, SetpointParams(rate_hz=100.0), on_initial_pose=poses.append)

    def last() -> tuple[float, float]:
        return (got[-1].drive.speed, got[-1].drive.steering_angle) if got else (math.nan, math.nan)

    async def scenario() -> None:
        task = asyncio.create_task(relay.run())
        await async_wait_for(lambda: len(got) >= 3)
        assert last() == (0.0, 0.0)
        bus.publish("/lab0/initialpose", String("0,0,0.0"))
        bus.publish("/lab0/velocity", Float64(2.0))
        bus.publish("/lab0/steering_angle", Float64(0.09))
        await async_wait_for(lambda: last() == pytest.approx((2.0, 0.09)))
        bus.publish("/lab0/steering_angle", Float64(-0.09))
        await async_wait_for(lambda: last() == pytest.approx((2.0, -0.09)))
        # a refused set-point keeps the car on the last good one
        bus.publish("/lab0/velocity", Float64(math.nan))
        bus.publish("/lab0/initialpose", String("here"))
        n = len(got)
        await async_wait_for(lambda: len(got) >= n + 3)
        assert last() == pytest.approx((2.0, -0.09))
        relay.reset()
        await async_wait_for(lambda: last() == (0.0, 0.0))
        bus.publish("/lab0/velocity", Float64(1.0))
        await async_wait_for(lambda: last() == (1.0, 0.0))
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(scenario())
    assert poses == [Pose2D(0.0, 0.0, 0.0)]
    assert relay.rejected == 2
    assert relay.published == len(got)
    assert last() == (0.0, 0.0)  # the stop sent on exit
    # after run() ends the relay no longer listens
    bus.publish("/lab0/velocity", Float64(1.5))
    assert relay.velocity == 0.0
    stamps = [m.header.stamp.to_ns() for m in got]
    assert stamps == sorted(stamps)


def test_ticker_keeps_absolute_deadlines() -> None:
    now = {"ns": 0}
    slept: list[float] = []

    async def fake_sleep(seconds: float) -> None:
        slept.append(seconds)
        now["ns"] += round(seconds * 1e9)

    ticker = Ticker(20.0, clock=lambda: now["ns"], sleep=fake_sleep)

    async def scenario() -> list[int]:
        dues = [await ticker.tick()]          # first tick at once
        now["ns"] += 10_000_000               # 10 ms of work
        dues.append(await ticker.tick())      # sleeps the remaining 40 ms
        now["ns"] += 120_000_000              # stalled until 170 ms: 100 ms and 150 ms have passed
        dues.append(await ticker.tick())      # 100 ms is skipped, 150 ms runs late at once
        dues.append(await ticker.tick())      # back on schedule
        ticker.reset()
        dues.append(await ticker.tick())      # a new schedule starts now
        return dues

    dues = asyncio.run(scenario())
    assert dues == [0, 50_000_000, 150_000_000, 200_000_000, 200_000_000]
    assert slept == [pytest.approx(0.04), pytest.approx(0.03)]
    assert ticker.missed == 1 and ticker.count == 5
    with pytest.raises(ValueError):
        Ticker(0.0)
