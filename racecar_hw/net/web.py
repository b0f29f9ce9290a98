"""The status page with an e-stop: a small aiohttp app inside the daemon's event loop.

One page (``static/status.html``) made for a phone: speeds, steering, battery, the active source,
arming, the safety state and its reason, link health and a top-down view of the scan with the swept
footprint, pushed over a WebSocket at ``push_rate_hz``. A big E-STOP button latches the mux e-stop;
releasing it is a separate, deliberate action (press and hold on the page).

Endpoints (each needs the token when one is set: ``?token=`` or ``Authorization: Bearer``):

* ``GET /``: the page; ``GET /ws``: the push WebSocket (the token in the URL: browsers cannot set
  headers on it); ``GET /api/state``: the same state as JSON;
* ``POST /api/estop``: latch the e-stop; handled in the event loop, straight to the mux, the brake
  command written before the answer; ``POST /api/release``: release it.

Security: loopback needs no token unless one is configured; any other bind needs one (configured, or
generated and printed at start), and requests without it get 401. WebSocket upgrades and POSTs from a
browser must come from the page's own origin (403 otherwise); without a token the ``Host`` must name
this machine (DNS rebinding). Refused requests are counted per source and reason in the daemon's
:class:`~racecar_hw.runtime.refusals.Refusals` (surface ``"web"``), which logs summaries, not a line
each. Every connection passes a :class:`~racecar_hw.net.gate.ConnectionGate` first: at most
``max_connections`` at once, the request head within ``head_timeout_s``, closed after
``idle_timeout_s`` with nothing received.

The push work runs right after a scan's motor command is out (:meth:`WebServer.control_idle`), in the
gap before the next scan, and only while a page is open; a client that cannot keep up skips frames.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import sys
from importlib import resources
from typing import Any

import numpy as np
from aiohttp import WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.log import server_logger

from mux.estop import Origin
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.loopback import is_loopback
from racecar_hw.base.messages import LaserScan
from racecar_hw.net.auth import bearer, local_host_header, new_token, same_origin, token_ok
from racecar_hw.net.band import band_polygon, body_corners, swept_band
from racecar_hw.net.control import CarControl, LiveState
from racecar_hw.net.gate import ConnectionGate
from racecar_hw.net.web_params import WebParams
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)


class WebServer:
    """The status page on ``host:port``; :meth:`start` and :meth:`stop` from the event loop."""

    def __init__(self, bus: Bus, params: WebParams, control: CarControl, *,
                 scan_topic: str = "/scan", refusals: Refusals | None = None) -> None:
        self.bus = bus
        #: refused requests and closed connections, counted per source and reason (surface "web")
        self.refusals = refusals if refusals is not None else Refusals()
        self.params = params
        self.control = control
        self.scan_topic = scan_topic
        self.token = params.token
        if not self.token and not is_loopback(params.host):
            self.token = new_token()
        self.port: int | None = None
        self.pushes = 0
        self.refused = 0
        self._runner: web.AppRunner | None = None
        self._server: asyncio.Server | None = None
        self.gate = ConnectionGate("web", params.limits(), self.refusals)
        self._clients: dict[web.WebSocketResponse, asyncio.Task[Any] | None] = {}
        self._idle = asyncio.Event()
        #: set while a page is open: with none, the push loop sleeps until one opens
        self._watched = asyncio.Event()
        self._next_push_ns = 0
        self._push_task: asyncio.Task[None] | None = None
        self._page = resources.files("racecar_hw.net").joinpath("static/status.html").read_text()

    # --- life cycle -----------------------------------------------------------------------------

    def app(self) -> web.Application:
        """The aiohttp application (also for tests with aiohttp's test client)."""
        app = web.Application(middlewares=[self._guard])
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/api/state", self._state)
        app.router.add_post("/api/estop", self._estop)
        app.router.add_post("/api/release", self._release)
        return app

    async def start(self) -> bool:
        """Listen; False (logged) when the address cannot be had."""
        # aiohttp serves the requests; the listening socket is ours, so that every connection passes
        # the gate first (a cap and a head timeout, which aiohttp does not have: see net.gate)
        runner = web.AppRunner(self.app(), handle_signals=False, access_log=None,
                               keepalive_timeout=self.params.idle_timeout_s,
                               logger=_RequestErrors(self.refusals))
        await runner.setup()
        try:
            server = await self.gate.serve(runner.server, self.params.host, self.params.port)
        except OSError as err:
            log.error("web: cannot listen on %s:%d (%s); the status page is off", self.params.host,
                      self.params.port, err)
            await runner.cleanup()
            return False
        self._runner, self._server = runner, server
        self.port = server.sockets[0].getsockname()[1] if server.sockets else self.params.port
        self._push_task = asyncio.get_running_loop().create_task(self._push_loop(), name="web-push")
        url = f"http://{self.params.host}:{self.port}/"
        if self.token and not self.params.token:
            # the operator needs this to open the page: printed even when logging is quiet
            print(f"racecar-hw: status page {url}?token={self.token} (web.token was not set; this token "
                  "is new every start)", file=sys.stderr, flush=True)
        log.info("web: status page on %s%s", url, " (token required)" if self.token else "")
        return True

    async def stop(self) -> None:
        """Close the pages' connections and stop listening (safe to call twice)."""
        task, self._push_task = self._push_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        for ws in list(self._clients):
            with contextlib.suppress(Exception):
                await ws.close()
        self._clients.clear()
        self.gate.close()
        server, self._server = self._server, None
        if server is not None:
            server.close()
        runner, self._runner = self._runner, None
        if runner is not None:
            await runner.cleanup()  # closes the connections aiohttp serves

    def control_idle(self) -> None:
        """The control path is idle until the next scan: push now if a push is due."""
        if self._clients and monotonic_ns() >= self._next_push_ns and not self._idle.is_set():
            self._idle.set()

    # --- access ---------------------------------------------------------------------------------

    @web.middleware
    async def _guard(self, request: web.Request, handler: Any) -> web.StreamResponse:
        given = request.query.get("token") or bearer(request.headers.get("Authorization"))
        if not token_ok(given, self.token):
            self.refused += 1
            self.refusals.note("web", request.remote or "unknown", "request without the token (401)")
            return _closing(web.Response(status=401, text="401: this page needs its token: open the URL "
                                                          "printed at start (…/?token=…)\n"))
        if not self.token and not local_host_header(request.host):
            self.refused += 1
            self.refusals.note("web", request.remote or "unknown", "foreign Host header (403)")
            return _closing(web.Response(status=403, text="403: open the page as localhost or 127.0.0.1\n"))
        browser_write = request.method == "POST" or request.headers.get("Upgrade", "").lower() == "websocket"
        if browser_write and not same_origin(request.headers.get("Origin"), request.host):
            self.refused += 1
            self.refusals.note("web", request.remote or "unknown", "cross-origin request (403)")
            return _closing(web.Response(status=403, text="403: cross-origin request refused\n"))
        return await handler(request)

    # --- handlers -------------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.Response:
        return web.Response(text=self._page, content_type="text/html",
                            headers={"Cache-Control": "no-store", "X-Frame-Options": "DENY",
                                     "Referrer-Policy": "no-referrer"})

    async def _state(self, request: web.Request) -> web.Response:
        return web.json_response(self.payload(self.control.live_state()))

    async def _estop(self, request: web.Request) -> web.Response:
        # straight to the mux, in this loop: the brake command is written before we answer
        message = self.control.engage_estop(Origin("web", f"web page ({request.remote})"))
        return web.json_response({"ok": True, "message": message,
                                  "state": self.payload(self.control.live_state(), scan=False)})

    async def _release(self, request: web.Request) -> web.Response:
        ok, message = self.control.release_estop(Origin("web", f"web page ({request.remote})"))
        return web.json_response({"ok": ok, "message": message,
                                  "state": self.payload(self.control.live_state(), scan=False)},
                                 status=200 if ok else 409)

    async def _ws(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=5.0)
        await ws.prepare(request)
        shape = self.control.shape
        await ws.send_str(json.dumps({"op": "hello", "rate_hz": self.params.push_rate_hz, "shape": {
            "front": shape.front_m, "rear": shape.rear_m, "half_width": shape.half_width_m,
            "body": _rounded(body_corners(shape))}}))
        self._clients[ws] = None
        self._watched.set()
        self._next_push_ns = 0
        try:
            async for msg in ws:  # the page sends nothing; this waits for the close
                if msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break
        finally:
            self._clients.pop(ws, None)
            if not self._clients:
                self._watched.clear()
        return ws

    # --- pushing --------------------------------------------------------------------------------

    async def _push_loop(self) -> None:
        period = 1.0 / self.params.push_rate_hz
        while True:
            await self._watched.wait()  # nobody watching: no wake-ups
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                # woken by control_idle() after a scan; the timeout covers a car without a lidar
                await asyncio.wait_for(self._idle.wait(), 1.5 * period)
            self._idle.clear()
            now = monotonic_ns()
            if not self._clients or now < self._next_push_ns:
                continue
            step = int(period * NS_PER_S)
            if now - self._next_push_ns > step:  # the first push, or the loop was held up: start afresh
                self._next_push_ns = now
            self._next_push_ns += step  # on a fixed grid: pushes after scans still average push_rate_hz
            self.push()

    def push(self) -> None:
        """Send the state to every open page; a page still busy with the last one skips this one."""
        text = json.dumps({"op": "state", **self.payload(self.control.live_state())})
        for ws, pending in list(self._clients.items()):
            if pending is not None and not pending.done():
                continue
            if ws.closed:
                self._clients.pop(ws, None)
                continue
            task = asyncio.ensure_future(ws.send_str(text))
            task.add_done_callback(_forget)  # a page that went away: its receive loop removes it
            self._clients[ws] = task
        self.pushes += 1

    def payload(self, s: LiveState, scan: bool = True) -> dict[str, Any]:
        """The page's view of the car: numbers, and (with ``scan``) the scan points and swept band."""
        out: dict[str, Any] = {
            "t": wall_ns() / NS_PER_S,
            "speed": {"commanded": _f(s.commanded_mps), "output": _f(s.output_mps),
                      "allowed": _f(s.allowed_mps), "measured": _f(s.measured_mps)},
            "steering": _f(s.steering_rad), "battery_v": _f(s.battery_v), "source": s.source,
            "mux": {"state": s.mux_state, "reason": s.mux_reason, "estop": s.estop}, "armed": s.armed,
            "safety": {"state": s.safety_colour, "reason": s.safety_reason, "intervening": s.intervening,
                       "free_distance": _f(s.free_distance_m)},
            "links": {"lidar": {"age_s": _f(s.lidar_scan_age_s), "rate_hz": _f(s.lidar_rate_hz),
                                "reconnects": s.lidar_reconnects},
                      "vesc": {"connected": s.vesc_connected, "reconnects": s.vesc_reconnects,
                               "crc_errors": s.vesc_crc_errors}},
            "obstacle": list(s.obstacle) if s.obstacle is not None else None,
            "refused": {"recent": s.refused_recently,
                        "counts": [{"surface": surface, "reason": reason, "count": n}
                                   for surface, reason, n in s.refused]},
            "control": {"ticks": s.control_ticks, "missed_ticks": s.control_missed_ticks},
        }
        if scan:
            shape = self.control.shape
            inner, outer = swept_band(shape, s.steering_rad, shape.stopping_distance(s.commanded_mps),
                                      s.commanded_mps < 0.0, stations=12)
            out["band"] = _rounded(band_polygon(inner, outer))
            out["scan"] = self._scan_points()
        return out

    def _scan_points(self) -> list[float]:
        """The latest scan in base_link as a flat [x0, y0, x1, y1, ...] list, centimetre precision."""
        scan: LaserScan | None = self.bus.latest(self.scan_topic)
        if scan is None or len(scan.ranges) == 0:
            return []
        step = max(1, math.ceil(len(scan.ranges) / self.params.scan_points))
        r = np.asarray(scan.ranges[::step], dtype=np.float64)
        a = scan.angle_min + scan.angle_increment * step * np.arange(len(r))
        lx, ly, lyaw = self.control.shape.laser
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r >= scan.range_min) & (r <= self.params.max_range_m)
        r, a = r[ok], a[ok] + lyaw
        xy = np.column_stack([lx + r * np.cos(a), ly + r * np.sin(a)])
        return np.round(xy, 2).ravel().tolist()


class _RequestErrors:
    """aiohttp's server log for the page: a request that does not parse (a bad header, an overlong
    line) is a refusal counted per source (:class:`Refusals`, summarised), not a traceback at
    ERROR per request, which anyone who can connect could otherwise write as fast as they send;
    anything else aiohttp reports goes to its own log as before."""

    def __init__(self, refusals: Refusals) -> None:
        self._refusals = refusals

    def exception(self, msg: str, *args: Any, exc_info: Any = None, **kwargs: Any) -> None:
        if isinstance(exc_info, HttpProcessingError):
            source = str(args[0]) if args and args[0] else "unknown"
            self._refusals.note("web", source, "malformed request (400)")
            return
        server_logger.exception(msg, *args, exc_info=exc_info, **kwargs)

    def __getattr__(self, name: str) -> Any:  # debug, warning, isEnabledFor, ...
        return getattr(server_logger, name)


def _closing(response: web.Response) -> web.Response:
    """``response``, and the connection closes after it: a refused client keeps no connection slot."""
    response.force_close()
    return response


def _forget(task: asyncio.Task[Any]) -> None:
    if not task.cancelled():
        task.exception()


def _f(value: float | None) -> float | None:
    """A number for JSON: None for unknown and for inf/nan (JSON has neither)."""
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), 3)


def _rounded(points: np.ndarray) -> list[list[float]]:
    return np.round(points, 3).tolist()
