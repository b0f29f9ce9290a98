"""A fake VESC speaking the real protocol over a pty, with a simple motor and battery model.

Run :meth:`FakeVesc.serve` in a :class:`~racecar_hw.runtime.devicethread.DeviceThread` (its own loop); any
client opens :attr:`FakeVesc.path` like ``/dev/ttyACM0``. The fake decodes requests with the same
:class:`~vesc.codec.VescCodec` as the driver (device role) and replies in the GET_VALUES layout of
its firmware version.

Model (integrated every ``tick_s``):

- SET_RPM: the ERPM follows the set point, changing at most ``accel_erpm_s`` ERPM/s.
- SET_DUTY: the set point is ``duty * erpm_per_volt * v_in``, same acceleration limit.
- SET_CURRENT: acceleration ``current * erpm_s_per_amp`` minus friction.
- SET_CURRENT_BRAKE: deceleration towards 0 at ``current * erpm_s_per_amp``.
- SET_POS: holds the rotor (ERPM set point 0).
- Released (firmware timeout, or brake current 0): the motor coasts down at ``coast_erpm_s``.
- The firmware command timeout (``timeout_s``, 1 s as shipped): with no SET_*/ALIVE command for
  that long the motor is released and status bit 0 is set; servo positions are kept.
- Battery: ``v_in = battery_v - battery_resistance_ohm * input_current``; input current is motor
  current times duty. Charge and energy are integrated. The tachometer counts 6 steps per
  electrical revolution.
- COMM_GET_IMU_DATA (firmware 3.52 and later): :attr:`FakeVesc.imu`, an
  :class:`~vesc.imu_model.ImuModel` fed the car's motion by the simulation (at rest otherwise).
- :meth:`stall` holds the wheels (after a collision): ERPM stays 0 whatever is commanded, and a
  driven motor draws ``stall_current_a``.

Read-only properties (``erpm``, ``servo``, ``commands``, counters) are safe from any thread; so are
the fault injections (``inject_garbage``, ``inject_reply``, ``corrupt_next_crc``, ``split_replies``,
``mute``, ``stop_reading``, ``unplug``, ``replug``), which run in the device loop.
"""

from __future__ import annotations

import asyncio
import math
import random
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from racecar_hw.base.clock import NS_PER_S, monotonic_ns, seconds
from racecar_hw.runtime.fakepty import port_for
from racecar_hw.runtime.ticker import PeriodicTimer
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
    SetCurrent,
    SetCurrentBrake,
    SetDuty,
    SetPosition,
    SetRpm,
    SetServoPosition,
    Values,
    VescCodec,
)
from vesc.imu_model import ImuModel

T = TypeVar("T")

STATUS_TIMEOUT = 0x01
STATUS_KILL_SWITCH = 0x02


@dataclass(frozen=True)
class CommandRecord:
    """A packet the fake decoded, when its bytes were read (monotonic ns) and its frame number.

    ``seq`` counts the frames decoded since the fake was made, from 1: with no frame lost on the
    wire it is the client's own count of frames written (the driver's ``stats.frames_tx``).
    """

    t_ns: int
    packet: Packet
    seq: int = 0


@dataclass
class MotorState:
    """The motor model's state, owned by the device loop."""

    mode: str = "released"  #: released, rpm, duty, current, brake, pos
    setpoint: float = 0.0
    erpm: float = 0.0
    current_motor: float = 0.0
    current_input: float = 0.0
    duty: float = 0.0
    v_in: float = 0.0
    amp_hours: float = 0.0
    amp_hours_charged: float = 0.0
    watt_hours: float = 0.0
    watt_hours_charged: float = 0.0
    tach: float = 0.0
    tach_abs: float = 0.0
    servo: float = 0.5
    status: int = 0


class FakeVesc:
    """A VESC at ``link`` (a symlink to a pty; None: only the pty's own path)."""

    def __init__(self, link: str | None, firmware: tuple[int, int] = (6, 2), *,
                 hw_name: str = "60", accel_erpm_s: float = 30000.0, erpm_per_volt: float = 3000.0,
                 erpm_s_per_amp: float = 2000.0, coast_erpm_s: float = 4000.0,
                 friction_current_a: float = 1.0, stall_current_a: float = 60.0,
                 battery_v: float = 16.8, battery_resistance_ohm: float = 0.05,
                 timeout_s: float = 1.0, tick_s: float = 0.005, log_size: int = 20000,
                 seed: int = 0, imu: ImuModel | None = None) -> None:
        self.firmware = firmware
        #: the on-board IMU (firmware 3.52 and later answer COMM_GET_IMU_DATA); by default at rest:
        #: the simulation sets its ``motion`` to the world's
        self.imu = imu if imu is not None else ImuModel(seed=seed)
        self.hw_name = hw_name
        self.accel_erpm_s = accel_erpm_s
        self.erpm_per_volt = erpm_per_volt
        self.erpm_s_per_amp = erpm_s_per_amp
        self.coast_erpm_s = coast_erpm_s
        self.friction_current_a = friction_current_a
        self.stall_current_a = stall_current_a
        self.battery_v = battery_v
        self.battery_resistance_ohm = battery_resistance_ohm
        self.timeout_s = timeout_s
        self.tick_s = tick_s
        self.port = port_for(link)
        self._codec = VescCodec(Role.DEVICE, firmware)
        self._state = MotorState(v_in=battery_v)
        self._lock = threading.Lock()
        self._log: deque[CommandRecord] = deque(maxlen=log_size)
        self._rng = random.Random(seed)
        self._uuid = bytes(self._rng.randrange(256) for _ in range(12))
        self._loop: asyncio.AbstractEventLoop | None = None
        #: replies waiting to be written (by a loop callback, in the pass after the first of them
        #: was queued: where a writer task woken by it would write them), with whether to split
        self._pending: deque[tuple[bytes, bool]] = deque()
        self._serving: object | None = None  # while serve() runs: its token (writes of another end)
        self._writing = False  # a write of the pending replies is scheduled or waits mid-reply
        self._stalled = False
        self._muted = False
        self._split = False
        self._corrupt_next = False
        self._last_reset_ns = monotonic_ns()
        self._motor_ns = self._last_reset_ns  # monotonic ns of the motor model's last step
        self._reading = False
        #: set while :meth:`serve` answers on the port; unplug and replug wait for it in tests
        self.ready = threading.Event()
        self.frames_rx = 0
        self.frames_tx = 0

    # --- lifecycle ----------------------------------------------------------------------------

    @property
    def path(self) -> str:
        """What a client opens: the symlink, or the pty slave when there is no link."""
        return self.port.path

    def open(self) -> FakeVesc:
        """Create the pty (and symlink) now, before :meth:`serve` runs. Returns self."""
        if not self.port.plugged:
            self.port.open()
        return self

    async def serve(self, motor_timer: bool = True) -> None:
        """Answer requests and run the motor model until cancelled; removes the pty on exit.

        ``motor_timer``: the motor model steps every ``tick_s`` on a loop timer of its own. False:
        the caller calls :meth:`step_motor` instead (the lockstep simulation, from the world's
        step on the same grid: one timer for both).
        """
        self._loop = asyncio.get_running_loop()
        self._serving = object()
        self.open()
        self._attach()
        self._motor_ns = monotonic_ns()

        failed: asyncio.Future[None] = self._loop.create_future()
        # a loop timer on the tick's grid, not a sleeping task (cheaper, and in step with the world)
        motor = PeriodicTimer(1.0 / self.tick_s, lambda _due, _periods: self.step_motor(monotonic_ns()),
                              on_error=lambda err: failed.done() or failed.set_exception(err))
        if motor_timer:
            motor.start()
        self.ready.set()
        try:
            await failed
        finally:
            self.ready.clear()
            motor.cancel()
            self._serving = None  # what was not written yet never will be
            self._pending.clear()
            self._writing = False
            self._detach()
            self.port.close()
            self._loop = None

    @property
    def tick_ns(self) -> int:
        """The motor model's step (ns): the period of its timer."""
        return round(NS_PER_S / (1.0 / self.tick_s))  # as the timer's rate gives it

    def step_motor(self, now_ns: int) -> None:
        """Step the motor model from its last step to monotonic ``now_ns`` (what its timer does
        every ``tick_s``; call it from the device loop)."""
        self._step(seconds(now_ns - self._motor_ns), now_ns)
        self._motor_ns = now_ns

    # --- what the world simulation and tests read ---------------------------------------------

    @property
    def erpm(self) -> float:
        """The motor's actual electrical RPM now."""
        with self._lock:
            return self._state.erpm

    @property
    def servo(self) -> float:
        """The last servo position received, 0..1."""
        with self._lock:
            return self._state.servo

    @property
    def status(self) -> int:
        """GET_VALUES status bits (bit 0: command timeout active)."""
        with self._lock:
            return self._state.status

    @property
    def timed_out(self) -> bool:
        """Whether the firmware command timeout has released the motor."""
        return bool(self.status & STATUS_TIMEOUT)

    @property
    def mode(self) -> str:
        """The motor control mode: released, rpm, duty, current, brake or pos."""
        with self._lock:
            return self._state.mode

    @property
    def commands(self) -> list[CommandRecord]:
        """Every decoded packet (bounded log, oldest first) with its arrival time."""
        with self._lock:
            return list(self._log)

    def clear_commands(self) -> None:
        """Empty the command log."""
        with self._lock:
            self._log.clear()

    @property
    def crc_errors(self) -> int:
        """Frames from the client that failed the CRC check."""
        return self._codec.stats.crc_errors

    def stall(self) -> None:
        """Hold the wheels (a collision): ERPM is 0 until :meth:`unstall`."""
        with self._lock:
            self._stalled = True
            self._state.erpm = 0.0

    def unstall(self) -> None:
        """Free the wheels again."""
        with self._lock:
            self._stalled = False

    # --- fault injection ----------------------------------------------------------------------

    def inject_garbage(self, n: int) -> None:
        """Send ``n`` random bytes to the client between replies."""
        data = bytes(self._rng.randrange(256) for _ in range(n))
        self._in_loop(lambda: self._enqueue(data, False))

    def inject_reply(self, packet: FwVersion | Values | RawPacket) -> None:
        """Send ``packet`` unasked, between replies: a stray FW_VERSION mid-session, impossible
        telemetry, or any payload (a :class:`~vesc.codec.RawPacket`; ``RawPacket(bytes(3))`` is
        the all-zero frame that line noise passes the CRC with, read as FW_VERSION 0.0)."""
        data = self._codec.send(packet)
        self._in_loop(lambda: self._enqueue(data, False))

    def corrupt_next_crc(self) -> None:
        """Send the next reply with a wrong CRC."""
        with self._lock:
            self._corrupt_next = True

    def split_replies(self, on: bool) -> None:
        """Send each reply in two writes a few milliseconds apart (or not)."""
        with self._lock:
            self._split = on

    def mute(self, on: bool) -> None:
        """Stop answering (a firmware that hung with its USB port still there): commands are still
        read and obeyed, no reply is sent; or answer again."""
        with self._lock:
            self._muted = on

    def stop_reading(self, on: bool) -> None:
        """Stop reading the port (a device that takes no more data: the host's writes back up in the
        OS buffer), or read again."""
        self._in_loop(self._detach if on else self._attach)

    def unplug(self) -> None:
        """Pull the USB cable: the pty and its symlink disappear. The motor model keeps running."""
        self._in_loop(self._unplug)

    def replug(self) -> None:
        """Plug the cable back in: a new pty at the same link."""
        self._in_loop(self._replug)

    @property
    def plugged(self) -> bool:
        """Whether the pty exists."""
        return self.port.plugged

    # --- internals ----------------------------------------------------------------------------

    def _in_loop(self, fn: Callable[[], T]) -> T:
        loop = self._loop
        if loop is None or not loop.is_running():
            return fn()
        try:
            if asyncio.get_running_loop() is loop:
                return fn()
        except RuntimeError:
            pass

        async def call() -> T:
            return fn()

        return asyncio.run_coroutine_threadsafe(call(), loop).result(10)

    def _attach(self) -> None:
        if self._loop is not None and self.port.plugged and not self._reading:
            self.port.watch(self._loop, self._on_readable)
            self._reading = True

    def _detach(self) -> None:
        if self._reading:
            self.port.unwatch()
        self._reading = False

    def _unplug(self) -> None:
        self._detach()
        self.port.unplug()
        self._codec.reset()

    def _replug(self) -> None:
        self._detach()
        self.port.replug()
        self._codec.reset()
        self._attach()

    def _on_readable(self) -> None:
        data = self.port.read()
        if not data:
            return
        now = monotonic_ns()
        self._codec.receive_data(data)
        for packet in self._codec.events():
            self.frames_rx += 1
            with self._lock:
                self._log.append(CommandRecord(now, packet, self.frames_rx))
            self._handle(packet, now)

    def _handle(self, packet: Packet, now: int) -> None:
        if isinstance(packet, TIMEOUT_RESETTING):
            self._last_reset_ns = now
            with self._lock:
                self._state.status &= ~STATUS_TIMEOUT
        if isinstance(packet, FwVersionRequest):
            self._reply(self._fw_version())
        elif isinstance(packet, GetValuesRequest):
            self._reply(self._values())
        elif isinstance(packet, GetImuDataRequest):
            if self.firmware >= IMU_SINCE:  # older firmware does not know the command: no answer
                self._reply(self.imu.sample(seconds(now), packet.mask))
        elif isinstance(packet, SetServoPosition):
            with self._lock:
                self._state.servo = min(max(packet.position, 0.0), 1.0)
        elif isinstance(packet, Alive):
            pass
        else:
            self._set_motor(packet)

    def _set_motor(self, packet: Packet) -> None:
        with self._lock:
            s = self._state
            if isinstance(packet, SetRpm):
                s.mode, s.setpoint = "rpm", float(packet.erpm)
            elif isinstance(packet, SetDuty):
                s.mode, s.setpoint = "duty", packet.duty
            elif isinstance(packet, SetCurrent):
                s.mode, s.setpoint = "current", packet.current
            elif isinstance(packet, SetCurrentBrake):
                s.mode, s.setpoint = "brake", abs(packet.current)
            elif isinstance(packet, SetPosition):
                s.mode, s.setpoint = "pos", packet.degrees

    def _step(self, dt: float, now: int) -> None:
        if dt <= 0.0:
            return
        timed_out = self.timeout_s > 0 and seconds(now - self._last_reset_ns) > self.timeout_s
        with self._lock:
            s = self._state
            if timed_out and not s.status & STATUS_TIMEOUT:
                s.status |= STATUS_TIMEOUT
                s.mode, s.setpoint = "released", 0.0
            before = s.erpm
            target_current = self._advance(s, dt)
            accel = (s.erpm - before) / dt
            if self._stalled:
                s.erpm = 0.0
                driven = s.mode in ("rpm", "duty", "current") and abs(target_current) > 0.0
                s.current_motor = math.copysign(self.stall_current_a, target_current) if driven else 0.0
            else:
                friction = self.friction_current_a * _sign(s.erpm)
                s.current_motor = accel / self.erpm_s_per_amp + friction
            erpm_full = max(self.erpm_per_volt * s.v_in, 1.0)
            s.duty = max(-1.0, min(1.0, s.erpm / erpm_full))
            s.current_input = s.current_motor * abs(s.duty)
            s.v_in = self.battery_v - self.battery_resistance_ohm * s.current_input
            hours = dt / 3600.0
            if s.current_input >= 0:
                s.amp_hours += s.current_input * hours
                s.watt_hours += s.current_input * s.v_in * hours
            else:
                s.amp_hours_charged -= s.current_input * hours
                s.watt_hours_charged -= s.current_input * s.v_in * hours
            steps = s.erpm / 60.0 * 6.0 * dt
            s.tach += steps
            s.tach_abs += abs(steps)

    def _advance(self, s: MotorState, dt: float) -> float:
        """Move ``s.erpm`` one tick; returns the sign-carrying drive effort (for stall current)."""
        max_step = self.accel_erpm_s * dt
        if s.mode in ("rpm", "duty", "pos"):
            if s.mode == "rpm":
                target = s.setpoint
            elif s.mode == "duty":
                target = s.setpoint * self.erpm_per_volt * s.v_in
            else:
                target = 0.0
            s.erpm += max(-max_step, min(max_step, target - s.erpm))
            return target
        if s.mode == "current":
            accel = s.setpoint * self.erpm_s_per_amp - self.coast_erpm_s * _sign(s.erpm)
            limit = self.erpm_per_volt * s.v_in
            s.erpm = max(-limit, min(limit, s.erpm + accel * dt))
            return s.setpoint
        rate = s.setpoint * self.erpm_s_per_amp if s.mode == "brake" else 0.0
        decel = (rate + self.coast_erpm_s) * dt
        s.erpm = 0.0 if abs(s.erpm) <= decel else s.erpm - math.copysign(decel, s.erpm)
        return 0.0

    def _fw_version(self) -> FwVersion:
        fw = self.firmware
        if fw < (3, 7):
            return FwVersion(fw[0], fw[1])
        if fw < (3, 9):
            return FwVersion(fw[0], fw[1], self.hw_name)
        extra = bytearray()
        if fw >= (3, 48):
            extra += b"\x00"  # pairing_done
        if fw >= (5, 0):
            extra += b"\x00"  # FW_TEST_VERSION_NUMBER
        if fw >= (5, 2):
            extra += b"\x00\x00"  # HW_TYPE_VESC, custom config count
        if fw >= (5, 3):
            extra += b"\x00\x00\x00"  # phase filters, QML in hardware, QML in app
        if fw >= (6, 0):
            extra += b"\x00racecar-fake\x00"  # nrf_flags, firmware name
        if fw >= (6, 5):
            extra += b"\x12\x34\x56\x78"  # hardware CRC
        return FwVersion(fw[0], fw[1], self.hw_name, self._uuid, bytes(extra))

    def _values(self) -> Values:
        with self._lock:
            s = self._state
            return Values(
                temp_fet=31.5, temp_motor=28.0, current_motor=_bounded(s.current_motor, 2e7),
                current_input=_bounded(s.current_input, 2e7), avg_id=0.0,
                avg_iq=_bounded(s.current_motor, 2e7), duty=s.duty, erpm=round(s.erpm),
                v_in=_bounded(s.v_in, 3000.0), amp_hours=s.amp_hours,
                amp_hours_charged=s.amp_hours_charged, watt_hours=s.watt_hours,
                watt_hours_charged=s.watt_hours_charged, tachometer=round(s.tach),
                tachometer_abs=round(s.tach_abs), fault=0, pid_pos=0.0, controller_id=0,
                temp_mos1=31.5, temp_mos2=31.0, temp_mos3=30.5, avg_vd=0.0,
                avg_vq=_bounded(s.duty * s.v_in, 2e6), status=s.status, temp_pcb=30.0)

    def _reply(self, packet: FwVersion | Values | ImuData) -> None:
        data = self._codec.send(packet)
        with self._lock:
            if self._muted:
                return
            corrupt, self._corrupt_next = self._corrupt_next, False
            split = self._split
        if corrupt:
            data = data[:-3] + bytes([data[-3] ^ 0xFF]) + data[-2:]
        self.frames_tx += 1
        self._enqueue(data, split)

    def _enqueue(self, data: bytes, split: bool) -> None:
        loop, token = self._loop, self._serving
        if loop is None or token is None:
            self.port.write(data)
            return
        self._pending.append((data, split))
        if not self._writing:
            self._writing = True
            loop.call_soon(self._write_pending, token)

    def _write_pending(self, token: object) -> None:
        """Write the pending replies in order; a split one in two halves 3 ms apart, the replies
        after it after its second half. (What a writer task awaiting a queue would do, in the same
        passes of the loop, without a task's wake-up per reply.)"""
        if token is not self._serving:
            return
        pending, loop = self._pending, self._loop
        assert loop is not None
        while pending:
            data, split = pending.popleft()
            if split and len(data) > 1:
                cut = len(data) // 2
                self.port.write(data[:cut])
                loop.call_later(0.003, loop.call_soon, self._write_rest, token, data[cut:])
                return
            self.port.write(data)
        self._writing = False

    def _write_rest(self, token: object, rest: bytes) -> None:
        if token is self._serving:
            self.port.write(rest)
            self._write_pending(token)

    def __repr__(self) -> str:
        return f"FakeVesc({self.path!r}, firmware={self.firmware})"


def _sign(x: float) -> float:
    return 0.0 if x == 0 else math.copysign(1.0, x)


def _bounded(x: float, limit: float) -> float:
    return max(-limit, min(limit, x))
