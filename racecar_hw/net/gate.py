"""A cap on a listening socket's connections, with a timeout for the request head and for idleness.

A status page or a relay must not let its clients take the process's file descriptors (the lidar's
reconnect needs one) or the event loop: 1,100 half-open connections under a 1,024-file limit once
kept the lidar away for 11 s. :class:`ConnectionGate` wraps the protocol factory given to
``loop.create_server``; every accepted connection passes it first:

* at most ``max_connections`` are open at once. A new connection beyond the cap closes the oldest one
  that has not sent its whole first request head yet (a half-open connection: a slow client or an
  attack; a browser sends its head in one packet), so a flood of half-open connections cannot lock a
  new browser out; when every open connection has sent its head (pages and viewers in use), the new
  one is closed at once;
* a connection that has not sent its first request head (up to the blank line, ``\\r\\n\\r\\n``)
  ``head_timeout_s`` after it opened is closed;
* a connection on which nothing moved for ``idle_timeout_s`` is closed: received bytes count, and
  what the owner reports with :meth:`ConnectionGate.touch` (the relay's copies to the client).

Each closed connection is counted in :class:`~racecar_hw.runtime.refusals.Refusals` under the
gate's surface, the client's address and the reason, which logs one line per (address, reason) per
interval, not one per connection.

Why a wrapper and not the server's own settings: aiohttp has no limit on connections and never times
out a request head that is not finished (its ``keepalive_timeout`` only runs between requests), and
the relay reads its heads with asyncio streams. The wrapper is an :class:`asyncio.Protocol` that
decides in ``connection_made`` and then hands every call on to the server's own protocol (aiohttp's
request handler, an asyncio stream protocol), which writes to the transport itself: no byte is
parsed here except the search for the head's end, and a refused connection never reaches the server.
The timeouts are checked by one timer per gate (every ``CHECK_PERIOD_S`` at most), not one per
connection.

:func:`quiet_accept_errors` turns asyncio's traceback for an ``accept()`` that failed for lack of
file descriptors (asyncio waits a second and accepts again) into a counted, rate-limited line.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from racecar_hw.base.params import param
from racecar_hw.runtime.refusals import Refusals

#: Connections accepted per wake-up of the event loop (asyncio takes it from ``backlog``): each costs
#: the loop some 50-100 us, and a newcomer's head must be read before ``max_connections`` later
#: arrivals could close it as the oldest unfinished one.
ACCEPT_BATCH = 8
#: Connections the kernel keeps waiting for accept() (Linux caps it at net.core.somaxconn): a burst
#: waits there instead of having its SYNs dropped, which would cost a browser a 1 s retry.
LISTEN_QUEUE = 1024
#: The longest time between two checks of the timeouts (s).
CHECK_PERIOD_S = 1.0
#: The end of an HTTP/1.x request head.
HEAD_END = b"\r\n\r\n"
#: asyncio's message when ``accept()`` fails with EMFILE, ENFILE, ENOBUFS or ENOMEM.
ACCEPT_OUT_OF_RESOURCES = "socket.accept() out of system resource"

#: Reasons a connection is closed, as counted and logged.
TOO_MANY = "too many connections, closed at once"
EVICTED = "too many connections: closed the oldest unfinished request"
HEAD_LATE = "request head not finished in time"
IDLE = "idle connection closed"


@dataclass(frozen=True)
class ConnectionLimits:
    """What one listening socket allows: connections at once, seconds for the head, seconds idle."""

    max_connections: int = 32
    head_timeout_s: float = 5.0
    idle_timeout_s: float = 60.0


def max_connections_param() -> Any:
    """The ``max_connections`` parameter of a config section whose server has a gate."""
    return param(ConnectionLimits.max_connections,
                 "connections open at once at most; beyond it the oldest one that has not finished "
                 "its request is closed, else the new one", min=1, max=1000)


def head_timeout_param() -> Any:
    """The ``head_timeout_s`` parameter of a config section whose server has a gate."""
    return param(ConnectionLimits.head_timeout_s, "a connection must send its request head within this",
                 unit="s", min=0.5, max=60.0)


def idle_timeout_param(rest: str) -> Any:
    """The ``idle_timeout_s`` parameter of a config section whose server has a gate; ``rest``: its
    description after "a connection" (what counts as idle there, and what keeps a client alive)."""
    return param(ConnectionLimits.idle_timeout_s, f"a connection {rest}", unit="s",
                 min=10.0, max=3600.0)


class GatedServerParams:
    """For a config section with the three parameters above: :meth:`limits`."""

    max_connections: int
    head_timeout_s: float
    idle_timeout_s: float

    def limits(self) -> ConnectionLimits:
        """The section's connection cap and timeouts."""
        return ConnectionLimits(self.max_connections, self.head_timeout_s, self.idle_timeout_s)


class _Conn:
    """One admitted connection: its transport, its peer, when it opened and last moved (s)."""

    __slots__ = ("head_done", "last", "opened", "source", "tail", "transport")

    def __init__(self, transport: asyncio.BaseTransport, source: str, now: float) -> None:
        self.transport = transport
        self.source = source
        self.opened = now
        self.last = now
        self.head_done = False
        self.tail = b""  # the last bytes of an unfinished head: its end may span two reads


class ConnectionGate:
    """The cap and the timeouts of one listening socket; ``surface`` names it for the counts.

    Used from the event loop that serves the socket only (:meth:`start` there).
    """

    def __init__(self, surface: str, limits: ConnectionLimits, refusals: Refusals, *,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.surface = surface
        self.limits = limits
        self.refusals = refusals
        self._clock = clock
        self._conns: dict[asyncio.BaseTransport, _Conn] = {}  # in the order they opened
        self._timer: asyncio.TimerHandle | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._period = min(CHECK_PERIOD_S, limits.head_timeout_s / 4, limits.idle_timeout_s / 4)
        #: connections admitted and closed by the gate, since the start
        self.admitted = 0
        self.closed = 0

    @property
    def active(self) -> int:
        """Connections open now."""
        return len(self._conns)

    def wrap(self, factory: Callable[[], asyncio.BaseProtocol]) -> Callable[[], asyncio.Protocol]:
        """A protocol factory for ``loop.create_server``: the gate, then ``factory``'s protocol."""
        return lambda: _Guarded(self, factory)

    async def serve(self, factory: Callable[[], asyncio.BaseProtocol], host: str,
                    port: int) -> asyncio.Server:
        """Listen on ``host:port`` with every connection through the gate, and start checking.

        asyncio uses its ``backlog`` for both the kernel's queue and the connections it accepts per
        wake-up; we want a long queue and short bursts, so the queue is lengthened afterwards (a second
        ``listen()`` on a listening socket only changes its backlog). Raises OSError like
        ``create_server``.
        """
        loop = asyncio.get_running_loop()
        server = await loop.create_server(self.wrap(factory), host, port, backlog=ACCEPT_BATCH)
        for listening in server.sockets:
            with contextlib.suppress(OSError), socket.socket(fileno=os.dup(listening.fileno())) as same:
                same.listen(LISTEN_QUEUE)
        self.start(loop)
        return server

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Check the timeouts from now on, in ``loop``."""
        self._loop = loop
        self._timer = loop.call_later(self._period, self._check)

    def close(self) -> None:
        """Stop checking (the owner closes its connections)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def touch(self, transport: asyncio.BaseTransport) -> None:
        """Something moved on ``transport`` that the gate does not see (bytes sent to the client)."""
        conn = self._conns.get(transport)
        if conn is not None:
            conn.last = self._clock()

    # --- the wrapper's calls ----------------------------------------------------------------------

    def _admit(self, transport: asyncio.BaseTransport) -> _Conn | None:
        source = _source(transport)
        if len(self._conns) >= self.limits.max_connections:
            oldest = next((c for c in self._conns.values() if not c.head_done), None)
            if oldest is None:
                self._close(transport, source, TOO_MANY)
                return None
            self._drop(oldest, EVICTED)
        conn = self._conns[transport] = _Conn(transport, source, self._clock())
        self.admitted += 1
        return conn

    def _release(self, conn: _Conn) -> None:
        self._conns.pop(conn.transport, None)

    def _drop(self, conn: _Conn, reason: str) -> None:
        self._conns.pop(conn.transport, None)
        self._close(conn.transport, conn.source, reason)

    def _close(self, transport: asyncio.BaseTransport, source: str, reason: str) -> None:
        self.closed += 1
        abort = getattr(transport, "abort", None)
        (abort or transport.close)()  # at once, without a goodbye: nothing is owed
        self.refusals.note(self.surface, source, reason)

    def _check(self) -> None:
        if self._loop is not None and self._timer is not None:  # the next check first, come what may
            self._timer = self._loop.call_later(self._period, self._check)
        now = self._clock()
        head_s, idle_s = self.limits.head_timeout_s, self.limits.idle_timeout_s
        for conn in list(self._conns.values()):
            if not conn.head_done and now - conn.opened >= head_s:
                self._drop(conn, HEAD_LATE)
            elif now - conn.last >= idle_s:
                self._drop(conn, IDLE)


class _Guarded(asyncio.Protocol):
    """The gate in front of one connection's own protocol (created only once admitted)."""

    __slots__ = ("_conn", "_factory", "_gate", "_inner")

    def __init__(self, gate: ConnectionGate, factory: Callable[[], asyncio.BaseProtocol]) -> None:
        self._gate = gate
        self._factory = factory
        self._inner: Any = None
        self._conn: _Conn | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        conn = self._gate._admit(transport)  # noqa: SLF001 - the gate's own wrapper
        if conn is None:
            return
        self._conn = conn
        self._inner = self._factory()
        self._inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        conn = self._conn
        if conn is None:
            return  # refused or closed by the gate: nothing more reaches the server
        conn.last = self._gate._clock()  # noqa: SLF001
        if not conn.head_done:
            conn.head_done, conn.tail = head_end(conn.tail, data)
        self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self._inner.eof_received() if self._inner is not None else None

    def connection_lost(self, exc: Exception | None) -> None:
        if self._conn is not None:
            self._gate._release(self._conn)  # noqa: SLF001
        if self._inner is not None:
            self._inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self._inner is not None:
            self._inner.pause_writing()

    def resume_writing(self) -> None:
        if self._inner is not None:
            self._inner.resume_writing()


def head_end(tail: bytes, data: bytes) -> tuple[bool, bytes]:
    """Whether a request head ends in ``data``, given the ``tail`` kept from the reads before it.

    Returns (ended, the tail to keep for the next read): the head's end, ``\r\n\r\n``, may be split
    across reads, so the last three bytes are kept, never more. Blank lines before the request line
    are not a head (HTTP servers skip them and wait on): until a byte other than CR or LF comes the
    tail stays empty, so a connection sending only line ends stays unfinished, evictable and bound
    by the head timeout.
    """
    if not tail:
        data = data.lstrip(b"\r\n")
        if not data:
            return False, b""
    seen = tail + data
    if HEAD_END in seen:
        return True, b""
    return False, seen[-(len(HEAD_END) - 1):]


def _source(transport: asyncio.BaseTransport) -> str:
    """The peer's address without its port: one source per client machine in the counts."""
    peer = transport.get_extra_info("peername")
    if isinstance(peer, tuple) and peer:
        return str(peer[0])
    return str(peer) if peer else "unknown"


def quiet_accept_errors(loop: asyncio.AbstractEventLoop, refusals: Refusals) -> Callable[[], None]:
    """Count ``accept()`` failures for lack of descriptors in ``refusals`` instead of a traceback each.

    asyncio itself stops accepting on that socket for a second and then tries again; every other
    error goes to the handler that was set before. Returns a function that puts that one back.
    """
    previous = loop.get_exception_handler()

    def handler(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        if context.get("message") == ACCEPT_OUT_OF_RESOURCES:
            sock, err = context.get("socket"), context.get("exception")
            try:
                where = "%s:%s" % sock.getsockname()[:2] if sock is not None else "a listening socket"  # noqa: UP031
            except (OSError, TypeError, ValueError):
                where = "a listening socket"
            reason = f"accept() failed ({getattr(err, 'strerror', None) or err}); trying again in 1 s"
            refusals.note("accept", where, reason)
            return
        if previous is not None:
            previous(loop, context)
        else:
            loop.default_exception_handler(context)

    loop.set_exception_handler(handler)
    return lambda: loop.set_exception_handler(previous)
