"""The safety-stop controller: cap the commanded speed so the car can always stop before what the
lidar sees on its path.

:class:`SafetyController` is pure logic (no bus, no clock): feed it scans with :meth:`on_scan` and
commands with :meth:`limit`, passing monotonic nanoseconds. It only ever lowers the magnitude of
the speed; it never raises it, never flips its sign and never touches the steering, except to
centre it while the lidar is blind (no, stale or bad scan; ``centre_when_blind``) and to centre a
non-finite steering angle. See ``docs/safety.md`` for the model.

Allowed speed, for a free path length ``d`` along the commanded arc::

    v * latency + v^2 / (2 * max_decel) <= d - margin

where ``latency`` is the configured reaction delay (with the scan's own ``scan_time`` when it is
longer than ``scan_period_s``) plus the age of the cached scan.

With the obstacle memory (``params.memory``, :mod:`safety.memory`) the swept points are the live
scan's and the remembered ones within ``memory.reach_m`` of the car, placed with the odom pose
given with the scan; reverse is then swept too, still capped at ``reverse_speed_cap_mps``. The
memory update is :meth:`SafetyController.remember`, called after the motor command is written.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.messages import AckermannDrive, LaserScan
from safety.arc import PathHit, SweptFootprint, free_distances, stopping_speed
from safety.blind import blind_beams, blind_radius
from safety.memory import ObstacleMemory, plausible_increment
from safety.params import SafetyParams

log = logging.getLogger(__name__)

#: Reasons that mean the lidar gives nothing to trust: allowed speed 0 (and, with
#: ``centre_when_blind``, the steering centred).
BLIND = frozenset(("no_scan", "stale_scan", "bad_scan"))
#: Why the allowed speed is what it is.
REASONS = ("clear", "obstacle", "stale_scan", "no_scan", "bad_scan", "reverse_cap", "exempt", "off",
           "fault")

#: Where the point that limits the path came from: the live scan, a blind sector of it (a run of
#: unusable beams, :mod:`safety.blind`) or the obstacle memory.
SOURCES = ("scan", "blind", "memory")

#: Intervention entries kept in :attr:`SafetyController.events` (the oldest are dropped).
MAX_EVENTS = 1000

#: A laser->base_link transform: a 4x4 homogeneous matrix, or planar (x, y, yaw) in metres/radians.
LaserTransform = np.ndarray | Sequence[float]

#: A planar pose of base_link in odom: x (m), y (m), yaw (rad).
Pose = tuple[float, float, float]


@dataclass(frozen=True)
class Obstacle:
    """The point that limits the path: base_link coordinates (at the cached scan) and path length
    to it, metres; ``source`` is one of :data:`SOURCES`."""

    x: float
    y: float
    distance: float
    source: str = "scan"


@dataclass(frozen=True)
class Intervention:
    """One intervention: when it started and ended (monotonic ns; ``end_ns`` None while it lasts),
    why, and what the controller saw at its start.

    ``obstacle`` is in base_link at the scan received at ``scan_ns`` (None when no point limits the
    path, e.g. a stale scan): where the car was at ``pose_ns``, the time of the odometry pose the
    scan was placed with (its first beam's; None without one); speeds in m/s.

    ``continues``: not a new intervention but the one before it, which started for something else
    (a late scan, the reverse cap), becoming a stop for an obstacle at ``t_ns``: what it stops for
    is only known from then. The entry before it ends at that ``t_ns``.
    """

    t_ns: int
    reason: str
    allowed_speed: float
    commanded_speed: float
    measured_speed: float
    obstacle: Obstacle | None
    scan_ns: int | None
    end_ns: int | None = None
    continues: bool = False
    pose_ns: int | None = None


@dataclass(frozen=True)
class SafetyState:
    """The controller's verdict on one command.

    ``allowed_speed``: largest permitted |speed|, m/s. ``free_distance``: free path length along the
    commanded arc (m, capped at ``max_path_m``; nan when not measured: no usable scan, or reverse
    without a rear view). ``obstacle``: the nearest point on the path, or None. ``reason``: one of
    :data:`REASONS`. ``intervening``: the controller is limiting (entered when the command or the
    measured speed exceeds the allowed speed, left with hysteresis).
    """

    allowed_speed: float
    free_distance: float
    obstacle: Obstacle | None
    reason: str
    intervening: bool


def planar_transform(laser_to_base: LaserTransform) -> np.ndarray:
    """A 2x3 matrix mapping laser-frame (x, y, 1) to base_link (x, y), from a 4x4 or (x, y, yaw).

    A 4x4 transform may hold any 3D rotation (a lidar mounted upside down); scan points lie in the
    laser's xy plane and are projected onto base_link's ground plane.
    """
    m = np.asarray(laser_to_base, dtype=np.float64)
    if m.shape == (4, 4):
        out = np.array([[m[0, 0], m[0, 1], m[0, 3]], [m[1, 0], m[1, 1], m[1, 3]]])
    elif m.shape == (3,):
        x, y, yaw = (float(v) for v in m)
        c, s = math.cos(yaw), math.sin(yaw)
        out = np.array([[c, -s, x], [s, c, y]])
    else:
        raise ValueError(f"laser->base_link transform must be 4x4 or (x, y, yaw), got shape {m.shape}")
    if not np.all(np.isfinite(out)):
        raise ValueError("laser->base_link transform is not finite")
    return out


@dataclass
class _CachedScan:
    """One scan, already reduced to its usable returns as base_link points.

    ``x[:live]``, ``y[:live]`` are the scan's own returns, the next ``blind`` the obstacles put on
    its blind sectors' rays, the rest remembered points; ``pose`` is base_link in odom at
    ``pose_ns`` (None without odometry); ``remembered``: folded into the memory.
    """

    x: np.ndarray
    y: np.ndarray
    received_ns: int
    usable_fraction: float
    sweep_s: float
    return_fraction: float = 1.0  #: beams with a range from range_min to range_max
    live: int = 0
    scan: LaserScan | None = None
    pose: Pose | None = None
    remembered: bool = False
    blind: int = 0
    pose_ns: int | None = None


class _Hysteresis:
    """Intervention state: CLEAR or INTERVENING, entered at once, left only after a held release.

    Transitions (evaluated once per command)::

        CLEAR        --needs cut-------------------------------------> INTERVENING (count, log)
        INTERVENING  --allowed >= ref + margin, held for hold_s------> CLEAR
        INTERVENING  --otherwise-------------------------------------> INTERVENING

    While a release is pending the cap stays at the last allowed speed seen before it started,
    so one noisy scan that briefly clears the path cannot make the output jump up and back.
    """

    def __init__(self, release_margin: float, hold_ns: int) -> None:
        self.release_margin = release_margin
        self.hold_ns = hold_ns
        self.intervening = False
        self.pending_since: int | None = None
        self.held_cap = math.inf

    def reset(self) -> None:
        self.intervening = False
        self.pending_since = None
        self.held_cap = math.inf

    def step(self, needs_cut: bool, allowed: float, ref: float, now_ns: int) -> tuple[float, bool]:
        """The speed cap for this command and whether an intervention just started."""
        if not self.intervening:
            if not needs_cut:
                return math.inf, False
            self.intervening = True
            self.pending_since = None
            self.held_cap = allowed
            return allowed, True
        if allowed >= ref + self.release_margin:
            if self.pending_since is None:
                self.pending_since = now_ns
            if now_ns - self.pending_since >= self.hold_ns:
                self.reset()
                return math.inf, False
            return min(allowed, self.held_cap), False
        self.pending_since = None
        self.held_cap = allowed
        return allowed, False


class SafetyController:
    """Limits Ackermann commands by the free distance along the commanded path.

    ``laser_to_base`` is the pose of the laser in base_link (4x4, or (x, y, yaw)); None takes it
    from ``params.laser``. ``steering_limit_rad`` is the largest steering angle the car can drive
    (the VESC driver's ``steering_max_rad``), or the (right, left) pair it drives at full right and
    full left (:meth:`vesc.ackermann.AckermannConversion.steering_range`, where the servo's limits
    clip a side further): a command beyond it is swept at the limit, the arc the car will actually
    follow. Times are integer nanoseconds on one monotonic clock of the caller's.
    """

    def __init__(self, params: SafetyParams, laser_to_base: LaserTransform | None = None,
                 steering_limit_rad: float | tuple[float, float] = math.inf) -> None:
        self.params = params
        if isinstance(steering_limit_rad, tuple):
            self.steering_range = (float(steering_limit_rad[0]), float(steering_limit_rad[1]))
        else:
            self.steering_range = (-float(steering_limit_rad), float(steering_limit_rad))
        if laser_to_base is None:
            laser_to_base = (params.laser.x_m, params.laser.y_m, params.laser.yaw_rad)
        self._to_base = planar_transform(laser_to_base)
        fp = params.footprint
        self.footprint = SweptFootprint(front_m=fp.front_m, rear_m=fp.rear_overhang_m,
                                        half_width_m=fp.width_m / 2.0 + params.lateral_margin_m,
                                        wheelbase_m=fp.wheelbase_m)
        self._body = SweptFootprint(fp.front_m, fp.rear_overhang_m, fp.width_m / 2.0, fp.wheelbase_m)
        # No return farther than this from the laser can be reached within max_path_m.
        corner = math.hypot(max(fp.front_m, fp.rear_overhang_m), self.footprint.half_width_m)
        self._reach = params.max_path_m + corner + math.hypot(self._to_base[0, 2], self._to_base[1, 2])
        self._scan: _CachedScan | None = None
        # the last free-distance query: its scan, (steering, reverse, max_path_m), PathHit
        self._hit_scan: _CachedScan | None = None
        self._hit_key: tuple[float, bool, float] | None = None
        self._hit = PathHit(math.nan, -1)
        self._live_hit = self._hit  # the nearest of the live scan's own points on that path
        self._dirs_key: tuple[float, float, int] | None = None
        self._dirs = np.zeros(0, dtype=np.complex128)
        self._origin = complex(self._to_base[0, 2], self._to_base[1, 2])  # the laser in base_link
        fp_swept = self.footprint
        self._blind_r = blind_radius(self._origin, fp_swept.front_m, fp_swept.rear_m, fp_swept.half_width_m)
        self._hyst = _Hysteresis(params.release_margin_mps, round(params.release_hold_s * NS_PER_S))
        self._exempt = set(params.exempt_sources)
        if params.exempt_teleop:
            self._exempt.add(params.teleop_source)
        self.interventions = 0
        #: interventions started, by reason (obstacle, stale_scan, no_scan, bad_scan, reverse_cap)
        self.interventions_by_reason: dict[str, int] = {}
        self.state = SafetyState(0.0, math.nan, None, "no_scan", False)
        #: the latest interventions, oldest first: an entry when one starts, and one more when one
        #: that started for another reason becomes a stop for an obstacle (``continues``)
        self.events: deque[Intervention] = deque(maxlen=MAX_EVENTS)
        self._obstacle_noted = False  # the current intervention has an entry with its obstacle
        m = params.memory
        self.memory = (ObstacleMemory(m.size_m, m.resolution_m, m.max_age_s, m.see_through_m, m.reach_m)
                       if m.enabled and params.mode == "arc" else None)
        self._memory_period_ns = round(m.update_period_s * NS_PER_S)
        self._memory_cell_m = m.resolution_m * math.sqrt(2.0)
        self._remembered_ns: int | None = None  # when the memory last took a scan in

    # --- scans --------------------------------------------------------------------------------

    def on_scan(self, scan: LaserScan, now_ns: int, pose: Pose | None = None,
                pose_ns: int | None = None) -> None:
        """Cache ``scan`` (received at ``now_ns``) as base_link points of its usable returns.

        A beam is usable when its range is at least ``range_min``: ``inf`` (no return) and
        readings past ``range_max`` count as usable beams without a point; NaN (a fault) and
        readings below ``range_min`` (dust, a blocked window) are not usable. Points come from
        usable finite readings within ``range_max`` (when the scan has a sensible one) and within
        reach of the path. A scan whose beams have no plausible directions (a non-finite angle;
        two or more beams less than :data:`~safety.memory.MIN_ANGLE_INCREMENT_RAD` or more than a
        turn apart) has no usable beam and no point: it is a ``bad_scan``.

        ``pose``: base_link in odom at ``pose_ns`` (default ``now_ns``; the daemon gives the time of
        the sweep's first beam), from odometry; None when there is none (a
        non-finite pose counts as none). With it and the memory on, the remembered points join the
        scan's (after them: ``live`` tells which are which). A scan not yet folded into the memory
        (no :meth:`remember` since) is folded in first.
        """
        previous = self._scan
        if previous is not None and not previous.remembered:
            self.remember()
        r = np.asarray(scan.ranges, dtype=np.float64)
        n = r.size
        if (math.isfinite(scan.angle_min) and math.isfinite(scan.angle_increment)
                and (n < 2 or plausible_increment(scan.angle_increment))):
            # NaN compares false and -inf is below range_min: neither is usable.
            at_least_min = r >= scan.range_min
        else:  # beams without sensible directions (all along one ray, or none): refuse the scan
            at_least_min = np.zeros(n, dtype=bool)
        usable = int(np.count_nonzero(at_least_min))
        # beams that returned a range (inf, no return, does not; nor a reading past range_max)
        top = scan.range_max if scan.range_max > scan.range_min else math.inf
        returned = int(np.count_nonzero(at_least_min & (r <= top))) if usable else 0
        if pose is not None and not (math.isfinite(pose[0]) and math.isfinite(pose[1])
                                     and math.isfinite(pose[2])):
            pose = None
        far = min(scan.range_max, self._reach) if scan.range_max > scan.range_min else self._reach
        # index arrays rather than boolean masks: the gathers the path sweep uses too; nonzero()
        # rather than np.flatnonzero, a chain of Python calls that costs more than the work here
        points = (at_least_min & (r <= far)).nonzero()[0]
        # base_link points as complex numbers x + iy: two numpy operations instead of six
        z = self._origin + r[points] * self._directions(scan, n)[points]
        if self.params.ignore_inside_footprint:
            body = self._body
            x, y = z.real, z.imag
            z = z[((x < -body.rear_m) | (x > body.front_m) | (np.abs(y) > body.half_width_m)).nonzero()[0]]
        sweep = float(scan.scan_time) if 0.0 < scan.scan_time <= 1.0 else 0.0
        live = len(z)
        # unusable beams ignored one by one, but a wide run of them is a sector the lidar is blind
        # in: an obstacle on each of its rays just outside the body (safety.blind)
        blind = blind_beams(at_least_min, scan.angle_increment) if usable else None
        if blind is not None and blind.size:
            z = np.concatenate((z, self._origin + self._blind_r * self._directions(scan, n)[blind]))
        memory = self.memory
        if memory is not None and pose is not None:
            remembered = memory.points()
            if remembered.size:
                # odom -> base_link at this scan: (p_odom - car) e^(-i yaw)
                px, py, yaw = pose
                turn = complex(math.cos(yaw), -math.sin(yaw))
                z = np.concatenate((z, remembered * turn - complex(px, py) * turn))
        self._scan = _CachedScan(z.real, z.imag, now_ns, usable / n if n else 0.0, sweep,
                                 returned / n if n else 0.0, live, scan, pose,
                                 blind=0 if blind is None else len(blind),
                                 pose_ns=None if pose is None else now_ns if pose_ns is None else pose_ns)

    def remember(self) -> None:
        """Fold the cached scan into the obstacle memory (once; nothing when the memory is off, or
        when it took a scan in less than ``memory.update_period_s`` ago).

        Off the scan-to-command path: the daemon calls it after the scan's motor command is
        written. Without a pose (no fresh odometry) the memory cannot place anything and forgets
        everything.
        """
        cached, memory = self._scan, self.memory
        if cached is None or cached.remembered:
            return
        cached.remembered = True
        if memory is None or cached.scan is None:
            return
        if cached.pose is None:
            if memory.window() is not None:
                memory.clear()
            self._remembered_ns = None
            return
        last = self._remembered_ns
        if last is not None and 0 <= cached.received_ns - last < self._memory_period_ns:
            return
        self._remembered_ns = cached.received_ns
        scan = cached.scan
        fp = self._body
        memory.update(cached.pose, self._to_base, scan.ranges, float(scan.angle_min),
                      float(scan.angle_increment), float(scan.range_min), float(scan.range_max),
                      cached.x[:cached.live], cached.y[:cached.live], cached.received_ns,
                      footprint=(fp.front_m, fp.rear_m, fp.half_width_m))

    @property
    def memory_active(self) -> bool:
        """Whether the memory is on and the cached scan came with a pose to place it."""
        return self.memory is not None and self._scan is not None and self._scan.pose is not None

    def _directions(self, scan: LaserScan, n: int) -> np.ndarray:
        """Unit beam directions in base_link as complex numbers, cached for the scan geometry."""
        key = (float(scan.angle_min), float(scan.angle_increment), n)
        if key != self._dirs_key:
            with np.errstate(invalid="ignore"):
                angles = key[0] + key[1] * np.arange(n, dtype=np.float64)
                c, s = np.cos(angles), np.sin(angles)
            t = self._to_base
            self._dirs = (t[0, 0] * c + t[0, 1] * s) + 1j * (t[1, 0] * c + t[1, 1] * s)
            self._dirs_key = key
        return self._dirs

    # --- commands -----------------------------------------------------------------------------

    def limit(self, drive: AckermannDrive, source: str, measured_speed_mps: float,
              now_ns: int) -> tuple[AckermannDrive, SafetyState]:
        """``drive`` with its speed capped to the allowed speed, and the verdict.

        ``source`` is the mux source that produced the command; ``measured_speed_mps`` the
        odometry speed (m/s, negative in reverse; 0 when unknown); ``now_ns`` monotonic time.
        ``drive`` is finite: a command is checked once, where it enters the mux (docs/architecture.md,
        "Finite commands").
        """
        speed, steering = float(drive.speed), float(drive.steering_angle)
        if not math.isfinite(measured_speed_mps):
            measured_speed_mps = 0.0
        mode = self.params.mode
        if mode == "off" or source in self._exempt:
            if self._hyst.intervening:
                self._ended(now_ns)
            self._hyst.reset()
            reason = "off" if mode == "off" else "exempt"
            self.state = SafetyState(math.inf, math.nan, None, reason, False)
            return drive, self.state

        driven = min(max(steering, self.steering_range[0]), self.steering_range[1])
        allowed, free, obstacle, reason = self._assess(driven, speed < 0.0, now_ns)
        magnitude = abs(speed)
        along = measured_speed_mps * math.copysign(1.0, speed) if speed != 0.0 else 0.0
        needs_cut = magnitude > allowed or along > allowed + self.params.measured_tolerance_mps
        was_intervening = self._hyst.intervening
        cap, started = self._hyst.step(needs_cut, allowed, max(magnitude, along), now_ns)
        intervening = self._hyst.intervening
        if was_intervening and not intervening:
            self._ended(now_ns)
        if not intervening and reason in ("obstacle", "reverse_cap"):
            reason = "clear"
        self.state = SafetyState(allowed, free, obstacle, reason, intervening)
        if started:
            self.interventions += 1
            self.interventions_by_reason[reason] = self.interventions_by_reason.get(reason, 0) + 1
            self._obstacle_noted = reason == "obstacle" and obstacle is not None
            self._record(Intervention(now_ns, reason, allowed, speed, measured_speed_mps, obstacle,
                                      **self._scan_times()), source)
        elif (intervening and needs_cut and reason == "obstacle" and obstacle is not None
              and not self._obstacle_noted):
            # started for a late scan or the reverse cap, and now an obstacle cuts the command: once
            # per intervention, however often the reason flips back and forth after this
            self._obstacle_noted = True
            self._ended(now_ns)
            self._record(Intervention(now_ns, reason, allowed, speed, measured_speed_mps, obstacle,
                                      **self._scan_times(), continues=True), source)
        if reason in BLIND and self.params.centre_when_blind:
            return dataclasses.replace(drive, speed=0.0, steering_angle=0.0), self.state
        if magnitude > cap:
            drive = dataclasses.replace(drive, speed=math.copysign(cap, speed) if cap > 0.0 else 0.0)
        return drive, self.state

    def _scan_times(self) -> dict[str, int | None]:
        """An intervention's ``scan_ns`` and ``pose_ns``: the cached scan's arrival and pose times."""
        scan = self._scan
        return {"scan_ns": None if scan is None else scan.received_ns,
                "pose_ns": None if scan is None else scan.pose_ns}

    def _record(self, event: Intervention, source: str) -> None:
        """Keep ``event`` and log it: one line per intervention start or change to an obstacle."""
        self.events.append(event)
        o = event.obstacle
        where = (f"obstacle ({o.source}) at ({o.x:.2f}, {o.y:.2f}) m, {o.distance:.2f} m along the path"
                 if o else "no obstacle")
        what = ("still intervening, now for an obstacle" if event.continues
                else f"intervening ({event.reason})")
        # a client may command 1e300 m/s (clamped long before the wire): %.2f wrote 300 digits
        commanded = event.commanded_speed
        shown = f"{commanded:.2f}" if abs(commanded) < 1e6 else f"{commanded:.3g}"
        log.warning("safety: %s on %s: commanded %s m/s, measured %.2f m/s, allowed %.2f m/s, %s",
                    what, source, shown, event.measured_speed, event.allowed_speed, where)

    def _ended(self, now_ns: int) -> None:
        """The current intervention ended at ``now_ns``."""
        if self.events and self.events[-1].end_ns is None:
            self.events[-1] = dataclasses.replace(self.events[-1], end_ns=now_ns)

    def _assess(self, steering: float, reverse: bool,
                now_ns: int) -> tuple[float, float, Obstacle | None, str]:
        """(allowed |speed|, free distance, obstacle, limiting reason) for the current scan."""
        p = self.params
        scan = self._scan
        if scan is None:
            return 0.0, math.nan, None, "no_scan"
        age_ns = now_ns - scan.received_ns
        if age_ns > p.scan_timeout_s * NS_PER_S:
            return 0.0, math.nan, None, "stale_scan"
        if (scan.usable_fraction < p.min_valid_fraction or scan.usable_fraction == 0.0
                or scan.return_fraction < p.min_return_fraction):
            return 0.0, math.nan, None, "bad_scan"
        if p.mode == "cone":
            # The cone node stops the car through the mux; here only a blind lidar stops it.
            return math.inf, math.nan, None, "clear"
        if reverse and not (p.reverse_uses_scan or (self.memory is not None and scan.pose is not None)):
            return p.reverse_speed_cap_mps, math.nan, None, "reverse_cap"
        key = (steering, reverse, p.max_path_m)
        if scan is self._hit_scan and key == self._hit_key:
            # the same scan and path as the last command: a control tick between scans
            hit, live = self._hit, self._live_hit
        else:
            # the nearest of the live scan's own points comes from the same sweep (for the name)
            hit, live = free_distances(scan.x, scan.y, steering, self.footprint, p.max_path_m, reverse,
                                       scan.live)
            self._hit_scan, self._hit_key, self._hit, self._live_hit = scan, key, hit, live
        # a lidar slower than configured (its scan_time) is taken at its word, never a faster one
        sweep = max(p.scan_period_s, scan.sweep_s)
        latency = sweep + p.processing_s + p.command_transfer_s + max(age_ns, 0) / NS_PER_S
        allowed = stopping_speed(hit.distance_m - p.margin_m, latency, p.max_decel_mps2)
        obstacle = None
        if hit.index >= 0:
            index = hit.index
            # A remembered cell can sit up to a cell's diagonal nearer than the live return it
            # came from: when the scan sees the same obstacle that close behind, the live scan
            # names it (the distance stays the nearer, remembered one).
            if (index >= scan.live and live.index >= 0
                    and live.distance_m <= hit.distance_m + self._memory_cell_m):
                index = live.index
            source = ("scan" if index < scan.live else "blind" if index < scan.live + scan.blind
                      else "memory")
            obstacle = Obstacle(float(scan.x[index]), float(scan.y[index]), hit.distance_m, source)
        if reverse and p.reverse_speed_cap_mps < allowed:
            return p.reverse_speed_cap_mps, hit.distance_m, obstacle, "reverse_cap"
        return allowed, hit.distance_m, obstacle, "obstacle"
