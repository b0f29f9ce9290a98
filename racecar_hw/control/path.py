"""The control path: a command's way from its arrival to the VESC, in one object.

::

    input arrived ─┐                       (mux input topics, on the bus; a remote input comes
                   │                        through take_input, for an early step)
    tick ──────────┼─> arbitration -> arming -> hold -> safety limit -> rate limiter ─┐
    e-stop ────────┘    (CommandMux.decide/decide_early; the e-stop bypasses limits)  │
    new scan ──> safety controller judges it -> last output re-checked ─> cut? ──────┤
                                              (CommandMux.cut clamps the limiter)     │
                                                                                      v
                                                                       VESC write (the first
                                                                       side effect)
                                                                                      │
                      then the bus observes: the scan, the mux output, the safety state,
                      diagnostics; then the deferred work (obstacle memory, outboxes)

Every entry point computes the command without a bus publication, writes it to the VESC, and
only then publishes: whatever subscribed to the scan or the output topic, in whatever order, sees
them after the motor command went out. The lidar driver hands each scan to :meth:`take_scan`
(its ``scan_sink``) instead of the bus, and the safety node takes it from there too.

The scan path and the early steps send nothing while the control loop is stalled (no tick in two
periods), so a dead loop still lets the VESC driver's command timeout brake the car; the watchdog
is pinged from the tick, so a stalled loop gets the daemon restarted.

Commands are finite from the edge on (docs/architecture.md, "Finite commands"): the network inbox
refuses a message with a NaN or infinite number, the mux turns a non-finite command on one of its
inputs into a stop; the VESC conversion refuses NaN/inf as the last guard before the hardware.

Times are monotonic integer nanoseconds. Use from the event loop thread only.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from lidar_drivers.base import LidarDriver
from mux.arbiter import MuxState
from mux.estop import Origin
from mux.node import CommandMux, Filter
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
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
from racecar_hw.control.stats import ControlStats
from racecar_hw.runtime.sdnotify import Notifier
from racecar_hw.runtime.ticker import PeriodicTimer
from safety.node import SafetyNode
from vesc.driver import VescDriver

log = logging.getLogger(__name__)

#: While a remote command was written within this long (ns), remote navigation code is taken to be
#: answering scans: the outboxes' batches wait for its next command rather than start after a scan.
REMOTE_ANSWER_NS = 100_000_000


@dataclass(frozen=True)
class EstopRequest:
    """An e-stop asked for through a live or network interface, for reports."""

    at_ns: int                      #: when the request reached the daemon (monotonic ns)
    who: str                        #: who asked, for the log ("web page (127.0.0.1)")
    #: frames the VESC driver had written before it (its ``stats.frames_tx``): the brake is
    #: the first motor command after them; None without a VESC
    vesc_frames_before: int | None


class ControlPath:
    """Arbitration, arming and hold, the safety limit, the rate limiter and the VESC write.

    ``filters`` run between arbitration and the safety limit (arming, the MAVLink hold); the safety
    node's :meth:`~safety.node.SafetyNode.limit` runs after them. ``remote_inputs`` maps a topic a
    remote client sends commands on to its mux input's name. ``statuses(now_ns)`` gives the
    diagnostic statuses published beside the mux's (the daemon adds network security and the inbox
    to :meth:`status`, the control loop's own; that alone by default).
    """

    def __init__(self, bus: Bus, mux: CommandMux, safety: SafetyNode, *, filters: Sequence[Filter],
                 vesc: VescDriver | None, lidar: LidarDriver | None, scan_topic: str,
                 diagnostics_rate_hz: float, notifier: Notifier,
                 remote_inputs: dict[str, str] | None = None,
                 statuses: Callable[[int], list[DiagnosticStatus]] | None = None) -> None:
        self.bus, self.mux, self.safety, self.vesc, self.lidar = bus, mux, safety, vesc, lidar
        self.filters: tuple[Filter, ...] = (*filters, safety.limit)
        self.scan_topic = scan_topic
        self.notifier = notifier
        self.remote_inputs = dict(remote_inputs or {})
        self.statuses = statuses if statuses is not None else lambda now_ns: [self.status()]
        self.stats = ControlStats()
        #: e-stops asked for through the live and network interfaces, for reports
        self.estop_requests: deque[EstopRequest] = deque(maxlen=1000)
        #: called with each scan right after its motor command (the network interfaces' early queues)
        self.early: list[Callable[[LaserScan], None]] = []
        #: called when the loop is idle until its next event (the outboxes' threads may take the GIL
        #: now): after each scan's bookkeeping and the obstacle memory's update, or, while remote
        #: navigation code answers scans, after its command's write instead
        self.idle: list[Callable[[], None]] = []
        self._write: Callable[[AckermannDrive], None] = vesc.command if vesc is not None else _nowhere
        self._period_ns = NS_PER_S / mux.params.rate_hz
        #: control ticks between two of the mux's diagnostics
        self._diagnostics_every = max(1, round(mux.params.rate_hz / diagnostics_rate_hz))
        self._watchdog_period_ns: int | None = None
        self._last_watchdog_ns = 0
        self._remote_write_ns = -REMOTE_ANSWER_NS  # monotonic ns of the last remote command's write
        if lidar is not None:
            lidar.scan_sink = self.take_scan

    # --- entry points ------------------------------------------------------------------------

    def tick(self, due: int, periods: int = 1) -> None:
        """One control tick due at ``due`` (monotonic ns), ``periods`` periods after the last."""
        stats = self.stats
        stats.missed_ticks += periods - 1
        msg = self.mux.decide(due, self.filters, periods)
        self._write(msg.drive)
        self._observe(msg, due)
        stats.ticks += 1
        stats.last_tick_ns = monotonic_ns()
        if stats.ticks % self._diagnostics_every == 0:  # after the motor command: only bookkeeping
            self.mux.publish_diagnostics(due)
            self._publish_diagnostics(due)
        if self._watchdog_period_ns and due - self._last_watchdog_ns >= self._watchdog_period_ns:
            self.notifier.watchdog()
            self._last_watchdog_ns = due

    def take_scan(self, scan: LaserScan) -> None:
        """A new scan: re-check the last output against it and write the command at once.

        A slower command is a cut (:meth:`CommandMux.cut`), which holds the limiter down too. The
        scan goes on the bus only after the write; the obstacle memory takes it in after that.
        Every scan goes on the bus, also while the control loop does not run.
        """
        now = monotonic_ns()
        self.safety.take_scan(scan)
        last = self.mux.last_output
        cut: AckermannDriveStamped | None = None
        wrote = False
        if last is not None and self.alive(now):
            wrote = True
            # the speed only: a blind lidar's centring (safety.centre_when_blind) is the ticks' to
            # make at the mux's steering rate (here the servo jumped to centre and back at the tick)
            drive = dataclasses.replace(self.safety.limit(last.drive, self.mux.source or "idle", now),
                                        steering_angle=last.drive.steering_angle)
            if abs(drive.speed) < abs(last.drive.speed):
                self.stats.scan_cuts += 1
                cut = self.mux.cut(drive, now)
                drive = cut.drive
            self._write(drive)
            if self.vesc is not None and self.lidar is not None:
                self._time_scan_path(self.vesc, self.lidar)
        for early in self.early:  # remote navigation code waits for the scan: queue it now
            early(scan)
        self.bus.publish(self.scan_topic, scan)
        if cut is not None:
            self.mux.publish_output(cut)
        if wrote:
            self.safety.publish_state_if_due(now)
        self.stats.note_scan(now)
        self.safety.remember()  # before waking the outboxes' threads, which would contend for the GIL
        if now - self._remote_write_ns > REMOTE_ANSWER_NS:
            self._idle()
        # else remote navigation code is answering scans: its command, on its way now, comes first

    def take_input(self, topic: str, msg: Message, origin: str = "") -> None:
        """A command from a network surface (the inbox's hand-over, ``origin`` its surface): on the
        bus, where the mux keeps it; if its input wins, it is sent now, not at the next tick."""
        self.bus.publish(topic, msg)
        name = self.remote_inputs.get(topic)
        now = monotonic_ns()
        if name is not None and self.alive(now):
            msg = self.mux.decide_early(name, now, self.filters)
            if msg is not None:
                self._write(msg.drive)
                self._observe(msg, now)
                self._remote_write_ns = now
                self._idle()

    def engage_estop(self, origin: Origin) -> None:
        """Latch the mux e-stop and write the brake now (not at the next tick)."""
        now = monotonic_ns()
        self._note_estop(now, str(origin))
        self.mux.engage_estop(f"e-stop from {origin}", origin)
        if self.stats.ticks:  # the control loop runs: one step out of turn sends the brake
            self._out_of_turn(now)

    def network_estop(self, topic: str, msg: Message, who: str) -> None:
        """An e-stop or release message from a network session (``who``: ``zenoh``, ``dds``).

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
            if self.alive(now):
                self._out_of_turn(now)

    async def run(self) -> None:
        """Tick at the mux rate from a loop timer (no task wake-up per tick) until cancelled."""
        interval = self.notifier.watchdog_interval_s()
        if interval:
            self._watchdog_period_ns = int(interval * NS_PER_S / 2)
        failed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

        def on_error(err: BaseException) -> None:
            if not failed.done():
                failed.set_exception(err)

        timer = PeriodicTimer(self.mux.params.rate_hz, self.tick, on_error=on_error)
        timer.start()
        try:
            await failed
        finally:
            timer.cancel()

    # --- helpers -----------------------------------------------------------------------------

    def alive(self, now_ns: int) -> bool:
        """Whether the control loop ticked within the last two periods.

        The scan path re-sends commands only while the control loop runs: a stalled loop must
        let the VESC driver's command timeout brake the car, not be masked by scans.
        """
        return self.stats.ticks > 0 and now_ns - self.stats.last_tick_ns < 2 * self._period_ns

    def stop_now(self) -> None:
        """The car was disarmed: its stop is written now, not at the next tick (until then a scan
        would re-send the command from before, which the arming filter has not seen)."""
        now = monotonic_ns()
        if self.alive(now):
            self._out_of_turn(now)

    def _out_of_turn(self, now: int) -> None:
        msg = self.mux.decide(now, self.filters)
        self._write(msg.drive)
        self._observe(msg, now)

    def _idle(self) -> None:
        """The loop is idle until its next event: the outboxes' threads may take the GIL now."""
        for idle in self.idle:
            idle()

    def _observe(self, msg: AckermannDriveStamped, now: int) -> None:
        """After the write: the bus sees the output and the safety state."""
        self.mux.publish_output(msg)
        self.safety.publish_state_if_due(now)

    def _note_estop(self, now: int, who: str) -> None:
        self.estop_requests.append(EstopRequest(now, who, self.vesc.stats.frames_tx
                                                if self.vesc is not None else None))

    def _time_scan_path(self, vesc: VescDriver, lidar: LidarDriver) -> None:
        """Record the time from the scan's arrival to its motor command, if one was written."""
        arrived = lidar.frame_arrival_ns
        written = vesc.last_motor_write_ns
        if arrived and written >= arrived:  # this scan's command reached the OS
            self.stats.scan_to_command_ns.append(written - arrived)
            cpu = vesc.last_motor_write_cpu_ns - lidar.frame_arrival_cpu_ns
            self.stats.scan_to_command_cpu_ns.append(min(cpu, written - arrived))

    def status(self) -> DiagnosticStatus:
        """The control loop's diagnostic status: ticks, missed ticks, scan cuts."""
        stats = self.stats
        message = f"{stats.ticks} ticks, {stats.missed_ticks} missed"
        return DiagnosticStatus(
            DiagnosticStatus.OK, "racecar_hw: control loop", message,
            "", [KeyValue("ticks", str(stats.ticks)), KeyValue("missed ticks", str(stats.missed_ticks)),
                 KeyValue("scan cuts", str(stats.scan_cuts))])

    def _publish_diagnostics(self, now_ns: int) -> None:
        """:attr:`statuses` on the diagnostics topic, each in its own DiagnosticArray."""
        try:
            statuses = self.statuses(now_ns)
            stamp = stamp_now("", wall_ns())
            for status in statuses:  # one array each, as the mux publishes
                self.bus.publish(self.mux.params.diagnostics_topic, DiagnosticArray(stamp, [status]))
        except Exception as err:  # bookkeeping must never stop the control tick
            log.error("daemon diagnostics failed: %r", err)


def _nowhere(drive: AckermannDrive) -> None:
    """The write without a VESC configured."""
