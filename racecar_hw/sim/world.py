"""The loopback world: one car on an occupancy map, driven by the fake VESC, seen by fake lidars.

The world reads the motor's ERPM and the servo position through two callables (the fake VESC's
``erpm`` and ``servo`` properties), moves the car with the kinematic bicycle of
:mod:`racecar_hw.sim.car`, stops it on contact with a wall or obstacle (and calls ``on_collision``,
e.g. the fake VESC's ``stall``), and answers fake lidars through :meth:`World.range_source`.

Time: the world's clock is the monotonic clock in integer nanoseconds (``time_ns``).
:meth:`World.run` steps on real time at absolute deadlines, so the state at ``time_ns`` is the car
"now"; sim time (``sim_time``, the trajectory's ``t``) is seconds since the world started running
(or since :meth:`World.reset`). :meth:`World.step` with an explicit ``dt`` advances the clock by
``dt`` instead, for tests and faster-than-real-time use; do not mix the two on one world.

Obstacles are fixed (:meth:`World.add_obstacle`) or movers (:class:`~racecar_hw.sim.movers.Mover`,
:meth:`World.add_mover`), which appear, move and disappear on sim time: collisions use where they
are at each step, lidars where they are at the scan's stamp.

Threads: :meth:`World.run` runs in the device thread; fake lidars call their range source from
theirs; scenarios read properties and add obstacles from anywhere. Every public member is
thread-safe; the ERPM/servo callables and ``on_collision`` are called from the stepping thread.
"""

from __future__ import annotations

import asyncio
import bisect
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.sim.car import (
    CarParams,
    Collider,
    Pose2D,
    advance,
    speed_from_erpm,
    steering_from_servo,
    wrap_angle,
)
from racecar_hw.sim.movers import Mover
from racecar_hw.sim.obstacles import Box, Circle, Obstacle, rectangle
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.raycast import RayCaster
from racecar_hw.sim.trajectory import TrajectoryReport, TrajectorySample, report
from vesc.imu_model import AT_REST, PlanarMotion

log = logging.getLogger(__name__)

#: A lidar asking for a time later than the last step sees the car extrapolated this far at most (s).
MAX_EXTRAPOLATION_S = 0.1


@dataclass(frozen=True)
class Collision:
    """A contact: sim time (s), the contact side's centre (front bumper forwards, rear in reverse)."""

    t: float
    x: float
    y: float


def compose(pose: tuple[float, float, float], local: tuple[float, float, float]) -> Pose2D:
    """``local`` (a pose in the frame of ``pose``) expressed in ``pose``'s parent frame."""
    x, y, yaw = pose
    lx, ly, lyaw = local
    c, s = math.cos(yaw), math.sin(yaw)
    return Pose2D(x + c * lx - s * ly, y + s * lx + c * ly, wrap_angle(yaw + lyaw))


class World:
    """A car on a map. See the module documentation for frames, time and threads."""

    def __init__(self, occ_map: OccupancyMap, car_params: CarParams | None = None,
                 start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 erpm_source: Callable[[], float] = lambda: 0.0,
                 servo_source: Callable[[], float] | None = None,
                 laser_pose_in_base: tuple[float, float, float] = (0.265, 0.0, 0.0),
                 noise_std_m: float = 0.01, seed: int | None = None,
                 on_collision: Callable[[], object] | None = None) -> None:
        self.map = occ_map
        self.params = car_params or CarParams()
        self.laser_pose_in_base = tuple(float(v) for v in laser_pose_in_base)
        self.noise_std_m = float(noise_std_m)
        self.on_collision = on_collision
        self._erpm_source = erpm_source
        centre = self.params.steering_angle_to_servo_offset
        self._servo_source = servo_source if servo_source is not None else (lambda: centre)
        self._seed = np.random.SeedSequence(seed)
        self._generation = 0
        self._raycaster = RayCaster(occ_map)
        self._collider = Collider(occ_map, self.params)
        self._lock = threading.Lock()
        self._obstacles: dict[int, Obstacle | Mover] = {}
        self._next_obstacle = 1
        self._start_pose = Pose2D(*(float(v) for v in start_pose))
        self._time_ns = monotonic_ns()
        self._reset_locked(self._start_pose)

    # --- state ---------------------------------------------------------------------------------

    def _shapes_locked(self, t: float) -> tuple[Obstacle, ...]:
        """The obstacles present at sim time ``t``, where they are then."""
        return tuple(shape for entry in self._obstacles.values()
                     if (shape := _shape_at(entry, t)) is not None)

    def _reset_locked(self, pose: Pose2D) -> None:
        obstacles = self._shapes_locked(0.0)
        if self._collider.collides(pose, obstacles):
            raise ConfigError("start_pose", f"the car's footprint at {tuple(pose)} overlaps a wall or "
                                            "an obstacle")
        self._generation += 1
        self._pose = pose
        self._speed = 0.0
        self._steering = 0.0
        self._motion = AT_REST
        self._collided = False
        self._collisions: list[Collision] = []
        self._distance = 0.0
        self._min_clearance = self._collider.clearance(pose, obstacles)
        self._t0_ns = self._time_ns
        self._steps = 0
        self._samples: list[TrajectorySample] = [TrajectorySample(0.0, pose.x, pose.y, pose.yaw, 0.0, 0.0)]
        self._times_ns: list[int] = [self._time_ns]

    def reset(self, pose: tuple[float, float, float] | None = None) -> None:
        """Put the car at ``pose`` (default: the start pose) at rest, clear the collision flag, the
        trajectory and the statistics, and restart sim time. Obstacles stay. Unstalling the fake VESC
        is the caller's job."""
        with self._lock:
            self._reset_locked(self._start_pose if pose is None else Pose2D(*(float(v) for v in pose)))

    @property
    def pose(self) -> Pose2D:
        """Rear-axle pose (x m, y m, yaw rad) in the map frame."""
        with self._lock:
            return self._pose

    @property
    def speed(self) -> float:
        """Car speed (m/s, negative in reverse); 0 after a collision."""
        with self._lock:
            return self._speed

    @property
    def steering(self) -> float:
        """Front-wheel steering angle (rad, + left)."""
        with self._lock:
            return self._steering

    def motion(self) -> PlanarMotion:
        """The car's motion at the rear axle over the last step (what its IMU feels)."""
        with self._lock:
            return self._motion

    @property
    def collided(self) -> bool:
        """Whether the car has hit something since the start or the last reset (latched)."""
        with self._lock:
            return self._collided

    @property
    def collisions(self) -> list[Collision]:
        """Every contact since the start or last reset."""
        with self._lock:
            return list(self._collisions)

    @property
    def min_clearance(self) -> float:
        """Smallest footprint-to-obstacle gap seen (m, capped at car.CLEARANCE_RANGE_M)."""
        with self._lock:
            return self._min_clearance

    @property
    def distance_travelled(self) -> float:
        """Path length driven, forwards and backwards (m)."""
        with self._lock:
            return self._distance

    @property
    def time_ns(self) -> int:
        """The world's clock (monotonic ns) at the last step."""
        with self._lock:
            return self._time_ns

    @property
    def sim_time(self) -> float:
        """Seconds since the start or the last reset."""
        with self._lock:
            return (self._time_ns - self._t0_ns) / NS_PER_S

    def sim_time_at(self, stamp_ns: int) -> float:
        """Sim time (s) at monotonic ``stamp_ns``."""
        with self._lock:
            return (stamp_ns - self._t0_ns) / NS_PER_S

    @property
    def trajectory(self) -> list[tuple[float, float, float, float, float]]:
        """(t, x, y, yaw, speed) after every step."""
        with self._lock:
            return [s[:5] for s in self._samples]

    @property
    def samples(self) -> list[TrajectorySample]:
        """Every step's full state, steering included (for the CSV)."""
        with self._lock:
            return list(self._samples)

    def report(self) -> TrajectoryReport:
        """The run's numbers; distance and minimum clearance as the world measured them every step."""
        with self._lock:
            samples, distance, clearance = list(self._samples), self._distance, self._min_clearance
        rep = report(samples, self.params.wheelbase)
        return replace(rep, distance_m=distance, min_clearance_m=clearance)

    def clearance(self, pose: tuple[float, float, float] | None = None) -> float:
        """Gap (m) between the footprint at ``pose`` (default: now) and the nearest wall or obstacle."""
        with self._lock:
            pose = self._pose if pose is None else pose
            obstacles = self._shapes_locked((self._time_ns - self._t0_ns) / NS_PER_S)
        return self._collider.clearance(pose, obstacles)

    # --- obstacles -----------------------------------------------------------------------------

    def add_obstacle(self, x: float, y: float, radius: float | None = None,
                     box: tuple[float, float] | None = None, yaw: float = 0.0) -> int:
        """Place a disc (``radius`` m) or a box (``box`` = (length, width) m, rotated by ``yaw``)
        centred at map-frame (``x``, ``y``). Returns an id for :meth:`remove_obstacle`."""
        if (radius is None) == (box is None):
            raise ValueError("give exactly one of radius or box")
        obstacle: Obstacle
        if radius is not None:
            if not radius > 0:
                raise ValueError(f"radius must be > 0, got {radius}")
            obstacle = Circle(float(x), float(y), float(radius))
        else:
            assert box is not None
            if not (box[0] > 0 and box[1] > 0):
                raise ValueError(f"box sides must be > 0, got {box}")
            obstacle = Box(float(x), float(y), float(box[0]), float(box[1]), float(yaw))
        with self._lock:
            ident = self._next_obstacle
            self._next_obstacle += 1
            self._obstacles[ident] = obstacle
        return ident

    def add_mover(self, mover: Mover) -> int:
        """Add an obstacle that appears, moves and disappears on sim time (see
        :class:`~racecar_hw.sim.movers.Mover`). Returns an id for :meth:`remove_obstacle`."""
        with self._lock:
            ident = self._next_obstacle
            self._next_obstacle += 1
            self._obstacles[ident] = mover
        return ident

    def add_obstacle_ahead(self, distance: float, radius: float = 0.2, lateral: float = 0.0) -> int:
        """A disc whose near edge is ``distance`` m ahead of the front bumper, ``lateral`` m to the left."""
        p = self.params
        front = p.length - p.rear_overhang
        x, y, _ = compose(self.pose, (front + distance + radius, lateral, 0.0))
        return self.add_obstacle(x, y, radius=radius)

    def remove_obstacle(self, ident: int) -> None:
        """Take away an obstacle; unknown ids are ignored."""
        with self._lock:
            self._obstacles.pop(ident, None)

    def clear_obstacles(self) -> None:
        """Take away every obstacle."""
        with self._lock:
            self._obstacles.clear()

    @property
    def obstacles(self) -> dict[int, Obstacle]:
        """The obstacles present now, by id, where they are now."""
        with self._lock:
            t = (self._time_ns - self._t0_ns) / NS_PER_S
            entries = list(self._obstacles.items())
        return {ident: shape for ident, entry in entries
                if (shape := _shape_at(entry, t)) is not None}

    def obstacles_at(self, t: float) -> list[tuple[str, Obstacle]]:
        """(name, shape) of every obstacle present at sim time ``t`` (s), where it is then; an
        obstacle without a name is called ``obstacle <id>``."""
        with self._lock:
            entries = list(self._obstacles.items())
        out = []
        for ident, entry in entries:
            shape = _shape_at(entry, t)
            if shape is not None:
                name = entry.name if isinstance(entry, Mover) and entry.name else f"obstacle {ident}"
                out.append((name, shape))
        return out

    def what_is_at(self, x: float, y: float, t: float | None = None, within: float = 0.15) -> str | None:
        """What occupies map point (``x``, ``y``) at sim time ``t`` (default now), within ``within``
        metres: the nearest obstacle's name, ``"map"`` for an occupied map cell, or None."""
        if t is None:
            t = self.sim_time
        best, name = within, None
        probe = rectangle(x, y, 0.0, -1e-3, 1e-3, -1e-3, 1e-3)
        for label, shape in self.obstacles_at(t):
            gap = shape.distance_to(probe)
            if gap <= best:
                best, name = gap, label
        if name is not None:
            return name
        res = self.map.resolution
        dx, dy = np.meshgrid(np.arange(-within, within + res, res), np.arange(-within, within + res, res))
        disc = np.hypot(dx, dy) <= within + res / 2
        return "map" if bool(np.any(self.map.is_occupied(x + dx[disc], y + dy[disc]))) else None

    # --- stepping ------------------------------------------------------------------------------

    def step(self, dt: float) -> None:
        """Advance the world by ``dt`` seconds with the current motor ERPM and servo position."""
        self._step_ns(max(int(round(dt * NS_PER_S)), 0))

    def _step_ns(self, dt_ns: int) -> None:
        p = self.params
        speed = speed_from_erpm(float(self._erpm_source()), p)
        steering = steering_from_servo(float(self._servo_source()), p)
        with self._lock:
            pose, collided, generation = self._pose, self._collided, self._generation
            obstacles = self._shapes_locked((self._time_ns + dt_ns - self._t0_ns) / NS_PER_S)
        dt = dt_ns / NS_PER_S
        travelled = 0.0
        hit = False
        if not collided and speed != 0.0 and dt > 0:
            # sub-steps short enough that a collision is found within half a cell
            turn = abs(speed * dt * math.tan(steering) / p.wheelbase)
            n = max(1, math.ceil(abs(speed) * dt / (self.map.resolution / 2)), math.ceil(turn / 0.05))
            h = dt / n
            for _ in range(n):
                nxt = advance(pose, speed, steering, h, p.wheelbase)
                if self._collider.collides(nxt, obstacles):
                    hit = True
                    break
                pose = nxt
                travelled += abs(speed) * h
        clearance = self._collider.clearance(pose, obstacles)
        with self._lock:
            if self._generation != generation:  # reset while we computed: the reset pose wins
                hit, pose, travelled, clearance = False, self._pose, 0.0, self._min_clearance
            moving = not (hit or self._collided)
            self._pose = pose
            new_speed = speed if moving else 0.0
            yaw_rate = new_speed * math.tan(steering) / p.wheelbase
            before = self._motion
            self._motion = (PlanarMotion(new_speed, yaw_rate, (new_speed - before.speed) / dt,
                                         (yaw_rate - before.yaw_rate) / dt) if dt > 0 else before)
            self._speed = new_speed
            self._steering = steering
            self._distance += travelled
            self._min_clearance = min(self._min_clearance, clearance)
            self._time_ns += dt_ns
            self._steps += 1
            t = (self._time_ns - self._t0_ns) / NS_PER_S
            if hit:
                self._collided = True
                self._min_clearance = 0.0
                side = p.length - p.rear_overhang if speed > 0 else -p.rear_overhang
                cx, cy, _ = compose(pose, (side, 0.0, 0.0))
                self._collisions.append(Collision(t, cx, cy))
            self._samples.append(TrajectorySample(t, pose.x, pose.y, pose.yaw, self._speed, steering))
            self._times_ns.append(self._time_ns)
        if hit:
            log.info("collision at t=%.3f s, pose %s", t, tuple(round(v, 3) for v in pose))
            if self.on_collision is not None:
                self.on_collision()

    async def run(self, rate_hz: float = 200.0) -> None:
        """Step on the monotonic clock at ``rate_hz`` with absolute deadlines, forever (cancel to stop).

        If nothing has been stepped yet, sim time starts now. After a stall of more than five
        periods the deadlines restart from now (the step that follows covers the whole gap)."""
        period_ns = int(round(NS_PER_S / rate_hz))
        with self._lock:
            if self._steps == 0:
                now = monotonic_ns()
                self._time_ns = self._t0_ns = now
                self._times_ns[0] = now
        deadline = monotonic_ns()
        while True:
            deadline += period_ns
            delay = deadline - monotonic_ns()
            if delay > 0:
                await asyncio.sleep(delay / NS_PER_S)
            elif -delay > 5 * period_ns:
                deadline = monotonic_ns()
            now = monotonic_ns()
            with self._lock:
                dt_ns = now - self._time_ns
            self._step_ns(max(dt_ns, 0))

    # --- sensing -------------------------------------------------------------------------------

    def pose_at(self, stamp_ns: int) -> Pose2D:
        """The rear-axle pose at monotonic time ``stamp_ns``: interpolated between steps, the first
        pose before the history, extrapolated (at most MAX_EXTRAPOLATION_S) after the last step."""
        with self._lock:
            times, samples = self._times_ns, self._samples
            k = bisect.bisect_right(times, stamp_ns)
            if k == 0:
                s = samples[0]
                return Pose2D(s.x, s.y, s.yaw)
            if k == len(times):
                s, last_ns = samples[-1], times[-1]
                ahead = min((stamp_ns - last_ns) / NS_PER_S, MAX_EXTRAPOLATION_S)
                return advance(Pose2D(s.x, s.y, s.yaw), s.speed, s.steering, ahead, self.params.wheelbase)
            a, b = samples[k - 1], samples[k]
            ta, tb = times[k - 1], times[k]
        f = (stamp_ns - ta) / (tb - ta) if tb > ta else 1.0
        return Pose2D(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y),
                      wrap_angle(a.yaw + f * wrap_angle(b.yaw - a.yaw)))

    def range_source(self, max_range: float = 10.0, noise_std_m: float | None = None,
                     laser_pose_in_base: tuple[float, float, float] | None = None) -> SimRangeSource:
        """A :class:`~lidar_drivers.base.RangeSource` for one fake lidar: ranges from its laser pose
        at the stamp time, with Gaussian noise (default: the world's ``noise_std_m``), ``inf`` beyond
        ``max_range`` metres. Each source has its own random stream derived from the world's seed."""
        with self._lock:
            rng = np.random.default_rng(self._seed.spawn(1)[0])
        return SimRangeSource(self, max_range, self.noise_std_m if noise_std_m is None else noise_std_m,
                              laser_pose_in_base or self.laser_pose_in_base, rng)

    def true_ranges(self, angles: np.ndarray, max_range: float = 30.0,
                    laser_pose: tuple[float, float, float] | None = None,
                    t: float | None = None) -> np.ndarray:
        """Noise-free ranges (m) along ``angles`` from ``laser_pose`` in the map frame (default: the
        laser on the car now), walls and the obstacles where they are at sim time ``t`` (default:
        now); ``inf`` beyond ``max_range``."""
        if laser_pose is None:
            laser_pose = compose(self.pose, self.laser_pose_in_base)
        x, y, yaw = laser_pose
        angles = np.asarray(angles, dtype=np.float64)
        ranges = self._raycaster.cast(x, y, yaw, angles, max_range)
        with self._lock:
            obstacles = self._shapes_locked((self._time_ns - self._t0_ns) / NS_PER_S if t is None else t)
        if obstacles:
            theta = angles + yaw
            c, s = np.cos(theta), np.sin(theta)
            for obstacle in obstacles:
                np.minimum(ranges, obstacle.ray_ranges(x, y, c, s), out=ranges)
            ranges[ranges > max_range] = np.inf
        return ranges


class SimRangeSource:
    """One lidar's view of a :class:`World`; thread-safe. Create with :meth:`World.range_source`."""

    def __init__(self, world: World, max_range: float, noise_std_m: float,
                 laser_pose_in_base: tuple[float, float, float], rng: np.random.Generator) -> None:
        self.world = world
        self.max_range = float(max_range)
        self.noise_std_m = float(noise_std_m)
        self.laser_pose_in_base = laser_pose_in_base
        self._rng = rng
        self._rng_lock = threading.Lock()

    def ranges(self, angles: np.ndarray, stamp_ns: int) -> np.ndarray:
        """Measured ranges (m) along ``angles`` (rad, CCW, laser frame) at ``stamp_ns`` (monotonic)."""
        laser = compose(self.world.pose_at(stamp_ns), self.laser_pose_in_base)
        ranges = self.world.true_ranges(angles, self.max_range, laser, self.world.sim_time_at(stamp_ns))
        if self.noise_std_m > 0:
            with self._rng_lock:
                noise = self._rng.normal(0.0, self.noise_std_m, size=ranges.shape)
            finite = np.isfinite(ranges)
            ranges[finite] = np.maximum(ranges[finite] + noise[finite], 0.0)
            ranges[ranges > self.max_range] = np.inf
        return ranges


def _shape_at(entry: Obstacle | Mover, t: float) -> Obstacle | None:
    """A fixed obstacle, or a mover where it is at sim time ``t`` (None while it is absent)."""
    return entry.at(t) if isinstance(entry, Mover) else entry
