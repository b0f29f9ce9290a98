"""The Slamtec RPLIDAR driver: one serial session at a time, scans published as LaserScans.

Session (each reconnect repeats it): STOP and discard whatever was still streaming; GET_INFO
(model, firmware, serial -> ``info``); GET_HEALTH (status 2 "protection stop" -> RESET, wait for
the banner to pass, ask again; still 2 -> DeviceError naming the code and its meaning);
GET_SAMPLERATE (sample period -> beam timing); motor start; SCAN or EXPRESS_SCAN
(``params.scan_mode``); then stream until the link fails or no scan arrives for
``params.stale_timeout_s`` (3 s allowed for the first one while the motor spins up).

Motor: A1 (model id series 1) runs while DTR is *cleared*; a port without modem lines (a pty,
some adapters) refuses DTR, which is logged once and otherwise ignored. A2/A3 get
SET_MOTOR_PWM(``params.motor_pwm``) when GET_ACC_BOARD_FLAG reports the accessory board. S1 and C1
spin by themselves. Closing a session sends STOP and stops the motor (PWM 0, DTR asserted).

Scan conventions (counter-clockwise fixed grid, negative ``time_increment``): see
:mod:`lidar_drivers.rplidar_scan`. Stamps are wall-clock ns: the arrival time of the bytes minus
their transfer time at the baud rate, minus the samples the express decoder still holds back.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from typing import TypeVar

from lidar_drivers import rplidar_models
from lidar_drivers.base import LidarDriver
from lidar_drivers.params import LidarParams
from lidar_drivers.rplidar_codec import (
    CAPSULE_LEN,
    NODE_LEN,
    AccBoardFlag,
    Command,
    DeviceInfo,
    Event,
    Health,
    Measurements,
    Request,
    RplidarClient,
    SampleRate,
    ScanStarted,
)
from lidar_drivers.rplidar_scan import ScanAssembler
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic_ns, wall_ns
from racecar_hw.base.errors import ConfigError, DeviceError, DeviceIOError, DeviceTimeout
from racecar_hw.base.link import Link, open_link

log = logging.getLogger(__name__)

E = TypeVar("E")

#: Every request is answered well within this (the SDK allows 2 s).
REQUEST_TIMEOUT_S = 1.0
#: After STOP, bytes already on their way are read and dropped for this long.
STOP_SETTLE_S = 0.05
#: After RESET the device reboots and prints its banner.
RESET_SETTLE_S = 0.5
#: The first scan may take this long (motor spin-up).
STARTUP_TIMEOUT_S = 3.0
BITS_PER_BYTE = 10  # 8N1


class RplidarDriver(LidarDriver):
    """Streams one RPLIDAR (models a1, a2m8, a2m7, a2m12, a3, s1, c1) to ``params.topic``."""

    def __init__(self, bus: Bus, params: LidarParams) -> None:
        super().__init__(bus, params)
        if not params.port:
            raise ConfigError("port", "an RPLIDAR needs a serial port (e.g. /dev/ttyUSB0)")
        self.spec = rplidar_models.model(params.model)
        self.baudrate = params.baudrate or self.spec.baudrate
        self.device_info: DeviceInfo | None = None
        self.health: Health | None = None
        self.sample_rate: SampleRate | None = None
        self.motor = "unknown"
        self._link: Link | None = None
        self._client = RplidarClient()
        self._events: deque[Event] = deque()
        self._dtr_refused_logged = False
        self._seen = (0, 0)  # (checksum errors + bad nodes, resyncs) already in self.stats

    # --- session -------------------------------------------------------------------------------

    async def _session(self) -> None:
        assert self.params.port is not None
        self._client = RplidarClient()
        self._seen = (0, 0)
        self._events.clear()
        link = open_link(self.params.port, self.baudrate)
        self._link = link
        await link.open()
        self._send(Request.simple(Command.STOP))
        await self._settle(STOP_SETTLE_S)
        info = await self._request(Request.simple(Command.GET_INFO), DeviceInfo)
        self.device_info = info
        await self._check_health()
        period_us = await self._sample_period_us()
        await self._start_motor(info)
        express = self.params.scan_mode == "express"
        self._send(Request.express_scan() if express else Request.simple(Command.SCAN))
        await self._wait(ScanStarted, REQUEST_TIMEOUT_S)
        self._fill_info(info, period_us)
        self.connected = True
        await self._stream(express, period_us * 1e-6)

    async def _check_health(self) -> None:
        health = await self._request(Request.simple(Command.GET_HEALTH), Health)
        if health.status == 2:
            log.warning("rplidar %s: health error 0x%04x (%s); resetting the device",
                        self.params.port, health.error_code, health.meaning)
            self._send(Request.simple(Command.RESET))
            await self._settle(RESET_SETTLE_S)
            health = await self._request(Request.simple(Command.GET_HEALTH), Health)
            if health.status == 2:
                self.health = health
                raise DeviceError(f"RPLIDAR health error, code 0x{health.error_code:04x}: "
                                  f"{health.meaning}; a reset did not clear it")
        elif health.status == 1:
            log.warning("rplidar %s: health warning 0x%04x (%s)", self.params.port,
                        health.error_code, health.meaning)
        self.health = health

    async def _sample_period_us(self) -> float:
        express = self.params.scan_mode == "express"
        try:
            rate = await self._request(Request.simple(Command.GET_SAMPLERATE), SampleRate)
        except DeviceTimeout:
            log.info("rplidar: no GET_SAMPLERATE answer; using the %s's nominal rate", self.spec.name)
            rate = SampleRate(self.spec.standard_us, self.spec.express_us)
        self.sample_rate = rate
        period = rate.express_us if express else rate.standard_us
        return float(period if period > 0 else (self.spec.express_us if express else self.spec.standard_us))

    async def _start_motor(self, info: DeviceInfo) -> None:
        if rplidar_models.uses_pwm_motor_control(info.model_id):
            try:
                flag = await self._request(Request.get_acc_board_flag(), AccBoardFlag)
            except DeviceTimeout:
                flag = AccBoardFlag(0)
            if flag.pwm_supported:
                self._send(Request.set_motor_pwm(self.params.motor_pwm))
                self.motor = f"pwm {self.params.motor_pwm}"
                return
        if rplidar_models.uses_dtr_motor_control(info.model_id) or \
                rplidar_models.uses_pwm_motor_control(info.model_id):
            self.motor = "dtr"
            self._set_dtr(self._link, False)  # cleared DTR = motor runs
        else:
            self.motor = "self-driven"

    def _set_dtr(self, link: Link | None, level: bool) -> None:
        if link is None:
            return
        try:
            link.set_dtr(level)
        except DeviceIOError as err:
            if not self._dtr_refused_logged:
                self._dtr_refused_logged = True
                log.warning("rplidar %s: cannot set DTR (%s); the motor is left as it is "
                            "(normal for a pty or an adapter without modem lines)", self.params.port, err)

    def _fill_info(self, info: DeviceInfo, period_us: float) -> None:
        health = self.health or Health(0, 0)
        self.info = {
            "model": info.model_name,
            "model_id": f"0x{info.model_id:02X}",
            "firmware": info.firmware,
            "hardware": str(info.hardware),
            "serial": info.serial_hex,
            "health": f"{health.status_name} (code 0x{health.error_code:04x})",
            "sample_period_us": f"{period_us:g}",
            "baudrate": str(self.baudrate),
            "scan_mode": self.params.scan_mode,
            "motor": self.motor,
        }

    async def _stream(self, express: bool, period_s: float) -> None:
        assembler = ScanAssembler(
            range_min=self.spec.range_min, range_max=self.spec.range_max, sample_period_s=period_s,
            frame_id=self.params.frame_id, intensities=self.params.intensities,
            crop_min=self.params.angle_min, crop_max=self.params.angle_max)
        frame_s = (CAPSULE_LEN if express else NODE_LEN) * BITS_PER_BYTE / self.baudrate
        byte_s = BITS_PER_BYTE / self.baudrate
        timeout = [STARTUP_TIMEOUT_S]  # until the first scan, then stale_timeout_s

        def add(m: Measurements, arrival_ns: int) -> None:
            if self._add(assembler, m, arrival_ns, frame_s, byte_s, period_s):
                timeout[0] = self.params.stale_timeout_s

        def backlog() -> None:  # samples that came with the scan descriptor
            events = self._events
            while events:
                ev = events.popleft()
                if isinstance(ev, Measurements):
                    add(ev, wall_ns())

        def on_bytes(chunk: bytes) -> None:
            self._stamp_rx()
            arrival = wall_ns()
            self._client.receive_data(chunk)
            self.stats.bytes_in += len(chunk)
            while (ev := self._client.next_event()) is not None:
                if isinstance(ev, Measurements):
                    add(ev, arrival)
            self._account()

        assert self._link is not None
        await self._stream_from(self._link, on_bytes, lambda: timeout[0], backlog)

    def _add(self, assembler: ScanAssembler, m: Measurements, arrival_ns: int, frame_s: float,
             byte_s: float, period_s: float) -> bool:
        in_flight_s = frame_s + self._client.buffered * byte_s + m.held_back * period_s
        published = False
        for scan in assembler.add(m, arrival_ns - round(in_flight_s * 1e9)):
            self.geometry = assembler.geometry
            self.publish(scan)
            published = True
        return published

    def _account(self) -> None:
        st = self._client.stats
        errors, resyncs = st.checksum_errors + st.bad_nodes, st.resyncs
        self.stats.checksum_errors += errors - self._seen[0]
        self.stats.resyncs += resyncs - self._seen[1]
        self._seen = (errors, resyncs)

    # --- link helpers --------------------------------------------------------------------------

    def _send(self, request: Request) -> None:
        assert self._link is not None
        self._link.write(self._client.send(request))

    async def _read(self, timeout_s: float) -> bytes:
        """At least one byte within ``timeout_s`` or DeviceTimeout.

        Not ``asyncio.wait_for``: before Python 3.12 it can swallow a cancellation that arrives
        while the read completes, and a driver streaming without pause would then never stop.
        """
        assert self._link is not None
        read = asyncio.ensure_future(self._link.read())
        try:
            done, _ = await asyncio.wait({read}, timeout=max(timeout_s, 0.001))
        except asyncio.CancelledError:
            read.cancel()
            raise
        if not done:
            read.cancel()
            raise DeviceTimeout(f"RPLIDAR at {self.params.port} sent nothing for {timeout_s:.2f} s")
        return read.result()

    async def _settle(self, seconds: float) -> None:
        """Read and drop everything for ``seconds`` (stale stream data, the reset banner)."""
        end = monotonic_ns() + round(seconds * 1e9)
        while (left := (end - monotonic_ns()) * 1e-9) > 0:
            with contextlib.suppress(DeviceTimeout):
                chunk = await self._read(left)
                self.stats.bytes_in += len(chunk)
                self._client.receive_data(chunk)
        self._client.events()
        self._events.clear()

    async def _wait(self, kind: type[E], timeout_s: float) -> E:
        end = monotonic_ns() + round(timeout_s * 1e9)
        while True:
            while (ev := self._client.next_event()) is not None:
                if isinstance(ev, kind):
                    self._events.extend(self._client.events())
                    return ev
            left = (end - monotonic_ns()) * 1e-9
            if left <= 0:
                raise DeviceTimeout(f"RPLIDAR at {self.params.port}: no {kind.__name__} answer "
                                    f"within {timeout_s:.1f} s (wrong baud rate? expected {self.baudrate})")
            chunk = await self._read(left)
            self.stats.bytes_in += len(chunk)
            self._client.receive_data(chunk)

    async def _request(self, request: Request, kind: type[E]) -> E:
        self._send(request)
        return await self._wait(kind, REQUEST_TIMEOUT_S)

    async def _close(self) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        if link.is_open:
            with contextlib.suppress(DeviceError):
                link.write(Request.simple(Command.STOP).encode())
                if self.motor.startswith("pwm"):
                    link.write(Request.set_motor_pwm(0).encode())
            if self.motor == "dtr":
                self._set_dtr(link, True)  # asserted DTR stops the A1 motor
        link.close()
