"""A fake Slamtec RPLIDAR on a pty, speaking the real serial protocol.

Clients open ``link`` like ``/dev/ttyUSB0``. The fake answers GET_INFO, GET_HEALTH,
GET_SAMPLERATE, GET_ACC_BOARD_FLAG, GET_LIDAR_CONF (the scan modes its model lists at its
firmware, from :mod:`lidar_drivers.rplidar_models`, its typical mode, desired motor speed and,
where the model has it, the motor's speed range MIN_ROT_FREQ / MAX_ROT_FREQ), SET_MOTOR_PWM,
SET_MOTOR_RPM, STOP, RESET (a text banner first, as the real A series prints after a reset) and
streams SCAN/FORCE_SCAN nodes, or EXPRESS_SCAN in any scan mode it lists (legacy express, ultra or
dense capsules), at 10 revolutions per second (S series: the rpm it was given / 60), paced by
absolute deadlines so no drift accumulates.

Firmware: the fake lists the scan-mode table of the firmware it reports (the A1 has an older,
three-mode one). Told to report firmware older than 1.24 (A series) it behaves like such a unit:
GET_LIDAR_CONF gets no answer, and EXPRESS_SCAN streams legacy express capsules whatever working
mode it names. C and S series units always have the configuration commands (as the SDK assumes).

Ultra capsules carry rotor angles; a sample's beam trails its rotor angle by the distance-dependent
lag the SDK corrects for (:func:`lidar_drivers.rplidar_capsules.ultra_beam_lag_deg`), so the
fake measures each ultra sample along ``rotor angle - lag`` (found by fixed-point iteration).

Angle conventions: the range source is asked in ROS angles (radians, counter-clockwise, 0 ahead);
the device reports clockwise degrees. Sample ``k`` of a revolution of ``M`` sits at device angle
``θ = 360·k/M`` and is measured along ROS angle ``-θ`` (normalised), so the driver's conversion
``ros = -device`` recovers the source's geometry.

Like the real A2/A3, models with a PWM-driven motor (accessory board flag set) only measure once
the host has set a non-zero PWM. A pty has no modem lines, so DTR (the A1 motor) is not observable:
the A1 motor always runs.

Fault injection (call from any thread): :meth:`inject_garbage`, :meth:`corrupt_next_checksum`,
:meth:`split_writes`, :meth:`unplug` / :meth:`replug`, :meth:`reboot`, :meth:`set_health`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import struct
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from lidar_drivers import rplidar_capsules, rplidar_models
from lidar_drivers.base import RangeSource
from lidar_drivers.rplidar_codec import (
    DECODED_ANSWERS,
    AccBoardFlag,
    AnswerType,
    Command,
    ConfKey,
    DeviceInfo,
    Health,
    Request,
    RequestParser,
    SampleRate,
    ScanMode,
    encode_acc_board_flag,
    encode_capsules,
    encode_health,
    encode_info,
    encode_lidar_conf,
    encode_nodes,
    encode_samplerate,
    encode_scan_descriptor,
    parse_conf_request,
    supports_conf_commands,
)
from lidar_drivers.rplidar_models import RplidarModel
from racecar_hw.base.clock import monotonic_ns
from racecar_hw.runtime.fakepty import port_for

log = logging.getLogger(__name__)

SCAN_HZ = 10.0
#: Legacy express capsules carry 14 bits of mm.
LEGACY_CAPSULE_MAX_M = 16.383
#: A first guess of an ultra sample's beam lag (degrees), refined per sample.
ULTRA_MEAN_LAG_DEG = 7.5
#: How often the streaming task wakes up to send the samples measured since the last wake-up.
TICK_S = 0.01
QUALITY = 47


def reset_banner(spec: RplidarModel) -> bytes:
    """The text an A-series unit prints after a reset or power-on (before any binary data)."""
    major, minor = spec.firmware
    return (f"RP LIDAR System.\r\nFirmware Ver {major}.{minor:02d} - rtm, HW Ver {spec.hardware}\r\n"
            f"Model: {spec.model_id:02X}\r\n").encode()


class FakeRplidar:
    """A fake RPLIDAR ``model`` measuring ``range_source``, on a pty reachable at ``link``."""

    def __init__(self, model: str, range_source: RangeSource, link: str | None = None,
                 seed: int = 0, firmware: tuple[int, int] | None = None) -> None:
        base = rplidar_models.model(model)
        #: the model as a unit with this firmware reports it (its scan-mode table)
        self.spec = base.for_firmware(firmware or base.firmware)
        self.range_source = range_source
        self.port = port_for(link)
        major, minor = self.spec.firmware
        self.info = DeviceInfo(self.spec.model_id, major, minor, self.spec.hardware,
                               bytes(range(0x10, 0x20)))
        #: whether GET_LIDAR_CONF is answered (as the SDK decides it from model and firmware)
        self.conf_commands = supports_conf_commands(self.info)
        self.scan_hz = SCAN_HZ
        self.motor_rpm: int | None = None  # the last SET_MOTOR_RPM
        #: the scan mode being streamed (a legacy express scan reports the Express row)
        self.mode: ScanMode | None = None
        self.health = Health(0, 0)
        self.health_clears_on_reset = True
        self.motor_pwm = 0
        self.scans_sent = 0
        self.requests: list[Request] = []
        self.resets = 0
        self.scanning: str | None = None  # "standard" or "express" (any capsule format)
        self._parser = RequestParser()
        self._rng = np.random.default_rng(seed)
        self._garbage = 0
        self._corrupt = False
        self._corrupt_all = False
        self._split = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._stream_task: asyncio.Task[None] | None = None
        self._out: asyncio.Queue[bytes] | None = None
        self._reading = False

    @property
    def link(self) -> str:
        """The path clients open."""
        return self.port.path

    @property
    def motor_running(self) -> bool:
        """A1 (DTR, invisible on a pty) always runs; PWM models run once PWM is non-zero; S-series
        models run unless told 0 rpm."""
        if self.spec.pwm_motor:
            return self.motor_pwm > 0
        return self.motor_rpm != 0

    def samples_per_rev(self, mode: ScanMode) -> int:
        """Samples in one revolution of ``mode`` at the current rotation speed."""
        return round(mode.samples_per_s / self.scan_hz)

    @property
    def samples_per_rev_standard(self) -> int:
        """Samples per revolution of a SCAN."""
        return self.samples_per_rev(self._legacy_mode(express=False))

    @property
    def samples_per_rev_express(self) -> int:
        """Samples per revolution of a legacy EXPRESS_SCAN (working mode 0)."""
        return self.samples_per_rev(self._legacy_mode(express=True))

    def _legacy_mode(self, express: bool) -> ScanMode:
        kind = AnswerType.EXPRESS if express else AnswerType.SCAN
        found = next((m for m in self.spec.modes if m.answer_type == kind), None)
        if found is not None:
            return found
        us = self.spec.express_us if express else self.spec.standard_us
        return ScanMode(1 if express else 0, "Express" if express else "Standard", us,
                        self.spec.range_max, kind)

    # --- life cycle ----------------------------------------------------------------------------

    async def serve(self) -> None:
        """Run the device until cancelled (inside a DeviceThread)."""
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._out = asyncio.Queue()
        if not self.port.plugged:
            self.port.open()
        self._watch()
        writer = asyncio.create_task(self._writer())
        try:
            await asyncio.Event().wait()
        finally:
            writer.cancel()
            self._stop_stream()
            self._unwatch()
            self.port.close()

    def _watch(self) -> None:
        if self.port.plugged and self._loop is not None and not self._reading:
            self.port.watch(self._loop, self._on_readable)
            self._reading = True

    def _unwatch(self) -> None:
        if self._reading:
            self.port.unwatch()
        self._reading = False

    def _on_readable(self) -> None:
        data = self.port.read()
        if not data:
            return
        for req in self._parser.receive_data(data):
            self.requests.append(req)
            self._handle(req)

    # --- requests ------------------------------------------------------------------------------

    def _handle(self, req: Request) -> None:
        cmd = req.command
        if cmd == Command.GET_INFO:
            self._send(encode_info(self.info))
        elif cmd == Command.GET_HEALTH:
            self._send(encode_health(self.health))
        elif cmd == Command.GET_SAMPLERATE:
            self._send(encode_samplerate(SampleRate(self.spec.standard_us, self.spec.express_us)))
        elif cmd == Command.GET_ACC_BOARD_FLAG:
            self._send(encode_acc_board_flag(AccBoardFlag(int(self.spec.pwm_motor))))
        elif cmd == Command.SET_MOTOR_PWM and len(req.payload) == 2:
            self.motor_pwm = int.from_bytes(req.payload, "little")
        elif cmd == Command.SET_MOTOR_RPM and len(req.payload) == 2:
            if rplidar_models.uses_rpm_motor_control(self.spec.model_id):
                self.motor_rpm = int.from_bytes(req.payload, "little")
                if self.motor_rpm:
                    self.scan_hz = self.motor_rpm / 60.0  # the next scan turns at this speed
        elif cmd == Command.GET_LIDAR_CONF:
            self._answer_conf(req)
        elif cmd == Command.STOP:
            self._stop_stream()
        elif cmd == Command.RESET:
            self._stop_stream()
            self.resets += 1
            self.motor_pwm, self.motor_rpm, self.scan_hz = 0, None, SCAN_HZ
            if self.health_clears_on_reset:
                self.health = Health(0, 0)
            self._send(reset_banner(self.spec))
        elif cmd in (Command.SCAN, Command.FORCE_SCAN, Command.EXPRESS_SCAN):
            if self.health.status == 2:
                return  # protection stop: the device refuses to measure
            mode = self._scan_mode(req)
            if mode is None:
                return  # a working mode the device does not list: no answer
            self._stop_stream()
            self._send(encode_scan_descriptor(True, mode.answer_type))
            self.scanning = "standard" if mode.answer_type == AnswerType.SCAN else "express"
            self.mode = mode
            assert self._loop is not None
            self._stream_task = self._loop.create_task(self._stream(mode))
        # unknown commands (and GET_LIDAR_CONF on an old firmware) get no answer.

    def _scan_mode(self, req: Request) -> ScanMode | None:
        """The mode a scan request starts: SCAN -> Standard, EXPRESS_SCAN working mode 0 (or any
        mode on an old firmware) -> legacy Express, else the listed mode with that id."""
        if req.command != Command.EXPRESS_SCAN:
            return self._legacy_mode(express=False)
        working = req.payload[0] if req.payload else 0
        if working == 0 or not self.conf_commands:
            return self._legacy_mode(express=True)
        mode = self.spec.mode(working)
        if mode is None or mode.answer_type not in DECODED_ANSWERS or \
                mode.answer_type == AnswerType.SCAN:
            return None
        return mode

    def _answer_conf(self, req: Request) -> None:
        """GET_LIDAR_CONF: the scan mode table, the desired motor speed and (models that have
        them) the motor's speed range in rpm; unknown keys, modes and old firmware get no
        answer."""
        parsed = parse_conf_request(req)
        if not self.conf_commands or parsed is None:
            return
        key, mode_id = parsed
        spec = self.spec
        value: bytes | None = None
        if key == ConfKey.SCAN_MODE_COUNT:
            value = struct.pack("<H", len(spec.modes))
        elif key == ConfKey.SCAN_MODE_TYPICAL:
            value = struct.pack("<H", spec.typical)
        elif key == ConfKey.DESIRED_ROT_FREQ:
            value = struct.pack("<HH", spec.desired_rpm, spec.desired_pwm)
        elif key in (ConfKey.MIN_ROT_FREQ, ConfKey.MAX_ROT_FREQ) and spec.rot_freq_range:
            value = struct.pack("<H", spec.rot_freq_range[key == ConfKey.MAX_ROT_FREQ])
        elif mode_id is not None and (mode := spec.mode(mode_id)) is not None:
            if key == ConfKey.SCAN_MODE_US_PER_SAMPLE:
                value = struct.pack("<I", round(mode.us_per_sample * 256))
            elif key == ConfKey.SCAN_MODE_MAX_DISTANCE:
                value = struct.pack("<I", round(mode.max_distance_m * 256))
            elif key == ConfKey.SCAN_MODE_ANS_TYPE:
                value = bytes((mode.answer_type,))
            elif key == ConfKey.SCAN_MODE_NAME:
                value = mode.name.encode("ascii") + b"\0"
        if value is not None:
            self._send(encode_lidar_conf(key, value))

    def _stop_stream(self) -> None:
        if self._stream_task is not None:
            self._stream_task.cancel()
            self._stream_task = None
        self.scanning = None
        self.mode = None

    # --- scan streaming ------------------------------------------------------------------------

    async def _stream(self, mode: ScanMode) -> None:
        kind = mode.answer_type
        per_rev = self.samples_per_rev(mode)
        group = DECODED_ANSWERS[kind]  # samples per packet
        period_ns = round(1e9 / (per_rev * self.scan_hz))
        step = 360.0 / per_rev
        # Ultra samples sit half a step off the grid, as a real rotor's do: the SDK finds a
        # revolution's start from the interpolated angles, which miss a capsule starting at 0.000.
        phase = 0.5 if kind == AnswerType.ULTRA_CAPSULED else 0.0
        t0 = monotonic_ns()
        k = 0  # next sample to send, counted from the scan request
        first = True
        lookahead: float | None = None  # ultra: the next capsule's first distance, already sent
        while True:
            await asyncio.sleep(TICK_S)
            now = monotonic_ns()
            if not self.motor_running:
                t0, k = now, 0  # no measurements while the motor stands still
                continue
            due = (now - t0) // period_ns
            due -= due % group
            if due <= k:
                continue
            idx = np.arange(k, due + (kind == AnswerType.ULTRA_CAPSULED), dtype=np.int64)
            theta = (idx % per_rev + phase) * step
            stamps = t0 + idx * period_ns
            if kind == AnswerType.ULTRA_CAPSULED:
                dist_mm = self._measure_ultra(theta, stamps, mode)
                if lookahead is not None:
                    dist_mm[0] = lookahead
                lookahead = float(dist_mm[-1])
                data = rplidar_capsules.encode_ultra(theta[:-1:group], dist_mm[:-1], lookahead,
                                                     first=first)
                idx = idx[:-1]
            else:
                dist_mm = self._measure(theta, stamps, mode)
                data = self._encode(kind, idx % per_rev == 0, theta, dist_mm, group, first)
            first = False
            if self._corrupt or self._corrupt_all:
                self._corrupt = False
                if kind == AnswerType.SCAN:  # the check bit of the first node
                    data = data[:1] + bytes((data[1] & 0xFE,)) + data[2:]
                else:  # a capsule's checksum
                    data = bytes((data[0] ^ 0x01,)) + data[1:]
            self.scans_sent += int(np.count_nonzero((idx % per_rev) == per_rev - 1))
            k = due
            self._send(data)

    @staticmethod
    def _encode(kind: int, start: np.ndarray, theta: np.ndarray, dist_mm: np.ndarray, group: int,
                first: bool) -> bytes:
        if kind == AnswerType.SCAN:
            return encode_nodes(start, np.where(dist_mm > 0, QUALITY, 0), theta, dist_mm)
        if kind == AnswerType.EXPRESS:
            return encode_capsules(theta[::group], dist_mm, first=first)
        return rplidar_capsules.encode_dense(theta[::group], dist_mm, first=first)

    def _measure(self, theta_deg: np.ndarray, stamps_ns: np.ndarray, mode: ScanMode) -> np.ndarray:
        """Distances (mm, 0 = no return) along device angles ``theta_deg`` (clockwise)."""
        ros = np.mod(-np.radians(theta_deg) + math.pi, 2 * math.pi) - math.pi
        r = np.asarray(self.range_source.ranges(ros, int(stamps_ns[0])), dtype=np.float64)
        limit = min(self.spec.range_max, mode.max_distance_m)
        if mode.answer_type == AnswerType.EXPRESS:
            limit = min(limit, LEGACY_CAPSULE_MAX_M)
        ok = np.isfinite(r) & (r >= self.spec.range_min) & (r <= limit)
        return np.where(ok, r * 1000.0, 0.0)

    def _measure_ultra(self, rotor_deg: np.ndarray, stamps_ns: np.ndarray,
                       mode: ScanMode) -> np.ndarray:
        """Ultra samples: each beam trails its rotor angle by a lag that depends on the distance
        it measures; a few fixed-point steps find the distance consistent with its own lag."""
        dist = self._measure(rotor_deg - ULTRA_MEAN_LAG_DEG, stamps_ns, mode)
        for _ in range(3):
            dist = self._measure(rotor_deg - rplidar_capsules.ultra_beam_lag_deg(dist), stamps_ns,
                                 mode)
        return np.minimum(dist, rplidar_capsules.ULTRA_MAX_MM)

    # --- output --------------------------------------------------------------------------------

    def _send(self, data: bytes) -> None:
        if self._garbage:
            data = self._rng.integers(0, 256, self._garbage, dtype=np.uint8).tobytes() + data
            self._garbage = 0
        assert self._out is not None
        self._out.put_nowait(data)

    async def _writer(self) -> None:
        assert self._out is not None
        while True:
            data = await self._out.get()
            if not self._split:
                self.port.write(data)
                continue
            i = 0
            while i < len(data):
                n = int(self._rng.integers(1, 17))
                self.port.write(data[i: i + n])
                i += n
                await asyncio.sleep(0.0002)

    # --- fault injection (thread-safe) ---------------------------------------------------------

    def _in_loop(self, fn: Callable[[], Any]) -> Any:
        if self._loop is None or self._loop_thread == threading.get_ident():
            return fn()
        done: concurrent.futures.Future[Any] = concurrent.futures.Future()

        def call() -> None:
            try:
                done.set_result(fn())
            except BaseException as err:  # noqa: BLE001 - handed to the calling thread
                done.set_exception(err)

        self._loop.call_soon_threadsafe(call)
        return done.result(10)

    def inject_garbage(self, n: int) -> None:
        """Put ``n`` random bytes before the next thing the device sends."""
        def apply() -> None:
            self._garbage += n
        self._in_loop(apply)

    def corrupt_next_checksum(self) -> None:
        """Break the next capsule's checksum (express) or the next node's check bit (standard)."""
        def apply() -> None:
            self._corrupt = True
        self._in_loop(apply)

    def corrupt_checksums(self, on: bool) -> None:
        """Break every capsule's checksum or node's check bit (as :meth:`corrupt_next_checksum`)
        until turned off."""
        def apply() -> None:
            self._corrupt_all = on
        self._in_loop(apply)

    def split_writes(self, on: bool) -> None:
        """Write everything in random pieces of 1..16 bytes with short pauses between them."""
        def apply() -> None:
            self._split = on
        self._in_loop(apply)

    def set_health(self, status: int, error_code: int = 0, clears_on_reset: bool = True) -> None:
        """What GET_HEALTH reports; with status 2 the device refuses to scan until a reset clears it."""
        def apply() -> None:
            self.health = Health(status, error_code)
            self.health_clears_on_reset = clears_on_reset
        self._in_loop(apply)

    def reboot(self) -> None:
        """The device resets by itself (brown-out): scanning stops, the banner is printed."""
        self._in_loop(lambda: self._handle(Request(Command.RESET)))

    def unplug(self) -> None:
        """Pull the USB cable: the pty and its symlink disappear, the device loses power."""
        def apply() -> None:
            self._stop_stream()
            self._unwatch()
            self.port.unplug()
            self.motor_pwm, self.motor_rpm, self.scan_hz = 0, None, SCAN_HZ
            self._parser = RequestParser()
        self._in_loop(apply)

    def replug(self) -> None:
        """Plug it back in: a new pty at the same link; the device boots and prints its banner."""
        def apply() -> None:
            self.port.replug()
            self._watch()
            self.port.write(reset_banner(self.spec))
        self._in_loop(apply)
