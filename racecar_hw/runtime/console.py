"""Console output that never blocks the event loop: text goes through a bounded queue to a thread.

The daemon writes its log records to stderr and its status panel to stdout. Under systemd both
are a socket to journald, on a laptop a terminal, and either can stop taking bytes (journald busy
on a slow disk, a terminal paused with Ctrl-S); a plain write would then stop the control loop
with it. A :class:`QueuedStream` takes the text at once and its own thread writes it. While the
stream stays blocked and ``max_pending`` writes wait, further text is dropped and counted, and a
note of how much was lost goes out where the gap is, before the next text that got through (or at
close).

:func:`setup_logging` is ``logging.basicConfig`` with the handler writing through a
:class:`QueuedStream`; the status panel gives its rich console one too.
"""

from __future__ import annotations

import atexit
import logging
import queue
import sys
import threading
import time
from typing import TextIO

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
CLOSE_TIMEOUT_S = 2.0
"""How long closing waits for queued text to be written (the stream may be blocked for good)."""


class QueuedStream:
    """A text stream whose ``write`` queues and returns; a thread writes to ``stream``.

    File-like enough for ``logging.StreamHandler`` and ``rich.console.Console`` (``write``,
    ``flush``, ``isatty``, ``encoding``, ``fileno``). ``dropped`` counts the writes refused
    while ``max_pending`` waited.
    """

    def __init__(self, stream: TextIO, max_pending: int = 1000, name: str = "console-writer") -> None:
        self.stream = stream
        self.dropped = 0
        # each write with the number of writes dropped before it
        self._queue: queue.Queue[tuple[int, str] | None] = queue.Queue(max_pending)
        self._reported = 0
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def encoding(self) -> str:
        return getattr(self.stream, "encoding", None) or "utf-8"

    def isatty(self) -> bool:
        isatty = getattr(self.stream, "isatty", None)
        return bool(isatty is not None and isatty())

    def fileno(self) -> int:
        return self.stream.fileno()

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        """Queue ``text`` for the stream; never blocks."""
        if text and not self._closed:
            try:
                self._queue.put_nowait((self.dropped, text))
            except queue.Full:
                self.dropped += 1
        return len(text)

    def flush(self) -> None:
        """Nothing to do: the writer thread flushes the stream after every write."""

    def drain(self, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
        """Wait until everything queued is written; False if that took longer than ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        done = self._queue.all_tasks_done  # what Queue.join() waits on, here with a deadline
        with done:
            while self._queue.unfinished_tasks:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                done.wait(left)
        return True

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> None:
        """Write what is queued (waiting at most ``timeout_s``) and stop the thread. Safe twice."""
        if self._closed:
            return
        self.drain(timeout_s)
        self._closed = True
        try:
            self._queue.put_nowait(None)  # the end, after a note of the last drops if any
        except queue.Full:
            return  # still blocked: the daemon thread goes with the process
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                dropped_before, text = item if item is not None else (self.dropped, "")
                if dropped_before > self._reported:
                    lost, self._reported = dropped_before - self._reported, dropped_before
                    self.stream.write(f"[{lost} console writes dropped while the stream was blocked]\n")
                self.stream.write(text)
                self.stream.flush()
            except (OSError, ValueError):
                pass  # the stream is closed or gone: there is nowhere else to write
            finally:
                self._queue.task_done()
            if item is None:
                return


def setup_logging(level: int, stream: TextIO | None = None) -> QueuedStream | None:
    """Log to ``stream`` (stderr) through a :class:`QueuedStream`, as ``logging.basicConfig`` would.

    Like ``basicConfig`` it does nothing when the root logger already has handlers (a test
    harness, an embedding program); it returns the queued stream it installed, else None. The
    stream is drained and closed at exit.
    """
    root = logging.getLogger()
    if root.handlers:
        return None
    queued = QueuedStream(stream if stream is not None else sys.stderr, name="log-writer")
    handler = logging.StreamHandler(queued)  # type: ignore[arg-type]
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    root.addHandler(handler)
    root.setLevel(level)
    atexit.register(queued.close)
    return queued
