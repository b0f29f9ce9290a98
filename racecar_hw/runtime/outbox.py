"""A bounded queue of work for a thread of its own, off the control path: the one sender/writer
thread of the network publishers (Foxglove, Zenoh, DDS) and of the bag recorder.

Bus callbacks run in the daemon's event-loop thread, on the way from a scan to its motor command.
For work that may take long (serialize and send a message to a remote client, serialize and write
it into a bag) they only :meth:`Outbox.put` a small job (a function and its arguments); a thread
of its own runs the jobs. When the queue is full a job is dropped and counted (:attr:`Outbox.dropped`):
the oldest (``drop="oldest"``: a network client wants the latest data) or the new one
(``drop="newest"``: a bag keeps what it has queued). Never by blocking the control path.

Idle behaviour. The thread is not woken per job: it runs what is queued every ``batch_s``
(:data:`BATCH_S`), at once when ``wake_at`` (:data:`WAKE_AT`) jobs wait, or when the control path
says it is idle (:meth:`Outbox.control_idle`, called by the daemon once a scan's command is out, or
a remote answer's while remote navigation code answers scans), so its work lands in the gap before
the next scan; on its own it waits at most ``2 * batch_s``.
A job queued with ``urgent=True`` wakes it at once: for a message queued in that gap whose
latency matters (the scan itself, queued after its motor command, for remote navigation code).
With nothing queued (and no ``on_batch``) the thread sleeps until a job comes, not waking on a
timer (a network interface nobody listens to costs no wake-ups); the first job into the empty
queue wakes it, and unless it is urgent the thread then waits up to ``batch_s`` for more.

Hooks for a writer that owns a resource in its thread (the recorder's bag: sqlite3 connections
belong to the thread that made them): ``start(setup)`` runs ``setup`` in the thread first and
re-raises what it raises; ``on_batch`` runs when the thread starts and after every batch, and
says in how many seconds it wants to run again (a periodic flush: the thread wakes for it);
``on_stop`` runs last, after :meth:`Outbox.stop` has run everything queued.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from racecar_hw.base.clock import wall_ns
from racecar_hw.runtime.threadname import name_this_thread

log = logging.getLogger(__name__)

#: The thread runs the queue at least this often (seconds), unless told otherwise.
BATCH_S = 0.02
#: ... or as soon as this many jobs wait.
WAKE_AT = 16
#: The sender thread's niceness relative to the daemon (Linux: per thread).
SENDER_NICE = 5
#: What goes when the queue is full.
DROP_POLICIES = ("oldest", "newest")

Job = tuple[Callable[..., None], tuple[Any, ...]]


def lower_thread_priority(nice: int) -> None:
    """Make the calling thread nicer by ``nice`` where the OS has per-thread priorities (Linux).

    Disk and network work then yields the CPU to the control path whenever both want it; lowering
    one's own priority needs no privilege.
    """
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)
    except (AttributeError, OSError):
        log.debug("cannot lower a thread's priority on this system")


class _Wake:
    """A wake-up flag for one waiting thread: :meth:`set` from any thread, :meth:`wait` in the thread.

    A bare lock held while nobody asked for a wake-up, released by :meth:`set`: waking the thread
    is one futex call and it wakes once, where :class:`threading.Event` goes through a
    :class:`threading.Condition` whose lock the woken thread must take again (the setter, which
    holds the GIL, often still has it), so a wake-up through an Event costs more context switches.
    """

    __slots__ = ("_lock", "_set")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()
        self._set = False

    def is_set(self) -> bool:
        """Whether a wake-up is pending."""
        return self._set

    def set(self) -> None:
        """Wake the thread (once, however often it is called before the thread wakes)."""
        if not self._set:
            self._set = True
            try:
                self._lock.release()
            except RuntimeError:  # already released: a wake-up is pending
                pass

    def wait(self, timeout_s: float | None) -> bool:
        """Wait for a wake-up or ``timeout_s`` (None: no limit), then clear the flag; whether it
        was a wake-up.

        Clears before the caller looks at its queue: a :meth:`set` after that wakes it again.
        """
        woken = self._lock.acquire(timeout=-1 if timeout_s is None else max(0.0, timeout_s))
        self._set = False
        return woken


class Outbox:
    """Jobs for one thread; :meth:`put` from any thread, never blocks."""

    def __init__(self, name: str, size: int = 1000, nice: int = SENDER_NICE, *,
                 batch_s: float = BATCH_S, wake_at: int = WAKE_AT, drop: str = "oldest",
                 on_batch: Callable[[], float | None] | None = None,
                 on_stop: Callable[[], None] | None = None) -> None:
        """``nice``: the thread's niceness relative to the daemon (0: the same priority);
        ``batch_s`` (s) and ``wake_at`` (jobs): when the thread runs the queue; ``drop``: which job
        goes when the queue is full (:data:`DROP_POLICIES`); ``on_batch`` and ``on_stop``: see the
        module docstring."""
        if size < 1:
            raise ValueError(f"size must be at least 1, got {size}")
        if drop not in DROP_POLICIES:
            raise ValueError(f"drop must be one of {DROP_POLICIES}, got {drop!r}")
        self.name = name
        self.size = size
        self.nice = nice
        self.batch_s = batch_s
        self.wake_at = max(1, wake_at)
        self._drop_newest = drop == "newest"
        self._on_batch = on_batch
        self._on_stop = on_stop
        self._queue: collections.deque[Job] = collections.deque(
            maxlen=None if self._drop_newest else size)
        self._wake = _Wake()
        self._stopping = False
        self._idle = False  # the thread sleeps, with no timer, until a job comes
        self._hurry = False  # an urgent job (or a full batch) is queued: no batch wait
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._abandoned = False
        self._failure: list[BaseException] = []
        self._drain_due = math.inf  # monotonic s: from then on a control_idle() wakes the thread
        #: jobs dropped because the queue was full
        self.dropped = 0
        #: jobs run, and jobs that raised
        self.done = 0
        self.failed = 0

    @property
    def running(self) -> bool:
        """Whether the thread is running."""
        return self._thread is not None and self._thread.is_alive()

    def start(self, setup: Callable[[], None] | None = None, *, wait: bool = True) -> None:
        """Start the thread (idempotent). ``setup`` runs in it first; what it raises is raised here
        (and the thread is gone). ``wait=False``: return at once; :meth:`wait_started` waits."""
        if self._thread is not None:
            return
        self._stopping = False
        self._ready = threading.Event()
        self._abandoned = False
        self._failure = []
        self._thread = threading.Thread(target=self._run, args=(setup, self._ready, self._failure),
                                        name=self.name, daemon=True)
        self._thread.start()
        if wait:
            self.wait_started(None)

    def wait_started(self, timeout_s: float | None) -> bool:
        """Wait for ``setup`` (see :meth:`start`), at most ``timeout_s`` (None: no limit); re-raise
        what it raised. False when it did not finish in time or :meth:`abandon_start` was called:
        the thread is then left behind (a daemon thread, stopping by itself if setup ever ends)."""
        thread = self._thread
        if thread is None:
            return False
        if self._ready.wait(timeout_s) and not self._abandoned:
            if self._failure:
                thread.join()
                self._thread = None
                raise self._failure[0]
            return True
        self._thread = None
        self._stopping = True  # should setup end after all: run what is queued, on_stop, end
        self._wake.set()
        return False

    @property
    def abandoned(self) -> bool:
        """Whether :meth:`abandon_start` was called since the last :meth:`start`."""
        return self._abandoned

    def abandon_start(self) -> None:
        """Make a :meth:`wait_started` in another thread return False now (any thread may call)."""
        self._abandoned = True
        self._ready.set()

    def stop(self, timeout_s: float | None = 2.0, *, stall_s: float | None = None) -> bool:
        """Run what is queued (then ``on_stop``), and stop the thread; safe to call twice. Whether
        the thread ended (True also when it was not running).

        ``timeout_s``: how long to wait for that (None: as long as it takes); ``stall_s``: with no
        ``timeout_s``, how long to wait without a job done (None: no limit; a disk that writes
        slowly is waited for, one that takes nothing is not). A thread still busy then is left
        behind (a daemon thread: it does not hold the process), with a warning.
        """
        thread, self._thread = self._thread, None
        if thread is None:
            return True
        self._stopping = True
        self._wake.set()
        if timeout_s is not None or stall_s is None:
            thread.join(timeout_s)
        else:
            done, since = self.done + self.failed, time.monotonic()
            while thread.is_alive() and time.monotonic() - since < stall_s:
                thread.join(min(1.0, stall_s))
                if self.done + self.failed != done:
                    done, since = self.done + self.failed, time.monotonic()
        if thread.is_alive():
            log.warning("%s: thread still busy after %.1f s%s; left behind", self.name,
                        timeout_s if timeout_s is not None else stall_s,
                        "" if timeout_s is not None else " without a job done")
            return False
        return True

    def put(self, fn: Callable[..., None], *args: Any, urgent: bool = False) -> None:
        """Queue ``fn(*args)`` for the thread; when full, a job is dropped (see ``drop``).

        ``urgent``: wake the thread now rather than at the next batch.
        """
        queue = self._queue
        if len(queue) >= self.size:
            self.dropped += 1
            if self._drop_newest:
                return
        queue.append((fn, args))
        if urgent or len(queue) >= self.wake_at:
            self._hurry = True
            if not self._wake.is_set():
                self._wake.set()
        elif self._idle and not self._wake.is_set():
            self._wake.set()  # the first job into an empty queue: the thread waits for its batch

    def clear(self) -> int:
        """Drop every queued job (not counted in :attr:`dropped`); returns how many."""
        n = len(self._queue)
        self._queue.clear()
        return n

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

    def _run(self, setup: Callable[[], None] | None, ready: threading.Event,
             failure: list[BaseException]) -> None:
        name_this_thread(self.name)
        if self.nice:
            lower_thread_priority(self.nice)
        try:
            if setup is not None:
                setup()
        except BaseException as err:
            failure.append(err)
            return
        finally:
            ready.set()
        queue = self._queue
        while True:
            wait_s: float | None = 2 * self.batch_s
            idle = False
            if self._on_batch is not None:  # at the start, then after every batch
                next_s = self._on_batch()
                if next_s is not None:
                    wait_s = min(2 * self.batch_s, max(0.0, next_s))
            else:
                # before looking at the queue: a put after the look wakes us
                self._idle = True
                if queue:
                    self._idle = False
                else:
                    idle = True
                    wait_s = None
            self._drain_due = time.monotonic() + self.batch_s
            self._wake.wait(wait_s)
            if idle:
                self._idle = False
                # woken by a job that can wait for its batch
                if not self._hurry and not self._stopping:
                    self._drain_due = time.monotonic() + self.batch_s
                    self._wake.wait(self.batch_s)
            self._hurry = False
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
                        log.exception("%s: a job failed (%d so far)", self.name, self.failed)
            if stopping:
                if self._on_stop is not None:
                    self._on_stop()
                return
