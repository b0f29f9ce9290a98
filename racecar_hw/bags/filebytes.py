"""The bytes of a bag's storage file, read where a scanner needs them, never held whole.

The recovery's scanners (:func:`racecar_hw.bags.recover.scan_ros1`, ``scan_mcap``) walk a storage
file record by record. They read it through :class:`ByteSource`: :class:`FileBytes` reads the file
with ``os.pread`` (a record header from a 1 MiB read-ahead window, a chunk as it is), so ``bag
info`` and ``bag recover`` hold one chunk, not the file (a 600 MB uncompressed ROS 1 bag took
600 MB when it was read whole); :class:`MemoryBytes` serves bytes already in memory (the records
of a decompressed chunk; tests) without copying them.

Why not ``mmap``: a file that shrinks under a map (a recording cut back, a copy rewritten in
place) kills the process with SIGBUS, where a read just comes back short, which is refused in one
line (:class:`FileBytes`). The size is the one the file had when opened: a file still being
recorded is read as far as it went then, as a copy taken at that moment would be.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol

from racecar_hw.bags.validate import open_regular
from racecar_hw.base.errors import BagError

#: Bytes read at once around a small read (a record header), in bytes; also the size of the pieces
#: :func:`pieces` gives (a compressed chunk fed to its decompressor).
READ_AHEAD = 1 << 20


class ByteSource(Protocol):
    """A storage file's bytes, read by position."""

    #: the number of bytes (of the file when it was opened)
    size: int

    def read(self, pos: int, n: int) -> memoryview:
        """The ``n`` bytes at ``pos``; fewer when the bytes end first."""


class MemoryBytes:
    """Bytes already in memory as a :class:`ByteSource`; :meth:`read` gives views, not copies."""

    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        self._view = memoryview(data).cast("B")
        self.size = len(self._view)

    def read(self, pos: int, n: int) -> memoryview:
        """The ``n`` bytes at ``pos`` (a view into the data)."""
        return self._view[pos:pos + n]


class FileBytes:
    """The regular file open as ``fd`` (``size`` bytes when opened), read with ``os.pread``.

    A read of at most :data:`READ_AHEAD` bytes is served from a window of that size read at once
    (a record header costs no system call of its own); a larger one (a chunk) is read on its own.
    A file that ends before ``size`` (cut back while it is read) raises :class:`BagError`.
    """

    def __init__(self, path: Path, fd: int, size: int) -> None:
        self.path = path
        self.size = size
        self._fd = fd
        self._at = 0
        self._window = memoryview(b"")

    def read(self, pos: int, n: int) -> memoryview:
        """The ``n`` bytes at ``pos`` (fewer past :attr:`size`)."""
        n = min(n, self.size - pos)
        if n <= 0:
            return memoryview(b"")
        if n > READ_AHEAD:
            return memoryview(self._pread(pos, n))
        if not (self._at <= pos and pos + n <= self._at + len(self._window)):
            self._at = pos
            self._window = memoryview(self._pread(pos, min(READ_AHEAD, self.size - pos)))
        return self._window[pos - self._at:pos - self._at + n]

    def _pread(self, pos: int, n: int) -> bytearray:
        out = bytearray(n)
        got = 0
        while got < n:  # a read may return less than asked (Linux: at most 2 GiB at once)
            step = os.preadv(self._fd, [memoryview(out)[got:]], pos + got)
            if step == 0:
                now = os.fstat(self._fd).st_size
                raise BagError(f"{self.path} has {now} bytes as it is read, {self.size} when it was opened "
                               "(is something cutting it back?); refused")
            got += step
        return out


@contextmanager
def open_file_bytes(path: Path) -> Iterator[FileBytes]:
    """The regular file ``path`` as :class:`FileBytes` (a FIFO or a device is refused, BagError,
    by :func:`~racecar_hw.bags.validate.open_regular`); closed on leaving."""
    with open_regular(path) as f:
        yield FileBytes(path, f.fileno(), os.fstat(f.fileno()).st_size)


def as_source(data: bytes | bytearray | memoryview | ByteSource) -> ByteSource:
    """``data`` as a :class:`ByteSource` (bytes in memory are wrapped, not copied)."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return MemoryBytes(data)
    return data


def pieces(src: ByteSource, pos: int, n: int) -> Iterator[memoryview]:
    """The ``n`` bytes at ``pos``, :data:`READ_AHEAD` at a time (fewer, once the bytes end)."""
    for at in range(pos, pos + n, READ_AHEAD):
        piece = src.read(at, min(READ_AHEAD, pos + n - at))
        if not piece:
            return
        yield piece


def occurrences(src: ByteSource, pattern: bytes, start: int, end: int) -> Iterator[int]:
    """Each position of ``pattern`` in ``src`` from ``start``, ending before ``end``, in order. Read
    :data:`READ_AHEAD` at a time, each piece overlapping the last by ``len(pattern) - 1``."""
    end = min(end, src.size)
    while start + len(pattern) <= end:
        piece = bytes(src.read(start, min(max(READ_AHEAD, 2 * len(pattern)), end - start)))
        at = piece.find(pattern)
        while at >= 0:
            yield start + at
            at = piece.find(pattern, at + 1)
        start += max(1, len(piece) - len(pattern) + 1)
