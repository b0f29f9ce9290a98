"""The in-process bus: delivery, latest-value cache, type checks, failing subscribers."""

from __future__ import annotations

import asyncio
import threading

import pytest

from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import TopicTypeError
from racecar_hw.base.messages import AckermannDriveStamped, Bool, String


def test_publish_delivers_in_order_and_caches_latest():
    bus = Bus()
    got: list[bool] = []
    bus.subscribe("/lock", lambda m: got.append(m.data))
    assert bus.latest("/lock") is None
    bus.publish("/lock", Bool(True))
    bus.publish("/lock", Bool(False))
    assert got == [True, False]
    assert bus.latest("/lock") == Bool(False)
    entry = bus.latest_entry("/lock")
    assert entry is not None and entry.received_ns > 0
    assert bus.topics() == {"/lock": Bool}


def test_wrong_type_is_refused_and_declare_fixes_type():
    bus = Bus()
    bus.publish("/a", Bool(True))
    with pytest.raises(TopicTypeError, match="/a carries std_msgs/msg/Bool"):
        bus.publish("/a", String("x"))
    bus.declare("/cmd", AckermannDriveStamped)
    with pytest.raises(TopicTypeError):
        bus.publish("/cmd", Bool(True))
    with pytest.raises(TopicTypeError):
        bus.declare("/cmd", Bool)


def test_failing_subscriber_does_not_stop_others():
    bus = Bus()
    got = []

    def bad(msg):
        raise RuntimeError("boom")

    bus.subscribe("/t", bad)
    bus.subscribe("/t", got.append)
    every = []
    bus.subscribe_all(lambda topic, msg: every.append(topic))
    bus.publish("/t", String("hi"))
    assert got == [String("hi")]
    assert every == ["/t"]
    assert bus.callback_errors == 1


def test_unsubscribe_is_idempotent():
    bus = Bus()
    got = []
    sub = bus.subscribe("/t", got.append)
    every = bus.subscribe_all(lambda t, m: got.append(t))
    sub.close()
    sub.close()
    every.close()
    bus.publish("/t", String("x"))
    assert got == []


def test_publish_threadsafe_delivers_in_loop_thread():
    async def scenario() -> None:
        bus = Bus()
        bus.bind_loop(asyncio.get_running_loop())
        seen: list[str] = []
        done = asyncio.Event()

        def on_msg(msg):
            seen.append(threading.current_thread().name)
            done.set()

        bus.subscribe("/t", on_msg)
        threading.Thread(target=bus.publish_threadsafe, args=("/t", String("x")), name="other").start()
        await asyncio.wait_for(done.wait(), 5)
        assert seen == [threading.current_thread().name]

    asyncio.run(scenario())


def test_publish_threadsafe_needs_a_loop():
    with pytest.raises(RuntimeError):
        Bus().publish_threadsafe("/t", String("x"))
