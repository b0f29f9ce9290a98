"""The front door of the Foxglove live view: who may talk to the Foxglove SDK's server.

The SDK's WebSocket server checks neither a token nor a browser's ``Origin``. So it listens on an
ephemeral loopback port, with TLS and a certificate only this relay trusts
(:mod:`racecar_hw.net.loopback_tls`, so a web page that finds the port cannot use it either), and this
relay listens on ``foxglove.host:port`` and decides:

* with a token (required off loopback, optional on it): a WebSocket upgrade must carry it
  (``?token=...`` in the URL, which Foxglove and Lichtblick keep, or an ``Authorization: Bearer``
  header), otherwise 401;
* without one (loopback): a browser's upgrade must come from an allowed origin
  (:func:`~racecar_hw.net.auth.browser_origin_allowed`: Foxglove's web app, a page served by this
  machine, a desktop app, or ``foxglove.allowed_origins``), otherwise 403. Non-browser clients send no
  Origin and pass. This is what keeps a page of some other site, open in a browser on this machine
  (or on a laptop with an ``ssh -L`` tunnel to the car), from releasing the e-stop, arming or driving.

Accepted clients are piped frame for frame to the SDK server with the subprotocol they asked for;
refused ones never reach it. The relay runs in a thread of its own with its own event loop (aiohttp
server and client), niced like the sender thread, so relaying scans to a viewer never runs in the
control loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from typing import Any

import aiohttp
from aiohttp import web

from racecar_hw.base.loopback import is_loopback
from racecar_hw.net.auth import bearer, browser_origin_allowed, token_ok
from racecar_hw.net.loopback_tls import LOOPBACK, pinned_context
from racecar_hw.net.outbox import SENDER_NICE

log = logging.getLogger(__name__)

#: Largest frame relayed (bytes): a map or a scan is far smaller.
MAX_FRAME = 64 * 1024 * 1024


class Relay:
    """Listens on ``host:port``; relays the clients it lets in to ``wss://127.0.0.1:upstream_port``.

    ``upstream_cert`` is the SDK server's certificate (PEM), the only one trusted upstream; ``token``
    (may be empty on a loopback host) and ``allowed_origins`` (lower case, no trailing slash) decide
    who gets in, as the module says.
    """

    def __init__(self, host: str, port: int, upstream_port: int, upstream_cert: bytes, *, token: str = "",
                 allowed_origins: tuple[str, ...] = ()) -> None:
        if not token and not is_loopback(host):
            raise ValueError(f"a relay on {host} without a token would let anyone in")
        self.host = host
        self.requested_port = port
        self.upstream = f"wss://{LOOPBACK}:{upstream_port}/"
        self.upstream_ssl = pinned_context(upstream_cert)
        self.token = token
        self.allowed_origins = allowed_origins
        self.port = 0
        #: upgrades refused: without the token, or from a foreign origin
        self.refused = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._stopped: asyncio.Event | None = None

    def start(self, timeout_s: float = 10.0) -> None:
        """Start the thread and listen; raises OSError when the address cannot be had."""
        started = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            with contextlib.suppress(AttributeError, OSError):  # Linux: per thread, like the sender's
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                               os.getpriority(os.PRIO_PROCESS, 0) + SENDER_NICE)
            loop = self._loop = asyncio.new_event_loop()
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
        app = web.Application()
        app.router.add_get("/{tail:.*}", self._handle)
        runner = self._runner = web.AppRunner(app, handle_signals=False, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, self.host, self.requested_port)
        try:
            await site.start()
        except OSError as err:
            failure.append(err)
            started.set()
            await runner.cleanup()
            return
        server = site._server  # noqa: SLF001 - the only way to read the port bound for port 0
        self.port = server.sockets[0].getsockname()[1] if server is not None else self.requested_port
        started.set()
        await self._stopped.wait()
        await runner.cleanup()

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        refusal = self._refusal(request)
        if refusal is not None:
            return refusal
        asked = request.headers.get("Sec-WebSocket-Protocol", "")
        protocols = [p.strip() for p in asked.split(",") if p.strip()]
        async with aiohttp.ClientSession() as session:
            try:
                upstream = await session.ws_connect(self.upstream, protocols=protocols,
                                                    max_msg_size=MAX_FRAME, ssl=self.upstream_ssl)
            except aiohttp.ClientError as err:
                log.error("foxglove: relay cannot reach the server: %s", err)
                return web.Response(status=502, text="502: the Foxglove server is not answering\n")
            client = web.WebSocketResponse(protocols=[upstream.protocol] if upstream.protocol else (),
                                           max_msg_size=MAX_FRAME)
            await client.prepare(request)
            log.info("foxglove: relaying %s", request.remote)
            pumps = [asyncio.ensure_future(_pump(client, upstream)),
                     asyncio.ensure_future(_pump(upstream, client))]
            stopped = asyncio.ensure_future(self._stopped.wait()) if self._stopped else None
            await asyncio.wait([*pumps, *([stopped] if stopped else [])], return_when=asyncio.FIRST_COMPLETED)
            for task in [*pumps, *([stopped] if stopped else [])]:
                task.cancel()
            await upstream.close()
            await client.close()
            return client

    def _refusal(self, request: web.Request) -> web.Response | None:
        """The answer for a client that may not come in (401, 403), or None to let it in."""
        if self.token:
            given = request.query.get("token") or bearer(request.headers.get("Authorization"))
            if token_ok(given, self.token):
                return None
            self.refused += 1
            log.warning("foxglove: refused %s without the token (%d so far)", request.remote, self.refused)
            return web.Response(status=401, text="401: token required (add ?token=... to the URL)\n")
        origin = request.headers.get("Origin")
        if browser_origin_allowed(origin, request.headers.get("User-Agent"), self.allowed_origins):
            return None
        self.refused += 1
        log.warning("foxglove: refused a browser page from %r (%d so far): a page of another site must not "
                    "drive the car; if it is a viewer of yours, add its origin to foxglove.allowed_origins",
                    origin, self.refused)
        return web.Response(status=403, text=f"403: origin {origin} not allowed (foxglove.allowed_origins)\n")


async def _pump(source: Any, sink: Any) -> None:
    async for msg in source:
        if msg.type == aiohttp.WSMsgType.BINARY:
            await sink.send_bytes(msg.data)
        elif msg.type == aiohttp.WSMsgType.TEXT:
            await sink.send_str(msg.data)
        else:
            return
