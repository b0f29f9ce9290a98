"""What the live interfaces read from the car and may ask of it.

The Foxglove server and the status page hold a :class:`CarControl` (the daemon). Reading
(:meth:`CarControl.live_state`) copies a few numbers in the event-loop thread; the requests (e-stop,
release, arm, disarm) act on the mux and the arming state at once, in the event-loop thread, with no
queue in between: an e-stop's brake command is written before the request returns.

Units: m/s, rad, V, s; positions in ``base_link`` (x forward, y left, metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from mux.estop import Origin

#: Safety colours, for the 3D scene and the page: free to drive, limited by the controller, held at 0.
CLEAR, LIMITING, STOPPED = "clear", "limiting", "stopped"


@dataclass(frozen=True)
class CarShape:
    """The footprint the safety controller sweeps and its stopping model (fixed while running)."""

    front_m: float        #: base_link to the front bumper
    rear_m: float         #: base_link to the rear bumper
    half_width_m: float   #: half the width plus the safety controller's lateral margin
    wheelbase_m: float
    latency_s: float      #: reaction delay before braking (sweep + processing + command transfer)
    max_decel_mps2: float
    margin_m: float       #: distance kept to an obstacle when stopped
    max_path_m: float     #: how far along the path the controller looks
    laser: tuple[float, float, float] = (0.0, 0.0, 0.0)  #: laser (x, y, yaw) in base_link

    def stopping_distance(self, speed_mps: float) -> float:
        """Path length (m) the car covers from ``speed_mps`` until stopped, plus the margin."""
        v = abs(speed_mps) if math.isfinite(speed_mps) else 0.0
        return min(self.max_path_m, v * self.latency_s + v * v / (2.0 * self.max_decel_mps2) + self.margin_m)


@dataclass(frozen=True)
class LiveState:
    """The car now. None: not known (no odometry yet, or none fresh) or not fitted (no lidar configured).

    ``measured_mps`` and ``battery_v`` come from the VESC's telemetry and are None while it is not
    fresh (:mod:`racecar_hw.control.state`); ``lidar_rate_hz`` counts the last second's scans only.
    """

    commanded_mps: float        #: what the active source asks for
    output_mps: float           #: what goes to the VESC (after safety and the rate limiter)
    allowed_mps: float          #: the safety controller's allowed speed; inf when it does not limit
    measured_mps: float | None  #: odometry, while fresh
    steering_rad: float         #: output steering, + left
    source: str                 #: the mux's active source (an input, idle, estop, fault)
    mux_state: str              #: running, estop or fault
    mux_reason: str             #: why estop or fault ("" while running)
    armed: bool
    safety_reason: str          #: clear, obstacle, stale_scan, no_scan, ... (safety.controller.REASONS)
    intervening: bool
    free_distance_m: float      #: along the commanded path; nan when not measured
    obstacle: tuple[float, float] | None  #: the limiting point in base_link
    battery_v: float | None
    vesc_connected: bool | None
    vesc_reconnects: int
    vesc_crc_errors: int
    lidar_scan_age_s: float | None
    lidar_rate_hz: float | None
    lidar_reconnects: int
    #: who latched the e-stop and when, or how the last latch ended ("" when never engaged)
    estop: str = ""
    #: what the network surfaces refused: (surface, reason, total since start) of each kind
    refused: tuple[tuple[str, str, int], ...] = ()
    refused_recently: bool = False  #: anything refused in the last few seconds
    control_ticks: int = 0              #: control loop ticks since the start
    control_missed_ticks: int = 0       #: ticks the loop was too late for (a held-up machine)

    @property
    def safety_colour(self) -> str:
        """:data:`CLEAR`, :data:`LIMITING` or :data:`STOPPED`."""
        if self.mux_state != "running" or not self.armed or self.allowed_mps <= 0.0:
            return STOPPED
        return LIMITING if self.intervening else CLEAR


class CarControl(Protocol):
    """The daemon as the live interfaces see it; call from the event-loop thread only."""

    shape: CarShape

    def live_state(self) -> LiveState:
        """A copy of the car's state now."""
        ...

    def engage_estop(self, origin: Origin) -> str:
        """Latch the mux e-stop and send the brake now; returns what happened, for the requester."""
        ...

    def release_estop(self, origin: Origin) -> tuple[bool, str]:
        """Release the latched e-stop if ``origin`` may (:mod:`mux.estop`): (released, why not or what
        happened)."""
        ...

    def arm(self, who: str) -> tuple[bool, str]:
        """Arm the car: (armed now, what happened)."""
        ...

    def disarm(self, who: str) -> tuple[bool, str]:
        """Disarm the car: (disarmed now, what happened)."""
        ...
