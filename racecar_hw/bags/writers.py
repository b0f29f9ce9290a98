"""rosbags' bag writers, adjusted so the files are what the real ROS tools write and read.

* :class:`Ros1Writer`: the ROS 1 file-header record laid out as ``rosbag`` (ROS Noetic,
  ``rosbag/bag.py``) lays it out. The format pads the header record to 4096 bytes; the real tool
  pads the *header* to 4096 bytes and then writes the padding as the record's data, with its own
  4-byte length, so the whole record is 4 + 4096 + 4 = 4104 bytes (``_write_record(...,
  padded_size=_FILE_HEADER_LENGTH)``: data = 4096 - len(header) spaces). rosbags makes the whole
  record 4096 bytes. Every tool reads either, but ``rosbag reindex``, ``rosbag fix`` and append
  mode *rewrite* the header in place with their layout: on a 4096-byte record that overwrites the
  first 8 bytes of the first chunk and the bag becomes unreadable. With the real layout they
  rewrite exactly the bytes that were there.
* :class:`Ros2FileWriter`: one storage file (``<stem>.mcap`` or ``<stem>.db3``) inside a bag
  directory that may already hold others, so the splits of a recording are one rosbag2 bag with
  several files, as ``ros2 bag record --max-bag-size`` makes them. ``metadata.yaml`` is the
  caller's (it describes every file); rosbags' own is written aside and removed.
* :class:`McapCrcWriter`: rosbags' MCAP storage writer, but every chunk record carries the CRC-32
  of its uncompressed records (rosbags writes 0, "not computed", so a flipped bit went unseen).
  :class:`Ros2Writer` and :class:`Ros2FileWriter` use it; the follower, ``bag info`` and
  ``bag recover`` verify it (docs/bags.md, "Checksums").

:data:`ROS2_METADATA_VERSION` is the metadata version written; see its comment.
"""

from __future__ import annotations

import contextlib
import struct
from binascii import crc32
from pathlib import Path
from typing import Any

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.rosbag2.storage_mcap import McapWriter

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


#: Size of the file-header record ``rosbag`` writes (and :class:`Ros1Writer` reserves).
ROS1_FILE_HEADER_RECORD = len(ros1_file_header(0, 0, 0))


class Ros1Writer(Writer1):
    """rosbags' ROS 1 writer with the file header of the real ``rosbag`` (see the module doc)."""

    def open(self) -> None:
        """Create the file: magic and an empty file header (index_pos 0: not yet indexed)."""
        super().open()
        assert self.bio is not None
        self.bio.seek(len(ROS1_MAGIC))
        self.bio.truncate()
        self.bio.write(ros1_file_header(0, 0, 0))

    def close(self) -> None:
        """Write the index (rosbags), then the file header again in rosbag's layout."""
        bio = self.bio
        assert bio is not None
        super().close()  # writes a 4096-byte header record inside our 4104 bytes, then closes
        with self.path.open("r+b") as fh:
            fh.seek(len(ROS1_MAGIC))
            fields = _read_header_fields(fh.read(ROS1_FILE_HEADER_RECORD))
            fh.seek(len(ROS1_MAGIC))
            fh.write(ros1_file_header(struct.unpack("<Q", fields[b"index_pos"])[0],
                                      struct.unpack("<I", fields[b"conn_count"])[0],
                                      struct.unpack("<I", fields[b"chunk_count"])[0]))


def _read_header_fields(record: bytes) -> dict[bytes, bytes]:
    (hlen,) = struct.unpack_from("<I", record, 0)
    header = record[4:4 + hlen]
    fields: dict[bytes, bytes] = {}
    pos = 0
    while pos + 4 <= len(header):
        (n,) = struct.unpack_from("<I", header, pos)
        name, _, value = header[pos + 4:pos + 4 + n].partition(b"=")
        fields[name] = value
        pos += 4 + n
    return fields


#: Where a chunk record's ``uncompressed_crc`` is, from the record's start: opcode (1), length (8),
#: message_start_time, message_end_time, uncompressed_size (8 each).
MCAP_CHUNK_CRC_OFFSET = 1 + 8 + 8 + 8 + 8
_CRC = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class McapCrcWriter(McapWriter):
    """rosbags' MCAP writer whose chunks carry their CRC-32 (of the uncompressed records).

    rosbags' ``close_chunk`` writes the chunk with CRC 0 and keeps its chunk index (whose third
    u64 is the chunk's file offset); the CRC is then written over the 0 in the file. One seek per
    chunk (1 MiB): the cost is the CRC itself (``benchmarks/bench_bags.py``).
    """

    def close_chunk(self) -> None:
        """Close the pending chunk as rosbags does, with the chunk's CRC in its record."""
        crc = crc32(self.chunk.bio.getbuffer())
        super().close_chunk()
        (start,) = _U64.unpack_from(self.chunks[-1].getbuffer(), 16)
        end = self.bio.tell()
        self.bio.seek(start + MCAP_CHUNK_CRC_OFFSET)
        self.bio.write(_CRC.pack(crc))
        self.bio.seek(end)


_PLUGINS = {**Writer2.STORAGE_PLUGINS, StoragePlugin.MCAP: McapCrcWriter}


class Ros2Writer(Writer2):
    """rosbags' rosbag2 writer with :class:`McapCrcWriter` for MCAP storage (checksummed chunks)."""

    STORAGE_PLUGINS = _PLUGINS


class _StorageDir:
    """Stands in for the bag path rosbags' storage plugins get: they create ``path / f"{path.name}.<ext>"``,
    and this makes that ``bagdir / f"{stem}.<ext>"``."""

    def __init__(self, bagdir: Path, stem: str) -> None:
        self.bagdir = bagdir
        self.name = stem

    def __truediv__(self, other: str) -> Path:
        return self.bagdir / other


class Ros2FileWriter(Ros2Writer):
    """rosbags' rosbag2 writer for one storage file ``<stem>.<ext>`` in the bag directory ``bagdir``.

    The directory may exist and hold other files of the same bag. rosbags' ``metadata.yaml`` for
    this file alone goes to a hidden file that :meth:`close` removes: the caller writes the bag's.
    """

    def __init__(self, bagdir: Path, stem: str, *, storage_plugin: StoragePlugin,
                 version: Any = ROS2_METADATA_VERSION) -> None:
        super().__init__(bagdir / stem, version=version, storage_plugin=storage_plugin)
        self.bagdir = bagdir
        self.stem = stem
        self.metapath = bagdir / f".{stem}.metadata.yaml"

    def open(self) -> None:
        """Create the bag directory if needed and the storage file in it."""
        self.bagdir.mkdir(mode=0o755, parents=True, exist_ok=True)
        place: Any = _StorageDir(self.bagdir, self.stem)
        self.storage = self.STORAGE_PLUGINS[self.storage_plugin](place, self.compression_mode)

    def close(self) -> None:
        """Finish the storage file (summary, index); the bag's metadata.yaml is the caller's."""
        super().close()
        with contextlib.suppress(FileNotFoundError):
            self.metapath.unlink()
