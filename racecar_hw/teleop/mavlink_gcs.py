"""A MAVLink 2 ground-station link over UDP: telemetry out, teleop, arming and modes in.

The car speaks as an ArduPilot Rover (MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_ARDUPILOTMEGA, custom
modes numbered as ArduPilot Rover numbers them: MANUAL 0, HOLD 4, GUIDED 15) to one ground station
at ``gcs_address`` (QGroundControl, MAVProxy, a pymavlink script). QGroundControl names custom modes
only through its ArduPilot plugin, which it picks for MAV_AUTOPILOT_ARDUPILOTMEGA (with GENERIC it
shows "Custom:0x0"); MAVProxy and pymavlink name them from the vehicle type whatever the autopilot
(except PX4). See docs/teleop.md. One UDP socket, bound to ``bind_address:bind_port``, sends and
receives; telemetry goes to ``gcs_address``, or, when its port is 0, to the port the first
authenticated message of the ground station came from. It never follows other senders.

Out: HEARTBEAT (1 Hz; armed flag from :class:`~racecar_hw.teleop.arming.Arming`), SYS_STATUS (with
sensor bits for the lidar and the motor controller) and BATTERY_STATUS (1 Hz, from
``/vesc/sensors/core``), ATTITUDE, LOCAL_POSITION_NED and VFR_HUD (from ``/odom``, REP-103 ENU/FLU
converted to NED/FRD) and OBSTACLE_DISTANCE (72 bins of 5 degrees in cm, from ``/scan``) at
``telemetry_rate_hz``, STATUSTEXT for events (arming, modes, safety state changes on
``/safety/state``, ground-station link lost and regained), COMMAND_ACK for every COMMAND_LONG,
COMMAND_INT and SET_MODE addressed to us, AUTOPILOT_VERSION on request, PARAM_VALUE for parameter
requests (a small read-only list).

In (only from the ground station's system id ``gcs_system_id``, ArduPilot's ``SYSID_MYGCS``):
MANUAL_CONTROL (ArduPilot Rover: ``y`` steering, +1000 = full right; ``z`` throttle, -1000..1000
with 0 = stop; ``x`` instead of ``z`` when ``throttle_axis: x``) and RC_CHANNELS_OVERRIDE (ch1
steering, ch3 throttle, PWM µs; 0 releases a channel, 65535 leaves a live value unchanged; a value
expires ``rc_override_time_s`` after it was sent, ArduPilot's ``RC_OVERRIDE_TIME``) drive the mux's
teleop input at ``rate_hz`` while the input is fresh, the mode is MANUAL and the ground station's
heartbeats are fresh. COMMAND_LONG / COMMAND_INT ARM_DISARM (400) and
DO_SET_MODE (176), and SET_MODE, change the arming and mode. HOLD stops the car through
:meth:`MavlinkGcs.filter` (a mux filter). When the ground station's heartbeats stop for more
than ``heartbeat_timeout_s``, its teleop input is dropped (one zero command, then silence) and a
STATUSTEXT says so.

Security: a ground station outside loopback needs MAVLink 2 signing (``signing_key_file``;
:class:`~racecar_hw.base.errors.ConfigError` otherwise). Datagrams are decoded by
:class:`~racecar_hw.teleop.mavlink_rx.MavlinkRx`: one datagram at a time, signatures verified
before any timestamp is recorded; with signing on, every unsigned or badly signed message is
refused and counted, and a signed frame stamped more than ``future_window_s`` ahead of our wall
clock is refused without recording its timestamp. Datagrams from any other host than the ground
station's are dropped and counted whatever the signing, and messages from other system ids are
ignored and counted. Every refusal is also counted in a
:class:`~racecar_hw.runtime.refusals.Refusals` (surface ``"mavlink"``, source ``host:port``),
which logs rate-limited summaries. :meth:`MavlinkGcs.restart_signing` forgets every stream's
timestamp, as a restart would (the daemon calls it on SIGUSR1, ``systemctl reload racecar-hw``).

Floods: the ground station's address has a socket of its own: a second socket on the same port
(``SO_REUSEPORT``), connected to the station, to which the kernel delivers the station's datagrams
in preference to the shared socket, so a flood from other addresses fills only the shared socket's
buffer and cannot push the station's heartbeats out. Each socket is drained each time it is
readable (the station's first), until empty or for ``DRAIN_BUDGET_NS``; a socket that still has
datagrams waiting after that rests for ``DRAIN_PAUSE_S`` (the kernel drops what overflows its
buffer), so a flood takes about 5 % of the event loop at most and the control loop keeps its time.
Forgeries are refused by :meth:`~racecar_hw.teleop.mavlink_rx.MavlinkRx.refuse_cheaply` before
any parsing, and refusals are noted once per wake-up.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import ipaddress
import logging
import math
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from racecar_hw import __version__
from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.loopback import is_loopback
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    DiagnosticArray,
    DiagnosticStatus,
    LaserScan,
    Odometry,
    VescStateStamped,
    stamp_now,
)
from racecar_hw.base.params import param
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.status import StatusSnapshot
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.teleop.arming import Arming, ArmingChange
from racecar_hw.teleop.mavlink_rx import MavlinkRx

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported anywhere: the MAVLink 2 dialects
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from racecar_hw.base.topics import TELEOP_TOPIC

log = logging.getLogger(__name__)

#: The HEARTBEAT autopilot: QGroundControl picks its ArduPilot Rover plugin, which names ArduPilot
#: Rover's custom modes, only for ARDUPILOTMEGA (src/FirmwarePlugin/APM/APMFirmwarePluginFactory.cc);
#: MAVProxy names them from the vehicle type for any autopilot but PX4 (pymavlink's
#: mavutil.mode_string_v10 and mode_mapping_rover).
AUTOPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
#: AUTOPILOT_VERSION capabilities: only what this link does.
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)
#: SYS_STATUS reports the lidar healthy while scans are this fresh, the VESC while its telemetry is.
SCAN_FRESH_NS = NS_PER_S
VESC_FRESH_NS = NS_PER_S // 2
#: ArduPilot Rover's custom mode numbers.
MODES: dict[str, int] = {"MANUAL": 0, "HOLD": 4, "GUIDED": 15}
MODE_NAMES: dict[int, str] = {v: k for k, v in MODES.items()}
#: The commands this link acts on; any other is acknowledged UNSUPPORTED.
ACTED_ON = frozenset((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_SET_MODE,
                      mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, mavlink.MAV_CMD_REQUEST_MESSAGE))
#: The float parameters of each command message (COMMAND_INT's x and y are integers).
_FLOAT_PARAMS = {"COMMAND_LONG": tuple(f"param{i}" for i in range(1, 8)),
                 "COMMAND_INT": ("param1", "param2", "param3", "param4", "z")}
#: COMMAND_ACK ``command`` for a SET_MODE message (its message id, as ArduPilot answers).
SET_MODE_ACK = mavlink.MAVLINK_MSG_ID_SET_MODE
FORCE_ARM_MAGIC = 21196
#: Seconds from the Unix epoch to the MAVLink signing epoch (2015-01-01 00:00:00 UTC).
SIGNING_EPOCH_S = 1_420_070_400
OBSTACLE_BINS = 72
UINT16_MAX = 65535
INT16_MAX = 32767
#: Refusals of one wake-up of the reader: (sender address, counter name) -> count.
Tally = dict[tuple[tuple[Any, ...], str], int]
#: MAVLink signing time units per second (10 µs each).
SIGNING_UNITS_PER_S = 100_000
#: The longest one wake-up drains a socket (ns) before the event loop's other work runs.
DRAIN_BUDGET_NS = 500_000
#: How long a socket that still had datagrams waiting after its budget rests (s): under a flood
#: a socket takes at most budget / (budget + pause) of the loop, about 5 %.
DRAIN_PAUSE_S = 0.010
#: Datagrams read per batch (the station's address is handled first within a batch).
DRAIN_BATCH = 64
#: Largest datagram read (bytes); a MAVLink 2 frame is at most 280.
RECV_SIZE = 65536
#: The log and diagnostics' words for each refusal counter (Refusals reason).
REFUSAL_REASONS = {
    "foreign": "not the ground station's host",
    "bad_data": "malformed datagram",
    "unknown_ids": "unknown message id",
    "mavlink1_refused": "MAVLink 1 frame",
    "unsigned_refused": "unsigned frame",
    "bad_signature": "bad signature",
    "old_timestamp": "replayed or old signing timestamp",
    "future_timestamp": "signing timestamp too far ahead of our clock",
    "other_sender": "not the ground station's system id",
}


def parse_address(text: str, key: str) -> tuple[str, int]:
    """``host:port`` to (host, port); ConfigError naming ``key`` otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(key, f"{text!r} is not host:port")
    return host.strip("[]"), int(port)


def station_host(host: str, key: str) -> str:
    """The ground station's host as datagrams from it name their source: an IP address in its
    canonical form (``2001:DB8::1`` is ``2001:db8::1``), or a loopback name kept as given.

    Any other host name is refused (ConfigError naming ``key``): datagrams are matched by source
    address, so an unresolved name would make every datagram foreign, and a name resolved once at
    start would silently go stale when the laptop's DHCP address changes (or fail at a track
    without DNS).
    """
    if is_loopback(host):
        return host
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        raise ConfigError(key, f"{host!r} is a host name: give the ground station's IP address "
                               "(datagrams are matched by their source address, not by name)") from None


_NEEDS_SIGNING = ("the ground station {} is not on loopback: MAVLink 2 signing is required; set "
                  "signing_key_file to a key file")


@dataclass
class MavlinkParams:
    """The ground-station link: addresses, identity, signing, timeouts and teleop scales."""

    enabled: bool = param(False, "run the MAVLink ground-station link")
    gcs_address: str = param("127.0.0.1:14550", "ground station IP:port telemetry is sent to "
                                                "([::1]:14550 for IPv6; no host names but localhost); "
                                                "port 0 = the port its first authenticated message "
                                                "came from; any non-loopback host requires signing")
    gcs_system_id: int = param(255, "the ground station's system id (ArduPilot's SYSID_MYGCS): only "
                                    "its messages are heard; it alone may arm, set modes and drive",
                               min=1, max=255)
    bind_address: str = param("auto", "local address to bind; auto = the loopback address of the "
                                      "ground station's family (127.0.0.1 or ::1) for a loopback "
                                      "ground station, all addresses (0.0.0.0 or ::) otherwise")
    bind_port: int = param(14555, "local UDP port (0 = ephemeral, for tests)", min=0, max=65535)
    system_id: int = param(1, "our MAVLink system id", min=1, max=255)
    component_id: int = param(1, "our MAVLink component id (1 = autopilot)", min=1, max=255)
    signing_key_file: str = param("", "MAVLink 2 signing key: 64 hex digits, 32 raw bytes, or a "
                                      "passphrase (hashed with SHA-256 as MAVProxy does)")
    signing_link_id: int = param(0, "link id in our signatures", min=0, max=255)
    future_window_s: float = param(60.0, "a signed frame stamped more than this far ahead of this "
                                         "car's wall clock is refused and its stream's timestamp "
                                         "is not advanced, so a station with a wrong clock cannot "
                                         "lock the operator out (beyond MAVLink's signing rules); "
                                         "0 = no limit (a car whose clock is not set)", unit="s",
                                   min=0.0, max=86400.0)
    heartbeat_timeout_s: float = param(2.0, "ground station lost after this long without its "
                                            "heartbeat: its teleop input is dropped", unit="s",
                                       min=0.2, max=60.0)
    input_timeout_s: float = param(1.0, "a MANUAL_CONTROL / RC override stops driving this long "
                                        "after it arrived", unit="s", min=0.05, max=10.0)
    rc_override_time_s: float = param(3.0, "an RC override channel value expires this long after the "
                                           "message that set it (ArduPilot's RC_OVERRIDE_TIME); "
                                           "65535 keeps a live value but never revives an expired "
                                           "one", unit="s", min=0.1, max=60.0)
    max_speed_mps: float = param(2.0, "speed at full throttle", unit="m/s", min=0.0, max=20.0)
    max_steering_rad: float = param(0.34, "steering at full deflection (+ left)", unit="rad",
                                    min=0.0, max=1.0)
    throttle_axis: str = param("z", "MANUAL_CONTROL axis carrying throttle (ArduPilot Rover: z)",
                               choices=("z", "x"))
    rc_min_us: int = param(1000, "RC override PWM at full reverse / full left", min=500, max=1500)
    rc_trim_us: int = param(1500, "RC override PWM at rest", min=800, max=2200)
    rc_max_us: int = param(2000, "RC override PWM at full forward / full right", min=1500, max=2500)
    start_mode: str = param("MANUAL", "mode at start", choices=tuple(MODES))
    rate_hz: float = param(20.0, "teleop command rate", unit="Hz", min=1.0, max=100.0)
    telemetry_rate_hz: float = param(4.0, "ATTITUDE, LOCAL_POSITION_NED, OBSTACLE_DISTANCE rate",
                                     unit="Hz", min=0.1, max=50.0)
    teleop_topic: str = param(TELEOP_TOPIC, "mux input the ground station drives")
    vesc_state_topic: str = param("/vesc/sensors/core", "vesc_msgs/VescStateStamped")
    odom_topic: str = param("/odom", "nav_msgs/Odometry")
    scan_topic: str = param("/scan", "sensor_msgs/LaserScan")
    safety_topic: str = param("/safety/state", "diagnostic_msgs/DiagnosticArray")

    def __post_init__(self) -> None:
        host, _ = parse_address(self.gcs_address, "mavlink.gcs_address")
        station_host(host, "mavlink.gcs_address")
        if not self.rc_min_us < self.rc_trim_us < self.rc_max_us:
            raise ConfigError("mavlink.rc_trim_us", "must lie strictly between rc_min_us and rc_max_us")
        if self.enabled and not self.signing_key_file and not is_loopback(host):
            raise ConfigError("mavlink.signing_key_file", _NEEDS_SIGNING.format(self.gcs_address))

    @property
    def gcs(self) -> tuple[str, int]:
        """The ground station's (host, port); the host as :func:`station_host` gives it."""
        host, port = parse_address(self.gcs_address, "mavlink.gcs_address")
        return station_host(host, "mavlink.gcs_address"), port

    @property
    def bind(self) -> tuple[str, int]:
        """The local (host, port) to bind: IPv6 when the ground station's address is IPv6."""
        host = self.bind_address
        if host == "auto":
            v6 = ":" in self.gcs[0]
            if is_loopback(self.gcs[0]):
                host = "::1" if v6 else "127.0.0.1"
            else:
                host = "::" if v6 else "0.0.0.0"
        return host, self.bind_port


def load_signing_key(path: str, key: str = "mavlink.signing_key_file") -> bytes:
    """The 32-byte secret from a key file (64 hex digits, 32 raw bytes, or a passphrase)."""
    try:
        raw = Path(path).read_bytes()
    except OSError as err:
        raise ConfigError(key, f"cannot read the signing key {path}: {err.strerror}") from err
    text = raw.strip()
    if len(text) == 64:
        with contextlib.suppress(ValueError):
            return bytes.fromhex(text.decode("ascii"))
    if len(raw) == 32:
        return raw
    if not text:
        raise ConfigError(key, f"the signing key file {path} is empty")
    return hashlib.sha256(text).digest()


def write_signing_key(path: str | Path) -> bytes:
    """Create a new random key file (64 hex digits, mode 0600); returns the key."""
    secret = os.urandom(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(secret.hex() + "\n")
    return secret


def signing_timestamp(unix_ns: int) -> int:
    """MAVLink signing time: units of 10 µs since 2015-01-01 UTC."""
    return max(0, (unix_ns - SIGNING_EPOCH_S * NS_PER_S) // 10_000)


# --- frame conversions (pure) ------------------------------------------------------------------

#: ENU (odom, REP-103) to NED: swap x and y, negate z. Also FLU to FRD after a sign flip of y, z.
_ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLU_TO_FRD = np.diag([1.0, -1.0, -1.0])


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The rotation matrix of a unit quaternion (normalised here)."""
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def odom_to_ned(odom: Odometry) -> tuple[tuple[float, float, float], tuple[float, float, float],
                                          tuple[float, float, float], tuple[float, float, float]]:
    """Position NED (m), velocity NED (m/s), attitude (roll, pitch, yaw rad, FRD in NED) and body
    rates (rad/s, FRD) from an odometry message whose pose is ENU (odom frame, x treated as east)
    and whose twist is FLU (base_link)."""
    p = odom.pose.pose.position
    q = odom.pose.pose.orientation
    r_enu_flu = quaternion_matrix(q.x, q.y, q.z, q.w)
    lin = odom.twist.twist.linear
    ang = odom.twist.twist.angular
    v_enu = r_enu_flu @ np.array([lin.x, lin.y, lin.z])
    r = _ENU_TO_NED @ r_enu_flu @ _FLU_TO_FRD
    yaw = math.atan2(r[1, 0], r[0, 0])
    pitch = -math.asin(max(-1.0, min(1.0, r[2, 0])))
    roll = math.atan2(r[2, 1], r[2, 2])
    position = (float(p.y), float(p.x), float(-p.z))
    velocity = (float(v_enu[1]), float(v_enu[0]), float(-v_enu[2]))
    rates = (float(ang.x), float(-ang.y), float(-ang.z))
    return position, velocity, (roll, pitch, yaw), rates


def obstacle_bins(scan: LaserScan, bins: int = OBSTACLE_BINS) -> tuple[list[int], int, int]:
    """OBSTACLE_DISTANCE distances (cm, bin 0 = forward, clockwise), min and max distance (cm).

    The laser frame is taken as aligned with base_link (x forward). A bin with no beam is
    UINT16_MAX (unknown); a bin whose beams saw nothing within range is max + 1 (no obstacle).
    """
    max_cm = int(min(UINT16_MAX - 2, max(1.0, scan.range_max * 100.0)))
    min_cm = int(min(max_cm, max(0.0, scan.range_min * 100.0)))
    out = np.full(bins, UINT16_MAX, dtype=np.int64)
    ranges = np.asarray(scan.ranges, dtype=np.float64)
    if ranges.size == 0:
        return out.tolist(), min_cm, max_cm
    width = 360.0 / bins
    clockwise_deg = np.degrees(-scan.angles())
    index = np.round(clockwise_deg / width).astype(np.int64) % bins
    finite = np.isfinite(ranges) & (ranges >= scan.range_min) & (ranges <= scan.range_max)
    seen = ~np.isnan(ranges)
    out[np.unique(index[seen])] = max_cm + 1
    cm = np.clip(np.round(ranges[finite] * 100.0), 0, max_cm).astype(np.int64)
    hit = np.full(bins, max_cm + 1, dtype=np.int64)
    np.minimum.at(hit, index[finite], cm)
    touched = np.zeros(bins, dtype=bool)
    touched[index[finite]] = True
    out[touched] = hit[touched]
    return out.tolist(), min_cm, max_cm


# --- the link ----------------------------------------------------------------------------------


@dataclass
class ManualInput:
    """The ground station's latest teleop request: speed (m/s), steering (rad, + left), arrival (ns)."""

    speed: float
    steering: float
    received_ns: int
    kind: str


@dataclass(frozen=True)
class ReadOnlyParam:
    """One parameter shown to the ground station (it cannot be set)."""

    name: str
    value: float
    type: int


_SEVERITY = {
    DiagnosticStatus.OK: mavlink.MAV_SEVERITY_INFO,
    DiagnosticStatus.WARN: mavlink.MAV_SEVERITY_WARNING,
    DiagnosticStatus.ERROR: mavlink.MAV_SEVERITY_CRITICAL,
    DiagnosticStatus.STALE: mavlink.MAV_SEVERITY_ERROR,
}


class MavlinkGcs:
    """The ground-station link on the bus. ``await run()`` until cancelled.

    ``status_source`` (optional) returns the daemon's :class:`~racecar_hw.runtime.status.StatusSnapshot`;
    its link counters go into SYS_STATUS ``errors_count1..3`` (VESC CRC errors, VESC reconnects,
    lidar reconnects) and its battery voltage is used while no VESC state has arrived.

    :attr:`counters` (for tests and end-to-end checks): ``rx``, ``tx``, ``foreign`` (datagrams from
    another host), ``bad_data``, ``unsigned_refused``, ``bad_signature``, ``old_timestamp``,
    ``future_timestamp``, ``commands``, ``acks``, ``manual_inputs``, ``inputs_ignored`` (teleop
    outside MANUAL or without a fresh ground-station heartbeat), ``gcs_timeouts``,
    ``teleop_published``, ``statustexts``, ``send_errors``, ``datagrams`` (read from the sockets),
    ``station_datagrams`` (of those, read from the station's own socket), ``drain_rests`` (a socket
    still had datagrams waiting after its budget: a flood), ``signing_restarts``.
    :attr:`heartbeat_gap_max_ns`: the longest time between two heartbeats of a connected station.

    ``refusals``: where refused input is counted and logged (the daemon's; a private one if None).
    """

    def __init__(self, bus: Bus, params: MavlinkParams, arming: Arming,
                 status_source: Callable[[], StatusSnapshot | None] | None = None, *,
                 clock: Callable[[], int] = monotonic_ns, wall_clock: Callable[[], int] = wall_ns,
                 refusals: Refusals | None = None) -> None:
        self.bus = bus
        self.refusals = refusals if refusals is not None else Refusals()
        self.params = params
        self.arming = arming
        self.status_source = status_source
        self._clock = clock
        self._wall_clock = wall_clock
        self._gcs_host, self._gcs_port = params.gcs
        self.secret_key: bytes | None = None
        if params.signing_key_file:
            self.secret_key = load_signing_key(params.signing_key_file)
        elif not is_loopback(self._gcs_host):
            raise ConfigError("mavlink.signing_key_file", _NEEDS_SIGNING.format(params.gcs_address))
        # pymavlink only packs and signs what we send; received datagrams go through self.rx
        self.mav = mavlink.MAVLink(self, params.system_id, params.component_id)
        self.rx = MavlinkRx(self.secret_key, signing_timestamp(wall_clock()),
                            future_window=round(params.future_window_s * SIGNING_UNITS_PER_S))
        if self.secret_key is not None:
            self.mav.signing.secret_key = self.secret_key
            self.mav.signing.link_id = params.signing_link_id
            self.mav.signing.timestamp = self.rx.timestamp
            self.mav.signing.sign_outgoing = True
        self.mode = MODES[params.start_mode]
        self.counters: dict[str, int] = dict.fromkeys((
            "rx", "tx", "foreign", "other_sender", "bad_data", "unknown_ids", "mavlink1_refused",
            "unsigned_refused", "bad_signature", "old_timestamp", "future_timestamp", "commands", "acks",
            "manual_inputs", "inputs_ignored", "gcs_timeouts", "teleop_published", "statustexts",
            "send_errors", "datagrams", "station_datagrams", "drain_rests", "signing_restarts"), 0)
        self.gcs_system_id = params.gcs_system_id
        self.gcs_heartbeat_ns: int | None = None
        self.heartbeat_gap_max_ns = 0
        self.gcs_alive = False
        self.manual: ManualInput | None = None
        self._rc: dict[int, tuple[int, int] | None] = {1: None, 3: None}  # channel: (µs, set at ns)
        self._publishing = False
        #: where telemetry goes: the configured address; with port 0, the first authenticated sender
        self._dest: tuple[str, int] | None = (self._gcs_host, self._gcs_port) if self._gcs_port else None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._sock: socket.socket | None = None  #: everyone's datagrams (and telemetry out, as a fallback)
        self._station_sock: socket.socket | None = None  #: connected to the station: its datagrams
        self._dest_addr: tuple[Any, ...] | None = None  #: _dest as a socket address of our family
        self._paused: dict[int, asyncio.TimerHandle] = {}  #: fd: the resumption of a resting socket
        self._buf = bytearray(RECV_SIZE)
        self._view = memoryview(self._buf)
        self._start_ns = clock()
        self._last_slow_ns: int | None = None
        self._last_fast_ns: int | None = None
        self._safety_key: tuple[int, str] | None = None
        self._vesc: VescStateStamped | None = None
        self._vesc_ns: int | None = None
        self._odom: Odometry | None = None
        self._scan: LaserScan | None = None
        self._scan_ns: int | None = None
        self.parameters = [
            ReadOnlyParam("SYSID_THISMAV", params.system_id, mavlink.MAV_PARAM_TYPE_INT32),
            ReadOnlyParam("FS_GCS_TIMEOUT", params.heartbeat_timeout_s, mavlink.MAV_PARAM_TYPE_REAL32),
            ReadOnlyParam("TELEOP_MAX_SPD", params.max_speed_mps, mavlink.MAV_PARAM_TYPE_REAL32),
            ReadOnlyParam("TELEOP_MAX_STR", params.max_steering_rad, mavlink.MAV_PARAM_TYPE_REAL32),
        ]
        bus.declare(params.teleop_topic, AckermannDriveStamped)
        self._subs: list[Subscription] = [
            bus.subscribe(params.vesc_state_topic, self._on_vesc),
            bus.subscribe(params.odom_topic, self._on_odom),
            bus.subscribe(params.scan_topic, self._on_scan),
            bus.subscribe(params.safety_topic, self._on_safety),
        ]
        self._remove_arming_callback = arming.on_change(self._on_arming)

    # --- properties for the daemon and tests -------------------------------------------------

    @property
    def port(self) -> int:
        """The bound local UDP port (after :meth:`start`)."""
        if self._sock is None:
            raise RuntimeError("the MAVLink link is not started")
        return int(self._sock.getsockname()[1])

    @property
    def station_socket(self) -> bool:
        """True while the ground station's address has its own connected socket."""
        return self._station_sock is not None

    @property
    def mode_name(self) -> str:
        """MANUAL, HOLD or GUIDED."""
        return MODE_NAMES[self.mode]

    @property
    def teleop_active(self) -> bool:
        """True while the ground station's teleop input is being published."""
        return self._publishing

    # --- transport ---------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind the UDP socket, and the ground station's own socket when its port is known."""
        loop = asyncio.get_running_loop()
        host, port = self.params.bind
        infos = await loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM, flags=socket.AI_PASSIVE)
        family, _, _, _, sockaddr = infos[0]
        if sockaddr[1]:
            _check_free(family, sockaddr)
        sock = _udp_socket(family)
        try:
            sock.bind(sockaddr)
            if self._dest is not None:
                dest = await loop.getaddrinfo(*self._dest, family=family, type=socket.SOCK_DGRAM)
                self._dest_addr = dest[0][4]
        except BaseException:
            sock.close()
            raise
        self._loop, self._sock = loop, sock
        loop.add_reader(sock.fileno(), self._on_shared_readable)
        if self._dest_addr is not None:
            self._open_station_socket(self._dest_addr)
        log.info("MAVLink link on udp %s:%d to ground station %s%s", self.params.bind[0], self.port,
                 self.params.gcs_address, " (signed)" if self.secret_key else "")

    def _open_station_socket(self, addr: tuple[Any, ...]) -> None:
        """A second socket on our port, connected to the station: the kernel hands it the
        station's datagrams before the shared socket, so a flood cannot crowd them out. Without
        it (no SO_REUSEPORT, a refused bind) the link works as before on the one socket."""
        if self._sock is None or self._loop is None or self._station_sock is not None:
            return
        sock = _udp_socket(self._sock.family)
        try:
            sock.bind(self._sock.getsockname())
            sock.connect(addr)
        except OSError as err:
            sock.close()
            log.warning("MAVLink: no socket of its own for the ground station (%s); its datagrams "
                        "share the socket with everyone's", err)
            return
        self._station_sock = sock
        self._loop.add_reader(sock.fileno(), self._on_station_readable)

    def write(self, buf: bytes) -> None:
        """pymavlink's file interface: send one packed message to the ground station (dropped and
        counted as a send error when the socket cannot take it now: nothing waits)."""
        try:
            if self._station_sock is not None:
                self._station_sock.send(buf)
            elif self._sock is not None and self._dest_addr is not None:
                self._sock.sendto(buf, self._dest_addr)
            else:
                return
        except OSError:  # a full buffer, or "connection refused" while no station listens
            self.counters["send_errors"] += 1
            return
        self.counters["tx"] += 1

    def close(self) -> None:
        """Unsubscribe and close the sockets (safe twice)."""
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        self._remove_arming_callback()
        for handle in self._paused.values():
            handle.cancel()
        self._paused.clear()
        for sock in (self._station_sock, self._sock):
            if sock is not None:
                if self._loop is not None and not self._loop.is_closed():
                    self._loop.remove_reader(sock.fileno())
                sock.close()
        self._station_sock = self._sock = None

    def restart_signing(self) -> int:
        """Forget every signing stream's timestamp and take our signing time from the wall clock
        again, as a restart of the daemon does: the way back should a wrongly stamped frame ever
        have been accepted (see docs/teleop.md). Our outgoing timestamps restart from the wall
        clock too. Returns how many streams were forgotten."""
        now = signing_timestamp(self._wall_clock())
        forgotten = self.rx.restart(now)
        self.mav.signing.timestamp = now
        self.counters["signing_restarts"] += 1
        log.warning("MAVLink: signing state restarted (%d stream(s) forgotten, our time from the "
                    "wall clock again)", forgotten)
        if self.secret_key is not None:
            self.statustext("Signing state restarted", mavlink.MAV_SEVERITY_NOTICE)
        return forgotten

    # --- receiving -----------------------------------------------------------------------------

    def _on_station_readable(self) -> None:
        self._read(self._station_sock)

    def _on_shared_readable(self) -> None:
        self._read(self._station_sock)  # the station's datagrams first, whichever socket woke us
        self._read(self._sock)

    def _read(self, sock: socket.socket | None) -> None:
        """Drain ``sock`` until empty or the budget is spent (then it rests); its refusals go to
        :attr:`refusals` once per wake-up."""
        if sock is None or sock.fileno() in self._paused:
            return
        tally: Tally = {}
        try:
            emptied = self._drain_socket(sock, time.monotonic_ns() + DRAIN_BUDGET_NS, tally)
        finally:
            for (addr, counter), count in tally.items():
                self._note(addr, counter, count)
        if not emptied and self._loop is not None:
            self.counters["drain_rests"] += 1
            fd = sock.fileno()
            self._loop.remove_reader(fd)
            self._paused[fd] = self._loop.call_later(DRAIN_PAUSE_S, self._resume, sock)

    def _resume(self, sock: socket.socket) -> None:
        """A resting socket reads again."""
        fd = sock.fileno()
        if self._paused.pop(fd, None) is None or self._loop is None or fd < 0:
            return
        station = sock is self._station_sock
        self._loop.add_reader(fd, self._on_station_readable if station else self._on_shared_readable)

    def _drain_socket(self, sock: socket.socket, deadline: int, tally: Tally) -> bool:
        """Read and handle ``sock``'s datagrams in batches; False when the budget ran out first."""
        station = sock is self._station_sock
        dest = self._dest_addr[:2] if self._dest_addr is not None else None
        while True:
            batch: list[tuple[bytes, tuple[Any, ...]]] = []
            empty = False
            for _ in range(DRAIN_BATCH):
                try:
                    n, addr = sock.recvfrom_into(self._buf)
                except BlockingIOError:
                    empty = True
                    break
                except ConnectionRefusedError:  # an ICMP error for an earlier send: not a datagram
                    self.counters["send_errors"] += 1
                    continue
                except OSError:
                    empty = True
                    break
                batch.append((bytes(self._view[:n]), addr))
            self.counters["datagrams"] += len(batch)
            if station:
                self.counters["station_datagrams"] += len(batch)
            elif dest is not None and len(batch) > 1:  # the station's address first (stable)
                batch.sort(key=lambda item: item[1][:2] != dest)
            for data, addr in batch:
                self.handle_datagram(data, addr, tally)
            if empty:
                return True
            if time.monotonic_ns() >= deadline:
                return False

    def _refused(self, addr: tuple[Any, ...], counter: str, tally: Tally | None) -> None:
        """Count a refusal from ``addr`` in :attr:`counters` and the refusals (``tally``: summed
        per wake-up and noted at its end; None: noted at once)."""
        self.counters[counter] += 1
        if tally is None:
            self._note(addr, counter, 1)
        else:
            key = (addr, counter)
            tally[key] = tally.get(key, 0) + 1

    def _note(self, addr: tuple[Any, ...], counter: str, count: int) -> None:
        host, port = addr[0], addr[1]
        source = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        self.refusals.note("mavlink", source, REFUSAL_REASONS[counter], count)

    async def run(self) -> None:
        """Bind (unless started), then tick at ``rate_hz`` until cancelled; a final stop on exit."""
        if self._sock is None:
            await self.start()
        ticker = Ticker(self.params.rate_hz, self._clock)
        try:
            while True:
                await ticker.tick()
                self.tick()
        finally:
            if self._publishing:
                self._publish_drive(AckermannDrive())
                self._publishing = False
            self.close()

    # --- outgoing ----------------------------------------------------------------------------

    def _time_boot_ms(self, now: int) -> int:
        return ((now - self._start_ns) // 1_000_000) & 0xFFFFFFFF

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """Send a STATUSTEXT (at most 50 characters are sent) and log it."""
        log.info("MAVLink status: %s", text)
        self.counters["statustexts"] += 1
        self.mav.statustext_send(severity, text.encode("utf-8", "replace")[:50])

    def send_heartbeat(self) -> None:
        """HEARTBEAT: rover, armed flag, custom mode."""
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.arming.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self.mode == MODES["MANUAL"]:
            base |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        elif self.mode == MODES["GUIDED"]:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        state = mavlink.MAV_STATE_ACTIVE if self.arming.armed else mavlink.MAV_STATE_STANDBY
        self.mav.heartbeat_send(mavlink.MAV_TYPE_GROUND_ROVER, AUTOPILOT, base, self.mode, state)

    def send_autopilot_version(self) -> None:
        """AUTOPILOT_VERSION: what we support (MAVLink 2, COMMAND_INT, C-cast parameter values) and
        racecar-hw's own version as the flight software version (no custom version, vendor or uid)."""
        self.mav.autopilot_version_send(CAPABILITIES, _software_version(__version__), 0, 0, 0,
                                        [0] * 8, [0] * 8, [0] * 8, 0, 0, 0)

    def _sensor_bits(self, now: int) -> tuple[int, int]:
        """SYS_STATUS (present and enabled, healthy): lidar as PROXIMITY, the VESC as MOTOR_OUTPUTS
        and BATTERY; healthy while their messages are fresh."""
        lidar = mavlink.MAV_SYS_STATUS_SENSOR_PROXIMITY
        motor = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
        healthy = 0
        if self._scan_ns is not None and now - self._scan_ns <= SCAN_FRESH_NS:
            healthy |= lidar
        if self._vesc_ns is not None and now - self._vesc_ns <= VESC_FRESH_NS:
            healthy |= motor
        return lidar | motor, healthy

    def send_power(self, now: int) -> None:
        """SYS_STATUS always; BATTERY_STATUS once the VESC has reported."""
        voltage_mv, current_ca = UINT16_MAX, -1
        snapshot = self.status_source() if self.status_source is not None else None
        vesc = self._vesc.state if self._vesc is not None else None
        if vesc is not None:
            voltage_mv = _clamp_int(vesc.voltage_input * 1000.0, 0, UINT16_MAX - 1)
            current_ca = _clamp_int(vesc.current_input * 100.0, -32768, INT16_MAX)
        elif snapshot is not None and snapshot.battery_v is not None and math.isfinite(snapshot.battery_v):
            voltage_mv = _clamp_int(snapshot.battery_v * 1000.0, 0, UINT16_MAX - 1)
        errors = (0, 0, 0)
        if snapshot is not None:
            errors = (snapshot.vesc_crc_errors, snapshot.vesc_reconnects, snapshot.lidar_reconnects)
        present, healthy = self._sensor_bits(now)
        self.mav.sys_status_send(present, present, healthy, 0, voltage_mv, current_ca, -1, 0, 0,
                                 *(min(e, UINT16_MAX) for e in errors), 0)
        if vesc is not None:
            cells = [voltage_mv] + [UINT16_MAX] * 9
            self.mav.battery_status_send(
                0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_UNKNOWN, INT16_MAX, cells,
                current_ca, _clamp_int(vesc.charge_drawn * 1000.0, -1, 2**31 - 1),
                _clamp_int(vesc.energy_drawn * 36.0, -1, 2**31 - 1), -1)

    def send_vfr_hud(self) -> None:
        """VFR_HUD: ground speed (m/s, also shown as airspeed: a car has none) and heading (degrees
        from north, NED) from odometry; throttle = |VESC duty cycle| in percent; altitude 0."""
        speed, heading = 0.0, 0
        if self._odom is not None:
            _, velocity, (_, _, yaw), _ = odom_to_ned(self._odom)
            if all(math.isfinite(v) for v in (*velocity, yaw)):
                speed = math.hypot(velocity[0], velocity[1])
                heading = round(math.degrees(yaw)) % 360
        throttle = 0
        if self._vesc is not None:
            throttle = _clamp_int(abs(self._vesc.state.duty_cycle) * 100.0, 0, 100)
        self.mav.vfr_hud_send(speed, speed, heading, throttle, 0.0, 0.0)

    def send_telemetry(self, now: int) -> None:
        """ATTITUDE, LOCAL_POSITION_NED and VFR_HUD (from odometry) and OBSTACLE_DISTANCE (from the
        scan)."""
        boot_ms = self._time_boot_ms(now)
        if self._odom is not None:
            position, velocity, attitude, rates = odom_to_ned(self._odom)
            if all(math.isfinite(v) for v in (*position, *velocity, *attitude, *rates)):
                self.mav.attitude_send(boot_ms, *attitude, *rates)
                self.mav.local_position_ned_send(boot_ms, *position, *velocity)
            self.send_vfr_hud()
        if self._scan is not None:
            distances, min_cm, max_cm = obstacle_bins(self._scan)
            self.mav.obstacle_distance_send(
                self._wall_clock() // 1000, mavlink.MAV_DISTANCE_SENSOR_LASER, distances, 0, min_cm, max_cm,
                360.0 / OBSTACLE_BINS, 0.0, mavlink.MAV_FRAME_BODY_FRD)

    def _ack(self, command: int, result: int, msg: Any) -> None:
        self.counters["acks"] += 1
        self.mav.command_ack_send(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    # --- the fixed-rate step ---------------------------------------------------------------------

    def tick(self, now_ns: int | None = None) -> None:
        """Heartbeat watch, teleop publishing, and telemetry when due."""
        now = self._clock() if now_ns is None else now_ns
        timeout = round(self.params.heartbeat_timeout_s * NS_PER_S)
        if self.gcs_alive and (self.gcs_heartbeat_ns is None or now - self.gcs_heartbeat_ns > timeout):
            self.gcs_alive = False
            self.counters["gcs_timeouts"] += 1
            self.manual = None
            log.warning("MAVLink: ground station heartbeat lost (%.1f s): its teleop input is dropped",
                        self.params.heartbeat_timeout_s)
            self.statustext("GCS heartbeat lost: teleop input dropped", mavlink.MAV_SEVERITY_WARNING)
        drive = self._teleop_command(now)
        if drive is not None:
            self._publish_drive(drive)
            self._publishing = True
        elif self._publishing:
            self._publish_drive(AckermannDrive())
            self._publishing = False
        if self._sock is None:
            return
        if self._last_slow_ns is None or now - self._last_slow_ns >= NS_PER_S:
            self._last_slow_ns = now
            self.send_heartbeat()
            self.send_power(now)
        if self._last_fast_ns is None or now - self._last_fast_ns >= NS_PER_S / self.params.telemetry_rate_hz:
            self._last_fast_ns = now
            self.send_telemetry(now)

    def _teleop_command(self, now: int) -> AckermannDrive | None:
        manual = self._live_input(now)
        if manual is None or not self.gcs_alive or self.mode != MODES["MANUAL"]:
            return None
        if now - manual.received_ns > round(self.params.input_timeout_s * NS_PER_S):
            return None
        return AckermannDrive(steering_angle=manual.steering, speed=manual.speed)

    def _live_input(self, now: int) -> ManualInput | None:
        """The latest teleop input with RC override expiry applied at ``now`` (on every tick and
        command, not only when a new RC message comes): an expired channel is at rest, and with both
        channels released or expired the override ends."""
        manual = self.manual
        if manual is None or manual.kind != "rc_override":
            return manual
        steering, throttle = self._rc_value(1, now), self._rc_value(3, now)
        if steering is None and throttle is None:
            self.manual = None
        else:
            self.manual = dataclasses.replace(manual, speed=self._pwm(throttle) * self.params.max_speed_mps,
                                              steering=-self._pwm(steering) * self.params.max_steering_rad)
        return self.manual

    def _publish_drive(self, drive: AckermannDrive) -> None:
        msg = AckermannDriveStamped(stamp_now("base_link", self._wall_clock()), drive)
        self.bus.publish(self.params.teleop_topic, msg)
        self.counters["teleop_published"] += 1

    def filter(self, drive: AckermannDrive, source: str, now_ns: int) -> AckermannDrive:
        """Mux filter: a stop while the mode is HOLD; ``drive`` unchanged otherwise."""
        return AckermannDrive() if self.mode == MODES["HOLD"] else drive

    # --- incoming ----------------------------------------------------------------------------

    def handle_datagram(self, data: bytes, addr: tuple[Any, ...], tally: Tally | None = None) -> None:
        """One UDP datagram from ``addr``: decode it alone and act on every verified message of
        the ground station in it. Refusals are counted in :attr:`counters` and :attr:`refusals`
        (``tally``: summed there for the caller to note; None: noted at once). Never raises."""
        host = addr[0]
        if host != self._gcs_host and not (is_loopback(host) and is_loopback(self._gcs_host)):
            self._refused(addr, "foreign", tally)
            return
        rx = self.rx
        refusal = rx.refuse_cheaply(data)  # an unsigned or forged frame: one hash, nothing parsed
        if refusal is not None:
            self._refused(addr, refusal, tally)
            return
        # our signing time follows the wall clock and every accepted timestamp, and never goes back
        wall = signing_timestamp(self._wall_clock())
        rx.timestamp = max(rx.timestamp, self.mav.signing.timestamp, wall)
        messages = rx.decode(data, wall)
        self.mav.signing.timestamp = max(self.mav.signing.timestamp, rx.timestamp)
        for counter in rx.refused:
            self._refused(addr, counter, tally)
        now = self._clock()
        for msg in messages:
            if msg.get_srcSystem() != self.gcs_system_id:
                self._refused(addr, "other_sender", tally)  # another system: heard, never obeyed
                continue
            self.counters["rx"] += 1
            if self._dest is None:  # gcs_address port 0: the first authenticated station
                self._dest = (host, addr[1])
                self._dest_addr = addr
                log.info("MAVLink telemetry to %s port %d", host, addr[1])
                self._open_station_socket(addr)
            kind = msg.get_type()
            try:
                self._dispatch(kind, msg, now)
            except Exception:
                log.exception("MAVLink %s handling failed", kind)

    def _for_us(self, system: int, component: int | None = None) -> bool:
        if system not in (0, self.params.system_id):
            return False
        return component is None or component in (0, self.params.component_id)

    def _dispatch(self, kind: str, msg: Any, now: int) -> None:
        if kind == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS:
                if self.gcs_alive and self.gcs_heartbeat_ns is not None:
                    self.heartbeat_gap_max_ns = max(self.heartbeat_gap_max_ns, now - self.gcs_heartbeat_ns)
                self.gcs_heartbeat_ns = now
                if not self.gcs_alive:
                    self.gcs_alive = True
                    self.statustext("GCS connected")
        elif kind == "MANUAL_CONTROL":
            if self._for_us(msg.target):
                self._take_manual_control(msg, now)
        elif kind == "RC_CHANNELS_OVERRIDE":
            if self._for_us(msg.target_system, msg.target_component):
                self._take_rc_override(msg, now)
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if self._for_us(msg.target_system, msg.target_component):
                self.counters["commands"] += 1
                try:
                    result = self._command(msg, now)
                except Exception:
                    log.exception("MAVLink command %s failed", msg.command)
                    result = mavlink.MAV_RESULT_FAILED
                self._ack(msg.command, result, msg)
                self._send_requested(msg, result)
        elif kind == "SET_MODE":
            if self._for_us(msg.target_system):
                self.counters["commands"] += 1
                self._ack(SET_MODE_ACK, self._set_mode(msg.custom_mode), msg)
        elif kind == "PARAM_REQUEST_LIST":
            if self._for_us(msg.target_system, msg.target_component):
                for index in range(len(self.parameters)):
                    self._send_param(index)
        elif kind == "PARAM_REQUEST_READ":
            if self._for_us(msg.target_system, msg.target_component):
                index = self._param_index(msg.param_id, msg.param_index)
                if index is not None:
                    self._send_param(index)
        elif kind == "PARAM_SET" and self._for_us(msg.target_system, msg.target_component):
            index = self._param_index(msg.param_id, -1)
            if index is not None:
                self._send_param(index)  # read-only: the unchanged value says "refused"

    def _param_index(self, name: str | bytes, index: int) -> int | None:
        if isinstance(name, bytes):
            name = name.decode("ascii", "replace")
        name = name.rstrip("\x00")
        if index >= 0:
            return index if index < len(self.parameters) else None
        for i, p in enumerate(self.parameters):
            if p.name == name:
                return i
        return None

    def _send_param(self, index: int) -> None:
        p = self.parameters[index]
        self.mav.param_value_send(p.name.encode("ascii"), float(p.value), p.type, len(self.parameters), index)

    def _accept_input(self) -> bool:
        if not self.gcs_alive or self.mode != MODES["MANUAL"]:
            self.counters["inputs_ignored"] += 1
            return False
        self.counters["manual_inputs"] += 1
        return True

    def _take_manual_control(self, msg: Any, now: int) -> None:
        if not self._accept_input():
            return
        throttle = msg.z if self.params.throttle_axis == "z" else msg.x
        self.manual = ManualInput(_axis(throttle) * self.params.max_speed_mps,
                                  -_axis(msg.y) * self.params.max_steering_rad, now, "manual_control")

    def _rc_value(self, channel: int, now: int) -> int | None:
        """The live override of ``channel`` (µs), or None when released or expired."""
        held = self._rc[channel]
        if held is None:
            return None
        if now - held[1] > round(self.params.rc_override_time_s * NS_PER_S):
            self._rc[channel] = None  # expired: 65535 cannot bring it back
            return None
        return held[0]

    def _take_rc_override(self, msg: Any, now: int) -> None:
        for channel, raw in ((1, msg.chan1_raw), (3, msg.chan3_raw)):
            if raw == UINT16_MAX:
                self._rc_value(channel, now)  # "unchanged": a live value stays as it was set
                continue
            self._rc[channel] = None if raw == 0 else (raw, now)
        steering, throttle = self._rc_value(1, now), self._rc_value(3, now)
        if steering is None and throttle is None:
            if self.manual is not None and self.manual.kind == "rc_override":
                self.manual = None  # both channels released or expired: stop driving now
            return
        if not self._accept_input():
            return
        self.manual = ManualInput(self._pwm(throttle) * self.params.max_speed_mps,
                                  -self._pwm(steering) * self.params.max_steering_rad, now, "rc_override")

    def _pwm(self, raw: int | None) -> float:
        """-1..1 from a PWM width (µs); None (released) is 0."""
        if raw is None:
            return 0.0
        p = self.params
        if raw >= p.rc_trim_us:
            return min(1.0, (raw - p.rc_trim_us) / (p.rc_max_us - p.rc_trim_us))
        return max(-1.0, (raw - p.rc_trim_us) / (p.rc_trim_us - p.rc_min_us))

    def _input_fresh(self, manual: ManualInput | None, now: int) -> bool:
        return (manual is not None
                and now - manual.received_ns <= round(self.params.input_timeout_s * NS_PER_S))

    def _command(self, msg: Any, now: int) -> int:
        """The result of a COMMAND_LONG / COMMAND_INT (every one is acknowledged). A command we act
        on is DENIED, and changes nothing, when any of its float parameters, used or not, is NaN or
        infinite (none of them has NaN as its default in MAVLink's common.xml)."""
        command, param1, param2 = msg.command, msg.param1, msg.param2
        if command not in ACTED_ON:
            return mavlink.MAV_RESULT_UNSUPPORTED
        if not all(math.isfinite(getattr(msg, name)) for name in _FLOAT_PARAMS[msg.get_type()]):
            self.statustext(f"Command {command} denied: NaN/inf parameter", mavlink.MAV_SEVERITY_WARNING)
            return mavlink.MAV_RESULT_DENIED
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if param1 == 1.0:
                manual = self._live_input(now)
                if (self._input_fresh(manual, now) and manual is not None and manual.speed != 0.0
                        and param2 != FORCE_ARM_MAGIC):
                    self.statustext("Arm refused: GCS throttle not centred", mavlink.MAV_SEVERITY_WARNING)
                    return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                self.arming.arm("gcs", "armed by the ground station")
                return mavlink.MAV_RESULT_ACCEPTED
            if param1 == 0.0:
                self.arming.disarm("gcs", "disarmed by the ground station")
                return mavlink.MAV_RESULT_ACCEPTED
            return mavlink.MAV_RESULT_DENIED
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            return self._set_mode(round(param2))
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return mavlink.MAV_RESULT_ACCEPTED if param1 == 1.0 else mavlink.MAV_RESULT_DENIED
        # MAV_CMD_REQUEST_MESSAGE
        return (mavlink.MAV_RESULT_ACCEPTED if round(param1) in self._requestable
                else mavlink.MAV_RESULT_UNSUPPORTED)

    @property
    def _requestable(self) -> dict[int, Callable[[], None]]:
        """Messages MAV_CMD_REQUEST_MESSAGE can ask for, by message id."""
        now = self._clock()
        return {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self.send_heartbeat,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.send_autopilot_version,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: lambda: self.send_power(now),
            mavlink.MAVLINK_MSG_ID_VFR_HUD: self.send_vfr_hud,
        }

    def _send_requested(self, msg: Any, result: int) -> None:
        """After an accepted request's ACK: the message it asked for."""
        if result != mavlink.MAV_RESULT_ACCEPTED:
            return
        if msg.command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self.send_autopilot_version()
        elif msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            self._requestable[round(msg.param1)]()

    def _set_mode(self, custom_mode: int) -> int:
        if custom_mode not in MODE_NAMES:
            self.statustext(f"Mode {custom_mode} not supported", mavlink.MAV_SEVERITY_WARNING)
            return mavlink.MAV_RESULT_DENIED
        if custom_mode != self.mode:
            self.mode = custom_mode
            self.statustext(f"Mode {MODE_NAMES[custom_mode]}", mavlink.MAV_SEVERITY_NOTICE)
        return mavlink.MAV_RESULT_ACCEPTED

    # --- bus callbacks -----------------------------------------------------------------------

    def _on_vesc(self, msg: VescStateStamped) -> None:
        self._vesc = msg
        self._vesc_ns = self._clock()

    def _on_odom(self, msg: Odometry) -> None:
        self._odom = msg

    def _on_scan(self, msg: LaserScan) -> None:
        self._scan = msg
        self._scan_ns = self._clock()

    def _on_safety(self, msg: DiagnosticArray) -> None:
        """A STATUSTEXT when the safety controller's level or reason changes (not for a first OK)."""
        status = next((s for s in msg.status if s.name == "safety"), msg.status[0] if msg.status else None)
        if status is None:
            return
        key = (status.level, status.message)
        if key == self._safety_key:
            return
        first = self._safety_key is None
        self._safety_key = key
        if not (first and status.level == DiagnosticStatus.OK):
            self.statustext(f"Safety: {status.message}",
                            _SEVERITY.get(status.level, mavlink.MAV_SEVERITY_WARNING))

    def _on_arming(self, change: ArmingChange) -> None:
        self.statustext(("Armed" if change.armed else "Disarmed") + f" by {change.source}",
                        mavlink.MAV_SEVERITY_NOTICE)
        self.send_heartbeat()


def _udp_socket(family: int) -> socket.socket:
    """A non-blocking UDP socket that may share its port with our other one (``SO_REUSEPORT``
    shares only with sockets of the same user)."""
    sock = socket.socket(family, socket.SOCK_DGRAM)
    sock.setblocking(False)
    reuse_port = getattr(socket, "SO_REUSEPORT", None)
    if reuse_port is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, reuse_port, 1)
    return sock


def _check_free(family: int, sockaddr: tuple[Any, ...]) -> None:
    """Raise the OSError (address in use) a plain bind gets when another socket holds the port:
    with ``SO_REUSEPORT`` a second racecar-hw of the same user would otherwise share it silently
    (each probes first, and a probe without ``SO_REUSEPORT`` cannot join a group)."""
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        probe.bind(sockaddr)


def _axis(value: int) -> float:
    """A MANUAL_CONTROL axis (-1000..1000; INT16_MAX = unused, taken as centred) to -1..1."""
    if value == INT16_MAX:
        return 0.0
    return max(-1.0, min(1.0, value / 1000.0))


def _software_version(text: str) -> int:
    """``major.minor.patch`` as AUTOPILOT_VERSION encodes it (ArduPilot's layout: one byte each,
    then the release type; we say FIRMWARE_VERSION_TYPE_DEV)."""
    parts = [int(p) if p.isdigit() else 0 for p in text.split(".")[:3]] + [0, 0, 0]
    major, minor, patch = (min(255, v) for v in parts[:3])
    return (major << 24) | (minor << 16) | (patch << 8) | mavlink.FIRMWARE_VERSION_TYPE_DEV


def _clamp_int(value: float, lo: int, hi: int) -> int:
    if not math.isfinite(value):
        return lo
    return int(max(lo, min(hi, round(value))))


__all__ = ["MODES", "MavlinkGcs", "MavlinkParams", "load_signing_key", "obstacle_bins", "odom_to_ned",
           "signing_timestamp", "write_signing_key"]
