"""The storage files of rosbag2 bags (MCAP with the ``mcap`` library, sqlite3 with ``sqlite3``)
and the layout facts ROS 1 bags share with the real ``rosbag``.

Nothing here reaches into rosbags: it reads bags, and its typestores give the definitions and
hashes; writing is ours (MCAP through the ``mcap`` library's public ``Writer``, sqlite3 through the
standard library, ROS 1 in :mod:`racecar_hw.bags.ros1_writer`).

* :class:`McapStorage`: one ``<stem>.mcap`` file of a rosbag2 bag as ``rosbag2_storage_mcap``
  writes it: profile ``ros2``, schemas ``ros2msg`` (the concatenated ``.msg`` definitions),
  messages ``cdr``, each channel's ``offered_qos_profiles`` and ``topic_type_hash`` (RIHS01) in
  its metadata, and at close a ``rosbag2`` metadata record whose ``serialized_metadata`` is the
  bag's metadata (:func:`storage_metadata`).
  Chunks (1 MiB) carry the CRC-32 of their uncompressed records (issue 24; the follower,
  ``bag info`` and ``bag recover`` verify it, docs/bags.md "Checksums"); schemas and channels are
  written into the chunk that first uses them, so a file cut off before its summary still says
  what its messages are.
* :class:`Sqlite3Storage`: one ``<stem>.db3`` file with rosbag2's sqlite3 schema (version 4).
* :class:`Ros2Bag`: a bag directory with one storage file and its ``metadata.yaml`` (the
  recovery's output; the recorder writes its splits' metadata itself).
* ROS 1: the file-header record laid out as ``rosbag`` (ROS Noetic, ``rosbag/bag.py``) lays it
  out. The format pads the header record to 4096 bytes; the real tool pads the *header* to 4096
  bytes and then writes the padding as the record's data, with its own 4-byte length, so the whole
  record is 4 + 4096 + 4 = 4104 bytes (``_write_record(..., padded_size=_FILE_HEADER_LENGTH)``:
  data = 4096 - len(header) spaces). ``rosbag reindex``, ``rosbag fix`` and append mode *rewrite*
  the header in place with their layout, so a writer must use it: :func:`ros1_file_header`.

A storage file is written by one thread (the sqlite3 connection is bound to the thread that opens
it, as rosbag2's is). :data:`ROS2_METADATA_VERSION` is the metadata version written; see its
comment.
"""

from __future__ import annotations

import os
import sqlite3
import struct
from pathlib import Path
from typing import Any, Protocol

import yaml

from racecar_hw.base.errors import BagError, BagWriteError
from racecar_hw.runtime.extras import require_extra

#: rosbag2 metadata version written. Humble (rosbag2 0.15, ``rosbag2_storage/src/rosbag2_storage/
#: metadata_io.cpp``) decodes any version without an upper bound, but reads each topic's
#: ``offered_qos_profiles`` as a string (``node["offered_qos_profiles"].as<std::string>()`` for
#: version >= 4). Version 9 (Jazzy) writes a YAML sequence there, which Humble refuses with
#: "yaml-cpp: bad conversion". Version 8 is the newest with the string form; it also carries the
#: type description hashes (RIHS01) that Iron and newer use, which Humble ignores.
ROS2_METADATA_VERSION = 8

#: ``custom_data.racecar_hw`` in the metadata.yaml of a bag still being written (or cut off by a
#: crash), and of one whose recorder closed it.
RECORDING_OPEN = "in progress: written at flush, rewritten at close"
RECORDING_CLOSED = "closed"

#: rosbag's ``_FILE_HEADER_LENGTH``: the file header's fields are padded to this many bytes.
ROS1_FILE_HEADER_LENGTH = 4096
ROS1_MAGIC = b"#ROSBAG V2.0\n"
_OP_FILE_HEADER = 0x03


def _field(name: bytes, value: bytes) -> bytes:
    return struct.pack("<I", len(name) + 1 + len(value)) + name + b"=" + value


def ros1_file_header(index_pos: int, conn_count: int, chunk_count: int) -> bytes:
    """The file-header record as ``rosbag`` writes it: 4104 bytes for the unencrypted header.

    Fields in rosbag's order (op, index_pos, conn_count, chunk_count), then the data: spaces up
    to :data:`ROS1_FILE_HEADER_LENGTH` bytes of header, each part with its 4-byte length.
    """
    header = (_field(b"op", bytes([_OP_FILE_HEADER])) + _field(b"index_pos", struct.pack("<Q", index_pos))
              + _field(b"conn_count", struct.pack("<I", conn_count))
              + _field(b"chunk_count", struct.pack("<I", chunk_count)))
    padding = b" " * max(0, ROS1_FILE_HEADER_LENGTH - len(header))
    return struct.pack("<I", len(header)) + header + struct.pack("<I", len(padding)) + padding


#: Size of the file-header record ``rosbag`` writes (and the ROS 1 writer reserves).
ROS1_FILE_HEADER_RECORD = len(ros1_file_header(0, 0, 0))





#: Where a chunk record's ``uncompressed_crc`` is, from the record's start: opcode (1), length (8),
#: message_start_time, message_end_time, uncompressed_size (8 each).
MCAP_CHUNK_CRC_OFFSET = 1 + 8 + 8 + 8 + 8


#: Chunk size of MCAP files (uncompressed records), as rosbags and rosbag2's default.
MCAP_CHUNK_SIZE = 2**20


def _sync(fh: Any) -> None:
    fh.flush()
    os.fsync(fh.fileno())


def file_identity(path: Path) -> tuple[int, int]:
    """(device, inode) of the file at ``path``: what :func:`check_still_there` compares with."""
    st = os.stat(path)
    return st.st_dev, st.st_ino


def check_still_there(path: Path, identity: tuple[int, int]) -> None:
    """Raise :class:`BagWriteError` when ``path`` is no longer the file being written (``identity``,
    :func:`file_identity` when it was created): deleted or moved while it was written, everything
    written into it is lost (or elsewhere) however well the writes went. One ``stat``: writers call
    it at each flush and at close, not per message."""
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        pass
    except OSError:  # cannot look (a folder made unreadable): not known to be gone
        return
    else:
        if (st.st_dev, st.st_ino) == identity:
            return
    raise BagWriteError(f"{path}: the bag file was deleted or moved while recording")


class Storage(Protocol):
    """One storage file of a rosbag2 bag, written by one thread."""

    path: Path

    def add_connection(self, topic: str, msgtype: str, msgdef: str, digest: str, qos: str) -> int:
        """Register ``topic`` (``msgtype`` ``pkg/msg/Type``, its ROS 2 definition and RIHS01 hash,
        its offered QoS as metadata.yaml text); returns the id :meth:`write` takes."""

    def write(self, cid: int, t_ns: int, data: bytes) -> None:
        """Append the CDR bytes ``data`` on connection ``cid`` at bag time ``t_ns`` (ns)."""

    def flush(self) -> None:
        """Push everything written so far into the file and fsync it (the crash-safe point)."""

    def close(self, metadata: str) -> None:
        """Finish the file (summary, index); ``metadata`` is the bag's metadata.yaml text."""

    def abort(self) -> None:
        """Close without finishing."""


def storage_metadata(metadata_yaml: str) -> str:
    """What a storage file keeps of the bag's ``metadata_yaml``: its ``rosbag2_bagfile_information``
    mapping alone (``version``, ``storage_identifier``, ...), as rosbag2 and rosbags write it.
    rosbag2 decodes it as a ``BagMetadata``; the whole document (the mapping under its top key)
    made Jazzy's ``ros2 bag`` fail with "invalid node; first invalid key: version" (a sqlite3 bag at
    open, an MCAP bag at play and at ``info`` of the file alone). Once per file, at its close."""
    info = yaml.safe_load(metadata_yaml)["rosbag2_bagfile_information"]
    return yaml.dump(info, Dumper=yaml.SafeDumper, sort_keys=False)


class McapStorage:
    """One rosbag2 MCAP storage file, written with the ``mcap`` library (see the module doc)."""

    def __init__(self, path: Path, compression: str = "none") -> None:
        # the mcap library (with zstandard, 23 MB) is the mcap extra: a car that records no MCAP
        # bag does without it (docs/install.md, "Extras")
        require_extra("mcap", "writing an MCAP bag", "recorder.format")
        from mcap import __version__ as MCAP_VERSION  # noqa: PLC0415
        from mcap.writer import CompressionType  # noqa: PLC0415
        from mcap.writer import Writer as McapWriter  # noqa: PLC0415

        self.path = path
        self._fh = path.open("xb")
        self._writer = McapWriter(self._fh, chunk_size=MCAP_CHUNK_SIZE,
                                  compression=CompressionType[compression.upper()], enable_crcs=True)
        self._writer.start(profile="ros2", library=f"racecar-hw (mcap {MCAP_VERSION})")
        self._identity = file_identity(path)
        self._schemas: dict[str, int] = {}

    def add_connection(self, topic: str, msgtype: str, msgdef: str, digest: str, qos: str) -> int:
        sid = self._schemas.get(msgtype)
        if sid is None:
            sid = self._schemas[msgtype] = self._writer.register_schema(msgtype, "ros2msg", msgdef.encode())
        # (rosbag2 from Jazzy on reads the type hash from here when it opens a .mcap file alone)
        return self._writer.register_channel(topic, "cdr", sid, {"offered_qos_profiles": qos,
                                                                  "topic_type_hash": digest})

    def write(self, cid: int, t_ns: int, data: bytes) -> None:
        self._writer.add_message(cid, t_ns, data, t_ns)

    def flush(self) -> None:
        self._writer.flush()  # closes the pending chunk (with its CRC) and writes it out
        _sync(self._fh)
        check_still_there(self.path, self._identity)

    def close(self, metadata: str) -> None:
        self._writer.add_metadata("rosbag2", {"serialized_metadata": storage_metadata(metadata)})
        self._writer.finish()
        _sync(self._fh)
        self._fh.close()
        check_still_there(self.path, self._identity)

    def abort(self) -> None:
        self._fh.close()


class Sqlite3Storage:
    """One rosbag2 sqlite3 storage file (schema version 4, as rosbag2 Humble and rosbags write)."""

    SCHEMA = """
    CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);
    CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL,
      metadata TEXT NOT NULL);
    CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
      serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL,
      type_description_hash TEXT NOT NULL);
    CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL,
      encoding TEXT NOT NULL, encoded_message_definition TEXT NOT NULL,
      type_description_hash TEXT NOT NULL);
    CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL,
      data BLOB NOT NULL);
    CREATE INDEX timestamp_idx ON messages (timestamp ASC);
    INSERT INTO schema(schema_version, ros_distro) VALUES (4, 'racecar_hw');
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        if path.exists():
            raise BagError(f"{path} exists already, not overwriting")
        self._conn = sqlite3.connect(path)
        self._conn.executescript(self.SCHEMA)
        self._identity = file_identity(path)
        self._types: set[str] = set()
        self._topics = 0

    def add_connection(self, topic: str, msgtype: str, msgdef: str, digest: str, qos: str) -> int:
        if msgtype not in self._types:
            self._types.add(msgtype)
            self._execute("INSERT INTO message_definitions (topic_type, encoding,"
                          " encoded_message_definition, type_description_hash) VALUES (?, ?, ?, ?)",
                          (msgtype, "ros2msg", msgdef, digest))
        self._topics += 1
        self._execute("INSERT INTO topics VALUES (?, ?, ?, ?, ?, ?)",
                      (self._topics, topic, msgtype, "cdr", qos, digest))
        return self._topics

    def write(self, cid: int, t_ns: int, data: bytes) -> None:
        self._execute("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)", (cid, t_ns, data))

    def _execute(self, sql: str, values: tuple[Any, ...]) -> None:
        # a database deleted under sqlite fails a transaction's first write (and the commit) with
        # "attempt to write a readonly database" (SQLITE_READONLY_DBMOVED): said as what happened
        try:
            self._conn.execute(sql, values)
        except sqlite3.Error:
            check_still_there(self.path, self._identity)
            raise

    def flush(self) -> None:
        self._commit()

    def _commit(self) -> None:
        try:
            self._conn.commit()
        except sqlite3.Error:
            check_still_there(self.path, self._identity)
            raise
        check_still_there(self.path, self._identity)

    def close(self, metadata: str) -> None:
        self._execute("INSERT INTO metadata (metadata_version, metadata) VALUES (?, ?)",
                      (ROS2_METADATA_VERSION, storage_metadata(metadata)))
        self._commit()
        self._conn.execute("PRAGMA optimize")
        self._conn.close()

    def abort(self) -> None:
        try:
            self._conn.rollback()
        finally:
            self._conn.close()


def open_storage(bagdir: Path, stem: str, fmt: str, compression: str = "none") -> Storage:
    """A new storage file ``<bagdir>/<stem>.mcap`` (``fmt`` "mcap") or ``.db3`` ("sqlite3"); the
    directory is created if needed. Raises :class:`BagError` if it cannot be created."""
    try:
        bagdir.mkdir(mode=0o755, parents=True, exist_ok=True)
        if fmt == "mcap":
            return McapStorage(bagdir / f"{stem}.mcap", compression)
        if fmt == "sqlite3":
            return Sqlite3Storage(bagdir / f"{stem}.db3")
    except (OSError, sqlite3.Error) as err:
        raise BagError(f"cannot create bag storage {bagdir / stem}: {err}") from err
    raise BagError(f"no rosbag2 storage {fmt!r} (mcap or sqlite3)")


def bag_info(storage_identifier: str, *, duration: int, start: int, count: int,
             files: list[tuple[str, int, int, int]], topics: list[tuple[str, str, str, str, int]],
             complete: bool) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` of metadata.yaml (version :data:`ROS2_METADATA_VERSION`).

    ``duration``, ``start`` (ns) and ``count`` are the bag's; ``files``: (name, start ns, duration
    ns, message count); ``topics``: (name, type, offered QoS text, RIHS01 hash, message count).
    """
    return {
        "version": ROS2_METADATA_VERSION,
        "storage_identifier": storage_identifier,
        "relative_file_paths": [n for n, *_x in files],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [
            {"topic_metadata": {"name": name, "type": msgtype, "serialization_format": "cdr",
                                "offered_qos_profiles": qos, "type_description_hash": digest},
             "message_count": n}
            for name, msgtype, qos, digest, n in topics],
        "compression_format": "",
        "compression_mode": "",
        "files": [{"path": n, "starting_time": {"nanoseconds_since_epoch": s},
                   "duration": {"nanoseconds": d}, "message_count": c} for n, s, d, c in files],
        "custom_data": {"racecar_hw": RECORDING_CLOSED if complete else RECORDING_OPEN},
        "ros_distro": "rosbags",
    }


class Ros2Bag:
    """A rosbag2 bag directory ``path`` with one storage file ``<path.name>.<ext>`` and its
    ``metadata.yaml``, written at :meth:`close` (a context manager: closes on success, aborts on
    an error). The recovery writes its output with it; ``compression``: MCAP chunk compression
    (``none``, ``zstd``, ``lz4``)."""

    def __init__(self, path: Path, fmt: str = "mcap", compression: str = "none") -> None:
        if path.exists():
            raise BagError(f"{path} exists already, not overwriting")
        self.path = path
        self.format = fmt
        self.storage = open_storage(path, path.name, fmt, compression)
        self._topics: dict[int, list[Any]] = {}
        self._first: int | None = None
        self._last = 0

    def add_connection(self, topic: str, msgtype: str, msgdef: str, digest: str, qos: str) -> int:
        """As :meth:`Storage.add_connection`."""
        cid = self.storage.add_connection(topic, msgtype, msgdef, digest, qos)
        self._topics[cid] = [topic, msgtype, qos, digest, 0]
        return cid

    def write(self, cid: int, t_ns: int, data: bytes) -> None:
        """As :meth:`Storage.write`."""
        self.storage.write(cid, t_ns, data)
        self._topics[cid][4] += 1
        self._first = t_ns if self._first is None else min(self._first, t_ns)
        self._last = max(self._last, t_ns)

    def metadata(self) -> str:
        """The bag's metadata.yaml text."""
        count = sum(t[4] for t in self._topics.values())
        start = self._first or 0
        duration = self._last - start if count else 0
        info = bag_info(self.format, duration=duration, start=start, count=count,
                        files=[(self.storage.path.name, start, duration, count)],
                        topics=[tuple(t) for t in self._topics.values()], complete=True)  # type: ignore[misc]
        return yaml.dump({"rosbag2_bagfile_information": info}, Dumper=yaml.SafeDumper, sort_keys=False)

    def close(self) -> None:
        """Finish the storage file and write metadata.yaml."""
        text = self.metadata()
        self.storage.close(text)
        (self.path / "metadata.yaml").write_text(text, encoding="utf8")

    def abort(self) -> None:
        """Close the storage file without finishing it (no metadata.yaml)."""
        self.storage.abort()

    def __enter__(self) -> Ros2Bag:
        return self

    def __exit__(self, exc_type: Any, *_args: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
