"""The Foxglove live view, seen by a raw WebSocket client (``websockets``) speaking ``foxglove.sdk.v1``.

``racecar-hw sim`` runs in a subprocess with the Foxglove server on a free port. The client reads the
advertised channels and decodes messages with a rosbags typestore built only from the schemas the
server advertised (a missing dependency in a schema fails there), and the protobuf scene with Google's
protobuf runtime from its advertised FileDescriptorSet; it publishes Twist messages as the Teleop
panel does, calls the e-stop and arming services, and tries to set parameters.
"""

from __future__ import annotations

import asyncio
import base64
import http.server
import json
import math
import re
import ssl
import struct
import threading
import time
from typing import Any

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from hypothesis import given, settings
from hypothesis import strategies as st
from live_sim import chromium, running_sim
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidMessage, InvalidStatus

from racecar_hw.base.messages import AckermannDrive, Twist, Vector3
from racecar_hw.net.auth import browser_origin_allowed
from racecar_hw.net.foxglove_server import (
    FoxgloveParams,
    decode_twist,
    flatten_parameters,
    trigger_response,
    twist_to_drive,
)
from racecar_hw.net.scene import COLOURS
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.sim.scenario import load_scenario

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
    "/clock": "rosgraph_msgs/msg/Clock",
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

    def decode_protobuf(self, topic: str, payload: bytes) -> Any:
        """Decode with Google's protobuf runtime from the advertised schema (a FileDescriptorSet) alone."""
        ch = self.channels[topic]
        assert ch["encoding"] == "protobuf" and ch["schemaEncoding"] == "protobuf"
        files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch["schema"]))
        pool = descriptor_pool.DescriptorPool()
        for proto in files.file:  # the SDK lists each file after its dependencies
            pool.Add(proto)
        message = message_factory.GetMessageClass(pool.FindMessageTypeByName(ch["schemaName"]))
        return message.FromString(payload)

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


class Teleop:
    """The Teleop panel: advertises the Twist topic and sends one at 10 Hz while the button is held."""

    def __init__(self, client: Client, linear: float = 0.6, angular: float = 0.3) -> None:
        self.client = client
        self.twist = ros2_types().serialize(Twist(Vector3(linear, 0.0, 0.0), Vector3(0.0, 0.0, angular)))
        self.held = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        await self.client.ws.send(json.dumps({"op": "advertise", "channels": [{
            "id": 7, "topic": TELEOP, "encoding": "cdr", "schemaName": "geometry_msgs/msg/Twist",
            "schema": ros2_types().msgdef("geometry_msgs/msg/Twist"), "schemaEncoding": "ros2msg"}]}))
        self.held.set()
        self._task = asyncio.ensure_future(self._send())

    async def _send(self) -> None:
        while self.held.is_set():
            await self.client.ws.send(struct.pack("<BI", 0x01, 7) + self.twist)
            await asyncio.sleep(0.1)

    async def let_go(self) -> None:
        self.held.clear()
        if self._task is not None:
            await self._task


async def _odometry(client: Client) -> int:
    client.ros_type("/odom")
    return await client.subscribe("/odom")


async def _speed_reaches(client: Client, odom: int, test: Any, timeout_s: float = 20.0) -> float:
    """The first odometry speed (m/s) after now that passes ``test``; fails after the timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        speed = _speed(client, await client.next_message(odom, time.monotonic()))
        if test(speed):
            return speed
        assert time.monotonic() < deadline, f"odometry speed stayed at {speed}"


async def _stays_still(client: Client, odom: int, seconds: float) -> None:
    until = time.monotonic() + seconds
    while time.monotonic() < until:
        assert abs(_speed(client, await client.next_message(odom, time.monotonic()))) < 0.05


async def _teleop_drives(client: Client, odom: int) -> Teleop:
    """Start the Teleop Twist; returns once the car goes faster than 0.4 m/s."""
    teleop = Teleop(client)
    await teleop.start()
    assert await _speed_reaches(client, odom, lambda v: v > 0.4) > 0.4
    return teleop


async def _stops_and_stays(client: Client, odom: int) -> None:
    await _speed_reaches(client, odom, lambda v: abs(v) < 0.02)
    await _stays_still(client, odom, 1.5)


async def _stops_when_let_go(client: Client, odom: int, teleop: Teleop) -> None:
    """The tab closes: the teleop input times out and the car stops."""
    await teleop.let_go()
    await _speed_reaches(client, odom, lambda v: abs(v) < 0.02, timeout_s=10.0)


def test_teleop_twist_drives_and_the_estop_service_stops_until_release(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            odom = await _odometry(client)
            teleop = await _teleop_drives(client, odom)
            log_from = len(sim.lines)
            response = await client.call("/racecar/estop", 1)
            assert response[4] == 1 and b"e-stop latched" in response
            # on the VESC wire the first motor command after the request is the brake, not a ramp
            await asyncio.to_thread(
                sim.wait_for, r"sim: e-stop from foxglove client \d+ .* fake VESC: brake SET_RPM 0 at "
                r"wall .*, the first motor command written after the request$", start=log_from)
            await _stops_and_stays(client, odom)  # while the Twist keeps coming
            response = await client.call("/racecar/release", 2)
            assert response[4] == 1
            assert await _speed_reaches(client, odom, lambda v: v > 0.4) > 0.4
            await _stops_when_let_go(client, odom, teleop)
        finally:
            await client.close()

    asyncio.run(main())


def test_the_disarm_service_stops_every_source_until_armed_again(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            odom = await _odometry(client)
            scene = await client.subscribe("/safety/scene")
            teleop = await _teleop_drives(client, odom)
            response = await client.call("/racecar/disarm", 21)
            assert response[4] == 1 and b"disarmed" in response
            await _stops_and_stays(client, odom)  # the Twist keeps coming: disarmed stops it
            label = client.decode_protobuf(
                "/safety/scene", await client.next_message(scene, time.monotonic())).entities[0].texts[0].text
            assert label.endswith("(disarmed)"), label
            assert (await client.call("/racecar/arm", 22))[4] == 1
            assert await _speed_reaches(client, odom, lambda v: v > 0.4) > 0.4
            await _stops_when_let_go(client, odom, teleop)
        finally:
            await client.close()

    asyncio.run(main())


def test_parameters_cannot_be_set(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            async def values(request: dict[str, Any]) -> dict[str, Any]:
                await client.ws.send(json.dumps(request))
                deadline = time.monotonic() + 10
                while True:
                    reply = next((m for m in client.json if m.get("op") == "parameterValues"
                                  and m.get("id") == request["id"]), None)
                    if reply is not None:
                        return {p["name"]: p["value"] for p in reply["parameters"]}
                    assert time.monotonic() < deadline, f"no answer to {request['op']}"
                    await asyncio.sleep(0.02)

            log_from = len(sim.lines)
            answer = await values({"op": "setParameters", "id": "set", "parameters": [
                {"name": "mux.rate_hz", "value": 5.0}, {"name": "web.token", "value": "mine"},
                {"name": "foxglove.teleop_max_speed_mps", "value": 9.0}]})
            # the answer is the current value, unchanged; a later read says the same
            assert answer == {"mux.rate_hz": 50.0, "foxglove.teleop_max_speed_mps": 1.0, "web.token": ""}
            again = await values({"op": "getParameters", "id": "get", "parameterNames": list(answer)})
            assert again == answer
            await asyncio.to_thread(sim.wait_for, r"foxglove: client \d+ tried to set parameters; they are "
                                    r"read-only", start=log_from)
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
            await _check_scene(client, scene)
            numbers = json.loads(await client.next_message(speeds))
            assert set(numbers) >= {"commanded", "output", "steering", "state"}
            assert numbers["state"] in ("clear", "limiting", "stopped")
            # one JSON type per field, as Foxglove and Lichtblick can parse (["number", "null"] makes
            # them refuse the channel and plot nothing), and every value of that type
            schema = client.channels["/safety/speeds"]
            assert schema["schemaEncoding"] == "jsonschema"
            fields = json.loads(schema["schema"])["properties"]
            assert set(numbers) <= set(fields) and {"allowed", "measured"} <= set(fields)
            python = {"number": (int, float), "string": str}
            for name, field in fields.items():
                assert field["type"] in python, name
                if name in numbers:
                    assert isinstance(numbers[name], python[field["type"]]), (name, numbers[name])
            started = time.monotonic()
            assert (await client.call("/racecar/arm", 11))[4] == 1
            deadline = time.monotonic() + 20
            while not any(b"/racecar/arm" in p for t, p in client.messages.get(logs, []) if t > started):
                assert time.monotonic() < deadline, "the service call's log record did not arrive"
                await asyncio.sleep(0.05)
        finally:
            await client.close()

    asyncio.run(main())


async def _check_scene(client: Client, scene: int) -> None:
    """A scene update, decoded from its advertised protobuf schema: the band, the body and the label."""
    deadline = time.monotonic() + 20
    while True:  # the first ones may come before the first scan ("stopped: no_scan")
        update = client.decode_protobuf("/safety/scene", await client.next_message(scene, time.monotonic()))
        safety = update.entities[0]
        label = safety.texts[0].text
        if "no_scan" not in label:
            break
        assert time.monotonic() < deadline, label
    assert [e.id for e in update.entities] == ["safety", "obstacle"]
    assert {e.frame_id for e in update.entities} == {"base_link"}
    assert abs(safety.timestamp.seconds + safety.timestamp.nanos / 1e9 - time.time()) < 10.0
    # the label: the safety state, its reason, the allowed speed; the band coloured by that state
    match = re.fullmatch(r"(clear|limiting|stopped): (\w+), (allowed \d+\.\d\d m/s|no limit)( \(.*\))?",
                         label)
    assert match, label
    (band,) = safety.triangles
    assert len(band.points) % 3 == 0 and len(band.points) >= 6
    rgba = (band.color.r, band.color.g, band.color.b, band.color.a)
    assert rgba == pytest.approx(COLOURS[match.group(1)])
    # the body: a closed loop of four corners around base_link (the centre of the rear axle)
    body, outer, inner = safety.lines
    assert body.type == 1 and outer.type == inner.type == 0  # LINE_LOOP, LINE_STRIP
    xs, ys = [p.x for p in body.points], [p.y for p in body.points]
    assert len(xs) == 4 and min(xs) < 0.0 < max(xs) and min(ys) == pytest.approx(-max(ys)) and max(ys) > 0.0
    # both edges of the band start at the front bumper (the car stands or drives forwards here)
    assert outer.points[0].x == pytest.approx(max(xs)) and inner.points[0].x == pytest.approx(max(xs))


def test_the_mux_and_network_security_diagnostics_reach_a_subscriber(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            client.ros_type("/diagnostics")
            diagnostics = await client.subscribe("/diagnostics")
            await client.next_message(diagnostics)
            statuses: dict = {}
            deadline = time.monotonic() + 20.0
            while not {"racecar_hw: command mux", "racecar_hw: network security"} <= statuses.keys() \
                    and time.monotonic() < deadline:  # each publishes its own array
                for _t, payload in list(client.messages.get(diagnostics, [])):
                    (status,) = client.decode("/diagnostics", payload).status
                    statuses[status.name] = status
                await asyncio.sleep(0.05)
            mux = statuses["racecar_hw: command mux"]
            values = {kv.key: kv.value for kv in mux.values}
            assert values["state"] == "running" and "input foxglove (priority 85)" in values
            security = statuses["racecar_hw: network security"]
            assert security.values[0].key == "refused in all"
        finally:
            await client.close()

    asyncio.run(main())


def test_the_simulations_clock_reaches_a_subscriber(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            assert client.ros_type("/clock") == "rosgraph_msgs/msg/Clock"
            sub = await client.subscribe("/clock")
            first = client.decode("/clock", await client.next_message(sub)).clock
            after = client.messages[sub][-1][0]
            later = client.decode("/clock", await client.next_message(sub, after)).clock
            # the real-time sim's clock: the wall clock, the stamps' time base; it advances
            assert abs(first.sec - time.time()) < 60
            assert (later.sec, later.nanosec) > (first.sec, first.nanosec)
        finally:
            await client.close()

    asyncio.run(main())


def test_the_true_pose_is_in_the_map_frame_on_free_ground_where_odometry_puts_the_car(sim):
    async def main() -> None:
        client = await _client(sim.port("foxglove"))
        try:
            for topic in ("/sim/pose", "/odom", "/tf_static", "/map"):
                client.ros_type(topic)
            grid = client.decode("/map", await client.next_message(await client.subscribe("/map")))
            tf_static = await client.subscribe("/tf_static")
            static = client.decode("/tf_static", await client.next_message(tf_static))
            map_odom = next(t.transform for t in static.transforms
                            if (t.header.frame_id, t.child_frame_id) == ("map", "odom"))
            # map -> odom is the scenario's start pose: odometry starts at zero where the car starts
            start = load_scenario("figure8").start
            assert (map_odom.translation.x, map_odom.translation.y, _yaw(map_odom.rotation)) == \
                pytest.approx(start, abs=1e-9)
            odom, true = await client.subscribe("/odom"), await client.subscribe("/sim/pose")
            now = time.monotonic()
            odometry = client.decode("/odom", await client.next_message(odom, now))
            pose = client.decode("/sim/pose", await client.next_message(true, now))
            assert pose.header.frame_id == "map" and odometry.header.frame_id == "odom"
            # odometry carried into map by the static transform lands where the world has the car
            # (within the fake odometry's drift after the other tests' driving)
            yaw0 = _yaw(map_odom.rotation)
            ox, oy = odometry.pose.pose.position.x, odometry.pose.pose.position.y
            in_map = (map_odom.translation.x + ox * math.cos(yaw0) - oy * math.sin(yaw0),
                      map_odom.translation.y + ox * math.sin(yaw0) + oy * math.cos(yaw0))
            x, y = pose.pose.position.x, pose.pose.position.y
            assert math.hypot(x - in_map[0], y - in_map[1]) < 0.3
            heading = _yaw(pose.pose.orientation) - (yaw0 + _yaw(odometry.pose.pose.orientation))
            assert abs(math.remainder(heading, math.tau)) < 0.2
            # and on a free cell of the map the simulator publishes
            info = grid.info
            assert _yaw(info.origin.orientation) == pytest.approx(0.0)
            col = int((x - info.origin.position.x) / info.resolution)
            row = int((y - info.origin.position.y) / info.resolution)
            assert 0 <= col < info.width and 0 <= row < info.height
            assert grid.data[row * info.width + col] == 0
        finally:
            await client.close()

    asyncio.run(main())


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


CHROME_UA = ("Mozilla/5.0 (X11; Linux x86_64) AppleWebKit/537.36 (KHTML, like Gecko) Chrome/156.0.0.0 "
             "Safari/537.36")
ELECTRON_UA = ("Mozilla/5.0 (X11; Linux x86_64) AppleWebKit/537.36 (KHTML, like Gecko) Lichtblick/1.22.0 "
               "Chrome/134.0.6998.44 Electron/35.0.1 Safari/537.36")


async def _handshake(port: int, origin: str | None = None, user_agent: str | None = None) -> int:
    """The HTTP status a WebSocket upgrade gets (101 when the server's hello followed)."""
    try:
        ws = await connect(f"ws://127.0.0.1:{port}/", subprotocols=[SUBPROTOCOL], origin=origin,
                           user_agent_header=user_agent, max_size=None)
    except InvalidStatus as err:
        return err.response.status_code
    try:
        assert json.loads(await asyncio.wait_for(ws.recv(), 10))["op"] == "serverInfo"
    finally:
        await ws.close()
    return 101


def test_an_open_loopback_port_lets_viewers_in_but_not_pages_of_other_sites(sim):
    port = sim.port("foxglove")

    async def main() -> None:
        # not a browser; Foxglove's web app; a page served by this machine; a desktop app's own files
        assert await _handshake(port) == 101
        assert await _handshake(port, "https://app.foxglove.dev", CHROME_UA) == 101
        assert await _handshake(port, "http://localhost:5173", CHROME_UA) == 101
        assert await _handshake(port, "http://127.0.0.1:8080", CHROME_UA) == 101
        assert await _handshake(port, "null", ELECTRON_UA) == 101
        assert await _handshake(port, "file://", ELECTRON_UA) == 101
        # a page of another site, one that resolved its own name to 127.0.0.1 (DNS rebinding), and a
        # sandboxed frame of any site (Origin: null, with the browser's own User-Agent)
        log_from = len(sim.lines)
        assert await _handshake(port, "https://evil.example", CHROME_UA) == 403
        assert await _handshake(port, "http://evil.example:8765", CHROME_UA) == 403
        assert await _handshake(port, "null", CHROME_UA) == 403
        assert await _handshake(port, "chrome-extension://abcdef", CHROME_UA) == 403
        await asyncio.to_thread(sim.wait_for, r"foxglove: refused a browser page from 'https://evil.example'",
                                start=log_from)

    asyncio.run(main())


def test_the_sdk_server_behind_the_relay_talks_only_tls_with_a_certificate_nobody_trusts(sim):
    sim.port("foxglove")
    inner = int(sim.wait_for(r"foxglove: the SDK's server on wss://127\.0\.0\.1:(\d+), behind the "
                             r"relay").group(1))

    async def main() -> None:
        with pytest.raises((InvalidMessage, ConnectionError, EOFError)):  # plain ws: no HTTP answer
            await connect(f"ws://127.0.0.1:{inner}/", subprotocols=[SUBPROTOCOL], open_timeout=10)
        with pytest.raises(ssl.SSLCertVerificationError):  # wss, trusting what a browser trusts
            await connect(f"wss://127.0.0.1:{inner}/", subprotocols=[SUBPROTOCOL], open_timeout=10)

    asyncio.run(main())


_ATTACK_PAGE = """<!doctype html><title>another site</title><body><script>
window.result = {};
function probe(name, url) {
  const ws = new WebSocket(url, "foxglove.sdk.v1");
  ws.onopen = () => { window.result[name] = "open"; ws.close(); };
  ws.onerror = () => { window.result[name] = "refused"; };
}
probe("relay", "ws://127.0.0.1:RELAY/");
probe("sdk-ws", "ws://127.0.0.1:INNER/");
probe("sdk-wss", "wss://127.0.0.1:INNER/");
window.addEventListener("message", (e) => { window.result.sandboxed = e.data; });
const frame = document.createElement("iframe");
frame.sandbox = "allow-scripts";
frame.srcdoc = "<script>const ws = new WebSocket('ws://127.0.0.1:RELAY/', 'foxglove.sdk.v1');" +
  "ws.onopen = () => parent.postMessage('open', '*');" +
  "ws.onerror = () => parent.postMessage('refused', '*');" +
  "<" + "/script>";
document.body.appendChild(frame);
</script>"""


def test_a_page_of_another_site_in_a_real_browser_cannot_reach_the_car(sim):
    """Headless Chromium opens a page of ``evil.example`` (resolved to this machine): the page, its
    sandboxed frame and a try at the SDK's own port all fail; the same page served by this machine
    connects."""
    port = sim.port("foxglove")
    inner = int(sim.wait_for(r"foxglove: the SDK's server on wss://127\.0\.0\.1:(\d+), behind the "
                             r"relay").group(1))
    page = _ATTACK_PAGE.replace("RELAY", str(port)).replace("INNER", str(inner)).encode()

    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the http.server name
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    driver = chromium("--host-resolver-rules=MAP evil.example 127.0.0.1")
    try:
        def results(url: str) -> dict[str, str]:
            driver.get(url)
            deadline = time.monotonic() + 20
            while True:
                got = driver.execute_script("return window.result")
                if len(got) == 4:
                    return got
                assert time.monotonic() < deadline, got
                time.sleep(0.05)

        log_from = len(sim.lines)
        evil = f"http://evil.example:{server.server_port}"
        assert results(evil + "/") == {"relay": "refused", "sandboxed": "refused", "sdk-ws": "refused",
                                       "sdk-wss": "refused"}
        # the relay saw both and said no (the browser did not block them on its own)
        sim.wait_for(rf"foxglove: refused a browser page from '{re.escape(evil)}'", start=log_from)
        sim.wait_for(r"foxglove: refused a browser page from 'null'", start=log_from)
        # the same page served by this machine may connect (its sandboxed frame still may not)
        own = results(f"http://127.0.0.1:{server.server_port}/")
        assert own["relay"] == "open" and own["sandboxed"] == "refused" and own["sdk-ws"] == "refused"
    finally:
        driver.quit()
        server.shutdown()


def test_browser_origins_the_relay_admits():
    allowed = FoxgloveParams().allowed_origins
    assert browser_origin_allowed(None, None, allowed)
    assert browser_origin_allowed("https://APP.foxglove.dev/", CHROME_UA, allowed)
    assert browser_origin_allowed("http://[::1]:3000", CHROME_UA, allowed)
    assert browser_origin_allowed("null", ELECTRON_UA, allowed)
    for origin in ("https://evil.example", "http://127.0.0.1.evil.example", "http://localhost.evil.example",
                   "https://app.foxglove.dev.evil.example", "null", "file://", "moz-extension://abc"):
        assert not browser_origin_allowed(origin, CHROME_UA, allowed), origin
    assert not browser_origin_allowed("null", None, allowed)
    # listed origins, normalised; "null" may be listed on purpose
    mine = FoxgloveParams(allowed_origins=["https://Lichtblick.example.org/", "null"]).allowed_origins
    assert mine == ["https://lichtblick.example.org", "null"]
    assert browser_origin_allowed("https://lichtblick.example.org", CHROME_UA, tuple(mine))
    assert browser_origin_allowed("null", CHROME_UA, tuple(mine))
    from racecar_hw.base.errors import ConfigError

    for bad in ("lichtblick.example.org", "https://x.example/path", "https://x.example:99999", "*", ""):
        with pytest.raises(ConfigError, match=r"foxglove\.allowed_origins\[1\]"):
            FoxgloveParams(allowed_origins=["https://ok.example", bad])


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
