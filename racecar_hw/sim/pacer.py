"""Real-time pacing of a simulation: a step at each deadline of a fixed rate on the monotonic clock.

Deadlines are absolute (whole multiples of the period on the monotonic clock:
:class:`~racecar_hw.runtime.ticker.PeriodicTimer`), so the pace does not drift; a deadline already
passed runs at once, and deadlines missed in a stall are skipped instead of firing in a burst (the
step that follows covers the whole gap: the callee is given the monotonic time, in ns, and steps
to it). The world's step, ``/clock`` and the run's watchers (the observer, the true pose) are
paced this way: loop timers, not tasks that sleep.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.runtime.ticker import PeriodicTimer


class Pacer:
    """Calls ``step_to(now_ns)`` at ``rate_hz`` (Hz) with :meth:`run`, forever (cancel to stop)."""

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = rate_hz
        self.period_ns = int(round(NS_PER_S / rate_hz))

    async def run(self, step_to: Callable[[int], None]) -> None:
        # a loop timer, not a sleeping task: half the event loop's work per step (it matters in
        # lockstep, where a 200 Hz world is stepped 200 times per simulated second as fast as it can)
        failed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

        def fail(err: BaseException) -> None:
            if not failed.done():
                failed.set_exception(err)

        timer = PeriodicTimer(self.rate_hz, lambda _due, _periods: step_to(monotonic_ns()), on_error=fail)
        timer.start()
        try:
            await failed
        finally:
            timer.cancel()


__all__ = ["Pacer"]
