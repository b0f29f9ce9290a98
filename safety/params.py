"""Parameters of the safety-stop controller.

Frames and units: ``base_link`` sits at the centre of the rear axle (REP-103: x forward, y left,
z up), distances in metres, angles in radians, speeds in m/s, times in seconds. The defaults
describe a 1/10-scale MIT RACECAR / F1TENTH car with a Hokuyo UST-10LX on its front deck; see
``docs/safety.md`` for why each default is what it is.
"""

from __future__ import annotations

from dataclasses import dataclass

from racecar_hw.base.params import param
from racecar_hw.base.topics import MUX_SAFETY_TOPIC

MODES = ("arc", "cone", "off")


@dataclass
class FootprintParams:
    """The car's outline: a rectangle around ``base_link`` (the rear axle centre)."""

    length_m: float = param(0.55, "bumper to bumper length", unit="m", min=0.05, max=5.0)
    width_m: float = param(0.30, "overall width, wheels included", unit="m", min=0.05, max=3.0)
    wheelbase_m: float = param(0.25, "rear axle to front axle; the VESC/vesc_to_odom default",
                               unit="m", min=0.05, max=3.0)
    rear_overhang_m: float = param(0.10, "rear axle (base_link) to the rear bumper; the front "
                                         "bumper is length_m - rear_overhang_m ahead of base_link",
                                   unit="m", min=0.0, max=2.0)

    def __post_init__(self) -> None:
        if self.rear_overhang_m >= self.length_m:
            raise ValueError(f"rear_overhang_m ({self.rear_overhang_m}) must be shorter than "
                             f"length_m ({self.length_m})")

    @property
    def front_m(self) -> float:
        """Distance from base_link forward to the front bumper, metres."""
        return self.length_m - self.rear_overhang_m


@dataclass
class LaserPoseParams:
    """Where the laser sits in base_link, used when the daemon gives no laser->base_link transform.

    The default, 0.265 m ahead of the rear axle on the centre line, facing forward, is the MIT
    RACECAR's static base_link->laser transform.
    """

    x_m: float = param(0.265, "laser origin, forward of base_link", unit="m", min=-5.0, max=5.0)
    y_m: float = param(0.0, "laser origin, left of base_link", unit="m", min=-5.0, max=5.0)
    yaw_rad: float = param(0.0, "laser heading relative to base_link, counter-clockwise", unit="rad",
                           min=-3.1416, max=3.1416)


@dataclass
class ConeParams:
    """The seeds' simple safety node: stop while anything is close inside a forward cone."""

    half_angle_rad: float = param(0.35, "half the cone's opening, around the laser's x axis",
                                  unit="rad", min=0.0, max=3.1416)
    stop_distance_m: float = param(0.5, "stop while a valid range in the cone is shorter than this",
                                   unit="m", min=0.0, max=30.0)
    release_margin_m: float = param(0.05, "resume only once every range in the cone exceeds "
                                           "stop_distance_m by this much (no chatter)",
                                    unit="m", min=0.0, max=5.0)
    topic: str = param(MUX_SAFETY_TOPIC, "where the zero-speed AckermannDriveStamped goes: the "
                                         "mux's top-priority safety input", topic=True)


@dataclass
class MemoryParams:
    """The obstacle memory: recent lidar returns kept in the odom frame, for where the lidar is blind.

    See ``docs/safety.md`` ("Obstacle memory") for the model, its assumptions and its limits.
    """

    enabled: bool = param(True, "remember what the lidar saw and check the reverse path (and the "
                                "sides it cannot see) against it; needs odometry on odom_topic")
    size_m: float = param(10.0, "side of the square window remembered around the car", unit="m",
                          min=1.0, max=50.0)
    resolution_m: float = param(0.05, "cell size of the remembered grid", unit="m", min=0.01, max=0.5)
    max_age_s: float = param(10.0, "forget a return not seen again for this long (odometry drifts)",
                             unit="s", min=0.1, max=600.0)
    see_through_m: float = param(0.1, "forget a remembered return once the lidar sees this far "
                                      "beyond it (range noise and the cell size stay below this)",
                                 unit="m", min=0.0, max=2.0)
    reach_m: float = param(3.0, "sweep remembered returns within this distance of the car (farther "
                                "ones matter only to paths the lidar sees, or to reversing faster "
                                "than reverse_speed_cap_mps)", unit="m", min=0.5, max=50.0)
    update_period_s: float = param(0.1, "take a scan into the memory at most this often (the update "
                                        "costs CPU; the live scan is used every time)", unit="s",
                                   min=0.0, max=1.0)


@dataclass
class SafetyParams:
    """The safety-stop controller: the largest speed from which the car surely stops in time."""

    mode: str = param("arc", "arc: limit speed by the free distance along the path the footprint "
                             "sweeps at the commanded steering; cone: the seeds' simple stop on the "
                             "mux safety input; off: no safety", choices=MODES)
    footprint: FootprintParams = param(FootprintParams(), "the car's outline")
    laser: LaserPoseParams = param(LaserPoseParams(), "laser pose in base_link when the daemon "
                                                      "gives none")
    lateral_margin_m: float = param(0.05, "added to each side of the footprint when sweeping the "
                                          "path", unit="m", min=0.0, max=1.0)
    margin_m: float = param(0.25, "distance kept between the stopped car's bumper and the obstacle",
                            unit="m", min=0.0, max=5.0)
    max_decel_mps2: float = param(4.0, "deceleration the car surely achieves when braking",
                                  unit="m/s^2", min=0.1, max=30.0)
    scan_period_s: float = param(0.025, "lidar sweep period (UST-10LX 40 Hz)", unit="s",
                                 min=0.0, max=1.0)
    processing_s: float = param(0.01, "scan transport and processing delay", unit="s",
                                min=0.0, max=1.0)
    command_transfer_s: float = param(0.02, "command to VESC and motor response delay", unit="s",
                                      min=0.0, max=1.0)
    max_path_m: float = param(10.0, "look this far along the path at most; it also bounds the "
                                    "allowed speed", unit="m", min=0.1, max=100.0)
    scan_timeout_s: float = param(0.1, "a scan older than this counts as stale: allowed speed 0",
                                  unit="s", min=0.01, max=10.0)
    min_valid_fraction: float = param(0.5, "refuse (allowed speed 0) a scan in which fewer beams "
                                           "than this are usable: NaN (device fault) or below "
                                           "range_min (blocked window) do not count; inf does",
                                      min=0.0, max=1.0)
    min_return_fraction: float = param(0.01, "refuse (allowed speed 0) a scan in which fewer beams "
                                              "than this return a range (from range_min to range_max): "
                                              "a blinded or failing lidar reports every beam as no "
                                              "return (an RPLIDAR's distance 0, published inf), which "
                                              "the car cannot tell from open space; 0 trusts such a scan",
                                       min=0.0, max=1.0)
    centre_when_blind: bool = param(True, "while the lidar is blind (no scan yet, a stale or a bad "
                                          "scan) the command is a stop with the steering centred, "
                                          "as every stale input's is; false keeps the commanded "
                                          "steering while the car brakes")
    ignore_inside_footprint: bool = param(False, "ignore returns inside the footprint (the lidar "
                                                 "seeing its own car); otherwise they block at 0 m")
    reverse_speed_cap_mps: float = param(0.5, "largest reverse speed (the forward lidar cannot see "
                                              "behind; the memory only lowers it)", unit="m/s",
                                         min=0.0, max=20.0)
    reverse_uses_scan: bool = param(False, "also sweep the path behind the car in reverse (a 360 deg "
                                           "lidar that sees behind)")
    memory: MemoryParams = param(MemoryParams(), "the obstacle memory (mode arc)")
    exempt_teleop: bool = param(False, "let teleop commands through unlimited")
    teleop_source: str = param("teleop", "mux source name of the joystick")
    exempt_sources: list[str] = param([], "mux source names let through unlimited")
    release_margin_mps: float = param(0.1, "an intervention ends only once the allowed speed exceeds "
                                           "the commanded and measured speed by this much",
                                      unit="m/s", min=0.0, max=10.0)
    release_hold_s: float = param(0.3, "... continuously for this long", unit="s", min=0.0, max=10.0)
    measured_tolerance_mps: float = param(0.1, "odometry noise allowed before a measured speed above "
                                               "the allowed one counts as an intervention",
                                          unit="m/s", min=0.0, max=5.0)
    odom_timeout_s: float = param(0.5, "odometry older than this is ignored (speed and memory)", unit="s",
                                  min=0.01, max=10.0)
    cone: ConeParams = param(ConeParams(), "mode cone only")
    scan_topic: str = param("/scan", "sensor_msgs/LaserScan input", topic=True)
    odom_topic: str = param("/odom", "nav_msgs/Odometry input: the measured speed (twist.linear.x) "
                                     "and the pose the obstacle memory follows", topic=True)
    state_topic: str = param("/safety/state", "diagnostic_msgs/DiagnosticArray output", topic=True)
    state_rate_hz: float = param(2.0, "state republish rate when nothing changes", unit="Hz",
                                 min=0.1, max=100.0)

    @property
    def latency_s(self) -> float:
        """Total reaction delay before braking starts: sweep + processing + command transfer."""
        return self.scan_period_s + self.processing_s + self.command_transfer_s
