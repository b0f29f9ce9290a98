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
    config: {safety: {margin_m: 0.3}}   # merged into the daemon's sim config

Scenario time starts when the car is ready to drive (the VESC answered and the first scan is in),
as a driver on a real car would wait; ``duration_s``, ``from_s``/``until_s`` and ``at_s`` count from
there. The report and the trajectory use world time, which starts with the simulation.

Driver types: ``constant`` (a fixed command), ``script`` (``steps: [[t_s, speed, steering], ...]``,
each held until the next), ``figure8`` (``speed_mps``, ``steering_rad``, ``figure8s``), ``setpoint``
(the lab-0 relay holding ``speed_mps``/``steering_rad``), ``follow`` (a bag, see racecar_hw.bags.follow).
Fault actions: ``lidar_unplug``, ``lidar_replug``, ``vesc_unplug``, ``vesc_replug``,
``obstacle_ahead`` (``distance_m`` ahead of the car's front, ``radius_m``), ``clear_obstacles``,
``vesc_garbage`` (``bytes``), ``estop``, ``estop_release``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.overrides import apply_override, load_yaml
from racecar_hw.base.params import build, param
from racecar_hw.base.resources import config_dir

DRIVER_TYPES = ("constant", "script", "figure8", "setpoint", "follow")
FAULT_ACTIONS = ("lidar_unplug", "lidar_replug", "vesc_unplug", "vesc_replug", "obstacle_ahead",
                 "clear_obstacles", "vesc_garbage", "estop", "estop_release")


@dataclass
class DriverSpec:
    """One scripted source of commands on a mux input."""

    type: str = param("constant", "how commands are made", choices=DRIVER_TYPES)
    input: str = param("nav_0", "mux input name the commands go to")
    from_s: float = param(0.0, "start publishing at this scenario time", unit="s", min=0.0)
    until_s: float | None = param(None, "stop publishing at this scenario time; none: never", unit="s")
    speed_mps: float = param(1.0, "speed (constant, setpoint, figure8)", unit="m/s", min=-10, max=10)
    steering_rad: float = param(0.0, "steering angle, + left (constant, setpoint, figure8)",
                                unit="rad", min=-1.0, max=1.0)
    steps: list[tuple[float, float, float]] = param([], "script: [t_s, speed_mps, steering_rad] rows")
    figure8s: int = param(1, "figure8: how many", min=0)
    rate_hz: float = param(20.0, "command rate", unit="Hz", min=1.0, max=200.0)
    bag: str = param("", "follow: the bag to follow")
    topic: str = param("", "follow: topic in the bag; empty: its only drive-command topic (with "
                           "several, its only mux input)")
    reverse: bool = param(False, "follow: backwards")
    use_timestamps: bool = param(False, "follow: the bag's own timing")


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
class LidarSpec:
    """Which fake lidar the scenario uses, and how the daemon reaches it."""

    model: str = param("ust-10lx", "fake lidar model")
    transport: str = param("tcp", "tcp (Ethernet Hokuyo) or pty (serial models)", choices=("tcp", "pty"))


@dataclass
class WorldSpec:
    """World simulation settings."""

    rate_hz: float = param(200.0, "physics step rate", unit="Hz", min=20.0, max=2000.0)
    noise_std_m: float = param(0.01, "lidar range noise (standard deviation)", unit="m", min=0.0)
    seed: int | None = param(1, "random seed for the noise; none: different every run")


@dataclass
class Scenario:
    """A whole scenario. See the module documentation for the file format."""

    description: str = param("", "what the scenario shows")
    map: str = param("track", "shipped map name or path to a map_server YAML")
    start: tuple[float, float, float] = param((0.0, 0.0, 0.0), "start pose x, y, yaw in the map frame",
                                              unit="m, m, rad")
    duration_s: float = param(20.0, "scenario time to run (from when the car is ready)", unit="s",
                              min=0.1, max=3600.0)
    firmware: str = param("6.2", "fake VESC firmware version X.Y (selects the telemetry layout)")
    lidar: LidarSpec = param(LidarSpec(), "the fake lidar")
    world: WorldSpec = param(WorldSpec(), "the world simulation")
    drivers: list[DriverSpec] = param([], "who drives")
    faults: list[FaultSpec] = param([], "what breaks, when")
    config: dict[str, Any] = param({}, "overrides merged into the daemon's sim config")
    name: str = param("", "scenario name (default: the file name)")

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

    def firmware_version(self) -> tuple[int, int]:
        """``firmware`` as (major, minor)."""
        major, sep, minor = self.firmware.partition(".")
        if not (sep and major.isdigit() and minor.isdigit()):
            raise ConfigError("firmware", f"{self.firmware!r} is not X.Y")
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
