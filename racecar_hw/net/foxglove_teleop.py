"""Foxglove's Teleop panel driving the car: client-published Twists into the mux input ``foxglove``.

A client advertises ``geometry_msgs/msg/Twist`` (``cdr`` or ``json``) on ``teleop_topic``; each
Twist (m/s forward, rad/s yaw rate) is converted with the wheelbase into an Ackermann command
(m/s, rad + left) and published on the mux input, whose short timeout stops the car when the tab
closes or the Wi-Fi drops. Twists closer together than :data:`MIN_TWIST_INTERVAL_NS` from one
client, over all its channels (200 channels of one client no longer make 200 times the rate), and
bytes that are no Twist, are refused and counted. Called from the SDK's threads; the
command is published from the event loop (``call_soon_threadsafe``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from typing import Any

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns, wall_ns
from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Twist, stamp_now
from racecar_hw.rosmsg.typestore import ros2_types

log = logging.getLogger(__name__)

TWIST_TYPES = ("geometry_msgs/msg/Twist", "geometry_msgs/Twist")
#: Twists closer together than this from one client (over all its channels) are dropped: a flooding
#: client cannot load the control loop (the Teleop panel sends 10 Hz, at most tens).
MIN_TWIST_INTERVAL_NS = 5_000_000


def twist_to_drive(twist: Twist, wheelbase_m: float, max_speed_mps: float,
                   max_steering_rad: float) -> AckermannDrive:
    """A Twist (m/s forward, rad/s yaw rate) as an Ackermann command for a car of ``wheelbase_m``.

    ``steering = atan(wheelbase * yaw_rate / speed)``, so the car turns at the asked yaw rate; with no
    speed a yaw rate points the wheels fully to its side. Non-finite values become a stop; speed and
    steering are clamped to the limits.
    """
    v, w = float(twist.linear.x), float(twist.angular.z)
    if not (math.isfinite(v) and math.isfinite(w)):
        return AckermannDrive()
    v = max(-max_speed_mps, min(max_speed_mps, v))
    if abs(v) < 1e-3:
        steering = math.copysign(max_steering_rad, w) if w else 0.0
    else:
        steering = math.atan(wheelbase_m * w / v)
    steering = max(-max_steering_rad, min(max_steering_rad, steering))
    return AckermannDrive(steering_angle=steering, speed=v)


def decode_twist(data: bytes, encoding: str) -> Twist:
    """A client's Twist (``cdr`` or ``json``); raises on anything that is not one."""
    if encoding == "json":
        obj = json.loads(data)
        lin, ang = obj.get("linear", {}), obj.get("angular", {})
        twist = Twist()
        twist.linear.x, twist.angular.z = float(lin.get("x", 0.0)), float(ang.get("z", 0.0))
        return twist
    msg = ros2_types().deserialize(data, Twist)
    assert isinstance(msg, Twist)
    return msg


#: How many channels not taken are logged one by one (then every hundredth).
LOGGED_CHANNELS = 10


def _shown(text: Any, limit: int = 80) -> str:
    """A name a client chose, as a log line may show it: quoted (escapes included), cut short."""
    shown = repr(str(text))
    return shown if len(shown) <= limit else shown[:limit - 4] + "...'"


class TwistTeleop:
    """The clients' Twist channels on ``teleop_topic``, driving ``teleop_input`` (None: teleop off).

    :attr:`twists` counts Twists turned into commands, :attr:`refused` refused ones.
    """

    def __init__(self, bus: Bus, teleop_topic: str, teleop_input: str | None, *, wheelbase_m: float,
                 max_speed_mps: float, max_steering_rad: float) -> None:
        self.bus = bus
        self.teleop_topic = teleop_topic
        self.teleop_input = teleop_input
        self.wheelbase_m = wheelbase_m
        self.max_speed_mps = max_speed_mps
        self.max_steering_rad = max_steering_rad
        self.loop: asyncio.AbstractEventLoop | None = None
        self._channels: dict[tuple[int, int], str] = {}  # (client, channel) -> encoding
        self._last_twist_ns: dict[int, int] = {}  # client -> its last Twist taken (monotonic ns)
        self.twists = 0
        self.refused = 0
        #: channels advertised that the car does not take (another topic, type or encoding)
        self.ignored_channels = 0

    def advertised(self, client_id: int, channel: Any) -> None:
        """A client advertised ``channel``: taken when it is a Twist on the teleop topic.

        Channels not taken are logged with their names quoted and cut short (a client chooses
        them: a line break in one would forge a log line), the first :data:`LOGGED_CHANNELS` and
        then every hundredth, so that a client advertising thousands does not flood the log."""
        if channel.topic != self.teleop_topic or self.teleop_input is None:
            self._note_ignored(logging.INFO, "foxglove: client %d advertised %s (%s); only %s is taken",
                               client_id, _shown(channel.topic), _shown(channel.schema_name),
                               self.teleop_topic)
            return
        if channel.schema_name not in TWIST_TYPES or channel.encoding not in ("cdr", "json"):
            self._note_ignored(logging.WARNING, "foxglove: %s must carry geometry_msgs/msg/Twist as cdr or "
                               "json, not %s as %s", channel.topic, _shown(channel.schema_name),
                               _shown(channel.encoding))
            return
        self._channels[(client_id, channel.id)] = channel.encoding
        log.info("foxglove: client %d drives through the mux input on %s", client_id, self.teleop_input)

    def _note_ignored(self, level: int, fmt: str, *args: Any) -> None:
        self.ignored_channels += 1
        n = self.ignored_channels
        if n <= LOGGED_CHANNELS or n % 100 == 0:
            log.log(level, fmt + (f" ({n} channels not taken so far)" if n > LOGGED_CHANNELS else ""), *args)

    def unadvertised(self, client_id: int, channel_id: int) -> None:
        """A client withdrew a channel: a teleop channel stops the car now, not at the timeout."""
        taken = self._channels.pop((client_id, channel_id), None)
        if not any(client == client_id for client, _ in self._channels):
            self._last_twist_ns.pop(client_id, None)
        if taken is not None and self.loop is not None:
            self.loop.call_soon_threadsafe(self._drive, AckermannDrive())

    def message(self, client_id: int, channel_id: int, data: bytes) -> None:
        """A client's message on one of its channels."""
        key = (client_id, channel_id)
        encoding = self._channels.get(key)
        if encoding is None or self.loop is None:
            return
        now = monotonic_ns()
        if now - self._last_twist_ns.get(client_id, 0) < MIN_TWIST_INTERVAL_NS:
            self.refused += 1
            return
        self._last_twist_ns[client_id] = now
        try:
            twist = decode_twist(data, encoding)
        except Exception as err:  # noqa: BLE001 - a client's bad bytes: refused, counted, logged
            self.refused += 1
            if self.refused == 1 or self.refused % 100 == 0:
                log.warning("foxglove: refused a Twist from client %d (%s; %d so far)", client_id, err,
                            self.refused)
            return
        drive = twist_to_drive(twist, self.wheelbase_m, self.max_speed_mps, self.max_steering_rad)
        self.twists += 1
        self.loop.call_soon_threadsafe(self._drive, drive)

    def _drive(self, drive: AckermannDrive) -> None:
        if self.teleop_input is not None:
            msg = AckermannDriveStamped(stamp_now("base_link", wall_ns()), drive)
            self.bus.publish(self.teleop_input, msg)


__all__ = ["MIN_TWIST_INTERVAL_NS", "TWIST_TYPES", "TwistTeleop", "decode_twist", "twist_to_drive"]
