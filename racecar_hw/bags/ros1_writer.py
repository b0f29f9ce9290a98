"""A ROS 1 bag writer (format 2.0), laid out as the real ``rosbag`` (ROS Noetic) lays it out.

The format (http://wiki.ros.org/Bags/Format/2.0): the magic ``#ROSBAG V2.0\n``; the file-header
record (``index_pos``, ``conn_count``, ``chunk_count``; 4104 bytes as ``rosbag`` writes it,
:func:`racecar_hw.bags.writers.ros1_file_header`); chunks, each followed by one index-data record
per connection it holds; then, at ``index_pos``, every connection record and one chunk-info
record per chunk. Every record is a header (``name=value`` fields, each with its uint32 length,
the whole with its uint32 length) and data (with its uint32 length). A chunk's data is its records
(connection records the first time a connection appears in the file, message-data records with
``conn`` and ``time``), uncompressed (``none``) or ``bz2``. Times are uint32 seconds and uint32
nanoseconds.

A file whose writer did not close it has ``index_pos`` 0 and every flushed chunk: ``rosbag
reindex`` and :func:`racecar_hw.bags.recover.recover_bag` rebuild its index. The tests read these
files with Debian's ``python3-rosbag`` (the real tool) and rosbags.
"""

from __future__ import annotations

import bz2
import os
import struct
from pathlib import Path
from typing import Any

from racecar_hw.bags.writers import ROS1_MAGIC, check_still_there, ros1_file_header
from racecar_hw.base.errors import BagError, BagWriteError

#: A chunk is written once its records exceed this many bytes (as rosbag's default, 768 KiB).
CHUNK_THRESHOLD = 768 * 1024
COMPRESSIONS = ("none", "bz2")

_OP_MSG_DATA, _OP_CHUNK, _OP_INDEX_DATA, _OP_CHUNK_INFO, _OP_CONNECTION = 0x02, 0x05, 0x04, 0x06, 0x07
_U32 = struct.Struct("<I")
_MSG_TAIL = struct.Struct("<III")  # the time field's value (sec, nsec), then the data length


def _field(name: str, value: bytes) -> bytes:
    raw = name.encode() + b"=" + value
    return _U32.pack(len(raw)) + raw


def _record_head(fields: list[tuple[str, bytes]], data_len: int) -> bytes:
    """A record up to its data: the header and the data's length."""
    header = b"".join(_field(n, v) for n, v in fields)
    return _U32.pack(len(header)) + header + _U32.pack(data_len)


def _record(fields: list[tuple[str, bytes]], data: bytes) -> bytes:
    return _record_head(fields, len(data)) + data


def _time(t_ns: int) -> bytes:
    sec, nsec = divmod(t_ns, 1_000_000_000)
    return struct.pack("<II", sec, nsec)


def _u32(v: int) -> bytes:
    return _U32.pack(v)


class Ros1Connection:
    """One connection (topic) of a ROS 1 bag: its id and the fields of its connection record."""

    def __init__(self, cid: int, topic: str, msgtype: str, md5sum: str, msgdef: str,
                 callerid: str | None, latching: int | None) -> None:
        self.id = cid
        self.topic = topic
        fields = [("topic", topic.encode()), ("type", msgtype.encode()), ("md5sum", md5sum.encode()),
                  ("message_definition", msgdef.encode())]
        if callerid is not None:
            fields.append(("callerid", callerid.encode()))
        if latching is not None:
            fields.append(("latching", str(latching).encode()))
        body = b"".join(_field(n, v) for n, v in fields)
        #: A message-data record's header up to the time field's value (op, conn, "time=").
        fixed = _field("op", bytes([_OP_MSG_DATA])) + _field("conn", _u32(cid))
        self.msg_header = _U32.pack(len(fixed) + 4 + 13) + fixed + _U32.pack(13) + b"time="
        self.record = _record([("op", bytes([_OP_CONNECTION])), ("conn", _u32(cid)),
                               ("topic", topic.encode())], body)


class Ros1Writer:
    """Writes one ROS 1 bag ``path`` (created; an existing file is refused).

    ``compression``: "none" or "bz2" (chunk compression). :meth:`flush` writes the pending chunk
    and fsyncs (the crash-safe point); :meth:`close` writes the index and the file header. A
    context manager: closes on success, aborts on an error.
    """

    def __init__(self, path: Path, compression: str = "none", chunk_threshold: int = CHUNK_THRESHOLD) -> None:
        if compression not in COMPRESSIONS:
            raise BagError(f"ROS 1 chunk compression {compression!r} is not one of {', '.join(COMPRESSIONS)}")
        self.path = Path(path)
        self.compression = compression
        self.chunk_threshold = chunk_threshold
        try:
            self._fh = self.path.open("xb")
        except OSError as err:
            raise BagWriteError(f"cannot create bag {self.path}: {err}") from err
        st = os.fstat(self._fh.fileno())
        self._identity = st.st_dev, st.st_ino
        self._fh.write(ROS1_MAGIC + ros1_file_header(0, 0, 0))
        self.connections: list[Ros1Connection] = []
        self._keys: dict[tuple[Any, ...], Ros1Connection] = {}
        self._unwritten: list[Ros1Connection] = []  # connection records not yet in any chunk
        self._chunk = bytearray()
        self._index: dict[int, list[bytes]] = {}  # conn -> (time, offset) entries of the pending chunk
        self._start = self._end = 0
        # chunk infos: (chunk position, start ns, end ns, {conn: count})
        self._chunks: list[tuple[int, int, int, dict[int, int]]] = []

    def add_connection(self, topic: str, msgtype: str, md5sum: str, msgdef: str, *,
                       callerid: str | None = None, latching: int | None = None) -> Ros1Connection:
        """A connection for ``topic`` of ``msgtype`` (ROS 1 form, ``pkg/Type``), its md5sum and
        full definition (with dependencies, as ``gendeps --cat``)."""
        key = (topic, msgtype, md5sum, msgdef, callerid, latching)
        if key in self._keys:
            return self._keys[key]
        conn = Ros1Connection(len(self.connections), topic, msgtype, md5sum, msgdef, callerid, latching)
        self.connections.append(conn)
        self._keys[key] = conn
        self._unwritten.append(conn)
        return conn

    def write(self, conn: Ros1Connection, t_ns: int, data: bytes) -> None:
        """Append ``data`` (ROS 1 serialized) on ``conn`` at bag time ``t_ns`` (ns)."""
        if self._unwritten:
            for c in self._unwritten:
                self._chunk += c.record
            self._unwritten.clear()
        chunk = self._chunk
        if not self._index:
            self._start = self._end = t_ns
        elif t_ns < self._start:
            self._start = t_ns
        elif t_ns > self._end:
            self._end = t_ns
        sec, nsec = divmod(t_ns, 1_000_000_000)
        self._index.setdefault(conn.id, []).append(struct.pack("<III", sec, nsec, len(chunk)))
        chunk += conn.msg_header
        chunk += _MSG_TAIL.pack(sec, nsec, len(data))
        chunk += data
        if len(chunk) > self.chunk_threshold:
            self._write_chunk()

    def _write_chunk(self) -> None:
        if not self._index:
            return
        raw = self._chunk  # written as it is, not copied: a chunk of one camera image is MBs
        data = bz2.compress(raw, 9) if self.compression == "bz2" else raw
        fh = self._fh
        pos = fh.tell()
        fh.write(_record_head([("op", bytes([_OP_CHUNK])), ("compression", self.compression.encode()),
                               ("size", _u32(len(raw)))], len(data)))
        fh.write(data)
        counts = {}
        for cid, entries in self._index.items():
            counts[cid] = len(entries)
            fh.write(_record([("op", bytes([_OP_INDEX_DATA])), ("ver", _u32(1)), ("conn", _u32(cid)),
                              ("count", _u32(len(entries)))], b"".join(entries)))
        self._chunks.append((pos, self._start, self._end, counts))
        self._chunk = bytearray()
        self._index = {}

    def flush(self) -> None:
        """Write the pending chunk (if it holds a message) and fsync: a crash keeps it. Raises
        :class:`BagWriteError` when the file was deleted or moved meanwhile."""
        self._write_chunk()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        check_still_there(self.path, self._identity)

    def close(self) -> None:
        """Write the pending chunk, the index (connections, chunk infos) and the file header."""
        self._write_chunk()
        fh = self._fh
        index_pos = fh.tell()
        for conn in self.connections:
            fh.write(conn.record)
        for pos, start, end, counts in self._chunks:
            fh.write(_record([("op", bytes([_OP_CHUNK_INFO])), ("ver", _u32(1)),
                              ("chunk_pos", struct.pack("<Q", pos)), ("start_time", _time(start)),
                              ("end_time", _time(end)), ("count", _u32(len(counts)))],
                             b"".join(_u32(c) + _u32(n) for c, n in counts.items())))
        fh.seek(len(ROS1_MAGIC))
        fh.write(ros1_file_header(index_pos, len(self.connections), len(self._chunks)))
        fh.flush()
        os.fsync(fh.fileno())
        fh.close()
        check_still_there(self.path, self._identity)

    def abort(self) -> None:
        """Close the file without writing the index."""
        self._fh.close()

    def __enter__(self) -> Ros1Writer:
        return self

    def __exit__(self, exc_type: Any, *_args: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
