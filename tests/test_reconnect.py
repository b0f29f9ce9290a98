"""The one reconnect loop of the device drivers (racecar_hw.runtime.reconnect): both backoff
policies, counting, logging once, stopping, and never dying of a bug in a step. The VESC and lidar
drivers run it against their fakes in tests/test_vesc_driver.py and tests/test_*lidar*/scip tests;
here a scripted device makes every step's outcome (and the pause it asks for) exact."""

from __future__ import annotations

import asyncio
import logging

import pytest

from racecar_hw.base.errors import DeviceError, DeviceIOError
from racecar_hw.runtime.reconnect import ReconnectingDevice

MIN_S, MAX_S = 0.05, 0.2


class Scripted(ReconnectingDevice):
    """Each attempt takes the next outcome: "open-fails", "open-bug", "lost", "clean", "bug"."""

    device_name = "scripted"

    def __init__(self, script: list[str], proves: bool) -> None:
        super().__init__(MIN_S, MAX_S)
        self.OPEN_PROVES_DEVICE = proves
        self.script = list(script)
        self.pauses: list[float] = []
        self.steps: list[str] = []
        self.opened = 0
        self._now = ""

    async def _open(self) -> None:
        if not self.script:
            self.stop_reconnecting()
            raise DeviceIOError("script over")
        self._now = self.script.pop(0)
        self.steps.append(self._now)
        if self._now == "open-fails":
            raise DeviceIOError("no such port")
        if self._now == "open-bug":
            raise RuntimeError("a bug")

    def _on_opened(self) -> None:
        self.opened += 1
        super()._on_opened()

    async def _session(self) -> None:
        if self._now == "lost":
            raise DeviceIOError("unplugged")
        if self._now == "bug":
            raise ValueError("a bug in a session")

    async def _pause(self, delay_s: float) -> None:
        self.pauses.append(delay_s)


def _run(device: Scripted) -> Scripted:
    asyncio.run(asyncio.wait_for(device.run(), 10))
    return device


def test_a_device_its_open_proves_restarts_the_backoff_when_it_opens_and_reopens_at_once(caplog):
    caplog.set_level(logging.DEBUG, "racecar_hw.runtime.reconnect")
    device = _run(Scripted(["open-fails", "open-fails", "open-fails", "open-fails", "lost",
                            "open-fails", "bug", "clean"], proves=True))
    # doubling to the cap, then from the minimum again after the open; a lost session: no pause
    assert device.pauses[:5] == [MIN_S, 2 * MIN_S, 4 * MIN_S, MAX_S, MIN_S]
    assert device.opened == 3 and device.ever_connected
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings.count("scripted not available: no such port") == 2  # once per run of failures
    assert "scripted link lost: unplugged" in warnings
    assert any(r.levelno == logging.ERROR and "session failed" in r.getMessage() for r in caplog.records)


def test_a_device_that_proves_itself_in_its_session_pauses_after_every_session():
    device = _run(Scripted(["lost", "lost", "lost", "clean", "lost"], proves=False))
    assert device.pauses[:5] == [MIN_S, 2 * MIN_S, 4 * MIN_S, MIN_S, 2 * MIN_S]


def test_an_unexpected_error_in_opening_is_not_the_end_and_keeps_the_last_error():
    device = _run(Scripted(["open-fails", "open-bug"], proves=True))
    assert device.last_error == "script over"
    assert device.pauses[:2] == [MIN_S, 2 * MIN_S]


def test_stop_ends_the_loop_and_a_cancelled_session_calls_the_hook():
    class Endless(Scripted):
        cancelled = 0

        async def _session(self) -> None:
            await asyncio.sleep(3600)

        def _on_cancelled(self) -> None:
            self.cancelled += 1

    async def scenario() -> Endless:
        device = Endless(["clean"], proves=True)
        task = asyncio.create_task(device.run())
        while device.opened == 0:
            await asyncio.sleep(0.001)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return device

    assert asyncio.run(scenario()).cancelled == 1


def test_a_device_error_is_a_device_error():
    assert issubclass(DeviceIOError, DeviceError)
