"""What the Zenoh bridge and the DDS interface share: one table, two wires.

Both take the same outgoing rows (:mod:`racecar_hw.net.topics`) off the bus the same way: a bus
callback queues ``(row, message, wall ns)`` in an :class:`~racecar_hw.runtime.outbox.Outbox`
(bounded, drop-oldest) only while somebody listens, the scan comes from the control path right
after its motor write (:class:`~racecar_hw.net.early.EarlyRows`), latched rows are queued at once
with the bus's latest message, and the publisher thread serializes and writes. Their own inboxes
(when the daemon gives none) hand over alike: on the bus, then ``on_input``. Only the write itself
and being open differ: :meth:`Bridge._write` and :attr:`Bridge.is_open`.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from typing import Any, ClassVar, Protocol

from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.messages import Message
from racecar_hw.net.early import EarlyRows
from racecar_hw.net.topics import Topic
from racecar_hw.runtime.outbox import Outbox

log = logging.getLogger(__name__)


class OutRow(Protocol):
    """One outgoing row of a bridge: its table row, whether it is latched, whether anyone listens."""

    row: Topic
    latched: bool
    matching: bool


class Bridge(ABC):
    """The outgoing side and the own inbox's hand-over of a network bridge.

    A subclass sets ``bus``, ``namespace``, ``on_input`` and ``stats`` (counting ``published``,
    ``skipped`` and ``publish_errors``), calls :meth:`_init_outgoing` in its constructor,
    :meth:`_take_rows` once its thread may run, :meth:`_stop_outgoing` when it closes, and defines
    :meth:`_write` and :attr:`is_open`.
    """

    #: the wire's name in log lines
    WIRE: ClassVar[str]
    bus: Bus
    namespace: str
    on_input: Callable[[str], None] | None
    stats: Any

    def _init_outgoing(self, thread: str, queue_size: int, urgent: Iterable[str],
                       early: Iterable[str]) -> None:
        """The publisher thread's queue (``queue_size`` jobs; not niced: remote navigation code waits
        for the scan it sends), the ``early`` rows, and the ``urgent`` ones (with the early ones)
        that wake the thread at once."""
        self.early = EarlyRows(early)
        self.urgent = frozenset(urgent) | self.early.topics
        self.outbox = Outbox(thread, queue_size, nice=0)
        self._bus_subs: list[Subscription] = []

    @property
    @abstractmethod
    def is_open(self) -> bool:
        """Whether the wire is up (the own inbox hands over only then)."""

    def ros_name(self, row: Topic) -> str:
        """The topic's full ROS name: the namespace (unless the row is absolute), then the row's ROS name."""
        return row.ros if row.absolute else self.namespace + row.ros

    # --- out: bus thread, then the publisher thread -------------------------------------------

    @property
    def dropped(self) -> int:
        """Outgoing messages dropped because the queue was full (the oldest go first)."""
        return self.outbox.dropped

    def control_idle(self) -> None:
        """The control path is idle until its next event (a scan's command is out): send now."""
        self.outbox.control_idle()

    def send_early(self, topic: str, msg: Message) -> None:
        """Queue ``msg`` of an ``early`` topic now (the event loop, after the scan's motor write)."""
        self.early.send(topic, msg)

    def _take_rows(self, outs: Iterable[OutRow]) -> None:
        """Start the publisher thread and take each row from the bus (or early); a latched row's
        latest message is queued at once."""
        self.outbox.start()
        for out in outs:
            enqueue = self._enqueuer(out)
            if not self.early.take(out.row.bus, out.latched, enqueue):
                self._bus_subs.append(self.bus.subscribe(out.row.bus, enqueue))
            latest = self.bus.latest(out.row.bus)
            if out.latched and latest is not None:
                enqueue(latest)

    def _stop_outgoing(self) -> None:
        """Forget the early rows, leave the bus, run what is queued and stop the thread (safe twice)."""
        self.early.clear()
        for sub in self._bus_subs:
            sub.close()
        self._bus_subs.clear()
        self.outbox.stop(5.0)

    def _enqueuer(self, out: OutRow) -> Callable[[Message], None]:
        return self.outbox.enqueuer(self._publish, out, self.stats, urgent=out.row.bus in self.urgent)

    def _publish(self, out: OutRow, msg: Message, stamp: int) -> None:
        """In the publisher thread: :meth:`_write` it; a failure is counted and logged now and then."""
        try:
            self._write(out, msg, stamp)
            self.stats.published += 1
        except Exception as err:  # noqa: BLE001 - one bad message never stops the thread
            self.stats.publish_errors += 1
            if self.stats.publish_errors in (1, 10, 100) or self.stats.publish_errors % 1000 == 0:
                log.warning("%s: could not publish %s (%d so far): %r", self.WIRE, out.row.ros,
                            self.stats.publish_errors, err)

    @abstractmethod
    def _write(self, out: Any, msg: Message, stamp: int) -> None:
        """In the publisher thread: serialize ``msg`` and send it on ``out`` with its source
        timestamp ``stamp`` (wall ns)."""

    # --- in: the own inbox's hand-over, in the event loop ------------------------------------

    def _deliver(self, topic: str, msg: Message, origin: str) -> None:
        """The own inbox's hand-over, in the event loop: on the bus, then ``on_input``."""
        if not self.is_open:
            return
        self.bus.publish(topic, msg)
        if self.on_input is not None:
            self.on_input(topic)


__all__ = ["Bridge", "OutRow"]
