"""SIGINT, SIGTERM and SIGHUP stop a command, whatever signal disposition the process inherited.

A process started in the background by a non-interactive shell (``cmd &`` in a script, a CI job,
a test harness that was itself started so) inherits SIGINT (and SIGQUIT) *ignored*, as POSIX
requires of such shells, and Python then leaves it ignored: ``asyncio.run`` installs its Ctrl-C
handling only over Python's default handler, and ``KeyboardInterrupt`` is never raised. A
``racecar-hw fake-vesc`` started that way ran on after SIGINT until killed. Commands that serve
until interrupted therefore install their handlers explicitly, here. Before that, from the start of
``racecar-hw``, a stop signal interrupts the start-up (:mod:`racecar_hw.runtime.interrupts`).
"""

from __future__ import annotations

import asyncio
import logging
import signal
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from racecar_hw.runtime.interrupts import (
    RESTART_SIGNING_SIGNAL,
    STOP_SIGNALS,
    StopSignals,
    ignore_restart_signing,
    interrupt_on_stop_signals,
)

__all__ = ["RESTART_SIGNING_SIGNAL", "STOP_SIGNALS", "StopSignals", "add_restart_signing_handler",
           "add_stop_handlers", "ignore_restart_signing", "interrupt_on_stop_signals",
           "run_until_stop_signal"]

T = TypeVar("T")


def add_stop_handlers(loop: asyncio.AbstractEventLoop, callback: Callable[[int], None], *,
                      noted: StopSignals | None = None) -> Callable[[], None]:
    """``callback(signum)`` on SIGINT, SIGTERM and SIGHUP in ``loop``; returns a function that removes them.

    ``noted``: the :class:`StopSignals` that covered the loop's start; a signal it noted is handed
    to ``callback`` at once (as soon as the loop runs), and it takes the signals back when the
    handlers are removed.
    """
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, callback, sig)
    if noted is not None and noted.noted is not None:
        loop.call_soon(callback, noted.noted)

    def remove() -> None:
        if noted is None:
            for sig in STOP_SIGNALS:
                loop.remove_signal_handler(sig)
            return
        # asyncio puts Python's default back as it removes its SIGINT handler, looking it up as
        # signal.default_int_handler: a Ctrl-C before handle_again() raised KeyboardInterrupt (exit
        # 130 after a finished run). Meanwhile that name is the noting handler. (Masking the
        # signal in this thread would not do: another thread takes it, and the handler runs here.)
        default = signal.default_int_handler
        signal.default_int_handler = noted.note  # type: ignore[assignment]
        try:
            for sig in STOP_SIGNALS:
                loop.remove_signal_handler(sig)
            noted.handle_again()  # not Python's defaults, which asyncio leaves behind
        finally:
            signal.default_int_handler = default  # type: ignore[assignment]

    return remove


def add_restart_signing_handler(loop: asyncio.AbstractEventLoop,
                                restart: Callable[[], str]) -> Callable[[], None]:
    """``restart()`` (the daemon's :meth:`~racecar_hw.daemon.Daemon.restart_mavlink_signing`) on
    :data:`RESTART_SIGNING_SIGNAL` in ``loop``, its answer logged; returns a function that removes
    the handler."""

    def on_signal() -> None:
        logging.getLogger("racecar_hw.daemon").warning("%s: %s", RESTART_SIGNING_SIGNAL.name, restart())

    loop.add_signal_handler(RESTART_SIGNING_SIGNAL, on_signal)

    def remove() -> None:
        loop.remove_signal_handler(RESTART_SIGNING_SIGNAL)  # (asyncio leaves the default behind)
        ignore_restart_signing()

    return remove


def run_until_stop_signal(make: Callable[[], Coroutine[Any, Any, T]]) -> T | None:
    """Run the coroutine ``make()`` until it ends or SIGINT/SIGTERM cancels it (then None).

    Until the loop's own handlers are in place a signal is only noted, then handed to them: an
    exception raised while ``asyncio.run`` builds its loop would leave a half-made loop behind
    (and an "Exception ignored" traceback when it is collected). The coroutine is created inside
    the running loop, so a signal that arrives before the loop starts leaves no coroutine "never
    awaited" behind. Its first step runs with the handlers in place (and before a signal noted
    earlier is handed to them), so what it does first, such as printing a "serving" banner,
    happens only once a stop signal is the coroutine's normal end.
    """
    stops = StopSignals()

    async def main() -> T | None:
        task = asyncio.ensure_future(make())
        remove = add_stop_handlers(asyncio.get_running_loop(), lambda _sig: task.cancel(), noted=stops)
        try:
            return await task
        except asyncio.CancelledError:
            if not task.cancelled():
                raise
            return None
        finally:
            remove()

    coro = main()
    with stops:
        try:
            return asyncio.run(coro)
        except KeyboardInterrupt:
            coro.close()  # not "never awaited", whatever raised it
            return None
