"""MAVLink ground-station link: a pymavlink ground station on loopback against MavlinkGcs on a real Bus."""

from __future__ import annotations

import asyncio
import hashlib
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import async_wait_for
from hypothesis import given
from hypothesis import strategies as st

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from mux.node import CommandMux  # noqa: E402
from mux.params import MuxParams  # noqa: E402
from racecar_hw.base.bus import Bus  # noqa: E402
from racecar_hw.base.clock import wall_ns  # noqa: E402
from racecar_hw.base.errors import ConfigError  # noqa: E402
from racecar_hw.base.messages import (  # noqa: E402
    AckermannDrive,
    AckermannDriveStamped,
    DiagnosticArray,
    DiagnosticStatus,
    LaserScan,
    Odometry,
    Quaternion,
    VescState,
    VescStateStamped,
)
from racecar_hw.teleop.arming import Arming  # noqa: E402
from racecar_hw.teleop.mavlink_gcs import (  # noqa: E402
    MavlinkGcs,
    MavlinkParams,
    load_signing_key,
    obstacle_bins,
    odom_to_ned,
    signing_timestamp,
    write_signing_key,
)

mav = mavutil.mavlink
TELEOP = "/vesc/low_level/ackermann_cmd_mux/input/teleop"


class Station:
    """A pymavlink ground station listening on an ephemeral loopback port; keeps what it received."""

    def __init__(self, url: str = "udpin:127.0.0.1:0") -> None:
        self.conn: Any = mavutil.mavlink_connection(url, source_system=255, source_component=190)
        self.got: list[Any] = []
        self.beating = False

    @property
    def port(self) -> int:
        return int(self.conn.port.getsockname()[1])

    def pump(self) -> None:
        while True:
            msg = self.conn.recv_msg()
            if msg is None:
                return
            if msg.get_type() != "BAD_DATA":
                self.got.append(msg)

    def find(self, kind: str, pred: Callable[[Any], bool] = lambda m: True) -> list[Any]:
        self.pump()
        return [m for m in self.got if m.get_type() == kind and pred(m)]

    async def wait(self, kind: str, pred: Callable[[Any], bool] = lambda m: True) -> Any:
        await async_wait_for(lambda: self.find(kind, pred))
        return self.find(kind, pred)[-1]

    def heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    async def beat(self, period: float = 0.3) -> None:
        while True:
            if self.beating:
                self.heartbeat()
            await asyncio.sleep(period)

    def close(self) -> None:
        self.conn.close()


class Recorder:
    def __init__(self, bus: Bus) -> None:
        self.drives: list[tuple[float, float]] = []
        bus.subscribe(TELEOP, lambda m: self.drives.append((m.drive.speed, m.drive.steering_angle)))


async def stop(task: asyncio.Task[None]) -> None:
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task


def ack_of(command: int) -> Callable[[Any], bool]:
    return lambda m: m.command == command


def test_loopback_session_heartbeat_arm_drive_disarm_timeout_params_modes() -> None:
    async def main() -> None:
        bus = Bus()
        arming = Arming(start_armed=False)
        mux = CommandMux(bus, MuxParams(limiter_enabled=False))
        rec = Recorder(bus)
        gs = Station()
        params = MavlinkParams(enabled=True, gcs_address=f"127.0.0.1:{gs.port}", bind_port=0, rate_hz=50.0)
        link = MavlinkGcs(bus, params, arming)
        task = asyncio.create_task(link.run())
        beats = asyncio.create_task(gs.beat())
        hb = await gs.wait("HEARTBEAT")
        assert hb.type == mav.MAV_TYPE_GROUND_ROVER and hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert mavutil.mode_string_v10(hb) == "MANUAL"  # as MAVProxy names it
        assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED and hb.custom_mode == 0  # MANUAL
        assert gs.find("SYS_STATUS")
        assert link.port != 0

        # manual control without a ground-station heartbeat is ignored
        gs.conn.mav.manual_control_send(1, 0, 0, 500, 0, 0)
        await async_wait_for(lambda: link.counters["inputs_ignored"] == 1)
        gs.beating = True
        await async_wait_for(lambda: link.gcs_alive)
        await gs.wait("STATUSTEXT", lambda m: "GCS connected" in m.text)

        gs.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM))
        assert ack.result == mav.MAV_RESULT_ACCEPTED and arming.armed and arming.source == "gcs"
        await gs.wait("HEARTBEAT", lambda m: m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)

        # ArduPilot Rover: z = throttle (+ forward), y = steering (+ right)
        gs.conn.mav.manual_control_send(1, 0, 500, 1000, 0, 0)
        await async_wait_for(lambda: rec.drives and rec.drives[-1][0] > 0)
        assert rec.drives[-1] == pytest.approx((2.0, -0.17))
        assert link.teleop_active
        out = mux.step(filters=[arming.filter, link.filter])
        assert (out.drive.speed, out.drive.steering_angle) == pytest.approx((2.0, -0.17))

        gs.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0)
        await async_wait_for(lambda: not arming.armed)
        assert gs.find("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM))[-1].result == 0
        out = mux.step(filters=[arming.filter, link.filter])
        assert rec.drives[-1][0] > 0  # the ground station still asks ...
        assert (out.drive.speed, out.drive.steering_angle) == (0.0, 0.0)  # ... the arming filter stops it
        assert arming.blocked >= 1

        # RC override: ch1 full left (1000 µs), ch3 half forward (1750 µs); 0 releases
        gs.conn.mav.rc_channels_override_send(1, 1, 1000, 65535, 1750, 65535, 65535, 65535, 65535, 65535)
        await async_wait_for(lambda: rec.drives[-1] == pytest.approx((1.0, 0.34)))
        gs.conn.mav.rc_channels_override_send(1, 1, 0, 65535, 0, 65535, 65535, 65535, 65535, 65535)
        await async_wait_for(lambda: not link.teleop_active)
        assert rec.drives[-1] == (0.0, 0.0)

        # parameters: a short read-only list, answered in full
        gs.conn.mav.param_request_list_send(1, 1)
        await async_wait_for(lambda: len(gs.find("PARAM_VALUE")) >= 4)
        values = gs.find("PARAM_VALUE")
        assert sorted(v.param_index for v in values) == [0, 1, 2, 3]
        assert {v.param_count for v in values} == {4}
        assert {v.param_id for v in values} >= {"SYSID_THISMAV", "FS_GCS_TIMEOUT"}

        # modes: DO_SET_MODE HOLD stops everything through the filter; SET_MODE; unknown commands
        arming.arm("test")
        gs.conn.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        ack = await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_DO_SET_MODE))
        assert ack.result == mav.MAV_RESULT_ACCEPTED and link.mode_name == "HOLD"
        await gs.wait("HEARTBEAT", lambda m: m.custom_mode == 4)
        bus.publish("/vesc/high_level/ackermann_cmd_mux/input/nav_0",
                    AckermannDriveStamped(drive=AckermannDrive(speed=1.0)))
        assert mux.step(filters=[arming.filter, link.filter]).drive.speed == 0.0
        gs.conn.mav.set_mode_send(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 15)
        ack = await gs.wait("COMMAND_ACK", ack_of(mav.MAVLINK_MSG_ID_SET_MODE))
        assert ack.result == mav.MAV_RESULT_ACCEPTED and link.mode_name == "GUIDED"
        gs.conn.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 1, 99, 0, 0, 0, 0, 0)
        await async_wait_for(lambda: len(gs.find("COMMAND_ACK", ack_of(mav.MAV_CMD_DO_SET_MODE))) == 2)
        assert gs.find("COMMAND_ACK", ack_of(mav.MAV_CMD_DO_SET_MODE))[-1].result == mav.MAV_RESULT_DENIED
        gs.conn.mav.command_long_send(1, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0,
                                      mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 0, 0, 0, 0, 0, 0)
        ack = await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_REQUEST_MESSAGE))
        assert ack.result == mav.MAV_RESULT_UNSUPPORTED
        assert link.counters["acks"] == link.counters["commands"] == 6
        gs.conn.mav.command_long_send(1, 1, mav.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0)
        await async_wait_for(lambda: link.mode_name == "MANUAL")

        # heartbeats stop: the teleop input is dropped with one zero command and a STATUSTEXT
        gs.conn.mav.manual_control_send(1, 0, 0, 500, 0, 0)
        await async_wait_for(lambda: rec.drives[-1] == pytest.approx((1.0, 0.0)))
        gs.beating = False
        sender = asyncio.create_task(keep_sending(gs))
        await gs.wait("STATUSTEXT", lambda m: "heartbeat lost" in m.text)
        assert link.counters["gcs_timeouts"] == 1 and not link.gcs_alive
        assert rec.drives[-1] == (0.0, 0.0)
        count = len(rec.drives)
        heartbeats = len(gs.find("HEARTBEAT"))
        await async_wait_for(lambda: len(gs.find("HEARTBEAT")) >= heartbeats + 2)
        assert len(rec.drives) == count  # manual control keeps coming, nothing is published
        assert link.counters["inputs_ignored"] > 1
        await stop(sender)
        await stop(beats)
        await stop(task)
        mux.close()
        gs.close()

    asyncio.run(main())


async def keep_sending(gs: Station) -> None:
    while True:
        gs.conn.mav.manual_control_send(1, 0, 0, 500, 0, 0)
        await asyncio.sleep(0.1)


def test_signing_refuses_unsigned_and_accepts_the_signed_station(tmp_path: Path) -> None:
    key_file = tmp_path / "mavlink.key"
    secret = write_signing_key(key_file)
    assert load_signing_key(str(key_file)) == secret
    assert key_file.stat().st_mode & 0o077 == 0

    async def main() -> None:
        bus = Bus()
        arming = Arming()
        gs = Station()
        gs.conn.setup_signing(secret, sign_outgoing=True, initial_timestamp=signing_timestamp(wall_ns()))
        params = MavlinkParams(enabled=True, gcs_address=f"127.0.0.1:{gs.port}", bind_port=0,
                               signing_key_file=str(key_file))
        link = MavlinkGcs(bus, params, arming)
        task = asyncio.create_task(link.run())
        await gs.wait("HEARTBEAT")
        assert gs.conn.mav.signing.goodsig_count >= 1  # our telemetry is signed

        rogue = Station(f"udpout:127.0.0.1:{link.port}")
        rogue.heartbeat()
        rogue.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        await async_wait_for(lambda: link.counters["unsigned_refused"] >= 2)
        assert not arming.armed and not link.gcs_alive and link.counters["acks"] == 0

        wrong = Station(f"udpout:127.0.0.1:{link.port}")
        wrong.conn.setup_signing(bytes(32), sign_outgoing=True,
                                 initial_timestamp=signing_timestamp(wall_ns()))
        wrong.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        await async_wait_for(lambda: link.counters["bad_signature"] >= 1)
        assert not arming.armed

        gs.heartbeat()
        gs.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM))
        assert ack.result == mav.MAV_RESULT_ACCEPTED and arming.armed and link.gcs_alive
        await stop(task)
        for s in (gs, rogue, wrong):
            s.close()

    asyncio.run(main())


def test_telemetry_battery_odometry_scan_and_safety() -> None:
    async def main() -> None:
        bus = Bus()
        gs = Station()
        params = MavlinkParams(enabled=True, gcs_address=f"127.0.0.1:{gs.port}", bind_port=0,
                               telemetry_rate_hz=20.0)
        link = MavlinkGcs(bus, params, Arming(start_armed=True))
        task = asyncio.create_task(link.run())
        await gs.wait("HEARTBEAT", lambda m: m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
        bus.publish("/vesc/sensors/core", VescStateStamped(state=VescState(
            voltage_input=12.3, current_input=4.5, charge_drawn=0.25, energy_drawn=3.0)))
        odom = Odometry()
        odom.pose.pose.position.x, odom.pose.pose.position.y = 1.0, 2.0
        odom.pose.pose.orientation = Quaternion.from_yaw(math.pi / 2)
        odom.twist.twist.linear.x = 1.5
        odom.twist.twist.angular.z = 0.5
        bus.publish("/odom", odom)
        bus.publish("/scan", LaserScan(angle_min=-math.pi / 2, angle_max=math.pi / 2,
                                       angle_increment=math.pi / 2, range_min=0.1, range_max=10.0,
                                       ranges=np.array([3.0, 1.0, np.inf], dtype=np.float32)))
        battery = await gs.wait("BATTERY_STATUS")
        assert battery.voltages[0] == 12300 and battery.current_battery == 450
        assert battery.current_consumed == 250 and battery.energy_consumed == 108
        status = await gs.wait("SYS_STATUS", lambda m: m.voltage_battery == 12300)
        assert status.current_battery == 450
        pos = await gs.wait("LOCAL_POSITION_NED")
        assert (pos.x, pos.y, pos.z) == pytest.approx((2.0, 1.0, 0.0))
        assert (pos.vx, pos.vy) == pytest.approx((1.5, 0.0), abs=1e-6)  # facing odom +y = north
        att = await gs.wait("ATTITUDE")
        assert att.yaw == pytest.approx(0.0, abs=1e-6) and att.yawspeed == pytest.approx(-0.5)
        obstacle = await gs.wait("OBSTACLE_DISTANCE")
        assert obstacle.frame == mav.MAV_FRAME_BODY_FRD and obstacle.increment_f == 5.0
        assert obstacle.distances[0] == 100 and obstacle.distances[18] == 300  # ahead; right = 90° cw
        assert obstacle.distances[54] == 1001 and obstacle.distances[1] == 65535
        bus.publish("/safety/state", DiagnosticArray(status=[DiagnosticStatus(0, "safety", "clear")]))
        bus.publish("/safety/state", DiagnosticArray(status=[DiagnosticStatus(1, "safety", "obstacle")]))
        text = await gs.wait("STATUSTEXT", lambda m: "Safety" in m.text)
        assert text.text == "Safety: obstacle" and text.severity == mav.MAV_SEVERITY_WARNING
        assert len(gs.find("STATUSTEXT", lambda m: "Safety" in m.text)) == 1  # the first "clear" is quiet
        await stop(task)
        gs.close()

    asyncio.run(main())


def test_non_loopback_station_requires_a_signing_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        MavlinkGcs(Bus(), MavlinkParams(gcs_address="192.168.1.20:14550"), Arming())
    assert info.value.key == "mavlink.signing_key_file"
    with pytest.raises(ConfigError, match="signing_key_file"):
        MavlinkGcs(Bus(), MavlinkParams(gcs_address="192.168.1.20:14550",
                                        signing_key_file=str(tmp_path / "missing.key")), Arming())
    with pytest.raises(ConfigError, match="gcs_address"):
        MavlinkParams(gcs_address="nowhere")
    passphrase = tmp_path / "phrase"
    passphrase.write_text("correct horse battery staple\n")
    assert load_signing_key(str(passphrase)) == hashlib.sha256(b"correct horse battery staple").digest()
    params = MavlinkParams(gcs_address="192.168.1.20:14550", signing_key_file=str(passphrase))
    assert params.bind == ("0.0.0.0", 14555)
    assert MavlinkParams().bind == ("127.0.0.1", 14555)


def test_listening_beyond_loopback_requires_a_signing_key_too(tmp_path: Path) -> None:
    """A loopback ground station with ``bind_address`` 0.0.0.0: the datagrams of other hosts are
    refused as foreign, but the port is open to the network, so it needs signing like the station."""
    for bind in ("0.0.0.0", "::", "192.168.1.5"):
        with pytest.raises(ConfigError, match="bind_address") as info:
            MavlinkParams(enabled=True, bind_address=bind)
        assert info.value.key == "mavlink.bind_address" and "signing" in str(info.value)
        with pytest.raises(ConfigError) as info:
            MavlinkGcs(Bus(), MavlinkParams(bind_address=bind), Arming())
        assert info.value.key == "mavlink.bind_address"
    key = tmp_path / "key"
    key.write_text("correct horse battery staple\n")
    assert MavlinkParams(enabled=True, bind_address="0.0.0.0", signing_key_file=str(key)).bind[0] == "0.0.0.0"
    assert MavlinkParams(enabled=True, bind_address="127.0.0.2").bind[0] == "127.0.0.2"


def odom_at(x: float, y: float, yaw: float, vx: float = 0.0, wz: float = 0.0) -> Odometry:
    odom = Odometry()
    odom.pose.pose.position.x, odom.pose.pose.position.y = x, y
    odom.pose.pose.orientation = Quaternion.from_yaw(yaw)
    odom.twist.twist.linear.x = vx
    odom.twist.twist.angular.z = wz
    return odom


@given(st.floats(-math.pi, math.pi), st.floats(-5, 5), st.floats(-2, 2))
def test_enu_to_ned_yaw_and_velocity(yaw: float, vx: float, wz: float) -> None:
    position, velocity, (roll, pitch, yaw_ned), rates = odom_to_ned(odom_at(3.0, -4.0, yaw, vx, wz))
    assert position == pytest.approx((-4.0, 3.0, 0.0))
    expected = math.atan2(math.sin(math.pi / 2 - yaw), math.cos(math.pi / 2 - yaw))
    assert math.cos(yaw_ned - expected) == pytest.approx(1.0)
    assert roll == pytest.approx(0.0, abs=1e-9) and pitch == pytest.approx(0.0, abs=1e-9)
    # velocity NED = forward speed along the NED heading
    assert velocity[0] == pytest.approx(vx * math.cos(yaw_ned), abs=1e-9)
    assert velocity[1] == pytest.approx(vx * math.sin(yaw_ned), abs=1e-9)
    assert rates[2] == pytest.approx(-wz)


def test_roll_keeps_its_sign_from_flu_to_frd() -> None:
    odom = Odometry()
    # roll 0.2 rad about x (FLU): left side up = right side down = positive FRD roll
    odom.pose.pose.orientation = Quaternion(math.sin(0.1), 0.0, 0.0, math.cos(0.1))
    _, _, (roll, pitch, _yaw), _ = odom_to_ned(odom)
    assert roll == pytest.approx(0.2) and pitch == pytest.approx(0.0, abs=1e-9)
    # nose up in FLU is a negative rotation about y (left); FRD pitch is positive nose up
    odom.pose.pose.orientation = Quaternion(0.0, math.sin(-0.1), 0.0, math.cos(-0.1))
    _, _, (roll, pitch, _yaw), _ = odom_to_ned(odom)
    assert pitch == pytest.approx(0.2)


@given(st.lists(st.one_of(st.floats(0.0, 40.0), st.just(float("inf")), st.just(float("nan"))),
                min_size=1, max_size=400),
       st.floats(-math.pi, 0.0))
def test_obstacle_bins_are_valid_cm(ranges: list[float], angle_min: float) -> None:
    n = len(ranges)
    scan = LaserScan(angle_min=angle_min, angle_max=angle_min + 2 * math.pi * (n - 1) / n,
                     angle_increment=2 * math.pi / n, range_min=0.05, range_max=30.0,
                     ranges=np.array(ranges, dtype=np.float32))
    distances, min_cm, max_cm = obstacle_bins(scan)
    assert len(distances) == 72 and (min_cm, max_cm) == (5, 3000)
    for d in distances:
        assert d == 65535 or 0 <= d <= max_cm + 1


def test_an_override_sent_while_the_station_was_lost_does_not_come_back_with_65535() -> None:
    """After the heartbeat-loss failsafe, one RC override with every channel 65535 ("unchanged")
    brought back the full throttle the station had sent while it was declared lost (a review
    reproduced it: 0 m/s, then 2.0 m/s). Refused overrides are not kept, and the failsafe (or any
    mode but MANUAL) forgets the held channels."""
    async def main() -> None:
        bus = Bus()
        arming = Arming(start_armed=True)
        rec = Recorder(bus)
        gs = Station()
        params = MavlinkParams(enabled=True, gcs_address=f"127.0.0.1:{gs.port}", bind_port=0, rate_hz=50.0)
        link = MavlinkGcs(bus, params, arming)
        task = asyncio.create_task(link.run())
        await gs.wait("HEARTBEAT")  # the station answers where the car's heartbeat came from
        gs.beating = True
        beats = asyncio.create_task(gs.beat())
        await async_wait_for(lambda: link.gcs_alive)
        gs.conn.mav.rc_channels_override_send(1, 1, 1500, 65535, 2000, 65535, 65535, 65535, 65535, 65535)
        await async_wait_for(lambda: rec.drives and rec.drives[-1][0] == pytest.approx(2.0))
        gs.beating = False  # the station goes quiet but its overrides keep coming
        lost = link.counters["gcs_timeouts"]
        while link.counters["gcs_timeouts"] == lost:
            gs.conn.mav.rc_channels_override_send(1, 1, 1500, 65535, 2000, 65535, 65535, 65535, 65535, 65535)
            await asyncio.sleep(0.1)
        await async_wait_for(lambda: rec.drives[-1] == (0.0, 0.0))
        ignored = link.counters["inputs_ignored"]
        for _ in range(3):  # refused: the station is lost
            gs.conn.mav.rc_channels_override_send(1, 1, 1500, 65535, 2000, 65535, 65535, 65535, 65535, 65535)
        await async_wait_for(lambda: link.counters["inputs_ignored"] >= ignored + 3)
        gs.heartbeat()
        await async_wait_for(lambda: link.gcs_alive)
        taken = link.counters["manual_inputs"]
        gs.conn.mav.rc_channels_override_send(1, 1, *[65535] * 8)
        await async_wait_for(lambda: link.counters["manual_inputs"] == taken + 1)
        link.tick()
        assert rec.drives[-1][0] == 0.0, rec.drives[-5:]
        await stop(beats)
        await stop(task)
        gs.close()

    asyncio.run(main())
