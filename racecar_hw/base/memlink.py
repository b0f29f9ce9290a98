"""In-memory device links for a simulation in lockstep, named ``mem://NAME``.

The model is python-can's virtual bus: a process-wide table of named channels. A fake device
plugs a :class:`MemoryPort` (the device end, shaped like the pty a fake uses in real time) in
under a name; a driver opens the same name as a :class:`MemoryLink` (the host end, a
:class:`~racecar_hw.base.link.Link` like a serial port or a TCP connection). The bytes are the
same as on a pty or a socket, through the same codecs; what changes is that each chunk is handed
to the other end by the event loop's next pass, with no OS in between, so virtual time (see
:mod:`racecar_hw.runtime.lockstep`) cannot move while a chunk is in flight.

Both ends live in one event loop. Unplugging the port fails the connected link (as EIO on a
pulled USB cable) and removes the name (a new open finds nothing), until the port is plugged in
again.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from racecar_hw.base.errors import DeviceIOError, DeviceNotFound
from racecar_hw.base.link import _ReceivingLink

SCHEME = "mem://"

_plugged: dict[str, MemoryPort] = {}


def is_memory(spec: str) -> bool:
    """Whether ``spec`` names an in-memory link."""
    return spec.startswith(SCHEME)


class MemoryPort:
    """The device end of the link ``name`` (``mem://NAME``): what a fake reads and writes.

    The same surface as :class:`~racecar_hw.runtime.fakepty.PtyPort` for the fakes: :meth:`open`
    plugs it in, :meth:`read` and :meth:`write` never block, :meth:`unplug` and :meth:`replug`.
    :meth:`watch` calls back when the host wrote (a pty's fake uses the loop's reader instead).
    """

    def __init__(self, name: str) -> None:
        if not is_memory(name):
            raise ValueError(f"a memory link's name starts with {SCHEME}, got {name!r}")
        self.link = name
        self.dropped_bytes = 0
        #: the host end connected now, if any
        self.peer: MemoryLink | None = None
        self._rx = bytearray()
        self._plugged = False
        self._on_data: Callable[[], None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._scheduled = False

    @property
    def path(self) -> str:
        return self.link

    @property
    def plugged(self) -> bool:
        return self._plugged

    master_fd = None  # no file descriptor: fakes watch it with watch()

    def open(self) -> MemoryPort:
        """Plug in: the name opens from now on. Returns self."""
        other = _plugged.get(self.link)
        if other is not None and other is not self:
            raise RuntimeError(f"{self.link} is plugged in already")
        _plugged[self.link] = self
        self._plugged = True
        return self

    def watch(self, loop: asyncio.AbstractEventLoop, on_data: Callable[[], None]) -> None:
        """Call ``on_data()`` from ``loop`` after the host wrote (then :meth:`read` the bytes)."""
        self._loop, self._on_data = loop, on_data
        if self._rx:
            self._schedule()

    def unwatch(self) -> None:
        self._on_data = None

    def read(self) -> bytes:
        """Bytes the host wrote, or b"" when there are none."""
        data = bytes(self._rx)
        self._rx.clear()
        return data

    def write(self, data: bytes) -> int:
        """Send ``data`` to the host; returns the bytes taken (none while nobody has it open)."""
        peer = self.peer
        if not self._plugged or peer is None or not peer.is_open:
            self.dropped_bytes += len(data)
            return 0
        peer.deliver(bytes(data))
        return len(data)

    def unplug(self) -> None:
        """Pull the cable: the open link fails, the name is gone until :meth:`open`."""
        if _plugged.get(self.link) is self:
            del _plugged[self.link]
        self._plugged = False
        self._rx.clear()
        peer, self.peer = self.peer, None
        if peer is not None:
            peer.lost(f"{self.link}: device unplugged")

    def replug(self) -> None:
        self.unplug()
        self.open()

    def close(self) -> None:
        self.unplug()

    # --- from the host end --------------------------------------------------------------------

    def _connect(self, link: MemoryLink) -> None:
        old, self.peer = self.peer, link
        self._rx.clear()
        if old is not None and old is not link:
            old.lost(f"{self.link}: opened again elsewhere")

    def _host_wrote(self, data: bytes) -> None:
        self._rx += data
        if self._on_data is not None:
            self._schedule()

    def _schedule(self) -> None:
        if not self._scheduled and self._loop is not None:
            self._scheduled = True
            self._loop.call_soon(self._fire)

    def _fire(self) -> None:
        self._scheduled = False
        if self._rx and self._on_data is not None:
            self._on_data()


class MemoryLink(_ReceivingLink):
    """The host end of ``mem://NAME``: a :class:`~racecar_hw.base.link.Link` to a fake's port.

    ``is_serial`` says which real link it stands for (a serial port, or a TCP connection).
    """

    def __init__(self, name: str, *, is_serial: bool = True) -> None:
        super().__init__()
        self.name = name
        self.is_serial = is_serial
        self._port: MemoryPort | None = None

    @property
    def is_open(self) -> bool:
        return self._port is not None and self._error is None

    def _closed(self) -> bool:
        return self._port is None

    async def open(self) -> None:
        self._reset()
        port = _plugged.get(self.name)
        if port is None:
            raise DeviceNotFound(f"no device at {self.name}")
        self._port = port
        port._connect(self)

    def deliver(self, data: bytes) -> None:
        """Bytes from the device, handed over by the loop's next pass."""
        assert self._loop is not None
        self._loop.call_soon(self._arrive, self._port, data)

    def _arrive(self, port: MemoryPort | None, data: bytes) -> None:
        if port is self._port and port is not None and self._error is None:
            self._received(data)

    def lost(self, why: str) -> None:
        """The device went away (from the device end)."""
        if self._loop is not None:
            self._loop.call_soon(self._fail, DeviceIOError(why))

    def _detach(self) -> None:
        port, self._port = self._port, None
        if port is not None and port.peer is self:
            port.peer = None

    def write(self, data: bytes) -> None:
        if self._error is not None:
            raise self._error
        if self._port is None:
            raise DeviceIOError(f"{self.name}: not open")
        self._port._host_wrote(bytes(data))

    def close(self) -> None:
        self._detach()
        self._receiver = None
        self._wake()


__all__ = ["SCHEME", "MemoryLink", "MemoryPort", "is_memory"]
