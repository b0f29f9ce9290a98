"""Byte links to devices for one asyncio loop: serial ports (pyserial) and TCP.

A :class:`Link` is the only place where driver bytes meet the OS. ``read()`` awaits at least one
byte, or ``set_receiver()`` hands every chunk to a callback straight from the loop's reader
callback, waking no task (how the drivers stream). ``write()`` never blocks (bytes the OS cannot
take yet wait in a buffer drained by the loop); ``close()`` is safe twice. OS and pyserial errors
become :class:`~racecar_hw.base.errors.DeviceNotFound` (nothing at that path or address) or
:class:`~racecar_hw.base.errors.DeviceIOError` (it went away).

A simulation in lockstep uses in-memory links instead (``mem://NAME``, :mod:`racecar_hw.base.memlink`).

Serial ports open through ``serial.serial_for_url``, so a path, a pty symlink, ``spy:///dev/ttyACM0``
(hexdump of the traffic) and ``socket://host:port`` all work. :func:`open_link` picks the link type
from a spec: ``tcp://HOST:PORT`` or ``HOST:PORT`` with no slash means TCP, anything else serial.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable
from typing import TypeVar

import serial
import serial.tools.list_ports

from racecar_hw.base.errors import DeviceIOError, DeviceNotFound, DeviceTimeout

_timeout = getattr(asyncio, "timeout", None)  # Python 3.11+
T = TypeVar("T")

#: Bytes a serial link queues beyond what the OS took before the device counts as gone (about a
#: second of a VESC's commands and polls at 50 Hz, once the OS's own buffer is full).
MAX_TX_PENDING = 2048


class Link(ABC):
    """A byte stream to one device. Use it from one event loop; it is an async context manager."""

    name: str = ""
    #: whether the link is a serial line (a USB device), not a network connection
    is_serial: bool = False

    @abstractmethod
    async def open(self) -> None:
        """Open the link; raises DeviceNotFound or DeviceIOError."""

    @abstractmethod
    async def read(self) -> bytes:
        """At least one byte from the device; raises DeviceIOError when the device goes away."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Queue ``data`` for the device without blocking; raises DeviceIOError if it is gone."""

    @abstractmethod
    def set_receiver(self, receiver: Callable[[bytes], None] | None) -> None:
        """Hand every chunk read to ``receiver(data)`` instead of buffering it for :meth:`read`."""

    @abstractmethod
    def close(self) -> None:
        """Close the link. Safe to call more than once."""

    def discard_unsent(self) -> None:  # noqa: B027 - nothing to discard unless a link queues
        """Drop what was written but not yet sent (before giving a device up); a link that queues
        nothing of its own has nothing to drop."""

    @property
    @abstractmethod
    def is_open(self) -> bool:
        """Whether the link is open and has not failed."""

    async def read_within(self, timeout_s: float) -> bytes:
        """:meth:`read`, or asyncio.TimeoutError after ``timeout_s`` seconds without a byte."""
        return await within(self.read(), timeout_s)

    @property
    def tx_pending(self) -> int:
        """Bytes written but not yet taken by the OS (none where writes go straight through)."""
        return 0

    def set_dtr(self, level: bool) -> None:  # noqa: B027 - optional capability
        """Set the serial DTR line (RPLIDAR A1 motor control). Links without DTR ignore it."""

    async def __aenter__(self) -> Link:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


async def within(aw: Awaitable[T], timeout_s: float) -> T:
    """``await aw``, or asyncio.TimeoutError after ``timeout_s`` seconds.

    Not ``asyncio.wait_for`` where ``asyncio.timeout`` exists (3.11+): before Python 3.12,
    wait_for swallows a cancellation that arrives as ``aw`` completes, so a driver cancelled while
    its connection was being made (a daemon stopped right after it started) went on streaming and
    its shutdown never ended; it also runs ``aw`` in a new task, two extra loop iterations between
    the bytes' arrival and the reader.
    """
    if _timeout is None:
        return await asyncio.wait_for(aw, timeout_s)
    async with _timeout(timeout_s):
        return await aw


class _ReceivingLink(Link):
    """Reading shared by the links: chunks go to a receiver callback, or into a buffer for read().

    A subclass calls :meth:`_received` with each chunk the OS hands over and :meth:`_fail` when the
    device goes away, and implements :meth:`_detach` (stop reading from the OS).
    """

    def __init__(self) -> None:
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending: asyncio.Future[None] | None = None
        self._rx = bytearray()
        self._error: DeviceIOError | None = None
        self._receiver: Callable[[bytes], None] | None = None
        self._receiver_error: Exception | None = None

    def _reset(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._error = None
        self._receiver_error = None
        self._rx.clear()

    def _received(self, data: bytes) -> None:
        if self._receiver is not None:
            self._deliver(data)
            return
        self._rx += data
        self._wake()

    def set_receiver(self, receiver: Callable[[bytes], None] | None) -> None:
        """Hand every chunk read to ``receiver(data)`` in the loop's reader callback, waking no task.

        :meth:`read` then returns only bytes buffered before, and otherwise waits until the link
        fails. An exception from ``receiver`` fails the link, and :meth:`read` raises it.
        None goes back to buffering for :meth:`read`.
        """
        self._receiver = receiver
        if receiver is not None and self._rx:
            data = bytes(self._rx)
            self._rx.clear()
            self._deliver(data)

    def _deliver(self, data: bytes) -> None:
        assert self._receiver is not None
        try:
            self._receiver(data)
        except Exception as err:
            self._receiver_error = err
            self._fail(DeviceIOError(f"{self.name}: receiver failed: {err!r}"))

    def _wake(self) -> None:
        if self._pending is not None and not self._pending.done():
            self._pending.set_result(None)

    def _fail(self, err: DeviceIOError) -> None:
        if self._error is None:
            self._error = err
        self._detach()
        self._wake()

    @abstractmethod
    def _detach(self) -> None:
        """Stop reading from the OS (the link failed or is closing)."""

    @abstractmethod
    def _closed(self) -> bool:
        """Whether the link was never opened or has been closed."""

    async def read(self) -> bytes:
        while not self._rx:
            if self._receiver_error is not None:
                err, self._receiver_error = self._receiver_error, None
                raise err
            if self._error is not None:
                raise self._error
            if self._closed():
                raise DeviceIOError(f"{self.name}: not open")
            assert self._loop is not None
            self._pending = self._loop.create_future()
            await self._pending
        data = bytes(self._rx)
        self._rx.clear()
        return data


class SerialLink(_ReceivingLink):
    """A serial port through pyserial, read and written by the event loop without threads."""

    is_serial = True

    def __init__(self, url: str, baudrate: int = 115200) -> None:
        super().__init__()
        self.url = url
        self.name = url
        self.baudrate = baudrate
        self._port: serial.SerialBase | None = None
        self._fd: int | None = None
        self._tx = bytearray()
        self._writer_armed = False

    @property
    def is_open(self) -> bool:
        return self._port is not None and self._error is None

    def _closed(self) -> bool:
        return self._port is None

    async def open(self) -> None:
        self._reset()
        try:  # exclusive: a second program (a second racecar-hw) must not share the port
            port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0,
                                         exclusive=True)
        except (FileNotFoundError, serial.SerialException, OSError, ValueError) as err:
            if _is_missing(err):
                raise DeviceNotFound(f"no serial device at {self.url}") from err
            if "exclusively lock" in str(err):
                raise DeviceIOError(f"{self.url} is in use by another program (a second racecar-hw? "
                                    "see lsof or fuser)") from err
            raise DeviceIOError(f"cannot open {self.url}: {err}") from err
        self._port = port
        try:
            fd = port.fileno()
        except (AttributeError, NotImplementedError, OSError):
            fd = None
        if fd is None:
            port.close()
            self._port = None
            raise DeviceIOError(f"{self.url}: only ports with a file descriptor are supported")
        self._fd = fd
        with contextlib.suppress(serial.SerialException, OSError):
            port.reset_input_buffer()
        os.set_blocking(fd, False)
        assert self._loop is not None
        self._loop.add_reader(fd, self._on_readable)

    def _on_readable(self) -> None:
        assert self._fd is not None
        try:
            data = os.read(self._fd, 65536)
        except BlockingIOError:
            return
        except OSError as err:
            self._fail(DeviceIOError(f"{self.url}: {os.strerror(err.errno or 0) or err}"))
            return
        if not data:
            self._fail(DeviceIOError(f"{self.url}: device closed"))
            return
        self._received(data)

    def _on_writable(self) -> None:
        self._flush()

    def _flush(self) -> None:
        if self._fd is None:
            return
        while self._tx:
            try:
                n = os.write(self._fd, self._tx)
            except BlockingIOError:
                break
            except OSError as err:
                self._fail(DeviceIOError(f"{self.url}: write failed: {err}"))
                return
            del self._tx[:n]
        assert self._loop is not None
        # the writer callback is registered only while bytes wait, so a write the OS takes at once
        # (the usual case) costs no selector calls
        if self._tx:
            if not self._writer_armed:
                self._loop.add_writer(self._fd, self._on_writable)
                self._writer_armed = True
        elif self._writer_armed:
            self._loop.remove_writer(self._fd)
            self._writer_armed = False

    def _detach(self) -> None:
        if self._fd is not None and self._loop is not None:
            with contextlib.suppress(Exception):
                self._loop.remove_reader(self._fd)
                self._loop.remove_writer(self._fd)
        self._fd = None
        self._writer_armed = False

    def write(self, data: bytes) -> None:
        """Queue ``data`` and write what the OS takes now; the rest goes when the port is writable.

        A device that takes nothing for long fails the link once :data:`MAX_TX_PENDING` bytes wait
        (a backlog of stale commands is worse than none: the reconnect starts afresh)."""
        if self._error is not None:
            raise self._error
        if self._fd is None:
            raise DeviceIOError(f"{self.url}: not open")
        if len(self._tx) + len(data) > MAX_TX_PENDING:
            self.discard_unsent()
            self._fail(DeviceIOError(f"{self.url}: the device takes no data ({len(self._tx)} bytes "
                                     "unwritten)"))
            raise self._error  # type: ignore[misc]
        self._tx += data
        self._flush()
        if self._error is not None:
            raise self._error

    @property
    def tx_pending(self) -> int:
        """Bytes written but not yet taken by the OS."""
        return len(self._tx)

    def set_dtr(self, level: bool) -> None:
        if self._port is None:
            return
        try:
            self._port.dtr = level
        except (serial.SerialException, OSError) as err:
            raise DeviceIOError(f"{self.url}: cannot set DTR: {err}") from err

    def discard_unsent(self) -> None:
        """Drop what was written but not yet sent, queued here and in the OS's buffer: stale commands
        to a device that stopped reading must not reach it when it reads again (before a close that
        gives the device up; a plain close sends what is queued, a shutdown's brake among it)."""
        self._tx.clear()
        if self._port is not None:
            with contextlib.suppress(Exception):
                self._port.reset_output_buffer()

    def close(self) -> None:
        self._detach()
        self._receiver = None
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()
        self._wake()
        self._tx.clear()


class _TcpProtocol(asyncio.Protocol):
    """Passes what the transport reports to its :class:`TcpLink`."""

    def __init__(self, link: TcpLink) -> None:
        self.link = link

    def data_received(self, data: bytes) -> None:
        self.link._received(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.link._lost(self, exc)


class TcpLink(_ReceivingLink):
    """A TCP connection (Hokuyo UST/UTM over Ethernet), on an asyncio transport."""

    def __init__(self, host: str, port: int, connect_timeout_s: float = 2.0) -> None:
        super().__init__()
        self.host = host
        self.port = port
        self.name = f"{host}:{port}"
        self.connect_timeout_s = connect_timeout_s
        self._transport: asyncio.Transport | None = None
        self._protocol: _TcpProtocol | None = None

    @property
    def is_open(self) -> bool:
        return (self._transport is not None and not self._transport.is_closing()
                and self._error is None)

    def _closed(self) -> bool:
        return self._transport is None

    async def open(self) -> None:
        self._reset()
        assert self._loop is not None
        protocol = _TcpProtocol(self)
        try:
            transport, _ = await within(
                self._loop.create_connection(lambda: protocol, self.host, self.port),
                self.connect_timeout_s)
        except asyncio.TimeoutError as err:
            raise DeviceTimeout(f"no answer from {self.name}") from err
        except ConnectionRefusedError as err:
            raise DeviceNotFound(f"nothing listens at {self.name}") from err
        except (OSError, OverflowError, ValueError) as err:  # the last two: a port out of range
            raise DeviceIOError(f"cannot connect to {self.name}: {err}") from err
        self._transport = transport  # type: ignore[assignment]
        self._protocol = protocol

    def _lost(self, protocol: _TcpProtocol, exc: Exception | None) -> None:
        if protocol is not self._protocol:
            return  # a connection this link already closed
        reason = f"{exc}" if exc is not None else "connection closed by the device"
        self._fail(DeviceIOError(f"{self.name}: {reason}"))

    def _detach(self) -> None:
        transport, self._transport = self._transport, None
        self._protocol = None
        if transport is not None:
            transport.close()

    def write(self, data: bytes) -> None:
        if self._error is not None:
            raise self._error
        if self._transport is None or self._transport.is_closing():
            raise DeviceIOError(f"{self.name}: not connected")
        self._transport.write(data)

    def close(self) -> None:
        self._detach()
        self._receiver = None
        self._wake()


def parse_host_port(spec: str, default_port: int | None = None) -> tuple[str, int]:
    """``HOST:PORT`` (or ``tcp://HOST:PORT``) as a (host, port) pair."""
    spec = spec.removeprefix("tcp://")
    host, sep, port = spec.rpartition(":")
    if not sep:
        if default_port is None:
            raise ValueError(f"{spec!r} is not HOST:PORT")
        return spec, default_port
    if not port.isdigit() or int(port) > 65535:
        raise ValueError(f"{spec!r}: port {port!r} is not a port number (0-65535)")
    if not host.strip("[]"):
        raise ValueError(f"{spec!r} names no host")
    return host.strip("[]"), int(port)


def open_link(spec: str, baudrate: int = 115200) -> Link:
    """A link for ``spec``: ``tcp://HOST:PORT`` for TCP, ``mem://NAME`` for a simulation's
    in-memory link (:mod:`racecar_hw.base.memlink`), otherwise a serial path or pyserial URL."""
    if spec.startswith("mem://"):
        from racecar_hw.base.memlink import MemoryLink  # noqa: PLC0415 - it builds on this module

        return MemoryLink(spec)
    if spec.startswith("tcp://"):
        host, port = parse_host_port(spec)
        return TcpLink(host, port)
    return SerialLink(spec, baudrate)


def find_serial_port(vid: int, pid: int, serial_number: str | None = None) -> str:
    """The device path of the USB serial port with this VID:PID (and serial number, if given)."""
    for info in serial.tools.list_ports.comports():
        if info.vid == vid and info.pid == pid and (
                serial_number is None or info.serial_number == serial_number):
            return info.device
    wanted = f"{vid:04x}:{pid:04x}" + (f" serial {serial_number}" if serial_number else "")
    raise DeviceNotFound(f"no USB serial device {wanted}")


def _is_missing(err: BaseException) -> bool:
    cur: BaseException | None = err
    while cur is not None:
        if isinstance(cur, FileNotFoundError) or getattr(cur, "errno", None) in (
                errno.ENOENT, errno.ENODEV, errno.ENXIO):
            return True
        cur = cur.__cause__ or cur.__context__
    return "No such file" in str(err) or "could not open port" in str(err) and "[Errno 2]" in str(err)
