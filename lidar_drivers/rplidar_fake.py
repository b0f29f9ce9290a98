"""A fake Slamtec RPLIDAR on a pty, speaking the real serial protocol.

Clients open ``link`` like ``/dev/ttyUSB0``. The fake answers GET_INFO, GET_HEALTH,
GET_SAMPLERATE, GET_ACC_BOARD_FLAG, SET_MOTOR_PWM, STOP, RESET (a text banner first, as the real
A series prints after a reset) and streams SCAN/FORCE_SCAN nodes or EXPRESS_SCAN capsules at
10 revolutions per second, paced by absolute deadlines so no drift accumulates.

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
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from lidar_drivers import rplidar_models
from lidar_drivers.base import RangeSource
from lidar_drivers.rplidar_codec import (
    SAMPLES_PER_CAPSULE,
    AccBoardFlag,
    Command,
    DeviceInfo,
    Health,
    Request,
    RequestParser,
    SampleRate,
    encode_acc_board_flag,
    encode_capsules,
    encode_health,
    encode_info,
    encode_nodes,
    encode_samplerate,
    encode_scan_descriptor,
)
from lidar_drivers.rplidar_models import RplidarModel
from racecar_hw.base.clock import monotonic_ns
from racecar_hw.runtime.fakepty import PtyPort

log = logging.getLogger(__name__)

SCAN_HZ = 10.0
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
                 seed: int = 0) -> None:
        self.spec = rplidar_models.model(model)
        self.range_source = range_source
        self.port = PtyPort(link)
        self.samples_per_rev_standard = round(1e6 / self.spec.standard_us / SCAN_HZ)
        self.samples_per_rev_express = round(1e6 / self.spec.express_us / SCAN_HZ)
        self.info = DeviceInfo(self.spec.model_id, self.spec.firmware[0], self.spec.firmware[1],
                               self.spec.hardware, bytes(range(0x10, 0x20)))
        self.health = Health(0, 0)
        self.health_clears_on_reset = True
        self.motor_pwm = 0
        self.scans_sent = 0
        self.requests: list[Request] = []
        self.resets = 0
        self.scanning: str | None = None  # "standard" or "express"
        self._parser = RequestParser()
        self._rng = np.random.default_rng(seed)
        self._garbage = 0
        self._corrupt = False
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
        """A1 (DTR, invisible on a pty) always runs; PWM models run once PWM is non-zero."""
        return not self.spec.pwm_motor or self.motor_pwm > 0

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
        if self.port.master_fd is not None and self._loop is not None and not self._reading:
            self._loop.add_reader(self.port.master_fd, self._on_readable)
            self._reading = True

    def _unwatch(self) -> None:
        if self._reading and self.port.master_fd is not None and self._loop is not None:
            self._loop.remove_reader(self.port.master_fd)
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
        elif cmd == Command.STOP:
            self._stop_stream()
        elif cmd == Command.RESET:
            self._stop_stream()
            self.resets += 1
            self.motor_pwm = 0
            if self.health_clears_on_reset:
                self.health = Health(0, 0)
            self._send(reset_banner(self.spec))
        elif cmd in (Command.SCAN, Command.FORCE_SCAN, Command.EXPRESS_SCAN):
            if self.health.status == 2:
                return  # protection stop: the device refuses to measure
            express = cmd == Command.EXPRESS_SCAN
            self._stop_stream()
            self._send(encode_scan_descriptor(express))
            self.scanning = "express" if express else "standard"
            assert self._loop is not None
            self._stream_task = self._loop.create_task(self._stream(express))
        # GET_LIDAR_CONF, SET_MOTOR_RPM and unknown commands get no answer.

    def _stop_stream(self) -> None:
        if self._stream_task is not None:
            self._stream_task.cancel()
            self._stream_task = None
        self.scanning = None

    # --- scan streaming ------------------------------------------------------------------------

    async def _stream(self, express: bool) -> None:
        per_rev = self.samples_per_rev_express if express else self.samples_per_rev_standard
        period_ns = round(1e9 / (per_rev * SCAN_HZ))
        t0 = monotonic_ns()
        k = 0  # next sample to send, counted from the scan request
        first = True
        while True:
            await asyncio.sleep(TICK_S)
            now = monotonic_ns()
            if not self.motor_running:
                t0, k = now, 0  # no measurements while the motor stands still
                continue
            due = (now - t0) // period_ns
            if express:
                due -= due % SAMPLES_PER_CAPSULE
            if due <= k:
                continue
            idx = np.arange(k, due, dtype=np.int64)
            theta = (idx % per_rev) * (360.0 / per_rev)
            dist_mm = self._measure(theta, t0 + idx * period_ns)
            if express:
                data = encode_capsules(theta[::SAMPLES_PER_CAPSULE], dist_mm, first=first)
                first = False
                if self._corrupt:
                    self._corrupt = False
                    data = bytes((data[0] ^ 0x01,)) + data[1:]
            else:
                start = (idx % per_rev) == 0
                quality = np.where(dist_mm > 0, QUALITY, 0)
                data = encode_nodes(start, quality, theta, dist_mm)
                if self._corrupt:
                    self._corrupt = False
                    data = data[:1] + bytes((data[1] & 0xFE,)) + data[2:]
            self.scans_sent += int(np.count_nonzero((idx % per_rev) == per_rev - 1))
            k = due
            self._send(data)

    def _measure(self, theta_deg: np.ndarray, stamps_ns: np.ndarray) -> np.ndarray:
        """Distances (mm, 0 = no return) along device angles ``theta_deg`` (clockwise)."""
        ros = np.mod(-np.radians(theta_deg) + math.pi, 2 * math.pi) - math.pi
        r = np.asarray(self.range_source.ranges(ros, int(stamps_ns[0])), dtype=np.float64)
        ok = np.isfinite(r) & (r >= self.spec.range_min) & (r <= self.spec.range_max)
        return np.where(ok, r * 1000.0, 0.0)

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
            self.motor_pwm = 0
            self._parser = RequestParser()
        self._in_loop(apply)

    def replug(self) -> None:
        """Plug it back in: a new pty at the same link; the device boots and prints its banner."""
        def apply() -> None:
            self.port.replug()
            self._watch()
            self.port.write(reset_banner(self.spec))
        self._in_loop(apply)
