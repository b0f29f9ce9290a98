"""A fake Hokuyo that speaks SCIP 2.0 on a pty (like a USB URG) and/or a TCP port (like a UST).

It answers VV, PP, II, BM, QT, RS, RT, %ST, TM0/1/2, GD/GE/GS and MD/ME/MS with the model's
parameters (:mod:`lidar_drivers.scip_models`), measures ranges from a
:class:`~lidar_drivers.base.RangeSource`, and streams frames at the model's true scan period on
absolute deadlines; the first frame follows the acknowledgement by one period, as on a real sensor.

Timing, as on the devices (and in urg_stamped's urg_sim): a streamed frame carries the device time
(the 24-bit ms counter) of step 0 of its sweep, and leaves once the sweep has reached the last
step the command asked for, ``end * period / ARES`` later. :attr:`FakeHokuyo.sweep_starts_ns`
records the true sweep starts for tests. A URG-04LX has no intensity commands (``ME``/``GE`` get
``0E``), reads code 19 on its steps outside AMIN..AMAX, and with ``scip1=True`` boots speaking
SCIP 1.1 as the classic URG-04LX does (every command but ``SCIP2.0`` gets ``E``).

Measurement model: metres become integer mm; nothing in reach or beyond DMAX becomes the model's
no-return code (1, "no object"), closer than DMIN becomes 2 ("too near"). With a cluster, a group
reports its nearest valid step, or its smallest code when none is valid. Intensity is a synthetic
``min(262143, 4e6 / (1000 + mm))`` for a return and 0 otherwise.

Each TCP connection is its own session (laser off, standby); the pty has one session that lives
until :meth:`unplug` (power loss). Faults for tests: :meth:`inject_garbage`,
:meth:`corrupt_next_checksum`, :meth:`split_writes`, :meth:`bunch_next_frames` (frames that
arrive together), :meth:`wrong_length` (scans of the wrong length), :meth:`fail_next_frame` (an
error status), :meth:`mute` (a silent device), :meth:`unplug`/:meth:`replug` (pty) and
:meth:`drop_connection` (TCP). Run :meth:`serve` in a
:class:`~racecar_hw.runtime.devicethread.DeviceThread`; the fault methods may be called from any
thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from lidar_drivers.base import RangeSource
from lidar_drivers.scip import (
    Command,
    CommandDecoder,
    InvalidCommand,
    ScanCommand,
    TimeCommand,
    UnknownCommand,
    encode_info,
    encode_reply,
    encode_scan,
    encode_state,
    encode_time,
)
from lidar_drivers.scip_models import HokuyoModel, get_model
from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.memlink import MemoryPort
from racecar_hw.runtime.fakepty import PtyPort, port_for

TOO_NEAR = 2
"""Error code for a return closer than DMIN."""
#: how many step ranges (start, end) :meth:`FakeHokuyo.measure` keeps the angles of
_MAX_SWEEPS = 16


class _Session:
    """One client's view of the device: laser, time-sync mode and the running stream."""

    def __init__(self, fake: FakeHokuyo, write: Callable[[bytes], Any], name: str,
                 plain_writes: bool = False) -> None:
        self.fake = fake
        self.name = name
        self._write = write  # plain or async
        #: ``write`` is a plain function (a port's: it never blocks or raises), not a coroutine
        self.plain_writes = plain_writes
        self._lock = asyncio.Lock()
        self.decoder = CommandDecoder()
        self.laser_on = False
        self.time_mode = False
        self.stream: asyncio.Task[None] | None = None
        self.closed = False
        self._held: list[bytes] = []  # streamed frames held back by FakeHokuyo.bunch_next_frames

    async def send(self, data: bytes) -> None:
        """Write one whole reply; faults (garbage, split writes) apply here."""
        async with self._lock:
            fake = self.fake
            if fake._garbage:
                data, fake._garbage = fake._garbage + data, b""
            if not fake._split:
                await self._out(data)
                return
            i = 0
            while i < len(data) and not self.closed:
                n = fake._rng.randint(1, 300)
                await self._out(data[i:i + n])
                i += n
                await asyncio.sleep(0.001)

    async def send_frame(self, data: bytes) -> None:
        """Write one scan frame whole, even if the stream is stopped meanwhile (QT stops it between
        frames only). With a port's plain write, nothing else being written and no fault
        (garbage, split writes) to apply, the write is a loop callback, where :meth:`send` in a
        task of its own would write (the same order of events), without the task."""
        fake = self.fake
        if self._lock.locked() or fake._garbage or fake._split or not self.plain_writes:
            await asyncio.shield(self.send(data))
            return
        asyncio.get_running_loop().call_soon(self._write, data)

    async def _out(self, data: bytes) -> None:
        result = self._write(data)
        if asyncio.iscoroutine(result):
            await result

    def feed(self, data: bytes) -> None:
        """Bytes from the host: answer every whole command, in order."""
        self.decoder.receive_data(data)
        for cmd in self.decoder:
            self.fake.received.append(getattr(cmd, "line", ""))
            reply = self.handle(cmd)
            if reply is not None:
                self.fake._spawn(self.send(reply))

    def stop_stream(self) -> None:
        if self.stream is not None:
            self.stream.cancel()
            self.stream = None

    def close(self) -> None:
        self.closed = True
        self.stop_stream()

    def state(self) -> str:
        if self.time_mode:
            return "002"
        if self.stream is not None:
            return "004"
        return "003" if self.laser_on else "000"

    def handle(self, cmd: Command | UnknownCommand | InvalidCommand) -> bytes | None:
        """The reply to one command (streams start as a side effect)."""
        m = self.fake.model
        if self.fake.scip1:
            return self._scip1(cmd)
        if isinstance(cmd, UnknownCommand):
            return encode_reply(cmd.line, "0E")
        if isinstance(cmd, InvalidCommand):
            return encode_reply(cmd.line, cmd.status)
        if isinstance(cmd, ScanCommand):
            return self._scan_command(cmd)
        if isinstance(cmd, TimeCommand):
            return self._time_command(cmd)
        name = cmd.name
        if name == "VV":
            return encode_info(cmd.line, {"VEND": "Hokuyo Automatic Co.,Ltd.", "PROD": m.model,
                                          "FIRM": m.firmware, "PROT": "SCIP 2.0",
                                          "SERI": self.fake.serial})
        if name == "PP":
            return encode_info(cmd.line, m.fields())
        if name == "II":
            return encode_info(cmd.line, {
                "MODL": m.model, "LASR": "ON" if self.laser_on else "OFF",
                "SCSP": f"Initial({m.scan_rpm}[rpm])", "MESM": "Measuring by Normal Mode",
                "SBPS": "USB only" if m.link == "serial" else "Ethernet 100 [Mbps]",
                "TIME": f"{self.fake.time_ms():06X}", "STAT": "Sensor is working normally"})
        if name == "%ST":
            return encode_state(cmd.line, self.state())
        if name == "BM":
            if self.laser_on:
                return encode_reply(cmd.line, "02")
            self.time_mode = False
            self.laser_on = True
            return encode_reply(cmd.line, "00")
        if name in ("QT", "RS", "RT"):
            self.stop_stream()
            self.laser_on = False
            if name != "QT":
                self.time_mode = False
                self.fake.reset_clock()
            return encode_reply(cmd.line, "00")
        return encode_reply(cmd.line, "0E")  # SCIP2.0: already in SCIP 2.0

    def _scip1(self, cmd: Command | UnknownCommand | InvalidCommand) -> bytes:
        """SCIP 1.1: only the switch to SCIP 2.0 is understood (status ``0``, no checksum)."""
        line = cmd.line
        if isinstance(cmd, Command) and cmd.name == "SCIP2.0":
            self.fake.scip1 = False
            return f"{line}\n0\n\n".encode()
        return f"{line}\nE\n\n".encode()

    def _time_command(self, cmd: TimeCommand) -> bytes:
        if cmd.code == 0:
            if self.time_mode:
                return encode_reply(cmd.line, "02")
            self.stop_stream()
            self.laser_on = False
            self.time_mode = True
            return encode_reply(cmd.line, "00")
        if cmd.code == 1:
            if not self.time_mode:
                return encode_reply(cmd.line, "04")
            return encode_time(cmd.line, self.fake.time_ms())
        if not self.time_mode:
            return encode_reply(cmd.line, "03")
        self.time_mode = False
        return encode_reply(cmd.line, "00")

    def _scan_command(self, cmd: ScanCommand) -> bytes:
        m = self.fake.model
        if cmd.intensities and not m.intensities:
            return encode_reply(cmd.line, "0E")  # no such command on this model
        if cmd.end > m.max_step or cmd.start > m.max_step:
            return encode_reply(cmd.line, "04")
        if cmd.streaming:
            self.stop_stream()
            self.time_mode = False
            self.laser_on = True
            self.stream = self.fake._spawn(self._stream(cmd))
            return encode_reply(cmd.line, "00")
        if not self.laser_on:
            return encode_reply(cmd.line, "10")
        # the reply leaves once the sweep reaches the last step asked for: step 0 was earlier
        ready_ns = round(cmd.end * self.fake.model.step_time_s * NS_PER_S)
        return self.fake.frame(cmd, cmd.line, "00", at_ns=monotonic_ns() - ready_ns)

    async def _stream(self, cmd: ScanCommand) -> None:
        loop = asyncio.get_running_loop()
        m = self.fake.model
        period = m.scan_period_s * (cmd.interval + 1)
        ready = cmd.end * m.step_time_s  # from step 0 until the last step asked for is measured
        # the first frame leaves one period after the acknowledgement
        step0 = loop.time() + period - ready  # loop.time() is the monotonic clock, in s
        remaining = cmd.count
        while True:
            delay = step0 + ready - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            elif delay < -period:  # fell far behind (loaded machine): skip sweeps, do not burst
                step0 += (-delay // period) * period
            if remaining:
                remaining -= 1
            fake = self.fake
            if fake._fail_status is not None:
                status, fake._fail_status = fake._fail_status, None
                await asyncio.shield(self.send(encode_reply(cmd.echo(remaining), status)))
            elif not fake._muted:
                # measured and stamped at the sweep's step 0, however late this host sends it
                step0_ns = round(step0 * NS_PER_S)
                frame = fake.frame(cmd, cmd.echo(remaining), "99", at_ns=step0_ns)
                fake.sweep_starts_ns.append(step0_ns)
                if fake._bunch > 1:  # held back, to leave with the next frame in one write
                    fake._bunch -= 1
                    self._held.append(frame)
                else:
                    frames, self._held = [*self._held, frame], []
                    fake._bunch = 0
                    # noted before the write: a reader may react before it returns
                    fake.frames_sent_ns.extend([monotonic_ns()] * len(frames))
                    await self.send_frame(b"".join(frames))
                    fake.scans_sent += len(frames)
            if cmd.count and remaining == 0:
                self.stream = None
                return
            step0 += period


class FakeHokuyo:
    """A Hokuyo lidar on a pty at ``link`` and/or a TCP server at ``tcp`` (port 0: any free port).

    With neither, a pty without a symlink (see :attr:`path`). After :attr:`ready` is set,
    :attr:`path` and :attr:`tcp_address` tell clients where to connect.
    """

    def __init__(self, model: str, range_source: RangeSource, link: str | None = None,
                 tcp: tuple[str, int] | None = None, seed: int | None = None,
                 scip1: bool = False) -> None:
        self.model: HokuyoModel = get_model(model)
        if scip1 and self.model.name != "urg-04lx":
            raise ValueError(f"only the URG-04LX boots in SCIP 1.1, not the {self.model.model}")
        #: speaks SCIP 1.1 until told ``SCIP2.0`` (a classic URG-04LX after power-on)
        self.scip1 = self.boots_scip1 = scip1
        self.range_source = range_source
        self._sweeps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.link = link
        self.tcp = tcp
        self.serial = "H1612345"
        self.ready = threading.Event()
        self.scans_sent = 0
        self.received: deque[str] = deque(maxlen=2000)
        #: monotonic ns just before each streamed frame was handed to the link (for latency probes)
        self.frames_sent_ns: deque[int] = deque(maxlen=100_000)
        #: monotonic ns of step 0 of each streamed frame's sweep (the time its stamp encodes)
        self.sweep_starts_ns: deque[int] = deque(maxlen=100_000)
        self.tcp_address: tuple[str, int] | None = None
        self._pty: PtyPort | MemoryPort | None = None
        self._pty_session: _Session | None = None
        self._server: asyncio.Server | None = None
        self._tcp_sessions: dict[asyncio.StreamWriter, _Session] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._boot_ns = monotonic_ns()
        self._rng = random.Random(seed)
        self._garbage = b""
        self._split = False
        self._bunch = 0
        self._corrupt = False
        self._extra_readings = 0
        self._fail_status: str | None = None
        self._muted = False
        self.unplugged = False

    # --- where clients connect --------------------------------------------------------------

    @property
    def path(self) -> str:
        """The serial path a client opens (the symlink, else the pty slave)."""
        return self._pty.path if self._pty is not None else (self.link or "")

    # --- the device clock and measurement ---------------------------------------------------

    def time_ms(self, at_ns: int | None = None) -> int:
        """The device's millisecond counter (24 bits), now or at monotonic ``at_ns``."""
        at = monotonic_ns() if at_ns is None else at_ns
        return ((at - self._boot_ns) // 1_000_000) & 0xFFFFFF

    def reset_clock(self) -> None:
        self._boot_ns = monotonic_ns()

    @property
    def clock_zero_ns(self) -> int:
        """The monotonic ns at which the device's millisecond counter read 0."""
        return self._boot_ns

    def measure(self, cmd: ScanCommand, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Distances (mm or error codes) and intensities for the steps ``cmd`` asks for."""
        m = self.model
        angles, outside = self._sweep(cmd.start, cmd.end)
        r = np.asarray(self.range_source.ranges(angles, stamp_ns), dtype=np.float64)
        limit = m.dmax if cmd.width == 3 else min(m.dmax, 4095)
        # no return (inf, nan, beyond the limit), too near, or the distance; then the steps the
        # model cannot measure (in place: a scan's 1,081 steps cost little, each numpy call more)
        with np.errstate(invalid="ignore", over="ignore"):
            mm = np.rint(r * 1000.0)
            dist = np.where(mm < m.dmin, TOO_NEAR, mm)
            dist[~(mm <= limit) | np.isneginf(mm)] = m.no_return
        dist[outside] = m.unmeasurable
        dist = dist.astype(np.int64)
        inten = np.minimum(262143, 4_000_000 // (1000 + dist))
        inten[dist < m.dmin] = 0
        cluster = max(cmd.cluster, 1)
        if cluster > 1:
            pad = (-dist.size) % cluster
            big = 1 << 30
            d = np.concatenate([dist, np.full(pad, big)]).reshape(-1, cluster)
            ok = d >= m.dmin
            nearest = np.where(ok, d, big).min(axis=1)
            code = np.where(~ok, d, big).min(axis=1)
            dist = np.where(nearest < big, nearest, code)
            i = np.concatenate([inten, np.zeros(pad, dtype=np.int64)]).reshape(-1, cluster)
            inten = i.max(axis=1)
        return dist, inten

    def _sweep(self, start: int, end: int) -> tuple[np.ndarray, np.ndarray]:
        """The angles (rad) of steps ``start`` to ``end`` and which of them the model cannot
        measure; kept (read-only) for the next scan, which a stream asks for with the same steps."""
        key = (start, end)
        sweep = self._sweeps.get(key)
        if sweep is None:
            m = self.model
            steps = np.arange(start, end + 1)
            angles = (steps - m.afrt) * (2.0 * np.pi / m.ares)
            outside = (steps < m.amin) | (steps > m.amax)
            angles.setflags(write=False)
            outside.setflags(write=False)
            if len(self._sweeps) >= _MAX_SWEEPS:
                self._sweeps.clear()
            sweep = self._sweeps[key] = (angles, outside)
        return sweep

    def frame(self, cmd: ScanCommand, echo: str, status: str, at_ns: int | None = None) -> bytes:
        """One encoded scan reply for ``cmd`` measured at monotonic ``at_ns`` (default: now)."""
        at = monotonic_ns() if at_ns is None else at_ns
        dist, inten = self.measure(cmd, at)
        if extra := self._extra_readings:  # a misbehaving device: more or fewer than asked for
            n = max(0, len(dist) + extra)
            dist, inten = np.resize(dist, n), np.resize(inten, n)
        data = encode_scan(echo, status, self.time_ms(at), dist, inten if cmd.intensities else None,
                           cmd.width)
        if self._corrupt:
            self._corrupt = False
            first_data = len(echo) + 1 + 4 + 6
            i = data.index(b"\n", first_data) - 1
            data = data[:i] + bytes([((data[i] - 0x30 + 1) & 0x3F) + 0x30]) + data[i + 1:]
        return data

    # --- serving ------------------------------------------------------------------------------

    async def serve(self) -> None:
        """Serve until cancelled."""
        self._loop = asyncio.get_running_loop()
        try:
            if self.link is not None or self.tcp is None:
                self._open_pty()
            if self.tcp is not None:
                self._server = await asyncio.start_server(self._on_client, self.tcp[0], self.tcp[1])
                host, port = self._server.sockets[0].getsockname()[:2]
                self.tcp_address = (host, port)
            self.ready.set()
            await asyncio.Event().wait()
        finally:
            self.ready.clear()
            if self._server is not None:
                self._server.close()
            for writer in list(self._tcp_sessions):
                self._drop(writer)
            self._close_pty()
            for task in list(self._tasks):
                task.cancel()

    def _spawn(self, coro: Any) -> asyncio.Task[Any]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _open_pty(self) -> None:
        assert self._loop is not None
        self.scip1 = self.boots_scip1  # powered on: back to the protocol it boots in
        self._pty = self._pty or port_for(self.link)
        self._pty.open()
        port = self._pty
        self._pty_session = _Session(self, port.write, port.path, plain_writes=True)
        port.watch(self._loop, self._on_pty_readable)
        self.unplugged = False

    def _on_pty_readable(self) -> None:
        if self._pty is None or self._pty_session is None:
            return
        data = self._pty.read()
        if data:
            self._pty_session.feed(data)

    def _close_pty(self) -> None:
        if self._pty is None:
            return
        self._pty.unwatch()
        if self._pty_session is not None:
            self._pty_session.close()
            self._pty_session = None
        self._pty.unplug()

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async def write(data: bytes) -> None:
            if writer.is_closing():
                return
            writer.write(data)
            with contextlib.suppress(ConnectionError, OSError):
                await writer.drain()

        session = _Session(self, write, str(writer.get_extra_info("peername")))
        self._tcp_sessions[writer] = session
        try:
            while not session.closed:
                try:
                    data = await reader.read(4096)
                except (ConnectionError, OSError):
                    break
                if not data:
                    break
                session.feed(data)
        except asyncio.CancelledError:
            # Ends the handler as a plain return: Python 3.11's start_server callback calls
            # exception() on a cancelled handler task and logs a CancelledError traceback
            # (fixed in 3.12), which a sim shutting down would print.
            pass
        finally:
            self._drop(writer)

    def _drop(self, writer: asyncio.StreamWriter) -> None:
        session = self._tcp_sessions.pop(writer, None)
        if session is not None:
            session.close()
        transport = writer.transport
        if transport is not None and not transport.is_closing():
            transport.abort()

    # --- fault injection (any thread) ---------------------------------------------------------

    def _in_loop(self, fn: Callable[[], None]) -> None:
        loop = self._loop
        if loop is None:
            raise RuntimeError("the fake lidar is not serving")
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            fn()
            return

        async def call() -> None:
            fn()

        asyncio.run_coroutine_threadsafe(call(), loop).result(10)

    def inject_garbage(self, n: int) -> None:
        """Send ``n`` random bytes before the next reply."""
        self._garbage += bytes(self._rng.randrange(256) for _ in range(n))

    def corrupt_next_checksum(self) -> None:
        """Give the next scan's first data line a wrong checksum."""
        self._corrupt = True

    def split_writes(self, on: bool = True) -> None:
        """Write each reply in random pieces of 1..300 bytes, 1 ms apart."""
        self._split = on

    def bunch_next_frames(self, n: int = 2) -> None:
        """Send the next ``n`` streamed frames in one write when the last of them is due, as a
        host that reads late finds them: each still carries its own sweep's device time."""
        self._bunch = n

    def wrong_length(self, extra: int) -> None:
        """Stream scans with ``extra`` readings more than asked for (fewer when negative; 0: right
        again), each line's checksum intact."""
        self._extra_readings = extra

    def fail_next_frame(self, status: str) -> None:
        """Answer the next streamed scan with ``status`` (e.g. ``"50"``, a hardware fault)."""
        self._fail_status = status

    def mute(self, on: bool = True) -> None:
        """Stop (or resume) sending streamed scans while still answering commands."""
        self._muted = on

    def unplug(self) -> None:
        """Pull the USB cable: the pty and its symlink disappear, the device loses power."""
        def do() -> None:
            self._close_pty()
            self.unplugged = True
        self._in_loop(do)

    def replug(self) -> None:
        """Plug the pty back in at the same path: a freshly powered device (laser off)."""
        def do() -> None:
            self._close_pty()
            self._open_pty()
        self._in_loop(do)

    def drop_connection(self) -> None:
        """Reset every TCP connection (cable pulled); the server keeps listening."""
        def do() -> None:
            for writer in list(self._tcp_sessions):
                self._drop(writer)
        self._in_loop(do)

    @property
    def clients(self) -> int:
        """Open TCP connections."""
        return len(self._tcp_sessions)
