"""The live view in Foxglove: a WebSocket server (the Foxglove SDK, subprotocol ``foxglove.sdk.v1``).

What it serves:

* every ``OUT`` row of the topic table (:mod:`racecar_hw.net.topics`) as a channel with its ROS 2
  schema (``ros2msg``, the full definition with its dependencies, as bags store it) and CDR payloads
  from :mod:`racecar_hw.rosmsg`, the serializer the recorder uses; latched rows (``/tf_static``,
  the mux's active source, the simulator's ``/map``) are sent again to each new subscriber;
* ``/safety/scene`` (``foxglove.SceneUpdate`` in base_link: the swept footprint out to the stopping
  distance, the limiting obstacle, coloured clear/limiting/stopped; see :mod:`racecar_hw.net.scene`)
  and ``/safety/speeds`` (JSON: commanded, output, allowed and measured speed, steering) at
  ``scene_rate_hz``;
* ``/log``: Python logging records (INFO and up) as ``foxglove.Log``;
* client publishing: ``geometry_msgs/msg/Twist`` on ``teleop_topic`` (the Teleop panel), converted
  with the wheelbase into the mux input ``foxglove``, whose short timeout stops the car when the tab
  closes or the Wi-Fi drops; services ``/racecar/estop``, ``/racecar/release``, ``/racecar/arm`` and
  ``/racecar/disarm`` (``std_srvs/srv/Trigger``); the effective configuration as read-only parameters.

Clients reach it through :mod:`racecar_hw.net.relay` (the token off loopback, the browser's Origin on an
open loopback port); the SDK's own server listens behind it, on loopback with TLS only the relay trusts.

Threads: bus callbacks run in the event loop and only queue jobs (:class:`~racecar_hw.runtime.outbox.Outbox`,
drop oldest) while a client subscribes to the channel; the outbox thread serializes and hands the bytes
to the SDK, whose own threads send them. The SDK calls the listener and the service handlers from its
threads; they hand work to the event loop (``call_soon_threadsafe``), and a service waits for its answer.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import foxglove
from foxglove import Capability, Parameter, Schema
from foxglove.channels import LogChannel, SceneUpdateChannel
from foxglove.messages import Log, LogLevel, Timestamp

from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.messages import Message
from racecar_hw.net.control import CarControl, LiveState
from racecar_hw.net.foxglove_params import FoxgloveParams
from racecar_hw.net.foxglove_services import (
    SERVICE_PREFIX,
    SERVICE_TIMEOUT_S,
    TriggerServices,
    trigger_response,
)
from racecar_hw.net.foxglove_teleop import (
    MIN_TWIST_INTERVAL_NS,
    TWIST_TYPES,
    TwistTeleop,
    decode_twist,
    twist_to_drive,
)
from racecar_hw.net.loopback_tls import LOOPBACK, PendingCert
from racecar_hw.net.parameters import HIDDEN, SECRET_WORDS
from racecar_hw.net.relay import Relay
from racecar_hw.net.scene import scene_update
from racecar_hw.net.topics import Direction, Topic
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.outbox import Outbox
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

SCENE_TOPIC = "/safety/scene"
SPEEDS_TOPIC = "/safety/speeds"
LOG_TOPIC = "/log"

_SPEEDS_SCHEMA = {
    "title": "racecar_hw.SafetySpeeds", "type": "object",
    "properties": {
        "commanded": {"type": "number", "description": "speed the active source asks for, m/s"},
        "output": {"type": "number", "description": "speed sent to the VESC, m/s"},
        # one type each: Foxglove and Lichtblick refuse a schema with ["number", "null"] (and then plot
        # nothing); a value that is not known is left out instead
        "allowed": {"type": "number", "description": "safety controller's allowed speed, m/s; absent: "
                                                    "no limit"},
        "measured": {"type": "number", "description": "odometry speed, m/s; absent: no odometry yet"},
        "steering": {"type": "number", "description": "output steering angle, rad, + left"},
        "state": {"type": "string", "description": "clear, limiting or stopped"},
        "reason": {"type": "string", "description": "the safety controller's reason"},
        "source": {"type": "string", "description": "the mux's active source"},
    },
}


@dataclass
class _Channel:
    topic: Topic
    channel: foxglove.Channel
    subscribers: int = 0


class FoxgloveServer:
    """The Foxglove WebSocket server on ``bus``; :meth:`start` in the event loop, :meth:`stop` at exit.

    ``topics`` are the rows to serve, ``parameters`` the effective configuration (a nested mapping),
    ``teleop_input`` the mux input topic a Twist drives through, ``wheelbase_m`` and
    ``max_steering_rad`` convert it.
    """

    def __init__(self, bus: Bus, params: FoxgloveParams, control: CarControl, topics: list[Topic], *,
                 parameters: dict[str, Any] | None = None, teleop_input: str | None = None,
                 wheelbase_m: float = 0.25, max_steering_rad: float = 0.34, name: str = "racecar-hw",
                 refusals: Refusals | None = None) -> None:
        self.bus = bus
        #: what the relay refused, counted per source and reason (surface "relay")
        self.refusals = refusals if refusals is not None else Refusals()
        self.params = params
        self.control = control
        self._rows = topics  # read at start(): the simulator adds its rows after building the daemon
        self.topics: list[Topic] = []
        self.parameters = flatten_parameters(parameters or {})
        #: the clients' Teleop panels (their Twists, refused ones counted)
        self.teleop = TwistTeleop(bus, params.teleop_topic, teleop_input if params.teleop else None,
                                  wheelbase_m=wheelbase_m, max_speed_mps=params.teleop_max_speed_mps,
                                  max_steering_rad=max_steering_rad)
        self.name = name
        self.outbox = Outbox("foxglove-sender", params.queue_size)
        self.server: Any = None
        self.relay: Relay | None = None
        self._context: foxglove.Context | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._channels: dict[int, _Channel] = {}
        self._by_bus: dict[str, _Channel] = {}
        self._subs: list[Subscription] = []
        self._scene: Any = None
        self._speeds: foxglove.Channel | None = None
        self._log: Any = None
        self._special: dict[int, int] = {}  # SDK channel id -> subscribers, for scene/speeds/log
        self._scene_id = self._speeds_id = self._log_id = -1
        self._next_scene_ns = 0
        self._log_handler: _LogHandler | None = None
        #: the SDK server's loopback certificate, made by a child process from now until start()
        self._cert: PendingCert | None = PendingCert(reuse=True)

    # --- life cycle -----------------------------------------------------------------------------

    @property
    def port(self) -> int | None:
        """The port clients connect to (the relay's), or None when not running."""
        return int(self.relay.port) if self.relay is not None else None

    def start(self) -> bool:
        """Create the channels and start listening; False (logged) when the port cannot be had."""
        self._loop = self.teleop.loop = asyncio.get_running_loop()
        ctx = self._context = foxglove.Context()
        types = ros2_types()
        self.topics = [t for t in self._rows if t.direction is Direction.OUT]
        for row in self.topics:
            schema = Schema(name=row.msgtype.ROS_TYPE, encoding="ros2msg",
                            data=types.msgdef(row.msgtype.ROS_TYPE).encode())
            channel = foxglove.Channel(row.ros, schema=schema, message_encoding="cdr", context=ctx,
                                       metadata={"what": row.what} if row.what else None)
            entry = _Channel(row, channel)
            self._channels[channel.id()] = entry
            self._by_bus[row.bus] = entry
        self._scene = SceneUpdateChannel(SCENE_TOPIC, context=ctx)
        self._speeds = foxglove.Channel(SPEEDS_TOPIC, schema=_SPEEDS_SCHEMA, context=ctx)
        self._log = LogChannel(LOG_TOPIC, context=ctx)
        self._scene_id, self._speeds_id, self._log_id = (
            c.id() for c in (self._scene, self._speeds, self._log))
        self._special = dict.fromkeys((self._scene_id, self._speeds_id, self._log_id), 0)
        capabilities = [Capability.Services, Capability.Parameters]
        if self.teleop.teleop_input is not None:
            capabilities.append(Capability.ClientPublish)
        # the SDK behind the relay, on loopback with TLS only the relay trusts (see net.relay)
        pending, self._cert = self._cert or PendingCert(reuse=True), None
        cert = pending.result()
        try:
            self.server = foxglove.start_server(
                name=self.name, host=LOOPBACK, port=0, capabilities=capabilities,
                server_listener=_Listener(self), supported_encodings=["cdr", "json"],
                services=TriggerServices(self.control, self._loop).services(), context=ctx,
                tls_cert=cert.cert_pem, tls_key=cert.key_pem)
        except RuntimeError as err:
            log.error("foxglove: cannot start the Foxglove server (%s); the Foxglove live view is off", err)
            return False
        self.relay = Relay(self.params.host, self.params.port, self.server.port, cert.cert_pem,
                           token=self.params.token, allowed_origins=tuple(self.params.allowed_origins),
                           limits=self.params.limits(), refusals=self.refusals)
        try:
            self.relay.start()
        except OSError as err:
            log.error("foxglove: cannot listen on %s:%d (%s); the Foxglove live view is off",
                      self.params.host, self.params.port, err)
            self.relay = None
            self.server.stop()
            self.server = None
            return False
        log.info("foxglove: the SDK's server on wss://%s:%d, behind the relay", LOOPBACK, self.server.port)
        self.outbox.start()
        for row in self.topics:
            self._subs.append(self.bus.subscribe(row.bus, self._sender(self._by_bus[row.bus])))
        self._log_handler = _LogHandler(self)
        logging.getLogger().addHandler(self._log_handler)
        log.info("foxglove: live view on ws://%s:%d (%d channels)", self.params.host, self.port,
                 len(self._channels) + 3)
        return True

    def stop(self) -> None:
        """Stop serving (safe to call twice)."""
        if self._cert is not None:  # never started
            self._cert.cancel()
            self._cert = None
        if self._log_handler is not None:
            logging.getLogger().removeHandler(self._log_handler)
            self._log_handler = None
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        if self.relay is not None:
            self.relay.stop()
            self.relay = None
        if self.server is not None:
            self.server.stop()
            self.server = None
        self.outbox.stop()

    def control_idle(self) -> None:
        """The control path is idle until the next scan: let the sender run if due."""
        self.outbox.control_idle()

    # --- outgoing -------------------------------------------------------------------------------

    def _sender(self, entry: _Channel) -> Callable[[Message], None]:
        put, send = self.outbox.put, self._send

        def on_message(msg: Message) -> None:
            if entry.subscribers:
                put(send, entry, msg, wall_ns())
        return on_message

    @staticmethod
    def _send(entry: _Channel, msg: Message, t_ns: int) -> None:
        entry.channel.log(ros2_types().serialize(msg), log_time=t_ns)

    def on_output(self) -> None:
        """A mux output went out: queue the safety scene and speeds when due and wanted."""
        special = self._special
        if not (special.get(self._scene_id) or special.get(self._speeds_id)):
            return
        now = monotonic_ns()
        if now < self._next_scene_ns:
            return
        self._next_scene_ns = now + int(NS_PER_S / self.params.scene_rate_hz)
        self.outbox.put(self._send_scene, self.control.live_state(), wall_ns())

    def _send_scene(self, state: LiveState, t_ns: int) -> None:
        if self._special[self._scene_id]:
            self._scene.log(scene_update(state, self.control.shape, t_ns), log_time=t_ns)
        if self._speeds is not None and self._special[self._speeds_id]:
            speeds = {
                "commanded": state.commanded_mps, "output": state.output_mps,
                "allowed": state.allowed_mps if math.isfinite(state.allowed_mps) else None,
                "measured": state.measured_mps, "steering": state.steering_rad,
                "state": state.safety_colour, "reason": state.safety_reason, "source": state.source,
            }
            self._speeds.log({k: v for k, v in speeds.items() if v is not None}, log_time=t_ns)

    def _send_log(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if record.exc_info and record.exc_info[1] is not None:
            text += f": {record.exc_info[1]!r}"
        t_ns = int(record.created * NS_PER_S)
        self._log.log(Log(timestamp=Timestamp(sec=t_ns // NS_PER_S, nsec=t_ns % NS_PER_S),
                          level=_LEVELS.get(record.levelno, LogLevel.Unknown), message=text,
                          name=record.name, file=record.pathname, line=record.lineno), log_time=t_ns)

    @property
    def log_wanted(self) -> bool:
        return bool(self._special.get(self._log_id))

    # --- from the SDK's threads -----------------------------------------------------------------

    def subscribed(self, channel_id: int, delta: int) -> None:
        entry = self._channels.get(channel_id)
        if entry is None:
            if channel_id in self._special:
                self._special[channel_id] = max(0, self._special[channel_id] + delta)
            return
        entry.subscribers = max(0, entry.subscribers + delta)
        if delta > 0 and entry.topic.qos.latched:
            latest = self.bus.latest(entry.topic.bus)  # a dict read: safe from this thread
            if latest is not None:
                self.outbox.put(self._send, entry, latest, wall_ns())

    def get_parameters(self, names: list[str]) -> list[Parameter]:
        wanted = names or list(self.parameters)
        return [Parameter(name, value=self.parameters[name]) for name in wanted if name in self.parameters]



def flatten_parameters(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Dotted keys to parameter values: scalars as they are, anything else as JSON text, secrets hidden."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if any(word in str(key).lower() for word in SECRET_WORDS):
            out[name] = HIDDEN if value else ""
        elif isinstance(value, dict):
            out.update(flatten_parameters(value, name + "."))
        elif isinstance(value, (bool, int, float, str)):
            out[name] = value
        elif isinstance(value, (list, tuple)) and value and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            out[name] = [float(v) for v in value]
        else:
            out[name] = json.dumps(value, default=str)
    return out


_LEVELS = {logging.DEBUG: LogLevel.Debug, logging.INFO: LogLevel.Info, logging.WARNING: LogLevel.Warning,
           logging.ERROR: LogLevel.Error, logging.CRITICAL: LogLevel.Fatal}


class _LogHandler(logging.Handler):
    """Hands INFO-and-up records to the sender while a client subscribes to ``/log``."""

    def __init__(self, server: FoxgloveServer) -> None:
        super().__init__(logging.INFO)
        self.server = server

    def emit(self, record: logging.LogRecord) -> None:
        if self.server.log_wanted and not record.name.startswith("foxglove"):
            self.server.outbox.put(self.server._send_log, record)


class _Listener:
    """The SDK's ServerListener: called from its threads, forwards to the server."""

    def __init__(self, server: FoxgloveServer) -> None:
        self.server = server
        self._lock = threading.Lock()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self.server.subscribed(channel.id, +1)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            self.server.subscribed(channel.id, -1)

    def on_client_advertise(self, client: Any, channel: Any) -> None:
        self.server.teleop.advertised(client.id, channel)

    def on_client_unadvertise(self, client: Any, client_channel_id: int) -> None:
        self.server.teleop.unadvertised(client.id, client_channel_id)

    def on_message_data(self, client: Any, client_channel_id: int, data: bytes) -> None:
        self.server.teleop.message(client.id, client_channel_id, data)

    def on_get_parameters(self, client: Any, param_names: list[str],
                          request_id: str | None = None) -> list[Parameter]:
        return self.server.get_parameters(param_names)

    def on_parameters_subscribe(self, param_names: list[str]) -> None:
        """Nothing to do: the parameters never change while the daemon runs."""

    def on_parameters_unsubscribe(self, param_names: list[str]) -> None:
        """Nothing to do (see :meth:`on_parameters_subscribe`)."""

    def on_set_parameters(self, client: Any, parameters: list[Parameter],
                          request_id: str | None = None) -> list[Parameter]:
        log.warning("foxglove: client %d tried to set parameters; they are read-only (edit the config "
                    "file and restart)", client.id)
        return self.server.get_parameters([p.name for p in parameters])


__all__ = ["LOG_TOPIC", "MIN_TWIST_INTERVAL_NS", "SCENE_TOPIC", "SERVICE_PREFIX", "SERVICE_TIMEOUT_S",
           "SPEEDS_TOPIC", "TWIST_TYPES", "FoxgloveParams", "FoxgloveServer", "decode_twist",
           "flatten_parameters", "trigger_response", "twist_to_drive"]
