"""The systemd notify protocol (``sd_notify``), for ``Type=notify`` with a watchdog.

systemd hands the service a unix datagram socket in ``$NOTIFY_SOCKET`` (a path, or a Linux
abstract-namespace name when it starts with ``@``) and, with ``WatchdogSec=``, the watchdog period
in ``$WATCHDOG_USEC`` (microseconds) for the process ``$WATCHDOG_PID``. Each datagram holds
newline-separated ``KEY=VALUE`` assignments: ``READY=1``, ``WATCHDOG=1``, ``STOPPING=1``,
``STATUS=...``.

Outside systemd (no ``$NOTIFY_SOCKET``) every call is a no-op. Sends never block and never raise:
a failure is counted in :attr:`Notifier.send_errors` and logged once per distinct error, so a
notifier can be called from the control loop. Ping :meth:`Notifier.watchdog` at half
:meth:`Notifier.watchdog_interval_s` (``watchdog_loop`` does so while a health check passes).
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)


class Notifier:
    """Sends state changes to systemd over ``$NOTIFY_SOCKET``; a no-op when there is none."""

    def __init__(self, address: str | None, watchdog_usec: int | None = None) -> None:
        """``address``: the socket path, ``@name`` for the abstract namespace, or None (no-op).

        ``watchdog_usec``: the watchdog period this process must meet, or None for no watchdog.
        """
        self.address = address or None
        self._watchdog_usec = watchdog_usec if watchdog_usec and watchdog_usec > 0 else None
        self._sock: socket.socket | None = None
        self.sent = 0
        self.send_errors = 0
        self.last_error: str | None = None

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, pid: int | None = None) -> Notifier:
        """A notifier for the socket and watchdog systemd passed to this process (``os.environ``).

        The watchdog applies only when ``$WATCHDOG_PID`` is absent or names this process (``pid``,
        by default ``os.getpid()``); a malformed ``$WATCHDOG_USEC`` means no watchdog.
        """
        env = os.environ if environ is None else environ
        return cls(env.get("NOTIFY_SOCKET") or None, _watchdog_usec(env, os.getpid() if pid is None else pid))

    @property
    def enabled(self) -> bool:
        """Whether a notify socket was given (the process runs under systemd)."""
        return self.address is not None

    def watchdog_interval_s(self) -> float | None:
        """The watchdog period in seconds systemd enforces, or None when there is no watchdog."""
        return None if self._watchdog_usec is None else self._watchdog_usec / 1_000_000

    def ready(self, status: str | None = None) -> bool:
        """Tell systemd start-up is complete (``READY=1``), optionally with a status line."""
        return self.notify("READY=1", *([_status(status)] if status is not None else []))

    def watchdog(self) -> bool:
        """Keep the watchdog from firing (``WATCHDOG=1``); call at half the interval."""
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        """Tell systemd the service is shutting down (``STOPPING=1``)."""
        return self.notify("STOPPING=1", *([_status(status)] if status is not None else []))

    def status(self, text: str) -> bool:
        """Set the one-line status ``systemctl status`` shows (``STATUS=...``)."""
        return self.notify(_status(text))

    def notify(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` assignments in one datagram; True when sent, False when not (no raise)."""
        if self.address is None:
            return False
        try:
            sock = self._socket()
            sock.sendto("\n".join(assignments).encode("utf-8"), _sockaddr(self.address))
        except (OSError, ValueError) as err:
            self.send_errors += 1
            message = f"{type(err).__name__}: {err}"
            if message != self.last_error:
                log.warning("systemd notify to %s failed: %s", self.address, message)
            self.last_error = message
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        """Close the socket; safe to call twice. Later calls reopen it."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _socket(self) -> socket.socket:
        if self._sock is None:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            sock.setblocking(False)
            self._sock = sock
        return self._sock


async def watchdog_loop(notifier: Notifier, healthy: Callable[[], bool] = lambda: True) -> None:
    """Ping the watchdog at half its interval while ``healthy()`` holds; returns at once if none.

    When ``healthy()`` is false the ping is skipped, so systemd restarts a wedged daemon. Runs until
    cancelled.
    """
    interval = notifier.watchdog_interval_s()
    if not notifier.enabled or interval is None:
        return
    period = interval / 2.0
    loop = asyncio.get_running_loop()
    deadline = loop.time()
    while True:
        try:
            ok = healthy()
        except Exception:
            log.exception("watchdog health check failed")
            ok = False
        if ok:
            notifier.watchdog()
        deadline += period
        now = loop.time()
        if deadline < now:
            deadline = now
        await asyncio.sleep(deadline - now)


def _status(text: str) -> str:
    # one datagram line per assignment: a newline would start a new KEY=VALUE
    return "STATUS=" + " ".join(text.splitlines())


def _sockaddr(address: str) -> str | bytes:
    if address.startswith("@"):
        return b"\0" + address[1:].encode("utf-8")
    return address


def _watchdog_usec(env: Mapping[str, str], pid: int) -> int | None:
    usec_text = env.get("WATCHDOG_USEC")
    if not usec_text:
        return None
    pid_text = env.get("WATCHDOG_PID")
    if pid_text:
        try:
            if int(pid_text) != pid:
                return None
        except ValueError:
            return None
    try:
        usec = int(usec_text)
    except ValueError:
        log.warning("ignoring malformed WATCHDOG_USEC=%r", usec_text)
        return None
    return usec if usec > 0 else None
