"""A MAVLink 2 ground-station link over UDP: telemetry out, teleop, arming and modes in.

The car speaks as an ArduPilot Rover (MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_ARDUPILOTMEGA, custom
modes numbered as ArduPilot Rover numbers them: MANUAL 0, HOLD 4, GUIDED 15) to one ground station
at ``gcs_address`` (QGroundControl, MAVProxy, a pymavlink script). QGroundControl names custom modes
only through its ArduPilot plugin, which it picks for MAV_AUTOPILOT_ARDUPILOTMEGA (with GENERIC it
shows "Custom:0x0"); MAVProxy and pymavlink name them from the vehicle type whatever the autopilot
(except PX4). See docs/teleop.md. One UDP socket, bound to ``bind_address:bind_port``, sends and
receives; telemetry goes to ``gcs_address``, or, when its port is 0, to the port the first
authenticated message of the ground station came from. It never follows other senders.

Out: HEARTBEAT (1 Hz; armed flag from :class:`~racecar_hw.teleop.arming.Arming`), SYS_STATUS (with
sensor bits for the lidar and the motor controller) and BATTERY_STATUS (1 Hz, from
``/vesc/sensors/core``), ATTITUDE, LOCAL_POSITION_NED and VFR_HUD (from ``/odom``, REP-103 ENU/FLU
converted to NED/FRD) and OBSTACLE_DISTANCE (72 bins of 5 degrees in cm, from ``/scan``) at
``telemetry_rate_hz``, STATUSTEXT for events (arming, modes, safety state changes on
``/safety/state``, ground-station link lost and regained), COMMAND_ACK for every COMMAND_LONG,
COMMAND_INT and SET_MODE addressed to us, AUTOPILOT_VERSION on request, PARAM_VALUE for parameter
requests (a small read-only list).

In (only from the ground station's system id ``gcs_system_id``, ArduPilot's ``SYSID_MYGCS``):
MANUAL_CONTROL (ArduPilot Rover: ``y`` steering, +1000 = full right; ``z`` throttle, -1000..1000
with 0 = stop; ``x`` instead of ``z`` when ``throttle_axis: x``) and RC_CHANNELS_OVERRIDE (ch1
steering, ch3 throttle, PWM µs; 0 releases a channel, 65535 leaves a live value unchanged; a value
expires ``rc_override_time_s`` after it was sent, ArduPilot's ``RC_OVERRIDE_TIME``) drive the mux's
teleop input at ``rate_hz`` while the input is fresh, the mode is MANUAL and the ground station's
heartbeats are fresh. COMMAND_LONG / COMMAND_INT ARM_DISARM (400) and
DO_SET_MODE (176), and SET_MODE, change the arming and mode. HOLD stops the car through
:meth:`MavlinkGcs.filter` (a mux filter). When the ground station's heartbeats stop for more
than ``heartbeat_timeout_s``, its teleop input is dropped (one zero command, then silence) and a
STATUSTEXT says so.

Security: a ground station outside loopback needs MAVLink 2 signing (``signing_key_file``;
:class:`~racecar_hw.base.errors.ConfigError` otherwise). Datagrams are decoded by
:class:`~racecar_hw.teleop.mavlink_rx.MavlinkRx`: one datagram at a time, signatures verified
before any timestamp is recorded; with signing on, every unsigned or badly signed message is
refused and counted, and a signed frame stamped more than ``future_window_s`` ahead of our wall
clock is refused without recording its timestamp. Datagrams from any other host than the ground
station's are dropped and counted whatever the signing, and messages from other system ids are
ignored and counted. Every refusal is also counted in a
:class:`~racecar_hw.runtime.refusals.Refusals` (surface ``"mavlink"``, source ``host:port``),
which logs rate-limited summaries. :meth:`MavlinkGcs.restart_signing` forgets every stream's
timestamp, as a restart would (the daemon calls it on SIGUSR1, ``systemctl reload racecar-hw``).

Floods: the ground station's address has a socket of its own: a second socket on the same port
(``SO_REUSEPORT``), connected to the station, to which the kernel delivers the station's datagrams
in preference to the shared socket, so a flood from other addresses fills only the shared socket's
buffer and cannot push the station's heartbeats out. Each socket is drained each time it is
readable (the station's first), until empty or for ``DRAIN_BUDGET_NS``; a socket that still has
datagrams waiting after that rests for ``DRAIN_PAUSE_S`` (the kernel drops what overflows its
buffer), so a flood takes about 5 % of the event loop at most and the control loop keeps its time.
Forgeries are refused by :meth:`~racecar_hw.teleop.mavlink_rx.MavlinkRx.refuse_cheaply` before
any parsing, and refusals are noted once per wake-up.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns, wall_ns
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    stamp_now,
)
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.status import StatusSnapshot
from racecar_hw.runtime.ticker import Ticker
from racecar_hw.teleop.arming import Arming, ArmingChange
from racecar_hw.teleop.mavlink_commands import Commands
from racecar_hw.teleop.mavlink_dialect import MODE_NAMES, MODES, mavlink
from racecar_hw.teleop.mavlink_params import MavlinkParams
from racecar_hw.teleop.mavlink_presence import StationPresence
from racecar_hw.teleop.mavlink_rx import MavlinkRx
from racecar_hw.teleop.mavlink_signing import (
    REFUSAL_REASONS,
    SIGNING_EPOCH_S,
    LinkSecurity,
    Tally,
    load_signing_key,
    signing_timestamp,
    write_signing_key,
)
from racecar_hw.teleop.mavlink_socket import MavlinkSocket
from racecar_hw.teleop.mavlink_sticks import ManualInput, Sticks
from racecar_hw.teleop.mavlink_telemetry import Telemetry, obstacle_bins, odom_to_ned, quaternion_matrix

log = logging.getLogger(__name__)

#: The names of :attr:`MavlinkGcs.counters`.
COUNTERS = (
    "rx", "tx", "foreign", "other_sender", "bad_data", "unknown_ids", "mavlink1_refused", "unsigned_refused",
    "bad_signature", "old_timestamp", "future_timestamp", "oversized", "overfull", "commands", "acks",
    "manual_inputs", "inputs_ignored", "gcs_timeouts", "teleop_published", "statustexts", "send_errors",
    "datagrams", "station_datagrams", "drain_rests", "signing_restarts")


class MavlinkGcs:
    """The ground-station link on the bus. ``await run()`` until cancelled.

    The link is wiring and the per-message dispatch; its parts each have one job:
    :class:`~racecar_hw.teleop.mavlink_socket.MavlinkSocket` (the UDP sockets),
    :class:`~racecar_hw.teleop.mavlink_signing.LinkSecurity` (who may talk to us),
    :class:`~racecar_hw.teleop.mavlink_sticks.Sticks` (teleop input),
    :class:`~racecar_hw.teleop.mavlink_commands.Commands` (arming, modes, requests) and
    :class:`~racecar_hw.teleop.mavlink_telemetry.Telemetry` (what the station is told).

    ``status_source`` (optional) returns the daemon's :class:`~racecar_hw.runtime.status.StatusSnapshot`;
    its link counters go into SYS_STATUS ``errors_count1..3`` (VESC CRC errors, VESC reconnects,
    lidar reconnects) and its battery voltage is used while no VESC state has arrived.

    :attr:`counters` (for tests and end-to-end checks): ``rx``, ``tx``, ``foreign`` (datagrams from
    another host), ``bad_data``, ``unsigned_refused``, ``bad_signature``, ``old_timestamp``,
    ``future_timestamp``, ``oversized`` and ``overfull`` (datagrams longer, or with more frames,
    than a ground station sends: :mod:`~racecar_hw.teleop.mavlink_rx`), ``commands``, ``acks``,
    ``manual_inputs``, ``inputs_ignored`` (teleop outside MANUAL or without a fresh ground-station
    heartbeat), ``gcs_timeouts``,
    ``teleop_published``, ``statustexts``, ``send_errors``, ``datagrams`` (read from the sockets),
    ``station_datagrams`` (of those, read from the station's own socket), ``drain_rests`` (a socket
    still had datagrams waiting after its budget: a flood), ``signing_restarts``.
    :attr:`heartbeat_gap_max_ns`: the longest time between two heartbeats of a connected station.

    ``refusals``: where refused input is counted and logged (the daemon's; a private one if None).
    """

    def __init__(self, bus: Bus, params: MavlinkParams, arming: Arming,
                 status_source: Callable[[], StatusSnapshot | None] | None = None, *,
                 clock: Callable[[], int] = monotonic_ns, wall_clock: Callable[[], int] = wall_ns,
                 refusals: Refusals | None = None) -> None:
        self.bus = bus
        self.refusals = refusals if refusals is not None else Refusals()
        self.params = params
        self.arming = arming
        self._clock = clock
        self._wall_clock = wall_clock
        gcs_host, gcs_port = params.gcs
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self.udp = MavlinkSocket(params.bind, (gcs_host, gcs_port) if gcs_port else None, self.counters,
                                 self.handle_datagram, lambda tally: self.security.note_tally(tally))
        # pymavlink only packs and signs what we send; received datagrams go through self.security
        self.mav = mavlink.MAVLink(self.udp, params.system_id, params.component_id)
        self.security = LinkSecurity(
            self.mav, gcs_host, params.gcs_address, params.gcs_system_id,
            signing_key_file=params.signing_key_file, signing_link_id=params.signing_link_id,
            future_window_s=params.future_window_s, counters=self.counters, refusals=self.refusals,
            wall_clock=wall_clock, bind_host=params.bind[0])
        self.gcs_system_id = params.gcs_system_id
        self._publishing = False
        bus.declare(params.teleop_topic, AckermannDriveStamped)
        self.telemetry = Telemetry(
            bus, self.mav, arming, lambda: self.commands.mode,
            topics=(params.vesc_state_topic, params.odom_topic, params.scan_topic, params.safety_topic),
            telemetry_rate_hz=params.telemetry_rate_hz, counters=self.counters,
            status_source=status_source, clock=clock, wall_clock=wall_clock)
        self.presence = StationPresence(params.heartbeat_timeout_s, self.counters, self.telemetry.statustext)
        self.sticks = Sticks(params, self._accept_input)
        self.commands = Commands(params, self.mav, arming, self.sticks, self.telemetry, self.counters, clock)
        self._remove_arming_callback = arming.on_change(self._on_arming)

    # --- properties for the daemon and tests -------------------------------------------------

    @property
    def rx(self) -> MavlinkRx:
        """The decoder of received datagrams (its signing streams and timestamp)."""
        return self.security.rx

    @property
    def port(self) -> int:
        """The bound local UDP port (after :meth:`start`)."""
        return self.udp.port

    @property
    def station_socket(self) -> bool:
        """True while the ground station's address has its own connected socket."""
        return self.udp.station_socket

    @property
    def gcs_alive(self) -> bool:
        """True while the ground station's heartbeats are fresh."""
        return self.presence.alive

    @property
    def heartbeat_gap_max_ns(self) -> int:
        """The longest time between two heartbeats of a connected station (ns)."""
        return self.presence.gap_max_ns

    @property
    def mode_name(self) -> str:
        """MANUAL, HOLD or GUIDED."""
        return MODE_NAMES[self.commands.mode]

    @property
    def manual(self) -> ManualInput | None:
        """The ground station's latest teleop request (None: none, or dropped)."""
        return self.sticks.manual

    @property
    def teleop_active(self) -> bool:
        """True while the ground station's teleop input is being published."""
        return self._publishing

    # --- life cycle ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind the UDP socket, and the ground station's own socket when its port is known."""
        await self.udp.start()
        log.info("MAVLink link on udp %s:%d to ground station %s%s", self.params.bind[0], self.port,
                 self.params.gcs_address, " (signed)" if self.security.secret_key else "")

    async def run(self) -> None:
        """Bind (unless started), then tick at ``rate_hz`` until cancelled; a final stop on exit."""
        if not self.udp.bound:
            await self.start()
        ticker = Ticker(self.params.rate_hz, self._clock)
        try:
            while True:
                await ticker.tick()
                self.tick()
        finally:
            if self._publishing:
                self._publish_drive(AckermannDrive())
                self._publishing = False
            self.close()

    def close(self) -> None:
        """Unsubscribe and close the sockets (safe twice)."""
        self.telemetry.close()
        self._remove_arming_callback()
        self.udp.close()

    def restart_signing(self) -> int:
        """Forget every signing stream's timestamp and take our signing time from the wall clock
        again, as a restart of the daemon does: the way back should a wrongly stamped frame ever
        have been accepted (see docs/teleop.md). Our outgoing timestamps restart from the wall
        clock too. Returns how many streams were forgotten."""
        forgotten = self.security.restart()
        if self.security.secret_key is not None:
            self.statustext("Signing state restarted", mavlink.MAV_SEVERITY_NOTICE)
        return forgotten

    # --- outgoing ----------------------------------------------------------------------------

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """Send a STATUSTEXT (at most 50 characters are sent) and log it."""
        self.telemetry.statustext(text, severity)

    def send_heartbeat(self) -> None:
        """HEARTBEAT: rover, armed flag, custom mode."""
        self.telemetry.send_heartbeat()

    def send_power(self, now: int) -> None:
        """SYS_STATUS always; BATTERY_STATUS once the VESC has reported."""
        self.telemetry.send_power(now)

    def send_vfr_hud(self) -> None:
        """VFR_HUD from odometry and the VESC's duty cycle."""
        self.telemetry.send_vfr_hud()

    # --- the fixed-rate step ---------------------------------------------------------------------

    def tick(self, now_ns: int | None = None) -> None:
        """Heartbeat watch, teleop publishing, telemetry and a requested parameter list when due."""
        now = self._clock() if now_ns is None else now_ns
        manual = self.commands.mode == MODES["MANUAL"]
        if self.presence.lost(now) or not manual:
            self.sticks.forget()
        drive = self.sticks.drive(now, self.gcs_alive and manual)
        if drive is not None:
            self._publish_drive(drive)
            self._publishing = True
        elif self._publishing:
            self._publish_drive(AckermannDrive())
            self._publishing = False
        if self.udp.bound:
            self.telemetry.send_due(now)
            self.commands.send_due()

    def _publish_drive(self, drive: AckermannDrive) -> None:
        msg = AckermannDriveStamped(stamp_now("base_link", self._wall_clock()), drive)
        self.bus.publish(self.params.teleop_topic, msg)
        self.counters["teleop_published"] += 1

    def filter(self, drive: AckermannDrive, source: str, now_ns: int) -> AckermannDrive:
        """Mux filter: a stop while the mode is HOLD; ``drive`` unchanged otherwise."""
        return AckermannDrive() if self.commands.mode == MODES["HOLD"] else drive

    # --- incoming ----------------------------------------------------------------------------

    def handle_datagram(self, data: bytes, addr: tuple[Any, ...], tally: Tally | None = None) -> None:
        """One UDP datagram from ``addr``: decode it alone and act on every verified message of
        the ground station in it. Refusals are counted in :attr:`counters` and :attr:`refusals`
        (``tally``: summed there for the caller to note; None: noted at once). Never raises."""
        messages = self.security.station_messages(data, addr, tally)
        now = self._clock()
        for msg in messages:
            self.udp.learn_station(addr)  # gcs_address port 0: the first authenticated station
            kind = msg.get_type()
            try:
                self._dispatch(kind, msg, now)
            except Exception:
                log.exception("MAVLink %s handling failed", kind)

    def _for_us(self, system: int, component: int | None = None) -> bool:
        if system not in (0, self.params.system_id):
            return False
        return component is None or component in (0, self.params.component_id)

    def _dispatch(self, kind: str, msg: Any, now: int) -> None:
        if kind == "HEARTBEAT":
            if msg.type == mavlink.MAV_TYPE_GCS:
                self.presence.heard(now)
        elif kind == "MANUAL_CONTROL":
            if self._for_us(msg.target):
                self.sticks.take_manual_control(msg, now)
        elif kind == "RC_CHANNELS_OVERRIDE":
            if self._for_us(msg.target_system, msg.target_component):
                self.sticks.take_rc_override(msg, now)
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if self._for_us(msg.target_system, msg.target_component):
                self.commands.on_command(msg, now)
        elif kind == "SET_MODE":
            if self._for_us(msg.target_system):
                self.commands.on_set_mode(msg)
        elif kind == "PARAM_REQUEST_LIST":
            if self._for_us(msg.target_system, msg.target_component):
                self.commands.on_param_request_list()
        elif kind == "PARAM_REQUEST_READ":
            if self._for_us(msg.target_system, msg.target_component):
                self.commands.on_param_request(msg.param_id, msg.param_index)
        elif kind == "PARAM_SET" and self._for_us(msg.target_system, msg.target_component):
            self.commands.on_param_request(msg.param_id, -1)

    def _accept_input(self) -> bool:
        if not self.gcs_alive or self.commands.mode != MODES["MANUAL"]:
            self.counters["inputs_ignored"] += 1
            return False
        self.counters["manual_inputs"] += 1
        return True

    # --- events ------------------------------------------------------------------------------

    def _on_arming(self, change: ArmingChange) -> None:
        self.statustext(("Armed" if change.armed else "Disarmed") + f" by {change.source}",
                        mavlink.MAV_SEVERITY_NOTICE)
        self.send_heartbeat()


__all__ = ["MODES", "REFUSAL_REASONS", "SIGNING_EPOCH_S", "MavlinkGcs", "MavlinkParams", "load_signing_key",
           "obstacle_bins", "odom_to_ned", "quaternion_matrix", "signing_timestamp", "write_signing_key"]
