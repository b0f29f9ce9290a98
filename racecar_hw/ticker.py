"""Fixed-rate loops on absolute deadlines: tick k is due at ``start + k * period`` and never drifts.

A tick that comes late (the event loop was busy) runs at once; ticks missed entirely are skipped
and counted in :attr:`Ticker.missed`, never replayed in a burst.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from racecar_hw.clock import NS_PER_S, monotonic_ns


class Ticker:
    """``await ticker.tick()`` returns at each deadline of a ``rate_hz`` schedule; the first at once."""

    def __init__(self, rate_hz: float, clock: Callable[[], int] = monotonic_ns,
                 sleep: Callable[[float], Awaitable[object]] = asyncio.sleep) -> None:
        """``clock`` (monotonic ns) and ``sleep`` (seconds) are replaceable for tests."""
        if not rate_hz > 0:
            raise ValueError(f"rate must be positive, got {rate_hz}")
        self.period_ns = round(NS_PER_S / rate_hz)
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
            self._due = now
        late = now - self._due
        if late >= self.period_ns:
            skipped = late // self.period_ns
            self.missed += skipped
            self._due += skipped * self.period_ns
        if self._due > now:
            await self._sleep((self._due - now) / NS_PER_S)
        due = self._due
        self._due += self.period_ns
        self.count += 1
        return due
