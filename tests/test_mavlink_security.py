"""Hostile and broken MAVLink input, with real pymavlink-built packets (signed and unsigned).

The link runs on a real UDP socket on loopback; attackers and the ground station are pymavlink
encoders whose bytes go out of plain UDP sockets, and the ground station reads our replies with
pymavlink. Time-dependent rules (RC override expiry, stale input) run on a test clock through
:meth:`MavlinkGcs.handle_datagram`, the same entry the socket uses.
"""

from __future__ import annotations

import asyncio
import math
import os
import random
import signal
import socket
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import async_wait_for

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from racecar_hw.base.bus import Bus  # noqa: E402
from racecar_hw.base.clock import NS_PER_S, wall_ns  # noqa: E402
from racecar_hw.base.errors import ConfigError  # noqa: E402
from racecar_hw.base.messages import LaserScan, Odometry, VescState, VescStateStamped  # noqa: E402
from racecar_hw.cli import main as cli_main  # noqa: E402
from racecar_hw.teleop.arming import Arming  # noqa: E402
from racecar_hw.teleop.mavlink_gcs import (  # noqa: E402
    MavlinkGcs,
    MavlinkParams,
    signing_timestamp,
    write_signing_key,
)
from racecar_hw.teleop.mavlink_rx import NEW_STREAM_LAG, MavlinkRx  # noqa: E402

mav = mavutil.mavlink
TELEOP = "/vesc/low_level/ackermann_cmd_mux/input/teleop"
GCS = 255


class Packer:
    """pymavlink as a ground station's (or an attacker's) encoder: messages to datagram bytes."""

    def __init__(self, system: int = GCS, component: int = 190, key: bytes | None = None,
                 link_id: int = 0, timestamp: int | None = None) -> None:
        self.out: list[bytes] = []
        self.mav = mav.MAVLink(self, system, component)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.link_id = link_id
            self.mav.signing.timestamp = signing_timestamp(wall_ns()) if timestamp is None else timestamp
            self.mav.signing.sign_outgoing = True

    def write(self, data: bytes) -> None:
        self.out.append(bytes(data))

    def heartbeat(self) -> bytes:
        self.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        return self.out.pop()

    def arm(self, on: bool = True, param2: float = 0.0) -> bytes:
        self.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1.0 if on else 0.0, param2,
                                   0, 0, 0, 0, 0)
        return self.out.pop()

    def command(self, command: int, *params: float, kind: str = "long") -> bytes:
        p = list(params) + [0.0] * (7 - len(params))
        if kind == "long":
            self.mav.command_long_send(1, 1, command, 0, *p)
        else:
            self.mav.command_int_send(1, 1, 0, command, 0, 0, *p[:4], 0, 0, p[6])
        return self.out.pop()

    def manual(self, z: int, y: int = 0) -> bytes:
        self.mav.manual_control_send(1, 0, y, z, 0, 0)
        return self.out.pop()

    def rc(self, ch1: int, ch3: int) -> bytes:
        self.mav.rc_channels_override_send(1, 1, ch1, 65535, ch3, 65535, 65535, 65535, 65535, 65535)
        return self.out.pop()


class Station:
    """The ground station's socket: sends datagrams, receives our telemetry with pymavlink."""

    def __init__(self, key: bytes | None = None, family: int = socket.AF_INET) -> None:
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        self.sock.bind(("::1" if family == socket.AF_INET6 else "127.0.0.1", 0))
        self.sock.setblocking(False)
        self.parser = mav.MAVLink(None)
        if key is not None:
            self.parser.signing.secret_key = key
        self.got: list[Any] = []

    @property
    def address(self) -> str:
        host, port = self.sock.getsockname()[:2]
        return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"

    def send(self, link: MavlinkGcs, *datagrams: bytes) -> None:
        host = "::1" if self.sock.family == socket.AF_INET6 else "127.0.0.1"
        for d in datagrams:
            self.sock.sendto(d, (host, link.port))

    def find(self, kind: str, pred: Callable[[Any], bool] = lambda m: True) -> list[Any]:
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                break
            self.got.extend(m for m in (self.parser.parse_buffer(data) or []) if m.get_type() != "BAD_DATA")
        return [m for m in self.got if m.get_type() == kind and pred(m)]

    async def wait(self, kind: str, pred: Callable[[Any], bool] = lambda m: True) -> Any:
        await async_wait_for(lambda: self.find(kind, pred))
        return self.find(kind, pred)[-1]

    def close(self) -> None:
        self.sock.close()


def ack_of(command: int, result: int | None = None) -> Callable[[Any], bool]:
    return lambda m: m.command == command and (result is None or m.result == result)


async def started(params: MavlinkParams, arming: Arming, bus: Bus | None = None) -> MavlinkGcs:
    link = MavlinkGcs(bus or Bus(), params, arming)
    await link.start()
    return link


def run(coro_fn: Callable[[], Any]) -> None:
    asyncio.run(coro_fn())


Scenario = Callable[[MavlinkGcs, Station, Arming, bytes], Awaitable[None]]


def run_signed(tmp_path: Path, scenario: Scenario) -> None:
    """``scenario(link, station, arming, key)`` against a link with signing on, started disarmed."""
    key = write_signing_key(tmp_path / "key")

    async def main() -> None:
        arming = Arming(start_armed=False)
        gs = Station(key)
        link = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0,
                                           signing_key_file=str(tmp_path / "key")), arming)
        try:
            await scenario(link, gs, arming, key)
        finally:
            link.close()
            gs.close()

    asyncio.run(main())


# --- signing: the lockout attacks fail ---------------------------------------------------------


def test_forged_far_future_packets_on_every_link_id_do_not_lock_out_the_signed_station(tmp_path: Path):
    async def scenario(link: MavlinkGcs, gs: Station, arming: Arming, key: bytes) -> None:
        attacker = Station()
        far_future = 2**48 - 10_000
        for link_id in range(256):  # the ground station's ids, every link id, a forged signature
            forged = Packer(key=os.urandom(32), link_id=link_id, timestamp=far_future)
            attacker.send(link, forged.heartbeat(), forged.arm())
            if link_id % 16 == 15:  # in bursts the socket buffer holds
                await async_wait_for(lambda n=2 * link_id + 2: link.counters["bad_signature"] == n)
        attacker.close()
        assert not link.rx.streams and not arming.armed and not link.gcs_alive
        station = Packer(key=key)
        gs.send(link, station.heartbeat(), station.arm())
        ack = await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM))
        assert ack.result == mav.MAV_RESULT_ACCEPTED and arming.armed and link.gcs_alive
        assert ack.get_signed()  # our reply is signed with the shared key

    run_signed(tmp_path, scenario)


def test_one_corrupted_timestamp_byte_or_a_replay_changes_nothing(tmp_path: Path):
    async def scenario(link: MavlinkGcs, gs: Station, arming: Arming, key: bytes) -> None:
        station = Packer(key=key)
        genuine = bytearray(station.heartbeat())
        genuine[-7] = 0xFF  # the timestamp's top byte, as a noisy link could flip it
        gs.send(link, bytes(genuine))
        await async_wait_for(lambda: link.counters["bad_signature"] == 1)
        assert not link.rx.streams  # nothing recorded from a frame whose signature failed
        beat = station.heartbeat()
        gs.send(link, beat)
        await async_wait_for(lambda: link.gcs_alive)
        gs.send(link, beat)  # a replay of the same signed frame
        await async_wait_for(lambda: link.counters["old_timestamp"] == 1)
        gs.send(link, station.arm())
        await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_RESULT_ACCEPTED))
        assert arming.armed

    run_signed(tmp_path, scenario)


def test_a_new_stream_may_lag_our_time_by_one_minute_and_not_more():
    """The signing spec's rule for a stream (link id, system, component) not seen before: accepted
    when its timestamp is at most one minute behind ours, which follows the largest accepted one."""
    key, now = bytes(range(32)), 10**12
    rx = MavlinkRx(key, now)
    ahead = Packer(key=key, link_id=0, timestamp=now + 100)
    assert len(rx.decode(ahead.heartbeat())) == 1 and rx.timestamp == now + 100
    at_limit = Packer(key=key, link_id=1, timestamp=now + 100 - NEW_STREAM_LAG)
    too_old = Packer(key=key, link_id=2, timestamp=now + 100 - NEW_STREAM_LAG - 1)
    assert len(rx.decode(at_limit.heartbeat())) == 1
    assert rx.decode(too_old.heartbeat()) == [] and rx.counters["old_timestamp"] == 1
    assert (2, GCS, 190) not in rx.streams  # a refused frame records nothing
    # the same station, once its clock is back within the minute, is heard
    caught_up = Packer(key=key, link_id=2, timestamp=now + 100 - NEW_STREAM_LAG + 6_000_000)
    assert len(rx.decode(caught_up.heartbeat())) == 1


def test_signing_streams_are_independent():
    """Each stream has its own last timestamp: one station far ahead neither blocks another stream
    still within the lag, nor lets that stream's own replays through; the same link id from another
    system or component is another stream."""
    key, now = bytes(range(32)), 10**12
    rx = MavlinkRx(key, now)
    fast = Packer(key=key, link_id=0, timestamp=now + 20 * 100_000)  # 20 s ahead
    slow = Packer(key=key, link_id=1, timestamp=now - 30 * 100_000)  # 30 s behind
    other_component = Packer(component=191, key=key, link_id=0, timestamp=now + 5)
    other_system = Packer(system=254, key=key, link_id=0, timestamp=now + 5)
    assert len(rx.decode(fast.heartbeat())) == 1
    beat = slow.heartbeat()
    assert len(rx.decode(beat)) == 1  # 50 s behind ours now: a new stream within the minute
    for _ in range(3):  # its own stream keeps increasing from where it is, below the fast one
        assert len(rx.decode(slow.heartbeat())) == 1
    assert rx.decode(beat) == [] and rx.counters["old_timestamp"] == 1  # its replay is not
    assert len(rx.decode(other_component.heartbeat())) == 1  # below link 0 of component 190
    assert len(rx.decode(other_system.heartbeat())) == 1
    assert set(rx.streams) == {(0, GCS, 190), (1, GCS, 190), (0, GCS, 191), (0, 254, 190)}
    assert rx.streams[(1, GCS, 190)] == now - 30 * 100_000 + 3
    assert len(rx.decode(fast.heartbeat())) == 1 and rx.timestamp == now + 20 * 100_000 + 1


def test_unsigned_packets_from_another_port_are_refused_and_never_redirect_telemetry(tmp_path: Path):
    async def scenario(link: MavlinkGcs, gs: Station, arming: Arming, key: bytes) -> None:
        stranger = Station()
        unsigned = Packer()
        stranger.send(link, unsigned.heartbeat(), unsigned.arm(), unsigned.manual(800))
        await async_wait_for(lambda: link.counters["unsigned_refused"] == 3)
        link.send_heartbeat()
        await gs.wait("HEARTBEAT")
        assert not stranger.find("HEARTBEAT") and not arming.armed
        stranger.close()

    run_signed(tmp_path, scenario)


# --- issue 24: a wrong clock, the way back, floods ----------------------------------------------

HOUR = 3600 * 100_000  # MAVLink signing units (10 µs)


def test_a_signed_frame_an_hour_ahead_is_refused_and_records_nothing(tmp_path: Path):
    """A second laptop with the station's key and a clock an hour fast, on the station's own
    stream: refused (beyond MAVLink's rules, which would adopt it), nothing recorded, counted and
    logged under its address; the station keeps control."""
    async def scenario(link: MavlinkGcs, gs: Station, arming: Arming, key: bytes) -> None:
        station = Packer(key=key)
        gs.send(link, station.heartbeat())
        await async_wait_for(lambda: link.gcs_alive)
        stream, ours = dict(link.rx.streams), link.rx.timestamp
        laptop = Station()
        fast = Packer(key=key, timestamp=signing_timestamp(wall_ns()) + HOUR)
        laptop.send(link, fast.heartbeat(), fast.arm())
        await async_wait_for(lambda: link.counters["future_timestamp"] == 2)
        assert link.rx.streams == stream and link.rx.timestamp < ours + HOUR // 2
        assert not arming.armed
        source = laptop.address
        assert link.refusals.by_source() == {
            ("mavlink", source, "signing timestamp too far ahead of our clock"): 2}
        gs.send(link, station.arm())
        await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_RESULT_ACCEPTED))
        assert arming.armed
        # within the window (here 30 s ahead) a frame is taken, as MAVLink's rules say
        soon = Packer(key=key, link_id=5, timestamp=signing_timestamp(wall_ns()) + 30 * 100_000)
        laptop.send(link, soon.heartbeat())
        await async_wait_for(lambda: (5, GCS, 190) in link.rx.streams)
        laptop.close()

    run_signed(tmp_path, scenario)


def test_without_the_window_a_frame_an_hour_ahead_locks_the_station_out_until_the_signing_restarts(
        tmp_path: Path):
    """``future_window_s: 0`` is MAVLink's plain rule: the frame an hour ahead is adopted and the
    station's own frames look old. :meth:`MavlinkGcs.restart_signing` (SIGUSR1, ``systemctl
    reload``) is the way back: the station is heard again."""
    key = write_signing_key(tmp_path / "key")

    async def main() -> None:
        arming = Arming(start_armed=False)
        gs = Station(key)
        link = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0,
                                           future_window_s=0, signing_key_file=str(tmp_path / "key")),
                             arming)
        station = Packer(key=key)
        gs.send(link, station.heartbeat())
        await async_wait_for(lambda: link.gcs_alive)
        fast = Packer(key=key, timestamp=signing_timestamp(wall_ns()) + HOUR)
        laptop = Station()
        laptop.send(link, fast.heartbeat())
        await async_wait_for(lambda: link.counters["rx"] == 2)
        gs.send(link, station.arm())
        await async_wait_for(lambda: link.counters["old_timestamp"] == 1)
        assert not arming.armed  # locked out
        assert link.restart_signing() == 1 and not link.rx.streams
        assert link.counters["signing_restarts"] == 1
        assert link.rx.timestamp < signing_timestamp(wall_ns()) + 100_000  # from the wall clock again
        gs.send(link, station.arm())
        await async_wait_for(lambda: arming.armed)
        link.close()
        gs.close()
        laptop.close()

    asyncio.run(main())


def test_sigusr1_restarts_the_signing_state_of_the_running_daemon(tmp_path: Path):
    from racecar_hw.commands.daemon import run_daemon
    from racecar_hw.config import load_config
    from racecar_hw.daemon import Daemon

    key = write_signing_key(tmp_path / "key")
    gs = Station(key)
    config = load_config(None, ["vesc.enabled=false", "lidar.enabled=false", "gamepad.enabled=false",
                                "status.enabled=false", "zenoh.enabled=false", "foxglove.enabled=false",
                                "web.enabled=false", "mavlink.enabled=true", "mavlink.bind_port=0",
                                f"mavlink.gcs_address={gs.address}",
                                f"mavlink.signing_key_file={tmp_path / 'key'}"])
    daemon = Daemon(config)
    link = daemon.mavlink
    assert link is not None

    async def main() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(run_daemon(daemon, stop))
        await async_wait_for(lambda: link.station_socket)
        gs.send(link, Packer(key=key).heartbeat())
        await async_wait_for(lambda: link.rx.streams)
        os.kill(os.getpid(), signal.SIGUSR1)
        await async_wait_for(lambda: link.counters["signing_restarts"] == 1)
        assert not link.rx.streams
        stop.set()
        await task

    asyncio.run(main())
    gs.close()


def test_the_cheap_refusal_takes_only_whole_frames_and_hides_no_good_frame():
    """A datagram that is one forged or unsigned frame is refused before the decoder; a damaged
    header whose length spans the datagram, with a genuine frame behind it, goes to the decoder,
    which finds the genuine frame."""
    key, now = bytes(range(32)), signing_timestamp(wall_ns())
    rx = MavlinkRx(key, now, future_window=60 * 100_000)
    assert rx.refuse_cheaply(Packer(key=os.urandom(32), timestamp=now).heartbeat()) == "bad_signature"
    assert rx.refuse_cheaply(Packer().heartbeat()) == "unsigned_refused"
    genuine = Packer(key=key, timestamp=now).heartbeat()
    assert rx.refuse_cheaply(genuine) is None and len(rx.decode(genuine, now)) == 1
    behind = Packer(key=key, timestamp=now + 10).manual(500)
    header = bytes((0xFD, len(behind) - 15, 0x01, 0, 0, GCS, 190, 0, 0, 0))  # spans the datagram
    assert rx.refuse_cheaply(header + behind) is None
    assert [m.get_type() for m in rx.decode(header + behind, now)] == ["MANUAL_CONTROL"]
    assert rx.refuse_cheaply(genuine + genuine) is None  # two frames: the decoder's
    assert rx.counters["bad_signature"] == 1 and rx.counters["unsigned_refused"] == 1


def test_a_bad_future_window_is_refused_naming_the_key(capsys):
    assert cli_main(["check-config", "--set", "mavlink.future_window_s=-1"]) == 1
    err = capsys.readouterr().err
    assert "mavlink.future_window_s" in err and "Traceback" not in err


def test_the_stations_socket_takes_only_the_stations_datagrams(tmp_path: Path):
    """The kernel hands the station's datagrams to the station's own (connected) socket and
    everyone else's to the shared one, so a flood there cannot crowd the station out."""
    async def scenario(link: MavlinkGcs, gs: Station, arming: Arming, key: bytes) -> None:
        assert link.station_socket
        attacker = Station()
        forged = Packer(key=os.urandom(32)).heartbeat()
        station = Packer(key=key)
        for i in range(20):
            attacker.send(link, *[forged] * 100)
            gs.send(link, station.heartbeat())
            await async_wait_for(lambda n=i + 1: link.counters["station_datagrams"] == n)
        await async_wait_for(lambda: link.counters["rx"] == 20)
        assert link.counters["station_datagrams"] == 20  # no forged datagram among them
        assert 0 < link.counters["bad_signature"] <= 2000  # the kernel may drop some of the flood
        attacker.close()

    run_signed(tmp_path, scenario)


def test_a_second_link_on_the_same_port_is_refused_as_before():
    """The sockets share their port with each other (SO_REUSEPORT), never with another link."""
    async def main() -> None:
        gs = Station()
        first = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0), Arming())
        assert first.station_socket
        second = MavlinkGcs(Bus(), MavlinkParams(enabled=True, gcs_address=gs.address,
                                                 bind_port=first.port), Arming())
        with pytest.raises(OSError):
            await second.start()
        second.close()
        first.close()
        gs.close()

    asyncio.run(main())


def test_with_port_0_the_station_gets_its_socket_once_it_is_heard(tmp_path: Path):
    async def main() -> None:
        gs = Station()
        link = await started(MavlinkParams(enabled=True, gcs_address="127.0.0.1:0", bind_port=0), Arming())
        assert not link.station_socket
        gs.send(link, Packer().heartbeat())
        await async_wait_for(lambda: link.gcs_alive)
        assert link.station_socket
        gs.send(link, Packer().heartbeat())
        await async_wait_for(lambda: link.counters["station_datagrams"] == 1)
        link.send_heartbeat()
        await gs.wait("HEARTBEAT")  # telemetry leaves from the station's socket, on our port
        link.close()
        gs.close()

    asyncio.run(main())


def test_a_flooded_socket_rests_and_reads_again(tmp_path: Path):
    """More forgeries than one budget takes: the shared socket rests, then reads again, and a
    signed message from another port of the station's host is still heard after the flood."""
    async def scenario(link: MavlinkGcs, gs: Station, arming: Arming, key: bytes) -> None:
        attacker = Station()
        forged = Packer(key=os.urandom(32)).heartbeat()
        for _ in range(20):
            attacker.send(link, *[forged] * 200)
            await asyncio.sleep(0)
        read = [-1]

        def drained() -> bool:  # nothing read for 0.2 s: the flood is over
            if link.counters["datagrams"] != read[0]:
                read[0] = link.counters["datagrams"]
                return False
            return True

        await async_wait_for(lambda: link.counters["datagrams"] > 0)
        while not drained():
            await asyncio.sleep(0.2)
        assert link.counters["drain_rests"] >= 1 and link.counters["bad_signature"] == read[0]
        other_port = Station()
        other_port.send(link, Packer(key=key, link_id=3).heartbeat())
        await async_wait_for(lambda: link.counters["rx"] == 1, timeout=20)
        assert link.gcs_alive
        attacker.close()
        other_port.close()

    run_signed(tmp_path, scenario)


# --- who may drive -----------------------------------------------------------------------------


def test_a_strangers_system_id_cannot_arm_drive_set_modes_or_redirect_telemetry():
    async def main() -> None:
        bus = Bus()
        drives: list[float] = []
        bus.subscribe(TELEOP, lambda m: drives.append(m.drive.speed))
        arming = Arming(start_armed=False)
        gs = Station()
        link = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0,
                                           rate_hz=50.0), arming, bus)
        task = asyncio.create_task(link.run())
        stranger = Station()
        other = Packer(system=77)
        for _ in range(3):
            stranger.send(link, other.heartbeat(), other.arm(), other.manual(900), other.rc(1500, 1900),
                          other.command(mav.MAV_CMD_DO_SET_MODE, 1, 4))
        await async_wait_for(lambda: link.counters["other_sender"] == 15)
        await gs.wait("HEARTBEAT")
        assert not link.gcs_alive and not arming.armed and link.mode_name == "MANUAL"
        assert link.counters["acks"] == 0 and link.manual is None and not drives
        assert not stranger.find("HEARTBEAT") and not stranger.find("COMMAND_ACK")
        # the ground station's own system id is obeyed
        station = Packer()
        gs.send(link, station.heartbeat(), station.arm())
        await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_RESULT_ACCEPTED))
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        gs.close()
        stranger.close()

    run(main)


def test_with_port_0_telemetry_latches_onto_the_first_authenticated_station():
    async def main() -> None:
        arming = Arming(start_armed=False)
        first, second, stranger = Station(), Station(), Station()
        link = await started(MavlinkParams(enabled=True, gcs_address="127.0.0.1:0", bind_port=0), arming)
        link.send_heartbeat()  # nowhere to go yet
        assert link.counters["tx"] == 0
        stranger.send(link, Packer(system=77).heartbeat())
        await async_wait_for(lambda: link.counters["other_sender"] == 1)
        first.send(link, Packer().heartbeat())
        await async_wait_for(lambda: link.gcs_alive)
        second.send(link, Packer().heartbeat())  # the same system id from elsewhere: heard ...
        await async_wait_for(lambda: link.counters["rx"] == 2)
        link.send_heartbeat()
        await first.wait("HEARTBEAT")  # ... but telemetry stays with the first
        assert not second.find("HEARTBEAT") and not stranger.find("HEARTBEAT")
        link.close()
        for s in (first, second, stranger):
            s.close()

    run(main)


# --- commands are always answered --------------------------------------------------------------


def test_every_command_is_acknowledged_even_with_nan_or_inf_parameters():
    async def main() -> None:
        arming = Arming(start_armed=False)
        gs = Station()
        link = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0), arming)
        p = Packer()
        nan, inf = math.nan, math.inf
        hold = (1.0, 4.0)  # DO_SET_MODE: custom mode enabled, HOLD
        cases = [
            (mav.MAV_CMD_COMPONENT_ARM_DISARM, (nan,), "long", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_COMPONENT_ARM_DISARM, (1.0, inf), "int", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_DO_SET_MODE, (1.0, nan), "long", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_DO_SET_MODE, (1.0, -inf), "int", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_REQUEST_MESSAGE, (nan,), "long", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_NAV_WAYPOINT, (nan,) * 7, "long", mav.MAV_RESULT_UNSUPPORTED),
            # a valid command with NaN or inf in a parameter it does not use: still refused
            (mav.MAV_CMD_DO_SET_MODE, (nan, 4.0), "long", mav.MAV_RESULT_DENIED),  # base mode
            (mav.MAV_CMD_DO_SET_MODE, (inf, 4.0), "int", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_DO_SET_MODE, (*hold, nan), "long", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_DO_SET_MODE, (*hold, 0, 0, 0, 0, -inf), "long", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_DO_SET_MODE, (*hold, 0, 0, 0, 0, nan), "int", mav.MAV_RESULT_DENIED),  # z
            (mav.MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0, nan), "long", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_COMPONENT_ARM_DISARM, (1.0, 0, 0, inf), "int", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, (1.0, nan), "long", mav.MAV_RESULT_DENIED),
            (mav.MAV_CMD_REQUEST_MESSAGE, (mav.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, inf), "long",
             mav.MAV_RESULT_DENIED),
        ]
        gs.send(link, p.heartbeat(), *(p.command(c, *params, kind=kind) for c, params, kind, _ in cases))
        await async_wait_for(lambda: len(gs.find("COMMAND_ACK")) == len(cases))
        acks = gs.find("COMMAND_ACK")
        assert [(a.command, a.result) for a in acks] == [(c, r) for c, _, _, r in cases]
        assert not arming.armed and link.mode_name == "MANUAL"
        assert not gs.find("AUTOPILOT_VERSION") and not gs.find("HEARTBEAT", lambda m: m.custom_mode == 4)
        # the same commands with finite parameters are obeyed
        gs.send(link, p.command(mav.MAV_CMD_DO_SET_MODE, 1.0, 4.0), p.arm())
        await gs.wait("COMMAND_ACK", ack_of(mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_RESULT_ACCEPTED))
        assert arming.armed and link.mode_name == "HOLD"
        link.close()
        gs.close()

    run(main)


def test_autopilot_version_vfr_hud_and_sensor_bits_for_ground_stations():
    async def main() -> None:
        bus = Bus()
        gs = Station()
        link = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0), Arming(), bus)
        p = Packer()
        gs.send(link, p.command(mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1),
                p.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, kind="int"))
        await async_wait_for(lambda: len(gs.find("AUTOPILOT_VERSION")) == 2)
        version = gs.find("AUTOPILOT_VERSION")[0]
        assert version.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert version.capabilities & mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        assert not version.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT  # no missions here
        assert version.flight_sw_version >> 8 == 0x000100  # racecar-hw 0.1.0
        assert [a.result for a in gs.find("COMMAND_ACK")] == [mav.MAV_RESULT_ACCEPTED] * 2
        # SYS_STATUS: lidar (proximity) and VESC (motor outputs, battery) present; healthy when fresh
        link.send_power(link._clock())  # noqa: SLF001 - the link's own clock
        status = await gs.wait("SYS_STATUS")
        lidar, motor = mav.MAV_SYS_STATUS_SENSOR_PROXIMITY, mav.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
        assert status.onboard_control_sensors_present & (lidar | motor) == lidar | motor
        assert not status.onboard_control_sensors_health & (lidar | motor)
        odom = Odometry()
        odom.twist.twist.linear.x = 1.5  # facing odom +x = east
        bus.publish("/odom", odom)
        bus.publish("/vesc/sensors/core",
                    VescStateStamped(state=VescState(voltage_input=12.0, duty_cycle=-0.25)))
        bus.publish("/scan", LaserScan(angle_increment=0.1, range_max=10.0))
        link.send_power(link._clock())  # noqa: SLF001
        link.send_vfr_hud()
        status = await gs.wait("SYS_STATUS", lambda m: m.onboard_control_sensors_health)
        assert status.onboard_control_sensors_health & (lidar | motor) == lidar | motor
        hud = await gs.wait("VFR_HUD")
        assert hud.groundspeed == pytest.approx(1.5) and hud.heading == 90 and hud.throttle == 25
        link.close()
        gs.close()

    run(main)


# --- datagrams are units -----------------------------------------------------------------------


def test_a_truncated_datagram_never_swallows_the_next_command():
    async def main() -> None:
        arming = Arming(start_armed=False)
        gs = Station()
        link = await started(MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0), arming)
        p = Packer()
        for i in range(20):
            gs.send(link, b"\xfd\x30", p.arm(on=i % 2 == 0))
        await async_wait_for(lambda: len(gs.find("COMMAND_ACK")) == 20)
        assert link.counters["bad_data"] == 20 and link.counters["commands"] == 20
        link.close()
        gs.close()

    run(main)


def test_garbage_and_unknown_message_ids_around_frames_in_one_datagram():
    link = MavlinkGcs(Bus(), MavlinkParams(), Arming())
    p = Packer()
    unknown = bytearray(p.heartbeat())
    unknown[7:10] = (0x39, 0x30, 0x00)  # message id 12345: no such message (its CRC cannot match)
    link.handle_datagram(b"\x00\xfe\x09" + bytes(unknown) + b"\xfdjunk" + p.heartbeat() + b"\xfd\x05",
                         ("127.0.0.1", 14550))
    assert link.gcs_alive and link.counters["rx"] == 1  # only the heartbeat counts as traffic
    assert link.counters["unknown_ids"] >= 1 and link.counters["bad_data"] == 1


def test_mavlink_1_frames_are_refused():
    link = MavlinkGcs(Bus(), MavlinkParams(), Arming())
    p = Packer()
    p.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0, force_mavlink1=True)
    v1 = p.out.pop()
    assert v1[0] == 0xFE
    link.handle_datagram(v1 + p.heartbeat(), ("127.0.0.1", 14550))
    assert link.counters["mavlink1_refused"] == 1 and link.counters["rx"] == 1 and link.gcs_alive


def test_ten_thousand_random_datagrams_make_no_station_and_no_lost_heartbeat_event():
    rng = random.Random(16)
    clock = [0]
    link = MavlinkGcs(Bus(), MavlinkParams(), Arming(), clock=lambda: clock[0])
    for i in range(10_000):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 80)))
        if i % 3 == 0:
            data = b"\xfd" + data  # start like a MAVLink 2 frame
        link.handle_datagram(data, ("127.0.0.1", 14550))
        clock[0] += NS_PER_S // 100
        link.tick()
    assert link.counters["rx"] == 0 and not link.gcs_alive and link.counters["gcs_timeouts"] == 0


# --- time: overrides expire, stale input does not block arming ---------------------------------


class Clocked:
    """A link on a test clock (ns); ``at(t)`` sends datagrams at ``t`` seconds and ticks."""

    def __init__(self, **params: Any) -> None:
        self.now = 0
        self.bus = Bus()
        self.arming = Arming(start_armed=True)
        self.drives: list[tuple[float, float]] = []
        self.bus.subscribe(TELEOP, lambda m: self.drives.append((m.drive.speed, m.drive.steering_angle)))
        self.link = MavlinkGcs(self.bus, MavlinkParams(**params), self.arming, clock=lambda: self.now)
        self.p = Packer()

    def at(self, t_s: float, *datagrams: bytes) -> tuple[float, float] | None:
        self.now = round(t_s * NS_PER_S)
        for d in datagrams:
            self.link.handle_datagram(d, ("127.0.0.1", 14550))
        count = len(self.drives)
        self.link.tick()
        return self.drives[-1] if len(self.drives) > count else None


def test_an_rc_override_value_expires_after_3_s_and_65535_never_revives_it():
    c = Clocked()
    p = c.p
    assert c.at(0.0, p.heartbeat(), p.rc(1500, 1750)) == pytest.approx((1.0, 0.0))
    t = 0.0
    while t < 2.9:  # steering changes, throttle "unchanged"
        t = round(t + 0.5, 1)
        assert c.at(min(t, 2.9), p.heartbeat(), p.rc(1600, 65535)) == pytest.approx((1.0, -0.068))
    assert c.at(3.1, p.heartbeat(), p.rc(1600, 65535)) == pytest.approx((0.0, -0.068))  # expired
    assert c.at(3.5, p.heartbeat(), p.rc(1600, 65535)) == pytest.approx((0.0, -0.068))  # not revived
    assert c.at(3.6, p.heartbeat(), p.rc(1600, 1375)) == pytest.approx((-0.5, -0.068))  # a new value
    # both channels unchanged after both expired: driving stops at once
    assert c.at(7.0, p.heartbeat(), p.rc(65535, 65535)) == (0.0, 0.0)
    assert c.link.manual is None


def test_an_rc_override_expires_on_time_even_with_a_longer_input_timeout():
    """input_timeout_s 10 s, rc_override_time_s 3 s (both allowed): the override stops driving at
    3 s by the ticks alone, with heartbeats but no further RC message."""
    c = Clocked(input_timeout_s=10.0, rc_override_time_s=3.0)
    p = c.p
    assert c.at(0.0, p.heartbeat(), p.rc(1500, 1750)) == pytest.approx((1.0, 0.0))
    for t in (0.5, 1.0, 2.0, 2.95):
        assert c.at(t, p.heartbeat()) == pytest.approx((1.0, 0.0))
    assert c.at(3.05, p.heartbeat()) == (0.0, 0.0)  # expired: one stop
    assert c.link.manual is None
    for t in (3.5, 4.0, 6.0, 9.0):
        assert c.at(t, p.heartbeat()) is None  # then silence
    # one channel expiring alone: the other keeps its value, the expired one rests
    assert c.at(10.0, p.heartbeat(), p.rc(1750, 1750)) == pytest.approx((1.0, -0.17))
    assert c.at(12.0, p.heartbeat(), p.rc(65535, 1625)) == pytest.approx((0.5, -0.17))
    assert c.at(13.5, p.heartbeat()) == pytest.approx((0.5, 0.0))  # steering set at 10.0: expired
    assert c.at(15.05, p.heartbeat()) == (0.0, 0.0)  # throttle set at 12.0: expired too


def test_an_expired_rc_throttle_does_not_block_arming_within_the_input_timeout():
    c = Clocked(input_timeout_s=10.0, rc_override_time_s=3.0)
    c.arming.disarm("test")
    p = c.p
    c.link.handle_datagram(p.heartbeat(), ("127.0.0.1", 14550))
    c.link.handle_datagram(p.rc(1500, 1800), ("127.0.0.1", 14550))
    c.now = NS_PER_S
    c.link.handle_datagram(p.arm(), ("127.0.0.1", 14550))
    assert not c.arming.armed  # a live throttle: refused
    c.now = 4 * NS_PER_S  # no tick in between: the arm command itself sees the expiry
    c.link.handle_datagram(p.heartbeat(), ("127.0.0.1", 14550))
    c.link.handle_datagram(p.arm(), ("127.0.0.1", 14550))
    assert c.arming.armed


def test_arming_is_not_refused_for_a_throttle_older_than_the_input_timeout():
    c = Clocked()
    c.arming.disarm("test")
    p = c.p
    c.at(0.0, p.heartbeat(), p.manual(600))
    c.at(0.1, p.heartbeat(), p.arm())
    assert not c.arming.armed  # a fresh throttle above zero: refused
    c.at(1.5, p.heartbeat(), p.arm())  # the throttle is 1.5 s old (input_timeout_s 1.0)
    assert c.arming.armed


# --- addresses and configuration ---------------------------------------------------------------


def test_an_ipv6_ground_station_address_binds_ipv6():
    """Config only, no socket: an IPv6 loopback station binds ::1, a remote one ::."""
    assert MavlinkParams(enabled=True, gcs_address="[::1]:14550", bind_port=0).bind == ("::1", 0)
    assert MavlinkParams(gcs_address="[::1]:14550").gcs == ("::1", 14550)
    remote = MavlinkParams(gcs_address="[2001:DB8::1]:14550", signing_key_file="k")
    assert remote.bind == ("::", 14555)
    assert remote.gcs == ("2001:db8::1", 14550)  # as the socket names a datagram's source
    assert MavlinkParams(gcs_address="192.0.2.7:14550", signing_key_file="k").bind == ("0.0.0.0", 14555)


def test_an_ipv6_loopback_ground_station_talks_over_ipv6():
    if not socket.has_ipv6:
        pytest.skip("no IPv6 on this machine")
    try:
        gs = Station(family=socket.AF_INET6)
    except OSError as err:
        pytest.skip(f"no IPv6 loopback here: {err}")

    async def main() -> None:
        params = MavlinkParams(enabled=True, gcs_address=gs.address, bind_port=0)
        link = await started(params, Arming(start_armed=False))
        gs.send(link, Packer().heartbeat())
        await async_wait_for(lambda: link.gcs_alive)
        link.send_heartbeat()
        await gs.wait("HEARTBEAT")
        link.close()
        gs.close()

    run(main)


def test_a_host_name_for_the_ground_station_is_refused_naming_the_key(capsys, tmp_path: Path):
    """A name would make every datagram foreign (they are matched by source address): refused in
    the config, by check-config and at start, with the key named; loopback names still work."""
    key = tmp_path / "key"
    write_signing_key(key)
    with pytest.raises(ConfigError) as info:
        MavlinkParams(enabled=True, gcs_address="gcs.lan:14550", signing_key_file=str(key))
    assert info.value.key == "mavlink.gcs_address" and "gcs.lan" in str(info.value)
    args = ["check-config", "--set", "mavlink.enabled=true", "--set", "mavlink.gcs_address=gcs.lan:14550",
            "--set", f"mavlink.signing_key_file={key}"]
    assert cli_main(args) == 1
    err = capsys.readouterr().err
    assert "mavlink.gcs_address" in err and "gcs.lan" in err and "IP address" in err
    assert "Traceback" not in err
    for name in ("localhost", "localhost.localdomain", "ip6-localhost"):
        link = MavlinkGcs(Bus(), MavlinkParams(enabled=True, gcs_address=f"{name}:14550"), Arming())
        link.handle_datagram(Packer().heartbeat(), ("127.0.0.1", 14550))
        assert link.gcs_alive and link.counters["foreign"] == 0, name


def test_a_remote_ipv6_station_written_in_capitals_is_heard(tmp_path: Path):
    key = write_signing_key(tmp_path / "key")
    link = MavlinkGcs(Bus(), MavlinkParams(enabled=True, gcs_address="[2001:DB8::7]:14550",
                                           signing_key_file=str(tmp_path / "key")), Arming())
    link.handle_datagram(Packer(key=key).heartbeat(), ("2001:db8::7", 14550, 0, 0))
    assert link.gcs_alive and link.counters["foreign"] == 0
    link.handle_datagram(Packer(key=key).heartbeat(), ("2001:db8::8", 14550, 0, 0))
    assert link.counters["foreign"] == 1


def test_check_config_refuses_a_remote_ground_station_without_a_signing_key(capsys, tmp_path: Path):
    args = ["check-config", "--set", "mavlink.enabled=true",
            "--set", "mavlink.gcs_address=192.168.1.20:14550"]
    assert cli_main(args) == 1
    err = capsys.readouterr().err
    assert "mavlink.signing_key_file" in err and "192.168.1.20" in err and "Traceback" not in err
    write_signing_key(tmp_path / "key")
    assert cli_main([*args, "--set", f"mavlink.signing_key_file={tmp_path / 'key'}"]) == 0
    assert cli_main(["check-config", "--set", "mavlink.gcs_address=192.168.1.20:14550"]) == 0  # disabled


if __name__ == "__main__":
    sys.exit(pytest.main([__file__]))
