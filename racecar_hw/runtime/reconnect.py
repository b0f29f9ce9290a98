"""A device driver that keeps its device: open, one session, close, and again after a backoff.

In the manner of python-can's ``BusABC``: the base class owns what every driver of a pluggable
device repeats (the reconnect loop, the exponential backoff, counting reconnects, remembering the
last error for the operator, logging a failure once rather than at every retry, stopping), and a
driver implements the device's steps:

* :meth:`ReconnectingDevice._session` (required): one connection's life, from the open link to its
  loss. It returns, or raises :class:`~racecar_hw.base.errors.DeviceError` when the link is lost.
* :meth:`ReconnectingDevice._open` (optional): open the link; a failure here is a failed attempt.
* :meth:`ReconnectingDevice._close` (optional): called after every session, also a failed one.
* The ``_on_*`` hooks: what to count and log when an attempt fails, a session starts or ends.

Two backoff policies, one per kind of device (:attr:`ReconnectingDevice.OPEN_PROVES_DEVICE`):

* the open proves the device (the VESC: a serial port that opens is its cable): the backoff
  restarts from ``backoff_min_s`` when the device opens, and a lost session is followed by a new
  attempt at once;
* the device proves itself in its session (a lidar: opening is part of its session, which streams
  scans): every session is followed by a pause; it doubles after each failed session and restarts
  from the minimum only after a session that ended without an error.

Either way the pause doubles from ``backoff_min_s`` up to ``backoff_max_s`` while attempts fail.
Nothing but :class:`asyncio.CancelledError` leaves :meth:`ReconnectingDevice.run`: an unexpected
exception in a step is logged with its traceback and the device is reconnected, so the stale-data
fail-safes downstream (the VESC's command timeout, the safety controller's scan age) act on a
dead device, not a dead task.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from abc import ABC, abstractmethod

from racecar_hw.base.errors import DeviceError

log = logging.getLogger(__name__)


class ReconnectingDevice(ABC):
    """The reconnect loop of one device; see the module docstring. Times in seconds."""

    #: The device's name in log lines.
    device_name = "device"
    #: True: the backoff restarts when :meth:`_open` succeeds and a lost session is retried at
    #: once; False: a pause follows every session, restarting from the minimum only after a
    #: session that ended without an error.
    OPEN_PROVES_DEVICE = True

    def __init__(self, backoff_min_s: float, backoff_max_s: float) -> None:
        self.backoff_min_s = backoff_min_s
        self.backoff_max_s = backoff_max_s
        #: why the device last failed (to open, or in a session), for the operator; None while it works
        self.last_error: str | None = None
        #: whether the device ever opened in this driver's life
        self.ever_connected = False
        self._stop = asyncio.Event()

    # --- the loop -----------------------------------------------------------------------------

    async def run(self) -> None:
        """Open, run a session, close; again after the backoff, until :meth:`stop_reconnecting` or
        cancellation."""
        backoff = self.backoff_min_s
        failures = 0
        while not self._stop.is_set():
            try:
                await self._open()
            except asyncio.CancelledError:
                raise
            except Exception as err:  # noqa: BLE001 - any failure to open is one failed attempt
                if isinstance(err, DeviceError):
                    failures += 1
                self._on_open_failed(err, failures)
                await self._pause(backoff)
                backoff = self._longer(backoff)
                continue
            failures = 0
            if self.OPEN_PROVES_DEVICE:
                backoff = self.backoff_min_s
            self._on_opened()
            self.ever_connected = True
            ended_cleanly = False
            try:
                await self._session()
                ended_cleanly = True
            except asyncio.CancelledError:
                self._on_cancelled()
                raise
            except DeviceError as err:
                self._on_session_lost(err)
            except Exception:  # noqa: BLE001 - a bug in a session: reconnect, never stop
                log.exception("%s session failed; reconnecting", self.device_name)
            finally:
                self._on_session_end()
                await self._close()
            if self.OPEN_PROVES_DEVICE:
                continue
            if ended_cleanly:
                backoff = self.backoff_min_s
            await self._pause(backoff)
            backoff = self._longer(backoff)

    def stop_reconnecting(self) -> None:
        """End :meth:`run` after the current session (a pause ends at once)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        """Whether :meth:`stop_reconnecting` was called."""
        return self._stop.is_set()

    def _longer(self, backoff: float) -> float:
        return min(backoff * 2.0, self.backoff_max_s)

    async def _pause(self, delay_s: float) -> None:
        """Wait ``delay_s`` or until :meth:`stop_reconnecting`."""
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._stop.wait(), delay_s)

    # --- the device's steps -------------------------------------------------------------------

    async def _open(self) -> None:  # noqa: B027 - optional step
        """Open the link (default: nothing; the session opens it)."""

    @abstractmethod
    async def _session(self) -> None:
        """One connection's life: return or raise DeviceError when the link is lost."""

    async def _close(self) -> None:  # noqa: B027 - optional step
        """Close the link after a session (called even when it failed)."""

    # --- hooks --------------------------------------------------------------------------------

    def _on_open_failed(self, err: Exception, failures: int) -> None:
        """An attempt to open failed (``failures``: DeviceErrors in a row): noted, logged once,
        then quietly; anything but a DeviceError is logged with its traceback."""
        if not isinstance(err, DeviceError):
            log.error("unexpected error opening the %s", self.device_name, exc_info=err)
            return
        self.last_error = str(err)
        (log.warning if failures == 1 else log.debug)("%s not available: %s", self.device_name, err)

    def _on_opened(self) -> None:
        """The device opened: a reconnect if it had opened before; the last error is over."""
        self.last_error = None

    def _on_session_lost(self, err: DeviceError) -> None:
        """A session ended with ``err`` (the link was lost)."""
        if not self._stop.is_set():
            log.warning("%s link lost: %s", self.device_name, err)

    def _on_session_end(self) -> None:  # noqa: B027 - optional hook
        """A session is over, whatever ended it (before :meth:`_close`)."""

    def _on_cancelled(self) -> None:  # noqa: B027 - optional hook
        """The task running :meth:`run` is being cancelled mid-session (leave the device safe)."""
