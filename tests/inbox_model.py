"""A stand-in event loop and clock for the network inbox's tests: the test says when the loop runs.

:class:`StepLoop` records what the inbox schedules (``call_soon_threadsafe``, ``call_later``) and
runs it when told, on a clock the test moves, so an interleaving of receiving threads and the
event loop is played exactly as a schedule says. :class:`Recorder` keeps every hand-over in order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from racecar_hw.base.messages import Message
from racecar_hw.net.inbox import Inbox

ESTOP, RELEASE = "/estop", "/estop_release"
NAV = "/nav_0"
TELEOP = "/teleop"


class Clock:
    """Monotonic nanoseconds that move only when told."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


class _Timer:
    def __init__(self, at_ns: int, callback: Callable[[], None]) -> None:
        self.at_ns = at_ns
        self.callback = callback
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


class StepLoop:
    """Enough of an asyncio loop for the inbox; :meth:`run` plays what is due now."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.soon: list[Callable[[], None]] = []
        self.timers: list[_Timer] = []

    def call_soon_threadsafe(self, callback: Callable[[], None]) -> None:
        self.soon.append(callback)

    def call_later(self, delay_s: float, callback: Callable[[], None]) -> _Timer:
        timer = _Timer(self.clock.ns + round(delay_s * 1e9), callback)
        self.timers.append(timer)
        return timer

    def run(self) -> int:
        """Run the ready callbacks, then the timers that are due (as one loop iteration); how many ran."""
        ran = 0
        ready, self.soon = self.soon, []
        for callback in ready:
            callback()
            ran += 1
        due = [t for t in self.timers if not t.cancelled and t.at_ns <= self.clock.ns]
        self.timers = [t for t in self.timers if not t.cancelled and t.at_ns > self.clock.ns]
        for timer in due:
            timer.callback()
            ran += 1
        return ran

    def next_timer_ns(self) -> int | None:
        live = [t.at_ns for t in self.timers if not t.cancelled]
        return min(live) if live else None


@dataclass
class Recorder:
    """Every hand-over in order: (``"estop"`` or ``"cmd"``, topic, message, origin, drain number)."""

    items: list[tuple[str, str, Message, str, int]] = field(default_factory=list)
    drains: int = 0

    def estop(self, topic: str, msg: Message, origin: str) -> None:
        self.items.append(("estop", topic, msg, origin, self.drains))

    def command(self, topic: str, msg: Message, origin: str) -> None:
        self.items.append(("cmd", topic, msg, origin, self.drains))


def make_inbox(period_s: float = 0.02) -> tuple[Inbox, StepLoop, Clock, Recorder]:
    """An inbox for two inputs and the e-stop topics, on a :class:`StepLoop`, recording hand-overs."""
    clock = Clock()
    loop = StepLoop(clock)
    rec = Recorder()
    inbox = Inbox([NAV, TELEOP], rec.command, period_s=period_s, estop_topic=ESTOP,
                  release_topic=RELEASE, on_estop=rec.estop, clock=clock)
    drain = inbox.drain

    def counted_drain() -> None:
        rec.drains += 1
        drain()

    inbox.drain = counted_drain  # type: ignore[method-assign]
    inbox.bind(loop)  # type: ignore[arg-type]
    return inbox, loop, clock, rec
