"""A lean per-message path into rosbags' MCAP writer, writing the bytes its ``write`` writes.

``rosbags.rosbag2.Writer.write`` costs several microseconds per message: a linear search of the
connection list comparing dataclasses, and a record built through a ``BytesIO`` with one call per
integer. :class:`McapAppender` appends the same Message record (opcode 0x05: channel id, sequence
0, log time and publish time both the bag time, the data) to the writer's pending chunk with one
``struct`` call, and keeps every counter the writer keeps (chunk and file time ranges, per-channel
counts, the rosbag2 writer's counts and time range), so rosbags' own ``close_chunk`` and ``close``
write the chunk index, summary and ``metadata.yaml`` exactly as if it had written the messages.
The resulting file is byte-identical (``tests/test_bag_record.py`` compares them).

It reaches into rosbags internals, so :meth:`McapAppender.attach` checks that they are the ones
it knows and returns None otherwise: the recorder then calls ``Writer.write`` as before.
"""

from __future__ import annotations

from struct import Struct
from typing import Any

from rosbags.rosbag2 import Writer as Writer2
from rosbags.rosbag2.storage_mcap import McapWriter

_MESSAGE_RECORD = Struct("<BQHIQQ")  # opcode, record length, channel id, sequence, log time, publish time
_MESSAGE_FIXED = 2 + 4 + 8 + 8
_CHUNK_LIMIT = 2**20  # rosbags closes a chunk once it grows past this many bytes

_STORAGE_ATTRS = ("chunk", "message_start_time", "message_end_time", "channel_stats", "close_chunk")
_CHUNK_ATTRS = ("bio", "msgs", "message_start_time", "message_end_time")
_WRITER_ATTRS = ("counts", "min_timestamp", "max_timestamp", "compression_mode")


class McapAppender:
    """Writes messages into an open rosbags MCAP writer; see the module docstring."""

    def __init__(self, writer: Writer2) -> None:
        self._writer = writer
        self._storage: Any = writer.storage

    @classmethod
    def attach(cls, writer: Writer2) -> McapAppender | None:
        """An appender for ``writer`` (open, MCAP, no per-message compression), or None."""
        storage: Any = getattr(writer, "storage", None)
        if not isinstance(storage, McapWriter):
            return None
        if not all(hasattr(storage, a) for a in _STORAGE_ATTRS):
            return None
        if not all(hasattr(storage.chunk, a) for a in _CHUNK_ATTRS):
            return None
        if not all(hasattr(writer, a) for a in _WRITER_ATTRS):
            return None
        if getattr(writer.compression_mode, "name", "") != "NONE":
            return None
        return cls(writer)

    def write(self, cid: int, t_ns: int, data: bytes) -> None:
        """Append ``data`` on channel ``cid`` at bag time ``t_ns`` (ns)."""
        storage = self._storage
        chunk = storage.chunk
        bio = chunk.bio
        chunk.msgs[cid].append((t_ns, bio.tell()))
        bio.write(_MESSAGE_RECORD.pack(0x05, _MESSAGE_FIXED + len(data), cid, 0, t_ns, t_ns))
        bio.write(data)
        if t_ns < chunk.message_start_time:
            chunk.message_start_time = t_ns
        if t_ns > chunk.message_end_time:
            chunk.message_end_time = t_ns
        if t_ns < storage.message_start_time:
            storage.message_start_time = t_ns
        if t_ns > storage.message_end_time:
            storage.message_end_time = t_ns
        storage.channel_stats[cid] += 1
        writer = self._writer
        writer.counts[cid] += 1  # type: ignore[attr-defined]
        if t_ns < writer.min_timestamp:  # type: ignore[attr-defined]
            writer.min_timestamp = t_ns  # type: ignore[attr-defined]
        if t_ns > writer.max_timestamp:  # type: ignore[attr-defined]
            writer.max_timestamp = t_ns  # type: ignore[attr-defined]
        if bio.tell() > _CHUNK_LIMIT:
            storage.close_chunk()
