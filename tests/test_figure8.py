"""The analytical figure-8: loop timing, the command at any time, a closed path, a run on the bus."""

from __future__ import annotations

import asyncio
import math

import pytest
from conftest import async_wait_for
from hypothesis import given, settings
from hypothesis import strategies as st

from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import AckermannDriveStamped
from racecar_hw.base.params import build
from racecar_hw.sources.figure8 import (
    Figure8Driver,
    Figure8Params,
    figure8_command,
    loop_duration_s,
    turn_radius_m,
)
from racecar_hw.sources.setpoint import NAV0_TOPIC


def test_loop_timing() -> None:
    # 0.25 m wheelbase, 45 degrees: R = 0.25 m; at 0.5 m/s one loop is 2 pi 0.25 / 0.5 = pi s
    assert turn_radius_m(math.pi / 4, 0.25) == pytest.approx(0.25)
    assert loop_duration_s(0.5, math.pi / 4, 0.25) == pytest.approx(math.pi)
    assert loop_duration_s(-0.5, -math.pi / 4, 0.25) == pytest.approx(math.pi)
    p = Figure8Params(speed_mps=0.5, steering_angle_rad=math.pi / 4, wheelbase_m=0.25, figure8s=3)
    assert p.loop_s == pytest.approx(math.pi)
    assert p.duration_s == pytest.approx(6 * math.pi)
    assert Figure8Params(figure8s=0).duration_s is None


def test_command_left_then_right_then_stop() -> None:
    p = Figure8Params(speed_mps=1.0, steering_angle_rad=0.3, wheelbase_m=0.25, figure8s=1)
    t = p.loop_s
    assert figure8_command(0.0, p).steering_angle == pytest.approx(0.3)
    assert figure8_command(0.999 * t, p).steering_angle == pytest.approx(0.3)
    assert figure8_command(1.001 * t, p).steering_angle == pytest.approx(-0.3)
    assert figure8_command(1.999 * t, p).speed == pytest.approx(1.0)
    stop = figure8_command(2.0 * t, p)
    assert (stop.speed, stop.steering_angle) == (0.0, 0.0)
    assert figure8_command(-0.1, p).speed == 0.0


def test_command_repeats_until_cancelled() -> None:
    p = Figure8Params(steering_angle_rad=-0.2, figure8s=0)
    t = p.loop_s
    assert figure8_command(100.5 * t, p).steering_angle == pytest.approx(-0.2)  # loop 100: first side
    assert figure8_command(101.5 * t, p).steering_angle == pytest.approx(0.2)


@settings(max_examples=40, deadline=None)
@given(st.floats(0.3, 3.0), st.floats(0.1, 0.6), st.floats(0.15, 0.5), st.booleans())
def test_figure8_closes_on_itself(speed: float, steering: float, wheelbase: float, backwards: bool) -> None:
    """Integrating the kinematic bicycle under the commands returns the car to its start pose."""
    p = Figure8Params(speed_mps=-speed if backwards else speed, steering_angle_rad=steering,
                      wheelbase_m=wheelbase, figure8s=1)
    assert p.duration_s is not None
    steps = 2000
    dt = p.duration_s / steps
    x = y = yaw = 0.0
    max_left = 0.0
    for i in range(steps):
        cmd = figure8_command((i + 0.5) * dt, p)  # midpoint rule
        yaw_mid = yaw + 0.5 * dt * cmd.speed * math.tan(cmd.steering_angle) / wheelbase
        x += cmd.speed * math.cos(yaw_mid) * dt
        y += cmd.speed * math.sin(yaw_mid) * dt
        yaw += dt * cmd.speed * math.tan(cmd.steering_angle) / wheelbase
        max_left = max(max_left, abs(y))
    assert math.hypot(x, y) < 1e-2 * p.radius_m
    assert math.remainder(yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    assert max_left == pytest.approx(2 * p.radius_m, rel=1e-2)  # each loop is a full circle


@pytest.mark.parametrize(("data", "key"), [
    ({"speed_mps": 0.0}, "speed_mps"),
    ({"steering_angle_rad": 0.0}, "steering_angle_rad"),
    ({"steering_angle_rad": 1.0}, "fig8.steering_angle_rad"),
    ({"figure8s": -1}, "fig8.figure8s"),
])
def test_bad_params(data: dict[str, float], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        build(Figure8Params, data, "fig8")
    assert key in str(info.value)


def test_driver_runs_one_figure8_on_the_bus_and_stops() -> None:
    params = Figure8Params(speed_mps=3.0, steering_angle_rad=0.6, wheelbase_m=0.25, figure8s=1,
                           rate_hz=100.0, topic="/fig8")
    assert params.duration_s is not None and params.duration_s < 2.0
    bus = Bus()
    got: list[AckermannDriveStamped] = []
    bus.subscribe("/fig8", got.append)
    driver = Figure8Driver(bus, params)

    async def scenario() -> None:
        await asyncio.wait_for(driver.run(), timeout=60)

    asyncio.run(scenario())
    assert driver.finished
    assert len(got) == driver.published
    steer = [m.drive.steering_angle for m in got]
    # left commands, then right commands, then exactly one stop at the end
    first_right = next(i for i, s in enumerate(steer) if s < 0)
    assert first_right > 0
    assert all(s > 0 for s in steer[:first_right])
    assert all(s < 0 for s in steer[first_right:-1])
    assert got[-1].drive.speed == 0.0 and got[-1].drive.steering_angle == 0.0
    assert all(m.drive.speed == pytest.approx(3.0) for m in got[:-1])
    assert all(m.header.frame_id == "base_link" for m in got)
    stamps = [m.header.stamp.to_ns() for m in got]
    assert stamps == sorted(stamps)
    # every deadline up to the end either published or was counted as missed (a stall skips ahead)
    assert driver.ticker.count + driver.ticker.missed >= params.duration_s * 100


def test_driver_until_cancelled_sends_a_stop() -> None:
    bus = Bus()
    got: list[AckermannDriveStamped] = []
    bus.subscribe(NAV0_TOPIC, got.append)
    driver = Figure8Driver(bus, Figure8Params(figure8s=0, rate_hz=100.0))

    async def scenario() -> None:
        task = asyncio.create_task(driver.run())
        await async_wait_for(lambda: len(got) >= 10)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(scenario())
    assert not driver.finished
    assert got[-1].drive.speed == 0.0
    assert all(m.drive.speed == pytest.approx(1.0) for m in got[:-1])
