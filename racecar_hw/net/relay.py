"""A token check in front of the Foxglove SDK's server, for a bind outside loopback.

The SDK's WebSocket server has no authentication hook, so when ``foxglove.host`` is not loopback the
SDK listens on an ephemeral loopback port and this relay listens on ``host:port``: a WebSocket upgrade
must carry the token (``?token=...`` in the URL, which Foxglove and Lichtblick keep, or an
``Authorization: Bearer`` header), otherwise it gets 401 and never reaches the SDK. Accepted clients
are piped frame for frame to the SDK server with the subprotocol they asked for.

The relay runs in a thread of its own with its own event loop (aiohttp server and client), so relaying
scans to a remote viewer never runs in the control loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from typing import Any

import aiohttp
from aiohttp import web

from racecar_hw.net.auth import bearer, token_ok

log = logging.getLogger(__name__)

#: Largest frame relayed (bytes): a map or a scan is far smaller.
MAX_FRAME = 64 * 1024 * 1024


class TokenRelay:
    """Listens on ``host:port``; relays token-bearing WebSocket clients to ``127.0.0.1:upstream_port``."""

    def __init__(self, host: str, port: int, upstream_port: int, token: str) -> None:
        if not token:
            raise ValueError("a relay without a token would let anyone in")
        self.host = host
        self.requested_port = port
        self.upstream = f"ws://127.0.0.1:{upstream_port}/"
        self.token = token
        self.port = 0
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
        given = request.query.get("token") or bearer(request.headers.get("Authorization"))
        if not token_ok(given, self.token):
            self.refused += 1
            log.warning("foxglove: refused %s without the token (%d so far)", request.remote, self.refused)
            return web.Response(status=401, text="401: token required (add ?token=... to the URL)\n")
        asked = request.headers.get("Sec-WebSocket-Protocol", "")
        protocols = [p.strip() for p in asked.split(",") if p.strip()]
        async with aiohttp.ClientSession() as session:
            try:
                upstream = await session.ws_connect(self.upstream, protocols=protocols,
                                                    max_msg_size=MAX_FRAME)
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


async def _pump(source: Any, sink: Any) -> None:
    async for msg in source:
        if msg.type == aiohttp.WSMsgType.BINARY:
            await sink.send_bytes(msg.data)
        elif msg.type == aiohttp.WSMsgType.TEXT:
            await sink.send_str(msg.data)
        else:
            return
