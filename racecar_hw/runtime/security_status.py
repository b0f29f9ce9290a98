"""What the network surfaces refused, as a ``/diagnostics`` status, a panel line and page rows.

:class:`SecurityStatus` reads a :class:`~racecar_hw.runtime.refusals.Refusals` (the daemon's
``Daemon.refusals``, fed by the web page, the Foxglove relay, MAVLink, the inbound flood guard and
the Zenoh login watch) and builds one ``diagnostic_msgs/DiagnosticStatus`` named
:data:`STATUS_NAME`: one KeyValue per ``surface: reason`` with its total since start, the sources
with the most refusals, and WARN while anything was refused in the last ``recent_s`` seconds (OK
otherwise). Called on the control tick at the mux's diagnostics rate, after the motor command: it
takes the counts only when the total has changed since the last call, so a quiet car pays for one
lock and one sum of a few integers. Callable from any thread (the panel and the page call it from
the event loop, the Foxglove server may from its own): one lock around the update.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.messages import DiagnosticStatus, KeyValue
from racecar_hw.runtime.refusals import Refusals

#: The status's name in ``/diagnostics``.
STATUS_NAME = "racecar_hw: network security"

#: How many sources (those with the most refusals) the status names.
TOP_SOURCES = 5


class SecurityStatus:
    """The refusal counts of ``refusals`` as a diagnostic status, a panel line and page rows.

    ``recent_s``: how long after the last refusal the status stays WARN (s); ``clock``: monotonic ns.
    """

    def __init__(self, refusals: Refusals, recent_s: float = 10.0,
                 clock: Callable[[], int] = monotonic_ns) -> None:
        self.refusals = refusals
        self.recent_ns = int(recent_s * NS_PER_S)
        self._clock = clock
        self._total = 0
        self._changed_ns: int | None = None  #: when the total last grew (monotonic ns)
        self._counts: dict[tuple[str, str], int] = {}
        self._values: list[KeyValue] = [KeyValue("refused in all", "0")]
        self._lock = threading.Lock()

    def _update(self, now_ns: int) -> int:
        """Take the counts if the total changed; the total."""
        with self._lock:
            return self._update_locked(now_ns)

    def _update_locked(self, now_ns: int) -> int:
        total = self.refusals.total()
        if total != self._total:
            self._total = total
            self._changed_ns = now_ns
            self._counts = self.refusals.counts()
            top = sorted(self.refusals.by_source().items(), key=lambda kv: -kv[1])[:TOP_SOURCES]
            self._values = ([KeyValue("refused in all", str(total))]
                            + [KeyValue(f"{surface}: {reason}", str(n))
                               for (surface, reason), n in self._counts.items()]
                            + [KeyValue(f"source {source} ({surface}: {reason})", str(n))
                               for (surface, source, reason), n in top])
        return total

    def recent(self, now_ns: int | None = None) -> bool:
        """Whether anything was refused in the last ``recent_s`` seconds (as of the last update)."""
        now = self._clock() if now_ns is None else now_ns
        return self._changed_ns is not None and now - self._changed_ns < self.recent_ns

    def status(self, now_ns: int | None = None) -> DiagnosticStatus:
        """The diagnostic status now (see the module docstring)."""
        now = self._clock() if now_ns is None else now_ns
        total = self._update(now)
        if not total:
            return DiagnosticStatus(DiagnosticStatus.OK, STATUS_NAME, "nothing refused", "",
                                    list(self._values))
        assert self._changed_ns is not None
        ago = (now - self._changed_ns) / NS_PER_S
        if self.recent(now):
            level, message = DiagnosticStatus.WARN, f"{total} refused, the last {ago:.0f} s ago"
        else:
            level, message = DiagnosticStatus.OK, f"{total} refused, none in the last {ago:.0f} s"
        return DiagnosticStatus(level, STATUS_NAME, message, "", list(self._values))

    def rows(self, now_ns: int | None = None) -> list[tuple[str, str, int]]:
        """(surface, reason, total) of every kind of refusal, for the status page."""
        self._update(self._clock() if now_ns is None else now_ns)
        return [(surface, reason, n) for (surface, reason), n in self._counts.items()]

    def line(self, now_ns: int | None = None) -> str | None:
        """One short line for the console panel (None: nothing refused yet)."""
        now = self._clock() if now_ns is None else now_ns
        total = self._update(now)
        if not total:
            return None
        parts = ", ".join(f"{surface} {reason} {n}" for (surface, reason), n in self._counts.items())
        return f"{total}{' (recent)' if self.recent(now) else ''}: {parts}"
