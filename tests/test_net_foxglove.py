"""The Foxglove live view, seen by a raw WebSocket client (``websockets``) speaking ``foxglove.sdk.v1``.

``racecar-hw sim`` runs in a subprocess with the Foxglove server on a free port. The client reads the
advertised channels and decodes messages with a rosbags typestore built only from the schemas the
server advertised (a missing dependency in a schema fails there), publishes Twist messages as the
Teleop panel does, and calls the e-stop services.
"""

from __future__ import annotations

import asyncio
import json
import math
import struct
import time
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from live_sim import running_sim
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from websockets.asyncio.client import connect

from racecar_hw.base.messages import AckermannDrive, Twist, Vector3
from racecar_hw.net.foxglove_server import (
    FoxgloveParams,
    decode_twist,
    flatten_parameters,
    trigger_response,
    twist_to_drive,
)
from racecar_hw.rosmsg.typestore import ros2_types

SUBPROTOCOL = "foxglove.sdk.v1"
TELEOP = "/foxglove/cmd_vel"
EXPECTED = {  # topic: schema name
    "/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry", "/tf": "tf2_msgs/msg/TFMessage",
    "/tf_static": "tf2_msgs/msg/TFMessage", "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "/vesc/low_level/ackermann_cmd_mux/output": "ackermann_msgs/msg/AckermannDriveStamped",
    "/vesc/low_level/ackermann_cmd_mux/active": "std_msgs/msg/String",
    "/vesc/sensors/core": "vesc_msgs/msg/VescStateStamped",
    "/safety/state": "diagnostic_msgs/msg/DiagnosticArray",
    "/map": "nav_msgs/msg/OccupancyGrid", "/sim/pose": "geometry_msgs/msg/PoseStamped",
    "/safety/scene": "foxglove.SceneUpdate", "/log": "foxglove.Log",
}


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    with running_sim(["--scenario", "figure8", "--scenario-set", "drivers=[]", "--duration", "300",
                      "--set", "foxglove.port=0", "--set", "web.enabled=false",
                      "--out", str(tmp_path_factory.mktemp("sim"))]) as proc:
        yield proc


class Client:
    """A minimal ws-protocol client: channels, subscriptions, client publishing, service calls."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}
        self.services: dict[str, dict[str, Any]] = {}
        self.store = get_typestore(Stores.EMPTY)
        self.messages: dict[int, list[tuple[float, bytes]]] = {}
        self.responses: dict[int, bytes] = {}
        self.json: list[dict[str, Any]] = []
        self._subs: dict[int, int] = {}
        self._reader: asyncio.Task[None] | None = None

    async def start(self) -> None:
        deadline = time.monotonic() + 20
        while not (self.server_info and self.services and "/scan" in self.channels):
            self._handle(await asyncio.wait_for(self.ws.recv(), max(0.1, deadline - time.monotonic())))
        self._reader = asyncio.ensure_future(self._read())

    async def _read(self) -> None:
        async for frame in self.ws:
            self._handle(frame)

    def _handle(self, frame: str | bytes) -> None:
        if isinstance(frame, str):
            msg = json.loads(frame)
            self.json.append(msg)
            if msg["op"] == "serverInfo":
                self.server_info = msg
            elif msg["op"] == "advertise":
                for ch in msg["channels"]:
                    self.channels[ch["topic"]] = ch
            elif msg["op"] == "advertiseServices":
                for svc in msg["services"]:
                    self.services[svc["name"]] = svc
            return
        if frame[0] == 0x01:
            sub, _t = struct.unpack_from("<IQ", frame, 1)
            self.messages.setdefault(sub, []).append((time.monotonic(), frame[13:]))
        elif frame[0] == 0x03:
            _service, call, n = struct.unpack_from("<III", frame, 1)
            self.responses[call] = frame[13 + n:]

    def ros_type(self, topic: str) -> str:
        """Register the advertised schema of ``topic`` (and only it) in the client's own store."""
        ch = self.channels[topic]
        assert ch["encoding"] == "cdr" and ch["schemaEncoding"] == "ros2msg"
        self.store.register(get_types_from_msg(ch["schema"], ch["schemaName"]))
        return ch["schemaName"]

    async def subscribe(self, topic: str) -> int:
        sub = len(self._subs) + 1
        self._subs[sub] = self.channels[topic]["id"]
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": sub, "channelId": self.channels[topic]["id"]}]}))
        return sub

    async def next_message(self, sub: int, after: float = 0.0, timeout_s: float = 20.0) -> bytes:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, payload in self.messages.get(sub, []):
                if t > after:
                    return payload
            await asyncio.sleep(0.02)
        raise AssertionError(f"no message on subscription {sub} within {timeout_s} s")

    def decode(self, topic: str, payload: bytes) -> Any:
        return self.store.deserialize_cdr(payload, self.channels[topic]["schemaName"])

    async def call(self, service: str, call_id: int, timeout_s: float = 10.0) -> bytes:
        svc = self.services[service]
        encoding = b"cdr"
        empty = b"\x00\x01\x00\x00\x00"  # CDR of an empty request (one placeholder byte)
        request = struct.pack("<BIII", 0x02, svc["id"], call_id, len(encoding)) + encoding + empty
        await self.ws.send(request)
        deadline = time.monotonic() + timeout_s
        while call_id not in self.responses:
            assert time.monotonic() < deadline, f"no answer from {service}"
            await asyncio.sleep(0.02)
        return self.responses[call_id]

    async def close(self) -> None:
        if self._reader is not None:
            self._reader.cancel()
        await self.ws.close()


async def _client(port: int) -> Client:
    ws = await connect(f"ws://127.0.0.1:{port}/", subprotocols=[SUBPROTOCOL], max_size=None)
    assert ws.subprotocol == SUBPROTOCOL
    client = Client(ws)
    await client.start()
    return client


def _speed(client: Client, payload: bytes) -> float:
    return float(client.decode("/odom", payload).twist.twist.linear.x)


def test_channels_have_complete_ros2_schemas_and_scans_decode_with_rosbags(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            caps = set(client.server_info["capabilities"])
            assert {"clientPublish", "services", "parameters"} <= caps
            assert {"cdr", "json"} <= set(client.server_info["supportedEncodings"])
            for topic, schema in EXPECTED.items():
                assert client.channels[topic]["schemaName"] == schema, topic
            for topic, ch in client.channels.items():
                if ch.get("schemaEncoding") == "ros2msg":
                    # each schema alone is enough to register its type: the dependencies are inside
                    store = get_typestore(Stores.EMPTY)
                    store.register(get_types_from_msg(ch["schema"], ch["schemaName"]))
                    assert ch["schemaName"] in store.fielddefs, topic
                    assert ch["schema"] == ros2_types().msgdef(ch["schemaName"])
            assert set(client.services) == {"/racecar/estop", "/racecar/release", "/racecar/arm",
                                            "/racecar/disarm"}
            client.ros_type("/scan")
            scan = client.decode("/scan", await client.next_message(await client.subscribe("/scan")))
            assert scan.header.frame_id == "laser" and len(scan.ranges) == 1081
            assert scan.angle_min == pytest.approx(-2.356, abs=1e-3)
            assert 0.0 < float(min(r for r in scan.ranges if math.isfinite(r))) < 10.0
            # latched: a late subscriber gets the static transforms and the map at once
            client.ros_type("/tf_static")
            tf = client.decode("/tf_static", await client.next_message(await client.subscribe("/tf_static")))
            pairs = {(t.header.frame_id, t.child_frame_id) for t in tf.transforms}
            assert {("base_link", "laser"), ("map", "odom")} <= pairs
            client.ros_type("/map")
            grid = client.decode("/map", await client.next_message(await client.subscribe("/map")))
            assert grid.info.width * grid.info.height == len(grid.data) > 1000
            # the configuration, read-only
            await client.ws.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "p"}))
            deadline = time.monotonic() + 10
            while not any(m.get("op") == "parameterValues" for m in client.json):
                assert time.monotonic() < deadline
                await asyncio.sleep(0.02)
            values = next(m for m in client.json if m.get("op") == "parameterValues")
            params = {p["name"]: p["value"] for p in values["parameters"]}
            assert params["mux.rate_hz"] == 50.0 and params["foxglove.teleop_topic"] == TELEOP
        finally:
            await client.close()

    asyncio.run(main())


def test_teleop_twist_drives_and_the_estop_service_stops_until_release(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            client.ros_type("/odom")
            odom = await client.subscribe("/odom")
            await client.ws.send(json.dumps({"op": "advertise", "channels": [{
                "id": 7, "topic": TELEOP, "encoding": "cdr", "schemaName": "geometry_msgs/msg/Twist",
                "schema": ros2_types().msgdef("geometry_msgs/msg/Twist"), "schemaEncoding": "ros2msg"}]}))
            twist = ros2_types().serialize(Twist(Vector3(0.6, 0.0, 0.0), Vector3(0.0, 0.0, 0.3)))
            stop_sending = asyncio.Event()

            async def teleop() -> None:  # the Teleop panel: 10 Hz while the button is held
                while not stop_sending.is_set():
                    await client.ws.send(struct.pack("<BI", 0x01, 7) + twist)
                    await asyncio.sleep(0.1)

            sender = asyncio.ensure_future(teleop())

            async def speed_reaches(test: Any, timeout_s: float = 20.0) -> float:
                deadline = time.monotonic() + timeout_s
                while True:
                    speed = _speed(client, await client.next_message(odom, time.monotonic()))
                    if test(speed):
                        return speed
                    assert time.monotonic() < deadline, f"odometry speed stayed at {speed}"

            assert await speed_reaches(lambda v: v > 0.4) > 0.4
            log_from = len(sim.lines)
            response = await client.call("/racecar/estop", 1)
            assert response[4] == 1 and b"e-stop latched" in response
            # on the VESC wire the first motor command after the request is the brake, not a ramp
            await asyncio.to_thread(
                sim.wait_for, r"sim: e-stop from foxglove client \d+ .* fake VESC: brake SET_RPM 0 at "
                r"wall .*, the first motor command written after the request$", start=log_from)
            await speed_reaches(lambda v: abs(v) < 0.02)
            # it stays stopped while the Twist keeps coming
            until = time.monotonic() + 1.5
            while time.monotonic() < until:
                assert abs(_speed(client, await client.next_message(odom, time.monotonic()))) < 0.05
            response = await client.call("/racecar/release", 2)
            assert response[4] == 1
            assert await speed_reaches(lambda v: v > 0.4) > 0.4
            # the tab closes: the teleop input times out and the car stops
            stop_sending.set()
            await sender
            await speed_reaches(lambda v: abs(v) < 0.02, timeout_s=10.0)
        finally:
            await client.close()

    asyncio.run(main())


def test_the_safety_scene_the_speeds_and_the_log_reach_a_subscriber(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            assert client.channels["/safety/speeds"]["encoding"] == "json"
            scene = await client.subscribe("/safety/scene")
            speeds = await client.subscribe("/safety/speeds")
            logs = await client.subscribe("/log")
            assert len(await client.next_message(scene)) > 100  # protobuf: entities with triangles
            numbers = json.loads(await client.next_message(speeds))
            assert set(numbers) >= {"commanded", "output", "allowed", "measured", "steering", "state"}
            assert numbers["state"] in ("clear", "limiting", "stopped")
            started = time.monotonic()
            assert (await client.call("/racecar/arm", 11))[4] == 1
            deadline = time.monotonic() + 20
            while not any(b"/racecar/arm" in p for t, p in client.messages.get(logs, []) if t > started):
                assert time.monotonic() < deadline, "the service call's log record did not arrive"
                await asyncio.sleep(0.05)
        finally:
            await client.close()

    asyncio.run(main())


def test_twist_to_ackermann_uses_the_wheelbase_and_the_limits():
    def drive(v: float, w: float) -> AckermannDrive:
        return twist_to_drive(Twist(Vector3(v, 0, 0), Vector3(0, 0, w)), 0.25, 1.0, 0.34)

    d = drive(0.5, 0.4)  # yaw rate v / L * tan(delta) = 0.4
    assert d.speed == 0.5 and d.steering_angle == pytest.approx(math.atan(0.25 * 0.4 / 0.5))
    assert drive(-0.5, 0.4).steering_angle == pytest.approx(-math.atan(0.25 * 0.4 / 0.5))  # reverse
    assert drive(3.0, 0.0).speed == 1.0 and drive(-3.0, 0.0).speed == -1.0
    assert drive(0.0, 1.0) == AckermannDrive(steering_angle=0.34, speed=0.0)
    assert drive(0.2, 50.0).steering_angle == 0.34
    assert drive(math.nan, 0.0) == AckermannDrive() == drive(0.5, math.inf)


def test_trigger_response_is_the_cdr_rosbags_writes():
    store = get_typestore(Stores.EMPTY)
    name = "std_srvs/msg/Trigger_Response"  # rosbags names message types pkg/msg/Name
    store.register(get_types_from_msg("bool success\nstring message\n", name))
    for ok, text in ((True, "e-stop latched"), (False, ""), (True, "ü")):
        msg = store.types[name](success=ok, message=text)
        assert trigger_response(ok, text) == bytes(store.serialize_cdr(msg, name))


def test_parameters_are_flat_and_hide_the_tokens():
    params = flatten_parameters({"web": {"token": "s3cret", "port": 8080}, "foxglove": {"token": ""},
                                 "mux": {"inputs": [{"name": "teleop"}], "rate_hz": 50.0},
                                 "static_transforms": [[0.1, 0.2]], "xyz": [0.265, 0, 0.1]})
    assert params["web.token"] == "(set, hidden)" and params["foxglove.token"] == ""
    assert "s3cret" not in json.dumps(params)
    assert params["web.port"] == 8080 and params["mux.rate_hz"] == 50.0 and params["xyz"] == [0.265, 0.0, 0.1]
    assert json.loads(params["mux.inputs"]) == [{"name": "teleop"}]


def test_a_non_loopback_bind_needs_a_token():
    from racecar_hw.base.errors import ConfigError

    with pytest.raises(ConfigError, match="foxglove.token"):
        FoxgloveParams(host="0.0.0.0")
    assert FoxgloveParams(host="0.0.0.0", token="secret").token == "secret"
    assert FoxgloveParams(host="::1").host == "::1"


@settings(max_examples=300, deadline=None)
@given(st.one_of(
    st.binary(max_size=80),
    st.binary(max_size=60).map(lambda b: b"\x00\x01\x00\x00" + b),  # a CDR header, then anything
    st.builds(lambda x, z: ros2_types().serialize(Twist(Vector3(x, 0, 0), Vector3(0, 0, z))),
              st.floats(allow_nan=True, allow_infinity=True), st.floats(allow_nan=True, allow_infinity=True)),
    st.recursive(st.none() | st.booleans() | st.floats() | st.text(max_size=5),
                 lambda inner: st.lists(inner, max_size=3) | st.dictionaries(
                     st.sampled_from(["linear", "angular", "x", "z"]), inner, max_size=3),
                 ).map(lambda v: json.dumps(v).encode()),
), st.sampled_from(["cdr", "json"]))
def test_any_bytes_from_a_client_become_a_finite_bounded_command_or_a_refusal(data, encoding):
    try:
        twist = decode_twist(data, encoding)
    except Exception:  # noqa: BLE001 - refused: FoxgloveServer.message counts and logs it
        return
    drive = twist_to_drive(twist, 0.25, 1.0, 0.34)
    assert math.isfinite(drive.speed) and abs(drive.speed) <= 1.0
    assert math.isfinite(drive.steering_angle) and abs(drive.steering_angle) <= 0.34
