"""The car's state as every display reads it: one read model.

:meth:`CarState.live_state` copies the numbers the live interfaces need (Foxglove's scene, the
status page) in the event-loop thread; :meth:`CarState.snapshot`, what the console panel and the
MAVLink telemetry show, is a view of the same read plus the panel's own lines (links, where the
live interfaces listen, the keyboard's keys). ``/diagnostics`` carries the same counters (the
control path's :meth:`~racecar_hw.control.path.ControlPath.status`, the mux's, the safety node's).

What comes from the VESC's telemetry (the measured speed from odometry, the battery voltage) is
shown only while it is fresh: when the last reply is older than ``safety.odom_timeout_s`` (0.5 s,
the age past which the safety controller takes no measured speed from odometry; at least two poll
periods, for a ``vesc.poll_rate_hz`` under 4 Hz) or the VESC's link
is not up, it is unknown (None; ``-`` in the status line), not the last value from before the VESC
went quiet. The scan rate counts recent arrivals only (:meth:`ControlStats.scan_rate_hz`).

Units: m/s, rad, V, s; positions in ``base_link``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

from lidar_drivers.base import LidarDriver
from mux.node import CommandMux
from racecar_hw.base.bus import Bus, Latest
from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.messages import AckermannDrive
from racecar_hw.base.topics import TOPIC_CORE
from racecar_hw.base.transforms import yaw_of
from racecar_hw.config import Config
from racecar_hw.control.stats import ControlStats
from racecar_hw.net.control import CarShape, LiveState
from racecar_hw.runtime.links import LinkWatch
from racecar_hw.runtime.security_status import SecurityStatus
from racecar_hw.runtime.status import StatusSnapshot
from racecar_hw.teleop.arming import Arming
from safety.node import SafetyNode
from vesc.driver import VescDriver


def car_shape(config: Config, laser: Any) -> CarShape:
    """The footprint the safety controller sweeps, for the live view; ``laser``: the base_link ->
    laser transform (4x4), or None to take the safety parameters' laser pose."""
    fp, safety = config.safety.footprint, config.safety
    return CarShape(
        front_m=fp.front_m, rear_m=fp.rear_overhang_m, half_width_m=fp.width_m / 2 + safety.lateral_margin_m,
        wheelbase_m=fp.wheelbase_m, latency_s=safety.latency_s, max_decel_mps2=safety.max_decel_mps2,
        margin_m=safety.margin_m, max_path_m=safety.max_path_m,
        laser=((float(laser[0, 3]), float(laser[1, 3]), yaw_of(laser)) if laser is not None
               else (safety.laser.x_m, safety.laser.y_m, safety.laser.yaw_rad)))


@dataclasses.dataclass
class CarState:
    """Reads the components; holds no state of its own. Call from the event-loop thread."""

    bus: Bus
    config: Config
    mux: CommandMux
    safety: SafetyNode
    arming: Arming
    vesc: VescDriver | None
    lidar: LidarDriver | None
    stats: ControlStats
    security: SecurityStatus
    links: dict[str, LinkWatch]
    #: where the live interfaces listen (``foxglove``, ``web``)
    urls: Callable[[], dict[str, str]]
    #: the keyboard's key hints for the panel, None without a keyboard
    keys: str | None = None
    #: extra fields for the status panel (the simulator adds its time, pose and clearance)
    extra_status: Callable[[], dict[str, Any]] | None = None

    def live_state(self) -> LiveState:
        """The car now, for the live interfaces (:class:`racecar_hw.net.control.CarControl`)."""
        mux, vesc, lidar = self.mux, self.vesc, self.lidar
        now = monotonic_ns()
        out = mux.last_output
        drive = out.drive if out is not None else AckermannDrive()
        asked = mux.last_command(mux.source)
        odom = self._fresh(self.config.safety.odom_topic, now)
        safety = self.safety.state
        state = self._fresh(TOPIC_CORE, now) if vesc is not None else None
        scan = self.bus.latest_entry(self.config.safety.scan_topic)
        return LiveState(
            commanded_mps=float(asked.speed) if asked is not None else 0.0,
            output_mps=float(drive.speed), allowed_mps=float(safety.allowed_speed),
            measured_mps=float(odom.twist.twist.linear.x) if odom is not None else None,
            steering_rad=float(drive.steering_angle), source=mux.source or "idle",
            mux_state=mux.state.value, mux_reason=mux.machine.reason, armed=self.arming.armed,
            safety_reason=safety.reason, intervening=safety.intervening,
            free_distance_m=float(safety.free_distance),
            obstacle=(safety.obstacle.x, safety.obstacle.y) if safety.obstacle is not None else None,
            battery_v=float(state.state.voltage_input) if state is not None else None,
            vesc_connected=vesc.connected if vesc is not None else None,
            vesc_reconnects=vesc.stats.reconnects if vesc is not None else 0,
            vesc_crc_errors=vesc.stats.crc_errors if vesc is not None else 0,
            lidar_scan_age_s=(now - scan.received_ns) / NS_PER_S if scan is not None else None,
            lidar_rate_hz=self.stats.scan_rate_hz(now) if lidar is not None else None,
            lidar_reconnects=lidar.stats.reconnects if lidar is not None else 0,
            estop=mux.estop_text() if mux.estop is not None else "",
            refused=tuple(self.security.rows()), refused_recently=self.security.recent(),
            control_ticks=self.stats.ticks, control_missed_ticks=self.stats.missed_ticks)

    def _fresh(self, topic: str, now_ns: int) -> Any | None:
        """The last VESC telemetry message on ``topic``, or None when it is older than
        ``safety.odom_timeout_s`` (s; with a VESC, at least two of its poll periods) at ``now_ns``
        (monotonic ns) or the VESC's link is not up."""
        entry: Latest[Any] | None = self.bus.latest_entry(topic)
        if entry is None or (self.vesc is not None and not self.vesc.connected):
            return None
        max_age_s = self.config.safety.odom_timeout_s
        if self.vesc is not None:  # a slow poll (vesc.poll_rate_hz under 2 Hz) is not a stale one
            max_age_s = max(max_age_s, 2.0 / self.config.vesc.poll_rate_hz)
        if now_ns - entry.received_ns > max_age_s * NS_PER_S:
            return None
        return entry.msg

    def snapshot(self) -> StatusSnapshot:
        """What the status panel and the MAVLink telemetry show: :meth:`live_state` and the panel's
        own lines."""
        live = self.live_state()
        out = self.mux.last_output
        vesc_link, lidar_link = self.links.get("vesc"), self.links.get("lidar")
        urls = self.urls()
        snap = StatusSnapshot(
            speed_mps=live.measured_mps,
            steering_rad=live.steering_rad if out is not None else None,
            mux_source=self.mux.source, battery_v=live.battery_v, scan_rate_hz=live.lidar_rate_hz,
            safety_state=live.safety_reason,
            safety_allowed_mps=live.allowed_mps if math.isfinite(live.allowed_mps) else None,
            vesc_crc_errors=live.vesc_crc_errors, vesc_reconnects=live.vesc_reconnects,
            lidar_reconnects=live.lidar_reconnects, armed=live.armed,
            vesc_link=vesc_link.text() if vesc_link is not None else None,
            lidar_link=lidar_link.text() if lidar_link is not None else None,
            live_view=urls.get("foxglove"), page=urls.get("web"), keys=self.keys,
            estop=live.estop or None, refused=self.security.line())
        if self.extra_status is not None:
            snap = dataclasses.replace(snap, **self.extra_status())
        return snap
