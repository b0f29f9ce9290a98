"""Hokuyo lidars over SCIP 2.0: URG-04LX and UTM-30LX on USB serial; UST-10LX/20LX and
UTM-30LX-EW on Ethernet.

A thin asyncio shell around :mod:`lidar_drivers.scip`. One session: open the link; ``QT`` and
``RS`` (stop any stream left running, laser off, clock zero); ``VV`` (vendor, product, firmware,
serial -> :attr:`info`), ``PP`` (the whole scan geometry: nothing is hard-coded per model),
``II`` (device status); then ``MD`` (or ``ME`` with intensities; back to ``MD`` if the device
refuses ``ME``) streaming forever, cropped to ``angle_min``/``angle_max``, with ``cluster`` and
``skip``. Each frame becomes a ``LaserScan`` on ``params.topic``.

Scan conventions (ROS, REP-103): the angle of step ``s`` is ``(s - AFRT) * 2*pi / ARES``,
counter-clockwise, 0 straight ahead. With a cluster of ``c`` steps, beam ``i`` is at step
``start + i*c`` and ``angle_increment = c * 2*pi / ARES``. ``angle_min``/``angle_max`` are the
first and last beam. Ranges in metres; readings below DMIN are error codes: 0 and 1 ("no
object", URG-04LX "possibly beyond range") become ``inf``, every other code ``nan``; readings
beyond DMAX become ``inf``. ``time_increment`` = ``c * 60 / (SCAN * ARES)`` s, ``scan_time`` =
``(skip + 1) * 60 / SCAN`` s (time between published scans).

Stamp: the estimated time of the first beam. The device sends a frame once its last requested
step is measured, so the stamp is the arrival time (wall clock) of the frame's last byte, minus
the sweep from the first to the last beam (``(end - start) * 60 / (SCAN * ARES)``), minus the
transfer time: ``bytes * 10 / baud`` on a serial link (URG-04LX USB CDC ignores the baud, so
this overestimates there), and 0 over TCP (a frame takes under 1 ms at 100 Mbit/s). The
device's own millisecond timestamp is not used for the stamp, with one exception: when one read
returns several frames (a host that read late), only the last of them was complete at the read's
time; each earlier one is stamped from the next one's stamp less the difference of their device
timestamps (less ``scan_time`` if that difference is not between 0 and 1 s), so every scan keeps
its own stamp, earlier than the next by about a scan period (:func:`frame_stamps`).

Reconnects (the base class loop): a lost link, a reply timeout or no scan for
``max(stale_timeout_s, 3 scan periods)`` raise :class:`~racecar_hw.base.errors.DeviceError`. Status
codes other than 00/99 are logged with their meaning and kept in :attr:`last_error`; a hardware
fault (50..97) or "laser off" during streaming restarts the session.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math

import numpy as np

from lidar_drivers.base import LidarDriver, ScanGeometry
from lidar_drivers.params import HOKUYO_USB_MODELS, LidarParams
from lidar_drivers.scip import (
    ChecksumMismatch,
    Command,
    Event,
    InfoReply,
    MalformedResponse,
    Reply,
    ResponseDecoder,
    ScanCommand,
    ScanReply,
    SensorParams,
    is_hardware_fault,
)
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import NS_PER_S, monotonic, wall_ns
from racecar_hw.base.errors import ConfigError, DeviceError, DeviceTimeout, RemoteProtocolError
from racecar_hw.base.link import Link, SerialLink, TcpLink, open_link, parse_host_port
from racecar_hw.base.memlink import MemoryLink, is_memory
from racecar_hw.base.messages import Header, LaserScan, Time

log = logging.getLogger(__name__)

DEFAULT_TCP = ("192.168.0.10", 10940)
"""Factory address of Ethernet Hokuyos."""
DEFAULT_SERIAL_PORT = "/dev/ttyACM0"
SERIAL_BAUD = 115200
"""Nominal baud of a USB Hokuyo (the USB CDC link ignores it)."""
REPLY_TIMEOUT_S = 1.0
"""How long a command may take to be answered (QT may first wait for a frame in flight)."""


def crop_steps(dev: SensorParams, angle_min: float | None, angle_max: float | None) -> tuple[int, int]:
    """First and last step inside [angle_min, angle_max] (None: the device's AMIN/AMAX)."""
    start = dev.amin if angle_min is None else max(dev.amin, math.ceil(dev.step_of(angle_min) - 1e-6))
    end = dev.amax if angle_max is None else min(dev.amax, math.floor(dev.step_of(angle_max) + 1e-6))
    if start > end:
        raise ConfigError("lidar.angle_min", f"no step between angle_min {angle_min} and "
                          f"angle_max {angle_max} (device covers {dev.angle_of(dev.amin):.3f}.."
                          f"{dev.angle_of(dev.amax):.3f} rad)")
    return start, end


def scan_geometry(dev: SensorParams, req: ScanCommand) -> ScanGeometry:
    """The LaserScan geometry of frames answering ``req``."""
    cluster = max(req.cluster, 1)
    inc = cluster * 2.0 * math.pi / dev.ares
    first = dev.angle_of(req.start)
    return ScanGeometry(angle_min=first, angle_max=first + (req.values - 1) * inc,
                        angle_increment=inc, range_min=dev.dmin / 1000.0,
                        range_max=dev.dmax / 1000.0,
                        scan_time=(req.interval + 1) * dev.scan_period_s,
                        time_increment=cluster * dev.step_time_s)


DEVICE_CLOCK_MODULUS_MS = 1 << 24
"""The device timestamp is a 24-bit millisecond counter."""
MAX_DEVICE_GAP_MS = 1000
"""A device-clock gap between two frames of one read that is taken as true (else: ``scan_time``)."""


def frame_stamps(frames: list[ScanReply], last_ns: int, scan_time_s: float) -> list[int]:
    """Stamps (ns) of ``frames``, decoded from one read in arrival order, given the last one's.

    Only the last frame was complete when the read returned: each earlier one precedes the next
    by the difference of their device timestamps (the frames' sweep starts, 1 ms resolution; a
    frame lost between them counts), or by ``scan_time_s`` when that difference is not in
    ``(0, MAX_DEVICE_GAP_MS]``. So the stamps strictly increase, about a scan period apart.
    """
    stamps = [last_ns] * len(frames)
    for i in range(len(frames) - 2, -1, -1):
        gap_ms = (frames[i + 1].timestamp_ms - frames[i].timestamp_ms) % DEVICE_CLOCK_MODULUS_MS
        if 0 < gap_ms <= MAX_DEVICE_GAP_MS:
            gap_ns = gap_ms * 1_000_000
        else:
            gap_ns = round(scan_time_s * NS_PER_S)
        stamps[i] = stamps[i + 1] - gap_ns
    return stamps


_NO_INTENSITIES = np.zeros(0, dtype=np.float32)
_NO_INTENSITIES.flags.writeable = False


@functools.lru_cache(maxsize=8)
def _cached_geometry(dev: SensorParams, req: ScanCommand) -> ScanGeometry:
    return scan_geometry(dev, req)


def ranges_m(dev: SensorParams, distances: np.ndarray) -> np.ndarray:
    """Device readings (mm or error codes) as metres with the inf/nan policy (float32).

    ``d * 0.001`` rounds to the same float32 as ``d / 1000`` for every whole ``d``, and uses an
    operation the scan path needs anyway (see :func:`lidar_drivers.scip.decode_data_lines`).
    """
    d = np.asarray(distances, dtype=np.float64)
    r = d * 0.001
    r[d > dev.dmax] = np.inf
    r[d < dev.dmin] = np.nan
    r[d < min(dev.dmin, 2)] = np.inf  # codes 0 and 1: no object (URG-04LX: possibly beyond range)
    return r.astype(np.float32)


class HokuyoDriver(LidarDriver):
    """A Hokuyo lidar speaking SCIP 2.0 over serial (``params.port``) or TCP (``params.tcp``)."""

    def __init__(self, bus: Bus, params: LidarParams) -> None:
        super().__init__(bus, params)
        self.device: SensorParams | None = None
        self.request: ScanCommand | None = None
        self._link: Link | None = None
        self._decoder = ResponseDecoder()
        self._rx_wall_ns = 0
        self._baud = params.baudrate or SERIAL_BAUD

    # --- link ---------------------------------------------------------------------------------

    def _make_link(self) -> Link:
        p = self.params
        if p.tcp and is_memory(p.tcp):  # a simulation in lockstep: stands for the Ethernet link
            return MemoryLink(p.tcp, is_serial=False)
        if p.tcp:
            try:
                host, port = parse_host_port(p.tcp, DEFAULT_TCP[1])
            except ValueError as err:
                raise ConfigError("lidar.tcp", str(err)) from err
            return TcpLink(host, port)
        if p.port:
            return open_link(p.port, self._baud)
        if p.model in HOKUYO_USB_MODELS:
            return SerialLink(DEFAULT_SERIAL_PORT, self._baud)
        return TcpLink(*DEFAULT_TCP)

    @property
    def serial(self) -> bool:
        """Whether the link is a serial port (the transfer time then counts in the stamp)."""
        return self._link is not None and self._link.is_serial

    async def _close(self) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        if link.is_open:
            try:
                link.write(Command("QT").encode())  # stop streaming, laser off
            except DeviceError:
                pass
        link.close()

    # --- events -------------------------------------------------------------------------------

    async def _next_event(self, deadline: float, what: str) -> Event:
        """The next event from the device, or DeviceTimeout at ``deadline`` (monotonic s)."""
        assert self._link is not None
        while True:
            event = self._decoder.next_event()
            if event is not None:
                self._count(event)
                return event
            remaining = deadline - monotonic()
            if remaining <= 0:
                raise DeviceTimeout(f"{self._link.name}: {what}")
            try:
                data = await self._link.read_within(remaining)
            except asyncio.TimeoutError:
                raise DeviceTimeout(f"{self._link.name}: {what}") from None
            self._receive(data)

    def _receive(self, data: bytes) -> None:
        """Stamp a chunk's arrival and hand it to the decoder."""
        self._stamp_rx()
        self._rx_wall_ns = wall_ns()
        self.stats.bytes_in += len(data)
        self._decoder.receive_data(data)

    def _count(self, event: Event) -> None:
        """Count a damaged reply; a stream that ends for want of scans names the last one's reason
        (:meth:`note_malformed`), each one is logged at DEBUG only."""
        if isinstance(event, ChecksumMismatch):
            self.stats.checksum_errors += 1
            self.note_malformed(f"checksum mismatch ({event.reason})")
            log.debug("lidar: %s", event.reason)
        elif isinstance(event, MalformedResponse):
            self.stats.resyncs += 1
            self.note_malformed(event.reason)
            log.debug("lidar: dropped %d bytes: %s", len(event.raw), event.reason)

    async def _request(self, cmd: Command, timeout: float = REPLY_TIMEOUT_S) -> Reply:
        """Send ``cmd`` and return its reply, skipping stale frames and noise."""
        assert self._link is not None
        self._link.write(cmd.encode())
        deadline = monotonic() + timeout
        while True:
            event = await self._next_event(deadline, f"no reply to {cmd.line}")
            if isinstance(event, Reply) and event.echo == cmd.line:
                if not event.ok:
                    self._note_status(event)
                return event

    def _note_status(self, reply: Reply) -> None:
        message = f"{reply.command} status {reply.status}: {reply.meaning}"
        if self.last_error != message:
            log.warning("lidar %s: %s", self.params.model, message)
        self.last_error = message

    async def _info(self, name: str) -> dict[str, str]:
        reply = await self._request(Command(name))
        if not isinstance(reply, InfoReply):
            raise DeviceError(f"{name} refused: status {reply.status} ({reply.meaning})")
        return dict(reply.fields)

    # --- session ------------------------------------------------------------------------------

    async def _session(self) -> None:
        self._decoder = ResponseDecoder()
        self._link = self._make_link()
        await self._link.open()
        if not await self._quiet():
            # a classic URG-04LX boots speaking SCIP 1.1: switch it, then stop it again
            log.info("lidar %s: the device speaks SCIP 1.1; switching it to SCIP 2.0",
                     self.params.model)
            self._link.write(b"SCIP2.0\n")
            await asyncio.sleep(0.1)
            await self._request(Command("QT"), 2 * REPLY_TIMEOUT_S)
        await self._request(Command("RS"))
        vv = await self._info("VV")
        pp = await self._info("PP")
        ii = await self._info("II")
        try:
            dev = SensorParams.from_fields(pp)
        except RemoteProtocolError as err:
            raise DeviceError(str(err)) from err
        self.device = dev
        self.info = {"vendor": vv.get("VEND", ""), "product": vv.get("PROD", ""),
                     "firmware": vv.get("FIRM", ""), "protocol": vv.get("PROT", ""),
                     "serial": vv.get("SERI", ""), "model": dev.model,
                     "status": ii.get("STAT", "")}
        log.info("lidar %s: %s %s firmware %s serial %s", self.params.model, self.info["vendor"],
                 self.info["product"], self.info["firmware"], self.info["serial"])
        req = await self._start_stream(dev)
        self.request = req
        self.geometry = scan_geometry(dev, req)
        self.connected = True
        await self._stream(dev, req)

    async def _quiet(self) -> bool:
        """QT: stop any stream a previous client left running. False if the device answers in
        SCIP 1.1 (``QT``, ``E``: urg_c's test) or not at all (it may be in SCIP 1.1 anyway)."""
        assert self._link is not None
        self._link.write(Command("QT").encode())
        deadline = monotonic() + 2 * REPLY_TIMEOUT_S
        while True:
            try:
                event = await self._next_event(deadline, "no reply to QT")
            except DeviceTimeout:
                return False
            if isinstance(event, Reply) and event.echo == "QT":
                return event.status != "E"
            if isinstance(event, MalformedResponse) and event.raw.split(b"\n")[-2:] == [b"QT", b"E"]:
                return False

    async def _start_stream(self, dev: SensorParams) -> ScanCommand:
        p = self.params
        start, end = crop_steps(dev, p.angle_min, p.angle_max)
        kinds = ("ME", "MD") if p.intensities else ("MD",)
        for kind in kinds:
            req = ScanCommand(name=kind, start=start, end=end, cluster=p.cluster, interval=p.skip,
                              count=0)
            ack = await self._request(req)
            if ack.status == "00":
                return req
            if kind == "ME":
                log.warning("lidar %s: ME refused (%s); streaming without intensities",
                            p.model, ack.meaning)
        raise DeviceError(f"MD refused: status {ack.status} ({ack.meaning})")

    async def _stream(self, dev: SensorParams, req: ScanCommand) -> None:
        """Publish frames from the link's reader callback until the stream ends (always raises)."""
        assert self._link is not None
        period = (req.interval + 1) * dev.scan_period_s
        stale = max(self.params.stale_timeout_s, 3 * period)
        echo_body = req.echo(0)[:-2]

        def is_scan(event: Event) -> bool:
            return (isinstance(event, ScanReply) and event.status == "99"
                    and event.echo.startswith(echo_body))

        def on_event(event: Event, stamps: dict[int, int]) -> None:
            self._count(event)
            if not isinstance(event, Reply) or not event.echo.startswith(echo_body):
                return
            if isinstance(event, ScanReply):
                if event.status == "99":
                    self.publish(self.to_laser_scan(event, dev, stamps[id(event)]))
                return
            if event.ok:
                return
            self._note_status(event)
            if is_hardware_fault(event.status) or event.status == "10":
                self._end_stream(DeviceError(f"{event.command} status {event.status}: "
                                             f"{event.meaning}"))

        def drain() -> None:  # first: the frames read with the acknowledgement
            # decode the whole read before publishing: only its last frame ends at the read's time
            events = list(iter(self._decoder.next_event, None))
            frames = [e for e in events if is_scan(e)]
            stamps: dict[int, int] = {}
            if frames:
                last_ns = self.first_beam_ns(frames[-1], dev)
                times = frame_stamps(frames, last_ns, period)
                stamps = {id(f): t for f, t in zip(frames, times, strict=True)}
            for event in events:
                on_event(event, stamps)

        def on_bytes(data: bytes) -> None:
            self._receive(data)
            drain()

        await self._stream_from(self._link, on_bytes, lambda: stale, drain)

    def first_beam_ns(self, frame: ScanReply, dev: SensorParams) -> int:
        """The first beam's estimated time (wall ns) of ``frame``, the last one the latest read
        completed: the read's time less the sweep from the first to the last beam and the
        transfer time."""
        req = frame.request
        sweep_s = (req.end - req.start) * dev.step_time_s
        transfer_s = frame.nbytes * 10.0 / self._baud if self.serial else 0.0
        return self._rx_wall_ns - round((sweep_s + transfer_s) * NS_PER_S)

    def to_laser_scan(self, frame: ScanReply, dev: SensorParams, stamp_ns: int | None = None
                      ) -> LaserScan:
        """One frame as a LaserScan stamped ``stamp_ns``, its first beam's estimated time (default:
        :meth:`first_beam_ns`, right for the last frame of a read; see :func:`frame_stamps`)."""
        geo = _cached_geometry(dev, frame.request)
        stamp = self.first_beam_ns(frame, dev) if stamp_ns is None else stamp_ns
        intensities = (frame.intensities.astype(np.float32) if frame.intensities is not None
                       else _NO_INTENSITIES)
        return LaserScan(
            header=Header(stamp=Time.from_ns(stamp), frame_id=self.params.frame_id),
            angle_min=geo.angle_min, angle_max=geo.angle_max, angle_increment=geo.angle_increment,
            time_increment=geo.time_increment, scan_time=geo.scan_time,
            range_min=geo.range_min, range_max=geo.range_max,
            ranges=ranges_m(dev, frame.distances), intensities=intensities)
