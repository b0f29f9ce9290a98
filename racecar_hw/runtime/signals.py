"""SIGINT and SIGTERM stop a command, whatever signal disposition the process inherited.

A process started in the background by a non-interactive shell (``cmd &`` in a script, a CI job,
a test harness that was itself started so) inherits SIGINT (and SIGQUIT) *ignored*, as POSIX
requires of such shells, and Python then leaves it ignored: ``asyncio.run`` installs its Ctrl-C
handling only over Python's default handler, and ``KeyboardInterrupt`` is never raised. A
``racecar-hw fake-vesc`` started that way ran on after SIGINT until killed. Commands that serve
until interrupted therefore install their handlers explicitly, here.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

T = TypeVar("T")

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _raise_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupt_on_stop_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM raise KeyboardInterrupt in the main thread."""
    previous = {sig: signal.signal(sig, _raise_interrupt) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def add_stop_handlers(loop: asyncio.AbstractEventLoop, callback: Callable[[int], None]) -> Callable[[], None]:
    """``callback(signum)`` on SIGINT and SIGTERM in ``loop``; returns a function that removes them."""
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, callback, sig)

    def remove() -> None:
        for sig in STOP_SIGNALS:
            loop.remove_signal_handler(sig)

    return remove


def run_until_stop_signal(make: Callable[[], Coroutine[Any, Any, T]]) -> T | None:
    """Run the coroutine ``make()`` until it ends or SIGINT/SIGTERM cancels it (then None).

    The coroutine is created inside the running loop, so a signal that arrives before the loop
    starts leaves no coroutine "never awaited" behind.
    """

    async def main() -> T | None:
        task = asyncio.ensure_future(make())
        remove = add_stop_handlers(asyncio.get_running_loop(), lambda _sig: task.cancel())
        try:
            return await task
        except asyncio.CancelledError:
            if not task.cancelled():
                raise
            return None
        finally:
            remove()

    coro = main()
    with interrupt_on_stop_signals():  # until the loop's own handlers are in place
        try:
            return asyncio.run(coro)
        except KeyboardInterrupt:
            coro.close()  # a signal before the loop ran it: not "never awaited"
            return None
