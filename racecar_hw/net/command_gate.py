"""At most one command per control period per input, the newest, offered from the thread it came in.

A network interface's receiving thread (Zenoh's, which calls a direct callback per sample) passes
every sample of a command row to :meth:`CommandGate.arrive`. A sample that comes a period or more
after the row's last offer is offered at once, in that thread: a client answering every scan
(40 Hz against a 50 Hz control period) costs no thread wake-up of ours. One that comes sooner is
kept as the row's pending sample, replacing any older pending one, and the gate's one thread (for
every row) offers the newest when the period is over. So a flood costs one offer per period and
per row, and a kept reference per sample; nothing is decoded until it is offered.

Offers of one row never overlap and keep their order: each row has a lock held around its offer.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from racecar_hw.runtime.threadname import name_this_thread

Offer = Callable[[Any], None]


class _Row:
    """One command row: when it was last offered (monotonic s), its pending sample, its offer lock."""

    __slots__ = ("offer", "last", "pending", "offering")

    def __init__(self, offer: Offer) -> None:
        self.offer = offer
        self.last = -float("inf")
        self.pending: Any = None
        self.offering = threading.Lock()


class CommandGate:
    """Rate gate for the command rows of one interface; ``period_s`` is the control period (s)."""

    def __init__(self, name: str, period_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.period_s = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self._deferred: list[_Row] = []
        self._wake = threading.Condition(self._lock)
        self._stopping = False
        self._thread: threading.Thread | None = None
        #: offers made by the gate's thread (samples that came within a period of the last)
        self.deferred_offers = 0

    def row(self, offer: Offer) -> Callable[[Any], None]:
        """A new row whose samples go to ``offer`` (one at a time); returns its ``arrive``."""
        row = _Row(offer)
        return lambda sample: self.arrive(row, sample)

    def arrive(self, row: _Row, sample: Any) -> None:
        """A sample of ``row`` came (in the receiving thread): offer it now, or keep it for later."""
        with self._lock:
            if row.pending is not None:  # already waiting for its period: the newest goes then
                row.pending = sample
                return
            now = self._clock()
            if now - row.last < self.period_s:
                row.pending = sample
                self._deferred.append(row)
                self._wake.notify()
                return
            row.last = now
        with row.offering:
            row.offer(sample)

    def start(self) -> None:
        """Start the thread that offers deferred samples (idempotent)."""
        if self._thread is None:
            self._stopping = False
            self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread; pending samples are dropped (safe to call twice)."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        with self._lock:
            self._stopping = True
            self._wake.notify()
        thread.join(timeout_s)

    def _run(self) -> None:
        name_this_thread(self.name)
        while True:
            with self._lock:
                while not self._stopping:
                    if not self._deferred:
                        self._wake.wait()  # no timer: an idle gate costs no wake-ups
                        continue
                    row = min(self._deferred, key=lambda r: r.last)
                    left = row.last + self.period_s - self._clock()
                    if left <= 0.0:
                        break
                    self._wake.wait(left)
                if self._stopping:
                    return
                self._deferred.remove(row)
                sample, row.pending = row.pending, None
                row.last = self._clock()
                self.deferred_offers += 1
            with row.offering:
                row.offer(sample)
