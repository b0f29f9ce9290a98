"""Scenario files: a map, a start pose, who drives, what breaks when, and for how long.

A scenario is YAML (shipped ones in ``config/scenarios/``; any path works too)::

    description: Drive at a wall at 2 m/s; the safety controller must stop the car.
    map: room                  # a shipped map name (config/maps/NAME.yaml) or a map YAML path
    start: [2.0, 5.0, 0.0]     # x (m), y (m), yaw (rad) in the map frame
    duration_s: 8
    lidar: {model: ust-10lx, transport: tcp}
    drivers:                   # each publishes on a mux input during [from_s, until_s)
      - {type: constant, input: nav_0, speed_mps: 2.0, steering_rad: 0.0}
    faults:                    # applied at at_s seconds of scenario time
      - {at_s: 3.0, action: lidar_unplug}
    obstacles:                 # besides the map; see docs/sim.md "Scenario obstacles"
      - {name: person, shape: disc, radius_m: 0.2, at: [3.5, 2.0], velocity_mps: [0.0, -1.5]}
      - {shape: box, size_m: [0.6, 0.4], yaw_rad: 0.3, at: [4.0, 2.5], waypoints: [[4.0, 0.0]],
         speed_mps: 1.0, appear_s: 0.5}
      - {shape: polygon, points: [[0, 0], [1, 0], [0.5, 0.8]], at: [6.0, -2.0], disappear_s: 4}
    config: {safety: {margin_m: 0.3}}   # merged into the daemon's sim config
    car: {speed_to_erpm_gain: 5075}     # the simulated car's true values (default: as configured)

Scenario time starts when the car is ready to drive (the VESC answered and the first scan is in),
as a driver on a real car would wait; ``duration_s``, ``from_s``/``until_s`` and ``at_s`` count from
there. The report and the trajectory use world time, which starts with the simulation.

Driver types: ``constant`` (a fixed command), ``script`` (``steps: [[t_s, speed, steering], ...]``,
each held until the next), ``figure8`` (``speed_mps``, ``steering_rad``, ``figure8s``), ``setpoint``
(the lab-0 relay holding ``speed_mps``/``steering_rad``), ``follow`` (a bag, see racecar_hw.bags.follow).
Fault actions: ``lidar_unplug``, ``lidar_replug``, ``vesc_unplug``, ``vesc_replug``,
``obstacle_ahead`` (``distance_m`` ahead of the car's front, ``radius_m``), ``clear_obstacles``,
``vesc_garbage`` (``bytes``), ``estop``, ``estop_release``, ``disarm`` (the operator lets go),
``arm``.
Obstacle shapes: ``disc`` (``radius_m``), ``box`` (``size_m``: length along ``yaw_rad``, width),
``polygon`` (convex ``points`` around ``at``, turned by ``yaw_rad``). Each appears at ``at`` at
``appear_s``, moves at ``velocity_mps`` or through ``waypoints`` at ``speed_mps`` (stopping at the
last), and is gone from ``disappear_s`` (none: never); positions in the map frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.overrides import apply_override, load_yaml
from racecar_hw.base.params import build, param
from racecar_hw.base.resources import config_dir
from racecar_hw.sim.movers import Mover
from racecar_hw.sim.obstacles import Box, Circle, Obstacle, Polygon

DRIVER_TYPES = ("constant", "script", "figure8", "setpoint", "follow")
OBSTACLE_SHAPES = ("disc", "box", "polygon")
FAULT_ACTIONS = ("lidar_unplug", "lidar_replug", "vesc_unplug", "vesc_replug", "obstacle_ahead",
                 "clear_obstacles", "vesc_garbage", "estop", "estop_release", "disarm", "arm")
#: what a driver may command: speed (m/s) and steering (rad, + left), lowest and highest
SPEED_RANGE_MPS = (-10.0, 10.0)
STEERING_RANGE_RAD = (-1.0, 1.0)


def check_finite(key: str, values: Iterable[float]) -> None:
    """Refuse (ConfigError naming ``key``) ``values`` unless every one is finite."""
    values = list(values)
    if not all(math.isfinite(v) for v in values):
        raise ConfigError(key, f"every value must be finite, got {values}")


def _check_range(key: str, value: float, bounds: tuple[float, float], unit: str) -> None:
    lo, hi = bounds
    if not lo <= value <= hi:
        raise ConfigError(key, f"{value!r} is out of range; allowed: {lo:g} to {hi:g} {unit}")


@dataclass
class DriverSpec:
    """One scripted source of commands on a mux input."""

    type: str = param("constant", "how commands are made", choices=DRIVER_TYPES)
    input: str = param("nav_0", "mux input name the commands go to")
    from_s: float = param(0.0, "start publishing at this scenario time", unit="s", min=0.0)
    until_s: float | None = param(None, "stop publishing at this scenario time; none: never", unit="s",
                                  min=0.0)
    speed_mps: float = param(1.0, "speed (constant, setpoint, figure8)", unit="m/s",
                             min=SPEED_RANGE_MPS[0], max=SPEED_RANGE_MPS[1])
    steering_rad: float = param(0.0, "steering angle, + left (constant, setpoint, figure8)",
                                unit="rad", min=STEERING_RANGE_RAD[0], max=STEERING_RANGE_RAD[1])
    steps: list[tuple[float, float, float]] = param([], "script: [t_s, speed_mps, steering_rad] rows "
                                                        "(t_s from 0, speed and steering in their ranges)")
    figure8s: int = param(1, "figure8: how many", min=0)
    rate_hz: float = param(20.0, "command rate", unit="Hz", min=1.0, max=200.0)
    bag: str = param("", "follow: the bag to follow")
    topic: str = param("", "follow: topic in the bag; empty: its only drive-command topic (with "
                           "several, its only mux input)")
    reverse: bool = param(False, "follow: backwards")
    use_timestamps: bool = param(False, "follow: the bag's own timing")

    def __post_init__(self) -> None:
        for k, (t_s, speed, steering) in enumerate(self.steps):
            if not (math.isfinite(t_s) and t_s >= 0):
                raise ConfigError(f"steps[{k}].t_s", f"{t_s!r} is not a time from 0 s on")
            _check_range(f"steps[{k}].speed_mps", speed, SPEED_RANGE_MPS, "m/s")
            _check_range(f"steps[{k}].steering_rad", steering, STEERING_RANGE_RAD, "rad")


@dataclass
class FaultSpec:
    """One thing that breaks (or is mended) at a given time."""

    at_s: float = param(0.0, "when, in scenario time", unit="s", min=0.0)
    action: str = param("lidar_unplug", "what happens", choices=FAULT_ACTIONS)
    distance_m: float = param(1.5, "obstacle_ahead: distance ahead of the car's front bumper",
                              unit="m", min=0.0)
    radius_m: float = param(0.2, "obstacle_ahead: obstacle radius", unit="m", min=0.01)
    bytes: int = param(64, "vesc_garbage: how many garbage bytes", min=1)


@dataclass
class ObstacleSpec:
    """An obstacle besides the map: its shape, where and when it appears, how it moves, when it goes.

    Positions are in the map frame, times in scenario time.
    """

    name: str = param("", "what the report calls it; none: obstacle N")
    shape: str = param("disc", "its outline", choices=OBSTACLE_SHAPES)
    radius_m: float = param(0.2, "disc: radius (a person: 0.2)", unit="m", min=0.01, max=50.0)
    size_m: tuple[float, float] = param((0.5, 0.5), "box: length (along yaw_rad) and width", unit="m")
    points: list[tuple[float, float]] = param([], "polygon: its convex corners, around its position",
                                              unit="m")
    at: tuple[float, float] = param((0.0, 0.0), "where it appears: the disc's or box's centre, the "
                                                 "origin of the polygon's points", unit="m")
    yaw_rad: float = param(0.0, "box, polygon: heading, counter-clockwise", unit="rad")
    appear_s: float = param(0.0, "appears at this scenario time", unit="s", min=0.0)
    disappear_s: float | None = param(None, "gone from this scenario time; none: stays", unit="s")
    velocity_mps: tuple[float, float] = param((0.0, 0.0), "moves at this constant velocity (x, y) "
                                                          "from when it appears", unit="m/s",
                                              min=-50.0, max=50.0)
    waypoints: list[tuple[float, float]] = param([], "or moves through these points in turn at "
                                                     "speed_mps, stopping at the last", unit="m")
    speed_mps: float = param(1.0, "speed along the waypoints", unit="m/s", min=0.01, max=50.0)

    def __post_init__(self) -> None:
        check_finite("at", self.at)
        check_finite("yaw_rad", [self.yaw_rad])
        check_finite("size_m", self.size_m)
        for key in ("points", "waypoints"):
            for k, point in enumerate(getattr(self, key)):
                check_finite(f"{key}[{k}]", point)
        self.mover()  # refuses a shape or a schedule that makes no obstacle

    def outline(self) -> Obstacle:
        """The shape around the origin, heading 0 (ValueError when it makes no shape)."""
        if self.shape == "disc":
            return Circle(0.0, 0.0, self.radius_m)
        if self.shape == "box":
            length, width = self.size_m
            if not (length > 0 and width > 0):
                raise ValueError(f"box size_m must be > 0, got {list(self.size_m)}")
            return Box(0.0, 0.0, length, width)
        return Polygon.convex(self.points)

    def mover(self, offset_s: float = 0.0, name: str = "") -> Mover:
        """The world's obstacle, its times shifted by ``offset_s`` (scenario -> world time)."""
        return Mover(self.outline(), tuple(self.at), self.yaw_rad, self.appear_s + offset_s,
                     None if self.disappear_s is None else self.disappear_s + offset_s,
                     tuple(self.velocity_mps), tuple(tuple(w) for w in self.waypoints),
                     self.speed_mps, self.name or name)


@dataclass
class LidarSpec:
    """Which fake lidar the scenario uses, and how the daemon reaches it."""

    model: str = param("ust-10lx", "fake lidar model")
    transport: str = param("tcp", "tcp (Ethernet Hokuyo) or pty; USB Hokuyo and RPLIDAR models "
                                  "always use a pty, as the real ones", choices=("tcp", "pty"))


@dataclass
class WorldSpec:
    """World simulation settings."""

    rate_hz: float = param(200.0, "physics step rate", unit="Hz", min=20.0, max=2000.0)
    noise_std_m: float = param(0.01, "lidar range noise (standard deviation)", unit="m", min=0.0,
                               max=1.0)
    seed: int | None = param(1, "random seed for the noise; none: different every run", min=0)
    clock_rate_hz: float = param(100.0, "/clock publish rate in simulation time (rosgraph_msgs/Clock "
                                 "for ROS 2 nodes with use_sim_time; docs/sim.md); 0: no /clock",
                                 unit="Hz", min=0.0, max=1000.0)


@dataclass
class CarSpec:
    """The simulated car where it is not what the daemon's config says: a miscalibrated car, for
    testing calibration and odometry honestly. Each ``null`` means "as configured" (a calibrated car).
    """

    speed_to_erpm_gain: float | None = param(None, "the motor's true ERPM per m/s",
                                             unit="ERPM/(m/s)", min=1.0, max=100000.0)
    steering_angle_to_servo_offset: float | None = param(None, "the servo position that truly steers "
                                                         "straight", min=0.0, max=1.0)
    steering_angle_to_servo_gain: float | None = param(None, "the true servo position per radian "
                                                       "(left turns)", unit="1/rad", min=-10.0, max=10.0)
    steering_angle_to_servo_gain_right: float | None = param(None, "the true servo position per radian "
                                                             "of right turns; null: as left",
                                                             unit="1/rad", min=-10.0, max=10.0)
    wheelbase_m: float | None = param(None, "the true wheelbase", unit="m", min=0.05, max=2.0)
    invert_motor: bool | None = param(None, "the motor truly wired backwards (its ERPM and tachometer "
                                      "count the other way); null: as vesc.invert_motor says")
    invert_servo: bool | None = param(None, "the servo truly mirrored about its centre; null: as "
                                      "vesc.invert_servo says")
    gyro_bias_dps: float = param(0.5, "the fake IMU's gyro z offset", unit="deg/s", min=-10.0, max=10.0)


@dataclass
class ScenarioCar:
    """One car of a scenario with several (``cars``): its own start, drivers, faults and daemon
    config, on the scenario's map and clock (see docs/sim.md, "Several cars")."""

    name: str = param("", "the car's name: unique, letters, digits and _; its default Zenoh/DDS "
                          "namespace is /NAME and other cars' reports call it so")
    start: tuple[float, float, float] = param((0.0, 0.0, 0.0), "start pose x, y, yaw in the map frame",
                                              unit="m, m, rad")
    lidar: LidarSpec | None = param(None, "its fake lidar; none: the scenario's")
    drivers: list[DriverSpec] = param([], "who drives it (scenario drivers; clients over the network "
                                          "need none)")
    faults: list[FaultSpec] = param([], "what breaks on it, when")
    config: dict[str, Any] = param({}, "overrides merged into its daemon's config, after the "
                                       "scenario's config")
    car: CarSpec = param(CarSpec(), "the simulated car's true gains where they differ from the config")

    def __post_init__(self) -> None:
        check_finite("start", self.start)
        if not (self.name and self.name.isidentifier() and self.name.isascii()):
            raise ValueError(f"name: {self.name!r}: a car's name is letters, digits and _ "
                             "(not starting with a digit)")


@dataclass
class Scenario:
    """A whole scenario. See the module documentation for the file format."""

    description: str = param("", "what the scenario shows")
    map: str = param("track", "shipped map name or path to a map_server YAML")
    start: tuple[float, float, float] = param((0.0, 0.0, 0.0), "start pose x, y, yaw in the map frame",
                                              unit="m, m, rad")
    duration_s: float = param(20.0, "scenario time to run (from when the car is ready)", unit="s",
                              min=0.1, max=3600.0)
    firmware: str = param("6.02", "fake VESC firmware version X.YY as vesc-info prints it (6.2 reads "
                                  "as 6.02; selects the telemetry layout)")
    lidar: LidarSpec = param(LidarSpec(), "the fake lidar")
    world: WorldSpec = param(WorldSpec(), "the world simulation")
    drivers: list[DriverSpec] = param([], "who drives")
    faults: list[FaultSpec] = param([], "what breaks, when")
    obstacles: list[ObstacleSpec] = param([], "obstacles besides the map: shapes that appear, move "
                                              "and disappear")
    config: dict[str, Any] = param({}, "overrides merged into the daemon's sim config")
    car: CarSpec = param(CarSpec(), "the simulated car's true gains where they differ from the config")
    name: str = param("", "scenario name (default: the file name)")
    cars: list[ScenarioCar] = param([], "several cars in one world, each with its own daemon (then "
                                        "start, drivers, faults and car are each car's); none: one car")

    def __post_init__(self) -> None:
        check_finite("start", self.start)
        if not self.cars:
            return
        names = [c.name for c in self.cars]
        for k, name in enumerate(names):
            if name in names[:k]:
                raise ValueError(f"cars[{k}].name: {name!r}: two cars have this name")
        for key in ("drivers", "faults"):
            if getattr(self, key):
                raise ValueError(f"{key}: with cars, each car has its own {key} (cars[N].{key})")
        if self.start != (0.0, 0.0, 0.0):
            raise ValueError("start: with cars, each car has its own start (cars[N].start)")
        if self.car != CarSpec():
            raise ValueError("car: with cars, each car has its own car (cars[N].car)")
        for k, spec in enumerate(self.obstacles):
            if spec.name in names:
                raise ValueError(f"obstacles[{k}].name: {spec.name!r} is a car's name")

    def map_path(self) -> Path:
        """The map YAML: a shipped map by name, or a path relative to the scenario file."""
        candidate = Path(self.map)
        if candidate.suffix in (".yaml", ".yml"):
            return candidate
        shipped = config_dir() / "maps" / f"{self.map}.yaml"
        if not shipped.exists():
            names = sorted(p.stem for p in (config_dir() / "maps").glob("*.yaml"))
            raise ConfigError("map", f"no shipped map {self.map!r}; shipped maps: {', '.join(names)}")
        return shipped

    def check_bags(self, key: str = "scenario") -> None:
        """Refuse (a ConfigError naming the driver's ``bag`` key and the path) a ``follow`` driver,
        the scenario's or a car's, whose bag is not there, starting nothing. A bag that is there is
        read, and a damaged one refused, when the run loads it (still before its devices start)."""
        groups = [(f"{key}.drivers", self.drivers)]
        groups += [(f"{key}.cars.{k}.drivers", car.drivers) for k, car in enumerate(self.cars)]
        for prefix, drivers in groups:
            for i, spec in enumerate(drivers):
                if spec.type != "follow":
                    continue
                if not spec.bag:
                    raise ConfigError(f"{prefix}.{i}.bag", "a follow driver needs a bag")
                if not Path(spec.bag).exists():
                    raise ConfigError(f"{prefix}.{i}.bag", f"bag not found: {spec.bag}")

    def firmware_version(self) -> tuple[int, int]:
        """``firmware`` as (major, minor)."""
        major, sep, minor = self.firmware.partition(".")
        if not (sep and major.isdigit() and minor.isdigit()):
            raise ConfigError("firmware", f"{self.firmware!r} is not X.YY, like 6.02")
        return int(major), int(minor)


def scenario_names() -> list[str]:
    """The shipped scenarios."""
    return sorted(p.stem for p in (config_dir() / "scenarios").glob("*.yaml"))


def load_scenario(name_or_path: str, overrides: list[str] | tuple[str, ...] = ()) -> Scenario:
    """A shipped scenario by name, or a scenario file by path, with ``key=value`` overrides."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = config_dir() / "scenarios" / f"{name_or_path}.yaml"
        if not path.exists():
            raise ConfigError("scenario", f"no shipped scenario {name_or_path!r}; shipped scenarios: "
                                          + ", ".join(scenario_names()))
    data = load_yaml(path)
    for assignment in overrides:
        apply_override(data, assignment)
    data.setdefault("name", path.stem)
    scenario = build(Scenario, data, "scenario")
    if Path(scenario.map).suffix in (".yaml", ".yml") and not Path(scenario.map).is_absolute():
        scenario.map = str((path.parent / scenario.map).resolve())
    return scenario
