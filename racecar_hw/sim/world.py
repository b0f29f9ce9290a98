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
are at each step, lidars where they are at the scan's stamp. The parts: the map and its obstacles
are a :class:`~racecar_hw.sim.scene.Scene` (ray-casting, what is where), contacts are found by the
car's :class:`~racecar_hw.sim.car.Collider`, and the past poses are a
:class:`~racecar_hw.sim.history.PoseHistory`.

Threads: :meth:`World.run` runs in the device thread; fake lidars call their range source from
theirs; scenarios read properties and add obstacles from anywhere. Every public member is
thread-safe; the ERPM/servo callables and ``on_collision`` are called from the stepping thread.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.sim.car import CarParams, Collider, Pose2D, speed_from_erpm, steering_from_servo
from racecar_hw.sim.car_state import CarState, Collision, compose
from racecar_hw.sim.history import MAX_EXTRAPOLATION_S, PoseHistory
from racecar_hw.sim.movers import Mover
from racecar_hw.sim.obstacles import Obstacle
from racecar_hw.sim.occupancy import OccupancyMap
from racecar_hw.sim.pacer import Pacer
from racecar_hw.sim.scene import Scene
from racecar_hw.sim.trajectory import TrajectoryReport, TrajectorySample, report
from vesc.imu_model import PlanarMotion

log = logging.getLogger(__name__)

#: Measurements a :class:`SimRangeSource` remembers (:meth:`SimRangeSource.measured_before`): a
#: UST-10LX's 40 sweeps a second for 40 minutes, an RPLIDAR's batches of beams for several.
MEASUREMENTS_KEPT = 100_000

#: How far (rad) a beam's angle may lie outside a measurement's beams and still be one of them: a
#: scan's beams are the device's, binned (an RPLIDAR's, 1° or less apart), not the ones measured.
BEAM_TOLERANCE_RAD = 0.02


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
        self.scene = Scene(occ_map)
        self._collider = Collider(occ_map, self.params)
        self._lock = threading.Lock()
        self._start_pose = Pose2D(*(float(v) for v in start_pose))
        self._reset_locked(self._start_pose, monotonic_ns())

    # --- state ---------------------------------------------------------------------------------

    def _reset_locked(self, pose: Pose2D, time_ns: int) -> None:
        if self._collider.collides(pose, obstacles := self.scene.shapes_at(0.0)):
            raise ConfigError("start_pose", f"the car's footprint at {tuple(pose)} overlaps a wall or "
                                            "an obstacle")
        self._generation += 1
        self._car = CarState(pose, self._collider.clearance(pose, obstacles))
        self._history = PoseHistory(pose, time_ns)

    def reset(self, pose: tuple[float, float, float] | None = None) -> None:
        """Put the car at ``pose`` (default: the start pose) at rest, clear the collision flag, the
        trajectory and the statistics, and restart sim time. Obstacles stay. Unstalling the fake VESC
        is the caller's job."""
        with self._lock:
            self._reset_locked(self._start_pose if pose is None else Pose2D(*(float(v) for v in pose)),
                               self._history.time_ns)

    @property
    def pose(self) -> Pose2D:
        """Rear-axle pose (x m, y m, yaw rad) in the map frame."""
        with self._lock:
            return self._car.pose

    @property
    def speed(self) -> float:
        """Car speed (m/s, negative in reverse); 0 after a collision."""
        with self._lock:
            return self._car.speed

    @property
    def steering(self) -> float:
        """Front-wheel steering angle (rad, + left)."""
        with self._lock:
            return self._car.steering

    def motion(self) -> PlanarMotion:
        """The car's motion at the rear axle over the last step (what its IMU feels)."""
        with self._lock:
            return self._car.motion

    @property
    def collided(self) -> bool:
        """Whether the car has hit something since the start or the last reset (latched)."""
        with self._lock:
            return self._car.collided

    @property
    def collisions(self) -> list[Collision]:
        """Every contact since the start or last reset."""
        with self._lock:
            return list(self._car.collisions)

    @property
    def min_clearance(self) -> float:
        """Smallest footprint-to-obstacle gap seen (m, capped at car.CLEARANCE_RANGE_M)."""
        with self._lock:
            return self._car.min_clearance

    @property
    def distance_travelled(self) -> float:
        """Path length driven, forwards and backwards (m)."""
        with self._lock:
            return self._car.distance

    @property
    def time_ns(self) -> int:
        """The world's clock (monotonic ns) at the last step."""
        with self._lock:
            return self._history.time_ns

    @property
    def sim_time(self) -> float:
        """Seconds since the start or the last reset."""
        with self._lock:
            return self._history.sim_time_at(self._history.time_ns)

    def sim_time_at(self, stamp_ns: int) -> float:
        """Sim time (s) at monotonic ``stamp_ns``."""
        with self._lock:
            return self._history.sim_time_at(stamp_ns)

    @property
    def trajectory(self) -> list[tuple[float, float, float, float, float]]:
        """(t, x, y, yaw, speed) after every step."""
        with self._lock:
            return [s[:5] for s in self._history.samples]

    @property
    def samples(self) -> list[TrajectorySample]:
        """Every step's full state, steering included (for the CSV)."""
        with self._lock:
            return list(self._history.samples)

    def report(self) -> TrajectoryReport:
        """The run's numbers; distance and minimum clearance as the world measured them every step."""
        with self._lock:
            samples, distance, clearance = (list(self._history.samples), self._car.distance,
                                            self._car.min_clearance)
        rep = report(samples, self.params.wheelbase)
        return replace(rep, distance_m=distance, min_clearance_m=clearance)


    def clearance(self, pose: tuple[float, float, float] | None = None) -> float:
        """Gap (m) between the footprint at ``pose`` (default: now) and the nearest wall or obstacle."""
        with self._lock:
            pose = self._car.pose if pose is None else pose
            t = self._history.sim_time_at(self._history.time_ns)
        return self._collider.clearance(pose, self.scene.shapes_at(t))

    # --- obstacles (kept by the scene) ---------------------------------------------------------

    def add_obstacle(self, x: float, y: float, radius: float | None = None,
                     box: tuple[float, float] | None = None, yaw: float = 0.0) -> int:
        """A disc or a box; see :meth:`Scene.add_obstacle <racecar_hw.sim.scene.Scene.add_obstacle>`."""
        return self.scene.add_obstacle(x, y, radius, box, yaw)

    def add_mover(self, mover: Mover) -> int:
        """Add an obstacle that appears, moves and disappears on sim time; returns its id."""
        return self.scene.add_mover(mover)

    def add_obstacle_ahead(self, distance: float, radius: float = 0.2, lateral: float = 0.0) -> int:
        """A disc whose near edge is ``distance`` m ahead of the front bumper, ``lateral`` m to the left."""
        front = self.params.length - self.params.rear_overhang
        x, y, _ = compose(self.pose, (front + distance + radius, lateral, 0.0))
        return self.add_obstacle(x, y, radius=radius)

    def remove_obstacle(self, ident: int) -> None:
        """Take away an obstacle; unknown ids are ignored."""
        self.scene.remove(ident)

    def clear_obstacles(self) -> None:
        """Take away every obstacle."""
        self.scene.clear()

    @property
    def obstacles(self) -> dict[int, Obstacle]:
        """The obstacles present now, by id, where they are now."""
        return self.scene.by_id_at(self.sim_time)

    def obstacles_at(self, t: float) -> list[tuple[str, Obstacle]]:
        """(name, shape) of every obstacle present at sim time ``t`` (s), where it is then."""
        return self.scene.named_at(t)

    def what_is_at(self, x: float, y: float, t: float | None = None, within: float = 0.15) -> str | None:
        """What occupies map point (``x``, ``y``) at sim time ``t`` (default now): an obstacle's name,
        ``"map"`` or None (see :meth:`~racecar_hw.sim.scene.Scene.what_is_at`)."""
        return self.scene.what_is_at(x, y, self.sim_time if t is None else t, within)

    # --- stepping ------------------------------------------------------------------------------

    def step(self, dt: float) -> None:
        """Advance the world by ``dt`` seconds with the current motor ERPM and servo position."""
        self._step_ns(max(round(dt * NS_PER_S), 0))

    def _step_ns(self, dt_ns: int) -> None:
        p = self.params
        speed = speed_from_erpm(float(self._erpm_source()), p)
        steering = steering_from_servo(float(self._servo_source()), p)
        with self._lock:
            pose, collided, generation = self._car.pose, self._car.collided, self._generation
            least = self._car.min_clearance
            obstacles_t = self._history.sim_time_at(self._history.time_ns + dt_ns)
        obstacles = self.scene.shapes_at(obstacles_t)  # where they will be at the step's end
        dt = dt_ns / NS_PER_S
        travelled, hit = 0.0, False
        if not collided and speed != 0.0 and dt > 0:
            pose, travelled, hit = self._collider.sweep(pose, speed, steering, dt, obstacles)
        # (exact only where it could lower the minimum: the running minimum is all it feeds)
        clearance = self._collider.clearance(pose, obstacles, exact_below=least)
        with self._lock:
            if self._generation != generation:  # reset while we computed: the reset pose wins
                hit, pose, travelled, clearance = False, self._car.pose, 0.0, self._car.min_clearance
            time_ns = self._history.time_ns + dt_ns
            t = self._history.sim_time_at(time_ns)
            self._car.stepped(pose, speed, steering, dt, travelled, clearance, hit, t, p)
            self._history.append(TrajectorySample(t, pose.x, pose.y, pose.yaw, self._car.speed, steering),
                                 time_ns)
        if hit:
            log.info("collision at t=%.3f s, pose %s", t, tuple(round(v, 3) for v in pose))
            if self.on_collision is not None:
                self.on_collision()

    async def run(self, rate_hz: float = 200.0, before_step: Callable[[int], None] | None = None) -> None:
        """Step on the monotonic clock at ``rate_hz`` with absolute deadlines, forever (cancel to stop;
        :class:`~racecar_hw.sim.pacer.Pacer`); sim time starts now if nothing was stepped yet.
        ``before_step(now_ns)`` runs first at each step: a device model on the same grid (the fake
        VESC's motor) stepped by the world's timer instead of a timer of its own."""
        with self._lock:
            if not self._history.stepped:
                self._history.restart(monotonic_ns())
        await Pacer(rate_hz).run(self._step_to if before_step is None else _chain(before_step, self._step_to))

    def _step_to(self, now_ns: int) -> None:
        with self._lock:
            dt_ns = now_ns - self._history.time_ns
        self._step_ns(max(dt_ns, 0))

    # --- sensing -------------------------------------------------------------------------------

    def pose_at(self, stamp_ns: int) -> Pose2D:
        """The rear-axle pose at monotonic time ``stamp_ns``: interpolated between steps, the first
        pose before the history, extrapolated (at most MAX_EXTRAPOLATION_S) after the last step."""
        with self._lock:
            return self._history.pose_at(stamp_ns, self.params.wheelbase)

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
        laser = compose(self.pose, self.laser_pose_in_base) if laser_pose is None else laser_pose
        return self.scene.ranges(laser, angles, max_range, self.sim_time if t is None else t)


def _chain(first: Callable[[int], None], then: Callable[[int], None]) -> Callable[[int], None]:
    """One step callback: ``first(now_ns)``, then ``then(now_ns)``."""

    def step(now_ns: int) -> None:
        first(now_ns)
        then(now_ns)

    return step


class SimRangeSource:
    """One lidar's view of a :class:`World`; thread-safe. Create with :meth:`World.range_source`."""

    def __init__(self, world: World, max_range: float, noise_std_m: float,
                 laser_pose_in_base: tuple[float, float, float], rng: np.random.Generator) -> None:
        self.world = world
        self.max_range = float(max_range)
        self.noise_std_m = float(noise_std_m)
        self.laser_pose_in_base = laser_pose_in_base
        self._rng = rng
        self._lock = threading.Lock()
        #: (monotonic ns when measured, the stamp measured at, lowest and highest angle) of the
        #: latest :data:`MEASUREMENTS_KEPT` calls of :meth:`ranges`
        self._measured: deque[tuple[int, int, float, float]] = deque(maxlen=MEASUREMENTS_KEPT)

    def ranges(self, angles: np.ndarray, stamp_ns: int) -> np.ndarray:
        """Measured ranges (m) along ``angles`` (rad, CCW, laser frame) at ``stamp_ns`` (monotonic)."""
        if len(angles):
            span = float(np.min(angles)), float(np.max(angles))
            with self._lock:
                self._measured.append((monotonic_ns(), stamp_ns, *span))
        laser = compose(self.world.pose_at(stamp_ns), self.laser_pose_in_base)
        ranges = self.world.true_ranges(angles, self.max_range, laser, self.world.sim_time_at(stamp_ns))
        if self.noise_std_m > 0:
            with self._lock:
                noise = self._rng.normal(0.0, self.noise_std_m, size=ranges.shape)
            # in place over every beam: a beam with no return (inf) stays inf, a finite one gets
            # its noise, clipped at 0 (the same numbers as masking the finite beams, fewer copies)
            np.add(ranges, noise, out=ranges)
            np.maximum(ranges, 0.0, out=ranges)
            ranges[ranges > self.max_range] = np.inf
        return ranges

    def measured_before(self, angle: float, before_ns: int) -> int | None:
        """The stamp (monotonic ns) a beam at ``angle`` (rad, laser frame) of a scan that arrived at
        ``before_ns`` was measured at: that of the latest measurement made by then whose beams span
        it (a sweep's, or a batch's of an RPLIDAR); None when no measurement kept does. A device
        measures a beam before it sends it, and a scan arrives after its sweep: the lidar saw its
        points from where the car was then, up to a scan period before the daemon had them."""
        with self._lock:
            kept = list(self._measured)
        angle = math.remainder(angle, math.tau)
        for measured_ns, stamp_ns, lo, hi in reversed(kept):
            if measured_ns <= before_ns and lo - BEAM_TOLERANCE_RAD <= angle <= hi + BEAM_TOLERANCE_RAD:
                return stamp_ns
        return None


__all__ = ["MAX_EXTRAPOLATION_S", "MEASUREMENTS_KEPT", "Collision", "SimRangeSource", "World", "compose"]
