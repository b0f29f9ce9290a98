"""What the daemon shows the operator: :class:`StatusSnapshot`, and its fields as text.

The control loop makes a snapshot; :func:`status_fields` and :func:`plain_line` put it in words (the
plain status line of logs and pipes). The live console panel that draws it with ``rich`` is
:mod:`racecar_hw.runtime.panel`, imported only where a panel is made (``status.enabled``, off in
the car's config): the daemon itself needs only the snapshot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

NONE = "-"


@dataclass(frozen=True)
class StatusSnapshot:
    """What the car is doing, for the operator. None means "not known (yet, or any more: a device gone
    quiet)" or "not fitted".

    Speed in m/s (rear axle, negative in reverse), steering in rad (positive left), battery in V,
    scan rate in Hz, the safety controller's state and the speed it allows (m/s), each device's
    link state (``up``, ``connecting 3 s``, ``lost since 14:02:31 (35 s)``) and counters, whether
    the car is armed (None: no arming input configured), what the network surfaces refused
    (:meth:`racecar_hw.runtime.security_status.SecurityStatus.line`; None: nothing yet), and, when
    running on fake hardware, the simulator's time (s), the car's pose in the map frame (x m, y m,
    yaw rad) and its clearance to the nearest wall or obstacle (m).
    """

    speed_mps: float | None = None
    steering_rad: float | None = None
    mux_source: str | None = None
    battery_v: float | None = None
    scan_rate_hz: float | None = None
    safety_state: str | None = None
    safety_allowed_mps: float | None = None
    vesc_crc_errors: int = 0
    vesc_reconnects: int = 0
    lidar_reconnects: int = 0
    armed: bool | None = None
    sim_pose: tuple[float, float, float] | None = None
    vesc_link: str | None = None
    lidar_link: str | None = None
    sim_time_s: float | None = None
    clearance_m: float | None = None
    #: where the Foxglove live view and the status page listen (URLs), when they are on
    live_view: str | None = None
    page: str | None = None
    #: the keys that drive, when keyboard teleop is on
    keys: str | None = None
    #: who latched the mux e-stop and when (``latched by web page (127.0.0.1) at 18:50:01.123``),
    #: or who released the last latch; None: never engaged
    estop: str | None = None
    refused: str | None = None


#: What a non-finite reading shows: a summary never says ``nan``.
INVALID = "invalid"


def _num(value: float | None, fmt: str, unit: str) -> str:
    if value is None:
        return NONE
    if not math.isfinite(value):
        return INVALID
    return f"{value:{fmt}} {unit}"


def _link(link: str | None, counters: str) -> str:
    return f"{link}, {counters}" if link else counters


def _armed(armed: bool | None) -> str:
    return {True: "ARMED", False: "disarmed", None: "n/a"}[armed]


def _safety(s: StatusSnapshot) -> str:
    state = s.safety_state or NONE
    if s.safety_allowed_mps is not None:
        state += f" (max {_num(s.safety_allowed_mps, '.2f', 'm/s')})"
    return state


def _pose(pose: tuple[float, float, float] | None) -> str:
    if pose is None:
        return NONE
    x, y, yaw = pose
    if not all(math.isfinite(v) for v in pose):
        return INVALID
    return f"x {x:.2f} m  y {y:.2f} m  yaw {math.degrees(yaw):.0f} deg"


def status_fields(s: StatusSnapshot) -> list[tuple[str, str]]:
    """(label, text) pairs in display order; the plain line and the panel show the same fields."""
    fields = [
        ("speed", _num(s.speed_mps, "+.2f", "m/s")),
        ("steer", _num(s.steering_rad, "+.3f", "rad")),
        ("mux", s.mux_source or "idle"),
        ("battery", _num(s.battery_v, ".1f", "V")),
        ("scan", _num(s.scan_rate_hz, ".1f", "Hz")),
        ("safety", _safety(s)),
        ("vesc", _link(s.vesc_link, f"crc errors {s.vesc_crc_errors}, reconnects {s.vesc_reconnects}")),
        ("lidar", _link(s.lidar_link, f"reconnects {s.lidar_reconnects}")),
        ("armed", _armed(s.armed)),
    ]
    if s.estop is not None:
        fields.append(("e-stop", s.estop))
    if s.refused is not None:
        fields.append(("refused", s.refused))
    if s.sim_time_s is not None:
        fields.append(("sim time", _num(s.sim_time_s, ".1f", "s")))
    if s.sim_pose is not None:
        fields.append(("sim pose", _pose(s.sim_pose)))
    if s.clearance_m is not None:
        fields.append(("clearance", _num(s.clearance_m, ".2f", "m")))
    if s.live_view is not None:
        fields.append(("live view", s.live_view))
    if s.page is not None:
        fields.append(("page", s.page))
    if s.keys is not None:
        fields.append(("keys", s.keys))
    return fields


def plain_line(s: StatusSnapshot) -> str:
    """One line for logs and pipes: ``speed +1.20 m/s | steer +0.150 rad | ...``."""
    return " | ".join(f"{label} {text}" for label, text in status_fields(s))
