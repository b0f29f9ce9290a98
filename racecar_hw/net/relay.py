"""The front door of the Foxglove live view: who may talk to the Foxglove SDK's server.

The SDK's WebSocket server checks neither a token nor a browser's ``Origin``. So it listens on an
ephemeral loopback port, with TLS and a certificate only this relay trusts
(:mod:`racecar_hw.net.loopback_tls`, so a web page that finds the port cannot use it either), and this
relay listens on ``foxglove.host:port`` and decides on each connection's first request:

* with a token (required off loopback, optional on it): a WebSocket upgrade must carry it
  (``?token=...`` in the URL, which Foxglove and Lichtblick keep, or an ``Authorization: Bearer``
  header), otherwise 401;
* without one (loopback): a browser's upgrade must come from an allowed origin
  (:func:`~racecar_hw.net.auth.browser_origin_allowed`: Foxglove's web app, a page served by this
  machine, a desktop app, or ``foxglove.allowed_origins``), otherwise 403. Non-browser clients send no
  Origin and pass. This is what keeps a page of some other site, open in a browser on this machine
  (or on a laptop with an ``ssh -L`` tunnel to the car), from releasing the e-stop, arming or driving.

A request that is not a WebSocket upgrade gets 400. Every refusal is counted per source and reason
(surface ``"relay"``) in :class:`~racecar_hw.runtime.refusals.Refusals`, which logs summaries. Every
connection passes a :class:`~racecar_hw.net.gate.ConnectionGate` before this relay reads it: a cap on
connections, a timeout for the request head, and one for idleness (nothing moved either way).

An admitted client's request goes to the SDK's server as it came, and from then on the relay copies
bytes both ways without reading them: the WebSocket handshake and the subprotocol are the SDK's and the
client's business. Refused clients never reach it. The relay runs in a thread of its own with its own
event loop, niced like the sender thread, so relaying scans to a viewer never runs in the control loop.

Why bytes and not WebSocket messages: a WebSocket proxy (aiohttp's, as before) parses and re-frames
every message in Python, about 3.5 % of a core for one viewer of every channel (430 messages a
second), and holds the GIL the control loop wants while it does; copying what arrives costs one read
and one write per burst, the TLS work in OpenSSL. The HTTP request head is read here with the standard
library (:func:`http.client.parse_headers`): a server framework would want to answer the request
itself, and this relay must hand the connection over instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import io
import logging
import os
import ssl
import threading
from collections.abc import Callable
from dataclasses import dataclass
from http import HTTPStatus
from urllib.parse import parse_qs, urlsplit

from racecar_hw.base.loopback import is_loopback
from racecar_hw.net.auth import bearer, browser_origin_allowed, token_ok
from racecar_hw.net.gate import ConnectionGate, ConnectionLimits, quiet_accept_errors
from racecar_hw.net.loopback_tls import LOOPBACK, pinned_context
from racecar_hw.runtime.outbox import SENDER_NICE
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

#: Largest request head read from a client (bytes); a WebSocket upgrade is well under 2 KiB.
MAX_HEAD = 16 * 1024
#: The SDK's server must accept the relay's connection within this (seconds).
UPSTREAM_TIMEOUT_S = 10.0
#: Refused browser origins (with their User-Agent) named in the log, each once; the rest are counted.
MAX_ORIGINS_NAMED = 16
#: Largest read copied at once (bytes).
CHUNK = 256 * 1024


@dataclass(frozen=True)
class _Request:
    """What the relay reads of a client's first request."""

    method: str
    target: str
    headers: http.client.HTTPMessage

    @property
    def token(self) -> str | None:
        """The token from ``?token=`` or an ``Authorization: Bearer`` header, or None."""
        given = parse_qs(urlsplit(self.target).query).get("token")
        return given[0] if given else bearer(self.headers.get("Authorization"))

    @property
    def is_websocket_upgrade(self) -> bool:
        return self.method == "GET" and (self.headers.get("Upgrade") or "").strip().lower() == "websocket"


def _parse(head: bytes) -> _Request | None:
    """The request in ``head`` (request line and headers, up to the blank line), or None if malformed."""
    line, _, rest = head.partition(b"\r\n")
    try:
        method, target, version = line.decode("ascii").split(" ")
        headers = http.client.parse_headers(io.BytesIO(rest))
    except (ValueError, UnicodeDecodeError, http.client.HTTPException):
        return None
    if not version.startswith("HTTP/1."):
        return None
    return _Request(method, target, headers)


class Relay:
    """Listens on ``host:port``; relays the clients it lets in to ``wss://127.0.0.1:upstream_port``.

    ``upstream_cert`` is the SDK server's certificate (PEM), the only one trusted upstream; ``token``
    (may be empty on a loopback host) and ``allowed_origins`` (lower case, no trailing slash) decide
    who gets in, as the module says. ``limits`` caps the connections and times out their heads and
    idleness (:mod:`racecar_hw.net.gate`); ``refusals`` counts what was refused (surface ``"relay"``).
    """

    def __init__(self, host: str, port: int, upstream_port: int, upstream_cert: bytes, *, token: str = "",
                 allowed_origins: tuple[str, ...] = (), limits: ConnectionLimits | None = None,
                 refusals: Refusals | None = None) -> None:
        if not token and not is_loopback(host):
            raise ValueError(f"a relay on {host} without a token would let anyone in")
        self.host = host
        self.requested_port = port
        self.upstream_port = upstream_port
        self.upstream_ssl = pinned_context(upstream_cert)
        self.token = token
        self.allowed_origins = allowed_origins
        self.port = 0
        #: requests refused: without the token, from a foreign origin, or not a WebSocket upgrade
        self.refused = 0
        self.refusals = refusals if refusals is not None else Refusals()
        self.gate = ConnectionGate("relay", limits or ConnectionLimits(), self.refusals)
        self._origins_named: set[tuple[str | None, str]] = set()  # (Origin, User-Agent) named in the log
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stopped: asyncio.Event | None = None
        self._clients: set[asyncio.Task[None]] = set()

    def start(self, timeout_s: float = 10.0) -> None:
        """Start the thread and listen; raises OSError when the address cannot be had."""
        started = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            with contextlib.suppress(AttributeError, OSError):  # Linux: per thread, like the sender's
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                               os.getpriority(os.PRIO_PROCESS, 0) + SENDER_NICE)
            loop = self._loop = asyncio.new_event_loop()
            quiet_accept_errors(loop, self.refusals)
            try:
                loop.run_until_complete(self._serve(started, failure))
            finally:
                loop.close()

        self._thread = threading.Thread(target=run, name="foxglove-relay", daemon=True)
        self._thread.start()
        if not started.wait(timeout_s):
            raise OSError(f"the relay did not start within {timeout_s} s")
        if failure:
            self._thread.join(timeout_s)
            raise OSError(str(failure[0])) from failure[0]

    def stop(self) -> None:
        """Close every connection and stop listening (safe to call twice)."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or self._stopped is None:
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(self._stopped.set)
        thread.join(5.0)
        self._thread = None

    async def _serve(self, started: threading.Event, failure: list[BaseException]) -> None:
        self._stopped = asyncio.Event()
        loop = asyncio.get_running_loop()

        def streams() -> asyncio.StreamReaderProtocol:  # what asyncio.start_server makes for each client
            return asyncio.StreamReaderProtocol(asyncio.StreamReader(limit=MAX_HEAD, loop=loop), self._client,
                                                loop=loop)

        try:  # every connection passes the gate first (the cap and the timeouts: see net.gate)
            server = await self.gate.serve(streams, self.host, self.requested_port)
        except OSError as err:
            failure.append(err)
            started.set()
            return
        self.port = server.sockets[0].getsockname()[1] if server.sockets else self.requested_port
        started.set()
        await self._stopped.wait()
        self.gate.close()
        server.close()
        for task in list(self._clients):
            task.cancel()
        await asyncio.gather(*self._clients, return_exceptions=True)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._clients.add(task)
        try:
            await self._relay(reader, writer)
        except asyncio.CancelledError:
            pass  # the relay is stopping; a stream callback that raises it logs a traceback on 3.11
        finally:
            writer.close()
            if task is not None:
                self._clients.discard(task)

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        remote = peer[0] if isinstance(peer, tuple) else str(peer)
        try:  # the gate closes a connection whose head is late
            head = await reader.readuntil(b"\r\n\r\n")
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, OSError):
            return
        request = _parse(head)
        if request is None or not request.is_websocket_upgrade:
            self.refused += 1
            self.refusals.note("relay", remote, "not a WebSocket upgrade (400)")
            await _answer(writer, HTTPStatus.BAD_REQUEST, "400: a WebSocket (foxglove.sdk.v1) port")
            return
        refusal = self._refusal(request, remote)
        if refusal is not None:
            await _answer(writer, *refusal)
            return
        try:
            up_reader, up_writer = await asyncio.wait_for(
                asyncio.open_connection(LOOPBACK, self.upstream_port, ssl=self.upstream_ssl, limit=CHUNK),
                UPSTREAM_TIMEOUT_S)
        except (OSError, ssl.SSLError, asyncio.TimeoutError) as err:
            log.error("foxglove: relay cannot reach the server: %s", err or type(err).__name__)
            await _answer(writer, HTTPStatus.BAD_GATEWAY, "502: the Foxglove server is not answering")
            return
        log.info("foxglove: relaying %s", remote)
        transport, gate = writer.transport, self.gate
        try:
            up_writer.write(head)
            await _splice(reader, writer, up_reader, up_writer, lambda: gate.touch(transport))
        finally:
            up_writer.close()

    def _refusal(self, request: _Request, remote: str) -> tuple[HTTPStatus, str] | None:
        """The answer for a client that may not come in (401, 403), or None to let it in."""
        if self.token:
            if token_ok(request.token, self.token):
                return None
            self.refused += 1
            self.refusals.note("relay", remote, "upgrade without the token (401)")
            return HTTPStatus.UNAUTHORIZED, "401: token required (add ?token=... to the URL)"
        origin = request.headers.get("Origin")
        if browser_origin_allowed(origin, request.headers.get("User-Agent"), self.allowed_origins):
            return None
        self.refused += 1
        self.refusals.note("relay", remote, "browser page of a foreign origin (403)")
        agent = (request.headers.get("User-Agent") or "")[:200]
        if len(self._origins_named) < MAX_ORIGINS_NAMED and (origin, agent) not in self._origins_named:
            # the operator needs the origin (and the client: a desktop app that changed its User-Agent)
            # to allow a viewer of theirs; named once each, a few at most (an attacker chooses both)
            self._origins_named.add((origin, agent))
            log.warning("foxglove: refused a browser page from %r: a page of another site must not drive "
                        "the car; if it is a viewer of yours, add its origin to foxglove.allowed_origins",
                        origin[:100] if origin else origin)
        return HTTPStatus.FORBIDDEN, f"403: origin {origin} not allowed (foxglove.allowed_origins)"


async def _answer(writer: asyncio.StreamWriter, status: HTTPStatus, text: str) -> None:
    """Send a plain-text HTTP answer; the connection closes after it."""
    body = (text + "\n").encode()
    writer.write(f"HTTP/1.1 {status.value} {status.phrase}\r\nContent-Type: text/plain; charset=utf-8\r\n"
                 f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode() + body)
    with contextlib.suppress(OSError):
        await writer.drain()


async def _copy(source: asyncio.StreamReader, sink: asyncio.StreamWriter,
                moved: Callable[[], None] | None = None) -> None:
    while data := await source.read(CHUNK):
        sink.write(data)
        await sink.drain()
        if moved is not None:
            moved()


async def _splice(a_reader: asyncio.StreamReader, a_writer: asyncio.StreamWriter,
                  b_reader: asyncio.StreamReader, b_writer: asyncio.StreamWriter,
                  to_a: Callable[[], None] | None = None) -> None:
    """Copy bytes a to b and b to a until either side ends (or fails); then stop both directions.

    ``to_a`` is called after each write to a that a took (the client's idle clock)."""
    pumps = [asyncio.ensure_future(_copy(a_reader, b_writer)),
             asyncio.ensure_future(_copy(b_reader, a_writer, to_a))]
    try:
        await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for pump in pumps:
            pump.cancel()
        await asyncio.gather(*pumps, return_exceptions=True)
