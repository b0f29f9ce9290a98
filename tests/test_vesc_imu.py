"""The IMU: the reply in SI units as sensor_msgs/Imu, the gyro bias at standstill, the fake's model,
and the real driver polling the fake VESC's IMU over a pty."""

from __future__ import annotations

import asyncio
import math

import pytest
from conftest import async_wait_for

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns
from vesc.codec import ImuData
from vesc.driver import TOPIC_IMU, VescDriver
from vesc.imu import G, GyroBias, ImuCovariances, imu_message
from vesc.imu_model import ImuErrors, ImuModel, PlanarMotion
from vesc.odometry import OdometryIntegrator
from vesc.params import VescParams

COV = ImuCovariances(0.001, 100.0, 2e-6, 2.5e-4)
EXACT = ImuErrors(gyro_bias_dps=0.0, gyro_noise_dps=0.0, accel_noise_g=0.0, vibration_g=0.0)


def test_imu_message_is_in_si_units_with_its_frame_and_covariances():
    data = ImuData(gyro_x=0.0, gyro_y=0.0, gyro_z=90.0, acc_x=0.5, acc_y=0.0, acc_z=1.0,
                   q0=math.cos(0.25), q1=0.0, q2=0.0, q3=math.sin(0.25))
    msg = imu_message(data, 1_500_000_000, "imu", COV)
    assert msg.header.frame_id == "imu"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 500_000_000)
    assert msg.angular_velocity.z == pytest.approx(math.pi / 2)
    assert msg.linear_acceleration.x == pytest.approx(0.5 * G)
    assert msg.linear_acceleration.z == pytest.approx(G)
    assert msg.orientation.yaw() == pytest.approx(0.5)
    assert list(msg.orientation_covariance[[0, 4, 8]]) == [0.001, 0.001, 100.0]
    assert list(msg.angular_velocity_covariance[[0, 4, 8]]) == [2e-6] * 3
    assert list(msg.linear_acceleration_covariance[[0, 4, 8]]) == [2.5e-4] * 3


def test_a_reply_without_the_quaternion_says_orientation_not_provided():
    msg = imu_message(ImuData(gyro_x=0.0, gyro_y=0.0, gyro_z=10.0), 0, "imu", COV)
    assert msg.orientation_covariance[0] == -1.0
    assert msg.angular_velocity.z == pytest.approx(math.radians(10.0))


def _provided(cov) -> bool:
    return cov[0] != -1.0


def test_a_group_the_mask_leaves_out_is_not_provided():
    """sensor_msgs/Imu: covariance element 0 at -1 means no estimate. A gyro-only reply (mask
    0x01C0) has no acceleration and no orientation; an accelerometer-only one no rates; a gyro
    with z alone (mask 0x0100) no whole angular velocity."""
    gyro_only = imu_message(ImuData(gyro_x=1.0, gyro_y=2.0, gyro_z=3.0), 0, "imu", COV)
    assert not _provided(gyro_only.linear_acceleration_covariance)
    assert not _provided(gyro_only.orientation_covariance)
    assert _provided(gyro_only.angular_velocity_covariance)
    assert gyro_only.angular_velocity.z == pytest.approx(math.radians(3.0))
    assert (gyro_only.linear_acceleration.x, gyro_only.linear_acceleration.z) == (0.0, 0.0)
    acc_only = imu_message(ImuData(acc_x=0.1, acc_y=0.0, acc_z=1.0), 0, "imu", COV)
    assert not _provided(acc_only.angular_velocity_covariance)
    assert _provided(acc_only.linear_acceleration_covariance)
    assert acc_only.linear_acceleration.z == pytest.approx(G)
    z_only = imu_message(ImuData(gyro_z=3.0), 0, "imu", COV)
    assert not _provided(z_only.angular_velocity_covariance)
    assert list(z_only.angular_velocity_covariance[1:]) == [0.0] * 8


@pytest.mark.parametrize("quat", [(0.0, 0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0)])
def test_a_quaternion_that_is_no_rotation_says_orientation_not_provided(quat):
    """All zeros (an IMU not yet running) or a norm far from 1 (damaged) is no orientation."""
    msg = imu_message(ImuData(gyro_x=0.0, gyro_y=0.0, gyro_z=10.0, q0=quat[0], q1=quat[1], q2=quat[2],
                              q3=quat[3]), 0, "imu", COV)
    assert msg.orientation_covariance[0] == -1.0
    assert msg.angular_velocity.z == pytest.approx(math.radians(10.0))


def test_gyro_bias_is_learned_at_standstill_and_held_while_moving():
    bias = GyroBias(tau_s=1.0)
    t = 0
    for _ in range(200):  # 2 s still at 100 Hz, the gyro reading 0.05 rad/s
        t += 10_000_000
        bias.update(0.05, True, t)
    assert bias.settled and bias.bias == pytest.approx(0.05, abs=1e-6)
    for _ in range(100):  # moving: a turn's rate must not leak into the bias
        t += 10_000_000
        bias.update(1.0, False, t)
    assert bias.bias == pytest.approx(0.05, abs=1e-6)
    assert not GyroBias(1.0).settled


def test_the_model_feels_gravity_the_turn_and_the_lever_arm():
    v, w = 2.0, 0.5
    model = ImuModel(lambda: PlanarMotion(v, w, 0.0, 0.0), mount=(0.2, 0.0, 0.0), errors=EXACT)
    model.sample(0.0)
    data = model.sample(1.0)
    assert data.gyro_z == pytest.approx(math.degrees(w))
    assert data.acc_z == pytest.approx(1.0)
    # centripetal v*omega to the left; the lever arm forward adds -omega^2 x on x
    assert data.acc_y * G == pytest.approx(v * w, rel=1e-6)
    assert data.acc_x * G == pytest.approx(-w * w * 0.2, rel=1e-6)
    # one second at 0.5 rad/s: the quaternion's yaw, and the firmware's negated yaw field
    yaw = 2 * math.atan2(data.q3, data.q0)
    assert yaw == pytest.approx(0.5) and data.yaw == pytest.approx(-0.5)


def test_a_mount_turned_90_degrees_sees_the_forward_acceleration_on_minus_y():
    model = ImuModel(lambda: PlanarMotion(1.0, 0.0, 3.0, 0.0), mount=(0.0, 0.0, math.pi / 2), errors=EXACT)
    data = model.sample(0.0)
    assert data.acc_x == pytest.approx(0.0, abs=1e-9)
    assert data.acc_y * G == pytest.approx(-3.0)


def test_the_model_is_repeatable_for_a_seed():
    def run(seed: int) -> list[float]:
        model = ImuModel(lambda: PlanarMotion(1.0, 0.2, 0.0, 0.0), seed=seed)
        return [model.sample(i * 0.02).gyro_z for i in range(50)]
    assert run(3) == run(3) and run(3) != run(4)


def test_the_model_reports_the_mean_acceleration_since_its_last_sample():
    """The world's speed rises in steps (at the 50 Hz command rate, held over its 5 ms steps), so
    its acceleration over the last step is 0 at most instants: a 50 Hz sample must still feel
    the mean acceleration since the previous sample, as a real accelerometer's low-pass does."""
    t = 0.0

    def staircase() -> PlanarMotion:  # +0.05 m/s every 20 ms, flat within: 2.5 m/s²
        step = int(t / 0.02 + 1e-9)
        return PlanarMotion(0.05 * step, 0.0, 0.0, 0.0)

    model = ImuModel(staircase, errors=EXACT)
    model.sample(t)
    seen = []
    for _ in range(10):
        t += 0.02
        seen.append(model.sample(t).acc_x * G)
    assert seen == pytest.approx([2.5] * 10)
    assert model.sample(t).acc_x * G == pytest.approx(2.5)  # again at the same instant: the same mean


def test_in_lockstep_the_imu_feels_the_car_speed_up():
    """The real daemon on the simulated car: while it speeds up, /imu's forward acceleration
    averages the world's dv/dt (it read about 0 from the last 5 ms world step)."""
    from racecar_hw.sim.env import RaceEnv

    seen: list = []
    with RaceEnv("corridor", overrides=["safety.mode=off"]) as env:
        env.reset()
        env.daemon.bus.subscribe(TOPIC_IMU, seen.append)
        for _ in range(25):
            env.step((0.0, 0.0))
        v0, t0, n0 = env.world.speed, env.time_s, len(seen)
        for _ in range(25):
            env.step((3.0, 0.0))
        dv_dt = (env.world.speed - v0) / (env.time_s - t0)
        ax = [m.linear_acceleration.x for m in seen[n0:]]
    assert dv_dt > 1.5 and len(ax) >= 20
    assert sum(ax) / len(ax) == pytest.approx(dv_dt, rel=0.15)


def test_odometry_takes_a_gyro_yaw_rate_in_place_of_the_steering_model():
    odo = OdometryIntegrator.from_params(VescParams())
    odo.update(4614.0, 0.5304, 0)
    odo.update(4614.0, 0.5304, 1_000_000_000, yaw_rate=0.3)
    assert odo.yaw_rate == 0.3 and odo.pose.yaw == pytest.approx(0.15)  # midpoint: (0 + 0.3) / 2


def _standing_fake(device_thread, tmp_path, gyro_bias_dps: float, **kw) -> tuple:
    """A fake VESC standing still whose gyro reads ``gyro_bias_dps`` and nothing else, a bus, and
    the list of what the driver publishes on /imu."""
    from test_vesc_driver import start_fake

    fake = start_fake(device_thread, tmp_path / "vesc", **kw)
    fake.imu.motion = lambda: PlanarMotion(0.0, 0.0, 0.0, 0.0)
    fake.imu.errors = ImuErrors(gyro_bias_dps=gyro_bias_dps, gyro_noise_dps=0.0, accel_noise_g=0.0,
                                vibration_g=0.0)
    bus = Bus()
    seen: list = []
    bus.subscribe(TOPIC_IMU, seen.append)
    return fake, bus, seen


@pytest.mark.parametrize("firmware", [(6, 2), (6, 5)])
def test_the_driver_polls_the_fake_imu_and_publishes_it(tmp_path, device_thread, firmware):
    fake, bus, seen = _standing_fake(device_thread, tmp_path, 2.0, firmware=firmware)

    async def scenario() -> None:
        params = VescParams(port=fake.path, odometry_yaw_rate="imu", imu_bias_time_s=0.3)
        async with VescDriver(bus, params) as driver:
            await async_wait_for(lambda: len(seen) >= 40 and driver.gyro_bias.settled, timeout=20)
            assert driver.gyro_bias.bias == pytest.approx(math.radians(2.0), rel=1e-3)

    asyncio.run(scenario())
    msg = seen[-1]
    assert msg.header.frame_id == "imu"
    assert msg.linear_acceleration.z == pytest.approx(G, rel=1e-5)
    assert msg.angular_velocity.z == pytest.approx(math.radians(2.0), rel=1e-5)  # published as measured


def test_imu_replies_beyond_the_sensors_full_scale_are_dropped_and_spare_the_gyro_bias(
        tmp_path, device_thread):
    """A gyro reading past +-2000 deg/s (finite, so not refused by the codec) is never published
    and never reaches the gyro bias or the odometry; plausible replies after it are."""
    fake, bus, seen = _standing_fake(device_thread, tmp_path, 5.0e6)

    async def scenario() -> None:
        params = VescParams(port=fake.path, odometry_yaw_rate="imu", imu_bias_time_s=0.3)
        async with VescDriver(bus, params) as driver:
            await async_wait_for(lambda: driver.stats.implausible_imu >= 20, timeout=20)
            assert seen == [] and driver.gyro_bias.bias == 0.0
            fake.imu.errors = ImuErrors(gyro_bias_dps=2.0, gyro_noise_dps=0.0, accel_noise_g=0.0,
                                        vibration_g=0.0)
            await async_wait_for(lambda: len(seen) >= 40 and driver.gyro_bias.settled, timeout=20)
            assert driver.gyro_bias.bias == pytest.approx(math.radians(2.0), rel=1e-3)

    asyncio.run(scenario())
    assert all(abs(m.angular_velocity.z) < 1.0 for m in seen)


def test_the_driver_publishes_a_reply_without_the_gyro_as_rates_not_provided(tmp_path, device_thread):
    """An accelerometer-only reply (mask 0x0038) is published with its acceleration, the rates and
    orientation marked not provided; it reaches neither the gyro bias nor odometry."""
    fake, bus, seen = _standing_fake(device_thread, tmp_path, 2.0)
    full = fake.imu.sample
    fake.imu.sample = lambda t_s, mask=0xFFFF: full(t_s, 0x0038)

    async def scenario() -> None:
        params = VescParams(port=fake.path, odometry_yaw_rate="imu", imu_bias_time_s=0.1)
        async with VescDriver(bus, params) as driver:
            await async_wait_for(lambda: len(seen) >= 10, timeout=20)
            assert driver.gyro_bias.still_s == 0.0 and driver._gyro_yaw_rate(monotonic_ns()) is None

    asyncio.run(scenario())
    msg = seen[-1]
    assert msg.linear_acceleration.z == pytest.approx(G, rel=1e-5)
    assert msg.linear_acceleration_covariance[0] > 0.0
    assert msg.angular_velocity_covariance[0] == -1.0 and msg.orientation_covariance[0] == -1.0


def test_old_firmware_is_not_asked_for_the_imu(tmp_path, device_thread):
    from test_vesc_driver import start_fake

    from vesc.codec import GetImuDataRequest, GetValuesRequest

    fake = start_fake(device_thread, tmp_path / "vesc", firmware=(3, 40))
    bus = Bus()
    seen = []
    bus.subscribe(TOPIC_IMU, seen.append)

    async def scenario() -> None:
        async with VescDriver(bus, VescParams(port=fake.path)) as driver:
            await async_wait_for(lambda: driver.connected and sum(
                isinstance(r.packet, GetValuesRequest) for r in fake.commands) >= 10, timeout=20)

    asyncio.run(scenario())
    assert not any(isinstance(r.packet, GetImuDataRequest) for r in fake.commands)
    assert seen == []
