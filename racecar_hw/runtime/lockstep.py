"""An asyncio event loop on virtual time: the daemon and its fakes in lockstep with the simulation.

:class:`VirtualTimeLoop` is asyncio's selector loop whose clock (``loop.time()``) is a counter of
virtual nanoseconds. The counter moves only when the loop has nothing left to do: no callback
ready, no reply pending on a device link, no job handed to a thread, no queue to a writer thread
still full. It then jumps to the next timer (``speed=None``: as fast as the machine allows) or
waits for it on the real clock scaled by ``speed`` (``speed=1``: real time). Whatever a fake device
sent is therefore consumed, in full, before the world moves on, and the same inputs give the same
run on an idle or a loaded machine. Timers due at the same instant (the world's step, a scan, the
control tick share many) run in the order they were set, not in the order of asyncio's heap, so
adding or removing a timer elsewhere does not change what the others compute.

Threads still work: a thread that hands the loop work (``call_soon_threadsafe``, a network
callback) wakes it (as fast as possible, a loop with work asks the OS for socket and thread events
at most every :data:`EVENTS_EVERY_S` of real time: what a thread hands over waits in the queue
meanwhile, and time does not jump past it); time stands still while a job given to a thread
(``run_in_executor``, ``asyncio.to_thread``) runs, and while any of :meth:`add_busy`'s predicates
holds (a recorder's queue to its writer thread). Those are the only real-time waits.

:func:`run` runs a coroutine on such a loop with the process's clock
(:mod:`racecar_hw.base.clock`) switched to the loop's, as ``asyncio.run`` would. A caller that
steps a simulation from outside the loop (:mod:`racecar_hw.sim.env`) uses
:meth:`VirtualTimeLoop.run_until_time` (run until a virtual time, with everything due by then
done), :meth:`VirtualTimeLoop.rewind` (the clock back to the start between two runs) and
:func:`close`.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import math
import selectors
import time
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from racecar_hw.base.clock import NS_PER_S, SIM_EPOCH_NS, use_virtual_time

T = TypeVar("T")

#: How long (real s) the loop looks for thread work between checks while time stands still.
BUSY_POLL_S = 0.002
#: How often (real s) a run as fast as possible asks the OS for socket and thread events while it
#: has work (a look costs a system call and a GIL hand-over; a pass of the loop, a few us).
#: Threads' callbacks (``call_soon_threadsafe``) are queued for the next pass without it.
EVENTS_EVERY_S = 0.001
#: Paced runs that fall this far (real s) behind their schedule start it again from now instead
#: of racing to catch up (a process held up on a loaded machine, a stall at start-up, a debugger):
#: racing through a hold would run the timers it owes back to back, and input from outside (a
#: client's 20 Hz stream) would look to the daemon as if it had paused for the hold, long enough
#: for a mux input's 0.2 s timeout. Virtual time loses the hold instead; shorter lags are caught up.
RESYNC_BEHIND_S = 0.05


class VirtualTimeLoop(asyncio.SelectorEventLoop):
    """A selector event loop whose time is virtual: see the module docstring.

    ``speed``: None runs as fast as the machine allows; a positive number paces virtual time at
    that multiple of real time. ``start_ns``: the virtual time at creation.
    """

    def __init__(self, speed: float | None = None, start_ns: int = SIM_EPOCH_NS) -> None:
        super().__init__()
        if speed is not None and not (math.isfinite(speed) and speed > 0):
            self.close()
            raise ValueError(f"speed must be positive or None (as fast as possible), got {speed}")
        self.speed = speed
        self._now_ns = start_ns
        self._jobs = 0
        self._busy: list[Callable[[], bool]] = []
        self._anchor: tuple[int, float] | None = None  # (virtual ns, real monotonic s) of the pace
        #: real seconds the loop waited for threads while virtual time stood still
        self.stood_still_s = 0.0
        self._events_due = 0.0  # real monotonic s of the next look for events (speed=None, busy)
        self._until_ns: int | None = None  # run_until_time's end: the loop stops instead of passing it
        self._selector = _VirtualSelector(self._selector, self)  # type: ignore[has-type]
        #: what ended the run from inside a callback or task (see :meth:`call_exception_handler`)
        self.fatal: BaseException | None = None
        self.set_task_factory(_watched_task)
        self._timer_seq = itertools.count()

    # --- timers: due at the same time, they run in the order they were set -------------------

    def call_at(self, when: float, callback: Callable[..., object], *args: Any,
                context: Any = None) -> asyncio.TimerHandle:
        """As asyncio's, but timers due at the same time run in the order they were set (asyncio's
        heap leaves their order to its shape, so a timer added or removed anywhere in the process
        would reorder the others' at every shared instant, and with them what a run computes)."""
        if when is None:
            raise TypeError("when cannot be None")
        self._check_closed()  # type: ignore[attr-defined]
        if self._debug:  # type: ignore[attr-defined]
            self._check_thread()  # type: ignore[attr-defined]
            self._check_callback(callback, "call_at")  # type: ignore[attr-defined]
        timer = _Timer(when, callback, args, self, context)
        timer._key = (when, next(self._timer_seq))
        if timer._source_traceback:  # type: ignore[attr-defined]  # (debug mode) this frame
            del timer._source_traceback[-1]  # type: ignore[attr-defined]
        heapq.heappush(self._scheduled, timer)  # type: ignore[attr-defined]
        timer._scheduled = True
        return timer

    # --- what ends a run from inside ----------------------------------------------------------

    def call_exception_handler(self, context: dict[str, Any]) -> None:
        """As asyncio's, but an exception that is not an ``Exception`` (a test's time limit, which
        pytest raises as its own ``BaseException``) stops the loop, and :func:`run` raises it: asyncio
        would log it and go on, and a run whose world or duration timer it ended would never end."""
        exc = context.get("exception")
        if _ends_the_run(exc):
            self._end(exc)
        super().call_exception_handler(context)

    def _end(self, exc: BaseException) -> None:
        if self.fatal is None:
            self.fatal = exc
            self.stop()

    # --- the clock ----------------------------------------------------------------------------

    def time(self) -> float:
        return self._now_ns / NS_PER_S

    def now_ns(self) -> int:
        """Virtual time in ns (what :func:`racecar_hw.base.clock.monotonic_ns` returns in a run)."""
        return self._now_ns

    def stall(self, seconds: float) -> None:
        """Move virtual time ``seconds`` ahead at once with nothing run: what a process held up (a
        long blocking call, a descheduled CPU) does to the loop. Every timer that fell due meanwhile
        then runs in one pass, in deadline order, as after a real hold-up. For tests of hold-ups."""
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"a stall lasts zero or more seconds, not {seconds}")
        self._now_ns += round(seconds * NS_PER_S)
        self._anchor = None

    # --- what holds time still ----------------------------------------------------------------

    def add_busy(self, predicate: Callable[[], bool]) -> Callable[[], None]:
        """Hold virtual time while ``predicate()`` is true (checked from the loop); returns a remover."""
        self._busy.append(predicate)

        def remove() -> None:
            if predicate in self._busy:
                self._busy.remove(predicate)

        return remove

    def run_in_executor(self, executor: Any, func: Callable[..., T], *args: Any) -> asyncio.Future[T]:
        fut = super().run_in_executor(executor, func, *args)
        self._jobs += 1

        def done(_: object) -> None:
            self._jobs -= 1

        fut.add_done_callback(done)
        return fut

    def _held(self) -> bool:
        return self._jobs > 0 or any(p() for p in self._busy)

    # --- stepping from outside ----------------------------------------------------------------

    def run_until_time(self, until_ns: int) -> None:
        """Run the (not running) loop until virtual time is ``until_ns`` and nothing is left to do
        at that instant: every timer due by then ran, and what they started ran to the point where
        only a later timer could go on (what a fake device sent at ``until_ns`` is consumed), as
        time would otherwise move on. The clock is then ``until_ns`` exactly. For callers that step
        a simulation from outside the loop (:mod:`racecar_hw.sim.env`); an exception in a callback
        goes to the loop's exception handler, as in ``run_forever``."""
        if until_ns < self._now_ns:
            raise ValueError(f"virtual time is {self._now_ns} ns already, past {until_ns} ns")
        self._until_ns = until_ns
        try:
            self.run_forever()
        finally:
            self._until_ns = None
        if self.fatal is not None:
            raise self.fatal

    def rewind(self, start_ns: int = SIM_EPOCH_NS) -> None:
        """Set virtual time back to ``start_ns`` between two runs in this loop, so each starts at the
        same time and runs the same (periodic timers on a grid of absolute time, and schedules in
        float seconds, meet their events at other offsets or nanoseconds from another start).
        Refused (RuntimeError) while the loop runs or holds anything that a clock going back would
        confuse: a task, a callback, a timer."""
        if self.is_running():
            raise RuntimeError("cannot rewind a running loop")
        live = [h for h in self._scheduled if not h.cancelled()]  # type: ignore[attr-defined]
        if live or self._ready or asyncio.all_tasks(self):  # type: ignore[attr-defined]
            raise RuntimeError("cannot rewind virtual time while tasks, callbacks or timers remain")
        self._scheduled.clear()  # type: ignore[attr-defined]  # cancelled timers only
        self._timer_cancelled_count = 0
        self._now_ns = start_ns
        self._anchor = None

    def _at_end(self, target: int | None) -> bool:
        """In :meth:`run_until_time`: whether the loop is idle at its end (and so stopped)."""
        until = self._until_ns
        if until is None or (target is not None and target <= until):
            return False
        if self._now_ns < until:  # nothing due before the end: time jumps (or is paced) to it
            return False
        self.stop()
        return True

    # --- advancing ----------------------------------------------------------------------------

    def _next_timer_ns(self) -> int | None:
        scheduled = self._scheduled  # type: ignore[attr-defined]  # asyncio drops cancelled heads first
        if not scheduled:
            return None
        when = scheduled[0]._when
        target = round(when * NS_PER_S)  # to the nearest ns: delays of whole ns stay exact
        if target / NS_PER_S + self._clock_resolution <= when:  # (asyncio's test for "due")
            target += 1
        return max(self._now_ns, target)

    def _select(self, select: Callable[[float | None], list[Any]],
                timeout: float | None) -> list[Any]:
        if timeout == 0:
            return self._look(select)
        if self._held():
            started = time.monotonic()
            events = select(BUSY_POLL_S if timeout is None else min(timeout, BUSY_POLL_S))
            self.stood_still_s += time.monotonic() - started
            self._anchor = None
            return events
        target = self._next_timer_ns() if timeout is not None else None
        if self._at_end(target):
            return select(0)
        if self._until_ns is not None and (target is None or target > self._until_ns):
            target = self._until_ns  # the end of run_until_time, as if it were a timer
        if target is None:  # no timer: only a thread can give the loop work
            return select(None if timeout is None else BUSY_POLL_S)
        if self.speed is None:
            events = self._look(select)
            if not events and not self._ready:  # type: ignore[attr-defined]  # (a thread's callback)
                self._now_ns = target
            return events
        return self._paced(select, target)

    def _look(self, select: Callable[[float | None], list[Any]]) -> list[Any]:
        """Events ready now, without waiting; as fast as possible, the OS asked at most every
        :data:`EVENTS_EVERY_S` (nothing new in between: what a thread handed over is queued)."""
        if self.speed is None:
            real = time.monotonic()
            if real < self._events_due:
                return []
            self._events_due = real + EVENTS_EVERY_S
        return select(0)

    def _paced(self, select: Callable[[float | None], list[Any]], target: int) -> list[Any]:
        assert self.speed is not None
        real = time.monotonic()
        if self._anchor is None:
            self._anchor = (self._now_ns, real)
        v0, r0 = self._anchor
        due = r0 + (target - v0) / NS_PER_S / self.speed
        if due - real < -RESYNC_BEHIND_S:
            self._anchor = (self._now_ns, real)
            due = real + (target - self._now_ns) / NS_PER_S / self.speed
        events = select(max(0.0, due - real))
        if events:  # a thread woke the loop before the timer: time runs up to now (paced)
            passed = round((time.monotonic() - r0) * self.speed * NS_PER_S)
            self._now_ns = max(self._now_ns, min(target, v0 + passed))
        else:
            self._now_ns = target
        return events


class _Timer(asyncio.TimerHandle):
    """A loop timer ordered by its time, then by when it was set: ``_key`` is (when, the loop's
    count of timers set), compared as one tuple."""

    __slots__ = ("_key",)

    def __lt__(self, other: object) -> bool:
        try:
            return self._key < other._key  # type: ignore[attr-defined,no-any-return]
        except AttributeError:  # (not one of the loop's: asyncio's order)
            return super().__lt__(other)  # type: ignore[no-any-return]


class _VirtualSelector:
    """The loop's selector with :meth:`select` routed through the loop's clock."""

    def __init__(self, inner: selectors.BaseSelector, loop: VirtualTimeLoop) -> None:
        self._inner = inner
        self._loop = loop

    def select(self, timeout: float | None = None) -> list[Any]:
        return self._loop._select(self._inner.select, timeout)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def _ends_the_run(exc: object) -> bool:
    return (isinstance(exc, BaseException) and not isinstance(exc, Exception)
            and not isinstance(exc, (asyncio.CancelledError, KeyboardInterrupt, SystemExit)))


def _watched_task(loop: asyncio.AbstractEventLoop, coro: Coroutine[Any, Any, Any],
                  **kwargs: Any) -> asyncio.Task[Any]:
    """A task whose end by an exception that :func:`_ends_the_run` ends the run (a task keeps
    what it raised until awaited, so the loop's exception handler would not hear of it)."""
    task = asyncio.Task(coro, loop=loop, **kwargs)

    def check(done: asyncio.Task[Any]) -> None:
        # the stored exception, read without marking it retrieved (``exception()`` would silence
        # asyncio's "never retrieved" report of an ordinary error)
        exc = getattr(done, "_exception", None)
        if _ends_the_run(exc) and isinstance(loop, VirtualTimeLoop):
            done.exception()  # retrieved: the run raises it
            loop._end(exc)

    task.add_done_callback(check)
    return task


def hold_while(predicate: Callable[[], bool]) -> Callable[[], None]:
    """In a lockstep run (the running loop is a :class:`VirtualTimeLoop`), hold virtual time while
    ``predicate()`` holds, e.g. while a writer thread is behind; elsewhere nothing. Returns the
    undo."""
    try:
        loop = asyncio.get_running_loop()
    except RuntimeError:
        return _nothing
    return loop.add_busy(predicate) if isinstance(loop, VirtualTimeLoop) else _nothing


def _nothing() -> None:
    pass


def run(main: Coroutine[Any, Any, T], speed: float | None = None, *,
        start_ns: int = SIM_EPOCH_NS) -> T:
    """Run ``main`` on a new :class:`VirtualTimeLoop` with the process's clock on it, as
    ``asyncio.run`` does (the remaining tasks cancelled, async generators and the default
    executor shut down, the loop closed)."""
    loop = VirtualTimeLoop(speed, start_ns)
    with use_virtual_time(loop.now_ns):
        try:
            asyncio.set_event_loop(loop)
            try:
                result = loop.run_until_complete(main)
            except RuntimeError:  # "stopped before Future completed": by what ended it, if anything
                if loop.fatal is not None:
                    raise loop.fatal from None
                raise
            if loop.fatal is not None:
                raise loop.fatal
            return result
        finally:
            try:
                close(loop)
            finally:
                asyncio.set_event_loop(None)


def close(loop: asyncio.AbstractEventLoop) -> None:
    """End a loop as ``asyncio.run`` does: cancel the remaining tasks (and wait for them), shut the
    async generators and the default executor down, close the loop."""
    try:
        _cancel_all(loop)
        loop.run_until_complete(loop.shutdown_asyncgens())
        loop.run_until_complete(loop.shutdown_default_executor())
    finally:
        loop.close()


def _cancel_all(loop: asyncio.AbstractEventLoop) -> None:
    tasks = asyncio.all_tasks(loop)
    if not tasks:
        return
    for task in tasks:
        task.cancel()
    loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
    for task in tasks:
        if not task.cancelled() and task.exception() is not None:
            loop.call_exception_handler({"message": "unhandled exception during lockstep shutdown",
                                         "exception": task.exception(), "task": task})


__all__ = ["BUSY_POLL_S", "EVENTS_EVERY_S", "RESYNC_BEHIND_S", "VirtualTimeLoop", "close", "hold_while",
           "run"]
