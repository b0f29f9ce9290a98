"""The Slamtec RPLIDAR driver: one serial session at a time, scans published as LaserScans.

Session (each reconnect repeats it): STOP and discard whatever was still streaming; GET_INFO
(model, firmware, serial -> ``info``); GET_HEALTH (status 2 "protection stop" -> RESET, wait for
the banner to pass, ask again; still 2 -> DeviceError naming the code and its meaning); the scan
modes; motor start; the scan; then stream until the link fails or no scan arrives for
``params.stale_timeout_s`` (3 s allowed for the first one while the motor spins up).

Scan modes, decided as Slamtec's SDK decides: a device with the configuration commands (every C
and S series unit, A series from firmware 1.24) lists its modes through GET_LIDAR_CONF (id, name,
µs per sample, maximum distance, answer type) and names its typical one; the driver logs them and
starts ``params.scan_mode`` (by name) or else the typical mode: SCAN for a standard-node mode,
EXPRESS_SCAN with the mode's id for the rest. An older device has two modes, Standard (SCAN) and
Express (EXPRESS_SCAN mode 0, legacy capsules), timed by GET_SAMPLERATE; Express is its typical
mode (Standard only below firmware 1.17, which had no express scan).

Motor, as Slamtec's SDK drives it: A1 (model id series 1) runs while DTR is *cleared*; a port
without modem lines (a pty, some adapters) refuses DTR, which is logged once as a warning and
otherwise ignored. A2/A3 get SET_MOTOR_PWM(``params.motor_pwm``) when GET_ACC_BOARD_FLAG reports
the accessory board (without it, DTR as the A1). The S series gets SET_MOTOR_RPM with the speed
it asks for (GET_LIDAR_CONF DESIRED_ROT_FREQ). The C1 runs its motor itself (``motor:
self-driven``): the SDK asks its accessory board flag and, finding no PWM, clears DTR as for an
A1, which the C1 ignores; the driver does the same, and a port that refuses DTR is normal there
(logged at debug level only). Closing a session sends STOP and stops the motor (PWM 0, DTR
asserted).

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
    DECODED_ANSWERS,
    PACKET_LEN,
    AccBoardFlag,
    AnswerType,
    Command,
    ConfKey,
    DeviceInfo,
    Event,
    Health,
    LidarConf,
    Measurements,
    Request,
    RplidarClient,
    SampleRate,
    ScanMode,
    ScanStarted,
    supports_conf_commands,
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
#: The SDK's sample period for an A-series unit older than firmware 1.17 (no GET_SAMPLERATE).
LEGACY_SAMPLE_US = 476
#: The maximum distance the SDK gives a legacy mode (a unit without GET_LIDAR_CONF cannot say).
LEGACY_MAX_DISTANCE_M = 16.0
#: The speed the SDK sets when a device does not say which it wants.
DEFAULT_RPM = 600


class RplidarDriver(LidarDriver):
    """Streams one RPLIDAR (models a1, a2m8, a2m7, a2m12, a3, s1, c1) to ``params.topic``."""

    MALFORMED_UNIT = "packets"

    def __init__(self, bus: Bus, params: LidarParams) -> None:
        super().__init__(bus, params)
        if not params.port:
            raise ConfigError("port", "an RPLIDAR needs a serial port (e.g. /dev/ttyUSB0)")
        self.spec = rplidar_models.model(params.model)
        self.baudrate = params.baudrate or self.spec.baudrate
        self.device_info: DeviceInfo | None = None
        self.health: Health | None = None
        self.sample_rate: SampleRate | None = None
        #: the scan modes the device listed (or the legacy two), and the one streaming
        self.scan_modes: list[ScanMode] = []
        self.scan_mode: ScanMode | None = None
        self.motor = "unknown"
        self._logged_modes: tuple[ScanMode, ...] = ()
        self._link: Link | None = None
        self._client = RplidarClient()
        self._events: deque[Event] = deque()
        self._dtr_refused_logged = False
        self._typical = 0
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
        self.info = {"model": info.model_name, "model_id": f"0x{info.model_id:02X}",
                     "firmware": info.firmware}
        await self._check_health()
        conf = supports_conf_commands(info)
        if conf:
            conf = await self._listed_modes()
        if not conf:
            await self._legacy_modes(info)
        mode = self._choose_mode()
        self.scan_mode = mode
        await self._start_motor(info)
        if mode.answer_type == AnswerType.SCAN:
            self._send(Request.simple(Command.SCAN))
        else:
            self._send(Request.express_scan(mode.id if conf else 0), mode.answer_type)
        await self._wait(ScanStarted, REQUEST_TIMEOUT_S)
        self._fill_info(info, mode)
        self.connected = True
        await self._stream(mode)

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

    async def _conf(self, key: ConfKey, mode: int | None = None, size: int = 0) -> LidarConf:
        """One GET_LIDAR_CONF answer for ``key`` with at least ``size`` value bytes."""
        ans = await self._request(Request.get_lidar_conf(key, mode), LidarConf)
        if ans.key != key or len(ans.value) < size:
            raise DeviceError(f"RPLIDAR answered configuration key 0x{key:x} with key "
                              f"0x{ans.key:x} and {len(ans.value)} value bytes")
        return ans

    async def _listed_modes(self) -> bool:
        """The device's own scan-mode table; False if it does not answer after all."""
        try:
            count = (await self._conf(ConfKey.SCAN_MODE_COUNT, size=2)).number(2) or 0
        except DeviceTimeout:
            log.warning("rplidar %s: no GET_LIDAR_CONF answer from a device that should have it; "
                        "using the legacy scan commands", self.params.port)
            return False
        typical = (await self._conf(ConfKey.SCAN_MODE_TYPICAL, size=2)).number(2)
        modes = []
        for i in range(count):
            us = (await self._conf(ConfKey.SCAN_MODE_US_PER_SAMPLE, i, 4)).number(4) or 0
            dist = (await self._conf(ConfKey.SCAN_MODE_MAX_DISTANCE, i, 4)).number(4) or 0
            kind = (await self._conf(ConfKey.SCAN_MODE_ANS_TYPE, i, 1)).number(1) or 0
            name = (await self._conf(ConfKey.SCAN_MODE_NAME, i, 1)).text
            modes.append(ScanMode(i, name, us / 256, dist / 256, kind))
        if not modes:
            raise DeviceError("RPLIDAR lists no scan modes")
        self.scan_modes = modes
        self._typical = typical if any(m.id == typical for m in modes) else modes[0].id
        return True

    async def _legacy_modes(self, info: DeviceInfo) -> None:
        """Standard and (firmware 1.17+) Express, timed by GET_SAMPLERATE as the SDK times them
        (and, as there, 16 m each: the device cannot say)."""
        express = info.major >= 4 or (info.firmware_major, info.firmware_minor) >= (1, 17)
        rate = SampleRate(LEGACY_SAMPLE_US, LEGACY_SAMPLE_US)
        if express:
            try:
                rate = await self._request(Request.simple(Command.GET_SAMPLERATE), SampleRate)
            except DeviceTimeout:
                log.info("rplidar: no GET_SAMPLERATE answer; using the %s's nominal rates",
                         self.spec.name)
                rate = SampleRate(self.spec.standard_us, self.spec.express_us)
        self.sample_rate = rate
        modes = [ScanMode(0, "Standard", rate.standard_us or LEGACY_SAMPLE_US,
                          LEGACY_MAX_DISTANCE_M, AnswerType.SCAN)]
        if express:
            modes.append(ScanMode(1, "Express", rate.express_us or LEGACY_SAMPLE_US,
                                  LEGACY_MAX_DISTANCE_M, AnswerType.EXPRESS))
        self.scan_modes = modes
        self._typical = modes[-1].id

    def _choose_mode(self) -> ScanMode:
        """``params.scan_mode`` by name (any case), else the typical mode; DeviceError naming the
        device's modes if that mode is not listed or its format is not decoded here."""
        modes = self.scan_modes
        listed = "; ".join(m.describe() for m in modes)
        if tuple(modes) != self._logged_modes:
            self._logged_modes = tuple(modes)
            typical = next(m.name for m in modes if m.id == self._typical)
            log.info("rplidar %s: scan modes: %s; typical: %s", self.params.port, listed, typical)
        wanted = self.params.scan_mode
        if wanted is None:
            mode = next(m for m in modes if m.id == self._typical)
        else:
            found = [m for m in modes if m.name.lower() == wanted.lower()]
            if not found:
                raise DeviceError(f"lidar.scan_mode {wanted!r} is not a scan mode of this "
                                  f"{self.info.get('model', 'RPLIDAR')}; it has: {listed}")
            mode = found[0]
        if mode.answer_type not in DECODED_ANSWERS:
            raise DeviceError(f"scan mode {mode.name} sends {mode.answer_name} "
                              f"(0x{mode.answer_type:02x}), which racecar-hw does not decode; "
                              f"set lidar.scan_mode to another of: {listed}")
        if mode.us_per_sample <= 0:
            raise DeviceError(f"scan mode {mode.name} reports no sample period")
        return mode

    async def _start_motor(self, info: DeviceInfo) -> None:
        if rplidar_models.uses_rpm_motor_control(info.model_id):
            try:
                rpm = (await self._conf(ConfKey.DESIRED_ROT_FREQ, size=2)).number(2) or 0
            except DeviceTimeout:
                rpm = 0
            rpm = rpm or DEFAULT_RPM
            self._send(Request.set_motor_rpm(rpm))
            self.motor = f"rpm {rpm}"
            return
        if rplidar_models.uses_pwm_motor_control(info.model_id):
            try:
                flag = await self._request(Request.get_acc_board_flag(), AccBoardFlag)
            except DeviceTimeout:
                flag = AccBoardFlag(0)
            if flag.pwm_supported:
                self._send(Request.set_motor_pwm(self.params.motor_pwm))
                self.motor = f"pwm {self.params.motor_pwm}"
                return
        model_id = info.model_id
        if rplidar_models.uses_dtr_motor_control(model_id) or (
                rplidar_models.uses_pwm_motor_control(model_id)
                and not rplidar_models.has_self_driven_motor(model_id)):
            self.motor = "dtr"
        else:
            self.motor = "self-driven"
        # Like the SDK without PWM or rpm control: cleared DTR = motor runs (the C1 ignores it).
        self._set_dtr(self._link, False)

    def _set_dtr(self, link: Link | None, level: bool) -> None:
        """Set DTR; a port that refuses (a pty, an adapter without modem lines) only matters
        when DTR drives the motor: then it is logged once as a warning, else at debug level."""
        if link is None:
            return
        try:
            link.set_dtr(level)
        except DeviceIOError as err:
            if self.motor != "dtr":
                log.debug("rplidar %s: cannot set DTR (%s); the motor does not use it",
                          self.params.port, err)
            elif not self._dtr_refused_logged:
                self._dtr_refused_logged = True
                log.warning("rplidar %s: cannot set DTR (%s); the motor is left as it is "
                            "(normal for a pty or an adapter without modem lines)", self.params.port, err)

    def _fill_info(self, info: DeviceInfo, mode: ScanMode) -> None:
        health = self.health or Health(0, 0)
        period_us = mode.us_per_sample
        typical = next((m.name for m in self.scan_modes if m.id == self._typical), "")
        self.info = {
            "model": info.model_name,
            "model_id": f"0x{info.model_id:02X}",
            "firmware": info.firmware,
            "hardware": str(info.hardware),
            "serial": info.serial_hex,
            "health": f"{health.status_name} (code 0x{health.error_code:04x})",
            "sample_period_us": f"{period_us:g}",
            "baudrate": str(self.baudrate),
            "scan_mode": mode.name,
            "scan_format": f"{mode.answer_name} (0x{mode.answer_type:02x}), "
                           f"{mode.samples_per_s / 1000:.1f} k samples/s",
            "scan_modes": ", ".join(m.name + ("*" if m.name == typical else "")
                                    for m in self.scan_modes) + " (* typical)",
            "motor": self.motor,
        }

    async def _stream(self, mode: ScanMode) -> None:
        period_s = mode.us_per_sample * 1e-6
        assembler = ScanAssembler(
            range_min=self.spec.range_min, range_max=self.spec.range_max, sample_period_s=period_s,
            frame_id=self.params.frame_id, intensities=self.params.intensities,
            crop_min=self.params.angle_min, crop_max=self.params.angle_max)
        frame_s = PACKET_LEN[mode.answer_type] * BITS_PER_BYTE / self.baudrate
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
        """Take the codec's new errors into the stats; a stream that ends for want of scans names
        them (:meth:`note_malformed`)."""
        st = self._client.stats
        errors, resyncs = st.checksum_errors + st.bad_nodes, st.resyncs
        new_errors, new_resyncs = errors - self._seen[0], resyncs - self._seen[1]
        self.stats.checksum_errors += new_errors
        self.stats.resyncs += new_resyncs
        self._seen = (errors, resyncs)
        if new_errors:
            self.note_malformed("bad checksum or check bit", new_errors)
        elif new_resyncs:
            self.note_malformed("out of sync (bytes that start no packet)", new_resyncs)

    # --- link helpers --------------------------------------------------------------------------

    def _send(self, request: Request, answer: int | None = None) -> None:
        assert self._link is not None
        self._link.write(self._client.send(request, answer))

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
            if self.motor in ("dtr", "self-driven"):
                self._set_dtr(link, True)  # asserted DTR stops the A1 motor (the SDK's stop)
        link.close()
