"""A bounded drop-oldest queue of work for a network sender thread, off the control path.

Bus callbacks run in the daemon's event-loop thread, on the way from a scan to its motor command.
For a remote client they only :meth:`Outbox.put` a small job (a function and its arguments, typically
"serialize this message and send it"); a thread of its own runs the jobs. When the queue is full the
oldest job is dropped and counted: a slow or stalled client loses old data, never delays a command.

The thread is not woken per job: it runs what is queued every :data:`BATCH_S`, at once when
:data:`WAKE_AT` jobs wait, or when the control path says it is idle (:meth:`Outbox.control_idle`,
called by the daemon once a scan's command is out), so its work lands in the gap before the next scan.
A job queued with ``urgent=True`` wakes it at once: for a message queued in that gap whose
latency matters (the scan itself, queued after its motor command, for remote navigation code).
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from racecar_hw.base.clock import wall_ns

log = logging.getLogger(__name__)

#: The sender thread runs the queue at least this often (seconds).
BATCH_S = 0.02
#: ... or as soon as this many jobs wait.
WAKE_AT = 16
#: The sender thread's niceness relative to the daemon (Linux: per thread).
SENDER_NICE = 5

Job = tuple[Callable[..., None], tuple[Any, ...]]


class Outbox:
    """Jobs for one sender thread; :meth:`put` from any thread, never blocks."""

    def __init__(self, name: str, size: int = 1000, nice: int = SENDER_NICE) -> None:
        """``nice``: the sender thread's niceness relative to the daemon (0: the same priority)."""
        if size < 1:
            raise ValueError(f"size must be at least 1, got {size}")
        self.name = name
        self.size = size
        self.nice = nice
        self._queue: collections.deque[Job] = collections.deque(maxlen=size)
        self._wake = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._drain_due = 0.0
        #: jobs dropped because the queue was full (the oldest go first)
        self.dropped = 0
        #: jobs run, and jobs that raised
        self.done = 0
        self.failed = 0

    def start(self) -> None:
        """Start the sender thread (idempotent)."""
        if self._thread is not None:
            return
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Run what is queued, then stop the thread; safe to call twice."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stopping = True
        self._wake.set()
        thread.join(timeout_s)
        if thread.is_alive():
            log.warning("%s: sender thread still busy after %.1f s; left behind", self.name, timeout_s)

    def put(self, fn: Callable[..., None], *args: Any, urgent: bool = False) -> None:
        """Queue ``fn(*args)`` for the sender thread; when full, the oldest job is dropped.

        ``urgent``: wake the thread now rather than at the next batch.
        """
        queue = self._queue
        if len(queue) == self.size:
            self.dropped += 1
        queue.append((fn, args))
        if (urgent or len(queue) >= WAKE_AT) and not self._wake.is_set():
            self._wake.set()

    def enqueuer(self, publish: Callable[[Any, Any, int], None], out: Any, stats: Any,
                 urgent: bool = False) -> Callable[[Any], None]:
        """A bus callback for one outgoing row of a network bridge: queue ``publish(out, msg, wall
        ns)``, or, while nobody subscribes (``out.matching`` false), count ``stats.skipped`` and
        serialize nothing."""
        put = self.put

        def enqueue(msg: Any) -> None:
            if not out.matching:
                stats.skipped += 1
                return
            put(publish, out, msg, wall_ns(), urgent=urgent)

        return enqueue

    def __len__(self) -> int:
        return len(self._queue)

    def control_idle(self) -> None:
        """The control path is idle until its next event: run the queue now if a run is due."""
        if self._queue and time.monotonic() >= self._drain_due and not self._wake.is_set():
            self._wake.set()

    def _run(self) -> None:
        if self.nice:
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                               os.getpriority(os.PRIO_PROCESS, 0) + self.nice)
            except (AttributeError, OSError):
                pass
        queue = self._queue
        while True:
            self._drain_due = time.monotonic() + BATCH_S
            self._wake.wait(2 * BATCH_S)
            self._wake.clear()
            stopping = self._stopping
            while queue:
                try:
                    fn, args = queue.popleft()
                except IndexError:
                    break
                try:
                    fn(*args)
                    self.done += 1
                except Exception:
                    self.failed += 1
                    if self.failed == 1 or self.failed % 1000 == 0:
                        log.exception("%s: sending failed (%d so far)", self.name, self.failed)
            if stopping:
                return
