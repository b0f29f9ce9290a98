"""racecar_hw.runtime.signals: SIGINT and SIGTERM stop a command whatever it inherited."""

from __future__ import annotations

import asyncio
import gc
import os
import signal
import warnings

from racecar_hw.runtime import signals


def test_a_signal_cancels_the_coroutine_and_its_clean_up_runs() -> None:
    ended = []

    async def serve() -> None:
        loop = asyncio.get_running_loop()
        loop.call_later(0.05, os.kill, os.getpid(), signal.SIGTERM)
        try:
            await asyncio.Event().wait()
        finally:
            ended.append(True)

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job inherits it
    try:
        assert signals.run_until_stop_signal(serve) is None
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # left as it was found
    finally:
        signal.signal(signal.SIGINT, previous)
    assert ended == [True]


def test_ctrl_c_before_the_loop_runs_leaves_nothing_never_awaited(monkeypatch) -> None:
    """An early Ctrl-C once printed "coroutine 'FakeVesc.serve' was never awaited"."""
    made = []

    async def serve() -> None:
        made.append(True)

    def interrupted_run(coro: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C while asyncio.run sets up its loop

    monkeypatch.setattr(signals.asyncio, "run", interrupted_run)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert signals.run_until_stop_signal(serve) is None
        gc.collect()
    assert not [w for w in caught if "never awaited" in str(w.message)]
    assert made == []
