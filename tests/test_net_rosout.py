"""The daemon's log as /rosout (racecar_hw.net.rosout): records become rcl_interfaces/msg/Log on the
bus from any thread, at or above the level only, rate-limited, never raising into the caller; and
a bridge carries them to a Zenoh subscriber as CDR."""

from __future__ import annotations

import asyncio
import logging
import threading
import time

import zenoh
from conftest import async_wait_for
from zenoh_util import endpoint, free_port

from mux.params import MuxParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import Log
from racecar_hw.config import load_config, network_topics
from racecar_hw.net import rmw
from racecar_hw.net.rosout import RosoutHandler, RosoutParams, logger_name, to_log
from racecar_hw.net.topics import ROSOUT, ROSOUT_TOPIC, topic_table
from racecar_hw.net.zenoh_bridge import ZenohBridge
from racecar_hw.net.zenoh_config import ZenohParams, session_config
from racecar_hw.rosmsg.typestore import ros2_types
from safety.params import SafetyParams


def _record(level: int, msg: str = "x %d", name: str = "mux.node") -> logging.LogRecord:
    return logging.LogRecord(name, level, "/src/mux/node.py", 42, msg, (7,), None, func="step")


def test_a_record_becomes_an_rcl_interfaces_log():
    log = to_log(_record(logging.WARNING), logger_name("/car1", "racecar_hw"))
    assert log.level == Log.WARN == logging.WARNING
    assert log.name == "car1.racecar_hw.mux.node" and log.msg == "x 7"
    assert (log.file, log.function, log.line) == ("/src/mux/node.py", "step", 42)
    assert log.stamp.sec > 1_600_000_000
    assert logger_name("", "racecar_hw") == "racecar_hw"


def test_records_reach_the_bus_from_any_thread_at_or_above_the_level_only():
    async def run() -> list[Log]:
        bus = Bus()
        got: list[Log] = []
        bus.subscribe(ROSOUT_TOPIC, got.append)
        bus.bind_loop(asyncio.get_running_loop())
        logger = logging.getLogger("test_rosout.levels")
        logger.propagate = False
        logger.setLevel(logging.DEBUG)
        handler = RosoutHandler(bus, RosoutParams(level="WARNING"), "racecar_hw")
        handler.install(logger)
        try:
            logger.info("not this one")
            logger.warning("from the loop")
            thread = threading.Thread(target=lambda: logger.error("from a thread"))
            thread.start()
            thread.join()
            await async_wait_for(lambda: len(got) >= 2, timeout=20)
            await asyncio.sleep(0.05)
        finally:
            handler.uninstall(logger)
        logger.warning("after uninstall")
        await asyncio.sleep(0.05)
        return got

    got = asyncio.run(run())
    assert sorted(m.msg for m in got) == ["from a thread", "from the loop"]
    assert {m.level for m in got} == {Log.WARN, Log.ERROR}


def test_a_log_storm_is_cut_to_the_rate_and_nothing_raises_without_a_loop():
    bus = Bus()
    handler = RosoutHandler(bus, RosoutParams(max_rate_hz=5.0), "racecar_hw")
    handler.emit(_record(logging.WARNING))  # no loop bound yet: dropped, not raised
    assert handler.dropped == 1 and handler.published == 0

    async def run() -> tuple[int, float]:
        bus.bind_loop(asyncio.get_running_loop())
        got: list[Log] = []
        bus.subscribe(ROSOUT_TOPIC, got.append)
        start = time.monotonic()
        for _ in range(200):
            handler.emit(_record(logging.WARNING))
        took = time.monotonic() - start
        await asyncio.sleep(0.05)
        return len(got), took

    delivered, took = asyncio.run(run())
    # a burst of one second's worth (5, one spent by the dropped record), plus the refill meanwhile
    assert 4 <= delivered <= 5 + 5 * took + 1 and handler.published == delivered
    assert handler.dropped == 1 + 200 - delivered


def test_the_topic_table_has_rosout_outside_any_namespace_with_rcls_qos():
    rows = topic_table(MuxParams(), SafetyParams(), rosout=True)
    (row,) = [r for r in rows if r.bus == ROSOUT_TOPIC]
    assert row.msgtype is Log and row.qos == ROSOUT and row.absolute
    assert ROSOUT_TOPIC not in {r.bus for r in topic_table(MuxParams(), SafetyParams())}
    config = load_config(None, ["rosout.enabled=false"])
    assert ROSOUT_TOPIC not in {r.bus for r in network_topics(config)}
    assert ROSOUT_TOPIC in {r.bus for r in network_topics(load_config(None))}


def test_a_zenoh_subscriber_gets_the_log_as_cdr_on_the_absolute_rosout_key():
    """The bridge in a namespace: /rosout stays /rosout (as rcl's), its tokens name the node."""

    async def run() -> tuple[Log, list[str]]:
        bus = Bus()
        port = free_port()
        rows = topic_table(MuxParams(), SafetyParams(), rosout=True)
        bridge = ZenohBridge(bus, ZenohParams(listen=[endpoint(port)], namespace="/car1"), rows)
        loop = asyncio.get_running_loop()
        bus.bind_loop(loop)
        await loop.run_in_executor(None, bridge.open, loop)
        peer = zenoh.open(session_config("client", [], [endpoint(port)]))
        got: list[bytes] = []
        logger = logging.getLogger("test_rosout.zenoh")
        logger.propagate = False
        handler = RosoutHandler(bus, RosoutParams(), logger_name("/car1", "racecar_hw"))
        handler.install(logger)
        try:
            key = rmw.topic_key(0, "/rosout", Log.ROS_TYPE, rmw.type_hash(Log.ROS_TYPE))
            sub = peer.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
            logger.warning("mux input nav_0 timed out")
            await async_wait_for(lambda: got, timeout=30)
            tokens = [str(r.ok.key_expr) for r in peer.liveliness().get(rmw.liveliness_pattern(0), timeout=5)
                      if r.ok is not None]
            sub.undeclare()
        finally:
            handler.uninstall(logger)
            peer.close()
            await loop.run_in_executor(None, bridge.close)
        return ros2_types().deserialize(got[0], Log), tokens

    log, tokens = asyncio.run(run())
    assert log.msg == "mux input nav_0 timed out" and log.name == "car1.racecar_hw.test_rosout.zenoh"
    (token,) = [t for t in tokens if "%rosout" in t]
    entity = rmw.parse_token(token)
    assert (entity.kind, entity.node, entity.topic) == (rmw.PUBLISHER, "/car1/racecar_hw", "/rosout")
    assert entity.qos.durability == rmw.TRANSIENT_LOCAL and entity.qos.depth == 1000
