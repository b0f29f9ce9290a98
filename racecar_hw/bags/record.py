"""Record bus topics into ROS 2 (MCAP or sqlite3) or ROS 1 bags, without ever delaying the bus.

:class:`Recorder` is a bus listener. Its callback runs in the bus's event-loop thread and only
queues ``(topic, message, receive time)`` in an :class:`~racecar_hw.runtime.outbox.Outbox` (the
queue and thread the network publishers use too); its writer thread serializes and writes.
The writer is not woken per message: it drains the queue every :data:`BATCH_S`, or at once when
:data:`WAKE_AT` messages (or a quarter of ``queue_size``) wait. A control loop that has idle
moments says so with :meth:`Recorder.control_idle`: the daemon calls it when a scan's motor command
is out, and a drain that is due then runs in the gap before the next scan instead of competing
with the scan path for the interpreter (the writer then waits at most ``2 * BATCH_S`` on its own).
Serialization uses the generated serializers of :mod:`racecar_hw.rosmsg.serde` (rosbags' bytes);
the files are written by :mod:`racecar_hw.bags.writers` (MCAP with the ``mcap`` library, sqlite3)
and :mod:`racecar_hw.bags.ros1_writer`. When the queue is full the message is dropped and counted
(``stats.dropped``, and a warning at most once per flush interval): never silently, never by
blocking the control loop.

Messages must not be mutated after they are published (the bus's rule too): the writer serializes
them later, in another thread.

Crash safety. Every ``flush_interval_s`` the writer pushes its buffered chunk to the file and
fsyncs it: for MCAP it closes the pending chunk, for ROS 1 it writes the pending chunk record, for
sqlite3 it commits. ROS 2 bags also get their ``metadata.yaml`` (re)written at every flush, not only
at close. A recording killed with SIGKILL or by a power loss therefore keeps everything up to the
last flush:

* sqlite3: the bag reads as it is (rosbags, ros2 bag) with every committed message.
* MCAP: the file lacks its summary and footer; the ``mcap`` stream reader reads it up to the last
  chunk, and :func:`racecar_hw.bags.recover.recover_bag` rewrites it into a closed bag.
* ROS 1: the file lacks its index (``index_pos`` 0); :func:`~racecar_hw.bags.recover.recover_bag`
  or the real ``rosbag reindex`` rebuilds it.

Splitting by size or duration closes each split as a complete file, so only the split being
written at the moment of the crash needs recovery. A ROS 2 recording is one bag directory
``<name>/`` whose files are the splits (``<name>_0.mcap``, ``<name>_1.mcap``, ... listed in its one
``metadata.yaml``), as ``ros2 bag record --max-bag-size`` writes them; a ROS 1 recording's splits
are ``<name>_<n>.bag`` files, as ``rosbag record --split`` writes them.

Latched topics: which topics are latched, and with what QoS, is the live topic table's knowledge
(:data:`racecar_hw.base.topics.LATCHED_TOPICS`: ``/tf_static``, the mux's active source, ``/map``,
``/rosout``; the daemon passes its configured table's latched rows). The latest message of each is
written at the start of every split, including one published before recording began, so a split
alone has the map and the static transforms. ROS 2 topics are offered with the QoS a ROS 2
publisher would use (:func:`offered_qos`, in ``metadata.yaml`` and in each MCAP channel's
metadata): latched topics transient-local, LaserScan the sensor-data profile; ROS 1 connections of
latched topics carry ``latching=1``, as ``rosbag record`` writes them.
"""

from __future__ import annotations

import logging
import math
import os
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from glob import escape as glob_escape
from pathlib import Path
from typing import Any

import yaml
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

from racecar_hw.bags.qos import dump_qos_v8
from racecar_hw.bags.ros1_writer import Ros1Writer
from racecar_hw.bags.writers import Storage, bag_info, open_storage
from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import NS_PER_S, wall_ns
from racecar_hw.base.errors import BagError, BagWriteError, ConfigError
from racecar_hw.base.messages import Message
from racecar_hw.base.params import param
from racecar_hw.base.qos import SENSOR_DATA, Durability, Reliability
from racecar_hw.base.qos import Qos as TopicQos
from racecar_hw.base.topics import LATCHED_TOPICS
from racecar_hw.rosmsg.typestore import BagTypes, types_for
from racecar_hw.runtime.extras import require_extra
from racecar_hw.runtime.lockstep import hold_while
from racecar_hw.runtime.outbox import Outbox

log = logging.getLogger(__name__)

#: The writer thread wakes this often to drain the queue (one wakeup per batch, not per message).
BATCH_S = 0.2
#: ... or as soon as this many messages wait (or a quarter of ``queue_size``, if smaller).
WAKE_AT = 256
#: The chunk compressions each format offers: MCAP's zstd as rosbag2's MCAP plug-in writes it
#: (``zstd_fast``); ROS 1's bz2 as ``rosbag record --bz2``.
COMPRESSIONS = {"mcap": ("none", "zstd"), "sqlite3": ("none",), "ros1": ("none", "bz2")}
LZ4_REFUSAL = (
    "lz4 is not offered for ROS 1 bags: the real rosbag (ROS Noetic, Debian python3-rosbag) cannot "
    "read the LZ4 chunks rosbags writes; use compression 'bz2' or 'none'"
)

#: Niceness the writer thread gives itself (Linux: per thread): disk work yields the CPU to the
#: control path whenever both want it. Lowering one's own priority needs no privilege.
WRITER_NICE = 10
#: At stop, the writer is waited for as long as it writes; after this long (s) without a message
#: written (a stuck disk), it is left behind and the bag incomplete (recoverable): a slow disk once
#: held the shutdown, and the car's service, for as long as it stayed slow.
WRITER_STALL_S = 15.0


@dataclass
class RecorderParams:
    """Parameters of the bag recorder (the ``bag`` section of the configuration)."""

    enabled: bool = param(False, "record bus topics into a bag")
    path: str = param("bags", "directory that receives the bags (created if missing)", nonempty=True)
    name: str = param("", "base name of the bag; empty = racecar_<YYYYmmdd-HHMMSS>")
    format: str = param("mcap", "bag format: ROS 2 mcap or sqlite3, or a ROS 1 .bag",
                        choices=("mcap", "sqlite3", "ros1"))
    compression: str = param("none", "chunk compression: zstd for MCAP, bz2 for ROS 1; lz4 is refused",
                             choices=("none", "zstd", "bz2", "lz4"))
    topics: list[str] = param([], "topics to record (shell patterns allowed); empty = all")
    exclude: list[str] = param([], "topics never recorded (shell patterns allowed)")
    queue_size: int = param(10000, "messages waiting for the writer before new ones are dropped",
                            min=1, max=10_000_000)
    flush_interval_s: float = param(1.0, "push buffered data to disk (crash-safe point) every",
                                    unit="s", min=0.01, max=3600.0)
    split_size_mb: float = param(0.0, "start a new bag when the current one exceeds this; 0 = never",
                                 unit="MB", min=0.0)
    split_duration_s: float = param(0.0, "start a new bag after this much recording; 0 = never",
                                    unit="s", min=0.0)

    def __post_init__(self) -> None:
        if self.enabled and self.format == "mcap":  # refused at start, not when the first bag opens
            require_extra("mcap", "recording MCAP bags (or format: sqlite3 or ros1)", "recorder.format")
        offered = COMPRESSIONS[self.format]
        if self.compression not in offered:
            raise ConfigError("compression", LZ4_REFUSAL if (self.format, self.compression) == ("ros1", "lz4")
                              else f"{self.compression} is not offered for format {self.format!r}: use "
                              + " or ".join(repr(c) for c in reversed(offered)))
        if self.name in (".", "..") or "/" in self.name or os.sep in self.name or "\0" in self.name:
            # a path would put the bag's files (ROS 2: and a metadata.yaml) outside recorder.path
            raise ConfigError("name", f"{self.name!r} is not a plain name (no '/', not '.' or '..'): "
                                      "the bag goes into recorder.path, named this")


@dataclass
class RecorderStats:
    """A snapshot of what the recorder did: counts, payload bytes and the bags it created.

    ``files``: the bag directory (ROS 2: one, whatever the splits) or every ``.bag`` (ROS 1).
    ``flushed`` counts the messages on disk as of the last flush: what survives a crash.
    """

    written: int = 0
    dropped: int = 0
    bytes: int = 0
    queued: int = 0
    flushed: int = 0
    files: list[Path] = field(default_factory=list)
    error: str | None = None


def bag_qos(qos: TopicQos) -> Qos:
    """A topic's QoS as rosbag2 writes an offered profile (KEEP_LAST ``depth``, no deadline,
    lifespan or lease, automatic liveliness)."""
    zero = QosTime(0, 0)
    reliability = (QosReliability.RELIABLE if qos.reliability is Reliability.RELIABLE
                   else QosReliability.BEST_EFFORT)
    durability = (QosDurability.TRANSIENT_LOCAL if qos.durability is Durability.TRANSIENT_LOCAL
                  else QosDurability.VOLATILE)
    return Qos(QosHistory.KEEP_LAST, qos.depth, reliability, durability, zero, zero,
               QosLiveliness.AUTOMATIC, zero, False)


def offered_qos(topic: str, cls: type[Message],
                latched: Mapping[str, TopicQos] = LATCHED_TOPICS) -> list[Qos]:
    """The QoS profiles a ROS 2 publisher of ``topic`` would offer: latched topics (``latched``, the
    live table's) transient-local, sensor streams (LaserScan) the sensor-data profile, everything
    else the default (none listed)."""
    if topic in latched:
        return [bag_qos(latched[topic])]
    if cls.ROS_TYPE == "sensor_msgs/msg/LaserScan":
        return [bag_qos(SENSOR_DATA)]
    return []


@dataclass
class _TopicInfo:
    msgtype: str
    qos: str
    digest: str
    closed_count: int = 0


class Ros2BagMetadata:
    """``metadata.yaml`` of a rosbag2 bag being recorded: every closed file plus the open one.

    A recording's splits are the files of one bag (``<name>_0.mcap``, ``<name>_1.mcap``, ...),
    as ``ros2 bag record --max-bag-size`` makes them. The text is rendered from a template dumped
    once per set of topics and files (see :meth:`text`), so a flush only joins numbers into it.
    """

    def __init__(self, bagdir: Path, storage_identifier: str) -> None:
        self.bagdir = bagdir
        self.storage_identifier = storage_identifier
        self.closed_files: list[tuple[str, int, int, int]] = []  # name, start ns, duration ns, count
        self.topics: dict[str, _TopicInfo] = {}
        self.complete = False
        self._template: tuple[tuple[int, int, bool], list[str], list[int]] | None = None

    def add_topic(self, topic: str, msgtype: str, qos: str, digest: str) -> None:
        """Note a topic the first time any file of the bag writes it (``qos``: metadata.yaml text)."""
        if topic not in self.topics:
            self.topics[topic] = _TopicInfo(msgtype, qos, digest)

    def file_closed(self, bag: BagFile) -> None:
        """Fold a finished file's numbers into the bag's."""
        start = bag.first_ns or 0
        self.closed_files.append((bag.file_name, start, bag.last_ns - start if bag.count else 0,
                                  bag.count))
        for topic, count in bag.topic_counts.items():
            self.topics[topic].closed_count += count

    def numbers(self, current: BagFile | None) -> list[int]:
        """Every number of the document, in the order :meth:`info` takes them."""
        files = list(self.closed_files)
        if current is not None:
            start = current.first_ns or 0
            files.append((current.file_name, start, current.last_ns - start if current.count else 0,
                          current.count))
        used = [(s, s + d) for _n, s, d, c in files if c]
        start = min((s for s, _e in used), default=0)
        end = max((e for _s, e in used), default=0)
        counts = [info.closed_count + (current.topic_counts.get(topic, 0) if current else 0)
                  for topic, info in self.topics.items()]
        per_file = [v for _n, s, d, c in files for v in (s, d, c)]
        return [end - start, start, sum(c for *_x, c in files), *counts, *per_file]

    def file_names(self, current: BagFile | None) -> list[str]:
        return [n for n, *_x in self.closed_files] + ([current.file_name] if current else [])

    def info(self, names: list[str], numbers: list[int]) -> dict[str, Any]:
        """The ``rosbag2_bagfile_information`` mapping for ``numbers`` (see :meth:`numbers`)."""
        duration, start, count = numbers[:3]
        counts = numbers[3:3 + len(self.topics)]
        per_file = numbers[3 + len(self.topics):]
        topics = [(topic, info.msgtype, info.qos, info.digest, n)
                  for (topic, info), n in zip(self.topics.items(), counts, strict=True)]
        files = [(name, per_file[3 * i], per_file[3 * i + 1], per_file[3 * i + 2])
                 for i, name in enumerate(names)]
        return bag_info(self.storage_identifier, duration=duration, start=start, count=count,
                        files=files, topics=topics, complete=self.complete)

    def text(self, current: BagFile | None) -> str:
        """``metadata.yaml``: the text ``yaml.safe_dump`` gives for :meth:`info`, from a template.

        The template is the document dumped with unique sentinel integers in place of the counts
        and times, split around them; a flush only joins the pieces with the current numbers.
        """
        numbers = self.numbers(current)
        names = self.file_names(current)
        key = (len(self.topics), len(names), self.complete)
        if self._template is None or self._template[0] != key:
            sentinels = [_SENTINEL + i for i in range(len(numbers))]
            text = yaml.dump({"rosbag2_bagfile_information": self.info(names, sentinels)},
                             Dumper=yaml.SafeDumper, sort_keys=False)
            pieces = re.split(r"(?<![0-9])(" + str(_SENTINEL)[:-3] + r"[0-9]{3})(?![0-9])", text)
            slots = [int(v) - _SENTINEL for v in pieces[1::2]]
            if sorted(set(slots)) != list(range(len(numbers))):
                # A number went missing from the text: dump every time (never happens with our keys).
                return yaml.dump({"rosbag2_bagfile_information": self.info(names, numbers)},
                                 Dumper=yaml.SafeDumper, sort_keys=False)
            self._template = (key, pieces, slots)
        _, pieces, slots = self._template
        values = [str(v) for v in numbers]
        parts = list(pieces)
        parts[1::2] = [values[i] for i in slots]
        return "".join(parts)

    def write(self, current: BagFile | None) -> None:
        """Write ``metadata.yaml`` atomically (temporary file, fsync, rename)."""
        text = self.text(current)
        meta = self.bagdir / "metadata.yaml"
        tmp = meta.with_suffix(".yaml.tmp")
        try:
            with tmp.open("w", encoding="utf8") as fh:
                fh.write(text)
                _sync(fh)
            tmp.replace(meta)
        except FileNotFoundError as err:  # the folder went (the storage file's check says so first)
            raise BagWriteError(f"{self.bagdir}: the bag folder was deleted or moved while "
                                "recording") from err


class UnserializableMessage(BagError):
    """A message the serializer refuses (a value that does not fit its field): that message is
    dropped and counted, the recording goes on."""


class BagFile:
    """One file being written (one split): connections by topic, flush to disk, close.

    ROS 1: ``path`` is the ``.bag`` file. ROS 2: ``path`` is the storage file without its
    extension, inside the bag directory ``path.parent``, whose ``metadata.yaml`` (``meta``,
    shared by the splits) describes every file of the bag.
    """

    def __init__(self, path: Path, fmt: str, compression: str, types: BagTypes,
                 meta: Ros2BagMetadata | None = None,
                 latched: Mapping[str, TopicQos] = LATCHED_TOPICS, seq: dict[str, int] | None = None) -> None:
        self.path = path
        self.format = fmt
        self.types = types
        self.latched = latched  # topic -> QoS of the latched topics
        self.bytes = 0
        self.count = 0
        self.first_ns: int | None = None
        self.last_ns = 0
        self._conns: dict[str, Any] = {}  # topic -> connection id (ROS 2) or Ros1Connection
        self.topic_counts: dict[str, int] = {}
        #: each topic's last ROS 1 header ``seq``: shared by the splits of a recording, so it goes
        #: on across them as ``rosbag record --split`` writes it (it started again at 1 in each)
        self.seq: dict[str, int] = {} if seq is None else seq
        if fmt != "ros1" and meta is None:
            meta = Ros2BagMetadata(path.parent, fmt)
        self.meta = meta
        self._ros1: Ros1Writer | None = None
        self._storage: Storage | None = None
        if fmt == "ros1":
            self._ros1 = Ros1Writer(path, compression)
            self.file_name = path.name
        else:
            self._storage = open_storage(path.parent, path.name, fmt, compression)
            self.file_name = self._storage.path.name
        if self.meta is not None:
            self.meta.write(self)

    def write(self, topic: str, msg: Message, t_ns: int) -> int:
        """Serialize and append ``msg``; returns the payload size in bytes."""
        seq = self.seq.get(topic, 0) + 1
        try:
            data = self.types.serialize(msg, seq)
        except Exception as err:
            raise UnserializableMessage(f"{topic}: a {type(msg).__name__} that cannot be serialized: "
                                        f"{type(err).__name__}: {err}") from err
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._add_connection(topic, type(msg))
        self.seq[topic] = seq
        if self._storage is not None:
            self._storage.write(conn, t_ns, data)
        else:
            assert self._ros1 is not None
            self._ros1.write(conn, t_ns, data)
        self.topic_counts[topic] += 1
        self.count += 1
        size = len(data)
        self.bytes += size
        if self.first_ns is None:
            self.first_ns = t_ns
        if t_ns > self.last_ns:
            self.last_ns = t_ns
        return size

    def flush(self) -> None:
        """Push buffered messages into the file and fsync: a crash keeps everything up to here."""
        if self._ros1 is not None:
            self._ros1.flush()
            return
        assert self._storage is not None and self.meta is not None
        self._storage.flush()
        self.meta.write(self)

    def close(self, last: bool = True) -> None:
        """Write the index/summary (and, ROS 2, the bag's metadata): the file is complete.

        ``last``: no further split of this bag follows, so the bag is complete too.
        """
        if self._ros1 is not None:
            self._ros1.close()
            return
        assert self._storage is not None and self.meta is not None
        self.meta.file_closed(self)
        self.meta.complete = last
        self._storage.close(self.meta.text(None))
        self.meta.write(None)

    def abort(self) -> None:
        """Close without finishing (after a write error)."""
        try:
            if self._ros1 is not None:
                self._ros1.abort()
            elif self._storage is not None:
                self._storage.abort()
        except OSError as err:  # the disk still takes nothing: the buffered bytes are lost, as said
            log.warning("bag %s: closed with its last buffered bytes unwritten (%s)", self.path, err)
        except Exception:
            log.exception("aborting bag %s failed", self.path)

    def _add_connection(self, topic: str, cls: type[Message]) -> Any:
        typename = cls.ROS_TYPE
        msgdef, digest = self.types.msgdef(typename), self.types.digest(typename)
        if self._ros1 is not None:
            pkg, _, name = typename.partition("/msg/")
            conn: Any = self._ros1.add_connection(topic, f"{pkg}/{name}", digest, msgdef,
                                                  callerid="/racecar_hw",
                                                  latching=1 if topic in self.latched else None)
        else:
            assert self._storage is not None and self.meta is not None
            qos = dump_qos_v8(offered_qos(topic, cls, self.latched))
            conn = self._storage.add_connection(topic, typename, msgdef, digest, qos)
            self.meta.add_topic(topic, typename, qos, digest)
        self._conns[topic] = conn
        self.topic_counts[topic] = 0
        return conn


class Splits:
    """The files of one recording, named as the ROS tools name them: ``rosbag record --split``'s
    ``<name>_0.bag``, ``<name>_1.bag`` ... (ROS 1), or one bag folder ``<name>/`` whose files are
    the splits (``ros2 bag record --max-bag-size``: ``<name>_0.mcap`` ...).

    Made at start, it refuses a name already taken there: a ROS 2 bag folder, or any ROS 1 split
    ``<name>_<n>.bag`` (one found only when the recording reached that split once ended it 0.4 s in).
    """

    def __init__(self, folder: Path, params: RecorderParams, types: BagTypes,
                 latched: Mapping[str, TopicQos] = LATCHED_TOPICS) -> None:
        base = params.name or time.strftime("racecar_%Y%m%d-%H%M%S")
        self.folder, self.base, self.params, self.types = folder, base, params, types
        self.latched = latched
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as err:  # no permission, a read-only file system, a file in the way
            raise BagError(f"cannot create the bag folder {folder} (recorder.path): "
                           f"{err.strerror or err}") from None
        self.index = 0
        self.files: list[Path] = []  # the bag folder (ROS 2) or every .bag (ROS 1)
        if params.format != "ros1":
            if (folder / base).exists():
                raise BagError(f"cannot create bag {folder / base}: it exists already, not overwriting")
            return
        taken = sorted(p.name for p in folder.glob(f"{glob_escape(base)}_*.bag")
                       if p.name[len(base) + 1:-4].isdigit())
        if taken:
            raise BagError(f"cannot record into {folder}: {', '.join(taken[:3])}"
                           f"{' ...' if len(taken) > 3 else ''} exists already, not overwriting "
                           "(recorder.name: choose another, or move those bags)")

    def due(self, f: BagFile, t_ns: int) -> bool:
        """Whether a message at ``t_ns`` goes into a new split rather than into ``f``."""
        if f.count == 0:
            return False
        p = self.params
        if p.split_size_mb and f.bytes >= p.split_size_mb * 1e6:
            return True
        first = f.first_ns if f.first_ns is not None else t_ns
        return bool(p.split_duration_s) and t_ns - first >= p.split_duration_s * NS_PER_S

    def open(self, previous: BagFile | None) -> BagFile:
        """The next split (``previous``: the one before, closed; ROS 2 shares its metadata)."""
        p, index = self.params, self.index
        if p.format == "ros1":
            path = self.folder / f"{self.base}_{index}.bag"
            bag = BagFile(path, "ros1", p.compression, self.types, latched=self.latched,
                          seq=previous.seq if previous is not None else None)
            self.files.append(path)
        else:
            bagdir = self.folder / self.base
            bag = BagFile(bagdir / f"{self.base}_{index}", p.format, p.compression, self.types,
                          previous.meta if previous is not None else None, self.latched)
            if index == 0:
                self.files.append(bagdir)
        self.index += 1
        return bag


#: Stand-ins for the numbers of metadata.yaml when its template is dumped (19 digits, unique).
_SENTINEL = 7_319_000_000_000_000_000


def _sync(fh: Any) -> None:
    fh.flush()
    os.fsync(fh.fileno())


class Recorder:
    """Records bus topics into bags; see the module docstring for guarantees.

    ``start()`` opens the first bag (raising :class:`BagError` when it cannot) and subscribes;
    ``stop()`` flushes and closes (safe twice). Also a context manager.
    """

    def __init__(self, bus: Bus, params: RecorderParams,
                 latched: Mapping[str, TopicQos] | None = None) -> None:
        self.bus = bus
        self.params = params
        #: the latched topics and their QoS: :data:`LATCHED_TOPICS` and ``latched`` (the daemon's
        #: configured topic table, where the mux's active topic may have another name)
        self.latched: Mapping[str, TopicQos] = {**LATCHED_TOPICS, **(latched or {})}
        self.types = types_for(1 if params.format == "ros1" else 2)
        # The writer drains every BATCH_S; a queue this long wakes it at once (well before drops).
        # A full queue drops the new message: the bag keeps what it has queued.
        self._outbox = Outbox("bag-writer", params.queue_size, WRITER_NICE, batch_s=BATCH_S,
                              wake_at=min(WAKE_AT, params.queue_size // 4), drop="newest",
                              on_batch=self._flush_if_due, on_stop=self._close)
        self._sub: Subscription | None = None
        self._wanted: dict[str, bool] = {}
        self._latest_latched: dict[str, Message] = {}  # the latest message of each latched topic
        self._file: BagFile | None = None
        self._splits: Splits | None = None
        self._dir = Path(params.path)
        self._next_flush = 0.0
        self._written = self._bytes = self._flushed = 0  # messages written, their bytes, on disk
        self._release_hold: Callable[[], None] = lambda: None
        # dropped after a write error (the outbox counts those of a full queue), and said so far
        self._dropped = self._dropped_logged = 0
        self._behind_said_at = -math.inf
        self._unserializable: set[str] = set()  # topics that had a message the serializer refused
        self._error: str | None = None

    # --- public API ---------------------------------------------------------------------------

    @property
    def stats(self) -> RecorderStats:
        """Counts so far (written, dropped, payload bytes, waiting) and the bags created."""
        return RecorderStats(self._written, self._all_dropped, self._bytes, len(self._outbox),
                             self._flushed, list(self._splits.files if self._splits else []), self._error)

    @property
    def _all_dropped(self) -> int:
        return self._dropped + self._outbox.dropped

    running = property(lambda self: self._outbox.running, doc="Whether the writer thread is running.")

    def start(self, timeout_s: float | None = None) -> None:
        """:meth:`open`, :meth:`wait_opened` (``timeout_s``), :meth:`subscribe`."""
        if self.open():
            self.wait_opened(timeout_s)
            self.subscribe()

    def open(self) -> bool:
        """Make the bag folder and start the writer thread, which opens the first bag (not waited
        for here); whether that is under way (not when disabled or started already)."""
        if not self.params.enabled:
            log.info("bag recording disabled")
            return False
        if self.running:
            return False
        self._splits = Splits(Path(self.params.path).expanduser(), self.params, self.types,
                              self.latched)
        self._dir = self._splits.folder
        now = wall_ns()
        for topic in self.latched:
            latest = self.bus.latest(topic)
            if latest is not None and self._is_wanted(topic):
                self._outbox.put(self._write, topic, latest, now)
        # The writer thread opens the bag: sqlite3 connections belong to the thread that made them.
        self._outbox.start(setup=self._open_first, wait=False)
        return True

    def wait_opened(self, timeout_s: float | None = None) -> None:
        """Wait (blocking) for the first bag to open, at most ``timeout_s`` (None: :data:`WRITER_STALL_S`)
        or until :meth:`abandon_open`; else :class:`BagError` (a stuck disk once held start and Ctrl-C)."""
        timeout_s = WRITER_STALL_S if timeout_s is None else timeout_s
        try:
            if not self._outbox.wait_started(timeout_s):
                why = ("stopped while its disk did not answer" if self._outbox.abandoned else
                       f"the disk did not answer for {timeout_s:g} s")
                raise BagError(f"cannot start recording into {self._dir} (recorder.path): {why}")
        except BagError as err:
            self._error = str(err)
            self._outbox.clear()
            raise

    def abandon_open(self) -> None:
        """Make a :meth:`wait_opened` in another thread raise its :class:`BagError` now (a stop)."""
        self._outbox.abandon_start()

    def subscribe(self) -> None:
        """Record from now on (after :meth:`wait_opened`; on the bus's event-loop thread)."""
        assert self._file is not None
        # in lockstep the sim's time waits for a writer that fell behind, instead of dropping (but
        # not for a writer thread that is gone: its queue would never drain)
        half, outbox = max(1, self.params.queue_size // 2), self._outbox
        self._release_hold = hold_while(lambda: len(outbox) >= half and outbox.running)
        self._sub = self.bus.subscribe_all(self._on_message)
        log.info("recording %s to %s", ", ".join(self.params.topics) or "all topics",
                 self._file.path)

    def stop(self) -> RecorderStats:
        """Unsubscribe, write what is queued, close the bag; returns the final stats."""
        self._release_hold()
        if self._sub is not None:
            self._sub.close()
            self._sub = None
        if self.running:
            # every recorded message reaches the file, however slow the disk, while it takes any
            if not self._outbox.stop(timeout_s=None, stall_s=WRITER_STALL_S):
                # left behind: a recording cut short, not a success (what it had queued is lost)
                bag = self.stats.files[-1] if self.stats.files else self._dir
                self._error = (f"the bag writer did not finish within {WRITER_STALL_S:g} s (a stuck "
                               f"disk?): {bag} is incomplete")
                self._lose_unflushed()
            stats = self.stats
            log.info("recorded %d messages (%d dropped, %d bytes) into %s", stats.written,
                     stats.dropped, stats.bytes, ", ".join(map(str, stats.files)))
            _warn_unmatched(self.params.topics, self._wanted)
        if self._error is not None:  # said when it happened; said again where a run ends
            log.error("recording stopped early (%s): %d messages on disk, %d dropped; racecar-hw "
                      "bag recover reads them", self._error, self.stats.flushed, self.stats.dropped)
        return self.stats

    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- bus thread ---------------------------------------------------------------------------

    def _on_message(self, topic: str, msg: Message) -> None:
        wanted = self._wanted.get(topic)
        if wanted is None:
            wanted = self._is_wanted(topic)
        if not wanted:
            return
        if self._error is not None:
            self._dropped += 1
            return
        self._outbox.put(self._write, topic, msg, wall_ns())
        if self._outbox.dropped > self._dropped_logged:  # said here: a stuck writer says nothing
            self._say_behind()

    def _say_behind(self) -> None:
        now = time.monotonic()
        if now >= self._behind_said_at + self.params.flush_interval_s:
            self._behind_said_at = now
            self._dropped_logged = self._all_dropped
            log.warning("bag writer is behind: dropped %d messages so far (queue_size %d)",
                        self._dropped_logged, self.params.queue_size)

    def control_idle(self) -> None:
        """The control path is idle until its next event: wake the writer if a drain is due."""
        self._outbox.control_idle()

    def _is_wanted(self, topic: str) -> bool:
        p = self.params
        wanted = ((not p.topics or any(fnmatchcase(topic, pat) for pat in p.topics))
                  and not any(fnmatchcase(topic, pat) for pat in p.exclude))
        self._wanted[topic] = wanted
        return wanted

    # --- writer thread ------------------------------------------------------------------------

    def _open_first(self) -> None:
        assert self._splits is not None
        self._file = self._splits.open(None)
        self._next_flush = time.monotonic() + self.params.flush_interval_s

    def _flush_if_due(self) -> float:
        """After every batch: flush when the interval is up; returns the seconds to the next flush."""
        now = time.monotonic()
        if now >= self._next_flush:
            self._next_flush = now + self.params.flush_interval_s
            try:
                self._flush()
            except Exception as err:
                self._fail(err)
        return self._next_flush - time.monotonic()

    def _write(self, topic: str, msg: Message, t_ns: int) -> None:
        if self._file is None:
            self._dropped += 1
            return
        try:
            self._write_file(topic, msg, t_ns)
        except Exception as err:
            self._fail(err)

    def _write_file(self, topic: str, msg: Message, t_ns: int) -> None:
        assert self._file is not None and self._splits is not None
        if topic in self.latched:
            self._latest_latched[topic] = msg
        if self._splits.due(self._file, t_ns):
            self._file.close(last=False)
            self._flushed = self._written  # a closed split is on disk
            self._file = self._splits.open(self._file)
            for latched_topic, latched_msg in self._latest_latched.items():
                if latched_topic != topic:
                    self._bytes += self._file.write(latched_topic, latched_msg, t_ns)
        try:
            self._bytes += self._file.write(topic, msg, t_ns)
        except UnserializableMessage as err:  # the message's fault, not the bag's: drop it, go on
            self._dropped += 1
            if topic not in self._unserializable:
                self._unserializable.add(topic)
                log.warning("bag: dropped %s (and any further such message on this topic, counted as "
                            "dropped)", err)
            return
        self._written += 1

    def _flush(self) -> None:
        if self._file is not None:
            self._file.flush()
            self._flushed = self._written

    def _fail(self, err: Exception) -> None:
        self._error = f"{type(err).__name__}: {err}"
        log.error("bag writing failed, recording stops (messages now count as dropped): %s",
                  self._error)
        self._lose_unflushed()
        if self._file is not None:
            self._file.abort()
            self._file = None

    def _lose_unflushed(self) -> None:
        """The recording stops short: what was queued, and what was written since the last flush
        (not known to be on disk), count as dropped; ``written`` is what is on disk."""
        self._dropped += self._outbox.clear() + self._written - self._flushed
        self._written = self._flushed

    def _close(self) -> None:
        if self._file is None:
            return
        try:
            self._file.close()
            self._flushed = self._written
        except Exception as err:
            self._fail(err)
        self._file = None
        dropped = self._all_dropped
        if dropped > self._dropped_logged:
            log.warning("bag recorder dropped %d messages in total", dropped)
            self._dropped_logged = dropped


def _warn_unmatched(patterns: list[str], seen: dict[str, bool]) -> None:
    """Warn of each of ``recorder.topics``'s ``patterns`` that matched none of the topics ``seen``
    on the bus while recording: a typo ("/scna") recorded nothing, and the run ended with exit 0 and
    an info line, the bag holding nothing of what was asked."""
    for pattern in patterns:
        if not any(fnmatchcase(topic, pattern) for topic in seen):
            log.warning("recorder.topics: nothing was published on %r while recording (published: %s)",
                        pattern, ", ".join(sorted(seen)) or "nothing")


def record_params(path: str | Path, fmt: str = "mcap", **overrides: Any) -> RecorderParams:
    """Enabled recorder parameters writing ``fmt`` bags into ``path`` (for the CLI's ``--record``)."""
    return RecorderParams(enabled=True, path=str(path), format=fmt, **overrides)
