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
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass


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


def taken_message(listener: Listener) -> str:
    """The refusal's text (after the key): what is taken, the likely holder, and the fixes."""
    return (f"{listener.address()} is already in use, so {listener.what} cannot listen there: "
            f"another program holds it, such as a second racecar-hw (run or sim). Stop it, or set "
            f"{listener.key} to a free port (racecar-hw sim takes free ports by itself)")
