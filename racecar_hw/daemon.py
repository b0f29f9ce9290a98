"""The daemon: every configured component on one bus, in one asyncio event loop.

Thread model (see docs/architecture.md): the event loop thread runs the drivers, the mux, the
safety controller and every publisher; the bag recorder writes from its own thread behind a bounded
queue; in ``racecar-hw sim`` the fake devices and the world run in a separate device thread.

The control path, at the mux rate (default 50 Hz)::

    mux inputs -> arbitration -> [arming] -> safety -> rate limiter -> output topic -> VESC

and, on every scan, at once: the last output is re-checked by the safety controller against the
new scan and goes to the VESC without waiting for the next tick, so a scan's verdict reaches the
motor within a millisecond or two. A cut is also published on the output topic and clamps the
limiter so later ticks cannot raise it again. The safety controller's obstacle memory takes in
the scan after that, off the scan-to-command path. The scan path sends nothing while the control loop
is stalled, so a dead loop still lets the VESC driver's command timeout brake the car. The
watchdog is pinged from the control tick, so a stalled control loop gets the daemon restarted.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import logging
import math
import sys
from collections import deque
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

from lidar_drivers.base import LidarDriver
from lidar_drivers.registry import make_driver
from mux.arbiter import MuxState
from mux.estop import Origin
from mux.node import CommandMux
from racecar_hw.bags.follow import BagFollower
from racecar_hw.bags.record import Recorder
from racecar_hw.bags.validate import CommandLimits
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    DiagnosticArray,
    DiagnosticStatus,
    KeyValue,
    LaserScan,
    Message,
    stamp_now,
)
from racecar_hw.base.params import describe, to_dict
from racecar_hw.base.transforms import TfTree, yaw_of
from racecar_hw.config import FOXGLOVE_INPUT, Config, cmd_vel_input_topic, listeners, network_topics
from racecar_hw.net import zenoh_logins
from racecar_hw.net.control import CarShape, LiveState
from racecar_hw.net.dds_bridge import DdsBridge
from racecar_hw.net.dds_config import cyclone_available
from racecar_hw.net.foxglove_server import FoxgloveServer
from racecar_hw.net.gate import quiet_accept_errors
from racecar_hw.net.inbox import Inbox
from racecar_hw.net.parameters import ParameterService
from racecar_hw.net.ports import port_taken, taken_message
from racecar_hw.net.rosout import RosoutHandler, logger_name
from racecar_hw.net.topics import Direction, Topic
from racecar_hw.net.web import WebServer
from racecar_hw.net.zenoh_bridge import ZenohBridge
from racecar_hw.runtime.fdlimit import FileLimit, raise_open_file_limit
from racecar_hw.runtime.links import LinkWatch
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.sdnotify import Notifier
from racecar_hw.runtime.security_status import SecurityStatus
from racecar_hw.runtime.status import StatusPanel, StatusSnapshot
from racecar_hw.runtime.ticker import PeriodicTimer
from racecar_hw.sources.cmd_vel import CmdVelConverter, CmdVelParams
from racecar_hw.sources.figure8 import Figure8Driver
from racecar_hw.sources.scan_summary import ScanSummaryPublisher
from racecar_hw.sources.setpoint import SetpointRelay
from racecar_hw.teleop.arming import Arming
from racecar_hw.teleop.gamepad import GamepadTeleop
from racecar_hw.teleop.keyboard import KEY_HINTS, KeyboardTeleop
from racecar_hw.teleop.mavlink_gcs import MavlinkGcs
from safety.node import SafetyNode
from vesc.driver import TOPIC_ODOM, TOPIC_TF, VescDriver

log = logging.getLogger(__name__)

Filter = Callable[[AckermannDrive, str, int], AckermannDrive]

#: How often the link watches are polled (s): panel link states and reminders.
LINK_POLL_S = 0.5

#: GIL switch interval while the daemon runs (seconds); CPython's default is 0.005.
SWITCH_INTERVAL_S = 0.0001


@dataclass(frozen=True)
class EstopRequest:
    """An e-stop asked for through a live interface (Foxglove service, status page)."""

    at_ns: int                      #: when the request reached the daemon (monotonic ns)
    who: str                        #: who asked, for the log ("web page (127.0.0.1)")
    #: frames the VESC driver had written before it (its ``stats.frames_tx``): the brake is
    #: the first motor command after them; None without a VESC
    vesc_frames_before: int | None


@dataclass
class ControlStats:
    """Counters of the control loop."""

    ticks: int = 0
    missed_ticks: int = 0
    scan_cuts: int = 0
    last_tick_ns: int = 0
    scan_rate_hz: float = 0.0
    #: recent scan-to-command latencies (ns): from the read that completed a scan returning to the
    #: scan path's VESC command written
    scan_to_command_ns: deque[int] = field(default_factory=lambda: deque(maxlen=100_000))
    #: the loop thread's CPU time (ns) in each of those: the rest of a latency is time the thread
    #: was off the CPU (preempted, or its virtual CPU not running)
    scan_to_command_cpu_ns: deque[int] = field(default_factory=lambda: deque(maxlen=100_000))
    #: arrival times (monotonic ns) of the last scans, for scan_rate_hz
    scan_times: deque[int] = field(default_factory=lambda: deque(maxlen=20))

    def latency_ms(self) -> dict[str, float]:
        """Percentiles of the recent scan-to-command latencies, milliseconds.

        ``p50``, ``p99``, ``max`` and ``count`` of the latencies; ``cpu_p50`` and ``cpu_p99`` of the
        CPU time in them, ``off_cpu_p99`` of the time off the CPU.
        """
        if not self.scan_to_command_ns:
            return {}
        wall = list(self.scan_to_command_ns)
        cpu = list(self.scan_to_command_cpu_ns)
        off = [w - c for w, c in zip(wall, cpu, strict=True)]
        return {"p50": _percentile(wall, 50) / 1e6, "p99": _percentile(wall, 99) / 1e6,
                "max": max(wall) / 1e6, "count": float(len(wall)),
                "cpu_p50": _percentile(cpu, 50) / 1e6, "cpu_p99": _percentile(cpu, 99) / 1e6,
                "off_cpu_p99": _percentile(off, 99) / 1e6}

    def summary(self) -> str:
        """One line for the log at exit; says so when no scan's command was timed (never ``nan``)."""
        head = f"{self.ticks} ticks, {self.missed_ticks} missed, {self.scan_cuts} scan cuts"
        lat = self.latency_ms()
        if not lat:
            return f"{head}; no scan-to-command latency measured (no scan led to a motor command)"
        return (f"{head}; scan-to-command latency p50={lat['p50']:.3f} ms p99={lat['p99']:.3f} ms "
                f"max={lat['max']:.3f} ms over {int(lat['count'])} scans; on the CPU "
                f"p50={lat['cpu_p50']:.3f} ms p99={lat['cpu_p99']:.3f} ms; off it "
                f"p99={lat['off_cpu_p99']:.3f} ms")


def _percentile(values: list[int], q: int) -> int:
    """The ``q``-th percentile of ``values`` (not empty): the nearest rank, no interpolation."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, (q * len(ordered)) // 100)]


def reverse_speed_cap(config: Config) -> float | None:
    """The fastest the safety controller lets the car reverse (m/s); None when it does not cap
    (``off``, and ``cone``, which only stops the car through the mux)."""
    return config.safety.reverse_speed_cap_mps if config.safety.mode == "arc" else None


def command_limits(config: Config) -> CommandLimits:
    """What a followed bag may ask of this car: the VESC's configured speed and steering limits."""
    return CommandLimits(config.vesc.speed_max_mps, config.vesc.steering_max_rad)


class Daemon:
    """Builds the configured components on ``bus`` and runs them until stopped."""

    def __init__(self, config: Config, *, bus: Bus | None = None, notifier: Notifier | None = None,
                 status: StatusPanel | None = None) -> None:
        self.config = config
        self.bus = bus if bus is not None else Bus()
        self.notifier = notifier if notifier is not None else Notifier.from_env()
        self.stats = ControlStats()
        #: what the network surfaces refused (bad logins, forged frames, floods), for /diagnostics,
        #: the panel, the status page and rate-limited log lines
        self.refusals = Refusals()
        #: the refusals as a status in /diagnostics, a panel line and rows on the status page
        self.security = SecurityStatus(self.refusals)
        self.tf = TfTree.from_params(config.static_transforms)
        self.vesc: VescDriver | None = VescDriver(self.bus, config.vesc) if config.vesc.enabled else None
        self.lidar: LidarDriver | None = (make_driver(self.bus, config.lidar)
                                          if config.lidar.enabled else None)
        self.mux = CommandMux(self.bus, config.mux, refusals=self.refusals)
        self.safety = SafetyNode(self.bus, config.safety, self._laser_to_base(), defer_memory=True,
                                 steering_limit_rad=config.vesc.steering_max_rad)
        self.arming = Arming.from_params(config.arming)
        pad = Origin("gamepad", "gamepad")
        self.gamepad = (GamepadTeleop(self.bus, config.gamepad, self.arming,
                                      on_estop=lambda: self.engage_estop(pad),
                                      on_release=lambda: log.warning("gamepad: %s",
                                                                     self.release_estop(pad)[1]))
                        if config.gamepad.enabled else None)
        keyboard = Origin("keyboard", "keyboard")
        self.keyboard = (KeyboardTeleop(self.bus, config.keyboard,
                                        on_estop=lambda: self.engage_estop(keyboard),
                                        on_release=lambda: log.warning("keyboard: %s",
                                                                       self.release_estop(keyboard)[1]))
                         if config.keyboard.enabled else None)
        self.mavlink = (MavlinkGcs(self.bus, config.mavlink, self.arming, status_source=self.snapshot,
                                   refusals=self.refusals)
                        if config.mavlink.enabled else None)
        hold = (self.mavlink.filter,) if self.mavlink is not None else ()
        self.filters: tuple[Filter, ...] = (self.arming.filter, *hold, self.safety.filter)
        self.scan_summary = (ScanSummaryPublisher(self.bus, config.scan_summary)
                             if config.scan_summary.enabled else None)
        self.setpoint = SetpointRelay(self.bus, config.setpoint) if config.setpoint.enabled else None
        self.figure8 = (Figure8Driver(self.bus, config.figure8.params(config.vesc.wheelbase_m))
                        if config.figure8.enabled else None)
        self.follower = (BagFollower(self.bus, config.follower, wheelbase_m=config.vesc.wheelbase_m,
                                     reverse_speed_cap_mps=reverse_speed_cap(config),
                                     limits=command_limits(config))
                         if config.follower.enabled else None)
        self.recorder = Recorder(self.bus, config.recorder) if config.recorder.enabled else None
        self.status = status
        #: extra fields for the status panel (the simulator adds its time, pose and clearance)
        self.extra_status: Callable[[], dict[str, Any]] | None = None
        self.links: dict[str, LinkWatch] = {}
        if self.vesc is not None:
            vesc = self.vesc
            self.links["vesc"] = LinkWatch("VESC", lambda: vesc.connected,
                                           detail=lambda: f"port {config.vesc.port}")
        if self.lidar is not None:
            lidar = self.lidar
            self.links["lidar"] = LinkWatch(f"lidar {config.lidar.model}", lambda: lidar.connected,
                                            detail=lambda: lidar.last_error)
        self._tasks: list[asyncio.Task[Any]] = []
        #: where the live interfaces listened once started (``live_urls``), for reports
        self.started_live: dict[str, str] = {}
        self._extra: list[Coroutine[Any, Any, Any]] = []
        self._watchdog_period_ns: int | None = None
        #: control ticks between two of the mux's diagnostics (``mux.diagnostics_rate_hz``)
        self._diagnostics_every = max(1, round(config.mux.rate_hz / config.mux.diagnostics_rate_hz))
        self._last_watchdog_ns = 0
        self._switch_interval: float | None = None
        self._file_limit: FileLimit | None = None
        self._restore_exception_handler: Callable[[], None] | None = None
        self._build_live()
        self.bus.subscribe(config.mux.output_topic, self._on_output)
        # The bus calls a topic's subscribers in order: the safety node's (above) caches the scan,
        # this one writes the motor command, and diagnostics subscribed in run() come after it.
        self.bus.subscribe(config.safety.scan_topic, self._on_scan)
        self._build_network(config)

    # --- wiring ---------------------------------------------------------------------------------

    def _laser_to_base(self) -> Any:
        frame = self.config.lidar.frame_id
        if self.tf.can_transform("base_link", frame):
            return self.tf.lookup("base_link", frame)
        if self.config.lidar.enabled and self.config.safety.mode == "arc":
            raise ConfigError("static_transforms", f"no transform from base_link to the lidar frame "
                                                   f"{frame!r}: the safety controller needs one")
        return None

    def _build_network(self, config: Config) -> None:
        """The network inbox, the Zenoh bridge (ROS 2 topics for remote code) and the /cmd_vel converter.

        Built after the scan path's subscriptions, so a scan reaches the bridge's queue only after
        its motor command is written. Every network surface hands its inbound messages to the one
        :class:`~racecar_hw.net.inbox.Inbox`, which coalesces them into the event loop.
        """
        self.zenoh: ZenohBridge | None = None
        self.dds: DdsBridge | None = None
        self.cmd_vel: CmdVelConverter | None = None
        self.inbox: Inbox | None = None
        z, d = config.zenoh, config.dds
        #: the daemon's log on /rosout (the topic table's row; every network interface carries it)
        self.rosout: RosoutHandler | None = (
            RosoutHandler(self.bus, config.rosout, logger_name(z.namespace, z.node_name))
            if config.rosout.enabled else None)
        #: the read-only parameter services' answers: the effective configuration
        self.parameters = ParameterService(to_dict(config),
                                           {name: doc for name, _, doc in describe(Config)})
        if not z.enabled and not d.enabled:
            return
        self._remote_inputs = {i.topic: i.name for i in config.mux.inputs}
        twist_input = cmd_vel_input_topic(config)
        if z.cmd_vel and twist_input:
            self.cmd_vel = CmdVelConverter(self.bus, CmdVelParams(
                z.cmd_vel_topic, twist_input, config.vesc.wheelbase_m, config.vesc.steering_max_rad))
            self._remote_inputs[z.cmd_vel_topic] = self._remote_inputs[twist_input]
        urgent = {config.safety.scan_topic, TOPIC_ODOM, TOPIC_TF}
        dds_on = d.enabled and cyclone_available()
        if d.enabled and not dds_on:
            log.warning("dds: the DDS interface is off: the cyclonedds package is not installed "
                        "(pip install cyclonedds; docs/dds.md), or set dds.enabled: false")
        if z.enabled or dds_on:
            self.inbox = Inbox([t.bus for t in self.live_topics if t.direction is Direction.IN],
                               self._on_network_input, period_s=1.0 / config.mux.rate_hz,
                               estop_topic=config.mux.estop_topic,
                               release_topic=config.mux.estop_release_topic,
                               on_estop=self.network_estop, refusals=self.refusals)
        if z.enabled:
            self.zenoh = ZenohBridge(self.bus, z, self.live_topics, urgent=urgent,
                                     early={config.safety.scan_topic},
                                     inbox=self.inbox, refusals=self.refusals, parameters=self.parameters)
            logins = zenoh_logins.installed()  # the command counts failed Zenoh logins: into our refusals
            if logins is not None:
                logins.attach(self.refusals)
        if dds_on:
            self.dds = DdsBridge(self.bus, d, self.live_topics, namespace=z.namespace, node_name=z.node_name,
                                 urgent=urgent, refusals=self.refusals, inbox=self.inbox,
                                 period_s=1.0 / config.mux.rate_hz)

    def _on_network_input(self, topic: str, msg: Message, origin: str) -> None:
        """A command from a network surface, handed over by the inbox: on the bus, then send it."""
        self.bus.publish(topic, msg)
        self._on_remote_input(topic)

    def _on_remote_input(self, topic: str) -> None:
        """A command from a remote client is on the bus: if its input wins, send it at once."""
        name = self._remote_inputs.get(topic)
        now = monotonic_ns()
        if name is not None and self._control_alive(now):
            self.mux.step_early(name, now, self.filters)

    def network_estop(self, topic: str, msg: Message, who: str) -> None:
        """An e-stop or release message from a network session (``who``: ``zenoh``, ``dds``), in the loop.

        It reaches the mux as from the ``network`` surface (:mod:`mux.estop`: it may engage, and
        release only what the e-stop topic alone engaged); an e-stop that latches writes the brake
        now, as the live interfaces' e-stops do.
        """
        now = monotonic_ns()
        frames = self.vesc.stats.frames_tx if self.vesc is not None else None
        was_running = self.mux.state is MuxState.RUNNING
        self.mux.publish_from(Origin("network", who), topic, msg)
        if was_running and self.mux.state is not MuxState.RUNNING:
            self.estop_requests.append(EstopRequest(now, f"network topic {topic} ({who})", frames))
            if self._control_alive(now):
                self.mux.step(now, self.filters)

    def add_task(self, coro: Coroutine[Any, Any, Any]) -> None:
        """Run ``coro`` with the daemon's components (sim drivers, teleop)."""
        self._extra.append(coro)

    def _on_output(self, msg: AckermannDriveStamped) -> None:
        if self.vesc is not None:
            self.vesc.command(msg.drive)
        if self.foxglove is not None:
            self.foxglove.on_output()

    def _on_scan(self, scan: LaserScan) -> None:
        """Re-check the current command against the new scan and send it at once.

        The motor command goes first; bookkeeping, the safety state and the obstacle memory's
        update come after it.
        """
        now = monotonic_ns()
        last = self.mux.last_output
        if last is not None and self._control_alive(now):
            cut = self.safety.limit(last.drive, self.mux.source or "idle", now)
            if abs(cut.speed) < abs(last.drive.speed):
                self.stats.scan_cuts += 1
                limiter = self.mux.limiter
                limiter.speed = math.copysign(min(abs(limiter.speed), abs(cut.speed)), limiter.speed)
                self.mux.step(now, (lambda drive, source, t: cut,))
            elif self.vesc is not None:
                self.vesc.command(cut)
            self.safety.publish_state_if_due(now)
            if self.vesc is not None and self.lidar is not None:
                self._time_scan_path(self.vesc, self.lidar)
        if self.zenoh is not None:  # remote navigation code waits for the scan: queue it now
            self.zenoh.send_early(self.config.safety.scan_topic, scan)
        times = self.stats.scan_times
        times.append(now)
        if len(times) >= 2:
            self.stats.scan_rate_hz = (len(times) - 1) * NS_PER_S / max(1, times[-1] - times[0])
        if self.zenoh is not None:
            self.zenoh.control_idle()
        if self.dds is not None:
            self.dds.control_idle()
        self.safety.remember()  # before waking the recorder's writer, which would contend for the GIL
        if self.recorder is not None:
            self.recorder.control_idle()
        if self.foxglove is not None:
            self.foxglove.control_idle()
        if self.web is not None:
            self.web.control_idle()

    def _time_scan_path(self, vesc: VescDriver, lidar: LidarDriver) -> None:
        """Record the time from the scan's arrival to its motor command, if one was written."""
        arrived = lidar.frame_arrival_ns
        written = vesc.last_motor_write_ns
        if arrived and written >= arrived:  # this scan's command reached the OS
            self.stats.scan_to_command_ns.append(written - arrived)
            cpu = vesc.last_motor_write_cpu_ns - lidar.frame_arrival_cpu_ns
            self.stats.scan_to_command_cpu_ns.append(min(cpu, written - arrived))

    def _control_alive(self, now_ns: int) -> bool:
        """Whether the control loop ticked within the last two periods.

        The scan path re-sends commands only while the control loop runs: a stalled loop must
        let the VESC driver's command timeout brake the car, not be masked by scans.
        """
        period = NS_PER_S / self.config.mux.rate_hz
        return self.stats.ticks > 0 and now_ns - self.stats.last_tick_ns < 2 * period

    # --- control loop ---------------------------------------------------------------------------

    async def _control_loop(self) -> None:
        """Tick the mux at its rate from a loop timer (no task wake-up per tick) until cancelled."""
        interval = self.notifier.watchdog_interval_s()
        if interval:
            self._watchdog_period_ns = int(interval * NS_PER_S / 2)
        failed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

        def on_error(err: BaseException) -> None:
            if not failed.done():
                failed.set_exception(err)

        timer = PeriodicTimer(self.config.mux.rate_hz, self._control_tick, on_error=on_error)
        timer.start()
        try:
            await failed
        finally:
            timer.cancel()

    def _control_tick(self, due: int, periods: int) -> None:
        """One control tick due at ``due`` (monotonic ns), ``periods`` periods after the last."""
        stats = self.stats
        stats.missed_ticks += periods - 1
        self.mux.step(due, self.filters, periods)
        stats.ticks += 1
        stats.last_tick_ns = monotonic_ns()
        if stats.ticks % self._diagnostics_every == 0:  # after the motor command: only bookkeeping
            self.mux.publish_diagnostics(due)
            self._publish_security(due)
            self._publish_diagnostics()
        if self._watchdog_period_ns and due - self._last_watchdog_ns >= self._watchdog_period_ns:
            self.notifier.watchdog()
            self._last_watchdog_ns = due

    def drives_itself(self) -> bool:
        """Whether a configured source drives the car without anyone at the controls (a followed
        bag, the figure-8): then a run that never reached the VESC has failed."""
        return self.follower is not None or self.figure8 is not None

    def undriven_reason(self) -> str | None:
        """Why no drive command reached a connected VESC in this run; None when one did, or
        when there is no VESC to reach."""
        vesc = self.vesc
        if vesc is None or vesc.stats.drive_commands:
            return None
        port = self.config.vesc.port
        if not vesc.ever_connected:
            why = f": {vesc.last_error}" if vesc.last_error else ""
            return (f"no motor command reached the VESC: it never connected on port {port}{why} "
                    f"(check vesc.port and the cable)")
        if vesc.firmware is None and vesc.stats.frames_rx == 0:
            return (f"no motor command reached the VESC: port {port} opened but the VESC never "
                    f"answered (check the baud rate and that it is a VESC)")
        return "no motor command reached the VESC: the run ended before a command was sent"

    def _publish_security(self, now_ns: int) -> None:
        """The network surfaces' refusals as their own DiagnosticArray on the diagnostics topic."""
        try:
            array = DiagnosticArray(stamp_now("", wall_ns()), [self.security.status(now_ns)])
            self.bus.publish(self.config.mux.diagnostics_topic, array)
        except Exception as err:  # bookkeeping must never stop the control tick
            log.error("network security diagnostics failed: %r", err)

    def _publish_diagnostics(self) -> None:
        """The daemon's own statuses beside the mux's: the control loop, and the network inbox."""
        stats = self.stats
        message = f"{stats.ticks} ticks, {stats.missed_ticks} missed"
        statuses = [DiagnosticStatus(
            DiagnosticStatus.OK, "racecar_hw: control loop", message,
            "", [KeyValue("ticks", str(stats.ticks)), KeyValue("missed ticks", str(stats.missed_ticks)),
                 KeyValue("scan cuts", str(stats.scan_cuts))])]
        if self.inbox is not None:
            statuses.append(self.inbox.diagnostics())
        stamp = stamp_now("", wall_ns())
        try:
            for status in statuses:  # one array each, as the mux and the network security publish
                self.bus.publish(self.config.mux.diagnostics_topic, DiagnosticArray(stamp, [status]))
        except Exception as err:  # bookkeeping must never stop the control tick
            log.error("daemon diagnostics failed: %r", err)

    def snapshot(self) -> StatusSnapshot:
        """What the status panel shows."""
        out = self.mux.last_output
        state = self.vesc.last_state if self.vesc is not None else None
        odom = self.bus.latest(self.config.safety.odom_topic)
        safety = self.safety.state
        vesc_link = self.links.get("vesc")
        lidar_link = self.links.get("lidar")
        snap = StatusSnapshot(
            speed_mps=float(odom.twist.twist.linear.x) if odom is not None else None,
            steering_rad=float(out.drive.steering_angle) if out is not None else None,
            mux_source=self.mux.source,
            battery_v=state.state.voltage_input if state is not None else None,
            scan_rate_hz=self.stats.scan_rate_hz if self.lidar is not None else None,
            safety_state=safety.reason,
            safety_allowed_mps=safety.allowed_speed if math.isfinite(safety.allowed_speed) else None,
            vesc_crc_errors=self.vesc.stats.crc_errors if self.vesc is not None else 0,
            vesc_reconnects=self.vesc.stats.reconnects if self.vesc is not None else 0,
            lidar_reconnects=self.lidar.stats.reconnects if self.lidar is not None else 0,
            armed=self.arming.armed,
            vesc_link=vesc_link.text() if vesc_link is not None else None,
            lidar_link=lidar_link.text() if lidar_link is not None else None,
            live_view=self.live_urls().get("foxglove"), page=self.live_urls().get("web"),
            keys=KEY_HINTS if self.keyboard is not None else None,
            estop=self.mux.estop_text() if self.mux.estop is not None else None,
            refused=self.security.line(),
        )
        if self.extra_status is not None:
            snap = dataclasses.replace(snap, **self.extra_status())
        return snap

    async def _watch_links(self) -> None:
        """Poll the link watches: panel states, and log reminders while a device stays away."""
        while True:
            for watch in self.links.values():
                watch.poll()
            await asyncio.sleep(LINK_POLL_S)

    # --- live interfaces: the Foxglove server and the status page (racecar_hw.net) ---------------

    def _build_live(self) -> None:
        config = self.config
        laser = self._laser_to_base()
        fp, safety = config.safety.footprint, config.safety
        self.shape = CarShape(
            front_m=fp.front_m, rear_m=fp.rear_overhang_m,
            half_width_m=fp.width_m / 2 + safety.lateral_margin_m,
            wheelbase_m=fp.wheelbase_m, latency_s=safety.latency_s, max_decel_mps2=safety.max_decel_mps2,
            margin_m=safety.margin_m, max_path_m=safety.max_path_m,
            laser=((float(laser[0, 3]), float(laser[1, 3]), yaw_of(laser)) if laser is not None
                   else (safety.laser.x_m, safety.laser.y_m, safety.laser.yaw_rad)))
        #: e-stops asked for through the live interfaces, for reports (the simulator's timing log)
        self.estop_requests: deque[EstopRequest] = deque(maxlen=1000)
        #: the topics the live interfaces (Foxglove, Zenoh) serve, named by ``zenoh.profile`` and
        #: ``zenoh.remap``; the simulator adds its own before run()
        self.live_topics: list[Topic] = network_topics(config)
        teleop = next((i.topic for i in config.mux.inputs if i.name == FOXGLOVE_INPUT), None)
        self.foxglove = (FoxgloveServer(self.bus, config.foxglove, self, self.live_topics,
                                        parameters=to_dict(config), teleop_input=teleop,
                                        wheelbase_m=config.vesc.wheelbase_m,
                                        max_steering_rad=config.vesc.steering_max_rad,
                                        refusals=self.refusals)
                         if config.foxglove.enabled else None)
        self.web = (WebServer(self.bus, config.web, self, scan_topic=safety.scan_topic,
                              refusals=self.refusals)
                    if config.web.enabled else None)

    def live_urls(self) -> dict[str, str]:
        """Where the live interfaces that run listen: ``foxglove`` (ws://) and ``web`` (http://)."""
        urls: dict[str, str] = {}
        if self.foxglove is not None and self.foxglove.port is not None:
            urls["foxglove"] = f"ws://{self.config.foxglove.host}:{self.foxglove.port}"
        if self.web is not None and self.web.port:
            urls["web"] = f"http://{self.config.web.host}:{self.web.port}/"
        return urls

    def live_state(self) -> LiveState:
        """The car now, for the live interfaces (:class:`racecar_hw.net.control.CarControl`)."""
        out = self.mux.last_output
        drive = out.drive if out is not None else AckermannDrive()
        asked = self.mux.last_command(self.mux.source)
        odom = self.bus.latest(self.config.safety.odom_topic)
        safety = self.safety.state
        vesc, lidar = self.vesc, self.lidar
        state = vesc.last_state if vesc is not None else None
        scan = self.bus.latest_entry(self.config.safety.scan_topic)
        return LiveState(
            commanded_mps=float(asked.speed) if asked is not None else 0.0,
            output_mps=float(drive.speed), allowed_mps=float(safety.allowed_speed),
            measured_mps=float(odom.twist.twist.linear.x) if odom is not None else None,
            steering_rad=float(drive.steering_angle), source=self.mux.source or "idle",
            mux_state=self.mux.state.value, mux_reason=self.mux.machine.reason, armed=self.arming.armed,
            safety_reason=safety.reason, intervening=safety.intervening,
            free_distance_m=float(safety.free_distance),
            obstacle=(safety.obstacle.x, safety.obstacle.y) if safety.obstacle is not None else None,
            battery_v=float(state.state.voltage_input) if state is not None else None,
            vesc_connected=vesc.connected if vesc is not None else None,
            vesc_reconnects=vesc.stats.reconnects if vesc is not None else 0,
            vesc_crc_errors=vesc.stats.crc_errors if vesc is not None else 0,
            lidar_scan_age_s=(monotonic_ns() - scan.received_ns) / NS_PER_S if scan is not None else None,
            lidar_rate_hz=self.stats.scan_rate_hz if lidar is not None else None,
            lidar_reconnects=lidar.stats.reconnects if lidar is not None else 0,
            estop=self.mux.estop_text() if self.mux.estop is not None else "",
            refused=tuple(self.security.rows()), refused_recently=self.security.recent(),
            control_ticks=self.stats.ticks, control_missed_ticks=self.stats.missed_ticks)

    def engage_estop(self, origin: Origin) -> str:
        """Latch the mux e-stop and write the brake command now (not at the next tick)."""
        now = monotonic_ns()
        self.estop_requests.append(EstopRequest(now, str(origin), self.vesc.stats.frames_tx
                                                if self.vesc is not None else None))
        self.mux.engage_estop(f"e-stop from {origin}", origin)
        if self.stats.ticks:  # the control loop runs: one step out of turn sends the brake
            self.mux.step(now, self.filters)
        return f"e-stop latched ({origin}); release it to drive again"

    def release_estop(self, origin: Origin) -> tuple[bool, str]:
        """Release the latched e-stop, unless the mux refuses (:meth:`CommandMux.release_estop`)."""
        if self.mux.release_estop(origin):
            return True, f"e-stop released by {origin}"
        why = self.mux.release_refusal(origin) or "refused"
        if self.mux.state.value == "fault":
            why += f" ({self.mux.machine.reason})"
        return False, f"refused: {why}"

    def restart_mavlink_signing(self) -> str:
        """The way back for the MAVLink link's signing state (SIGUSR1, ``systemctl reload``):
        every stream's timestamp forgotten, ours from the wall clock again, as at start."""
        if self.mavlink is None:
            log.warning("restart of the MAVLink signing state asked for: the MAVLink link is off")
            return "the MAVLink link is off"
        forgotten = self.mavlink.restart_signing()
        return f"MAVLink signing state restarted ({forgotten} stream(s) forgotten)"

    def arm(self, who: str) -> tuple[bool, str]:
        """Arm the car for every source."""
        self.arming.arm(who)
        return True, "armed"

    def disarm(self, who: str) -> tuple[bool, str]:
        """Disarm: every source is stopped until armed again."""
        self.arming.disarm(who)
        return True, "disarmed"

    async def _start_live(self) -> None:
        if self.foxglove is not None and not self.foxglove.start():
            self.foxglove = None
        if self.web is not None and not await self.web.start():
            self.web = None

    async def _stop_live(self) -> None:
        if self.foxglove is not None:
            with contextlib.suppress(Exception):
                self.foxglove.stop()
        if self.web is not None:
            with contextlib.suppress(Exception):
                await self.web.stop()

    # --- life cycle -----------------------------------------------------------------------------

    def _publish_static_transforms(self) -> None:
        if not self.config.static_transforms:
            return
        self.bus.publish("/tf_static", self.tf.to_tf_message(wall_ns()))

    def _refuse_taken_ports(self) -> None:
        """Refuse to start (a one-line ConfigError naming the key) when the live view's or the
        page's port is taken: the rule for every interface (docs/live-view.md, "Ports"); Zenoh's
        own open refuses a taken listen port the same way, naming ``zenoh.listen[i]``."""
        for item in listeners(self.config):
            if not item.key.startswith("zenoh.") and port_taken(item.host, item.port):
                raise ConfigError(item.key, taken_message(item))

    async def run(self, stop: asyncio.Event) -> None:
        """Run every component until ``stop`` is set; then brake, centre, flush and return."""
        loop = asyncio.get_running_loop()
        self.bus.bind_loop(loop)
        # every socket takes a descriptor: take what the system allows, and let an accept() that
        # still finds none be a counted line, not a traceback a second (see docs/live-view.md, "Connections")
        self._file_limit = raise_open_file_limit()
        self._restore_exception_handler = quiet_accept_errors(loop, self.refusals)
        if self.rosout is not None:
            self.rosout.install()
        if self.inbox is not None:
            self.inbox.bind(loop)
        try:
            self._refuse_taken_ports()
            for bridge in (self.zenoh, self.dds):
                if bridge is not None:
                    await loop.run_in_executor(None, bridge.open, loop)
        except BaseException:
            if self.zenoh is not None:
                await loop.run_in_executor(None, self.zenoh.close)
            for coro in self._extra:  # never started: no "coroutine was never awaited"
                coro.close()
            self._extra = []
            self._restore_process()
            raise
        self._publish_static_transforms()
        if self.recorder is not None:
            self.recorder.start()
        if self.scan_summary is not None:
            self.scan_summary.start()
        if self.setpoint is not None:
            self.setpoint.start()
        await self._start_live()
        self.started_live = self.live_urls()
        for what, url in self.started_live.items():  # where to look, also when the log is quiet
            log.info("%s on %s", {"foxglove": "live view (Foxglove)", "web": "status page"}[what], url)
        coros: list[Coroutine[Any, Any, Any]] = [self._control_loop(), self.safety.run()]
        if self.links:
            coros.append(self._watch_links())
        if self.vesc is not None:
            coros.append(self.vesc.run())
        if self.lidar is not None:
            coros.append(self.lidar.run())
        if self.setpoint is not None:
            coros.append(self.setpoint.run())
        if self.figure8 is not None:
            coros.append(self.figure8.run())
        if self.follower is not None:
            coros.append(self.follower.run())
        for teleop in (self.gamepad, self.keyboard, self.mavlink):
            if teleop is not None:
                coros.append(teleop.run())
        coros.extend(self._extra)
        self._extra = []
        self._tasks = [asyncio.create_task(c) for c in coros]
        if self.status is not None:
            self.status.source = self.snapshot
            self.status.start()
        # Everything built so far (type stores, drivers, maps) lives until exit: keep it out of the
        # cyclic garbage collector, whose full passes over it would stall the control path.
        gc.collect()
        gc.freeze()
        # The recorder's writer thread serializes in Python; a short GIL switch interval hands the
        # GIL back to the control path within 0.1 ms instead of CPython's default 5 ms.
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        self.notifier.ready("racecar-hw running")
        log.info("racecar-hw running")
        waiter = asyncio.create_task(stop.wait())
        try:
            done, _ = await asyncio.wait([waiter, *self._tasks], return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if task is not waiter and not task.cancelled() and task.exception() is not None:
                    log.error("component failed: %r", task.exception(), exc_info=task.exception())
            # components that finish on their own (a figure-8, a bag) leave the rest running
            while not stop.is_set():
                pending = [t for t in self._tasks if not t.done()]
                await asyncio.wait([waiter, *pending], return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
            await self.shutdown()

    async def shutdown(self) -> None:
        """Brake and centre, stop every component, flush the recorder. Safe to call twice."""
        self.notifier.stopping("racecar-hw stopping")
        log.info("control summary: %s", self.stats.summary())
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        if self.vesc is not None:
            with contextlib.suppress(Exception):
                await self.vesc.shutdown()
        if self.status is not None:
            with contextlib.suppress(Exception):
                await self.status.stop()
        await self._stop_live()
        if self.recorder is not None:
            with contextlib.suppress(Exception):
                await asyncio.get_running_loop().run_in_executor(None, self.recorder.stop)
        if self.scan_summary is not None:
            self.scan_summary.close()
        if self.setpoint is not None:
            self.setpoint.close()
        if self.mavlink is not None:
            self.mavlink.close()
        if self.inbox is not None:
            self.inbox.close()
        for bridge in (self.zenoh, self.dds):
            if bridge is not None:
                with contextlib.suppress(Exception):
                    await asyncio.get_running_loop().run_in_executor(None, bridge.close)
        if self.rosout is not None:
            self.rosout.uninstall()
            if self.rosout.dropped:
                log.info("rosout: %d log records published, %d dropped (over rosout.max_rate_hz or "
                         "before the loop ran)", self.rosout.published, self.rosout.dropped)
        if self.cmd_vel is not None:
            self.cmd_vel.close()
        self.safety.close()
        self.mux.close()
        self.refusals.flush()
        self.notifier.close()
        # A daemon run inside a longer-lived process (the sim, tests) leaves it as it found it.
        gc.unfreeze()
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None
        self._restore_process()

    def _restore_process(self) -> None:
        """Put back the open-file limit, the loop's exception handler and the log handlers run()
        changed."""
        if self.rosout is not None:
            self.rosout.uninstall()
        if self._file_limit is not None:
            self._file_limit.restore()
            self._file_limit = None
        if self._restore_exception_handler is not None:
            self._restore_exception_handler()
            self._restore_exception_handler = None
