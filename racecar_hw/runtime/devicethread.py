"""A background thread with its own asyncio loop, where fake devices live.

Fake devices stand in for separate hardware, so they run outside the daemon's loop: a stalled
daemon cannot stall its fakes, and the fakes keep their own timing (scan periods, the VESC's
command timeout). Tests and ``racecar-hw sim`` use one :class:`DeviceThread` for all fakes.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


class DeviceThread:
    """Runs coroutines on a private event loop in a daemon thread. A context manager."""

    def __init__(self, name: str = "fake-hardware") -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._tasks: list[concurrent.futures.Future[Any]] = []

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()

    def start(self) -> DeviceThread:
        """Start the thread. Returns self."""
        self._thread.start()
        return self

    def spawn(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        """Run ``coro`` as a task in the device loop; it is cancelled on :meth:`stop`."""
        fut = asyncio.run_coroutine_threadsafe(coro, self.loop)
        self._tasks.append(fut)
        return fut

    def call(self, fn: Callable[..., T | Awaitable[T]], *args: Any, timeout: float = 10.0) -> T:
        """Call ``fn(*args)`` in the device loop and wait for its result (awaiting it if async)."""

        async def invoke() -> T:
            result = fn(*args)
            if asyncio.iscoroutine(result) or isinstance(result, asyncio.Future):
                return await result  # type: ignore[no-any-return]
            return result  # type: ignore[return-value]

        return asyncio.run_coroutine_threadsafe(invoke(), self.loop).result(timeout)

    def stop(self) -> None:
        """Cancel every spawned task, stop the loop and join the thread. Safe twice."""
        if not self._thread.is_alive():
            return
        for fut in self._tasks:
            fut.cancel()

        async def drain() -> None:
            tasks = [t for t in asyncio.all_tasks(self.loop) if t is not asyncio.current_task()]
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        asyncio.run_coroutine_threadsafe(drain(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10)
        self.loop.close()

    def __enter__(self) -> DeviceThread:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
