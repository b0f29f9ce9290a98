"""Port clashes: one rule for every interface that listens (Zenoh, the Foxglove live view, the page).

The rule (docs/live-view.md, "Ports"): before anything starts, each port the configuration asks
for is tried (TCP, and the MAVLink link's UDP port). ``racecar-hw run`` and ``follow`` (the car:
clients expect the configured ports) refuse to start with one line naming the key whose port is
taken and the fix; ``racecar-hw sim`` (a demo on a laptop, perhaps the second on it) listens on a
free port instead and prints where.

:func:`port_taken` tries a port the way the servers bind it (``SO_REUSEADDR``, as asyncio and Zenoh
do, so a port in TIME_WAIT is free and one another program listens on is taken). :class:`Listener`
names one listening interface of a configuration; :func:`taken_message` is the one line of the
refusal. Nothing here keeps a socket open.

Trying a port and binding it are two moments: two sims started together both found 7447 free and
both bound it, and the second exited. :class:`PortLock` closes that gap between the processes of one
user on this machine: a sim holds it from trying its ports until it listens on them.
"""

from __future__ import annotations

import errno
import fcntl
import os
import socket
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

#: How long (s) a sim waits for another one on this machine to listen on the ports it took, before
#: it tries its own anyway (a sim starts listening within a second or two of taking them).
PORT_LOCK_WAIT_S = 10.0


@dataclass(frozen=True)
class Listener:
    """One port the configuration asks to listen on (TCP, or UDP where ``kind`` says so).

    ``key`` is the config key to fix (``foxglove.port``, ``zenoh.listen[0]``), ``what`` names the
    interface for a person (``the Foxglove live view``), ``host``/``port`` the address.
    """

    key: str
    what: str
    host: str
    port: int
    #: "tcp", or "udp" (the MAVLink link)
    kind: str = "tcp"

    def address(self) -> str:
        """``host:port``, with brackets around an IPv6 host."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"


def port_taken(host: str, port: int, kind: str = "tcp") -> bool:
    """Whether another socket listens on (or holds) ``host:port`` now. Port 0 is never taken; an
    address this machine does not have is not "taken" (the server's own bind reports that). A UDP
    port is tried with a plain bind, as the MAVLink link checks its own."""
    if port == 0:
        return False
    try:
        infos = socket.getaddrinfo(host, port, type=_TYPES[kind], flags=socket.AI_PASSIVE)
    except socket.gaierror:
        return False
    for family, sock_type, proto, _, address in infos[:1]:
        with socket.socket(family, sock_type, proto) as s:
            if kind == "tcp":
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(address)
            except OSError as err:
                return err.errno == errno.EADDRINUSE
    return False


def free_port(host: str, kind: str = "tcp") -> int:
    """A TCP (or UDP) port nobody uses on ``host`` now (the OS picks it)."""
    infos = socket.getaddrinfo(host, 0, type=_TYPES[kind], flags=socket.AI_PASSIVE)
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.bind(address)
        return int(s.getsockname()[1])


_TYPES = {"tcp": socket.SOCK_STREAM, "udp": socket.SOCK_DGRAM}


class PortLock:
    """The lock the sims of one user on this machine hold from trying their ports until they listen
    on them: ``flock`` on ``racecar-hw-ports-UID.lock`` in the temporary directory (not followed if
    it is a symbolic link), let go by :meth:`release` or when the process ends, however it ends."""

    def __init__(self, path: Path | None = None) -> None:
        default = Path(tempfile.gettempdir()) / f"racecar-hw-ports-{os.getuid()}.lock"
        self.path = path if path is not None else default
        self._fd: int | None = None

    def acquire(self, wait_s: float = PORT_LOCK_WAIT_S) -> bool:
        """Take the lock, waiting up to ``wait_s`` for another holder (blocking: before anything of
        the run starts); False when it could not be had (the sim goes on without it, as before)."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o600)
        except OSError:
            return False
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if time.monotonic() < deadline:
                    time.sleep(0.02)
                    continue
            except OSError:
                pass
            else:
                self._fd = fd
                return True
            os.close(fd)
            return False

    async def released(self) -> None:
        """:meth:`release`, as a task: added to a daemon, whose components' tasks start once its
        interfaces listen, it lets go then."""
        self.release()

    def release(self) -> None:
        """Let go of the lock (safe to call twice, or without it)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)  # closing the only descriptor of the open file lets go of the flock


def taken_message(listener: Listener) -> str:
    """The refusal's text (after the key): what is taken, the likely holder, and the fixes."""
    return (f"{listener.address()} is already in use, so {listener.what} cannot listen there: "
            f"another program holds it, such as a second racecar-hw (run or sim). Stop it, or set "
            f"{listener.key} to a free port (racecar-hw sim takes free ports by itself)")
