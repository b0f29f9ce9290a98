"""SIGINT, SIGTERM and SIGHUP from a command's first moment: noted during start-up, then KeyboardInterrupt.

SIGHUP (the terminal or SSH session a command runs in went away) stops a command as SIGTERM does:
``racecar-hw run`` started by hand over SSH brakes, centres, closes its bag and exits 0 when the
Wi-Fi drops. Python leaves SIGHUP at its default, which killed the daemon on the spot: the motor
ran on until the VESC's own timeout and the bag was left open.

``racecar-hw`` takes about a second to start (imports, building the argument parser). Python's own
Ctrl-C handling then printed a ``KeyboardInterrupt`` traceback, SIGTERM killed the process
wherever it was, and a process started as a background job of a non-interactive shell, which
inherits SIGINT *ignored*, lost a SIGINT sent before the command installed its handlers (a
``fake-vesc`` ran on for ten minutes). :func:`racecar_hw.cli.main` therefore handles both signals
first of all, with :class:`StopSignals`:

* while the modules are imported, a stop signal is only *noted*: an exception raised in the middle
  of an import can come out as another error (Python wraps one raised while a class is created in
  a ``RuntimeError``, with a traceback) or leave half-imported modules;
* then :meth:`StopSignals.interrupt` raises ``KeyboardInterrupt`` for a noted signal, and for every
  later one until the command installs its own handling (:mod:`racecar_hw.runtime.signals`);
  ``main`` turns it into exit status :data:`INTERRUPTED`, without a traceback.

This module imports nothing but :mod:`signal` and :mod:`contextlib`, so that it costs nothing
before the handlers are in place. A signal in the few tens of milliseconds before (the interpreter
starting) meets the disposition the process inherited: SIGTERM and a foreground SIGINT end it
there, a SIGINT a background job inherited as ignored is discarded by the kernel.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

#: The signal that restarts the MAVLink link's signing state in a running daemon (``systemctl
#: reload racecar-hw`` sends it; see docs/teleop.md). Not SIGHUP: a daemon run in an SSH session
#: ends when the session hangs up (a stop signal). Outside the daemon's run (its start-up, its
#: shutdown, other commands) it does nothing (:func:`ignore_restart_signing`): its default would
#: kill the process.
RESTART_SIGNING_SIGNAL = signal.SIGUSR1


def _nothing(signum: int, frame: object) -> None:
    """A handler that does nothing (not SIG_IGN, which a child process would inherit)."""


def ignore_restart_signing() -> None:
    """:data:`RESTART_SIGNING_SIGNAL` does nothing until the daemon takes it
    (:func:`racecar_hw.runtime.signals.add_restart_signing_handler`): a ``systemctl reload`` or a
    ``kill -USR1`` during start-up killed the daemon (the signing state is new then anyway)."""
    signal.signal(RESTART_SIGNING_SIGNAL, _nothing)


#: The exit status of a command stopped by a stop signal before it could finish (as a shell
#: reports a program stopped by Ctrl-C): during start-up, a one-shot command, a third signal to
#: ``sim``. Commands that serve until stopped exit 0 on a stop signal (their documented end).
INTERRUPTED = 130


def _raise_interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupt_on_stop_signals() -> Iterator[None]:
    """Within the block, SIGINT, SIGTERM and SIGHUP raise KeyboardInterrupt in the main thread; the
    handlers found are put back after it (an inherited "ignored" included)."""
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class StopSignals:
    """SIGINT, SIGTERM and SIGHUP noted (:attr:`noted`) from ``with`` on, raised after :meth:`interrupt`.

    Leaving the block puts back the handlers found on entering it; with ``keep`` (a command that
    runs until stopped, inside :func:`racecar_hw.cli.main`'s own block) it leaves its noting handler
    in place instead, so that a second Ctrl-C while the command finishes (closing its bag, writing
    its report) is noted, not raised as KeyboardInterrupt (exit 130, the report unwritten);
    ``main``'s block puts back the process's own handlers when the command has returned.
    """

    def __init__(self, keep: bool = False) -> None:
        #: the first stop signal received, None while there was none
        self.noted: int | None = None
        self._raising = False
        self._keep = keep
        self._previous: dict[int, object] = {}

    def __enter__(self) -> StopSignals:
        self._previous = {sig: signal.signal(sig, self._handle) for sig in STOP_SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        if self._keep:
            return
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]

    def handle_again(self) -> None:
        """Take SIGINT, SIGTERM and SIGHUP back (after an event loop's own handlers were removed: asyncio
        then leaves Python's defaults, KeyboardInterrupt and death by SIGTERM, not ours)."""
        for sig in STOP_SIGNALS:
            signal.signal(sig, self._handle)

    def interrupt(self) -> None:
        """From now on a stop signal raises KeyboardInterrupt; one noted before raises it at once."""
        self._raising = True
        if self.noted is not None:
            raise KeyboardInterrupt

    def note(self, signum: int, frame: FrameType | None) -> None:
        """The noting handler itself (a signal handler's signature)."""
        self._handle(signum, frame)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.noted is None:
            self.noted = signum
        if self._raising:
            raise KeyboardInterrupt
