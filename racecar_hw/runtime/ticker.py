"""Fixed-rate loops on absolute deadlines: every tick is due at a whole multiple of the period on
the monotonic clock, so a schedule never drifts and schedules of the same rate (or of rates whose
periods are multiples of each other's) fire together, in one pass of the event loop: each wake-up
of a process costs CPU (about 0.17 ms on the development machine), so timers that share wake-ups
save it. The first tick comes at once, due at the grid point just before it.

A tick that comes late (the event loop was busy) runs at once; ticks missed entirely are skipped
and counted (``missed``), never replayed in a burst.

Two shapes of the same schedule:

* :class:`Ticker`, awaited in a task: ``due = await ticker.tick()``;
* :class:`PeriodicTimer`, a plain event-loop timer calling ``callback(due_ns, periods)``. It wakes
  no task, so a tick costs one pass of the event loop instead of two (the timer, then the task);
  the daemon's control loop and the VESC poll use it.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from racecar_hw.base.clock import NS_PER_S, monotonic_ns


def _catch_up(due_ns: int, now_ns: int, period_ns: int) -> tuple[int, int]:
    """(the deadline to run, deadlines skipped): a deadline a whole period behind ``now_ns`` or more
    is skipped for the last one on the grid not after ``now_ns``."""
    late = now_ns - due_ns
    if late < period_ns:
        return due_ns, 0
    skipped = late // period_ns
    return due_ns + skipped * period_ns, skipped


def _grid_floor(now_ns: int, period_ns: int) -> int:
    """The last deadline of the ``period_ns`` grid not after ``now_ns``."""
    return now_ns - now_ns % period_ns


def _period_ns(rate_hz: float) -> int:
    if not rate_hz > 0:
        raise ValueError(f"rate must be positive, got {rate_hz}")
    return round(NS_PER_S / rate_hz)


class Ticker:
    """``await ticker.tick()`` returns at each deadline of a ``rate_hz`` schedule; the first at once."""

    def __init__(self, rate_hz: float, clock: Callable[[], int] = monotonic_ns,
                 sleep: Callable[[float], Awaitable[object]] = asyncio.sleep) -> None:
        """``clock`` (monotonic ns) and ``sleep`` (seconds) are replaceable for tests."""
        self.period_ns = _period_ns(rate_hz)
        self._clock = clock
        self._sleep = sleep
        self._due: int | None = None
        self.count = 0
        self.missed = 0

    def reset(self) -> None:
        """Start the schedule again from the next tick (which returns at once)."""
        self._due = None

    async def tick(self) -> int:
        """Wait for the next deadline; returns the monotonic ns it was due at."""
        now = self._clock()
        if self._due is None:
            self._due = _grid_floor(now, self.period_ns)
        self._due, skipped = _catch_up(self._due, now, self.period_ns)
        self.missed += skipped
        if self._due > now:
            await self._sleep((self._due - now) / NS_PER_S)
        due = self._due
        self._due += self.period_ns
        self.count += 1
        return due


class PeriodicTimer:
    """Calls ``callback(due_ns, periods)`` from the event loop at each deadline of a ``rate_hz`` schedule.

    The first call comes at once after :meth:`start`. ``due_ns`` is the monotonic ns the tick was
    due at; ``periods`` how many periods passed since the previous call (1 when on time, k > 1
    after k - 1 skipped deadlines). The schedule is that of :class:`Ticker`. Deadlines are loop
    timers (``loop.call_at``), so ``clock`` must be the loop's clock in nanoseconds
    (``time.monotonic_ns`` for asyncio's loops). An exception from ``callback`` stops the timer
    and is passed to ``on_error`` (default: re-raised into the loop's exception handler).
    """

    def __init__(self, rate_hz: float, callback: Callable[[int, int], object], *,
                 clock: Callable[[], int] = monotonic_ns,
                 on_error: Callable[[BaseException], object] | None = None) -> None:
        self.period_ns = _period_ns(rate_hz)
        self._callback = callback
        self._clock = clock
        self._on_error = on_error
        self._loop: asyncio.AbstractEventLoop | None = None
        self._handle: asyncio.Handle | None = None
        self._due = 0
        self.count = 0
        self.missed = 0

    @property
    def running(self) -> bool:
        """Whether a next tick is scheduled."""
        return self._handle is not None

    def start(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Tick now (from the loop, soon) and then on the schedule; restarts a running timer."""
        self.cancel()
        self._loop = loop if loop is not None else asyncio.get_running_loop()
        self._due = _grid_floor(self._clock(), self.period_ns)
        self._handle = self._loop.call_soon(self._fire)

    def cancel(self) -> None:
        """Stop ticking (safe twice)."""
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None

    def _fire(self) -> None:
        now = self._clock()
        due, skipped = _catch_up(self._due, now, self.period_ns)
        self.missed += skipped
        self.count += 1
        self._due = due + self.period_ns
        assert self._loop is not None
        # scheduled before the callback runs, so the callback may cancel it
        self._handle = self._loop.call_at(self._due / NS_PER_S, self._fire)
        try:
            self._callback(due, 1 + skipped)
        except BaseException as err:
            self.cancel()
            if self._on_error is None:
                raise
            self._on_error(err)
