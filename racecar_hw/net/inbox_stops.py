"""The inbox's e-stop FIFO: e-stop and release messages in their order, never coalesced away.

A message that engages the e-stop (``data`` true on the e-stop topic) is due at once; the FIFO
is otherwise handed over at most once per period (ns, monotonic). Only what cannot engage is ever
dropped: a release or a ``false`` replaced by a newer one on the same topic, or the oldest of them
when the FIFO holds :data:`MAX_STOPS`; a repeated engaging message right behind an identical one
from the same surface is merged into it. Dropping those can only keep the car stopped, never let
it go. Not thread-safe: the :class:`~racecar_hw.net.inbox.Inbox` calls it under its lock.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from racecar_hw.base.messages import Message

#: The most e-stop messages waiting at once; beyond it the oldest that cannot engage goes.
MAX_STOPS = 32

#: (topic, message, origin) of one waiting e-stop message.
Stop = tuple[str, Message, str]


class StopQueue:
    """E-stop messages for ``estop_topic`` and its release, handed over at most every ``period_ns``.

    ``superseded(topic)`` is told of each message merged or dropped, by its topic.
    """

    def __init__(self, estop_topic: str | None, period_ns: int, superseded: Callable[[str], None]) -> None:
        self.estop_topic = estop_topic
        self.period_ns = period_ns
        self._superseded = superseded
        self._stops: deque[Stop] = deque()
        self._engage = False  #: an engaging message waits: hand over at once
        self.next_ns = 0      #: when the FIFO may be handed over next (unless one engages)

    def __bool__(self) -> bool:
        return bool(self._stops)

    def engages(self, topic: str, msg: Message) -> bool:
        """Whether ``msg`` on ``topic`` engages the e-stop."""
        return topic == self.estop_topic and bool(getattr(msg, "data", False))

    def queue(self, topic: str, msg: Message, origin: str, now: int,
              timer_ns: int | None) -> tuple[bool, bool]:
        """Queue a message at ``now``, a loop timer being due at ``timer_ns`` (None: none):
        (wake the loop now?, was a message dropped or merged?)."""
        stops = self._stops
        if self.engages(topic, msg):
            # merged into an e-stop from the same surface already waiting with only e-stops
            # behind it: handing over both would engage twice in a row, nothing in between
            for t, m, o in reversed(stops):
                if not self.engages(t, m):
                    break
                if o == origin:
                    self._superseded(topic)
                    return True, True
            stops.append((topic, msg, origin))
            self._engage = True
            return True, False
        dropped = False
        if stops and stops[-1][0] == topic and not self.engages(*stops[-1][:2]):
            stops.pop()  # a release or a false replaced by a newer one on its topic
            dropped = True
        elif len(stops) >= MAX_STOPS:
            victim = next((i for i, (t, m, _) in enumerate(stops) if not self.engages(t, m)), None)
            if victim is not None:
                self._superseded(stops[victim][0])
                del stops[victim]
        if dropped:
            self._superseded(topic)
        stops.append((topic, msg, origin))
        due = self._engage or now >= self.next_ns
        return due or timer_ns is None or timer_ns > self.next_ns, dropped

    def take(self, now: int) -> list[Stop]:
        """Everything waiting, in order, when due at ``now`` (the next hand-over a period later);
        nothing otherwise."""
        if not (self._stops and (self._engage or now >= self.next_ns)):
            return []
        stops = list(self._stops)
        self._stops.clear()
        self._engage = False
        self.next_ns = now + self.period_ns
        return stops


__all__ = ["MAX_STOPS", "Stop", "StopQueue"]
