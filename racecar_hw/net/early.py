"""Outgoing rows a network interface takes from the control path instead of the bus.

The daemon names the scan: the control path hands it to each interface right after the scan's motor
write (:attr:`racecar_hw.control.path.ControlPath.early`), before its bookkeeping, the obstacle
memory and the bus's other subscribers, which a bus subscription made after theirs would wait for.
Each interface (the Zenoh bridge, the DDS interface) keeps one :class:`EarlyRows`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any


class EarlyRows:
    """The ``topics`` handed over early, and the enqueuers waiting for them."""

    def __init__(self, topics: Iterable[str] = ()) -> None:
        self.topics = frozenset(topics)
        self._enqueue: dict[str, list[Callable[[Any], None]]] = {}

    def take(self, topic: str, latched: bool, enqueue: Callable[[Any], None]) -> bool:
        """Keep ``enqueue`` for ``topic`` if it is early (a latched row never is); whether it was."""
        if topic not in self.topics or latched:
            return False
        self._enqueue.setdefault(topic, []).append(enqueue)
        return True

    def send(self, topic: str, msg: Any) -> None:
        """Queue ``msg`` of an early topic with every enqueuer kept for it (the event loop)."""
        for enqueue in self._enqueue.get(topic, ()):
            enqueue(msg)

    def clear(self) -> None:
        """Forget the enqueuers (the interface closes)."""
        self._enqueue = {}
