"""The VESC serial driver: an asyncio shell around :class:`~vesc.codec.VescCodec`.

:meth:`VescDriver.run` opens the port, asks for FW_VERSION until the VESC answers (the reply picks
the GET_VALUES layout), then polls GET_VALUES at ``poll_rate_hz`` and publishes:

=========================================  ========================  ===========================
topic                                      type                      when
=========================================  ========================  ===========================
``/vesc/sensors/core``                     VescStateStamped          every telemetry reply
``/vesc/sensors/servo_position_command``   Float64 (0..1)            every servo position sent, as
                                                                     the VESC receives it (thousandths)
``/odom``                                  Odometry                  every telemetry reply
``/tf``                                    TFMessage (odom->base)    every reply, if publish_tf
``/imu``                                   Imu (SI, ``imu`` frame)   every IMU reply, if imu
=========================================  ========================  ===========================

With ``imu`` on and firmware 3.52 or later, every poll also asks COMM_GET_IMU_DATA (all fields);
the reply is published in SI units (:mod:`vesc.imu`), the gyro as measured. The gyro's z bias is
learned while the motor stands still; with ``odometry_yaw_rate: imu`` odometry takes its yaw rate
from the bias-corrected gyro once the bias has settled and while IMU replies keep coming (else the
steering model).

:meth:`VescDriver.command` (called by the daemon's control loop at about 50 Hz) converts an
AckermannDrive and writes SET_RPM + SET_SERVO_POS at once. Those motor commands keep the firmware's
own 1 s command timeout fed; while moving, ALIVE goes out if no motor command was written for
``alive_interval_s``.

Failsafe: ``command_timeout_s`` after the last valid command (a precise loop timer, not the poll
tick) the driver sends brake (SET_RPM 0, or SET_CURRENT_BRAKE in ``brake_mode`` "current") and the
servo centre, then repeats both on every poll tick until a fresh command arrives. A NaN or infinite
command brakes at once. The first frames after every (re)connect are brake and centre.

Hostile or noisy input: a FW_VERSION frame is believed only as the answer to our own request
during the handshake, and only for a firmware whose layout the codec knows
(:func:`~vesc.codec.known_firmware`); any other (line noise decodes as "0.0", a stray frame
mid-session) is ignored and counted, so the telemetry layout never changes without a new handshake.
Telemetry with physically impossible values (ERPM beyond :data:`IMPLAUSIBLE_ERPM_FACTOR` times
the ERPM at ``speed_max_mps``, input voltage outside 0-100 V, duty cycle beyond +-1) is dropped
and counted, never published; so is an IMU reply beyond the sensor's full scale
(:data:`PLAUSIBLE_GYRO_DPS`, :data:`PLAUSIBLE_ACC_G`), which would also have poisoned the gyro bias.

An unplug (DeviceIOError/DeviceNotFound) closes the port and reopens it with exponential backoff
from ``reconnect_backoff_min_s`` to ``reconnect_backoff_max_s``; so does a VESC that stops
answering with its port still open (after the handshake, no valid frame for ``reply_timeout_s``
with :data:`UNANSWERED_POLLS` polls or more written since:
:class:`~racecar_hw.base.errors.DeviceTimeout`; counting polls keeps a process that was held up,
and its reader with it, from calling a live VESC lost), and one that stops reading (the link's
transmit backlog full). No exception leaves :meth:`run`
except CancelledError; :meth:`shutdown` brakes, centres, closes and is safe twice.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass
from typing import TypeVar

from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns, nanoseconds, seconds, wall_ns
from racecar_hw.base.errors import DeviceError, DeviceIOError, DeviceTimeout, LocalProtocolError
from racecar_hw.base.link import Link, find_serial_port, open_link
from racecar_hw.base.messages import (
    AckermannDrive,
    Float64,
    Header,
    Imu,
    Odometry,
    TFMessage,
    Time,
    VescState,
    VescStateStamped,
)
from racecar_hw.base.topics import TOPIC_CORE, TOPIC_IMU, TOPIC_ODOM, TOPIC_SERVO, TOPIC_TF
from racecar_hw.runtime.reconnect import ReconnectingDevice
from racecar_hw.runtime.ticker import PeriodicTimer
from vesc.ackermann import AckermannConversion
from vesc.codec import (
    IMU_SINCE,
    TIMEOUT_RESETTING,
    Alive,
    FwVersion,
    FwVersionRequest,
    GetImuDataRequest,
    GetValuesRequest,
    ImuData,
    Packet,
    RawPacket,
    Role,
    SetCurrentBrake,
    SetRpm,
    SetServoPosition,
    Values,
    VescCodec,
    known_firmware,
    servo_on_wire,
)
from vesc.imu import DEG, GyroBias, ImuCovariances, imu_message, imu_provides
from vesc.odometry import OdometryIntegrator
from vesc.params import VescParams

log = logging.getLogger(__name__)
R = TypeVar("R")

#: Encoded frames remembered by :meth:`VescDriver._encode` (host commands: no firmware dependence).
_MAX_CACHED_FRAMES = 256
#: Telemetry whose |ERPM| exceeds this many times the ERPM at ``speed_max_mps`` is impossible for
#: the car (a motor that fast would have left the track): it is dropped, not published.
IMPLAUSIBLE_ERPM_FACTOR = 4.0
#: Input voltages (V) a VESC can report; outside them the reply is garbage (VESC 6: 8-60 V).
PLAUSIBLE_V_IN = (0.0, 100.0)
#: Largest |duty cycle| a reply can carry (the firmware clamps to 0.95).
PLAUSIBLE_DUTY = 1.0

#: Largest |angular rate| (deg/s) and |acceleration| (g) an IMU reply can carry: the VESC's IMUs
#: (BMI160, LSM6DS3, MPU9250) read at most +-2000 deg/s and +-16 g, with a tenth of margin.
PLAUSIBLE_GYRO_DPS = 2200.0
PLAUSIBLE_ACC_G = 17.6

#: Telemetry polls written without a frame coming back before a silent VESC counts as lost (with
#: ``reply_timeout_s`` passed too).
UNANSWERED_POLLS = 3

#: IMU replies older than this many poll periods are not used for odometry's yaw rate.
IMU_STALE_POLLS = 3


@dataclass
class VescLinkStats:
    """Link statistics, cumulative over reconnects.

    ``drive_commands``: drive commands (:meth:`VescDriver.command`) written to a connected VESC
    (one that answered FW_VERSION); ``failsafes``: times the no-command failsafe engaged;
    ``refused_commands``: NaN/inf drive commands; ``write_errors``: writes that found the port
    gone; ``ignored_fw_versions``: FW_VERSION frames not taken (unasked, mid-session, or an
    unknown version); ``implausible_telemetry``: GET_VALUES replies dropped for physically
    impossible values; ``implausible_imu``: IMU replies dropped for values beyond the sensor's
    full scale.
    """

    frames_tx: int = 0
    frames_rx: int = 0
    crc_errors: int = 0
    resyncs: int = 0
    dropped_bytes: int = 0
    raw_packets: int = 0
    reconnects: int = 0
    failsafes: int = 0
    refused_commands: int = 0
    write_errors: int = 0
    ignored_fw_versions: int = 0
    implausible_telemetry: int = 0
    imu_replies: int = 0
    implausible_imu: int = 0
    drive_commands: int = 0


def values_to_state(v: Values) -> VescState:
    """A decoded GET_VALUES reply as vesc_msgs/VescState (``speed`` is ERPM, not negated)."""
    return VescState(
        temp_fet=v.temp_fet, temp_motor=v.temp_motor, current_motor=v.current_motor,
        current_input=v.current_input, avg_id=v.avg_id, avg_iq=v.avg_iq, duty_cycle=v.duty,
        speed=float(v.erpm), voltage_input=v.v_in, charge_drawn=v.amp_hours,
        charge_regen=v.amp_hours_charged, energy_drawn=v.watt_hours,
        energy_regen=v.watt_hours_charged, displacement=v.tachometer,
        distance_traveled=v.tachometer_abs, fault_code=v.fault, pid_pos_now=v.pid_pos,
        controller_id=v.controller_id, ntc_temp_mos1=v.temp_mos1, ntc_temp_mos2=v.temp_mos2,
        ntc_temp_mos3=v.temp_mos3, avg_vd=v.avg_vd, avg_vq=v.avg_vq)


class VescDriver(ReconnectingDevice):
    """One VESC on a serial port, publishing on ``bus``. An async context manager running :meth:`run`.

    The reconnect loop is :class:`~racecar_hw.runtime.reconnect.ReconnectingDevice`'s: a port that
    opens proves the VESC, so the backoff restarts then and a lost link is reopened at once.
    """

    device_name = "VESC"

    def __init__(self, bus: Bus, params: VescParams | None = None) -> None:
        self.bus = bus
        self.params = params or VescParams()
        super().__init__(self.params.reconnect_backoff_min_s, self.params.reconnect_backoff_max_s)
        self.conversion = AckermannConversion.from_params(self.params)
        self.odometry = OdometryIntegrator.from_params(self.params)
        self.stats = VescLinkStats()
        self._codec = VescCodec(Role.HOST)
        self._link: Link | None = None
        self._firmware: tuple[int, int] | None = None
        self._fw_reply: FwVersion | None = None
        self._fw_asked = False  # a FW_VERSION request went out on this connection
        params = self.params
        self._max_erpm = IMPLAUSIBLE_ERPM_FACTOR * (params.speed_max_mps * params.speed_to_erpm_gain
                                                    + abs(params.speed_to_erpm_offset))
        self._last_state: VescStateStamped | None = None
        self._servo_sent = self.conversion.servo_centre
        self._moving = False
        self._last_command_ns = 0
        self._last_motor_tx_ns = 0
        self._last_motor_tx_cpu_ns = 0
        self._failsafe_timer: asyncio.TimerHandle | None = None
        self._failsafe_loop: asyncio.AbstractEventLoop | None = None
        self._frames: dict[Packet, bytes] = {}
        self._closed = False
        self._run_task: asyncio.Task[None] | None = None
        self._timeout_ns = nanoseconds(self.params.command_timeout_s)
        self._alive_ns = nanoseconds(self.params.alive_interval_s)
        # A poll is due 0.9 poll periods after the last one: a command going out then carries it, so
        # telemetry keeps the configured rate (at most ~10 % above it) with fewer writes.
        self._poll_due_ns = nanoseconds(0.9 / self.params.poll_rate_hz)
        self._last_poll_ns = 0
        #: no valid frame for this long, with UNANSWERED_POLLS polls written, is a lost link
        self._reply_timeout_ns = nanoseconds(self.params.reply_timeout_s)
        self._last_rx_ns = 0
        self._unanswered = 0
        #: why the poll loop dropped the link, raised by the session in place of the link's "not open"
        self._lost: DeviceError | None = None
        #: what each poll asks for: GET_VALUES, and the IMU where the firmware has one
        self._polls: tuple[Packet, ...] = (GetValuesRequest(),)
        self._imu_cov = ImuCovariances(params.imu_orientation_variance, params.imu_yaw_variance,
                                       params.imu_angular_velocity_variance,
                                       params.imu_linear_acceleration_variance)
        self.gyro_bias = GyroBias(params.imu_bias_time_s)
        self._last_imu: Imu | None = None
        #: the last gyro z rate (rad/s, bias included) and when it came (monotonic ns)
        self._gyro_z: float | None = None
        self._gyro_z_ns = 0
        self._imu_stale_ns = nanoseconds(IMU_STALE_POLLS / params.poll_rate_hz)
        self._standing = True  # the last telemetry said ERPM 0

    # --- public state -------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the port is open and the VESC answered FW_VERSION on it."""
        return self._link is not None and self._link.is_open and self._firmware is not None

    @property
    def last_motor_write_ns(self) -> int:
        """Monotonic ns when the OS last took a motor command (RPM, current, brake or duty); 0 if never."""
        return self._last_motor_tx_ns

    @property
    def last_motor_write_cpu_ns(self) -> int:
        """The writing thread's CPU time (``time.thread_time_ns``) at :attr:`last_motor_write_ns`."""
        return self._last_motor_tx_cpu_ns

    @property
    def firmware(self) -> tuple[int, int] | None:
        """(major, minor) of the connected VESC's firmware, None before the handshake."""
        return self._firmware

    @property
    def firmware_info(self) -> FwVersion | None:
        """The whole FW_VERSION reply (hardware name, UUID) of the last handshake."""
        return self._fw_reply

    @property
    def last_state(self) -> VescStateStamped | None:
        """The last telemetry published on ``/vesc/sensors/core``."""
        return self._last_state

    @property
    def last_imu(self) -> Imu | None:
        """The last message published on ``/imu``."""
        return self._last_imu

    @property
    def servo_sent(self) -> float:
        """The last servo position written to the VESC (0..1), in the thousandths it travels in."""
        return self._servo_sent

    @property
    def moving(self) -> bool:
        """Whether a fresh drive command is in force (False: failsafe brake and centre)."""
        return self._moving

    # --- commands -----------------------------------------------------------------------------

    def command(self, drive: AckermannDrive) -> None:
        """Drive now: SET_RPM and SET_SERVO_POS are written before this returns. Never blocks or raises.

        Commands before the FW_VERSION handshake only arm the failsafe (as the ROS driver, which
        drops them). A NaN/inf command is refused and brakes at once.
        """
        if self._closed:
            return
        try:
            setpoint = self.conversion.to_vesc(drive)
        except LocalProtocolError as err:
            self.stats.refused_commands += 1
            log.warning("drive command refused (%s): braking", err)
            self._engage_failsafe()
            return
        now = self._last_command_ns = monotonic_ns()
        self._moving = True
        if self._firmware is not None:
            if now - self._last_poll_ns >= self._poll_due_ns:
                # the telemetry poll rides along: one write instead of two
                self._last_poll_ns = now
                written = self._write(SetRpm(setpoint.erpm), SetServoPosition(setpoint.servo), *self._polls)
            else:
                written = self._write(SetRpm(setpoint.erpm), SetServoPosition(setpoint.servo))
            if written:
                self.stats.drive_commands += 1
        self._arm_failsafe_timer()  # counts from _last_command_ns; the write need not wait for it

    def brake_and_centre(self) -> None:
        """Send brake and the servo centre now (what the failsafe sends)."""
        brake = (SetRpm(0) if self.params.brake_mode == "rpm"
                 else SetCurrentBrake(self.params.brake_current_a))
        self._write(brake, SetServoPosition(self.conversion.servo_centre))

    # --- lifecycle ----------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, handshake, poll and reconnect until :meth:`shutdown` (or cancellation)."""
        self._run_task = asyncio.current_task()
        try:
            await super().run()
        finally:
            self._close_link()

    def _on_opened(self) -> None:
        if self.ever_connected:
            self.stats.reconnects += 1
        super()._on_opened()

    def _on_cancelled(self) -> None:
        self.brake_and_centre()  # leave the car braked

    async def _close(self) -> None:
        self._close_link()

    async def shutdown(self) -> None:
        """Brake, centre the servo, close the port and stop :meth:`run`. Safe twice."""
        if self._closed:
            return
        self._closed = True
        self.stop_reconnecting()
        self._moving = False
        if self._failsafe_timer is not None:
            self._failsafe_timer.cancel()
        link = self._link
        if link is not None and link.is_open:
            self.brake_and_centre()
            deadline = monotonic_ns() + nanoseconds(0.2)
            while link.is_open and link.tx_pending and monotonic_ns() < deadline:
                await asyncio.sleep(0.005)
        self._close_link()
        task = self._run_task
        if task is not None and task is not asyncio.current_task() and not task.done():
            done, _ = await asyncio.wait({task}, timeout=2.0)
            if not done:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task

    async def __aenter__(self) -> VescDriver:
        self._run_task = asyncio.create_task(self.run(), name="vesc-driver")
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.shutdown()

    # --- internals ----------------------------------------------------------------------------

    def _resolve_port(self) -> str:
        if self.params.port != "auto":
            return self.params.port
        vid, pid = self.params.usb_ids
        return find_serial_port(vid, pid, self.params.usb_serial)

    async def _open(self) -> None:
        try:
            url = self._resolve_port()
        except OSError as err:
            raise DeviceIOError(f"cannot list serial ports: {err}") from err
        link = open_link(url, self.params.baudrate)
        await link.open()
        self._link = link
        log.info("VESC port %s open", url)

    def _close_link(self) -> None:
        link, self._link = self._link, None
        self._firmware = None
        if link is not None:
            link.close()

    async def _session(self) -> None:
        link = self._link
        assert link is not None
        self._codec.reset()
        self._codec.firmware = None
        self._firmware = None
        self._fw_asked = False
        self.brake_and_centre()
        ticker = asyncio.create_task(self._tick_loop(link), name="vesc-poll")
        # replies are decoded in the link's reader callback, without waking this task
        link.set_receiver(self._on_bytes)
        self._lost, self._unanswered = None, 0
        try:
            while True:
                self._on_bytes(await link.read())  # with a receiver set, this raises once the link fails
        except DeviceError:
            lost, self._lost = self._lost, None
            if lost is not None:
                raise lost from None
            raise
        finally:
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker

    async def _tick_loop(self, link: Link) -> None:
        """FW_VERSION until the VESC answers, then GET_VALUES polls from a loop timer until the link closes.

        The polls run as :class:`~racecar_hw.runtime.ticker.PeriodicTimer` callbacks on absolute deadlines
        (missed deadlines are skipped, never burst), so a poll wakes no task.
        """
        loop = asyncio.get_running_loop()
        try:
            while link.is_open:
                if self._firmware is None:
                    now = monotonic_ns()
                    self._write(FwVersionRequest())
                    self._fw_asked = True
                    if not self._fresh(now):
                        self.brake_and_centre()
                    await asyncio.sleep(self.params.handshake_interval_s)
                    continue
                ended: asyncio.Future[None] = loop.create_future()

                def poll(due_ns: int, periods: int, ended: asyncio.Future[None] = ended) -> None:
                    if not (link.is_open and self._firmware is not None):
                        if not ended.done():
                            ended.set_result(None)
                        return
                    self._poll()

                def failed(err: BaseException, ended: asyncio.Future[None] = ended) -> None:
                    if not ended.done():
                        ended.set_exception(err)

                timer = PeriodicTimer(self.params.poll_rate_hz, poll, on_error=failed)
                timer.start(loop)
                try:
                    await ended
                finally:
                    timer.cancel()
        except asyncio.CancelledError:
            raise
        except DeviceError as err:  # a VESC that stopped answering: its queued commands are stale
            self._lost = err
            link.discard_unsent()
            link.close()
        except Exception:
            log.exception("VESC poll loop failed; dropping the link to reconnect")
            link.close()

    def _poll(self) -> None:
        """One poll tick: GET_VALUES (unless a command just carried one), then the failsafe or ALIVE.

        While the failsafe timer is armed, it alone decides when a moving car brakes. After the
        whole process was held up (a descheduled CPU, a throttled cgroup), every overdue loop timer
        runs in one pass in the order of its deadline: the control tick, due before the failsafe
        deadline, sends its command first. A poll tick that ran first and judged the command's
        age would brake a car whose commands were never stale.
        """
        now = monotonic_ns()
        if now - self._last_rx_ns > self._reply_timeout_ns and self._unanswered >= UNANSWERED_POLLS:
            raise DeviceTimeout(f"{self.params.port}: the VESC sent no valid frame for "
                                f"{seconds(now - self._last_rx_ns):.2f} s")
        if now - self._last_poll_ns >= self._poll_due_ns:
            self._last_poll_ns = now
            self._write(*self._polls)
        if not (self._fresh(now) or self._failsafe_timer_armed()):
            self._engage_failsafe()  # engages, or repeats brake and centre while braked
        elif now - self._last_motor_tx_ns >= self._alive_ns:
            self._write(Alive())

    def _failsafe_timer_armed(self) -> bool:
        """Whether a moving car's failsafe timer is pending on the running loop."""
        timer = self._failsafe_timer
        return (self._moving and timer is not None and not timer.cancelled()
                and self._failsafe_loop is asyncio.get_running_loop())

    def _fresh(self, now_ns: int) -> bool:
        return self._moving and now_ns - self._last_command_ns < self._timeout_ns

    def _arm_failsafe_timer(self) -> None:
        """Make sure the failsafe fires ``command_timeout_s`` after the latest command.

        A pending timer due more than half a timeout from now is left as it is: should commands
        stop, it fires, finds the later command and waits out the rest. One due sooner is moved.
        So while commands come at least every half timeout the timer never wakes the loop (a
        wake-up costs far more than moving a timer), and it is moved at most twice per timeout
        rather than at every command. :meth:`command` calls this after its write.
        """
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return  # no loop: the poll tick enforces the timeout instead
        timer = self._failsafe_timer
        if timer is not None:
            if (self._failsafe_loop is loop and not timer.cancelled()
                    and timer.when() - loop.time() > 0.5 * self.params.command_timeout_s):
                return
            timer.cancel()
        self._failsafe_loop = loop
        self._failsafe_timer = loop.call_at(seconds(self._last_command_ns + self._timeout_ns),
                                            self._on_failsafe_timer)

    def _on_failsafe_timer(self) -> None:
        self._failsafe_timer = None
        if not self._moving or self._closed:
            return
        deadline = self._last_command_ns + self._timeout_ns
        if deadline > monotonic_ns():  # commands came after the timer was set
            self._failsafe_timer = asyncio.get_running_loop().call_at(seconds(deadline),
                                                                      self._on_failsafe_timer)
            return
        self._engage_failsafe()

    def _engage_failsafe(self) -> None:
        if self._moving:
            self._moving = False
            self.stats.failsafes += 1
            log.warning("no fresh drive command for %.0f ms: brake and centre",
                        self.params.command_timeout_s * 1e3)
        self.brake_and_centre()

    def _encode(self, packet: Packet) -> bytes:
        """The framed bytes of ``packet``, memoised: a car mostly repeats the same few commands."""
        frames = self._frames
        data = frames.get(packet)
        if data is None:
            data = self._codec.send(packet)
            if len(frames) >= _MAX_CACHED_FRAMES:
                frames.clear()
            frames[packet] = data
        return data

    def _write(self, *packets: Packet) -> bool:
        """Write ``packets`` in one write; whether the OS took them."""
        link = self._link
        if link is None or not link.is_open:
            return False
        data = b"".join([self._encode(p) for p in packets])
        try:
            link.write(data)
        except DeviceError as err:
            self.stats.write_errors += 1
            log.debug("VESC write failed: %s", err)
            return False
        self.stats.frames_tx += len(packets)
        now = monotonic_ns()
        for p in packets:
            if isinstance(p, TIMEOUT_RESETTING):
                self._last_motor_tx_ns = now
                self._last_motor_tx_cpu_ns = time.thread_time_ns()
            elif isinstance(p, SetServoPosition):
                # what the VESC received (thousandths): calibration fits against it, odometry steers by it
                self._servo_sent = servo_on_wire(p.position)
                self.bus.publish(TOPIC_SERVO, Float64(self._servo_sent))
            elif isinstance(p, GetValuesRequest):
                self._unanswered += 1
        return True

    def _on_bytes(self, data: bytes) -> None:
        self._codec.receive_data(data)
        while (packet := self._codec.next_event()) is not None:
            self._on_packet(packet)
        self._sync_codec_stats()

    def _sync_codec_stats(self) -> None:
        s = self._codec.stats
        self.stats.frames_rx = s.frames
        self.stats.crc_errors = s.crc_errors + s.zero_payloads
        self.stats.resyncs = s.resyncs
        self.stats.dropped_bytes = s.dropped_bytes
        self.stats.raw_packets = s.raw_packets

    def _on_packet(self, packet: Packet) -> None:
        self._last_rx_ns = monotonic_ns()  # a frame with a valid CRC: the VESC is there
        self._unanswered = 0
        if isinstance(packet, Values):
            self._on_values(packet)
        elif isinstance(packet, ImuData):
            self._on_imu(packet)
        elif isinstance(packet, FwVersion):
            self._on_fw_version(packet)
        elif isinstance(packet, RawPacket):
            if packet.command_id == 21:  # COMM_PRINT
                log.info("VESC says: %s", packet.payload[1:].decode("utf-8", "replace").rstrip())
            else:
                log.debug("VESC packet not decoded (%s): id %d, %d bytes", packet.reason,
                          packet.command_id, len(packet.payload))

    def _on_fw_version(self, packet: FwVersion) -> None:
        """Take the handshake's answer; ignore (and count) every other FW_VERSION frame."""
        if self._firmware is not None or not self._fw_asked or not known_firmware(packet.version):
            self.stats.ignored_fw_versions += 1
            why = ("mid-session" if self._firmware is not None else "unasked" if not self._fw_asked
                   else "not a firmware version this driver knows")
            (log.warning if self.stats.ignored_fw_versions == 1 else log.debug)(
                "VESC FW_VERSION %d.%02d ignored (%s)", packet.major, packet.minor, why)
            return
        log.info("VESC firmware %d.%02d, hardware %s", packet.major, packet.minor, packet.hw_name or "?")
        self._firmware = packet.version
        self._codec.firmware = packet.version
        self._fw_reply = packet
        with_imu = self.params.imu and packet.version >= IMU_SINCE
        self._polls = (GetValuesRequest(), GetImuDataRequest()) if with_imu else (GetValuesRequest(),)

    def _plausible(self, values: Values) -> bool:
        lo, hi = PLAUSIBLE_V_IN
        return (abs(values.erpm) <= self._max_erpm and lo <= values.v_in <= hi
                and abs(values.duty) <= PLAUSIBLE_DUTY)

    def _on_values(self, values: Values) -> None:
        if self._firmware is None:
            return  # a reply to a poll of the previous connection; its layout is unknown
        if not self._plausible(values):
            self.stats.implausible_telemetry += 1
            (log.warning if self.stats.implausible_telemetry == 1 else log.debug)(
                "VESC telemetry dropped: impossible values (ERPM %d, %.1f V, duty %.3f)",
                values.erpm, values.v_in, values.duty)
            return
        mono, stamp = monotonic_ns(), wall_ns()
        msg = VescStateStamped(Header(Time.from_ns(stamp), ""), values_to_state(values))
        self._last_state = msg
        self._standing = values.erpm == 0
        self.bus.publish(TOPIC_CORE, msg)
        self.odometry.update(values.erpm, self._servo_sent, mono, self._gyro_yaw_rate(mono))
        odom: Odometry = self.odometry.odometry(stamp)
        self.bus.publish(TOPIC_ODOM, odom)
        if self.params.publish_tf:
            self.bus.publish(TOPIC_TF, TFMessage([self.odometry.transform(stamp)]))

    def _gyro_yaw_rate(self, now_ns: int) -> float | None:
        """The bias-corrected gyro z rate (rad/s) for odometry, or None: use the steering model."""
        if (self.params.odometry_yaw_rate != "imu" or self._gyro_z is None or not self.gyro_bias.settled
                or now_ns - self._gyro_z_ns > self._imu_stale_ns):
            return None
        return self._gyro_z - self.gyro_bias.bias

    def _on_imu(self, data: ImuData) -> None:
        if self._firmware is None:
            return
        if not _plausible_imu(data):
            self.stats.implausible_imu += 1
            (log.warning if self.stats.implausible_imu == 1 else log.debug)(
                "VESC IMU reply dropped: beyond the sensor's full scale (gyro %s deg/s, acc %s g)",
                (data.gyro_x, data.gyro_y, data.gyro_z), (data.acc_x, data.acc_y, data.acc_z))
            return
        mono, stamp = monotonic_ns(), wall_ns()
        msg = imu_message(data, stamp, self.params.imu_frame_id, self._imu_cov)
        if not imu_provides(msg):  # no whole group (e.g. a magnetometer-only mask): nothing to say
            return
        self.stats.imu_replies += 1
        if data.gyro_z is not None:  # the bias and odometry need only z
            self._gyro_z = data.gyro_z * DEG
            self._gyro_z_ns = mono
            self.gyro_bias.update(self._gyro_z, self._standing, mono)
        self._last_imu = msg
        self.bus.publish(TOPIC_IMU, msg)


def _plausible_imu(data: ImuData) -> bool:
    """Whether every rate and acceleration the reply carries is within the sensor's full scale."""
    rates = (data.gyro_x, data.gyro_y, data.gyro_z)
    accelerations = (data.acc_x, data.acc_y, data.acc_z)
    return (all(abs(w) <= PLAUSIBLE_GYRO_DPS for w in rates if w is not None)
            and all(abs(a) <= PLAUSIBLE_ACC_G for a in accelerations if a is not None))


async def probe(port: str, baudrate: int = 115200,
                timeout_s: float = 2.0) -> tuple[FwVersion, Values | None]:
    """Ask the VESC at ``port`` for its firmware version and one telemetry sample.

    The sample is None when the firmware is not one whose telemetry layout the codec knows
    (:func:`~vesc.codec.known_firmware`): it is not asked for, rather than decoded in a layout that
    may be wrong. (The driver ignores such a FW_VERSION reply, so it would not drive this VESC.)
    Raises DeviceNotFound, DeviceIOError, or DeviceTimeout when no reply comes within ``timeout_s``.
    """
    link = open_link(port, baudrate)
    await link.open()
    codec = VescCodec(Role.HOST)
    try:
        fw = await _ask(link, codec, FwVersionRequest(), FwVersion, timeout_s)
        if not known_firmware(fw.version):
            return fw, None
        codec.firmware = fw.version
        values = await _ask(link, codec, GetValuesRequest(), Values, timeout_s)
        return fw, values
    finally:
        link.close()


async def _ask(link: Link, codec: VescCodec, request: Packet, reply_type: type[R],
               timeout_s: float) -> R:
    deadline = monotonic_ns() + nanoseconds(timeout_s)
    while monotonic_ns() < deadline:
        link.write(codec.send(request))
        resend = monotonic_ns() + nanoseconds(0.2)
        while (now := monotonic_ns()) < min(resend, deadline):
            try:
                data = await link.read_within(seconds(min(resend, deadline) - now))
            except asyncio.TimeoutError:
                break
            codec.receive_data(data)
            for packet in codec.events():
                if isinstance(packet, reply_type):
                    return packet
    raise DeviceTimeout(f"no {reply_type.__name__} reply from {link.name} within {timeout_s:g} s")
