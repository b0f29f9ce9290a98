"""Drive the car from Python code that is not ROS: scans, odometry and safety state in, commands out.

::

    from racecar_hw.client import Car

    with Car() as car:                      # the daemon on this machine (tcp/127.0.0.1:7447)
        for scan in car.scans():            # the newest scan each time; older ones are skipped
            ahead = scan.ranges[abs(scan.angles) < 0.1].min()
            car.drive(speed=1.0 if ahead > 1.5 else 0.0, steering=0.0)
    # leaving the block sends a stop

It speaks ROS 2's rmw_zenoh wire format (:mod:`racecar_hw.net.rmw`) on the car's topic names, so it
also talks to real ROS 2 nodes. :meth:`Car.drive` publishes an ``AckermannDriveStamped`` on a mux
input (``nav_0`` unless told otherwise): the mux's timeout applies (0.2 s by default), so code
that stops sending stops the car; send at 10-50 Hz. The operator's inputs (``safety`` and
``teleop`` by default: ``network: false`` in the daemon's ``mux.inputs``) take no network commands,
and asking for one is a :class:`ClientError`. :class:`AsyncCar` is the same for asyncio.

Units: metres, radians (+ left, counter-clockwise), seconds, m/s; scans in the laser frame, odometry
in ``odom``. Stamps are seconds since the epoch (the sender's clock).

**Where the laser sits.** A scan's ranges and angles are in the laser's frame (``Scan.frame_id``,
``laser``): angle 0 is straight ahead of the lidar, + to the left. The lidar is not at the car's
origin (``base_link``, the rear axle's centre): the config's ``static_transforms`` place it, in the
shipped configs 0.265 m ahead of the rear axle and 0.10 m up, facing forward (``xyz: [0.265, 0.0,
0.1]``), so a wall 1.0 m from the lidar is 1.265 m from the rear axle. ``racecar-hw topic echo
/tf_static`` prints the transform the daemon uses; :data:`LASER_IN_BASE_LINK` is the shipped one.

**At start** ``car.scan``, ``car.odom`` and ``car.safety`` are None until the first message arrives
(a few tens of milliseconds after connecting, longer while the daemon starts): iterate
(``car.scans()``), or wait with ``car.next_scan()`` / ``car.next_odom()`` / :meth:`Car.wait_ready`,
which raise :class:`ClientError` after their timeout instead of returning None. ``wait_ready`` waits
for a scan and odometry only: the safety state, republished at 2 Hz while nothing changes, may come
half a second later (``next(car.safety_states())`` waits for it). After :meth:`Car.close` every
read raises ``ClientError("the client is closed")``, these properties too.

**Simulation time.** ``Car(use_sim_time=True)`` follows the simulator's ``/clock`` as a ROS 2 node
with ``use_sim_time`` does: :meth:`Car.now` is the newest ``/clock`` (seconds; 0.0 until the
first arrives, :meth:`Car.wait_clock` waits for it), :meth:`Car.sleep` and :meth:`Car.sleep_until`
count simulation time, :meth:`Car.on_clock` calls back per ``/clock``, and commands are stamped
with it. In the real-time simulation ``/clock`` is the wall clock (the stamps' time base); in
lockstep it is the simulation's own clock, which runs as fast as the machine allows, so code that
paces itself with ``car.sleep`` keeps step with the car. Without it, these use the wall clock.

:class:`SafetyState`'s ``values`` hold numbers as numbers (``allowed_speed`` 0.5, ``interventions``
3), ``true``/``false`` as bools, and the rest as text.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import os
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np

from mux.estop import REFUSED_ASSERTED
from mux.params import MuxParams
from racecar_hw.base.clock import NS_PER_S, nanoseconds
from racecar_hw.base.errors import ConfigError, RacecarError
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Bool,
    Clock,
    DiagnosticArray,
    LaserScan,
    Message,
    Odometry,
    Twist,
    Vector3,
    stamp_now,
)
from racecar_hw.base.topics import CLOCK_TOPIC, CMD_VEL_BUS_TOPIC
from racecar_hw.net import rmw
from racecar_hw.net.topics import (
    CLOCK_SUBSCRIPTION,
    CMD_VEL_INPUT,
    DEFAULT,
    SENSOR_DATA,
    Direction,
    Qos,
    Topic,
    named,
    topic_table,
)
from racecar_hw.net.zenoh_config import (
    DEFAULT_ENDPOINT,
    PROFILES,
    ZenohAuthParams,
    check_connect,
    session_config,
)
from racecar_hw.net.zenoh_node import ZenohNode
from racecar_hw.net.zenoh_security import check_credentials, zenoh_error_text
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.foreign_threads import hold_thread_state
from safety.params import SafetyParams

T = TypeVar("T")
#: Where the lidar sits on the car in the shipped configs (``static_transforms`` base_link ->
#: laser): x forward, y left, z up (m) and yaw (rad) in ``base_link`` (the rear axle's centre).
LASER_IN_BASE_LINK = (0.265, 0.0, 0.1, 0.0)


class ClientError(RacecarError):
    """The client could not connect, or was asked for something the car does not offer."""


@dataclass(frozen=True)
class Scan:
    """One lidar scan: ``ranges[i]`` (m; inf: no return) at ``angles[i]`` (rad, laser frame, + left).

    The laser frame is the lidar's own (``frame_id``), not the car's: see "Where the laser sits" in
    the module's documentation and :data:`LASER_IN_BASE_LINK`. ``ranges`` is the scan's own
    (float64) array; ``angles`` is shared by every scan of the same geometry and read-only, and so
    are the arrays of ``msg`` (views of the received bytes).
    """

    stamp_s: float
    frame_id: str
    ranges: np.ndarray
    angles: np.ndarray
    range_min: float
    range_max: float
    msg: LaserScan = field(repr=False)


@dataclass(frozen=True)
class Odom:
    """Wheel odometry: pose in ``odom`` (x, y m; yaw rad), forward speed (m/s), yaw rate (rad/s)."""

    stamp_s: float
    x: float
    y: float
    yaw: float
    speed: float
    yaw_rate: float
    msg: Odometry = field(repr=False)


@dataclass(frozen=True)
class SafetyState:
    """The safety controller's state: why it limits (``reason``), the speed it allows (m/s); every
    key it publishes in ``values``, typed (:func:`typed_value`): ``values["commanded_speed"]`` is a
    float, ``values["intervening"]`` a bool, ``values["source"]`` a str."""

    stamp_s: float
    reason: str
    intervening: bool
    allowed_speed: float
    values: dict[str, str | float | int | bool]
    msg: DiagnosticArray = field(repr=False)


@dataclass(frozen=True)
class MuxStatus:
    """The command mux's state from its ``/diagnostics``: ``running``, ``estop`` or ``fault``, who
    latched the e-stop (``latched by web page (127.0.0.1) at 18:50:01.123``), and the releases it
    refused (count, and the last one with its reason)."""

    state: str
    estop: str
    release_refusals: int
    last_refusal: str


#: The name of the mux's status in ``/diagnostics``.
MUX_STATUS_NAME = "racecar_hw: command mux"


def _mux_status(msg: DiagnosticArray) -> MuxStatus:
    status = next(s for s in msg.status if s.name == MUX_STATUS_NAME)  # StopIteration: not the mux's
    values = {kv.key: kv.value for kv in status.values}
    return MuxStatus(values.get("state", ""), values.get("estop", ""),
                     int(values.get("estop_release_refusals", "0")), values.get("estop_last_refusal", ""))


@functools.lru_cache(maxsize=8)
def _angles(angle_min: float, angle_increment: float, n: int) -> np.ndarray:
    """The beam angles of a scan geometry (rad), computed once per geometry; read-only."""
    angles = angle_min + angle_increment * np.arange(n)
    angles.flags.writeable = False
    return angles


def _scan(msg: LaserScan) -> Scan:
    ranges = msg.ranges.astype(np.float64)
    return Scan(msg.header.stamp.to_ns() / NS_PER_S, msg.header.frame_id, ranges,
                _angles(msg.angle_min, msg.angle_increment, len(ranges)),
                float(msg.range_min), float(msg.range_max), msg)


def _odom(msg: Odometry) -> Odom:
    pose, twist = msg.pose.pose, msg.twist.twist
    return Odom(msg.header.stamp.to_ns() / NS_PER_S, pose.position.x, pose.position.y,
                pose.orientation.yaw(), twist.linear.x, twist.angular.z, msg)


def typed_value(text: str) -> str | float | int | bool:
    """A diagnostic value (always text on the wire) as what it means: ``"3"`` -> 3, ``"0.500"`` ->
    0.5, ``"inf"`` -> inf, ``"true"``/``"false"`` -> bool; anything else stays text (``""`` too)."""
    if text in ("true", "false"):
        return text == "true"
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def _safety(msg: DiagnosticArray) -> SafetyState:
    status = msg.status[0] if msg.status else None
    values = {kv.key: typed_value(kv.value) for kv in status.values} if status else {}
    allowed = values.get("allowed_speed", math.nan)
    reason = values.get("reason", "")
    return SafetyState(msg.header.stamp.to_ns() / NS_PER_S, str(reason),
                       values.get("intervening") is True,
                       float(allowed) if isinstance(allowed, (int, float)) else math.nan, values, msg)


def _names(mux: MuxParams, safety: SafetyParams, profile: str,
           remap: Mapping[str, str] | None) -> dict[str, str]:
    """bus topic -> ROS name as the daemon names them, with the same checks as its config."""
    rows = topic_table(mux, safety, cmd_vel_topic="/cmd_vel")
    if all(row.bus != CMD_VEL_BUS_TOPIC for row in rows):  # the daemon adds this input when /cmd_vel is on
        rows.append(Topic(CMD_VEL_BUS_TOPIC, AckermannDriveStamped, Direction.IN, DEFAULT))
    try:
        if profile not in PROFILES:
            raise ConfigError("profile", f"unknown topic profile {profile!r}; profiles: "
                                         + ", ".join(PROFILES))
        for bus, ros in (remap or {}).items():
            try:
                rmw.check_topic_name(ros)
            except rmw.WireError as err:
                raise ConfigError(f"remap.{bus}", str(err)) from None
        return {row.bus: row.ros for row in named(rows, mux, profile, remap, key="")}
    except ConfigError as err:
        raise ClientError(str(err).lstrip(".")) from None


def _endpoints(endpoints: list[str]) -> list[str]:
    """``endpoints`` if each is ``<protocol>/<address>`` (:func:`check_connect`); ClientError naming it."""
    try:
        return [check_connect(endpoint, "connect") for endpoint in endpoints]
    except ConfigError as err:
        raise ClientError(str(err)) from None


class _Stream(Generic[T]):
    """One subscribed topic: the newest value, callbacks, and a one-slot mailbox per reader.

    Samples are decoded when somebody reads them: in Zenoh's thread while callbacks are registered,
    otherwise when :attr:`latest` or :meth:`wait_newer` is read, and only the newest one. A topic
    nobody reads (the odometry of code that only drives from scans) costs no decoding, and a slow
    reader decodes only what it takes.

    ``shared``: the topic carries other publishers' samples that ``decode`` rejects (the mux's
    status among the other components' arrays on ``/diagnostics``). Such a stream decodes every
    sample on arrival and counts only those it accepts, so a rejected one never hides the one
    a reader waits for.
    """

    def __init__(self, decode: Callable[[bytes], T], shared: bool = False) -> None:
        self.decode = decode
        self.shared = shared
        self.count = 0
        self.callbacks: list[Callable[[T], None]] = []
        self._cond = threading.Condition()
        self._latest: T | None = None
        self._raw: bytes | None = None  # the newest sample, not yet decoded
        self._raw_count = 0  # the count at that sample
        self._version = 0  # the count at the sample that gave ``_latest``
        #: the client was closed: readers waiting, and any that come, get a ClientError
        self.closed = False
        #: called when the stream closes (an async reader's wake-up)
        self.on_close: list[Callable[[], None]] = []

    @property
    def latest(self) -> T | None:
        """The newest value so far, or None (a sample that does not decode counts as none);
        ClientError once the client is closed, as every read then."""
        with self._cond:
            if self.closed:
                raise ClientError("the client is closed")
            return self._take()

    def _take(self) -> T | None:
        raw, self._raw = self._raw, None
        if raw is not None:
            try:
                self._latest = self.decode(raw)
                self._version = self._raw_count
            except Exception:  # noqa: BLE001 - a malformed sample is skipped
                pass
        return self._latest

    def push_raw(self, raw: bytes) -> None:
        """A new sample's payload (Zenoh's thread)."""
        if self.callbacks or self.shared:
            try:
                value = self.decode(raw)
            except Exception:  # noqa: BLE001 - a malformed sample is skipped
                return
            self.push(value)
            return
        with self._cond:
            self._raw = raw
            self.count += 1
            self._raw_count = self.count
            self._cond.notify_all()

    def push(self, value: T) -> None:
        with self._cond:
            self._latest, self._raw = value, None
            self.count += 1
            self._version = self.count
            self._cond.notify_all()
        for callback in list(self.callbacks):
            callback(value)

    def close(self) -> None:
        """Wake every reader with a ClientError (the client closed); later reads get it at once."""
        with self._cond:
            self.closed = True
            self._cond.notify_all()
        for wake in list(self.on_close):
            wake()

    def wait_newer(self, seen: int, timeout: float | None) -> tuple[T, int]:
        """The newest value once the count passed ``seen``; ClientError after ``timeout`` s, or
        once the client is closed."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                left = None if deadline is None else max(0.0, deadline - time.monotonic())
                arrived = self._cond.wait_for(lambda s=seen: self.count > s or self.closed, left)
                if self.closed:
                    raise ClientError("the client is closed")
                if not arrived:
                    raise ClientError(f"nothing received for {timeout:g} s: is the daemon running and "
                                      "reachable, with the same domain id and namespace?")
                value = self._take()
                if value is not None and self._version > seen:
                    return value, self.count
                seen = self.count  # only samples that did not decode since: wait for the next


class _EstopControls:
    """The e-stop part of :class:`Car`: engage, read the mux's state, release (as an operator may)."""

    # what :class:`Car` provides
    mux: MuxParams
    mux_stream: _Stream[MuxStatus] | None
    _lock: threading.Lock
    publish: Callable[[str, Message], None]
    _subscribe: Callable[..., _Stream[Any]]

    def estop(self) -> None:
        """Engage the daemon's latched e-stop."""
        self.publish(self.mux.estop_topic, Bool(True))

    def mux_status(self, timeout: float | None = 5.0) -> MuxStatus:
        """The mux's state from its next ``/diagnostics`` (2 Hz); ClientError after ``timeout`` s."""
        with self._lock:
            if self.mux_stream is None:
                self.mux_stream = self._subscribe(self.mux.diagnostics_topic, DiagnosticArray,
                                                  _mux_status, DEFAULT, shared=True)
            stream = self.mux_stream
        value, _ = stream.wait_newer(stream.count, timeout)
        return value

    def release_estop(self, timeout: float = 5.0) -> None:
        """Release the daemon's e-stop, if the daemon lets this client: returns once the mux runs.

        Stop is for anyone, release is for an operator: the release topic this sends on releases
        only an e-stop that the e-stop topic alone engaged (this client's :meth:`estop`, another
        network node), and only where the daemon's ``mux.estop_release_sources`` names ``network``.
        An e-stop latched on the status page, in Foxglove or by ``start_estopped`` is released there.
        Raises :class:`ClientError` saying why when the daemon refuses (read back from the mux's
        ``/diagnostics``), or when the mux does not answer within ``timeout`` s. Returns at once
        when the e-stop is not engaged.
        """
        deadline = time.monotonic() + timeout
        before = self.mux_status(timeout)
        if before.state == "running":
            return
        self.publish(self.mux.estop_topic, Bool(False))
        self.publish(self.mux.estop_release_topic, Bool(True))
        retried = False
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ClientError(f"the e-stop was not released within {timeout} s ({before.estop})")
            status = self.mux_status(left)
            if status.state == "running":
                return
            if status.release_refusals > before.release_refusals:
                if not retried and status.last_refusal.endswith(REFUSED_ASSERTED):
                    # the release overtook our own "false" (two topics, two of Zenoh's threads):
                    # once more, now that the false is in
                    retried, before = True, status
                    self.publish(self.mux.estop_release_topic, Bool(True))
                    continue
                raise ClientError(f"the daemon refused the release: {status.last_refusal} "
                                  f"(the e-stop was {status.estop})")


def _clock_ns(msg: Clock) -> int:
    return msg.clock.to_ns()


class _SimTime:
    """The clock part of :class:`Car`: the simulation's ``/clock`` (``use_sim_time=True``), else the
    wall clock. See "Simulation time" in the module's documentation."""

    # what :class:`Car` provides
    _subscribe: Callable[..., _Stream[Any]]
    #: ``/clock`` in ns (``use_sim_time``), else None
    clock_stream: _Stream[int] | None = None

    def _follow_clock(self) -> None:
        # /clock is absolute: ROS 2's time source reads it whatever the node's namespace
        self.clock_stream = self._subscribe(CLOCK_TOPIC, Clock, _clock_ns, CLOCK_SUBSCRIPTION, absolute=True)

    @property
    def use_sim_time(self) -> bool:
        """Whether this client follows ``/clock``."""
        return self.clock_stream is not None

    def now_ns(self) -> int:
        """The time in ns: the newest ``/clock`` with ``use_sim_time`` (0 until the first arrives, as
        on a ROS 2 node), else the wall clock (since the epoch)."""
        if self.clock_stream is None:
            return time.time_ns()
        latest = self.clock_stream.latest
        return 0 if latest is None else latest

    def now(self) -> float:
        """:meth:`now_ns` in seconds."""
        return self.now_ns() / NS_PER_S

    def wait_clock(self, timeout: float | None = 5.0) -> float:
        """With ``use_sim_time``: wait for the first ``/clock`` and return :meth:`now` (at once when one
        has arrived); ClientError when none comes within ``timeout`` wall-clock seconds."""
        return self._wait_until_ns(0, timeout) / NS_PER_S

    def sleep(self, seconds: float, timeout: float | None = 5.0) -> None:
        """Sleep ``seconds`` of the client's time. With ``use_sim_time`` that is ``seconds`` of
        simulation time, counted from the newest ``/clock`` (from the first, if none has arrived
        yet); ClientError when ``/clock`` stops for ``timeout`` wall-clock seconds."""
        if self.clock_stream is None:
            time.sleep(max(0.0, seconds))
            return
        start = self._wait_until_ns(0, timeout)
        self._wait_until_ns(start + nanoseconds(seconds), timeout)

    def sleep_until(self, t: float, timeout: float | None = 5.0) -> None:
        """Sleep until the client's time (:meth:`now`, seconds) reaches ``t``."""
        if self.clock_stream is None:
            time.sleep(max(0.0, t - time.time()))
            return
        self._wait_until_ns(nanoseconds(t), timeout)

    def on_clock(self, callback: Callable[[float], None]) -> None:
        """Call ``callback(now_s)`` for every ``/clock``, in Zenoh's thread (``use_sim_time`` only)."""
        stream = self._sim_clock()
        stream.callbacks.append(lambda ns: callback(ns / NS_PER_S))

    def _sim_clock(self) -> _Stream[int]:
        if self.clock_stream is None:
            raise ClientError("this client follows the wall clock: make it with Car(use_sim_time=True)")
        return self.clock_stream

    def _wait_until_ns(self, target_ns: int, timeout: float | None) -> int:
        """The first ``/clock`` (ns) at or after ``target_ns``; ClientError when ``/clock`` stops."""
        stream = self._sim_clock()
        seen = stream.count
        value = stream.latest
        while value is None or value < target_ns:
            try:
                value, seen = stream.wait_newer(seen, timeout)
            except ClientError:
                raise ClientError(f"no /clock for {timeout:g} s: is a simulation running, with /clock "
                                  "on (world.clock_rate_hz)?") from None
        return value


class Car(_SimTime, _EstopControls):
    """A connection to one car. See the module documentation.

    ``connect``: Zenoh endpoints of the daemon (or of a router it is connected to); ``mode``:
    ``client`` (through what it connects to) or ``peer``; ``namespace`` and ``domain_id`` as the
    daemon's ``zenoh`` section (``domain_id`` None: ``ROS_DOMAIN_ID`` or 0); ``profile`` and
    ``remap``: the daemon's ``zenoh.profile`` and ``zenoh.remap`` (bus topic -> ROS name), so the
    client finds topics the daemon renamed; ``input``: the mux input :meth:`drive` commands by default;
    ``user``/``password`` when the daemon requires them; ``ros_distro``: the daemon's
    ``zenoh.ros_distro`` (``humble`` puts ``TypeHashNotSupported`` in keys where ``jazzy`` puts
    RIHS01); ``session``: an open Zenoh session to share (another :class:`Car`'s, to reach several
    cars through one session; it is not closed here); ``use_sim_time``: follow the simulation's
    ``/clock`` (:meth:`now`, :meth:`sleep`, command stamps), as a ROS 2 node with ``use_sim_time``.
    """

    def __init__(self, connect: str | list[str] = DEFAULT_ENDPOINT, *, namespace: str = "",
                 domain_id: int | None = None, mode: str = "client", profile: str = "racecar",
                 remap: Mapping[str, str] | None = None,
                 input: str = "nav_0", user: str = "", password: str = "",  # noqa: A002
                 node_name: str = "", mux: MuxParams | None = None,
                 safety: SafetyParams | None = None, session: Any = None,
                 ros_distro: str = "jazzy", use_sim_time: bool = False) -> None:
        import zenoh  # noqa: PLC0415 - the Rust extension loads only when a client is made

        self.endpoints = _endpoints([connect] if isinstance(connect, str) else list(connect))
        if ros_distro not in rmw.ROS_DISTROS:
            raise ClientError(f"ros_distro {ros_distro!r}: one of {', '.join(rmw.ROS_DISTROS)} "
                              "(the daemon's zenoh.ros_distro)")
        self.ros_distro = ros_distro
        self.namespace = rmw.check_namespace(namespace)
        env = os.environ.get("ROS_DOMAIN_ID", "").strip()
        self.domain_id = domain_id if domain_id is not None else (int(env) if env.isdigit() else 0)
        self.mux = mux if mux is not None else MuxParams()
        safety = safety if safety is not None else SafetyParams()
        self._names = _names(self.mux, safety, profile, remap)
        self._inputs = {i.name: i.topic for i in self.mux.inputs}
        self._inputs.setdefault(CMD_VEL_INPUT, CMD_VEL_BUS_TOPIC)
        #: name -> its index in mux.inputs, for the inputs that take no network commands
        self._operator_inputs = {i.name: n for n, i in enumerate(self.mux.inputs) if not i.network}
        self.input = input
        self.input_topic(input)  # refuse an unknown input now
        try:
            check_credentials(user, password, "user", "password")
        except ConfigError as err:
            raise ClientError(str(err)) from None
        auth = ZenohAuthParams(user=user, password=password)
        self._own_session = session is None
        try:
            self.session = session if session is not None else zenoh.open(
                session_config(mode, [], self.endpoints, auth=auth))
        except zenoh.ZError as err:
            hint = "is the daemon running, and are user and password right?" if user else (
                "is the daemon running, and does it want a user and password?")
            raise ClientError(f"cannot connect to {', '.join(self.endpoints)} ({mode} mode): {hint} "
                              f"(Zenoh: {zenoh_error_text(err)})") from None
        self.node = ZenohNode(self.session, rmw.NodeNames(
            self.domain_id, self.namespace, node_name or f"racecar_client_{os.getpid()}", ros_distro))
        self.zid = self.node.names.zid
        self._pubs: dict[str, tuple[Any, rmw.SampleStamps]] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._streams: list[_Stream[Any]] = []  # closed with the client: their readers wake
        self.scan_stream: _Stream[Scan] = self._subscribe("/scan", LaserScan, _scan, SENSOR_DATA)
        self.odom_stream: _Stream[Odom] = self._subscribe("/odom", Odometry, _odom, DEFAULT)
        self.safety_stream: _Stream[SafetyState] = self._subscribe(safety.state_topic, DiagnosticArray,
                                                                   _safety, DEFAULT)
        #: the mux's state, subscribed on the first :meth:`release_estop` (``/diagnostics``)
        self.mux_stream: _Stream[MuxStatus] | None = None
        if use_sim_time:
            self._follow_clock()

    # --- names --------------------------------------------------------------------------------

    def ros_name(self, bus_topic: str) -> str:
        """The full ROS name of a daemon topic: namespace, then the profile's name for it."""
        return self.namespace + self._names.get(bus_topic, bus_topic)

    def input_topic(self, name: str) -> str:
        """The bus topic of the mux input ``name``; ClientError naming the inputs this client may
        drive if unknown, or if the input takes no network commands (``network: false`` in ``mux``:
        ``safety`` and ``teleop`` by default, which the daemon would refuse)."""
        usable = ", ".join(n for n in self._inputs if n not in self._operator_inputs)
        if name in self._operator_inputs:
            raise ClientError(f"mux input {name!r} takes no network commands (the daemon's mux.inputs"
                              f"[{self._operator_inputs[name]}].network is false: only the car's "
                              f"operator drives it); inputs a client may drive: {usable}")
        try:
            return self._inputs[name]
        except KeyError:
            raise ClientError(f"no mux input {name!r}; inputs: {usable}") from None

    # --- subscriptions ------------------------------------------------------------------------

    def _subscribe(self, bus_topic: str, msgtype: type[Message], convert: Callable[[Any], T],
                   qos: Qos, shared: bool = False, absolute: bool = False) -> _Stream[T]:
        deserialize = ros2_types().deserialize

        def decode(raw: bytes) -> T:
            return convert(deserialize(raw, msgtype))

        stream: _Stream[T] = _Stream(decode, shared)
        self._streams.append(stream)

        def on_sample(sample: Any) -> None:
            hold_thread_state()
            stream.push_raw(sample.payload.to_bytes())

        import zenoh  # noqa: PLC0415 - loaded already: the session is open

        # called in Zenoh's receiving thread (not ``indirect``, which puts a Python thread of its
        # own between every sample and the reader it wakes)
        self.node.subscriber(bus_topic if absolute else self.ros_name(bus_topic), msgtype, qos,
                             zenoh.handlers.Callback(on_sample, indirect=False))
        return stream

    @staticmethod
    def _iterate(stream: _Stream[T], timeout: float | None) -> Iterator[T]:
        seen = stream.count
        while True:
            value, seen = stream.wait_newer(seen, timeout)
            yield value

    def scans(self, timeout: float | None = 5.0) -> Iterator[Scan]:
        """Scans as they arrive; a slow reader gets the newest (ClientError after ``timeout`` s of none)."""
        return self._iterate(self.scan_stream, timeout)

    def odometry(self, timeout: float | None = 5.0) -> Iterator[Odom]:
        """Odometry as it arrives (newest first, as :meth:`scans`)."""
        return self._iterate(self.odom_stream, timeout)

    def safety_states(self, timeout: float | None = 5.0) -> Iterator[SafetyState]:
        """The safety controller's state as it arrives."""
        return self._iterate(self.safety_stream, timeout)

    def next_scan(self, timeout: float | None = 5.0) -> Scan:
        """The next scan to arrive."""
        return next(self.scans(timeout))

    def next_odom(self, timeout: float | None = 5.0) -> Odom:
        """The next odometry to arrive."""
        return next(self.odometry(timeout))

    @property
    def scan(self) -> Scan | None:
        """The newest scan so far, or None."""
        return self.scan_stream.latest

    @property
    def odom(self) -> Odom | None:
        """The newest odometry so far; None until the first arrives (see :meth:`wait_ready`)."""
        return self.odom_stream.latest

    def wait_ready(self, timeout: float | None = 5.0) -> None:
        """Wait until a scan and odometry have arrived, so ``scan`` and ``odom`` are not None
        (``safety`` may still be None); ClientError after ``timeout`` s (the daemon not running, or
        not reachable), or at once when the client is closed."""
        if self.scan_stream.latest is None:
            self.next_scan(timeout)
        if self.odom_stream.latest is None:
            self.next_odom(timeout)

    @property
    def safety(self) -> SafetyState | None:
        """The newest safety state so far, or None."""
        return self.safety_stream.latest

    def on_scan(self, callback: Callable[[Scan], None]) -> None:
        """Call ``callback(scan)`` for every scan, in Zenoh's thread: keep it short."""
        self.scan_stream.callbacks.append(callback)

    def on_odom(self, callback: Callable[[Odom], None]) -> None:
        """Call ``callback(odom)`` for every odometry message, in Zenoh's thread."""
        self.odom_stream.callbacks.append(callback)

    def on_safety(self, callback: Callable[[SafetyState], None]) -> None:
        """Call ``callback(state)`` for every safety state, in Zenoh's thread."""
        self.safety_stream.callbacks.append(callback)

    # --- commands -----------------------------------------------------------------------------

    def publish(self, bus_topic: str, msg: Message) -> None:
        """Publish ``msg`` on a daemon topic (by its bus name; the profile and namespace apply)."""
        topic = self.ros_name(bus_topic)
        with self._lock:
            if self._closed:
                raise ClientError("the client is closed")
            entry = self._pubs.get(topic)
            if entry is None:
                entry = self._pubs[topic] = self.node.publisher(topic, type(msg), DEFAULT)
            publisher, stamps = entry
            publisher.put(ros2_types().serialize(msg), attachment=stamps.next(time.time_ns()))

    def drive(self, speed: float, steering: float, input: str | None = None) -> None:  # noqa: A002
        """Command ``speed`` (m/s, + forward) and ``steering`` (rad, + left) on a mux input.

        The command holds for the input's timeout (0.2 s by default): call this at 10-50 Hz. It is
        stamped with :meth:`now_ns` (simulation time with ``use_sim_time``).
        """
        if not (math.isfinite(speed) and math.isfinite(steering)):
            raise ValueError(f"speed and steering must be finite, got {speed!r}, {steering!r}")
        msg = AckermannDriveStamped(stamp_now("base_link", self.now_ns()),
                                    AckermannDrive(steering_angle=float(steering), speed=float(speed)))
        self.publish(self.input_topic(input or self.input), msg)

    def twist(self, linear: float, angular: float, topic: str = "/cmd_vel") -> None:
        """Send a geometry_msgs/Twist (m/s, rad/s) as Nav2 would, to the daemon's /cmd_vel."""
        if not (math.isfinite(linear) and math.isfinite(angular)):  # as drive(): the daemon drops it
            raise ValueError(f"linear and angular must be finite, got {linear!r}, {angular!r}")
        self.publish(topic, Twist(Vector3(x=float(linear)), Vector3(z=float(angular))))

    def stop(self, input: str | None = None) -> None:  # noqa: A002
        """Command zero speed, centred steering on the input (the mux then times it out)."""
        self.drive(0.0, 0.0, input)

    # --- life cycle ---------------------------------------------------------------------------

    def close(self) -> None:
        """Undeclare everything and close the session (safe twice)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for stream in self._streams:
            stream.close()
        self.node.close()
        if self._own_session:
            with contextlib.suppress(Exception):
                self.session.close()

    def __enter__(self) -> Car:
        return self

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(Exception):
            if self._pubs:
                self.stop()
        self.close()


class AsyncCar:
    """:class:`Car` for asyncio: ``async with AsyncCar() as car: async for scan in car.scans(): ...``.

    Construct it inside a running event loop. Commands are the same non-blocking calls as
    :class:`Car`'s; iteration yields the newest value when the loop gets to it.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.car = Car(*args, **kwargs)
        self._loop = asyncio.get_running_loop()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.car, name)

    async def _iterate(self, stream: _Stream[T], timeout: float | None) -> AsyncIterator[T]:
        box: asyncio.Queue[T] = asyncio.Queue(maxsize=1)
        loop = self._loop

        def put(value: T) -> None:
            if box.full():
                box.get_nowait()
            box.put_nowait(value)

        def callback(value: T) -> None:
            with contextlib.suppress(RuntimeError):  # the loop closed
                loop.call_soon_threadsafe(put, value)

        closed = asyncio.Event()

        def wake() -> None:
            with contextlib.suppress(RuntimeError):  # the loop closed
                loop.call_soon_threadsafe(closed.set)

        stream.callbacks.append(callback)
        stream.on_close.append(wake)
        try:
            while True:
                if stream.closed:
                    raise ClientError("the client is closed")
                getter, closing = asyncio.ensure_future(box.get()), asyncio.ensure_future(closed.wait())
                try:
                    await asyncio.wait((getter, closing), timeout=timeout,
                                       return_when=asyncio.FIRST_COMPLETED)
                finally:  # also when the reader is cancelled: no task left pending
                    closing.cancel()
                    if not getter.done():
                        getter.cancel()
                if not getter.done() or getter.cancelled():
                    if closed.is_set():
                        raise ClientError("the client is closed")
                    raise ClientError(f"nothing received for {timeout:g} s: is the daemon running and "
                                      "reachable?")
                yield getter.result()
        finally:
            stream.callbacks.remove(callback)
            stream.on_close.remove(wake)

    def scans(self, timeout: float | None = 5.0) -> AsyncIterator[Scan]:
        """Scans as they arrive (the newest when the loop gets to it)."""
        return self._iterate(self.car.scan_stream, timeout)

    def odometry(self, timeout: float | None = 5.0) -> AsyncIterator[Odom]:
        """Odometry as it arrives."""
        return self._iterate(self.car.odom_stream, timeout)

    def safety_states(self, timeout: float | None = 5.0) -> AsyncIterator[SafetyState]:
        """The safety state as it arrives."""
        return self._iterate(self.car.safety_stream, timeout)

    async def release_estop(self, timeout: float = 5.0) -> None:
        """:meth:`Car.release_estop` without blocking the loop (it waits for the mux's answer)."""
        await self._loop.run_in_executor(None, self.car.release_estop, timeout)

    async def mux_status(self, timeout: float | None = 5.0) -> MuxStatus:
        """:meth:`Car.mux_status` without blocking the loop."""
        return await self._loop.run_in_executor(None, self.car.mux_status, timeout)

    async def sleep(self, seconds: float, timeout: float | None = 5.0) -> None:
        """:meth:`Car.sleep` (simulation time with ``use_sim_time``) without blocking the loop."""
        if not self.car.use_sim_time:
            await asyncio.sleep(max(0.0, seconds))
            return
        await self._loop.run_in_executor(None, self.car.sleep, seconds, timeout)

    async def wait_clock(self, timeout: float | None = 5.0) -> float:
        """:meth:`Car.wait_clock` without blocking the loop."""
        return await self._loop.run_in_executor(None, self.car.wait_clock, timeout)

    async def close(self) -> None:
        """Close the connection without blocking the loop."""
        await self._loop.run_in_executor(None, self.car.close)

    async def __aenter__(self) -> AsyncCar:
        return self

    async def __aexit__(self, *exc: object) -> None:
        with contextlib.suppress(Exception):
            if self.car._pubs:
                self.car.stop()
        await self.close()
