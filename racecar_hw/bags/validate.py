"""Reading damaged bags safely: one error type, bounded memory, and commands that make sense.

A damaged or hostile bag must not crash the follower or the recovery tool, exhaust memory, or put
absurd values into the control path. Three pieces, used by every bag reader here:

* :func:`guarded` / :func:`reading`: whatever a reader raises (rosbags' ``ReaderError``, an
  ``AssertionError`` or ``KeyError`` from a malformed index, ``struct.error``, sqlite errors, a
  decompressor's error, ``MemoryError``) leaves as one :class:`~racecar_hw.base.errors.BagError`
  naming the file and the cause; a BagError that does not name the file gets it in front.
* :func:`check_storage`: before a reader allocates anything, the sizes the file declares (records,
  chunks and their uncompressed sizes, the offsets its index points at) are checked against the
  file and against ``max_message_bytes``, and every compressed chunk is decompressed once in
  pieces, its output counted and thrown away (:func:`inflate`), so a chunk that lies about its
  uncompressed size is refused before a reader decompresses it whole. It follows what rosbags
  reads: a ROS 1 bag's header, index and chunk records; every record of an MCAP file; the largest
  message of a sqlite3 bag. Every MCAP chunk that carries a CRC-32 (non-zero: recorded by this
  project's recorder) is checked against it (:func:`mcap_chunk_crc_error` alone for ``bag info``
  and ``bag recover``): a mismatch is refused naming the chunk (its number and byte offset).
* :func:`check_commands`: every loaded drive command must be finite and physically possible
  (:data:`ABSURD_SPEED_MPS`, :data:`ABSURD_STEERING_RAD`), or the bag is refused naming the first
  bad message's index and time. A command merely beyond this car's configured limits is not
  refused: the follower clamps it to :class:`CommandLimits`, as the VESC driver clamps any command
  (a bag recorded on a car that steers further, F1TENTH's 0.4189 rad, is normal).
"""

from __future__ import annotations

import bz2
import contextlib
import dataclasses
import functools
import math
import os
import sqlite3
import stat
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import IO, Any, Protocol, TypeVar

import yaml

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.errors import BagError, BagWriteError
from racecar_hw.base.messages import AckermannDrive
from racecar_hw.base.overrides import ShallowSafeLoader
from racecar_hw.base.text import one_line

#: The largest record (a message, or a chunk of messages) read from a bag, in bytes. A drive
#: command is under 100 bytes; a chunk of a recording with camera images can reach a few MB.
DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
LZ4_FRAME_MAGIC = b"\x04\x22\x4d\x18"
#: MCAP records rosbags reads into memory whole (header, schema, channel, message, chunk, chunk
#: index, statistics); it seeks past the others (attachments, metadata, indexes it does not use).
MCAP_READ_WHOLE = frozenset((0x01, 0x03, 0x04, 0x05, 0x06, 0x08, 0x0B))
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
#: Bytes of compressed input read, and of output taken from a decompressor, at a time: what bounding
#: a chunk's decompression holds in memory (plus the decompressor's own state, a few MB for bz2).
INFLATE_STEP = 1 << 20

F = TypeVar("F", bound=Callable[..., Any])


# --- one error type ---------------------------------------------------------------------------


#: The longest cause quoted from a reader's exception (some quote a whole message definition).
MAX_CAUSE_CHARS = 160


def describe(err: BaseException) -> str:
    """A reader's exception as a one-line cause a user can act on."""
    if isinstance(err, MemoryError):
        return "it declares more data than fits in memory (damaged?)"
    # one line of printable text: a damaged bag's bytes (NULs, control characters) can be in it
    text = one_line(err, MAX_CAUSE_CHARS) or "no details"
    if isinstance(err, sqlite3.Error):
        return f"its sqlite3 storage is damaged ({text})"
    name = type(err).__name__
    return text if name.endswith(("ReaderError", "BagError")) else f"damaged data ({name}: {text})"


@contextlib.contextmanager
def reading(path: str | Path) -> Iterator[None]:
    """Turn anything but :class:`BagError` raised inside into a BagError naming ``path``. A
    :class:`BagWriteError` (an output that cannot be written: it names that) leaves as it is."""
    try:
        yield
    except BagError as err:
        if str(path) in str(err) or isinstance(err, BagWriteError):
            raise
        raise BagError(f"{path}: {err}") from err  # a scanner's error, said without the file
    except (Exception, MemoryError, RecursionError) as err:
        raise BagError(f"cannot read bag {path}: {describe(err)}") from err


def guarded(fn: F) -> F:
    """Decorate a bag reader whose first argument is the bag's path: only BagError escapes."""

    @functools.wraps(fn)
    def wrapper(path: str | Path, *args: Any, **kwargs: Any) -> Any:
        with reading(path):
            return fn(path, *args, **kwargs)

    return wrapper  # type: ignore[return-value]


# --- bounded memory ---------------------------------------------------------------------------


def check_storage(path: Path, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> None:
    """Refuse (BagError) a bag whose declared sizes exceed the file or ``max_bytes``.

    ``path`` is a ROS 1 ``.bag`` file, an MCAP file, or a ROS 2 bag directory (each of its
    :func:`storage_files` is checked). Files of other kinds are left to the reader, which refuses
    them. Only regular files are read: anything else is refused (:func:`regular_file`).
    """
    files = storage_files(path) if path.is_dir() else [regular_file(path)]
    for file in files:
        if file.suffix == ".db3":
            _check_sqlite3(file, max_bytes)
            continue
        with open_regular(file) as f:
            magic = f.read(len(ROS1_MAGIC))
            size = file.stat().st_size
            if magic.startswith(MCAP_MAGIC):
                _check_mcap(_Storage(file, f, size, max_bytes))
            elif magic == ROS1_MAGIC:
                _check_ros1(_Storage(file, f, size, max_bytes))


#: The names a ROS 2 bag's storage files have: the readers here (``bag info``, ``bag recover``) and
#: :func:`check_storage` find them by name.
STORAGE_SUFFIXES = (".mcap", ".db3")


def regular_file(path: Path) -> Path:
    """``path``, when it is a regular file (or a symbolic link to one); else :class:`BagError`.

    A FIFO or a device named like a bag file would make a reader wait forever (or read without
    end): it is refused, naming it, before anything opens it."""
    try:
        mode = path.stat().st_mode
    except OSError as err:
        raise BagError(f"cannot read bag file {path}: {describe(err)}") from err
    if not stat.S_ISREG(mode):
        raise BagError(_not_regular(path, mode))
    return path


def _not_regular(path: Path, mode: int) -> str:
    kinds = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
             (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"))
    kind = next((name for test, name in kinds if test(mode)), "of another kind")
    return f"{path} is {kind}, not a regular file: refused, not read"


def open_regular(path: Path) -> IO[bytes]:
    """``path`` opened for reading, refused (BagError) unless it is a regular file when opened: the
    check before opening and this one leave no moment where a FIFO put in its place blocks the open."""
    fd = os.open(regular_file(path), os.O_RDONLY | os.O_NONBLOCK)
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise BagError(_not_regular(path, mode))
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


class MetadataLoader(ShallowSafeLoader):
    """PyYAML's safe loader (flow nesting limited) refusing aliases (``*name``) in ``metadata.yaml``.

    rosbag2, rosbags and our writers never write one, and 600 bytes of aliases nested 8 deep stand
    for 10^8 strings to whatever walks the result: ``bag info`` took 833 MB and 28 s on such a file.
    """

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(None, None, f"an alias (*{event.anchor}), which bag metadata "
                                              "never has", event.start_mark)
        return super().compose_node(parent, index)


def load_metadata(bagdir: Path) -> tuple[dict | None, str]:
    """``rosbag2_bagfile_information`` of the bag's ``metadata.yaml``, or None and why it is not usable."""
    try:
        text = (bagdir / "metadata.yaml").read_text("utf8")
    except FileNotFoundError:
        return None, "metadata.yaml is missing"
    except (OSError, ValueError) as err:
        return None, f"metadata.yaml is not readable ({type(err).__name__})"
    try:
        data = yaml.load(text, Loader=MetadataLoader)  # noqa: S506 - a SafeLoader
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark
        at = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        return None, f"metadata.yaml is not usable: {at}{err.problem or err.context}"
    except (yaml.YAMLError, RecursionError) as err:
        return None, f"metadata.yaml is not usable ({type(err).__name__})"
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        return None, "metadata.yaml is not usable: it has no rosbag2_bagfile_information"
    return info, ""


def listed_names(meta: dict) -> list[str]:
    """The file names ``relative_file_paths`` lists, each once: only the name of each path, as rosbags
    reads it (rosbag2 before version 4 wrote ``<bag>/<file>``), so only files in the bag directory
    are ever taken; an entry that is not a string is left out (never turned into one)."""
    paths = meta.get("relative_file_paths")
    if not isinstance(paths, list):
        return []
    names = (PurePath(p).name for p in paths if isinstance(p, str))
    return list(dict.fromkeys(n for n in names if n not in ("", ".", "..")))


def storage_files(bagdir: Path) -> list[Path]:
    """The storage files of the ROS 2 bag directory ``bagdir``: every ``.mcap`` and ``.db3`` in it,
    which include every file its ``metadata.yaml`` lists (the files rosbags opens), all regular files.

    Refused (:class:`BagError`, naming the file): a listed file not named ``*.mcap`` or ``*.db3``
    (nothing here would find it by name, so nothing would check it before rosbags reads it
    whole), and a storage file that is not a regular file (:func:`regular_file`).
    """
    for name in listed_names(load_metadata(bagdir)[0] or {}):
        if not name.endswith(STORAGE_SUFFIXES):
            raise BagError(f"{bagdir / name}: metadata.yaml lists a storage file not named *.mcap or "
                           "*.db3; the bag is refused (its storage files must be named by their kind)")
    files = sorted(p for p in bagdir.iterdir() if p.suffix in STORAGE_SUFFIXES)
    return [regular_file(p) for p in files]


@dataclass
class _Storage:
    """An open bag file, its size, and the limit."""

    path: Path
    f: IO[bytes]
    size: int
    limit: int

    def read(self, pos: int, n: int) -> bytes:
        self.f.seek(pos)
        data = self.f.read(n)
        if len(data) != n:
            raise BagError(f"{self.path}: the file ends at byte {self.size}, inside a record at byte "
                           f"{pos} (truncated? an interrupted recording can be recovered with "
                           f"racecar_hw.bags.recover)")
        return data

    def declared(self, what: str, pos: int, n: int, end: int | None = None, limited: bool = True) -> None:
        """``n`` bytes declared at ``pos`` must fit the file (up to ``end``) and, when the reader
        will hold them in memory (``limited``), the limit."""
        left = (self.size if end is None else end) - pos
        if n > left:
            raise BagError(f"{self.path}: {what} at byte {pos} declares {n} bytes, but only {left} "
                           "follow (a damaged or truncated file)")
        if limited and n > self.limit:
            raise BagError(f"{self.path}: {what} at byte {pos} declares {n} bytes, over the "
                           f"limit of {self.limit} (max_message_bytes); refused before reading it")

    def pieces(self, pos: int, n: int) -> Iterator[bytes]:
        """The ``n`` bytes at ``pos`` (already checked to be in the file), :data:`INFLATE_STEP` at a time."""
        for at in range(pos, pos + n, INFLATE_STEP):
            yield self.read(at, min(INFLATE_STEP, pos + n - at))

    def inflates_within(self, pos: int, compression: str, data_pos: int, n: int, declared: int) -> None:
        """The chunk at ``pos`` (``n`` bytes of ``compression`` data at ``data_pos``) decompresses to
        no more than the ``declared`` bytes (at most the limit, checked before)."""
        what = (f"{self.path}: the {compression} chunk at byte {pos} declares {declared} bytes "
                "uncompressed, but it")
        inflated_size(self.pieces(data_pos, n), compression, declared, what)


def _lz4_content_size(data: bytes) -> int | None:
    """The content size an LZ4 frame header declares (None when it declares none)."""
    if len(data) < 6 or data[:4] != LZ4_FRAME_MAGIC or not data[4] & 0x08:
        return None
    return _U64.unpack_from(data, 6)[0] if len(data) >= 14 else None


def _decompressor(compression: str) -> Callable[[], Any] | None:
    """A new streaming decompressor for a chunk's ``compression`` (None: nothing to decompress,
    or a compression the readers refuse themselves)."""
    if compression == "bz2":
        return bz2.BZ2Decompressor
    if compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        return lz4.frame.LZ4FrameDecompressor  # type: ignore[no-any-return]
    if compression == "zstd":
        try:
            from compression import zstd  # type: ignore[import-not-found]
        except ImportError:  # before Python 3.14: the backport rosbags uses too
            from backports import zstd  # type: ignore[import-not-found,no-redef]
        return zstd.ZstdDecompressor  # type: ignore[no-any-return]
    return None


def inflate(pieces: Iterable[bytes], compression: str, bound: int, what: str) -> Iterator[bytes]:
    """The decompressed output of a chunk's data, given in ``pieces``, at most :data:`INFLATE_STEP`
    bytes at a time; nothing for an uncompressed chunk (``none`` or empty) or an unknown compression.

    As the readers decompress: bz2 and zstd every concatenated stream, lz4 its first frame (the
    rest is ignored). Raises :class:`BagError` ("``what`` decompresses to more than ``bound``
    bytes") as soon as the output passes ``bound``, so memory stays bounded whatever the data
    claims. A stream that ends early just ends: the reader reports that itself.
    """
    make = _decompressor(compression)
    if make is None:
        return
    d = make()
    total = 0
    for piece in pieces:
        data = piece
        while True:
            if d.eof:
                if compression == "lz4":
                    return
                data = d.unused_data + data
                if not data:
                    break
                d = make()
            elif not data and d.needs_input:
                break
            out = d.decompress(data, INFLATE_STEP)
            data = b""
            total += len(out)
            if total > bound:
                raise BagError(f"{what} decompresses to more than {bound} bytes (a damaged chunk or a "
                               "decompression bomb); refused before decompressing the rest")
            if out:
                yield out


def inflated_size(pieces: Iterable[bytes], compression: str, bound: int, what: str) -> int:
    """How many bytes :func:`inflate` gives (BagError past ``bound``); the output is thrown away."""
    return sum(len(out) for out in inflate(pieces, compression, bound, what))


# ROS 1: what rosbags reads - the bag header, the index at index_pos (connections, chunk infos),
# then each chunk and the index data records behind it.


def _ros1_record(s: _Storage, pos: int) -> tuple[dict[str, bytes], int, int]:
    """(header fields, data position, data length) of the record at ``pos``."""
    (hlen,) = _U32.unpack(s.read(pos, 4))
    s.declared("a record header", pos + 4, hlen)
    header = s.read(pos + 4, hlen)
    fields: dict[str, bytes] = {}
    i = 0
    while i < hlen:
        if i + 4 > hlen:
            raise BagError(f"{s.path}: a damaged record header at byte {pos}")
        (flen,) = _U32.unpack_from(header, i)
        name, sep, value = header[i + 4:i + 4 + flen].partition(b"=")
        if i + 4 + flen > hlen or not sep:
            raise BagError(f"{s.path}: a damaged record header at byte {pos}")
        fields[name.decode("ascii", "replace")] = value
        i += 4 + flen
    data_pos = pos + 4 + hlen + 4
    (dlen,) = _U32.unpack(s.read(pos + 4 + hlen, 4))
    s.declared("a record's data", data_pos, dlen)
    return fields, data_pos, dlen


def _field_int(s: _Storage, fields: dict[str, bytes], name: str, fmt: struct.Struct) -> int:
    value = fields.get(name)
    if value is None or len(value) != fmt.size:
        raise BagError(f"{s.path}: a record lacks its {name!r} field (a damaged file)")
    return int(fmt.unpack(value)[0])


def _check_ros1(s: _Storage) -> None:
    fields, data_pos, dlen = _ros1_record(s, len(ROS1_MAGIC))
    index_pos = _field_int(s, fields, "index_pos", _U64)
    conn_count = _field_int(s, fields, "conn_count", _U32)
    chunk_count = _field_int(s, fields, "chunk_count", _U32)
    if not index_pos or not chunk_count:
        return  # rosbags refuses an unindexed bag, and an empty one reads nothing more
    pos = index_pos
    for _ in range(conn_count):
        _, data_pos, dlen = _ros1_record(s, pos)
        pos = data_pos + dlen
    for _ in range(chunk_count):
        fields, data_pos, dlen = _ros1_record(s, pos)
        count = _field_int(s, fields, "count", _U32)
        if count * 8 > dlen:
            raise BagError(f"{s.path}: a chunk info at byte {pos} lists more connections than it holds")
        _check_ros1_chunk(s, _field_int(s, fields, "chunk_pos", _U64), count)
        pos = data_pos + dlen


def _check_ros1_chunk(s: _Storage, pos: int, index_records: int) -> None:
    fields, data_pos, dlen = _ros1_record(s, pos)
    if fields.get("op") != b"\x05":
        raise BagError(f"{s.path}: the index points at byte {pos}, which holds no chunk")
    uncompressed = _field_int(s, fields, "size", _U32)
    if uncompressed > s.limit:
        raise BagError(f"{s.path}: the chunk at byte {pos} declares {uncompressed} bytes uncompressed, "
                       f"over the limit of {s.limit} (max_message_bytes); refused before reading it")
    compression = fields.get("compression", b"").decode("ascii", "replace")
    if compression == "lz4":
        content = _lz4_content_size(s.read(data_pos, min(dlen, 14)))
        if content is not None and content > s.limit:
            raise BagError(f"{s.path}: the chunk at byte {pos} decompresses to {content} bytes, over "
                           f"the limit of {s.limit} (max_message_bytes)")
    s.inflates_within(pos, compression, data_pos, dlen, uncompressed)
    pos = data_pos + dlen
    for _ in range(index_records):
        _, data_pos, dlen = _ros1_record(s, pos)
        pos = data_pos + dlen


# MCAP: every record from the header to the footer; the chunk indexes must point at chunks.


def _check_mcap(s: _Storage) -> None:
    pos = len(MCAP_MAGIC)
    end = s.size - len(MCAP_MAGIC)
    if end < pos or s.read(end, len(MCAP_MAGIC)) != MCAP_MAGIC:
        return  # not closed (an interrupted recording): the reader refuses it and says so
    starts: set[int] = set()
    chunks: dict[int, _McapChunk] = {}  # by the chunk record's offset
    while pos < end:
        op = s.read(pos, 1)[0]
        (length,) = _U64.unpack(s.read(pos + 1, 8))
        starts.add(pos)
        s.declared(f"record 0x{op:02x}", pos + 9, length, end, limited=op in MCAP_READ_WHOLE)
        if op == 0x02:  # footer: the summary it points at must start at a record
            if length >= 8:
                (summary,) = _U64.unpack(s.read(pos + 9, 8))
                if summary and summary not in starts:
                    raise BagError(f"{s.path}: the footer points at byte {summary}, which starts no record")
            return
        if op == 0x06:
            chunks[pos] = _check_mcap_chunk(s, pos, length, len(chunks) + 1)
        elif op == 0x08:
            _check_mcap_chunk_index(s, pos, length, chunks)
        pos += 9 + length
    raise BagError(f"{s.path}: no footer record (truncated? an interrupted recording can be recovered "
                   "with racecar_hw.bags.recover)")


def crc_mismatch(path: Path | str, number: int, pos: int, recorded: int, computed: int,
                 hint: bool = True) -> str:
    """What is said of MCAP chunk ``number`` (1 = the file's first) at byte ``pos`` of ``path`` whose
    records do not have the CRC-32 its record carries (``hint``: and what to do about it)."""
    text = (f"{path}: chunk {number} (at byte {pos}) fails its checksum: its records have CRC-32 "
            f"0x{computed:08x}, the chunk says 0x{recorded:08x}")
    return text + (" (the file is damaged; racecar-hw bag recover keeps the good chunks)" if hint else "")


def _chunk_crc(s: _Storage, pos: int, length: int, number: int) -> None:
    """Raise BagError (:func:`crc_mismatch`) when the chunk record at ``pos`` carries a CRC-32 (not 0)
    its uncompressed records do not have; a chunk of a compression this cannot decompress is left
    to the reader."""
    body = pos + 9
    end = body + length
    (uncompressed,) = _U64.unpack(s.read(body + 16, 8))
    (recorded,) = _U32.unpack(s.read(body + 24, 4))
    if not recorded:
        return
    compression, compressed = _mcap_sizes(s, body + 28, end)
    data = body + 28 + 4 + len(compression.encode()) + 8
    s.declared("a chunk's data", data, compressed, end)
    pieces: Iterable[bytes]
    if compression in ("", "none"):
        pieces = s.pieces(data, compressed)
    elif _decompressor(compression) is not None:
        what = (f"{s.path}: the {compression} chunk at byte {pos} declares {uncompressed} bytes "
                "uncompressed, but it")
        pieces = inflate(s.pieces(data, compressed), compression, min(uncompressed, s.limit), what)
    else:
        return
    computed = 0
    for piece in pieces:
        computed = zlib.crc32(piece, computed)
    if computed != recorded:
        raise BagError(crc_mismatch(s.path, number, pos, recorded, computed))


def mcap_chunk_crc_error(path: Path, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> str | None:
    """The first chunk of the MCAP file at ``path`` that fails its CRC-32 (:func:`crc_mismatch`), or
    None. Walks the records up to the footer or the first one cut off (an interrupted recording):
    structure is the readers' business (and :func:`check_storage`'s), only checksums are checked."""
    with open_regular(path) as f:
        s = _Storage(path, f, path.stat().st_size, max_bytes)
        pos = len(MCAP_MAGIC)
        number = 0
        while pos + 9 <= s.size:
            op = s.read(pos, 1)[0]
            (length,) = _U64.unpack(s.read(pos + 1, 8))
            if op == 0x02 or pos + 9 + length > s.size:
                return None
            if op == 0x06:
                number += 1
                try:
                    _chunk_crc(s, pos, length, number)
                except BagError as err:
                    if "fails its checksum" in str(err):
                        return str(err)
                    return None  # damaged otherwise: the readers say how
            pos += 9 + length
    return None


def _mcap_sizes(s: _Storage, at: int, end: int) -> tuple[str, int]:
    """(compression, the u64 after it) of a chunk or chunk index record."""
    (n,) = _U32.unpack(s.read(at, 4))
    s.declared("a compression name", at + 4, n, end)
    name = s.read(at + 4, n).decode("ascii", "replace")
    (value,) = _U64.unpack(s.read(at + 4 + n, 8))
    return name, value


@dataclass(frozen=True)
class _McapChunk:
    """What a chunk record says of itself; its chunk index must say the same (rosbags takes the
    compression and sizes from the index)."""

    length: int
    compression: str
    compressed: int
    uncompressed: int


def _check_mcap_chunk(s: _Storage, pos: int, length: int, number: int) -> _McapChunk:
    body = pos + 9
    end = body + length
    (uncompressed,) = _U64.unpack(s.read(body + 16, 8))
    compression, compressed = _mcap_sizes(s, body + 28, end)
    data = body + 28 + 4 + len(compression.encode()) + 8
    s.declared("a chunk's data", data, compressed, end)
    if uncompressed > s.limit:
        raise BagError(f"{s.path}: the chunk at byte {pos} declares {uncompressed} bytes uncompressed, "
                       f"over the limit of {s.limit} (max_message_bytes); refused before reading it")
    if compression == "lz4":
        content = _lz4_content_size(s.read(data, min(compressed, 14)))
        if content is not None and content > s.limit:
            raise BagError(f"{s.path}: the chunk at byte {pos} decompresses to {content} bytes, over "
                           f"the limit of {s.limit} (max_message_bytes)")
    s.inflates_within(pos, compression, data, compressed, uncompressed)
    _chunk_crc(s, pos, length, number)
    return _McapChunk(length, compression, compressed, uncompressed)


def _check_mcap_chunk_index(s: _Storage, pos: int, length: int, chunks: dict[int, _McapChunk]) -> None:
    body = pos + 9
    end = body + length
    start, chunk_length = _U64.unpack(s.read(body + 16, 8))[0], _U64.unpack(s.read(body + 24, 8))[0]
    chunk = chunks.get(start)
    if chunk is None or chunk.length != chunk_length - 9:
        raise BagError(f"{s.path}: a chunk index at byte {pos} points at byte {start}, which holds no "
                       "chunk of that length")
    (offsets_len,) = _U32.unpack(s.read(body + 32, 4))
    s.declared("a chunk index's offsets", body + 36, offsets_len, end)
    compression, compressed = _mcap_sizes(s, body + 36 + offsets_len + 8, end)
    (uncompressed,) = _U64.unpack(s.read(body + 36 + offsets_len + 8 + 4 + len(compression.encode()) + 8, 8))
    if compressed > chunk_length or uncompressed > s.limit:
        raise BagError(f"{s.path}: a chunk index at byte {pos} declares {compressed} compressed, "
                       f"{uncompressed} uncompressed bytes: a damaged index, or over the limit of "
                       f"{s.limit} (max_message_bytes)")
    if (compression, compressed, uncompressed) != (chunk.compression, chunk.compressed, chunk.uncompressed):
        raise BagError(f"{s.path}: a chunk index at byte {pos} says {compression or 'no'} compression, "
                       f"{compressed} compressed, {uncompressed} uncompressed bytes; its chunk at byte "
                       f"{start} says {chunk.compression or 'no'}, {chunk.compressed}, "
                       f"{chunk.uncompressed} (a damaged index)")


def _check_sqlite3(db: Path, max_bytes: int) -> None:
    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    except sqlite3.Error as err:
        raise BagError(f"cannot read bag {db}: {describe(err)}") from err
    try:
        tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        # no table at all (0 bytes: a split killed as it opened, left out by the recovery): no message
        (largest,) = (con.execute("SELECT MAX(LENGTH(data)) FROM messages").fetchone()
                      if tables else (None,))
    except sqlite3.Error as err:
        raise BagError(f"cannot read bag {db}: {describe(err)}") from err
    finally:
        con.close()
    if largest is not None and largest > max_bytes:
        raise BagError(f"{db}: a message of {largest} bytes, over the limit of {max_bytes} "
                       "(max_message_bytes); refused before reading it")


# --- commands that make sense -----------------------------------------------------------------


@dataclass(frozen=True)
class CommandLimits:
    """What this car can be asked for: |speed| (m/s) and |steering| (rad); inf = no limit.

    Loaded commands beyond them are clamped to them (:meth:`clamp`), not refused.
    """

    max_speed_mps: float = math.inf
    max_steering_rad: float = math.inf

    def clamp(self, drive: AckermannDrive) -> AckermannDrive:
        """``drive`` with its speed and steering angle clamped to the limits (the same object when
        within them)."""
        speed = min(max(drive.speed, -self.max_speed_mps), self.max_speed_mps)
        steering = min(max(drive.steering_angle, -self.max_steering_rad), self.max_steering_rad)
        if speed == drive.speed and steering == drive.steering_angle:
            return drive
        return dataclasses.replace(drive, speed=speed, steering_angle=steering)


class _Timed(Protocol):
    t_ns: int
    drive: AckermannDrive


#: No 1/10-scale car drives this fast (m/s; the RC speed record is about 90 m/s): a bag asking for
#: more is damaged or not a drive command, and is refused.
ABSURD_SPEED_MPS = 100.0
#: A steered wheel cannot turn further than this (rad): a bag asking for more is refused.
ABSURD_STEERING_RAD = math.pi / 2


def check_commands(commands: Sequence[_Timed], path: str | Path, topic: str) -> None:
    """Refuse (BagError) the bag at the first command that is not finite or physically absurd
    (beyond :data:`ABSURD_SPEED_MPS` or :data:`ABSURD_STEERING_RAD`), naming its index on ``topic``
    and its time (seconds after the first command, and bag time)."""
    t0 = commands[0].t_ns if commands else 0
    for i, cmd in enumerate(commands):
        d = cmd.drive
        fields = {"speed": d.speed, "steering_angle": d.steering_angle, "acceleration": d.acceleration,
                  "jerk": d.jerk, "steering_angle_velocity": d.steering_angle_velocity}
        problem = next((f"{name} {value}" for name, value in fields.items() if not math.isfinite(value)),
                       None)
        if problem is None and abs(d.speed) > ABSURD_SPEED_MPS:
            problem = f"speed {d.speed:g} m/s, which no 1/10-scale car drives (over {ABSURD_SPEED_MPS:g} m/s)"
        if problem is None and abs(d.steering_angle) > ABSURD_STEERING_RAD:
            problem = (f"steering {d.steering_angle:g} rad, which no wheel turns (over "
                       f"{ABSURD_STEERING_RAD:.4g} rad)")
        if problem is not None:
            raise BagError(f"{path}: message {i} on {topic} ({(cmd.t_ns - t0) / NS_PER_S:.3f} s into "
                           f"the recording, bag time {cmd.t_ns / NS_PER_S:.3f} s) asks for {problem}; "
                           "the bag is refused")


__all__ = ["ABSURD_SPEED_MPS", "ABSURD_STEERING_RAD", "DEFAULT_MAX_MESSAGE_BYTES", "STORAGE_SUFFIXES",
           "CommandLimits", "MetadataLoader", "check_commands", "check_storage", "crc_mismatch", "describe",
           "guarded", "inflate", "inflated_size", "listed_names", "load_metadata", "mcap_chunk_crc_error",
           "open_regular", "reading", "regular_file", "storage_files"]
