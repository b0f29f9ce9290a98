"""The daemon: every configured component on one bus, in one asyncio event loop. It is wiring.

Thread model (see docs/architecture.md): the event loop thread runs the drivers, the mux, the
safety controller and every publisher; the bag recorder writes from its own thread behind a bounded
queue; in ``racecar-hw sim`` the fake devices and the world run in a separate device thread in
real time, or as tasks in the same loop in lockstep (:mod:`racecar_hw.runtime.lockstep`).

What a command goes through, from arrival to the VESC write, is one object: the
:class:`~racecar_hw.control.path.ControlPath` (the mux, arming and hold, the safety controller,
the rate limiter; the bus observes after the write). What every display reads of the car is one
read model, :class:`~racecar_hw.control.state.CarState`. The network and live interfaces are
:class:`~racecar_hw.interfaces.Interfaces`.

Components have one small protocol: built by :class:`Daemon` from the config (they subscribe to
the bus; nothing runs), started in :meth:`Daemon.run` (a task, or their ``start``/``open``), and
stopped by a callback pushed on the daemon's exit stack as each one starts, so shutdown is
start-up in reverse: the VESC driver's brake comes right after the tasks stop, and the components
built first (the mux, the safety node, the notifier) close last.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import sys
from collections.abc import Coroutine
from typing import TYPE_CHECKING, Any

from lidar_drivers.base import LidarDriver
from lidar_drivers.registry import make_driver
from mux.estop import Origin
from mux.node import CommandMux
from racecar_hw.bags.follow import BagFollower
from racecar_hw.bags.record import Recorder
from racecar_hw.bags.validate import CommandLimits
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import wall_ns
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import DiagnosticStatus
from racecar_hw.base.transforms import TfTree
from racecar_hw.config import Config, topic_keys
from racecar_hw.control.path import ControlPath
from racecar_hw.control.state import CarState, car_shape
from racecar_hw.interfaces import Interfaces
from racecar_hw.net.gate import quiet_accept_errors
from racecar_hw.runtime.extras import require_extra
from racecar_hw.runtime.fdlimit import raise_open_file_limit
from racecar_hw.runtime.links import LinkWatch
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.sdnotify import Notifier
from racecar_hw.runtime.security_status import SecurityStatus
from racecar_hw.runtime.teardown import quietly
from racecar_hw.sources.figure8 import Figure8Driver
from racecar_hw.sources.scan_summary import ScanSummaryPublisher
from racecar_hw.sources.setpoint import SetpointRelay
from racecar_hw.teleop.arming import Arming
from racecar_hw.teleop.gamepad import GamepadTeleop
from racecar_hw.teleop.keyboard import KEY_HINTS, KeyboardTeleop
from safety.node import SafetyNode
from vesc.ackermann import AckermannConversion
from vesc.driver import VescDriver

if TYPE_CHECKING:  # imported where switched on: rich (a panel), the mavlink extra
    from racecar_hw.runtime.panel import StatusPanel
    from racecar_hw.teleop.mavlink_gcs import MavlinkGcs

log = logging.getLogger(__name__)

#: How often the link watches are polled (s): panel link states and reminders.
LINK_POLL_S = 0.5

#: GIL switch interval while the daemon runs (seconds); CPython's default is 0.005.
SWITCH_INTERVAL_S = 0.0001


def reverse_speed_cap(config: Config) -> float | None:
    """The fastest the safety controller lets the car reverse (m/s); None when it does not cap
    (``off``, and ``cone``, which only stops the car through the mux)."""
    return config.safety.reverse_speed_cap_mps if config.safety.mode == "arc" else None


def command_limits(config: Config) -> CommandLimits:
    """What a followed bag may ask of this car: the VESC's configured speed and steering limits."""
    return CommandLimits(config.vesc.speed_max_mps, config.vesc.steering_max_rad)


def laser_to_base(config: Config, tf: TfTree) -> Any:
    """The base_link -> lidar frame transform (4x4), or None where none is configured (refused
    when the arc safety controller needs one)."""
    frame = config.lidar.frame_id
    if tf.can_transform("base_link", frame):
        return tf.lookup("base_link", frame)
    if config.lidar.enabled and config.safety.mode == "arc":
        raise ConfigError("static_transforms", f"no transform from base_link to the lidar frame "
                                               f"{frame!r}: the safety controller needs one")
    return None


def car_ready(links: list[LinkWatch], safety: SafetyNode, has_lidar: bool) -> bool:
    """Whether a command would move the car: every device link is up and, with a lidar, the
    safety controller has a scan (without one it holds the car). What a bag replay waits for."""
    if not all(watch.connected() for watch in links):
        return False
    return not has_lidar or safety.state.reason != "no_scan"


def undriven_reason(vesc: VescDriver | None, port: str) -> str | None:
    """Why no drive command reached a connected VESC in this run; None when one did, or when there
    is no VESC to reach."""
    if vesc is None or vesc.stats.drive_commands:
        return None
    if not vesc.ever_connected:
        why = f": {vesc.last_error}" if vesc.last_error else ""
        return (f"no motor command reached the VESC: it never connected on port {port}{why} "
                f"(check vesc.port and the cable)")
    if vesc.firmware is None and vesc.stats.frames_rx == 0:
        return (f"no motor command reached the VESC: port {port} opened but the VESC never "
                f"answered (check the baud rate and that it is a VESC)")
    return "no motor command reached the VESC: the run ended before a command was sent"


class Daemon:
    """Builds the configured components on ``bus`` and runs them until stopped."""

    def __init__(self, config: Config, *, bus: Bus | None = None, notifier: Notifier | None = None,
                 status: StatusPanel | None = None) -> None:
        self.config = config
        self.bus = bus = bus if bus is not None else Bus()
        bus.config_keys = lambda topic: topic_keys(config, topic)  # a type clash names its key
        self.notifier = notifier if notifier is not None else Notifier.from_env()
        #: undoes start-up in reverse (:meth:`shutdown`); what is built here closes last
        self._stack = stack = contextlib.AsyncExitStack()
        stack.callback(self.notifier.close)
        #: what the network surfaces refused (bad logins, forged frames, floods), for /diagnostics,
        #: the panel, the status page and rate-limited log lines
        self.refusals = Refusals()
        stack.callback(self.refusals.flush)
        #: the refusals as a status in /diagnostics, a panel line and rows on the status page
        self.security = SecurityStatus(self.refusals)
        self.tf = TfTree.from_params(config.static_transforms)
        laser = laser_to_base(config, self.tf)
        self.vesc: VescDriver | None = VescDriver(bus, config.vesc) if config.vesc.enabled else None
        self.lidar: LidarDriver | None = make_driver(bus, config.lidar) if config.lidar.enabled else None
        conversion = AckermannConversion.from_params(config.vesc)
        steering_range = conversion.steering_range()
        self.mux = CommandMux(bus, config.mux, refusals=self.refusals, steering_range=steering_range,
                              speed_max_mps=conversion.speed_max_mps)
        stack.callback(self.mux.close)
        self.safety = SafetyNode(bus, config.safety, laser, defer_memory=True, scans_from_bus=False,
                                 steering_limit_rad=steering_range)
        stack.callback(self.safety.close)
        self.arming = Arming.from_params(config.arming)
        pad, keys = Origin("gamepad", "gamepad"), Origin("keyboard", "keyboard")
        self.gamepad = (GamepadTeleop(bus, config.gamepad, self.arming,
                                      on_estop=lambda: self.engage_estop(pad),
                                      on_release=lambda: self._log_release(pad))
                        if config.gamepad.enabled else None)
        self.keyboard = (KeyboardTeleop(bus, config.keyboard, on_estop=lambda: self.engage_estop(keys),
                                        on_release=lambda: self._log_release(keys))
                         if config.keyboard.enabled else None)
        self.mavlink: MavlinkGcs | None = None
        if config.mavlink.enabled:
            require_extra("mavlink", "the MAVLink ground-station link", "mavlink.enabled")
            from racecar_hw.teleop.mavlink_gcs import MavlinkGcs  # noqa: PLC0415 - needs the extra

            self.mavlink = MavlinkGcs(bus, config.mavlink, self.arming, status_source=lambda: self.snapshot(),
                                      refusals=self.refusals)
        if self.mavlink is not None:
            stack.callback(self.mavlink.close)
        hold = (self.mavlink.filter,) if self.mavlink is not None else ()
        #: arrival -> arbitration -> arming/hold -> safety -> limiter -> VESC write, then the bus
        self.control = ControlPath(bus, self.mux, self.safety, filters=(self.arming.filter, *hold),
                                   vesc=self.vesc, lidar=self.lidar, scan_topic=config.safety.scan_topic,
                                   diagnostics_rate_hz=config.mux.diagnostics_rate_hz,
                                   notifier=self.notifier, statuses=self._statuses)
        self.stats = self.control.stats
        self.arming.on_change(lambda change: change.armed or self.control.stop_now())
        #: e-stops asked for through the live and network interfaces (the simulator's timing log)
        self.estop_requests = self.control.estop_requests
        self.scan_summary = (ScanSummaryPublisher(bus, config.scan_summary)
                             if config.scan_summary.enabled else None)
        self.setpoint = SetpointRelay(bus, config.setpoint) if config.setpoint.enabled else None
        self.figure8 = (Figure8Driver(bus, config.figure8.params(config.vesc.wheelbase_m))
                        if config.figure8.enabled else None)
        self.follower = (BagFollower(bus, config.follower, wheelbase_m=config.vesc.wheelbase_m,
                                     reverse_speed_cap_mps=reverse_speed_cap(config),
                                     limits=command_limits(config))
                         if config.follower.enabled else None)
        self.status = status
        self.links: dict[str, LinkWatch] = {}
        if self.vesc is not None:
            vesc = self.vesc
            self.links["vesc"] = LinkWatch("VESC", lambda: vesc.connected,
                                           detail=lambda: f"port {config.vesc.port}")
        if self.lidar is not None:
            lidar = self.lidar
            self.links["lidar"] = LinkWatch(f"lidar {config.lidar.model}", lambda: lidar.connected,
                                            detail=lambda: lidar.last_error)
        if self.follower is not None:
            links, safety, has_lidar = list(self.links.values()), self.safety, self.lidar is not None
            self.follower.ready = lambda: car_ready(links, safety, has_lidar)
        self.shape = car_shape(config, laser)
        #: the network and live interfaces; the daemon is their CarControl
        self.net = net = Interfaces(config, bus, self.control, self, self.refusals)
        self.zenoh, self.dds, self.inbox, self.cmd_vel = net.zenoh, net.dds, net.inbox, net.cmd_vel
        self.live_topics = net.live_topics
        #: records with the live table's latched topics (its QoS, latching, every split starting with them)
        self.recorder = (Recorder(bus, config.recorder,
                                  latched={t.bus: t.qos for t in self.live_topics if t.qos.latched})
                         if config.recorder.enabled else None)
        if self.cmd_vel is not None:
            stack.callback(self.cmd_vel.close)
        if self.recorder is not None:
            self.control.idle.append(self.recorder.control_idle)
        #: the one read model: the panel, MAVLink, Foxglove and the status page read it
        self.state = CarState(bus, config, self.mux, self.safety, self.arming, self.vesc, self.lidar,
                              self.stats, self.security, self.links, net.urls,
                              KEY_HINTS if self.keyboard is not None else None)
        self.snapshot, self.live_state = self.state.snapshot, self.state.live_state
        self._tasks: list[asyncio.Task[Any]] = []
        #: the component whose failure ended the run, and its exception (None: it was stopped)
        self.failure: tuple[str, BaseException] | None = None
        #: where the live interfaces listened once started (``net.urls()``), for reports
        self.started_live: dict[str, str] = {}
        self._extra: list[Coroutine[Any, Any, Any]] = []

    def add_task(self, coro: Coroutine[Any, Any, Any]) -> None:
        """Run ``coro`` with the daemon's components (sim drivers, teleop)."""
        self._extra.append(coro)

    def drives_itself(self) -> bool:
        """Whether a configured source drives the car without anyone at the controls (a followed
        bag, the figure-8): then a run that never reached the VESC has failed."""
        return self.follower is not None or self.figure8 is not None

    def undriven_reason(self) -> str | None:
        """Why no drive command reached a connected VESC in this run (:func:`undriven_reason`)."""
        return undriven_reason(self.vesc, self.config.vesc.port)

    def _statuses(self, now_ns: int) -> list[DiagnosticStatus]:
        """The daemon's statuses beside the mux's: network security, the control loop, the inbox."""
        statuses = [self.security.status(now_ns), self.control.status()]
        if self.inbox is not None:
            statuses.append(self.inbox.diagnostics())
        return statuses

    async def _watch_links(self) -> None:
        """Poll the link watches: panel states, and log reminders while a device stays away."""
        while True:
            for watch in self.links.values():
                watch.poll()
            await asyncio.sleep(LINK_POLL_S)

    # --- what the live interfaces may ask (racecar_hw.net.control.CarControl) -------------------

    def engage_estop(self, origin: Origin) -> str:
        """Latch the mux e-stop and write the brake command now (not at the next tick)."""
        self.control.engage_estop(origin)
        return f"e-stop latched ({origin}); release it to drive again"

    def release_estop(self, origin: Origin) -> tuple[bool, str]:
        """Release the latched e-stop, unless the mux refuses (:meth:`CommandMux.release_estop`)."""
        if self.mux.release_estop(origin):
            return True, f"e-stop released by {origin}"
        why = self.mux.release_refusal(origin) or "refused"
        if self.mux.state.value == "fault":
            why += f" ({self.mux.machine.reason})"
        return False, f"refused: {why}"

    def _log_release(self, origin: Origin) -> None:
        """A release from a teleop button: what happened goes to the log."""
        log.warning("%s: %s", origin, self.release_estop(origin)[1])

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

    # --- life cycle -----------------------------------------------------------------------------

    async def run(self, stop: asyncio.Event) -> None:
        """Start every component, run until ``stop`` is set; then brake, centre, flush and return."""
        loop = asyncio.get_running_loop()
        self.bus.bind_loop(loop)
        stack = self._stack
        # every socket takes a descriptor: take what the system allows, and let an accept() that
        # still finds none be a counted line, not a traceback a second (see docs/live-view.md, "Connections")
        stack.callback(raise_open_file_limit().restore)
        stack.callback(quiet_accept_errors(loop, self.refusals))
        coros: list[Coroutine[Any, Any, Any]] = []
        try:  # whatever fails before the components run closes what was opened (a bag that cannot be
            # created once left Zenoh's threads running, and the process hung)
            await self.net.open(loop, stack)
            if self.config.static_transforms:
                self.bus.publish("/tf_static", self.tf.to_tf_message(wall_ns()))
            if self.recorder is not None:
                await start_recorder(self.recorder, stop)
                stack.push_async_callback(quietly, loop.run_in_executor, None, self.recorder.stop)
            for part in (self.scan_summary, self.setpoint):
                if part is not None:
                    part.start()
                    stack.callback(part.close)
            self.started_live = await self.net.start_live(self.control, stack)
            for what, url in self.started_live.items():  # where to look, also when the log is quiet
                log.info("%s on %s", {"foxglove": "live view (Foxglove)", "web": "status page"}[what], url)
            if self.status is not None:
                self.status.source = self.snapshot
                self.status.start()
                stack.push_async_callback(quietly, self.status.stop)
            parts = (self.vesc, self.lidar, self.setpoint, self.figure8, self.follower, self.gamepad,
                     self.keyboard, self.mavlink)
            coros = [self.control.run(), self.safety.run(), *([self._watch_links()] if self.links else []),
                     *(part.run() for part in parts if part is not None), *self._extra]
            self._extra = []
            self._tasks = [asyncio.create_task(c) for c in coros]
        except BaseException:
            for coro in [*self._extra, *coros]:  # never started: no "coroutine was never awaited"
                coro.close()
            self._extra = []
            await stack.aclose()
            raise
        stack.push_async_callback(self._stop_tasks)  # and brake
        # Everything built so far (type stores, drivers, maps) lives until exit: keep it out of the
        # cyclic garbage collector, whose full passes over it would stall the control path.
        gc.collect()
        gc.freeze()
        stack.callback(gc.unfreeze)  # a daemon run inside a longer-lived process leaves it as it was
        # The recorder's writer thread serializes in Python; a short GIL switch interval hands the
        # GIL back to the control path within 0.1 ms instead of CPython's default 5 ms.
        stack.callback(sys.setswitchinterval, sys.getswitchinterval())
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        self.notifier.ready("racecar-hw running")
        log.info("racecar-hw running")
        stack.callback(self._stopping)
        try:
            self.failure = await _until_stop_or_failure(stop, self._tasks)
        finally:
            await self.shutdown()

    def _stopping(self) -> None:
        self.notifier.stopping("racecar-hw stopping")
        log.info("control summary: %s", self.stats.summary())

    async def _stop_tasks(self) -> None:
        """Cancel every component's task, then brake and centre through the VESC driver."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        if self.vesc is not None:
            await quietly(self.vesc.shutdown)

    async def shutdown(self) -> None:
        """Undo start-up in reverse: stop the tasks and brake, stop the live interfaces, flush the
        recorder, close the network, then what was built first. Safe to call twice."""
        await self._stack.aclose()


async def start_recorder(recorder: Recorder, stop: asyncio.Event) -> None:
    """Start ``recorder`` without holding the event loop while its first bag opens (in an executor
    job): a disk that does not answer fails the start after WRITER_STALL_S with a BagError naming
    recorder.path, and ``stop`` set meanwhile ends the wait at once (a stuck disk once held the
    start, and Ctrl-C, for as long as it stayed stuck)."""
    if not recorder.open():
        return
    opened = asyncio.get_running_loop().run_in_executor(None, recorder.wait_opened, None)
    stopped = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait((opened, stopped), return_when=asyncio.FIRST_COMPLETED)
    finally:
        stopped.cancel()
        if not opened.done():
            recorder.abandon_open()
    await opened
    recorder.subscribe()


async def _until_stop_or_failure(stop: asyncio.Event, tasks: list[asyncio.Task[Any]]
                                 ) -> tuple[str, BaseException] | None:
    """Wait until ``stop`` is set or a component's task fails: then the failed one's name and
    exception, logged (the run then ends and the car brakes: a component that is down, a teleop
    link that could not open, must not leave the car driving without it). Components that finish
    on their own (a figure-8, a bag) leave the rest running."""
    waiter = asyncio.create_task(stop.wait())
    try:
        while not stop.is_set():
            pending = [t for t in tasks if not t.done()]
            done, _ = await asyncio.wait([waiter, *pending], return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if task is not waiter and not task.cancelled() and task.exception() is not None:
                    err = task.exception()
                    name = getattr(task.get_coro(), "__qualname__", task.get_name())
                    log.error("component failed, stopping: %s: %r", name, err, exc_info=err)
                    return name, err  # type: ignore[return-value]
        return None
    finally:
        waiter.cancel()
