"""What the network surfaces refused or dropped, counted per source and reason, logged sparingly.

A flood of forged MAVLink frames, failed Zenoh logins or refused web requests must be visible
(counted, in ``/diagnostics`` and on the status page, named by source address in the log) without
the log itself becoming the attack: 10,000 refused requests must not write 10,000 lines.
:class:`Refusals` logs the first refusal of each (source, reason) at once, then at most one
summary line per pair per ``interval_s`` with the count since the last line; :meth:`Refusals.flush`
writes what is still pending (at shutdown).

Callable from any thread (Zenoh's callbacks, the relay thread, the event loop): one lock, held for
a dictionary update. The number of distinct sources is bounded (``max_sources``): beyond it new
sources are counted under ``"other sources"``, so spoofed addresses cannot grow memory. So is the
number of reasons per source (``max_reasons``, beyond it ``"other reasons"``) and a reason's length
(:data:`MAX_REASON_CHARS`): a reason may quote what the sender sent (a Zenoh sample's type name and
hash), and a sender varying it must not grow the counts, the log or ``/diagnostics`` either. Sources
and reasons are logged as one line of printable text (:func:`racecar_hw.base.text.one_line`): a
newline or a terminal escape in a sender's type name forges no log line.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.text import one_line

log = logging.getLogger("racecar_hw.refusals")

#: Where sources beyond ``max_sources`` are counted.
OTHER_SOURCES = "other sources"
#: Where a source's reasons beyond ``max_reasons`` are counted.
OTHER_REASONS = "other reasons"
#: Longer reasons are cut to this many characters (the last one an ellipsis).
MAX_REASON_CHARS = 160
#: Longer sources are cut to this many characters (the last one an ellipsis).
MAX_SOURCE_CHARS = 120


@dataclass
class _Pair:
    """One (source, reason): its total, what the log has not said yet, and when it last spoke."""

    total: int = 0
    pending: int = 0
    logged_ns: int | None = None


class Refusals:
    """Counts of refused network input by ``(surface, source, reason)``, with rate-limited log lines.

    ``surface`` names the interface (``"zenoh"``, ``"mavlink"``, ``"web"``, ``"relay"``), ``source``
    the peer (an address, ``"127.0.0.1:40112"`` or a host), ``reason`` what was wrong
    (``"bad signature"``, ``"too many connections"``). ``interval_s`` is the least time between two
    log lines of one pair (s); ``clock`` is monotonic ns.
    """

    def __init__(self, interval_s: float = 10.0, *, max_sources: int = 256, max_reasons: int = 16,
                 logger: logging.Logger = log, clock: Callable[[], int] = monotonic_ns) -> None:
        self.interval_ns = int(interval_s * NS_PER_S)
        self.max_sources = max_sources
        self.max_reasons = max_reasons
        self.logger = logger
        self._clock = clock
        self._lock = threading.Lock()
        self._pairs: dict[tuple[str, str, str], _Pair] = {}
        #: (surface, source) -> how many reasons it has
        self._sources: dict[tuple[str, str], int] = {}

    def note(self, surface: str, source: str, reason: str, count: int = 1) -> None:
        """Count ``count`` refusals; log a line if this pair has not spoken for ``interval_s``."""
        now = self._clock()
        line: tuple[str, str, str, int, int, int | None] | None = None
        source, reason = one_line(source, MAX_SOURCE_CHARS), one_line(reason, MAX_REASON_CHARS)
        with self._lock:
            if (surface, source) not in self._sources:
                if len(self._sources) >= self.max_sources:
                    source = OTHER_SOURCES
                self._sources.setdefault((surface, source), 0)
            pair = self._pairs.get((surface, source, reason))
            if pair is None:
                if self._sources[(surface, source)] >= self.max_reasons:
                    reason = OTHER_REASONS
                    pair = self._pairs.get((surface, source, reason))
                else:
                    self._sources[(surface, source)] += 1
                if pair is None:
                    pair = self._pairs[(surface, source, reason)] = _Pair()
            pair.total += count
            pair.pending += count
            if pair.logged_ns is None or now - pair.logged_ns >= self.interval_ns:
                line = (surface, source, reason, pair.pending, pair.total, pair.logged_ns)
                pair.pending = 0
                pair.logged_ns = now
        if line is not None:
            self._log(*line, now)

    def _log(self, surface: str, source: str, reason: str, count: int, total: int,
             since_ns: int | None, now_ns: int) -> None:
        if since_ns is None:
            self.logger.warning("%s: refused %s: %s (further refusals summarised every %.0f s)",
                                surface, source, reason, self.interval_ns / NS_PER_S)
        else:
            self.logger.warning("%s: refused %s: %s, %d times in the last %.0f s (%d in all)",
                                surface, source, reason, count, (now_ns - since_ns) / NS_PER_S, total)

    def flush(self) -> None:
        """Log every pair with refusals the log has not mentioned yet (at shutdown)."""
        now = self._clock()
        with self._lock:
            lines = [(*key, p.pending, p.total, p.logged_ns) for key, p in self._pairs.items() if p.pending]
            for p in self._pairs.values():
                if p.pending:
                    p.pending = 0
                    p.logged_ns = now
        for line in lines:
            self._log(*line, now)

    def total(self, surface: str | None = None, reason: str | None = None) -> int:
        """All refusals counted, or those of one surface and/or reason."""
        with self._lock:
            return sum(p.total for (s, _, r), p in self._pairs.items()
                       if (surface is None or s == surface) and (reason is None or r == reason))

    def counts(self) -> dict[tuple[str, str], int]:
        """Totals by ``(surface, reason)``, every source added up: what ``/diagnostics`` shows."""
        out: dict[tuple[str, str], int] = {}
        with self._lock:
            for (surface, _, reason), p in self._pairs.items():
                out[(surface, reason)] = out.get((surface, reason), 0) + p.total
        return dict(sorted(out.items()))

    def by_source(self) -> dict[tuple[str, str, str], int]:
        """Totals by ``(surface, source, reason)``."""
        with self._lock:
            return {key: p.total for key, p in sorted(self._pairs.items())}

    def lines(self) -> list[str]:
        """One short line per (surface, reason) for the panel and the status page."""
        return [f"{surface}: {reason}: {n}" for (surface, reason), n in self.counts().items()]
