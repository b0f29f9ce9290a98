"""Link state of each device for the operator: connecting, up, or lost since when; and reminders.

A device driver logs when a link fails and keeps reconnecting quietly with backoff. A person at
the console needs more: the status panel shows each device's state (``connecting 12 s``, ``up``,
``lost since 14:02:31 (35 s)``), and while a device stays away the log says so again every
``remind_s`` seconds (doubling up to ``remind_max_s``), so a missing VESC is not one line in a log
that then goes quiet. :class:`LinkWatch` is polled (:meth:`LinkWatch.poll`); it never touches the
device.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from racecar_hw.base.clock import NS_PER_S, monotonic_ns

log = logging.getLogger(__name__)

CONNECTING, UP, LOST = "connecting", "up", "lost"


@dataclass
class LinkWatch:
    """Watches one link through ``connected()``; ``detail()`` may say why it is down (last error).

    ``clock`` is monotonic ns; ``wall`` gives the wall-clock seconds shown for "lost since".
    """

    name: str
    connected: Callable[[], bool]
    detail: Callable[[], str | None] = lambda: None
    remind_s: float = 10.0
    remind_max_s: float = 60.0
    clock: Callable[[], int] = monotonic_ns
    wall: Callable[[], float] = time.time
    state: str = CONNECTING
    since_ns: int = 0
    since_wall: float = 0.0
    reminders: int = 0
    _next_remind_ns: int = 0
    _interval_s: float = field(default=0.0, repr=False)

    def __post_init__(self) -> None:
        self.since_ns = self.clock()
        self.since_wall = self.wall()
        self._interval_s = self.remind_s
        self._next_remind_ns = self.since_ns + round(self.remind_s * NS_PER_S)

    def poll(self) -> str:
        """Update the state from ``connected()``; log a reminder when one is due. Returns the state."""
        now = self.clock()
        up = bool(self.connected())
        if up and self.state != UP:
            if self.reminders:
                log.warning("%s link up after %.0f s", self.name, (now - self.since_ns) / NS_PER_S)
            self._enter(UP, now)
        elif not up and self.state == UP:
            self._enter(LOST, now)
        elif not up and now >= self._next_remind_ns:
            self.reminders += 1
            why = self.detail()
            what = "still not connected" if self.state == CONNECTING else "still lost"
            log.warning("%s %s after %.0f s%s; retrying", self.name, what,
                        (now - self.since_ns) / NS_PER_S, f" ({why})" if why else "")
            self._interval_s = min(self._interval_s * 2, self.remind_max_s)
            self._next_remind_ns = now + round(self._interval_s * NS_PER_S)
        return self.state

    def _enter(self, state: str, now: int) -> None:
        self.state = state
        self.since_ns = now
        self.since_wall = self.wall()
        self.reminders = 0
        self._interval_s = self.remind_s
        self._next_remind_ns = now + round(self.remind_s * NS_PER_S)

    def text(self) -> str:
        """``up``, ``connecting 12 s`` or ``lost since 14:02:31 (35 s)``, for the panel."""
        if self.state == UP:
            return UP
        age = max(0.0, (self.clock() - self.since_ns) / NS_PER_S)
        if self.state == CONNECTING:
            return f"connecting {age:.0f} s"
        return f"lost since {time.strftime('%H:%M:%S', time.localtime(self.since_wall))} ({age:.0f} s)"
