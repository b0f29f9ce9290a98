"""The Foxglove server's hostile edges: Trigger services against a busy event loop (what the caller
is told is what happens), and channels a client advertises that the car does not take.

A real Foxglove SDK server with :class:`TriggerServices` on a free port and a raw WebSocket client
(the SDK's binary service-call frame); the daemon's event loop runs in a thread and is held busy
for longer than the services' timeout. The car's control is a recorder of the calls: what is under
test is the handler's contract with the loop, not the car.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import struct
import threading
import time

import foxglove
from websockets.asyncio.client import connect

from racecar_hw.net.foxglove_services import SERVICE_TIMEOUT_S, TriggerServices


class Calls:
    """Which actions ran, and when (monotonic s)."""

    def __init__(self) -> None:
        self.ran: list[tuple[str, float]] = []

    def _note(self, name: str) -> tuple[bool, str]:
        self.ran.append((name, time.monotonic()))
        return True, name

    def engage_estop(self, origin: object) -> str:
        self._note("estop")
        return "latched"

    def release_estop(self, origin: object) -> tuple[bool, str]:
        return self._note("release")

    def arm(self, who: str) -> tuple[bool, str]:
        return self._note("arm")

    def disarm(self, who: str) -> tuple[bool, str]:
        return self._note("disarm")


def test_a_call_the_busy_daemon_could_not_run_in_time_fails_and_never_runs_later():
    """The loop busy for longer than the timeout: /racecar/arm is answered as failed ("not done"),
    and arming does not happen once the loop is free again (it used to, a second later: a release
    of the e-stop reported as failed would still have released it). A call made once the loop is
    free runs as usual."""
    calls = Calls()
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    ctx = foxglove.Context()
    server = foxglove.start_server(host="127.0.0.1", port=0, context=ctx,
                                   capabilities=[foxglove.Capability.Services],
                                   services=TriggerServices(calls, loop).services())

    async def call(ws, service_id: int, call_id: int) -> dict:
        await ws.send(struct.pack("<BIII", 2, service_id, call_id, 3) + b"cdr" + b"\x00\x01\x00\x00\x00")
        while True:
            reply = await asyncio.wait_for(ws.recv(), 30)
            if isinstance(reply, str):
                message = json.loads(reply)
                if message.get("op") == "serviceCallFailure":
                    return message
            else:
                return {"op": "serviceCallResponse"}

    async def main() -> tuple[dict, dict]:
        async with connect(f"ws://127.0.0.1:{server.port}/", subprotocols=["foxglove.sdk.v1"]) as ws:
            ids: dict[str, int] = {}
            while "/racecar/arm" not in ids:
                message = json.loads(await asyncio.wait_for(ws.recv(), 30))
                if message["op"] == "advertiseServices":
                    ids.update({s["name"]: s["id"] for s in message["services"]})
            loop.call_soon_threadsafe(time.sleep, SERVICE_TIMEOUT_S + 1.5)  # the daemon held up
            failed = await call(ws, ids["/racecar/arm"], 1)
            free = concurrent.futures.Future()
            loop.call_soon_threadsafe(free.set_result, time.monotonic)
            await asyncio.wrap_future(free)  # the loop has run everything queued before it
            later = await call(ws, ids["/racecar/disarm"], 2)
            return failed, later

    try:
        failed, later = asyncio.run(main())
    finally:
        server.stop()
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
    assert failed["op"] == "serviceCallFailure" and "not done: the daemon was busy" in failed["message"]
    assert [name for name, _ in calls.ran] == ["disarm"], calls.ran
    assert later["op"] == "serviceCallResponse"


def test_channels_a_client_advertises_cannot_flood_or_forge_the_log(caplog):
    """2,000 channels the car does not take, with a line break and a forged log line in a topic
    and a 10,000-character schema name: a few quoted lines, none of them spanning two."""
    from types import SimpleNamespace

    from racecar_hw.base.bus import Bus
    from racecar_hw.net.foxglove_teleop import LOGGED_CHANNELS, TwistTeleop

    teleop = TwistTeleop(Bus(), "/teleop_twist", "foxglove", wheelbase_m=0.25, max_speed_mps=1.0,
                         max_steering_rad=0.3)
    forged = "/x\n2026-11-27 19:50:00,000 CRITICAL racecar_hw.daemon: e-stop released by operator"
    with caplog.at_level("INFO", logger="racecar_hw.net.foxglove_teleop"):
        for i in range(1000):
            other = SimpleNamespace(id=i, topic=forged, schema_name="x" * 10_000, encoding="cdr")
            wrong = SimpleNamespace(id=1000 + i, topic="/teleop_twist", schema_name="y" * 10_000,
                                    encoding="cdr")
            teleop.advertised(1, other)
            teleop.advertised(1, wrong)
    lines = [r.getMessage() for r in caplog.records]
    assert teleop.ignored_channels == 2000
    assert len(lines) == LOGGED_CHANNELS + 2000 // 100  # the first ten, then every hundredth
    assert all("\n" not in line and len(line) < 400 for line in lines), lines[:3]
    assert "(2000 channels not taken so far)" in lines[-1]


def test_a_client_cannot_multiply_its_twist_rate_with_more_channels():
    """200 Teleop channels of one client, a Twist on each at one instant (virtual time: the same
    instant however loaded the machine is): one is taken, 199 refused. Per channel, all 200 were
    taken (40,000 a second from one client in a review, the car driving on for seconds after)."""
    from types import SimpleNamespace

    from racecar_hw.base.bus import Bus
    from racecar_hw.net.foxglove_teleop import TwistTeleop
    from racecar_hw.runtime import lockstep

    async def scenario() -> tuple[int, int]:
        teleop = TwistTeleop(Bus(), "/teleop_twist", "foxglove", wheelbase_m=0.25, max_speed_mps=1.0,
                             max_steering_rad=0.3)
        teleop.loop = asyncio.get_running_loop()
        for i in range(200):
            teleop.advertised(7, SimpleNamespace(id=i, topic="/teleop_twist",
                                                 schema_name="geometry_msgs/msg/Twist", encoding="json"))
        for i in range(200):
            teleop.message(7, i, b'{"linear": {"x": 0.5}, "angular": {"z": 0.0}}')
        return teleop.twists, teleop.refused

    assert lockstep.run(scenario()) == (1, 199)
