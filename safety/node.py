"""Bus adapters of the safety controller.

:class:`SafetyNode` sits between the mux and the VESC: the daemon passes every arbitrated command
through :meth:`SafetyNode.filter`. It listens to ``/scan`` and ``/odom`` and publishes its verdict
on ``/safety/state`` (diagnostic_msgs/DiagnosticArray) when it changes and at a low rate.

:class:`ConeSafety` is the seeds' simple safety node (UW CSE490R lab 0): while a valid range in a
forward cone is shorter than a threshold, it publishes a zero-speed AckermannDriveStamped on the
mux's top-priority safety input at the scan rate, and publishes nothing otherwise so the mux falls
through to the other sources once the input times out.

All times are ``racecar_hw.base.clock.monotonic_ns`` unless a caller passes its own clock.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
from collections.abc import Callable

import numpy as np

from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    DiagnosticArray,
    DiagnosticStatus,
    Header,
    KeyValue,
    LaserScan,
    Odometry,
    Time,
    stamp_now,
)
from safety.controller import LaserTransform, SafetyController, SafetyState
from safety.params import ConeParams, SafetyParams

log = logging.getLogger(__name__)

_LEVELS = {
    "clear": DiagnosticStatus.OK, "exempt": DiagnosticStatus.OK,
    "obstacle": DiagnosticStatus.WARN, "reverse_cap": DiagnosticStatus.WARN,
    "off": DiagnosticStatus.WARN,
    "stale_scan": DiagnosticStatus.ERROR, "no_scan": DiagnosticStatus.ERROR,
    "bad_scan": DiagnosticStatus.ERROR, "fault": DiagnosticStatus.ERROR,
}


#: The longest sweep :func:`sweep_ns` believes (s): a lidar turns at least once a second.
MAX_SWEEP_S = 1.0


def sweep_ns(scan: LaserScan) -> int:
    """How long (ns) before its last beam a scan's first beam was measured: ``|time_increment|``
    times the beams between them, at most the scan's ``scan_time`` (when it gives one) and
    :data:`MAX_SWEEP_S`; 0 when the scan does not say (a non-finite or zero increment)."""
    step = abs(float(scan.time_increment))
    if not (math.isfinite(step) and step > 0.0):
        return 0
    span = step * max(len(scan.ranges) - 1, 0)
    period = float(scan.scan_time)
    if math.isfinite(period) and period > 0.0:
        span = min(span, period)
    return round(min(span, MAX_SWEEP_S) * NS_PER_S)


class SafetyNode:
    """The safety controller on the bus: scans and odometry in, filtered commands and state out.

    An unexpected exception inside the controller latches a fault: every later command is
    braked to speed 0 until :meth:`reset_fault`.
    """

    def __init__(self, bus: Bus, params: SafetyParams, laser_to_base: LaserTransform | None = None,
                 clock: Callable[[], int] = monotonic_ns, defer_memory: bool = False,
                 steering_limit_rad: float | tuple[float, float] = math.inf,
                 scans_from_bus: bool = True) -> None:
        """``defer_memory``: leave the memory update of each scan to :meth:`remember` (the daemon
        calls it after the scan's motor command is written); otherwise it follows each scan.
        ``steering_limit_rad``: the steering the car can drive (see :class:`SafetyController`).
        ``scans_from_bus``: take scans from ``scan_topic`` on the bus; False: the caller hands each
        scan to :meth:`take_scan` (the daemon's control path, before the scan is on the bus)."""
        self.bus = bus
        self.params = params
        self.clock = clock
        self.controller = SafetyController(params, laser_to_base, steering_limit_rad)
        self.cone = (ConeSafety(bus, params.cone, params.scan_topic) if params.mode == "cone"
                     else None)
        self.fault: str | None = None
        self.faults = 0
        self.defer_memory = defer_memory
        self._odom: tuple[float, int] | None = None
        # the odometry pose: x, y, yaw, speed, yaw rate and when it came (monotonic ns)
        self._odom_pose: tuple[float, float, float, float, float, int] | None = None
        self._last_command_ns: int | None = None
        self._last_publish_ns: int | None = None
        self._published_key: tuple[str, bool] | None = None
        self._source = ""
        self._commanded = 0.0
        self._output = 0.0
        bus.declare(params.state_topic, DiagnosticArray)
        self._subs: list[Subscription] = [bus.subscribe(params.odom_topic, self._on_odom)]
        if scans_from_bus:
            self._subs.append(bus.subscribe(params.scan_topic, self.take_scan))

    @property
    def state(self) -> SafetyState:
        """The latest verdict."""
        if self.fault is not None:
            return SafetyState(0.0, math.nan, None, "fault", True)
        return self.controller.state

    @property
    def interventions(self) -> int:
        """How many interventions have started."""
        return self.controller.interventions

    def take_scan(self, scan: LaserScan) -> None:
        """Judge the next commands against ``scan`` (never raises: a failure latches a fault).

        The scan's points are where the lidar saw them, relative to where the car was then: the
        odometry pose the controller places them with (in the obstacle memory) and brings the
        remembered points into their frame with is the one at the sweep's first beam
        (:func:`sweep_ns` before the scan's arrival), not at its arrival, up to 19 ms later for a
        UST-10LX: at 5 m/s in a full-lock turn that placed a pole 0.28 m from where it was."""
        now = self.clock()
        try:
            placed = now - sweep_ns(scan)
            self.controller.on_scan(scan, now, self.pose_at(placed), placed)
        except Exception as err:
            self._latch(err, "taking a scan in")
            return
        if not self.defer_memory:
            self.remember()

    def remember(self) -> None:
        """Fold the latest scan into the obstacle memory; never raises (a failure latches a fault)."""
        if self.fault is not None:
            return
        try:
            self.controller.remember()
        except Exception as err:
            self._latch(err, "the obstacle memory")

    def _latch(self, err: Exception, what: str) -> None:
        """Latch a fault for ``err``, raised by the controller in ``what``: brake until reset."""
        self.fault = f"{type(err).__name__}: {err}"
        self.faults += 1
        log.exception("safety: %s failed; braking every command until reset", what)

    def _on_odom(self, odom: Odometry) -> None:
        now = self.clock()
        twist = odom.twist.twist
        self._odom = (float(twist.linear.x), now)
        pose = odom.pose.pose
        self._odom_pose = (float(pose.position.x), float(pose.position.y), pose.orientation.yaw(),
                           float(twist.linear.x), float(twist.angular.z), now)

    def pose_at(self, now_ns: int) -> tuple[float, float, float] | None:
        """base_link in odom at ``now_ns``: the latest odometry pose carried by its twist to that
        time, forward or back (at most ``odom_timeout_s``); None without odometry that near or
        finite."""
        if self._odom_pose is None:
            return None
        x, y, yaw, v, w, at = self._odom_pose
        dt = (now_ns - at) / NS_PER_S
        if abs(dt) > self.params.odom_timeout_s:
            return None
        heading = yaw + 0.5 * w * dt
        pose = (x + v * dt * math.cos(heading), y + v * dt * math.sin(heading), yaw + w * dt)
        return pose if all(math.isfinite(p) for p in pose) else None

    def measured_speed(self, now_ns: int) -> float:
        """The odometry speed (m/s), or 0 when there is none fresher than ``odom_timeout_s``."""
        if self._odom is None:
            return 0.0
        speed, at = self._odom
        if now_ns - at > self.params.odom_timeout_s * NS_PER_S or not math.isfinite(speed):
            return 0.0
        return speed

    def filter(self, drive: AckermannDrive, source: str, now_ns: int | None = None) -> AckermannDrive:
        """``drive`` from mux source ``source`` with its speed limited; publishes state changes.

        Never raises: a failure inside the controller latches a fault and brakes.
        """
        now = self.clock() if now_ns is None else now_ns
        out = self.limit(drive, source, now)
        self.publish_state_if_due(now)
        return out

    def limit(self, drive: AckermannDrive, source: str, now_ns: int) -> AckermannDrive:
        """What :meth:`filter` returns, leaving the state to :meth:`publish_state_if_due`.

        For the scan path: it writes the motor command first and publishes the state after.
        """
        self._last_command_ns = now_ns
        self._source = source
        self._commanded = _finite_or_zero(drive.speed)
        out = self._limit(drive, source, now_ns)
        self._output = float(out.speed)
        return out

    def _limit(self, drive: AckermannDrive, source: str, now: int) -> AckermannDrive:
        if self.fault is None:
            try:
                out, _ = self.controller.limit(drive, source, self.measured_speed(now), now)
                return out
            except Exception as err:
                self._latch(err, "limiting a command")
        return dataclasses.replace(drive, speed=0.0, steering_angle=_finite_or_zero(drive.steering_angle))

    def reset_fault(self) -> None:
        """Clear a latched controller fault."""
        self.fault = None

    def tick(self, now_ns: int | None = None) -> None:
        """Refresh and publish the state when due; with no recent command, assess a stop command."""
        now = self.clock() if now_ns is None else now_ns
        period = NS_PER_S / self.params.state_rate_hz
        if self._last_command_ns is None or now - self._last_command_ns >= period:
            self._limit(AckermannDrive(), "", now)
            self._source, self._commanded, self._output = "", 0.0, 0.0
        self.publish_state_if_due(now)

    async def run(self) -> None:
        """Publish the state at ``state_rate_hz`` until cancelled."""
        period = 1.0 / self.params.state_rate_hz
        while True:
            self.tick()
            await asyncio.sleep(period)

    def publish_state_if_due(self, now: int) -> None:
        """Publish the state if it changed or ``state_rate_hz`` says it is due."""
        state = self.state
        key = (state.reason, state.intervening)
        due = (self._last_publish_ns is None
               or now - self._last_publish_ns >= NS_PER_S / self.params.state_rate_hz)
        if key != self._published_key or due:
            self.bus.publish(self.params.state_topic, self.state_message())
            self._published_key = key
            self._last_publish_ns = now

    def state_message(self) -> DiagnosticArray:
        """The current state as one DiagnosticStatus named ``safety``."""
        s = self.state
        obstacle = s.obstacle
        memory = self.controller.memory
        values = {
            "mode": self.params.mode,
            "reason": s.reason,
            "intervening": str(s.intervening).lower(),
            "allowed_speed": f"{s.allowed_speed:.3f}",
            "free_distance": f"{s.free_distance:.3f}",
            "obstacle_x": f"{obstacle.x:.3f}" if obstacle else "",
            "obstacle_y": f"{obstacle.y:.3f}" if obstacle else "",
            "obstacle_distance": f"{obstacle.distance:.3f}" if obstacle else "",
            "obstacle_source": obstacle.source if obstacle else "",
            "memory": ("off" if memory is None
                       else "on" if self.controller.memory_active else "no_odometry"),
            "memory_points": str(memory.points().size) if memory is not None else "0",
            "source": self._source,
            "commanded_speed": f"{self._commanded:.3f}",
            "output_speed": f"{self._output:.3f}",
            "interventions": str(self.controller.interventions),
            "fault": self.fault or "",
        }
        if self.cone is not None:
            values["cone_stopping"] = str(self.cone.stopping).lower()
            values["cone_closest"] = f"{self.cone.closest:.3f}"
        status = DiagnosticStatus(level=_LEVELS.get(s.reason, DiagnosticStatus.ERROR), name="safety",
                                  message=s.reason, hardware_id="racecar-hw",
                                  values=[KeyValue(k, v) for k, v in values.items()])
        return DiagnosticArray(header=stamp_now("base_link", wall_ns()), status=[status])

    def close(self) -> None:
        """Stop listening (safe to call twice)."""
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        if self.cone is not None:
            self.cone.close()


def _finite_or_zero(value: object) -> float:
    """``value`` as a finite float, or 0.0 when it is not a finite number (the node never raises,
    whatever a caller hands it; behind the mux every command is finite already)."""
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return 0.0
    return number if math.isfinite(number) else 0.0


class ConeSafety:
    """The seeds' safety node: zero speed on the mux safety input while the cone is blocked.

    The cone is ``|angle| <= half_angle_rad`` around the laser's x axis. A range counts when it is
    finite and within [range_min, range_max]. Once stopping, it keeps stopping until every range in
    the cone exceeds ``stop_distance_m + release_margin_m``. Steering in the stop command is 0.
    """

    def __init__(self, bus: Bus, params: ConeParams, scan_topic: str = "/scan",
                 frame_id: str = "base_link") -> None:
        self.bus = bus
        self.params = params
        self.frame_id = frame_id
        self.stopping = False
        self.closest = math.inf
        self.stops_published = 0
        bus.declare(params.topic, AckermannDriveStamped)
        self._sub: Subscription | None = bus.subscribe(scan_topic, self.on_scan)

    def on_scan(self, scan: LaserScan) -> bool:
        """Judge one scan, publish a stop if the cone is blocked, and return whether it is."""
        r = np.asarray(scan.ranges, dtype=np.float64)
        angles = np.mod(scan.angles() + math.pi, 2.0 * math.pi) - math.pi
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(r) & (r >= scan.range_min) & (np.abs(angles) <= self.params.half_angle_rad)
            if scan.range_max > scan.range_min:
                valid &= r <= scan.range_max
        self.closest = float(r[valid].min()) if valid.any() else math.inf
        threshold = self.params.stop_distance_m
        if self.stopping:
            threshold += self.params.release_margin_m
        if self.closest < threshold and not self.stopping:
            log.warning("safety cone: stopping, obstacle at %.2f m", self.closest)
        self.stopping = self.closest < threshold
        if self.stopping:
            stamp = Time(scan.header.stamp.sec, scan.header.stamp.nanosec)
            stop = AckermannDriveStamped(Header(stamp, self.frame_id), AckermannDrive())
            self.bus.publish(self.params.topic, stop)
            self.stops_published += 1
        return self.stopping

    def close(self) -> None:
        """Stop listening (safe to call twice)."""
        if self._sub is not None:
            self._sub.close()
            self._sub = None
