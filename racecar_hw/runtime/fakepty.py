"""The device end of a pseudo-terminal, for fake devices that clients open like a serial port.

:class:`PtyPort` creates a pty in raw mode and a symlink to its slave at ``link``, so any client
(our drivers, pyserial, third-party tools) opens ``link`` as if it were ``/dev/ttyACM0``.
:meth:`PtyPort.unplug` closes the pty and removes the symlink, which a client sees as EIO and a
missing path, just like a USB device pulled out; :meth:`PtyPort.replug` makes a new pty at the
same ``link``. Bytes written while no client reads are dropped once the pty buffer is full, as on a
real serial line, and counted in ``dropped_bytes``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from collections.abc import Callable

from racecar_hw.base.memlink import MemoryPort, is_memory


class PtyPort:
    """A pty whose slave is reachable at ``link``; the fake device reads and writes the master."""

    def __init__(self, link: str | None = None) -> None:
        self.link = link
        self.master_fd: int | None = None
        self._slave_fd: int | None = None
        self.slave_path = ""
        self.dropped_bytes = 0
        self._watching: asyncio.AbstractEventLoop | None = None

    @property
    def path(self) -> str:
        """The path a client opens: the symlink if there is one, else the slave device."""
        return self.link or self.slave_path

    @property
    def plugged(self) -> bool:
        """Whether the pty exists (the device is plugged in)."""
        return self.master_fd is not None

    def open(self) -> PtyPort:
        """Create the pty and the symlink. Returns self."""
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self.slave_path = os.ttyname(slave)
        if self.link:
            tmp = f"{self.link}.{os.getpid()}.tmp"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self.slave_path, tmp)
            os.replace(tmp, self.link)
        # plugged only once the link is there: a client thread that waits for ``plugged`` opens it
        self._slave_fd, self.master_fd = slave, master
        return self

    def watch(self, loop: asyncio.AbstractEventLoop, on_data: Callable[[], None]) -> None:
        """Call ``on_data()`` from ``loop`` when the client wrote (then :meth:`read` the bytes)."""
        if self.master_fd is not None:
            loop.add_reader(self.master_fd, on_data)
            self._watching = loop

    def unwatch(self) -> None:
        """Stop :meth:`watch`."""
        loop, self._watching = self._watching, None
        if loop is not None and self.master_fd is not None:
            with contextlib.suppress(Exception):
                loop.remove_reader(self.master_fd)

    def read(self) -> bytes:
        """Bytes the client wrote, or b"" when there are none (never blocks)."""
        if self.master_fd is None:
            return b""
        try:
            return os.read(self.master_fd, 65536)
        except (BlockingIOError, OSError):
            return b""

    def write(self, data: bytes) -> int:
        """Send ``data`` to the client; returns bytes taken. The rest is dropped and counted."""
        if self.master_fd is None:
            self.dropped_bytes += len(data)
            return 0
        sent = 0
        view = memoryview(data)
        while sent < len(data):
            try:
                sent += os.write(self.master_fd, view[sent:])
            except (BlockingIOError, OSError):
                break
        self.dropped_bytes += len(data) - sent
        return sent

    def unplug(self) -> None:
        """Remove the device: close the pty and delete the symlink."""
        self.unwatch()
        if self.link:
            with contextlib.suppress(FileNotFoundError):
                if os.path.islink(self.link) and os.readlink(self.link) == self.slave_path:
                    os.unlink(self.link)
        for fd in (self.master_fd, self._slave_fd):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master_fd = self._slave_fd = None

    def replug(self) -> None:
        """Plug the device back in: a new pty at the same ``link``."""
        self.unplug()
        self.open()

    def close(self) -> None:
        """Remove the device for good. Safe to call twice."""
        self.unplug()

    def __enter__(self) -> PtyPort:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()


def port_for(link: str | None) -> PtyPort | MemoryPort:
    """The device end a fake serves ``link`` on: an in-memory port for ``mem://NAME`` (a simulation
    in lockstep), otherwise a pty with a symlink at ``link``."""
    if link is not None and is_memory(link):
        return MemoryPort(link)
    return PtyPort(link)
