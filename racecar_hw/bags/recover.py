"""Recover bags whose recording was killed (SIGKILL, power loss) before they were closed.

What a killed :class:`~racecar_hw.bags.record.Recorder` leaves, and what this module does with it:

* MCAP (ROS 2): header and every chunk flushed so far, no summary and no footer. rosbags refuses
  the file ("File end magic is invalid"). :func:`recover_bag` scans the records up to the last
  complete one and rewrites schemas, channels and messages into a new, closed bag directory.
* ROS 1: the bag header with ``index_pos`` 0, then the chunks flushed so far. rosbags and rosbag
  refuse it ("not indexed"). :func:`recover_bag` scans the chunk records (none, bz2 or lz4) up to
  the last complete one and rewrites connections and messages into a new, indexed bag.
* sqlite3 (ROS 2): every committed transaction. The bag already reads as it is; :func:`recover_bag`
  rolls back a hot journal (by opening the database normally) and rewrites ``metadata.yaml`` in
  place with the real message counts.

The scanners are plain functions over bytes (no I/O), so they can be tested on truncated data.
"""

from __future__ import annotations

import bz2
import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from racecar_hw.bags.validate import guarded
from racecar_hw.base.errors import BagError

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0\n"

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


@dataclass
class RecoveryResult:
    """Where the readable bag is, how many messages it holds, and whether it was already closed."""

    path: Path
    messages: int
    was_complete: bool


# --- MCAP -------------------------------------------------------------------------------------


@dataclass
class McapScan:
    """Records found in an MCAP file, up to the first truncated one."""

    schemas: dict[int, tuple[str, str, bytes]]          # id -> (name, encoding, data)
    channels: dict[int, tuple[int, str, str]]           # id -> (schema id, topic, encoding)
    messages: list[tuple[int, int, bytes]]              # (channel id, log time ns, data)
    complete: bool                                       # a footer was found


def scan_mcap(data: bytes) -> McapScan:
    """Every schema, channel and message in ``data`` up to the first truncated record."""
    if not data.startswith(MCAP_MAGIC):
        raise BagError("not an MCAP file (bad magic)")
    scan = McapScan({}, {}, [], False)
    for op, body in _mcap_records(data, len(MCAP_MAGIC)):
        if op == 0x06:
            _mcap_chunk(body, scan)
        elif op == 0x02:
            scan.complete = True
        else:
            _mcap_record(op, body, scan)
    return scan


def _mcap_records(data: bytes, pos: int) -> Iterator[tuple[int, bytes]]:
    end = len(data)
    while pos + 9 <= end:
        op = data[pos]
        (length,) = _U64.unpack_from(data, pos + 1)
        stop = pos + 9 + length
        if stop > end:
            return
        yield op, data[pos + 9:stop]
        pos = stop


def _mcap_string(body: bytes, pos: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(body, pos)
    return body[pos + 4:pos + 4 + n].decode(), pos + 4 + n


def _mcap_chunk(body: bytes, scan: McapScan) -> None:
    pos = 8 + 8 + 8 + 4
    compression, pos = _mcap_string(body, pos)
    (size,) = _U64.unpack_from(body, pos)
    records = body[pos + 8:pos + 8 + size]
    if compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        records = lz4.frame.decompress(records)
    elif compression:
        raise BagError(f"MCAP chunk compression {compression!r} is not supported by the recovery")
    for op, rec in _mcap_records(records, 0):
        _mcap_record(op, rec, scan)


def _mcap_record(op: int, body: bytes, scan: McapScan) -> None:
    if op == 0x03:
        (sid,) = _U16.unpack_from(body, 0)
        name, pos = _mcap_string(body, 2)
        encoding, pos = _mcap_string(body, pos)
        (n,) = _U32.unpack_from(body, pos)
        scan.schemas[sid] = (name, encoding, body[pos + 4:pos + 4 + n])
    elif op == 0x04:
        cid, sid = struct.unpack_from("<HH", body, 0)
        topic, pos = _mcap_string(body, 4)
        encoding, pos = _mcap_string(body, pos)
        scan.channels[cid] = (sid, topic, encoding)
    elif op == 0x05:
        cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", body, 0)
        scan.messages.append((cid, log_time, body[22:]))


def _recover_mcap(bagdir: Path, file: Path, out: Path) -> RecoveryResult:
    scan = scan_mcap(file.read_bytes())
    if scan.complete:
        return RecoveryResult(bagdir, len(scan.messages), True)
    store = get_typestore(Stores.EMPTY)
    for name, _enc, text in scan.schemas.values():
        store.register(get_types_from_msg(text.decode(), name))
    with Writer2(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for cid, (sid, topic, _enc) in scan.channels.items():
            name, _enc2, text = scan.schemas[sid]
            conns[cid] = writer.add_connection(topic, name, msgdef=text.decode(),
                                               rihs01=store.hash_rihs01(name))
        count = 0
        for cid, t_ns, payload in scan.messages:
            if cid in conns:
                writer.write(conns[cid], t_ns, payload)
                count += 1
    return RecoveryResult(out, count, False)


# --- ROS 1 ------------------------------------------------------------------------------------


@dataclass
class Ros1Scan:
    """Connections and messages found in a ROS 1 bag, up to the first truncated record."""

    connections: dict[int, dict[str, bytes]]            # id -> connection header fields
    messages: list[tuple[int, int, bytes]]              # (connection id, time ns, data)
    indexed: bool                                        # the bag header points at an index


def scan_ros1(data: bytes) -> Ros1Scan:
    """Every connection and message in the chunks of ``data`` up to the first truncated record."""
    if not data.startswith(ROS1_MAGIC):
        raise BagError("not a ROS 1 bag (bad magic)")
    scan = Ros1Scan({}, [], False)
    for fields, body in _ros1_records(data, len(ROS1_MAGIC)):
        op = fields.get("op", b"\x00")[0]
        if op == 0x03:
            scan.indexed = _U64.unpack(fields["index_pos"])[0] != 0
        elif op == 0x05:
            compression = fields["compression"].decode()
            if compression == "bz2":
                body = bz2.decompress(body)
            elif compression != "none":  # lz4: the recorder never writes it
                raise BagError(f"unknown ROS 1 chunk compression {compression!r}")
            for inner, inner_body in _ros1_records(body, 0):
                _ros1_record(inner, inner_body, scan)
        else:
            _ros1_record(fields, body, scan)
    return scan


def _ros1_fields(header: bytes) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(header):
        (n,) = _U32.unpack_from(header, pos)
        name, _, value = header[pos + 4:pos + 4 + n].partition(b"=")
        fields[name.decode()] = value
        pos += 4 + n
    return fields


def _ros1_records(data: bytes, pos: int) -> Iterator[tuple[dict[str, bytes], bytes]]:
    end = len(data)
    while pos + 4 <= end:
        (hlen,) = _U32.unpack_from(data, pos)
        if pos + 8 + hlen > end:
            return
        header = data[pos + 4:pos + 4 + hlen]
        (dlen,) = _U32.unpack_from(data, pos + 4 + hlen)
        start = pos + 8 + hlen
        if start + dlen > end:
            return
        yield _ros1_fields(header), data[start:start + dlen]
        pos = start + dlen


def _ros1_record(fields: dict[str, bytes], body: bytes, scan: Ros1Scan) -> None:
    op = fields.get("op", b"\x00")[0]
    if op == 0x07:
        (cid,) = _U32.unpack(fields["conn"])
        scan.connections.setdefault(cid, _ros1_fields(body))
    elif op == 0x02:
        (cid,) = _U32.unpack(fields["conn"])
        sec, nsec = struct.unpack("<II", fields["time"])
        scan.messages.append((cid, sec * 1_000_000_000 + nsec, body))


def _ros2_name(ros1_type: str) -> str:
    pkg, _, name = ros1_type.partition("/")
    return f"{pkg}/msg/{name}"


def _recover_ros1(file: Path, out: Path) -> RecoveryResult:
    scan = scan_ros1(file.read_bytes())
    if scan.indexed:
        return RecoveryResult(file, len(scan.messages), True)
    with Writer1(out) as writer:
        conns = {}
        for cid, f in scan.connections.items():
            latching = f.get("latching")
            conns[cid] = writer.add_connection(
                f["topic"].decode(), _ros2_name(f["type"].decode()),
                msgdef=f["message_definition"].decode(), md5sum=f["md5sum"].decode(),
                callerid=f["callerid"].decode() if "callerid" in f else None,
                latching=int(latching) if latching else None)
        count = 0
        for cid, t_ns, payload in scan.messages:
            if cid in conns:
                writer.write(conns[cid], t_ns, payload)
                count += 1
    return RecoveryResult(out, count, False)


# --- sqlite3 ----------------------------------------------------------------------------------


def _recover_sqlite3(bagdir: Path, db: Path) -> RecoveryResult:
    con = sqlite3.connect(db)  # opening read-write rolls back a hot journal
    try:
        topics = con.execute("SELECT id, name, type, serialization_format, offered_qos_profiles,"
                             " type_description_hash FROM topics ORDER BY id").fetchall()
        counts = dict(con.execute("SELECT topic_id, count(*) FROM messages GROUP BY topic_id"))
        lo, hi = con.execute("SELECT min(timestamp), max(timestamp) FROM messages").fetchone()
    finally:
        con.close()
    total = sum(counts.values())
    start = lo or 0
    duration = (hi - lo) if total else 0
    info = {
        "version": 9, "storage_identifier": "sqlite3", "relative_file_paths": [db.name],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start}, "message_count": total,
        "topics_with_message_count": [
            {"topic_metadata": {"name": name, "type": typ, "serialization_format": fmt,
                                "offered_qos_profiles": yaml.safe_load(qos) if qos else [],
                                "type_description_hash": digest},
             "message_count": counts.get(tid, 0)}
            for tid, name, typ, fmt, qos, digest in topics
        ],
        "compression_format": "", "compression_mode": "",
        "files": [{"path": db.name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": total}],
        "custom_data": {"racecar_hw": "recovered"}, "ros_distro": "rosbags",
    }
    meta = bagdir / "metadata.yaml"
    tmp = meta.with_suffix(".yaml.tmp")
    tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False), "utf8")
    tmp.replace(meta)
    return RecoveryResult(bagdir, total, False)


# --- entry point ------------------------------------------------------------------------------


@guarded
def recover_bag(path: str | Path, out: str | Path | None = None) -> RecoveryResult:
    """Make the bag at ``path`` readable after an interrupted recording; a bag too damaged for that
    gives a :class:`BagError` naming it and the cause, and nothing else.

    MCAP and ROS 1 bags are rewritten to ``out`` (default: ``<name>.recovered`` next to it for a
    ROS 2 directory, ``<stem>.recovered.bag`` for ROS 1); sqlite3 bags are fixed in place. A bag
    that was closed normally is left alone (``was_complete``).
    """
    src = Path(path)
    if not src.exists():
        raise BagError(f"bag not found: {src}")
    if src.is_file():
        if src.stat().st_size == 0:
            raise BagError(f"{src} is empty (0 bytes): nothing was flushed before the recording ended")
        target = Path(out) if out else src.with_name(f"{src.stem}.recovered.bag")
        return _recover_ros1(src, target)
    mcaps = sorted(src.glob("*.mcap"))
    dbs = sorted(src.glob("*.db3"))
    if len(mcaps) == 1:
        if mcaps[0].stat().st_size == 0:
            raise BagError(f"{mcaps[0]} is empty (0 bytes): nothing was flushed before the end")
        return _recover_mcap(src, mcaps[0], Path(out) if out else src.with_name(f"{src.name}.recovered"))
    if len(dbs) == 1:
        return _recover_sqlite3(src, dbs[0])
    raise BagError(f"{src} holds no single .mcap or .db3 file to recover")
