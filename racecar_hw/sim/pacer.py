"""Real-time pacing of a simulation: a step at each deadline of a fixed rate on the monotonic clock.

Deadlines are absolute (``period`` apart from the start), so the pace does not drift; a deadline
already passed runs at once. After a stall of more than :data:`STALL_PERIODS` periods the
deadlines restart from now instead of firing in a burst (the step that follows covers the whole
gap: the callee is given the monotonic time, in ns, and steps to it).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from racecar_hw.base.clock import NS_PER_S, monotonic_ns

#: Periods of delay after which the deadlines restart from now.
STALL_PERIODS = 5


class Pacer:
    """Calls ``step_to(now_ns)`` at ``rate_hz`` (Hz) with :meth:`run`, forever (cancel to stop)."""

    def __init__(self, rate_hz: float) -> None:
        self.period_ns = int(round(NS_PER_S / rate_hz))

    async def run(self, step_to: Callable[[int], None]) -> None:
        period_ns = self.period_ns
        deadline = monotonic_ns()
        while True:
            deadline += period_ns
            delay = deadline - monotonic_ns()
            if delay > 0:
                await asyncio.sleep(delay / NS_PER_S)
            elif -delay > STALL_PERIODS * period_ns:
                deadline = monotonic_ns()
            step_to(monotonic_ns())


__all__ = ["STALL_PERIODS", "Pacer"]
