"""Check bags and recover those whose recording was killed (SIGKILL, power loss) before they were closed.

What a killed :class:`~racecar_hw.bags.record.Recorder` leaves, and what this module does with it:

* MCAP (ROS 2): every closed split complete; the last file with its header and every chunk flushed
  so far, no summary and no footer. rosbags refuses it ("File end magic is invalid").
  :func:`recover_bag` scans the records of every file up to the last complete one and rewrites
  schemas, channels (with their QoS) and messages into a new, closed bag directory.
* ROS 1: the bag header with ``index_pos`` 0, then the chunks flushed so far. rosbags and rosbag
  refuse it ("not indexed"). :func:`recover_bag` scans the chunk records (none, bz2 or lz4) up to
  the last complete one and rewrites connections and messages into a new, indexed bag. An index
  is only trusted when it is consistent with the chunks (:func:`check_ros1_index`): a header
  pointing at garbage (a file rewritten by a tool with another header layout) is rebuilt too.
* sqlite3 (ROS 2): every committed transaction. The bag already reads as it is; :func:`recover_bag`
  rolls back a hot journal (by opening each database normally) and rewrites ``metadata.yaml`` in
  place (or in a copy of the bag, when given an output) with the real message counts.

A recording killed just after it opened a new split leaves that file empty (0 bytes, MCAP's magic
alone, a ROS 1 header, a database without tables): it holds no messages, and the other files are
read and recovered as they are.

:func:`inspect_bag` says which format a bag is in, which files it has, and whether it is complete
(and if not, why), without changing anything. The scanners are plain functions over the bytes of
a file, given as bytes or read from the file as they go (:mod:`racecar_hw.bags.filebytes`), so
they can be tested on truncated and damaged data and never hold a whole file.
"""

from __future__ import annotations

import shutil
import sqlite3
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any, TypeVar

import yaml
from rosbags.interfaces import Qos
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from racecar_hw.bags.filebytes import (
    ByteSource,
    FileBytes,
    MemoryBytes,
    as_source,
    occurrences,
    open_file_bytes,
    pieces,
)
from racecar_hw.bags.qos import dump_qos_v8
from racecar_hw.bags.ros1_writer import Ros1Writer
from racecar_hw.bags.validate import (
    DEFAULT_MAX_MESSAGE_BYTES,
    crc_mismatch,
    describe,
    guarded,
    inflate,
    listed_names,
    load_metadata,
    mcap_chunk_crc_error,
    open_regular,
)
from racecar_hw.bags.writers import (
    MCAP_CHUNK_CRC_OFFSET,
    RECORDING_OPEN,
    ROS1_MAGIC,
    ROS2_METADATA_VERSION,
    Ros2Bag,
)
from racecar_hw.base.errors import BagError, BagWriteError
from racecar_hw.base.text import one_line

MCAP_MAGIC = b"\x89MCAP0\r\n"

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


@dataclass
class RecoveryResult:
    """Where the readable bag is, how many messages it holds, and whether it was already closed."""

    path: Path
    messages: int
    was_complete: bool
    #: chunks left out because they fail their CRC-32, each named (file, number, byte offset)
    bad_chunks: list[str] = field(default_factory=list)


@dataclass
class BagState:
    """A bag's format (``ros1``, ``mcap``, ``sqlite3``), its storage files, and whether it is complete.

    ``problem`` says why it is not (empty when it is).
    """

    path: Path
    format: str
    files: list[Path]
    complete: bool
    problem: str = ""


# --- messages counted, not kept ---------------------------------------------------------------

#: Called by a scanner for each message it finds: (connection or channel id, time in ns, the
#: serialized message, a view valid only during the call: copy it to keep it).
MessageSink = Callable[[int, int, memoryview], None]


@dataclass
class Tally:
    """The messages a scan found, per connection (ROS 1) or channel (MCAP) id: how many, and the
    first and last time (ns). The messages themselves are not kept: a bag of sixteen 60 MB
    messages in 11 kB of bz2 took ``bag info`` to 1 GB when they were."""

    counts: dict[int, int] = field(default_factory=dict)
    first: dict[int, int] = field(default_factory=dict)
    last: dict[int, int] = field(default_factory=dict)

    def add(self, cid: int, t_ns: int) -> None:
        """Count one message on ``cid`` at ``t_ns`` (ns)."""
        n = self.counts.get(cid, 0)
        self.counts[cid] = n + 1
        if not n or t_ns < self.first[cid]:
            self.first[cid] = t_ns
        if not n or t_ns > self.last[cid]:
            self.last[cid] = t_ns

    @property
    def total(self) -> int:
        """Messages on every id."""
        return sum(self.counts.values())


#: The chunk compressions a recovered bag keeps, in order of preference, when its source used them;
#: any other (ROS 1 lz4, which the ROS 1 writer does not write) is written uncompressed.
ROS1_COMPRESSIONS = ("bz2",)
MCAP_COMPRESSIONS = ("zstd", "lz4")


def kept_compression(found: set[str], supported: tuple[str, ...]) -> str:
    """The chunk compression a recovered bag is written with: the first of ``supported`` among the
    compressions ``found`` in its source's chunks, else ``none``. A small bag of compressible
    messages (sixteen 60 MB messages in 11 KB of bz2) stays small, where it was written out whole
    (960 MB)."""
    return next((c for c in supported if c in found), "none")


# --- MCAP -------------------------------------------------------------------------------------


@dataclass
class McapScan:
    """Records found in an MCAP file, up to the first truncated one; messages are counted
    (``tally``), not kept."""

    schemas: dict[int, tuple[str, str, bytes]]          # id -> (name, encoding, data)
    channels: dict[int, tuple[int, str, str]]           # id -> (schema id, topic, encoding)
    complete: bool = False                               # a footer was found
    qos: dict[int, str] = field(default_factory=dict)   # channel id -> offered_qos_profiles
    #: the chunks left out because they fail their CRC-32 (:func:`crc_mismatch`, without the path)
    bad_chunks: list[str] = field(default_factory=list)
    tally: Tally = field(default_factory=Tally)         # messages per channel id, counted
    compressions: set[str] = field(default_factory=set)  # of the chunks ("none", "zstd", "lz4")


def scan_mcap(data: bytes | ByteSource, on_message: MessageSink | None = None) -> McapScan:
    """Every schema and channel in ``data`` (bytes, or a file's :class:`ByteSource`) up to the first
    truncated record, its messages counted (``tally``) and, if given, passed to ``on_message`` one at
    a time, none of them kept: memory holds one record or chunk (a compressed one decompressed: at
    most DEFAULT_MAX_MESSAGE_BYTES), not the file.

    An empty ``data``, or one cut inside the magic (a split killed as it was opened), holds nothing.
    A chunk that carries a CRC-32 its records do not have is left out whole (``bad_chunks``): the
    good chunks are kept. A closed file repeats the schemas and channels after its chunks, so the
    other chunks' messages keep their channels even when the damaged chunk defined them: a caller
    that needs every message's channel scans twice (once for the channels, once with ``on_message``).
    """
    src = as_source(data)
    head = bytes(src.read(0, len(MCAP_MAGIC)))
    if head != MCAP_MAGIC:
        if MCAP_MAGIC.startswith(head):
            return McapScan({}, {})
        raise BagError("not an MCAP file (bad magic)")
    scan = McapScan({}, {})
    chunks = 0
    for pos, op, start, length in _mcap_records_at(src, len(MCAP_MAGIC)):
        if op == 0x06:
            chunks += 1
            _mcap_chunk(src, start, length, scan, chunks, pos, on_message)
        elif op == 0x02:
            scan.complete = True
        elif op in _MCAP_SCANNED:
            _mcap_record(op, src.read(start, length), scan, on_message)
    return scan


#: The MCAP records a scan reads (schema, channel, message); it steps over the others (indexes,
#: statistics, attachments, metadata) without reading them.
_MCAP_SCANNED = frozenset((0x03, 0x04, 0x05))


def _mcap_records_at(src: ByteSource, pos: int) -> Iterator[tuple[int, int, int, int]]:
    """(offset, opcode, offset of the body, length of the body) of each record from ``pos`` up to the
    first one cut off; the bodies are not read."""
    end = src.size
    while pos + 9 <= end:
        head = src.read(pos, 9)
        op = head[0]
        (length,) = _U64.unpack_from(head, 1)
        stop = pos + 9 + length
        if stop > end:
            return
        yield pos, op, pos + 9, length
        pos = stop


def _mcap_string(body: memoryview, pos: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(body, pos)
    return bytes(body[pos + 4:pos + 4 + n]).decode(), pos + 4 + n


def _mcap_chunk(src: ByteSource, start: int, length: int, scan: McapScan, number: int, at: int,
                on_message: MessageSink | None) -> None:
    """The records of chunk ``number`` (1 = the first), at byte ``at``, its body the ``length`` bytes
    at ``start``, into ``scan``; none of them when the chunk fails its CRC-32. A compressed chunk is
    read in pieces as it is decompressed, an uncompressed one whole."""
    head = src.read(start, min(length, 32))
    (n,) = _U32.unpack_from(head, 28)  # the compression's name, then the records' length
    head = src.read(start, min(length, 32 + n + 8))
    compression, pos = _mcap_string(head, 28)
    (size,) = _U64.unpack_from(head, pos)
    first = start + pos + 8
    size = max(0, min(size, start + length - first))  # no further than the chunk
    records: memoryview | bytearray
    if compression in ("lz4", "zstd"):
        (declared,) = _U64.unpack_from(head, 16)
        records = _decompress(pieces(src, first, size), compression, declared,
                              f"chunk {number} (at byte {at})")
    elif compression:
        raise BagError(f"MCAP chunk compression {compression!r} is not supported by the recovery")
    else:
        records = src.read(first, size)
    scan.compressions.add(compression or "none")
    (recorded,) = _U32.unpack_from(head, MCAP_CHUNK_CRC_OFFSET - 9)
    if recorded:
        computed = zlib.crc32(records)
        if computed != recorded:
            scan.bad_chunks.append(crc_mismatch("", number, at, recorded, computed, hint=False)[2:])
            return
    inner = MemoryBytes(records)
    for _at, op, body, n in _mcap_records_at(inner, 0):
        if op in _MCAP_SCANNED:
            _mcap_record(op, inner.read(body, n), scan, on_message)


def _decompress(pieces: Iterable[memoryview], compression: str, declared: int, where: str) -> bytearray:
    """A chunk's records (the chunk ``where``: its number or offset; its data given in ``pieces``),
    decompressed in bounded steps: no more than the ``declared`` size, nor than the largest chunk
    the follower reads (DEFAULT_MAX_MESSAGE_BYTES), else BagError. Grown in place, so the chunk is
    in memory once."""
    bound = min(declared, DEFAULT_MAX_MESSAGE_BYTES)
    what = f"the {compression} {where} declaring {declared} bytes uncompressed"
    out = bytearray()
    try:
        for piece in inflate(pieces, compression, bound, what):
            out += piece
    except BagError:
        if declared <= bound:  # it lies about its size
            raise
        raise BagError(f"the {compression} {where} holds more than {bound} bytes uncompressed (it declares "
                       f"{declared}), over the limit of {bound} (max_message_bytes) a chunk may have; "
                       "refused") from None
    return out


def _mcap_record(op: int, body: memoryview, scan: McapScan, on_message: MessageSink | None) -> None:
    if op == 0x03:
        (sid,) = _U16.unpack_from(body, 0)
        name, pos = _mcap_string(body, 2)
        encoding, pos = _mcap_string(body, pos)
        (n,) = _U32.unpack_from(body, pos)
        scan.schemas[sid] = (name, encoding, bytes(body[pos + 4:pos + 4 + n]))
    elif op == 0x04:
        cid, sid = struct.unpack_from("<HH", body, 0)
        topic, pos = _mcap_string(body, 4)
        encoding, pos = _mcap_string(body, pos)
        scan.channels[cid] = (sid, topic, encoding)
        (size,) = _U32.unpack_from(body, pos)
        pos += 4
        stop = pos + size
        while pos < stop:
            key, pos = _mcap_string(body, pos)
            value, pos = _mcap_string(body, pos)
            if key == "offered_qos_profiles":
                scan.qos[cid] = value
    elif op == 0x05:
        cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", body, 0)
        scan.tally.add(cid, log_time)
        if on_message is not None:
            on_message(cid, log_time, body[22:])


def _cannot_write(target: Path, err: BaseException) -> BagWriteError:
    """``err`` (an OSError, or a BagError raised for one) met writing the recovery's output ``target``,
    as one line naming ``target`` and the OS's reason: the disk's fault, not the bag's (a full disk
    was said as "cannot read bag <input>: damaged data (OSError: [Errno 28] ...)")."""
    cause = err if isinstance(err, OSError) else err.__cause__
    reason = cause.strerror if isinstance(cause, OSError) and cause.strerror else one_line(err, 160)
    return BagWriteError(f"cannot write {target}: {reason}")


@contextmanager
def _staged(target: Path) -> Iterator[Path]:
    """Where to write the recovered bag ``target`` (a file or a directory): in a hidden folder beside
    it, renamed to ``target`` once the writing is done; on any exception, Ctrl-C included, the
    folder is removed and ``target`` never appears half written (which a later recover would refuse
    to overwrite, and which would look like another interrupted bag). The source bag is untouched."""
    folder = target.parent / f".{target.name}.partial"
    shutil.rmtree(folder, ignore_errors=True)  # an earlier attempt's, stopped before it could clean
    try:
        folder.mkdir(parents=True)
    except OSError as err:
        raise _cannot_write(target, err) from err
    try:
        yield folder / target.name
        try:
            (folder / target.name).rename(target)
        except OSError as err:
            raise _cannot_write(target, err) from err
    finally:
        shutil.rmtree(folder, ignore_errors=True)


W = TypeVar("W", Ros2Bag, Ros1Writer)


@contextmanager
def _output(target: Path, open_writer: Callable[[], W]) -> Iterator[W]:
    """The writer of the recovered bag ``target`` (``open_writer`` makes it, in the staging folder):
    closed when the body is done, aborted when it fails. An OSError opening or closing it is said
    as :func:`_cannot_write`, naming ``target``; the body's writes go through :func:`_write_to`."""
    try:
        writer = open_writer()
    except (OSError, BagWriteError) as err:
        raise _cannot_write(target, err) from err
    try:
        yield writer
    except BaseException:
        with suppress(Exception):  # closing flushes the buffered bytes: on a full disk, it fails too
            writer.abort()
        raise
    try:
        writer.close()
    except OSError as err:
        with suppress(Exception):
            writer.abort()
        raise _cannot_write(target, err) from err


def _write_to(target: Path, write: Callable[..., None], *args: Any) -> None:
    """``write(*args)`` into the recovered bag ``target``; an OSError is said as :func:`_cannot_write`
    (the scan around it reads the input, whose errors stay "damaged data")."""
    try:
        write(*args)
    except OSError as err:
        raise _cannot_write(target, err) from err


def _recover_mcap(files: list[Path], out: Path) -> RecoveryResult:
    """Two passes over each file: its schemas and channels (which a closed file repeats after the
    chunks), then its messages, written one at a time (none is kept: memory holds one chunk, not the
    file)."""
    scans = [_scan_mcap_file(f) for f in files]
    store = get_typestore(Stores.EMPTY)
    compression = kept_compression(set().union(*(scan.compressions for scan in scans)), MCAP_COMPRESSIONS)
    with _staged(out) as staging, _output(out, lambda: Ros2Bag(staging, "mcap", compression)) as writer:
        conns = {}  # (topic, type, qos) -> connection, over every file
        count = 0
        for file, scan in zip(files, scans, strict=True):
            for name, _enc, text in scan.schemas.values():
                if name not in store.types:
                    store.register(get_types_from_msg(text.decode(), name))
            mine = {}
            for cid, (sid, topic, _enc) in scan.channels.items():
                name, _enc2, text = scan.schemas[sid]
                qos = scan.qos.get(cid, "")
                key = (topic, name, qos)
                if key not in conns:
                    conns[key] = writer.add_connection(topic, name, text.decode(), store.hash_rihs01(name),
                                                       dump_qos_v8(_qos(qos)))
                mine[cid] = conns[key]

            def write(cid: int, t_ns: int, payload: memoryview, mine: dict[int, int] = mine) -> None:
                if cid in mine:
                    _write_to(out, writer.write, mine[cid], t_ns, payload)

            _scan_mcap_file(file, write)
            count += sum(n for cid, n in scan.tally.counts.items() if cid in mine)
    bad = [f"{f.name}: {text}" for f, scan in zip(files, scans, strict=True) for text in scan.bad_chunks]
    return RecoveryResult(out, count, False, bad)


def _scan_mcap_file(file: Path, on_message: MessageSink | None = None) -> McapScan:
    """:func:`scan_mcap` of the file ``file``, read from it as the scan goes."""
    with open_file_bytes(file) as data:
        return scan_mcap(data, on_message)


def _qos(text: str) -> list[Qos]:
    from rosbags.rosbag2.metadata import parse_qos  # noqa: PLC0415 - rosbags' bag package, for reading only

    try:
        return parse_qos(text)
    except Exception:  # a profile we cannot parse: the message data matters more than its QoS
        return []


# --- ROS 1 ------------------------------------------------------------------------------------


@dataclass
class Ros1Scan:
    """Connections and messages found in a ROS 1 bag, up to the first truncated record; messages
    are counted (``tally``), not kept."""

    connections: dict[int, dict[str, bytes]]            # id -> connection header fields
    indexed: bool = False                                # the bag header points at an index
    index_pos: int = 0
    conn_count: int = 0
    chunk_count: int = 0
    chunks: list[int] = field(default_factory=list)     # file offsets of the chunk records
    damaged: list[int] = field(default_factory=list)    # offsets of unreadable records stepped over
    tally: Tally = field(default_factory=Tally)         # messages per connection id, counted
    compressions: set[str] = field(default_factory=set)  # of the chunks ("none", "bz2", "lz4")


#: A record: its header fields, and the offset and length of its data (not read)
_Record = tuple[dict[str, bytes], int, int]


def scan_ros1(data: bytes | ByteSource, on_message: MessageSink | None = None) -> Ros1Scan:
    """Every connection in the chunks of ``data`` (bytes, or a file's :class:`ByteSource`) up to the
    first truncated record, and its messages counted (``tally``) and, if given, passed to
    ``on_message`` one at a time, none of them kept: memory holds one chunk (a compressed one
    decompressed: at most DEFAULT_MAX_MESSAGE_BYTES), not the file.

    The file header is read by its own length fields, so both layouts (rosbag's and rosbags')
    work. Damaged bytes between records (a chunk whose start was overwritten) are stepped over
    to the next chunk record.
    """
    src = as_source(data)
    if bytes(src.read(0, len(ROS1_MAGIC))) != ROS1_MAGIC:
        raise BagError("not a ROS 1 bag (bad magic)")
    scan = Ros1Scan({})
    pos = len(ROS1_MAGIC)
    end = src.size
    while pos + 8 <= end:  # chunks, then (in a closed bag) the index's connection and chunk-info records
        record = _ros1_record_at(src, pos, end)
        if record is None:
            if _ros1_truncated(src, pos, end):
                break
            found = _ros1_next_chunk(src, pos, end)
            if found is None:
                break
            scan.damaged.append(pos)
            pos, record = found
        fields, start, length = record
        op = fields.get("op", b"\x00")[0]
        if op == 0x03:
            scan.index_pos = _U64.unpack(fields["index_pos"])[0]
            scan.conn_count = _U32.unpack(fields["conn_count"])[0]
            scan.chunk_count = _U32.unpack(fields["chunk_count"])[0]
            scan.indexed = scan.index_pos != 0
        elif op == 0x05:
            scan.chunks.append(pos)
            _ros1_chunk(src, record, scan, pos, on_message)
        else:
            _ros1_record(src, record, scan, on_message)
        pos = start + length
    return scan


def _ros1_chunk(src: ByteSource, chunk: _Record, scan: Ros1Scan, at: int,
                on_message: MessageSink | None) -> None:
    """The records of the chunk record at byte ``at`` into ``scan``: a compressed chunk read in pieces
    as it is decompressed, an uncompressed one whole."""
    fields, start, length = chunk
    compression = fields["compression"].decode()
    if compression in ("bz2", "lz4"):
        size = fields["size"]
        declared = _U32.unpack(size)[0] if len(size) == 4 else DEFAULT_MAX_MESSAGE_BYTES
        records = MemoryBytes(_decompress(pieces(src, start, length), compression, declared,
                                          f"chunk at byte {at}"))
    elif compression == "none":
        records = MemoryBytes(src.read(start, length))
    else:
        raise BagError(f"unknown ROS 1 chunk compression {compression!r}")
    scan.compressions.add(compression)
    for record in _ros1_records(records):
        _ros1_record(records, record, scan, on_message)


def _ros1_fields(header: bytes) -> dict[str, bytes] | None:
    fields: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(header):
        (n,) = _U32.unpack_from(header, pos)
        if pos + 4 + n > len(header):
            return None
        name, eq, value = header[pos + 4:pos + 4 + n].partition(b"=")
        if not eq or not name:
            return None
        fields[name.decode(errors="replace")] = value
        pos += 4 + n
    return fields if pos == len(header) else None


def _u32_at(src: ByteSource, pos: int) -> int:
    return int(_U32.unpack(src.read(pos, 4))[0])


def _ros1_truncated(src: ByteSource, pos: int, end: int) -> bool:
    """Whether the record at ``pos`` runs past ``end`` (an interrupted write)."""
    hlen = _u32_at(src, pos)
    if pos + 8 + hlen > end:
        return hlen < 1 << 20  # plausible length: cut off; else garbage
    dlen = _u32_at(src, pos + 4 + hlen)
    return pos + 8 + hlen + dlen > end and _ros1_fields(bytes(src.read(pos + 4, hlen))) is not None


def _ros1_record_at(src: ByteSource, pos: int, end: int) -> _Record | None:
    """The record at ``pos`` (ending by ``end``): its fields and where its data is; None if damaged."""
    head = src.read(pos, 256)  # the lengths and header of most records, in one read
    (hlen,) = _U32.unpack_from(head, 0)
    if pos + 8 + hlen > end:
        return None
    if len(head) < 8 + hlen:
        head = src.read(pos, 8 + hlen)
    fields = _ros1_fields(bytes(head[4:4 + hlen]))
    if not fields or "op" not in fields or len(fields["op"]) != 1:
        return None
    (dlen,) = _U32.unpack_from(head, 4 + hlen)
    start = pos + 8 + hlen
    if start + dlen > end:
        return None
    if fields["op"][0] == 0x05 and not {"compression", "size"} <= set(fields):
        return None
    return fields, start, dlen


_CHUNK_OP = _U32.pack(4) + b"op=\x05"


def _ros1_next_chunk(src: ByteSource, pos: int, end: int) -> tuple[int, _Record] | None:
    """The next chunk record at or after ``pos`` whose header and data parse, or None.

    Rewriting a bag's header with a longer layout overwrites the first chunk's header length;
    its fields after that are intact, so a chunk record whose op field starts 4 bytes in is
    read from its fields (op, compression, size: the three a chunk header has).
    """
    for found in occurrences(src, b"op=\x05", pos, end):
        start = found - 8  # the record's two length fields may be the damaged bytes before pos
        if start < len(ROS1_MAGIC):
            continue
        record = _ros1_record_at(src, start, end) if bytes(src.read(found - 4, 8)) == _CHUNK_OP else None
        if record is None:
            record = _ros1_chunk_from_fields(src, found, end)
        if record is not None:
            return start, record
    return None


def _ros1_chunk_from_fields(src: ByteSource, op_at: int, end: int) -> _Record | None:
    fields: dict[str, bytes] = {"op": b"\x05"}
    pos = op_at + 4
    while pos + 4 <= end and not {"compression", "size"} <= set(fields):
        n = _u32_at(src, pos)
        if n > 64 or pos + 4 + n > end:
            return None
        name, eq, value = bytes(src.read(pos + 4, n)).partition(b"=")
        if not eq or name not in (b"compression", b"size"):
            return None
        fields[name.decode()] = value
        pos += 4 + n
    if pos + 4 > end or len(fields.get("size", b"")) != 4:
        return None
    dlen = _u32_at(src, pos)
    if pos + 4 + dlen > end:
        return None
    return fields, pos + 4, dlen


def _ros1_records(src: ByteSource) -> Iterator[_Record]:
    """The records of a chunk's data, up to the first damaged one."""
    pos = 0
    while pos + 8 <= src.size:
        record = _ros1_record_at(src, pos, src.size)
        if record is None:
            return
        yield record
        pos = record[1] + record[2]


def _ros1_record(src: ByteSource, record: _Record, scan: Ros1Scan, on_message: MessageSink | None) -> None:
    fields, start, length = record
    op = fields.get("op", b"\x00")[0]
    if op == 0x07:
        (cid,) = _U32.unpack(fields["conn"])
        conn = _ros1_fields(bytes(src.read(start, length)))
        if conn is not None:
            scan.connections.setdefault(cid, conn)
    elif op == 0x02:
        (cid,) = _U32.unpack(fields["conn"])
        sec, nsec = struct.unpack("<II", fields["time"])
        t_ns = sec * 1_000_000_000 + nsec
        scan.tally.add(cid, t_ns)
        if on_message is not None:
            on_message(cid, t_ns, src.read(start, length))


def check_ros1_index(data: bytes | ByteSource, scan: Ros1Scan) -> str:
    """Why the index of a scanned bag (``data``: bytes, or a file's :class:`ByteSource`) cannot be
    trusted; empty when it can.

    Trusted: the header points inside the file at ``conn_count`` connection records and
    ``chunk_count`` chunk-info records, every chunk info points at a chunk record, and the
    chunk infos count exactly the messages the chunks hold.
    """
    src = as_source(data)
    size = src.size
    if not scan.indexed:
        return "not indexed (index_pos 0: the recording was not closed)"
    if scan.damaged:
        return (f"damaged bytes at offset {scan.damaged[0]} (a chunk was overwritten, e.g. by a tool "
                "rewriting the file header in another layout)")
    if not len(ROS1_MAGIC) < scan.index_pos <= size:  # an empty index ends the file
        return f"the header's index_pos {scan.index_pos} is outside the file ({size} bytes)"
    conns = infos = counted = 0
    chunks = set(scan.chunks)
    pos = scan.index_pos
    while pos + 8 <= size:
        record = _ros1_record_at(src, pos, size)
        if record is None:
            return f"unreadable index record at byte {pos}"
        fields, start, length = record
        pos = start + length
        op = fields["op"][0]
        if op == 0x07:
            conns += 1
        elif op == 0x06:
            infos += 1
            (chunk_pos,) = _U64.unpack(fields["chunk_pos"])
            if chunk_pos not in chunks:
                return f"the index names a chunk at byte {chunk_pos}, where there is none"
            body = src.read(start, length)
            counted += sum(_U32.unpack_from(body, i + 4)[0] for i in range(0, len(body) - 7, 8))
        else:
            return f"unexpected record (op {op}) in the index at byte {pos}"
    if conns != scan.conn_count or infos != scan.chunk_count:
        return (f"the header counts {scan.conn_count} connections and {scan.chunk_count} chunks, "
                f"the index holds {conns} and {infos}")
    if infos != len(scan.chunks) or counted != scan.tally.total:
        return (f"the index counts {counted} messages in {infos} chunks, the file holds "
                f"{scan.tally.total} in {len(scan.chunks)}")
    return ""


def _recover_ros1(file: Path, out: Path) -> RecoveryResult:
    """Two passes: the connections (and whether the index can be trusted), then the messages,
    written one at a time (none is kept: memory holds one chunk, not the file)."""
    with open_file_bytes(file) as data:
        return _rewrite_ros1(data, out)


def _rewrite_ros1(data: FileBytes, out: Path) -> RecoveryResult:
    scan = scan_ros1(data)
    if not check_ros1_index(data, scan):
        return RecoveryResult(data.path, scan.tally.total, True)
    compression = kept_compression(scan.compressions, ROS1_COMPRESSIONS)
    with _staged(out) as staging, _output(out, lambda: Ros1Writer(staging, compression)) as writer:
        conns = {}
        for cid, f in scan.connections.items():
            latching = f.get("latching")
            conns[cid] = writer.add_connection(
                f["topic"].decode(), f["type"].decode(), f["md5sum"].decode(),
                f["message_definition"].decode(),
                callerid=f["callerid"].decode() if "callerid" in f else None,
                latching=int(latching) if latching else None)

        def write(cid: int, t_ns: int, payload: memoryview) -> None:
            if cid in conns:
                _write_to(out, writer.write, conns[cid], t_ns, payload)

        scan_ros1(data, write)
        count = sum(n for cid, n in scan.tally.counts.items() if cid in conns)
    return RecoveryResult(out, count, False)


# --- sqlite3 ----------------------------------------------------------------------------------


@dataclass
class DbContent:
    """What one sqlite3 storage file holds; ``empty``: no table at all (0 bytes, or the recording
    was killed as it created them), which is a file holding no messages."""

    path: Path
    topics: list[tuple[int, str, str, str, str, str]]  # id, name, type, format, qos, hash
    counts: dict[int, int]
    start: int
    end: int
    empty: bool = False



def read_db(db: Path, *, readonly: bool = False) -> DbContent:
    """Topics, message counts per topic id and time range (ns) of the sqlite3 file ``db``.

    ``readonly``: change nothing (for ``bag info``); otherwise opening it rolls back a hot journal.
    """
    if _size(db) == 0:
        return DbContent(db, [], {}, 0, 0, empty=True)
    try:
        # immutable: no lock, no -shm or -wal file created next to a bag that may be read-only
        con = sqlite3.connect(f"file:{db}?immutable=1", uri=True) if readonly else sqlite3.connect(db)
        try:
            tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if not tables:  # one without the other is a damaged file, and an error below
                return DbContent(db, [], {}, 0, 0, empty=True)
            columns = {row[1] for row in con.execute("PRAGMA table_info(topics)")}
            digest = "type_description_hash" if "type_description_hash" in columns else "''"
            topics = con.execute(f"SELECT id, name, type, serialization_format, offered_qos_profiles,"
                                 f" {digest} FROM topics ORDER BY id").fetchall()
            counts = dict(con.execute("SELECT topic_id, count(*) FROM messages GROUP BY topic_id"))
            lo, hi = con.execute("SELECT min(timestamp), max(timestamp) FROM messages").fetchone()
        finally:
            con.close()
    except sqlite3.Error as err:
        if err.sqlite_errorcode == sqlite3.SQLITE_FULL:  # rolling back a journal onto a full disk
            raise BagWriteError(f"cannot write {db}: {err}") from err
        raise BagError(f"{db} is not a readable sqlite3 bag: {err}") from err
    return DbContent(db, topics, counts, lo or 0, hi or 0)


def _sqlite3_problem(bagdir: Path, dbs: list[Path]) -> str:
    meta, unusable = load_metadata(bagdir)
    if meta is None:
        return unusable
    # A hot rollback journal is a transaction that never finished. (A -wal file is not: in WAL
    # mode it holds committed transactions until a checkpoint, and readers take them.)
    hot = [db.name for db in dbs if _hot_journal(db.parent / f"{db.name}-journal")]
    if hot:
        return f"{', '.join(hot)} has a journal left by an interrupted write"
    listed = set(listed_names(meta))
    contents = []
    for db in dbs:
        try:
            content = read_db(db, readonly=True)
        except BagError as err:
            return f"{db.name} is not readable: {err.__cause__ or err}"
        if content.empty and db.name in listed:  # unlisted and empty: not part of the bag
            return (f"{db.name} is empty ({_size(db)} bytes, no tables): the recording was killed "
                    "as it opened this split")
        contents.append(content)
    custom = meta.get("custom_data")
    if isinstance(custom, dict) and custom.get("racecar_hw") == RECORDING_OPEN:
        return "the recording was not closed (metadata.yaml is from its last flush)"
    said = _listed_counts(meta)
    for content in contents:
        name, n = content.path.name, sum(content.counts.values())
        if name in said and said[name] != n:
            return f"metadata.yaml counts {said[name]} messages in {name}, it holds {n}"
    return ""


def _hot_journal(path: Path) -> bool:
    """Whether a rollback journal holds a transaction to roll back, as SQLite judges it: not empty
    and its first byte not zero. A journal whose header is zeroed is finished: SQLite leaves it so
    in PERSIST mode, or after a rollback that could not delete it, and never rolls it back."""
    try:
        with open_regular(path) as f:
            return f.read(1) not in (b"", b"\0")
    except (OSError, BagError):
        return _size(path) > 0  # there but unreadable, or not a regular file: not to be trusted


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _recover_sqlite3(bagdir: Path, dbs: list[Path]) -> RecoveryResult:
    # Opening a database read-write rolls back its journal wherever the database really is: through a
    # link, that can be outside the bag. (A copy, -o OUT, holds the linked files' contents instead.)
    for db in dbs:
        for part in (db, *(db.with_name(db.name + end) for end in ("-journal", "-wal", "-shm"))):
            if part.is_symlink():
                raise BagError(f"{part} is a symbolic link: not recovered in place, which could change "
                               "the file it points to outside the bag; give an output (-o OUT) to "
                               "recover a copy")
    # a file without tables holds nothing: left out of metadata.yaml, which readers go by
    contents = [c for c in (read_db(db) for db in dbs) if not c.empty]
    topics: dict[str, dict[str, object]] = {}
    counts: dict[str, int] = {}
    for c in contents:
        for tid, name, typ, fmt, qos, digest in c.topics:
            topics.setdefault(name, {"name": name, "type": typ, "serialization_format": fmt,
                                     "offered_qos_profiles": dump_qos_v8(_qos(qos or "")),
                                     "type_description_hash": digest or ""})
            counts[name] = counts.get(name, 0) + c.counts.get(tid, 0)
    used = [c for c in contents if sum(c.counts.values())]
    start = min((c.start for c in used), default=0)
    end = max((c.end for c in used), default=0)
    total = sum(counts.values())
    info = {
        "version": ROS2_METADATA_VERSION, "storage_identifier": "sqlite3",
        "relative_file_paths": [c.path.name for c in contents],
        "duration": {"nanoseconds": end - start},
        "starting_time": {"nanoseconds_since_epoch": start}, "message_count": total,
        "topics_with_message_count": [{"topic_metadata": t, "message_count": counts[name]}
                                      for name, t in topics.items()],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": c.path.name, "starting_time": {"nanoseconds_since_epoch": c.start},
                   "duration": {"nanoseconds": c.end - c.start},
                   "message_count": sum(c.counts.values())} for c in contents],
        "custom_data": {"racecar_hw": "recovered"}, "ros_distro": "rosbags",
    }
    meta = bagdir / "metadata.yaml"
    tmp = meta.with_suffix(".yaml.tmp")
    try:
        tmp.unlink(missing_ok=True)  # a file (or a link to one outside the bag) left there is not written in
        tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False), "utf8")
        tmp.replace(meta)
    except OSError as err:
        with suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise _cannot_write(meta, err) from err
    return RecoveryResult(bagdir, total, False)


# --- which bag, which files, complete? --------------------------------------------------------


def _metadata(bagdir: Path) -> dict | None:
    return load_metadata(bagdir)[0]


def _listed_counts(meta: dict) -> dict[str, int]:
    """Message count per file name from ``files``; entries not as rosbag2 writes them are left out."""
    files = meta.get("files")
    counts: dict[str, int] = {}
    for f in files if isinstance(files, list) else []:
        if isinstance(f, dict) and isinstance(f.get("path"), str):
            n = f.get("message_count")
            if isinstance(n, int) and not isinstance(n, bool):
                counts[PurePath(f["path"]).name] = n
    return counts


def _storage_files(bagdir: Path, suffix: str) -> list[Path]:
    """The bag's files, all in ``bagdir``: in metadata.yaml's order, then any other on disk (written
    after it)."""
    listed = [bagdir / name for name in listed_names(_metadata(bagdir) or {}) if name.endswith(suffix)]
    listed = [p for p in listed if p.is_file()]
    extra = sorted(p for p in bagdir.glob(f"*{suffix}") if p not in listed and p.is_file())
    return listed + extra


@guarded
def inspect_bag(path: str | Path) -> BagState:
    """Format, files and completeness of the bag at ``path``; nothing is changed.

    Raises :class:`BagError` for a missing path, an empty file and a directory with no storage.
    """
    src = Path(path)
    if not src.exists():
        raise BagError(f"bag not found: {src}")
    if src.is_file():
        if src.stat().st_size == 0:
            raise BagError(f"{src} is empty (0 bytes): nothing was flushed before the recording ended")
        with open_file_bytes(src) as data:
            head = bytes(data.read(0, len(ROS1_MAGIC)))
            if ROS1_MAGIC.startswith(head) and data.size <= len(ROS1_MAGIC):
                raise BagError(f"{src} holds only {data.size} bytes, a cut-off bag header: nothing was "
                               "flushed before the recording ended")
            if not head.startswith(MCAP_MAGIC):
                problem = check_ros1_index(data, scan_ros1(data))
                return BagState(src, "ros1", [src], not problem, problem)
        src = src.parent  # a ROS 2 bag's .mcap file: the bag is its directory
    mcaps = _storage_files(src, ".mcap")
    dbs = _storage_files(src, ".db3")
    if mcaps:
        for f in mcaps:
            size = f.stat().st_size
            if size <= len(MCAP_MAGIC):  # nothing past the magic: killed as this split was opened
                return BagState(src, "mcap", mcaps, False,
                                f"{f.name} is empty ({size} bytes): the recording was killed as it "
                                "opened this split; it holds no messages")
            with f.open("rb") as fh:
                fh.seek(size - len(MCAP_MAGIC))
                if size < 2 * len(MCAP_MAGIC) or fh.read() != MCAP_MAGIC:
                    return BagState(src, "mcap", mcaps, False,
                                    f"{f.name} has no footer (the recording was not closed)")
        meta, unusable = load_metadata(src)
        if meta is None:
            return BagState(src, "mcap", mcaps, False, unusable)
        for f in mcaps:
            bad = mcap_chunk_crc_error(f)
            if bad is not None:
                return BagState(src, "mcap", mcaps, False, bad)
        return BagState(src, "mcap", mcaps, True)
    if dbs:
        problem = _sqlite3_problem(src, dbs)
        return BagState(src, "sqlite3", dbs, not problem, problem)
    raise BagError(f"{src} holds no .mcap or .db3 file: not a ROS 2 bag")


@guarded
def recover_bag(path: str | Path, out: str | Path | None = None) -> RecoveryResult:
    """Make the bag at ``path`` readable after an interrupted recording; a bag too damaged for that
    gives a :class:`BagError` naming it and the cause, and nothing else.

    MCAP and ROS 1 bags are rewritten to ``out`` (default: ``<name>.recovered`` next to it for a
    ROS 2 directory, ``<stem>.recovered.bag`` for ROS 1); sqlite3 bags are fixed in place, or in a
    copy at ``out`` when it is given. A bag that was closed normally is left alone
    (``was_complete``). An empty split file (a recording killed as it opened a new split) holds no
    messages; the other files' messages are all kept.
    """
    state = inspect_bag(path)
    src = state.path
    if out is not None and Path(out).exists():
        raise BagError(f"{out} exists already, not overwriting")
    if state.format == "ros1":
        target = Path(out) if out else src.with_name(f"{src.stem}.recovered.bag")
        if not state.complete and target.exists():
            raise BagError(f"{target} exists already, not overwriting (give another output)")
        return _recover_ros1(src, target)
    if state.format == "mcap":
        if state.complete:
            messages = sum(_scan_mcap_file(f).tally.total for f in state.files)
            return RecoveryResult(src, messages, True)
        if all(_size(f) <= len(MCAP_MAGIC) for f in state.files):
            raise BagError(f"nothing to recover: every file of {src} is empty (the recording was "
                           "killed before it wrote anything)")
        target = Path(out) if out else src.with_name(f"{src.name}.recovered")
        if target.exists():
            raise BagError(f"{target} exists already, not overwriting (give another output)")
        return _recover_mcap(state.files, target)
    if state.complete:
        return RecoveryResult(src, sum(sum(read_db(db).counts.values()) for db in state.files), True)
    if out is None:
        return _recover_sqlite3(src, state.files)
    # a copy to fix, the bag as it was left alone (journals and WAL files go along)
    target = Path(out)
    try:
        target.mkdir(parents=True)
    except FileExistsError as err:
        raise BagError(f"{out} exists already, not overwriting") from err
    except OSError as err:
        raise _cannot_write(target, err) from err
    try:  # a copy that fails (a full disk) is removed: a retry would refuse an OUT that exists
        _copy_bag(src, target)
        return _recover_sqlite3(target, [target / f.name for f in state.files])
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        raise


#: Bytes copied at a time by :func:`_copy_bag`.
COPY_STEP = 1 << 20


def _copy_bag(src: Path, target: Path) -> None:
    """The bag directory ``src`` copied into the (new, empty) directory ``target``, each file's
    contents as :func:`shutil.copytree` copies them, a failure said in one line: reading ``src`` as
    the bag's (``cannot read bag``), writing as ``target``'s (:func:`_cannot_write`). (copytree's
    own error was the Python list of every file's (source, destination, error).)"""

    def copy_file(from_path: str, to_path: str) -> None:
        try:  # a FIFO would block the copy: refused (BagError), as every reader here refuses it
            fin = open_regular(Path(from_path))
        except OSError as err:
            raise BagError(f"cannot read bag file {from_path}: {describe(err)}") from err
        with fin:
            try:
                fout = open(to_path, "xb", buffering=0)  # noqa: SIM115 - as fin
            except OSError as err:
                raise _cannot_write(target, err) from err
            with fout:
                while True:
                    try:
                        block = fin.read(COPY_STEP)
                    except OSError as err:
                        raise BagError(f"cannot read bag file {from_path}: {describe(err)}") from err
                    if not block:
                        break
                    view = memoryview(block)
                    while view:
                        try:
                            view = view[fout.write(view):]
                        except OSError as err:
                            raise _cannot_write(target, err) from err
        with suppress(OSError):  # times and modes: nothing a reader needs
            shutil.copystat(from_path, to_path)

    try:
        shutil.copytree(src, target, copy_function=copy_file, dirs_exist_ok=True)
    except shutil.Error as err:  # a folder's times or modes, or a link copytree could not follow
        problems = err.args[0] if err.args and isinstance(err.args[0], list) else []
        why = problems[0][-1] if problems else err  # (source, destination, error text) each
        raise BagError(f"cannot copy {src} to {target}: {one_line(why, 160)}") from err
    except OSError as err:
        raise BagError(f"cannot copy {src} to {target}: {err.strerror or one_line(err, 160)}") from err
