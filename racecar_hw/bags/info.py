"""What is in a bag (``racecar-hw bag info``): topics, types, counts, time range, and whether it is complete.

A complete bag is summarized from its index (ROS 1) or summary and metadata (ROS 2) through
rosbags, without reading every message (a ROS 1 bag's chunks are read once all the same, by
:func:`~racecar_hw.bags.recover.inspect_bag`, to check its index against them). An incomplete one
(an interrupted recording) is summarized from what :mod:`racecar_hw.bags.recover` finds in its
files: the messages a recovery would keep (an empty split file holds none). Either way messages
are counted as they are read, never kept, and the files are read as they are scanned
(:mod:`racecar_hw.bags.filebytes`): memory holds one chunk (a compressed one at most 64 MiB
decompressed, ``max_message_bytes``), whatever the number of messages and the size of the file.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass, field
from pathlib import Path

from racecar_hw.bags.filebytes import open_file_bytes
from racecar_hw.bags.recover import BagState, Tally, inspect_bag, read_db, scan_mcap, scan_ros1
from racecar_hw.bags.validate import MCAP_MAGIC, describe, guarded, open_regular, storage_files
from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.errors import BagError
from racecar_hw.rosmsg.typestore import ros2_types

FORMAT_NAMES = {"ros1": "ROS 1 (rosbag v2.0)", "mcap": "ROS 2 (mcap)", "sqlite3": "ROS 2 (sqlite3)"}


@dataclass(frozen=True)
class TopicSummary:
    """One topic: its ROS 2 type name and how many messages the bag holds on it."""

    topic: str
    msgtype: str
    count: int


@dataclass
class BagInfo:
    """A bag's summary. Times are bag times in ns since the epoch (None: no messages)."""

    state: BagState
    topics: list[TopicSummary] = field(default_factory=list)
    start_ns: int | None = None
    end_ns: int | None = None

    @property
    def messages(self) -> int:
        """Messages on every topic."""
        return sum(t.count for t in self.topics)

    @property
    def duration_s(self) -> float:
        """Seconds from the first message to the last (0 without messages)."""
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / NS_PER_S


@guarded
def bag_info(path: str | Path) -> BagInfo:
    """Summarize the bag at ``path`` (a ROS 1 file or a ROS 2 directory); raises :class:`BagError`.

    As ``racecar-hw follow``, it reads only regular files, and refuses a ROS 2 bag whose
    metadata.yaml lists a storage file not named ``*.mcap`` or ``*.db3`` (:func:`storage_files`).
    """
    src = Path(path)
    if src.is_dir():
        storage_files(src)
    elif src.exists() or src.is_symlink():
        with open_regular(src) as f:
            if f.read(len(MCAP_MAGIC)) == MCAP_MAGIC:  # a ROS 2 bag's .mcap file: the bag is its directory
                storage_files(src.parent)
    state = inspect_bag(path)
    if state.complete:
        return _from_reader(state)
    if state.format == "sqlite3":
        return _from_databases(state)
    found = _Found()
    if state.format == "ros1":
        with open_file_bytes(state.path) as data:
            scan = scan_ros1(data)
        for cid, conn in scan.connections.items():
            pkg, _, name = conn["type"].decode().partition("/")
            found.add(scan.tally, cid, conn["topic"].decode(), f"{pkg}/msg/{name}")
    else:
        for file in state.files:
            with open_file_bytes(file) as data:
                mcap = scan_mcap(data)
            for cid, (sid, topic, _enc) in mcap.channels.items():
                found.add(mcap.tally, cid, topic, mcap.schemas[sid][0] if sid in mcap.schemas else "?")
    topics = [TopicSummary(t, found.types[t], n) for t, n in sorted(found.counts.items())]
    return BagInfo(state, topics, min(found.starts, default=None), max(found.ends, default=None))


@dataclass
class _Found:
    """What a scan's tally says of the topics of an unfinished bag (messages on a connection or
    channel id the scan found no definition of are left out, as a recovery leaves them out)."""

    counts: dict[str, int] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    starts: list[int] = field(default_factory=list)
    ends: list[int] = field(default_factory=list)

    def add(self, tally: Tally, cid: int, topic: str, msgtype: str) -> None:
        n = tally.counts.get(cid, 0)
        if not n:
            return
        self.counts[topic] = self.counts.get(topic, 0) + n
        self.types[topic] = msgtype
        self.starts.append(tally.first[cid])
        self.ends.append(tally.last[cid])


def _from_databases(state: BagState) -> BagInfo:
    """An incomplete sqlite3 bag, read database by database (changing nothing): a file without
    tables, which a reader of the whole bag refuses, holds no messages."""
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    starts, ends = [], []
    for db in state.files:
        content = read_db(db, readonly=True)
        names = {}
        for tid, name, msgtype, *_rest in content.topics:
            names[tid] = name
            types.setdefault(name, msgtype)
            counts.setdefault(name, 0)
        for tid, n in content.counts.items():
            if tid in names:
                counts[names[tid]] += n
        if content.counts:
            starts.append(content.start)
            ends.append(content.end)
    topics = [TopicSummary(t, types[t], n) for t, n in sorted(counts.items())]
    return BagInfo(state, topics, min(starts, default=None), max(ends, default=None))


def _from_reader(state: BagState) -> BagInfo:
    from rosbags.highlevel import AnyReader  # noqa: PLC0415 - rosbags' readers, only where a bag is read

    target = state.path
    try:
        with AnyReader([target], default_typestore=ros2_types().store) as reader:
            counts: dict[str, int] = {}
            types: dict[str, str] = {}
            for conn in reader.connections:
                counts[conn.topic] = counts.get(conn.topic, 0) + conn.msgcount
                types.setdefault(conn.topic, conn.msgtype)
            has_messages = reader.message_count > 0
            start = reader.start_time if has_messages else None
            end = reader.end_time - 1 if has_messages else None  # rosbags: one past the last
    except Exception as err:
        raise BagError(f"cannot read bag {target}: {describe(err)}") from err
    topics = [TopicSummary(t, types[t], n) for t, n in sorted(counts.items())]
    return BagInfo(state, topics, start, end)


def _when(t_ns: int | None) -> str:
    if t_ns is None:
        return "-"
    utc = datetime.datetime.fromtimestamp(t_ns / NS_PER_S, tz=datetime.timezone.utc)
    return f"{utc:%Y-%m-%d %H:%M:%S.%f} UTC ({t_ns // NS_PER_S}.{t_ns % NS_PER_S:09d})"


def format_info(info: BagInfo) -> str:
    """The summary as ``racecar-hw bag info`` prints it."""
    s = info.state
    files = f", {len(s.files)} files" if len(s.files) > 1 else ""
    if s.complete:
        complete = "yes"
    else:
        complete = f"no: {s.problem}\n{'':11}recover with: racecar-hw bag recover {s.path}"
        if s.format == "sqlite3":
            complete += " (rewrites metadata.yaml in place; -o OUT fixes a copy instead)"
    lines = [f"{'path:':<11}{s.path}",
             f"{'format:':<11}{FORMAT_NAMES[s.format]}{files}",
             f"{'complete:':<11}{complete}",
             f"{'messages:':<11}{info.messages}" + ("" if s.complete else " (readable ones)"),
             f"{'duration:':<11}{info.duration_s:.3f} s",
             f"{'start:':<11}{_when(info.start_ns)}",
             f"{'end:':<11}{_when(info.end_ns)}",
             "topics:" if info.topics else "topics:    none"]
    width = max((len(t.topic) for t in info.topics), default=0)
    type_width = max((len(t.msgtype) for t in info.topics), default=0)
    for t in info.topics:
        lines.append(f"  {t.topic:<{width}}  {t.msgtype:<{type_width}}  {t.count:>8} msgs")
    return "\n".join(lines)
