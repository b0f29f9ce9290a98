"""An in-process publish/subscribe bus with ROS topic names and a latest-value cache.

The bus belongs to the daemon's event loop thread: publish and subscribe from that thread only.
Callbacks run synchronously inside :meth:`Bus.publish`, in subscription order; a callback that
raises is logged and counted, and never stops delivery to the others or the publisher.
Code in another thread hands messages over with :meth:`Bus.publish_threadsafe`.

Each topic carries one message type, fixed by its first publisher (or by :meth:`Bus.declare`).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from racecar_hw.base.clock import monotonic_ns
from racecar_hw.base.errors import ConfigError, TopicTypeError
from racecar_hw.base.messages import Message

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)
Callback = Callable[[Any], None]
AnyCallback = Callable[[str, Any], None]


@dataclass
class Latest(Generic[M]):
    """The last message on a topic and when it arrived (monotonic ns)."""

    msg: M
    received_ns: int


class Subscription:
    """A handle returned by :meth:`Bus.subscribe`; :meth:`close` stops delivery (safe twice)."""

    def __init__(self, bus: Bus, topic: str | None, callback: Callable[..., None]) -> None:
        self._bus = bus
        self.topic = topic
        self.callback = callback

    def close(self) -> None:
        """Stop delivering messages to the callback."""
        self._bus._unsubscribe(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Bus:
    """Topics by name, each with subscribers and the latest message."""

    def __init__(self) -> None:
        self._subs: dict[str, list[Subscription]] = {}
        self._all: list[Subscription] = []
        self._latest: dict[str, Latest[Any]] = {}
        self._types: dict[str, type[Message]] = {}
        self.callback_errors = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        #: for a daemon built from a config: a topic -> (the key to name, every key set to it), so
        #: that two components declaring one topic with two types is a ConfigError naming the key
        self.config_keys: Callable[[str], tuple[str, list[str]] | None] | None = None

    def declare(self, topic: str, msgtype: type[Message]) -> None:
        """Fix the type of ``topic`` before anything is published on it."""
        known = self._types.setdefault(topic, msgtype)
        if known is not msgtype:
            clash = f"{topic} carries {known.ROS_TYPE}, not {msgtype.ROS_TYPE}"
            keys = self.config_keys(topic) if self.config_keys is not None else None
            if keys is not None:
                raise ConfigError(keys[0], f"{clash}: two things of different types cannot share a "
                                           f"topic (keys set to {topic}: {', '.join(keys[1])})")
            raise TopicTypeError(clash)

    def publish(self, topic: str, msg: Message) -> None:
        """Deliver ``msg`` to every subscriber of ``topic`` and remember it as the latest."""
        known = self._types.get(topic)
        if known is None:
            self._types[topic] = type(msg)
        elif type(msg) is not known:
            raise TopicTypeError(f"{topic} carries {known.ROS_TYPE}, not {type(msg).ROS_TYPE}")
        self._latest[topic] = Latest(msg, monotonic_ns())
        # the calls inline: a scan passes through here on its way to the motor command
        for sub in self._subs.get(topic, ()):
            try:
                sub.callback(msg)
            except Exception:
                self._failed(f"subscriber of {topic}")
        for sub in self._all:
            try:
                sub.callback(topic, msg)
            except Exception:
                self._failed(f"subscriber of every topic, on {topic}")

    def bind_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        """Name the event loop that owns this bus, for :meth:`publish_threadsafe`."""
        self._loop = loop

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        """The event loop that owns this bus (None before :meth:`bind_loop`)."""
        return self._loop

    def publish_threadsafe(self, topic: str, msg: Message) -> None:
        """Publish from another thread: the message is delivered in the bus's loop."""
        if self._loop is None:
            raise RuntimeError("bus has no event loop: call bind_loop() first")
        self._loop.call_soon_threadsafe(self.publish, topic, msg)

    def subscribe(self, topic: str, callback: Callback) -> Subscription:
        """Call ``callback(msg)`` for every message published on ``topic``."""
        sub = Subscription(self, topic, callback)
        self._subs.setdefault(topic, []).append(sub)
        return sub

    def subscribe_all(self, callback: AnyCallback) -> Subscription:
        """Call ``callback(topic, msg)`` for every message on every topic (recorders)."""
        sub = Subscription(self, None, callback)
        self._all.append(sub)
        return sub

    def latest(self, topic: str) -> Any | None:
        """The last message published on ``topic``, or None."""
        entry = self._latest.get(topic)
        return entry.msg if entry else None

    def latest_entry(self, topic: str) -> Latest[Any] | None:
        """The last message on ``topic`` with its arrival time, or None."""
        return self._latest.get(topic)

    def topics(self) -> dict[str, type[Message]]:
        """Every topic seen so far and its message type."""
        return dict(self._types)

    def _unsubscribe(self, sub: Subscription) -> None:
        bucket = self._all if sub.topic is None else self._subs.get(sub.topic, [])
        if sub in bucket:
            bucket.remove(sub)

    def _failed(self, who: str) -> None:
        """Count and log the exception being handled, raised by the subscriber ``who``."""
        self.callback_errors += 1
        log.exception("%s failed", who)
