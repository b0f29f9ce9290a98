"""A live console status panel for the daemon (``rich``), or a plain line when not on a terminal.

The control loop hands a :class:`~racecar_hw.runtime.status.StatusSnapshot` to
:meth:`StatusPanel.update` (a cheap attribute store) whenever it likes; the panel redraws on its own
asyncio timer in the same event loop, at ``refresh_hz`` (4 Hz) on a terminal. When the console is
not a terminal (systemd, a pipe, a log file) it writes one plain status line every
``plain_interval_s`` seconds instead, even when nothing changed, so a log shows the daemon is alive.
Rendering happens in the loop (rich's own auto-refresh thread is turned off); the text goes to the
terminal through a :class:`~racecar_hw.runtime.console.QueuedStream`, so a terminal that stops
reading (Ctrl-S) or a busy journald never blocks the loop.

While the live panel is on a terminal, log records that would go to that terminal are printed
through the panel's console instead (above the panel, which rich then redraws below them): a log
line written behind the panel's back would scroll the screen and leave fragments of the box. The
columns have a fixed width, so the box does not jump as values change; a value too long for its
column ends in an ellipsis.

Apart from :mod:`racecar_hw.runtime.status` so that a daemon without a panel (the car's config)
does not import ``rich``'s renderers.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import sys
import time
from collections.abc import Callable

from rich.console import Console, ConsoleOptions, Group, RenderableType, RenderResult
from rich.constrain import Constrain
from rich.live import Live
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from racecar_hw.runtime.console import QueuedStream
from racecar_hw.runtime.status import StatusSnapshot, plain_line, status_fields

log = logging.getLogger(__name__)


def _style(label: str, s: StatusSnapshot) -> str:
    if label == "armed":
        return {True: "bold green", False: "bold red", None: "dim"}[s.armed]
    if label == "e-stop":
        return "bold red" if s.estop and s.estop.startswith("latched") else ""
    if label == "safety" and s.safety_state and s.safety_state.lower() not in ("ok", "clear", "free"):
        return "bold yellow"
    link = s.vesc_link if label == "vesc" else s.lidar_link if label == "lidar" else None
    if link is not None and link != "up":
        return "bold red" if link.startswith("lost") else "yellow"
    if label == "vesc" and (s.vesc_crc_errors or s.vesc_reconnects):
        return "yellow"
    if label == "lidar" and s.lidar_reconnects:
        return "yellow"
    if label == "refused":
        return "bold yellow" if "(recent)" in (s.refused or "") else "yellow"
    return ""


#: Widths of the panel and its label columns (characters): fixed, so the box keeps its size whatever
#: the values (the value columns get 36 each); a longer value (a lost link with its counters) ends
#: in an ellipsis, its start (the state) kept. The plain line has every value in full. On a terminal
#: narrower than the panel (80 columns) the fields stand one per row, every value whole (wrapped
#: in the rare case it is longer than the row).
PANEL_WIDTH, LABEL_WIDTH = 100, 9


class _StatusView:
    """The panel, laid out for the width it is drawn in (see :data:`PANEL_WIDTH`)."""

    def __init__(self, s: StatusSnapshot, title: str) -> None:
        self.snapshot, self.title = s, title

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        s = self.snapshot
        pairs = 2 if options.max_width >= PANEL_WIDTH else 1
        grid = Table.grid(padding=(0, 2), expand=True)
        for _pair in range(pairs):
            grid.add_column(style="bold cyan", no_wrap=True, width=LABEL_WIDTH)
            if pairs == 2:
                grid.add_column(no_wrap=True, overflow="ellipsis", ratio=1)  # the two share the rest
            else:
                grid.add_column(overflow="fold", ratio=1)
        fields = status_fields(s)
        # in two columns the e-stop line (who latched it, when) is too long for a column: a row
        # of its own, across the panel
        wide = [(label, text) for label, text in fields if pairs == 2 and label in _WIDE]
        cells = [(label, Text(text, style=_style(label, s))) for label, text in fields
                 if not (pairs == 2 and label in _WIDE)]
        for i in range(0, len(cells), pairs):
            row: list[RenderableType] = []
            for label, text in cells[i:i + pairs]:
                row += [label, text]
            grid.add_row(*row)
        body: RenderableType = grid
        if wide:
            lines = Table.grid(padding=(0, 2), expand=True)
            lines.add_column(style="bold cyan", no_wrap=True, width=LABEL_WIDTH)
            lines.add_column(no_wrap=True, overflow="ellipsis", ratio=1)
            for label, text in wide:
                lines.add_row(label, Text(text, style=_style(label, s)))
            body = Group(grid, lines)
        yield Constrain(Panel(body, title=self.title, expand=True), PANEL_WIDTH)


def render(s: StatusSnapshot, title: str = "racecar-hw") -> RenderableType:
    """The snapshot as a rich panel: two label/value columns, 100 columns wide; on a narrower
    terminal (80 columns) one field per row, every value whole."""
    return _StatusView(s, title)


#: Fields shown on a row of their own, across the panel.
_WIDE = ("e-stop",)


class StatusPanel:
    """Shows the latest snapshot: a rich live panel on a terminal, else a plain line now and then.

    ``update()`` may be called at any rate; ``source``, if given, is polled at each redraw instead.
    Call :meth:`start` from inside the running event loop and ``await stop()`` at shutdown.
    """

    def __init__(self, console: Console | None = None, *, refresh_hz: float = 4.0,
                 plain_interval_s: float = 5.0, title: str = "racecar-hw",
                 source: Callable[[], StatusSnapshot] | None = None) -> None:
        if refresh_hz <= 0 or plain_interval_s <= 0:
            raise ValueError("refresh_hz and plain_interval_s must be positive")
        # a console of our own writes through a queue: a paused terminal never stops the loop
        self._queued = None if console is not None else QueuedStream(sys.stdout, name="status-writer")
        self.console = console if console is not None else Console(file=self._queued)
        self.refresh_hz = refresh_hz
        self.plain_interval_s = plain_interval_s
        self.title = title
        self.source = source
        self.snapshot = StatusSnapshot()
        self.redraws = 0
        self.render_errors = 0
        self._live: Live | None = None
        self._task: asyncio.Task[None] | None = None
        self._log_handler: _PanelLogHandler | None = None
        self._muted: list[logging.Handler] = []

    @property
    def interactive(self) -> bool:
        """Whether the console is a terminal (live panel) rather than a pipe or file (plain lines)."""
        return self.console.is_terminal

    def update(self, snapshot: StatusSnapshot) -> None:
        """Remember ``snapshot``; it is drawn at the next redraw."""
        self.snapshot = snapshot

    def renderable(self) -> RenderableType:
        """The current snapshot as the panel shows it."""
        return render(self.snapshot, self.title)

    def start(self) -> None:
        """Start redrawing on a timer in the running event loop (idempotent)."""
        if self._task is not None:
            return
        if self.interactive:
            self._live = Live(self.renderable(), console=self.console, auto_refresh=False,
                              redirect_stdout=False, redirect_stderr=False)
            self._live.start(refresh=True)
            self._route_logs()
        self._task = asyncio.get_running_loop().create_task(self._run(), name="status-panel")

    async def stop(self) -> None:
        """Stop redrawing for good; the terminal keeps the last panel. Safe to call twice."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        live, self._live = self._live, None
        if live is not None:
            live.update(self.renderable(), refresh=True)
            live.stop()
        self._restore_logs()
        if self._queued is not None:
            self._queued.close()  # the last panel goes out before whatever the caller prints next

    def _route_logs(self) -> None:
        """Send log records bound for a terminal through the panel's console (see the module doc)."""
        root = logging.getLogger()
        self._muted = [h for h in root.handlers if type(h) is logging.StreamHandler and _is_tty(h.stream)]
        if not self._muted:
            return
        handler = self._log_handler = _PanelLogHandler(self.console)
        handler.setLevel(min(h.level for h in self._muted))
        handler.setFormatter(self._muted[0].formatter)
        for h in self._muted:
            root.removeHandler(h)
        root.addHandler(handler)

    def _restore_logs(self) -> None:
        root = logging.getLogger()
        if self._log_handler is not None:
            root.removeHandler(self._log_handler)
            self._log_handler = None
        for h in self._muted:
            root.addHandler(h)
        self._muted = []

    def draw(self) -> None:
        """Redraw once now (the timer calls this); never raises."""
        try:
            if self.source is not None:
                self.snapshot = self.source()
            if self._live is not None:
                self._live.update(self.renderable(), refresh=True)
            else:
                self.console.out(plain_line(self.snapshot), highlight=False)
            self.redraws += 1
        except Exception:
            self.render_errors += 1
            if self.render_errors == 1:
                log.exception("status display failed")

    async def _run(self) -> None:
        period = 1.0 / self.refresh_hz if self._live is not None else self.plain_interval_s
        loop = asyncio.get_running_loop()
        deadline = loop.time()
        drawn = -math.inf
        while True:
            # at most one redraw per period of real time: a person reads it, however fast a
            # simulation in lockstep runs the loop's clock
            if (real := time.monotonic()) - drawn >= 0.9 * period:
                self.draw()
                drawn = real
            deadline += period
            now = loop.time()
            if deadline < now:  # fell behind (loop busy): skip the missed redraws
                deadline = now + period
            await asyncio.sleep(deadline - now)


def _is_tty(stream: object) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty is not None and isatty())
    except (OSError, ValueError):
        return False


class _PanelLogHandler(logging.Handler):
    """Prints log records through the live panel's console, above the panel."""

    def __init__(self, console: Console) -> None:
        super().__init__()
        self.console = console

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.console.print(Text(self.format(record)), highlight=False, soft_wrap=True)
        except Exception:
            self.handleError(record)
