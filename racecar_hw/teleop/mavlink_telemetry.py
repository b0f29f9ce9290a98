"""The car's state as MAVLink telemetry: the frame conversions and the telemetry streams.

HEARTBEAT (1 Hz; armed flag from :class:`~racecar_hw.teleop.arming.Arming`), SYS_STATUS (with
sensor bits for the lidar and the motor controller) and BATTERY_STATUS (1 Hz, from
``/vesc/sensors/core``), ATTITUDE, LOCAL_POSITION_NED and VFR_HUD (from ``/odom``, REP-103 ENU/FLU
converted to NED/FRD) and OBSTACLE_DISTANCE (72 bins of 5 degrees in cm, from ``/scan``) at
``telemetry_rate_hz``, STATUSTEXT for events, AUTOPILOT_VERSION on request.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from racecar_hw import __version__
from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.messages import DiagnosticArray, DiagnosticStatus, LaserScan, Odometry, VescStateStamped
from racecar_hw.runtime.status import StatusSnapshot
from racecar_hw.teleop.arming import Arming
from racecar_hw.teleop.mavlink_dialect import AUTOPILOT, INT16_MAX, MODES, UINT16_MAX, mavlink

log = logging.getLogger(__name__)

#: AUTOPILOT_VERSION capabilities: only what this link does.
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)
#: SYS_STATUS reports the lidar healthy while scans are this fresh, the VESC while its telemetry is.
SCAN_FRESH_NS = NS_PER_S
VESC_FRESH_NS = NS_PER_S // 2
OBSTACLE_BINS = 72
#: STATUSTEXT severity of each safety level.
_SEVERITY = {
    DiagnosticStatus.OK: mavlink.MAV_SEVERITY_INFO,
    DiagnosticStatus.WARN: mavlink.MAV_SEVERITY_WARNING,
    DiagnosticStatus.ERROR: mavlink.MAV_SEVERITY_CRITICAL,
    DiagnosticStatus.STALE: mavlink.MAV_SEVERITY_ERROR,
}

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


# --- the streams -------------------------------------------------------------------------------


class Telemetry:
    """What the ground station is told: the latest VESC state, odometry and scan from the bus,
    encoded and sent through ``mav`` (pymavlink's packer) when :meth:`send_due` finds a stream due,
    and a STATUSTEXT when the safety state (``topics``' fourth) changes.

    ``mode`` gives the current custom mode; ``status_source`` (optional) the daemon's
    :class:`~racecar_hw.runtime.status.StatusSnapshot` (link counters for SYS_STATUS
    ``errors_count1..3``, the battery voltage while no VESC state has arrived). Times are
    monotonic ns from ``clock``; OBSTACLE_DISTANCE is stamped from ``wall_clock`` (µs).
    """

    def __init__(self, bus: Bus, mav: Any, arming: Arming, mode: Callable[[], int], *,
                 topics: tuple[str, str, str, str], telemetry_rate_hz: float, counters: dict[str, int],
                 status_source: Callable[[], StatusSnapshot | None] | None,
                 clock: Callable[[], int], wall_clock: Callable[[], int]) -> None:
        self.mav = mav
        self.arming = arming
        self.status_source = status_source
        self.counters = counters
        self._mode = mode
        self._fast_period_ns = NS_PER_S / telemetry_rate_hz
        self._clock = clock
        self._wall_clock = wall_clock
        self._start_ns = clock()
        self._last_slow_ns: int | None = None
        self._last_fast_ns: int | None = None
        self._vesc: VescStateStamped | None = None
        self._vesc_ns: int | None = None
        self._odom: Odometry | None = None
        self._scan: LaserScan | None = None
        self._scan_ns: int | None = None
        self._safety_key: tuple[int, str] | None = None
        vesc_topic, odom_topic, scan_topic, safety_topic = topics
        self._subs: list[Subscription] = [
            bus.subscribe(vesc_topic, self._on_vesc),
            bus.subscribe(odom_topic, self._on_odom),
            bus.subscribe(scan_topic, self._on_scan),
            bus.subscribe(safety_topic, self._on_safety),
        ]

    def close(self) -> None:
        """Stop listening to the bus (safe twice)."""
        for sub in self._subs:
            sub.close()
        self._subs.clear()

    def send_due(self, now: int) -> None:
        """HEARTBEAT and power once a second, the fast streams at ``telemetry_rate_hz``."""
        if self._last_slow_ns is None or now - self._last_slow_ns >= NS_PER_S:
            self._last_slow_ns = now
            self.send_heartbeat()
            self.send_power(now)
        if self._last_fast_ns is None or now - self._last_fast_ns >= self._fast_period_ns:
            self._last_fast_ns = now
            self.send_telemetry(now)

    def _time_boot_ms(self, now: int) -> int:
        return ((now - self._start_ns) // 1_000_000) & 0xFFFFFFFF

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """Send a STATUSTEXT (at most 50 characters are sent) and log it."""
        log.info("MAVLink status: %s", text)
        self.counters["statustexts"] += 1
        self.mav.statustext_send(severity, text.encode("utf-8", "replace")[:50])

    def send_heartbeat(self) -> None:
        """HEARTBEAT: rover, armed flag, custom mode."""
        mode = self._mode()
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.arming.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if mode == MODES["MANUAL"]:
            base |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        elif mode == MODES["GUIDED"]:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        state = mavlink.MAV_STATE_ACTIVE if self.arming.armed else mavlink.MAV_STATE_STANDBY
        self.mav.heartbeat_send(mavlink.MAV_TYPE_GROUND_ROVER, AUTOPILOT, base, mode, state)

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


__all__ = ["CAPABILITIES", "OBSTACLE_BINS", "Telemetry", "obstacle_bins", "odom_to_ned", "quaternion_matrix"]
