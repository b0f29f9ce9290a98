"""A pymavlink ground station on 127.0.0.1 against ``racecar-hw sim`` (issue: MAVLink teleop).

The ground station arms the simulated car and drives it with MANUAL_CONTROL through the real
daemon, the real mux and safety controller, the fake VESC on a pty and the world simulation.
"""

from __future__ import annotations

import asyncio
import os
from typing import Any

from conftest import NO_DDS, NO_ZENOH, async_wait_for

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from racecar_hw.sim.loopback import Loopback  # noqa: E402
from racecar_hw.sim.scenario import load_scenario  # noqa: E402
from racecar_hw.teleop.mavlink_gcs import write_signing_key  # noqa: E402

mav = mavutil.mavlink


class Station:
    """A ground station listening on an ephemeral loopback port, beating at 1 Hz when asked."""

    def __init__(self, key: bytes | None = None) -> None:
        self.conn: Any = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                                    source_component=190)
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=True)
        self.got: list[Any] = []
        self.beating = True

    @property
    def port(self) -> int:
        return int(self.conn.port.getsockname()[1])

    def find(self, kind: str, pred=lambda m: True) -> list[Any]:
        while (msg := self.conn.recv_msg()) is not None:
            if msg.get_type() != "BAD_DATA":
                self.got.append(msg)
        return [m for m in self.got if m.get_type() == kind and pred(m)]

    async def heartbeats(self) -> None:
        while True:
            if self.beating:
                self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            await asyncio.sleep(0.5)

    def arm(self, on: bool) -> None:
        self.conn.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                        1 if on else 0, 0, 0, 0, 0, 0, 0)

    async def throttle(self, z: int, seconds: float) -> None:
        for _ in range(int(seconds * 10)):
            self.conn.mav.manual_control_send(1, 0, 0, z, 0, 0)
            await asyncio.sleep(0.1)


def _loopback(station: Station, script, *extra: str) -> Loopback:
    scenario = load_scenario("wall", ["drivers=[]", "duration_s=60"])
    overrides = ["mavlink.enabled=true", "mavlink.bind_port=0",
                 f"mavlink.gcs_address=127.0.0.1:{station.port}", "arming.start_armed=false", NO_ZENOH,
                 NO_DDS, *extra]

    def setup(lb: Loopback) -> None:
        lb.daemon.add_task(script(lb))

    return Loopback(scenario, overrides=overrides, setup=setup)


def test_ground_station_arms_drives_disarms_and_failsafes_the_sim_car():
    station = Station()
    checks: dict[str, Any] = {}

    async def script(lb: Loopback) -> None:
        beats = asyncio.ensure_future(station.heartbeats())
        try:
            world = lb.world
            hb = await _wait(station, "HEARTBEAT", lambda m: m.type == mav.MAV_TYPE_GROUND_ROVER)
            checks["disarmed_at_start"] = not (hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
            await async_wait_for(lambda: lb.daemon.lidar.stats.scans > 0, timeout=20)
            # no motion before arming, whatever the ground station asks
            await station.throttle(500, 1.0)
            checks["still_when_disarmed"] = abs(world.speed) < 0.01
            await station.throttle(0, 0.3)  # arming is refused while the station's throttle is up
            station.arm(True)
            await _wait(station, "COMMAND_ACK", lambda m: m.command == mav.MAV_CMD_COMPONENT_ARM_DISARM
                        and m.result == mav.MAV_RESULT_ACCEPTED)
            await _wait(station, "HEARTBEAT", lambda m: m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
            start = world.distance_travelled
            await station.throttle(500, 2.0)  # half throttle: 1 m/s
            checks["moving_when_armed"] = world.distance_travelled - start > 0.8
            station.arm(False)
            await station.throttle(500, 1.5)
            checks["stopped_by_disarm"] = abs(world.speed) < 0.01
            await station.throttle(0, 0.3)
            station.arm(True)
            start = world.distance_travelled
            await station.throttle(500, 1.5)
            checks["moving_again"] = world.distance_travelled - start > 0.6
            station.beating = False
            await station.throttle(500, 4.0)
            checks["stopped_by_lost_heartbeat"] = abs(world.speed) < 0.01
            checks["statustext"] = [m.text for m in station.find("STATUSTEXT")]
            checks["collided"] = world.collided
        finally:
            beats.cancel()
            lb.request_stop()

    asyncio.run(_loopback(station, script).run())
    assert checks["disarmed_at_start"]
    assert checks["still_when_disarmed"]
    assert checks["moving_when_armed"]
    assert checks["stopped_by_disarm"]
    assert checks["moving_again"]
    assert checks["stopped_by_lost_heartbeat"]
    assert any("ground station" in t.lower() or "gcs" in t.lower() for t in checks["statustext"])
    assert not checks["collided"]


def test_unsigned_commands_are_refused_when_signing_is_on(tmp_path):
    key_file = tmp_path / "mavlink.key"
    key = write_signing_key(key_file)
    unsigned = Station()
    checks: dict[str, Any] = {}

    async def script(lb: Loopback) -> None:
        try:
            await _wait(unsigned, "HEARTBEAT", lambda m: m.type == mav.MAV_TYPE_GROUND_ROVER)
            await async_wait_for(lambda: lb.daemon.lidar.stats.scans > 0, timeout=20)
            for _ in range(3):
                unsigned.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                unsigned.arm(True)
                await asyncio.sleep(0.3)
            await unsigned.throttle(500, 1.0)
            checks["armed"] = lb.daemon.arming.armed
            checks["speed"] = lb.world.speed
            checks["refused"] = lb.daemon.mavlink.counters
            checks["acks"] = unsigned.find("COMMAND_ACK")
        finally:
            lb.request_stop()

    asyncio.run(_loopback(unsigned, script, f"mavlink.signing_key_file={key_file}").run())
    assert key
    assert checks["armed"] is False
    assert abs(checks["speed"]) < 0.01
    assert not [a for a in checks["acks"] if a.result == mav.MAV_RESULT_ACCEPTED]
    assert checks["refused"]["unsigned_refused"] >= 3, checks["refused"]


async def _wait(station: Station, kind: str, pred=lambda m: True, timeout: float = 20.0) -> Any:
    await async_wait_for(lambda: station.find(kind, pred), timeout=timeout)
    return station.find(kind, pred)[-1]
