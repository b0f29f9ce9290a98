"""What every lidar shares: scan geometry, range sources for fakes, statistics, scan summaries.

Conventions (ROS sensor_msgs/LaserScan, REP-103): angles in radians, counter-clockwise seen from
above, 0 straight ahead along the laser frame's x axis; ranges in metres.

Invalid-reading policy, the same for every driver: a reading the device flags as an error (Hokuyo
codes below DMIN, RPLIDAR distance 0 or quality 0) becomes ``inf`` when it means "no return within
range" and ``nan`` when the device reports a fault for that beam; readings beyond ``range_max``
become ``inf``. Consumers treat both as "no obstacle seen on this beam"; the safety controller
additionally refuses a scan whose valid beams are too few (see safety/).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from abc import abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lidar_drivers.params import LidarParams
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import monotonic, monotonic_ns
from racecar_hw.base.errors import DeviceError, DeviceIOError, DeviceTimeout
from racecar_hw.base.link import Link
from racecar_hw.base.messages import LaserScan
from racecar_hw.runtime.reconnect import ReconnectingDevice

log = logging.getLogger(__name__)


def beam_count(angle_min: float, angle_max: float, angle_increment: float) -> int:
    """Beams from the first at ``angle_min`` to the last at ``angle_max``, both included."""
    return round((angle_max - angle_min) / angle_increment) + 1


@dataclass(frozen=True)
class ScanGeometry:
    """One sweep's geometry as a device reports it, in ROS conventions.

    ``angle_min``/``angle_max`` are the first and last beam (rad, CCW), ``scan_time`` the sweep
    period (s), ``time_increment`` the time between beams (s), ranges in metres.
    """

    angle_min: float
    angle_max: float
    angle_increment: float
    range_min: float
    range_max: float
    scan_time: float
    time_increment: float

    @property
    def beams(self) -> int:
        """Number of beams in a sweep."""
        return beam_count(self.angle_min, self.angle_max, self.angle_increment)

    def angles(self) -> np.ndarray:
        """The angle of every beam, radians."""
        return self.angle_min + self.angle_increment * np.arange(self.beams)


class RangeSource(Protocol):
    """What a fake lidar measures: the world simulation, a fixed room, random ranges.

    ``ranges(angles, stamp_ns)`` returns the true distance in metres along each angle (radians,
    CCW, laser frame) at time ``stamp_ns`` (monotonic ns), ``inf`` where nothing is in reach. It is
    called from the fake device's thread and must not block.
    """

    def ranges(self, angles: np.ndarray, stamp_ns: int) -> np.ndarray: ...


class RoomRangeSource:
    """A laser at (``x``, ``y``, heading ``yaw``) inside an axis-aligned rectangular room."""

    def __init__(self, width: float = 8.0, depth: float = 6.0, x: float | None = None,
                 y: float | None = None, yaw: float = 0.0) -> None:
        self.width, self.depth = width, depth
        self.x = width / 2 if x is None else x
        self.y = depth / 2 if y is None else y
        self.yaw = yaw

    def ranges(self, angles: np.ndarray, stamp_ns: int = 0) -> np.ndarray:
        a = np.asarray(angles, dtype=np.float64) + self.yaw
        c, s = np.cos(a), np.sin(a)
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = np.where(c > 0, (self.width - self.x) / c, np.where(c < 0, -self.x / c, np.inf))
            ty = np.where(s > 0, (self.depth - self.y) / s, np.where(s < 0, -self.y / s, np.inf))
        return np.minimum(tx, ty)


class RandomRangeSource:
    """The seeds' fake scan: every range uniform in [``low``, ``high``) metres."""

    def __init__(self, low: float = 1.0, high: float = 10.0, seed: int | None = None) -> None:
        self.low, self.high = low, high
        self._rng = np.random.default_rng(seed)

    def ranges(self, angles: np.ndarray, stamp_ns: int = 0) -> np.ndarray:
        return self._rng.uniform(self.low, self.high, size=len(angles))


@dataclass
class LidarStats:
    """Link statistics every lidar driver keeps and publishes."""

    scans: int = 0
    bytes_in: int = 0
    checksum_errors: int = 0
    resyncs: int = 0
    reconnects: int = 0
    device_errors: int = 0


@dataclass(frozen=True)
class ScanSummary:
    """The seeds' scan_range and open space: closest and farthest valid return with their angles."""

    closest: float
    closest_angle: float
    farthest: float
    farthest_angle: float
    valid_beams: int


def summarize(scan: LaserScan) -> ScanSummary:
    """Closest and farthest finite return within [range_min, range_max]; nan fields if none."""
    r = np.asarray(scan.ranges, dtype=np.float64)
    range_min, range_max = float(scan.range_min), float(scan.range_max)
    valid = (r >= range_min) & (r <= range_max)
    if not (math.isfinite(range_min) and math.isfinite(range_max)):
        valid &= np.isfinite(r)  # finite bounds already exclude inf and nan
    n = int(np.count_nonzero(valid))
    if n == 0:
        return ScanSummary(math.nan, math.nan, math.nan, math.nan, 0)
    # invalid beams masked by values no valid one can tie: argmin/argmax find the first extreme
    lo = int(np.argmin(np.where(valid, r, np.inf)))
    hi = int(np.argmax(np.where(valid, r, -np.inf)))
    return ScanSummary(float(r[lo]), float(scan.angle_min + scan.angle_increment * lo),
                       float(r[hi]), float(scan.angle_min + scan.angle_increment * hi), n)


#: A lost session whose cause repeats is logged again at most this often (s); :attr:`last_error`
#: (the status panel, the link reminders) has every one.
REPEAT_LOG_S = 60.0


class NoScan(DeviceTimeout):
    """No scan for the stale timeout. ``key`` says what the loss is without its counts and, for
    malformed data, without the timeout (log lines repeat by it): when the device sent malformed
    data meanwhile, the text names it ("the last 12 replies were malformed: 540 readings, expected
    1081")."""

    def __init__(self, text: str, key: str) -> None:
        super().__init__(text)
        self.key = key


class LidarDriver(ReconnectingDevice):
    """One lidar: connect, configure, stream scans to the bus, reconnect forever.

    Subclasses implement :meth:`_session`, one connection's life: open the link, read the
    device's geometry, stream, and return or raise :class:`~racecar_hw.base.errors.DeviceError` when the
    link is lost. :meth:`run` is :class:`~racecar_hw.runtime.reconnect.ReconnectingDevice`'s
    reconnect loop: the lidar proves itself by streaming, so every session is followed by the
    backoff, which doubles after each failed session.
    """

    OPEN_PROVES_DEVICE = False
    #: what the device's malformed data is counted in, for :class:`NoScan`'s text
    MALFORMED_UNIT = "replies"

    def __init__(self, bus: Bus, params: LidarParams) -> None:
        super().__init__(params.reconnect_backoff_min_s, params.reconnect_backoff_max_s)
        self.bus = bus
        self.params = params
        self.stats = LidarStats()
        self.geometry: ScanGeometry | None = None
        self.info: dict[str, str] = {}
        self.connected = False
        self._attempted = False  # a session was attempted before: the next one is a reconnect
        #: monotonic ns when the latest read from the device returned (see :meth:`_stamp_rx`)
        self.rx_ns = 0
        #: the reading thread's CPU time (ns) when that read returned
        self.rx_cpu_ns = 0
        #: monotonic ns when the read that completed the latest published scan returned
        self.frame_arrival_ns = 0
        #: the reading thread's CPU time (ns) then: what the scan path has used of the CPU since is
        #: ``time.thread_time_ns() - frame_arrival_cpu_ns`` (in the same thread)
        self.frame_arrival_cpu_ns = 0
        #: who takes each finished scan first: None publishes it on the bus (``params.topic``);
        #: the daemon's control path takes it, writes its motor command and then publishes it
        self.scan_sink: Callable[[LaserScan], None] | None = None
        self._last_scan_s = 0.0  # clock.monotonic() of the latest published scan
        self._session_scans = 0  # scans published by the current session
        self._previous_error: str | None = None  # last_error when the current session began
        self._ended: asyncio.Future[None] | None = None
        #: malformed replies (or packets) since the latest scan or stream start, and the last's reason
        self._malformed, self._malformed_reason = 0, ""
        self._logged: tuple[str, float] | None = None  # the last loss logged: its key, monotonic s

    @property
    def device_name(self) -> str:  # type: ignore[override]
        return f"lidar {self.params.model}"

    async def _open(self) -> None:
        """Count a reconnect and start the session's bookkeeping (the session opens the link)."""
        if self._attempted:
            self.stats.reconnects += 1
        self._attempted = True
        self._session_scans, self._previous_error = 0, self.last_error

    def _on_opened(self) -> None:
        """The error that ended the last session stands until this one publishes a scan."""

    def _on_session_lost(self, err: DeviceError) -> None:
        """Logged when its cause (:attr:`NoScan.key`, else the text) differs from the last logged
        loss's, and at most every :data:`REPEAT_LOG_S` while it repeats."""
        self.stats.device_errors += 1
        key, now = getattr(err, "key", str(err)), monotonic()
        if self._logged is None or self._logged[0] != key or now - self._logged[1] >= REPEAT_LOG_S:
            log.warning("lidar %s: %s; reconnecting", self.params.model, err)
            self._logged = (key, now)
        self.last_error = str(err)

    def note_malformed(self, reason: str, count: int = 1) -> None:
        """``count`` malformed replies (or packets) came, the last for ``reason``; a stream that
        ends for want of scans says so (:class:`NoScan`)."""
        self._malformed += count
        self._malformed_reason = reason

    def _no_scan(self, link: Link, timeout_s: float) -> NoScan:
        text = f"{link.name}: no scan for {timeout_s:.2f} s"
        if not self._malformed:
            return NoScan(text, text)
        why = self._malformed_reason
        return NoScan(f"{text}; the last {self._malformed} {self.MALFORMED_UNIT} were malformed: {why}",
                      f"{link.name}: no scan; malformed: {why}")

    def _on_session_end(self) -> None:
        self.connected = False

    @abstractmethod
    async def _session(self) -> None:
        """One connection: open, configure, stream. Set ``connected`` once streaming."""

    def _stamp_rx(self) -> None:
        """Note that a read from the device has just returned (subclasses call it first thing)."""
        self.rx_ns = monotonic_ns()
        self.rx_cpu_ns = time.thread_time_ns()

    def publish(self, scan: LaserScan) -> None:
        """Publish one finished scan and count it. The first scan after a reconnect clears the
        error that ended the previous session (:attr:`last_error`): the device works again."""
        if self._session_scans == 0 and self.last_error == self._previous_error:
            self.last_error = None
            self._logged = None  # the device works again: its next loss is news, whatever its cause
        self._session_scans += 1
        self._malformed = 0
        self.stats.scans += 1
        self.frame_arrival_ns = self.rx_ns
        self.frame_arrival_cpu_ns = self.rx_cpu_ns
        self._last_scan_s = monotonic()
        sink = self.scan_sink
        if sink is not None:
            sink(scan)
        else:
            self.bus.publish(self.params.topic, scan)

    async def _stream_from(self, link: Link, on_bytes: Callable[[bytes], None],
                           timeout_s: Callable[[], float],
                           backlog: Callable[[], None] | None = None) -> None:
        """Hand every chunk ``link`` reads to ``on_bytes`` until the stream ends; always raises.

        ``backlog`` first handles what was read before (frames that came with the start reply).
        ``on_bytes`` runs in the link's reader callback, so a scan reaches the safety controller
        and the VESC without waking a task. The stream ends with the link's DeviceError, with the
        error given to :meth:`_end_stream`, or with :class:`NoScan` when no scan is published for
        ``timeout_s()`` seconds (checked by a loop timer, rearmed only when it fires). Any other
        exception from the handlers (a fault in handling a frame) is logged and becomes a
        DeviceError, so the driver reconnects rather than stops.
        """
        loop = asyncio.get_running_loop()
        ended: asyncio.Future[None] = loop.create_future()
        self._ended = ended
        self._last_scan_s = monotonic()
        self._malformed = 0

        def check_overdue() -> None:
            nonlocal timer
            if ended.done():
                return
            left = self._last_scan_s + timeout_s() - monotonic()
            if left <= 0:
                ended.set_exception(self._no_scan(link, timeout_s()))
            else:
                timer = loop.call_later(left, check_overdue)

        timer = loop.call_later(timeout_s(), check_overdue)
        failed: asyncio.Future[bytes] | None = None
        try:
            if backlog is not None:
                backlog()
            link.set_receiver(on_bytes)
            failed = asyncio.ensure_future(link.read())  # with a receiver set: ends when the link fails
            await asyncio.wait([ended, failed], return_when=asyncio.FIRST_COMPLETED)
            if ended.done():
                ended.result()
            failed.result()  # the link's error, or what on_bytes raised
            raise DeviceIOError(f"{link.name}: the link ended")
        except DeviceError:
            raise
        except Exception as err:
            log.error("lidar %s: handling a frame failed", self.params.model, exc_info=err)
            raise DeviceError(f"handling a frame failed: {err!r}") from err
        finally:
            timer.cancel()
            link.set_receiver(None)
            self._ended = None
            for fut in (ended, failed):
                if fut is None:
                    continue
                if fut.done() and not fut.cancelled():
                    fut.exception()  # seen: the stream is over either way
                else:
                    fut.cancel()

    def _end_stream(self, err: DeviceError) -> None:
        """End the running :meth:`_stream_from` with ``err`` (from ``on_bytes``: a device fault)."""
        if self._ended is not None and not self._ended.done():
            self._ended.set_exception(err)
