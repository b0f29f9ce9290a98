"""The daemon's log as ROS 2's ``/rosout``: ``rcl_interfaces/msg/Log`` on a bus topic.

Every ROS 2 node publishes its log records on ``/rosout``, where ``rqt_console``, ``ros2 topic echo
/rosout`` and log views read them. :class:`RosoutHandler` is a :class:`logging.Handler` on the root
logger that turns each record at or above ``rosout.level`` (WARNING by default) into a
:class:`~racecar_hw.base.messages.Log` and hands it to the bus's event loop; the topic table's
``/rosout`` row then carries it on every network interface, serialized in that interface's sender
thread, never in the caller's.

Cheap and never blocking, whatever thread logs: below the level the record never reaches the
handler (``logging``'s own level check); at or above it, the handler builds one small dataclass and
queues a call on the loop (``call_soon_threadsafe``). Records beyond ``rosout.max_rate_hz`` (a token
bucket, bursts up to one second's worth) are dropped and counted, so a log storm, or a feedback loop
through an interface that logs its own failures, cannot flood the loop or the network. Nothing
happens on the scan path unless something logs there at the level.

The Log fields: ``stamp`` the record's wall-clock time (sim time in lockstep), ``level``
Python's level number (ROS's DEBUG 10, INFO 20, WARN 30, ERROR 40, FATAL 50 are the same
numbers), ``name`` the node's logger name then the Python logger's (``racecar_hw.mux.node``;
with a namespace ``car1.racecar_hw....``, as rcl names a namespaced node's logger), ``msg`` the
formatted message, and where it was logged.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import is_virtual, monotonic, wall_ns
from racecar_hw.base.messages import Log, Time
from racecar_hw.base.params import param
from racecar_hw.net.topics import ROSOUT_TOPIC

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


@dataclass
class RosoutParams:
    """The daemon's log on ROS 2's /rosout (every network interface that carries the topic table)."""

    enabled: bool = param(True, "publish the daemon's log records as rcl_interfaces/msg/Log on /rosout")
    level: str = param("WARNING", "the lowest level published (records below it cost nothing)",
                       choices=LEVELS)
    max_rate_hz: float = param(20.0, "at most this many records a second (bursts of as many), the "
                                     "rest dropped and counted", unit="Hz", min=0.1, max=10000.0)


def logger_name(namespace: str, node_name: str) -> str:
    """The ROS logger name of a node: its namespace and name joined by dots (``car1.racecar_hw``)."""
    parts = [p for p in namespace.split("/") if p]
    return ".".join([*parts, node_name])


def to_log(record: logging.LogRecord, node_logger: str) -> Log:
    """One log record as ``rcl_interfaces/msg/Log``."""
    # the process's clock: in lockstep a record is stamped in sim time, as every message is
    ns = wall_ns() if is_virtual() else int(record.created * 1e9)
    text = record.getMessage()
    if record.exc_info and record.exc_info[1] is not None:
        text = f"{text}: {record.exc_info[1]!r}"
    return Log(stamp=Time.from_ns(ns), level=max(0, min(255, record.levelno)),
               name=f"{node_logger}.{record.name}" if record.name != "root" else node_logger,
               msg=text, file=record.pathname or "", function=record.funcName or "",
               line=max(0, min(2**32 - 1, record.lineno or 0)))


class RosoutHandler(logging.Handler):
    """Publishes log records on ``topic`` of ``bus`` from any thread, rate-limited, never blocking.

    Records logged before the bus has an event loop (``Bus.bind_loop``) or after it closed are dropped.
    """

    def __init__(self, bus: Bus, params: RosoutParams, node_logger: str, topic: str = ROSOUT_TOPIC) -> None:
        super().__init__(getattr(logging, params.level))
        self.bus = bus
        self.topic = topic
        self.node_logger = node_logger
        self.rate = params.max_rate_hz
        self.burst = max(1.0, params.max_rate_hz)
        self._tokens = self.burst
        self._refilled = monotonic()
        self._lock = threading.Lock()
        #: records published, and dropped (over the rate, or no loop to hand them to)
        self.published = 0
        self.dropped = 0

    def emit(self, record: logging.LogRecord) -> None:
        """Queue the record for the bus (never raises, never blocks beyond a short lock)."""
        try:
            with self._lock:
                now = monotonic()
                self._tokens = min(self.burst, self._tokens + (now - self._refilled) * self.rate)
                self._refilled = now
                if self._tokens < 1.0:
                    self.dropped += 1
                    return
                self._tokens -= 1.0
            loop = self.bus.loop
            if loop is None or loop.is_closed():
                self.dropped += 1
                return
            loop.call_soon_threadsafe(self.bus.publish, self.topic, to_log(record, self.node_logger))
            self.published += 1
        except Exception:  # noqa: BLE001 - a log handler must never raise into the code that logs
            self.dropped += 1

    def install(self, logger: logging.Logger | None = None) -> None:
        """Attach to ``logger`` (the root logger by default)."""
        (logger or logging.getLogger()).addHandler(self)

    def uninstall(self, logger: logging.Logger | None = None) -> None:
        """Detach (safe twice)."""
        (logger or logging.getLogger()).removeHandler(self)
