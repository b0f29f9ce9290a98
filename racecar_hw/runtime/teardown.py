"""Shutdown steps that never stop the shutdown, for :class:`contextlib.AsyncExitStack` callbacks.

The daemon pushes the undoing of each start-up step on one exit stack, so shutdown runs them in the
reverse order of start-up; a step that fails is logged and the next one still runs (the brake was
written long before, by the VESC driver's own shutdown).
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable
from typing import Any

log = logging.getLogger(__name__)


async def quietly(fn: Callable[..., Awaitable[Any]], *args: Any) -> None:
    """Await ``fn(*args)``; an exception is logged (debug), not raised."""
    try:
        await fn(*args)
    except Exception as err:
        log.debug("shutdown step %r failed: %r", fn, err)


def quietly_sync(fn: Callable[..., Any], *args: Any) -> None:
    """Call ``fn(*args)``; an exception is logged (debug), not raised."""
    try:
        fn(*args)
    except Exception as err:
        log.debug("shutdown step %r failed: %r", fn, err)
