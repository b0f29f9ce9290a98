"""racecar_hw.bags.record: round trips through every format, read back by independent readers (the real
rosbag, the mcap packages), drops, splitting, and recovery after SIGKILL."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from bag_ros1tools import append_with_real_rosbag, read_real_bag, rosbag_cli
from conftest import StuckDisk, wait_for
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, QosDurability, QosReliability
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from mux.params import MuxParams
from racecar_hw.bags.follow import load_commands, summarize_bag
from racecar_hw.bags.record import BagFile, Recorder, RecorderParams, offered_qos, record_params
from racecar_hw.bags.recover import inspect_bag, recover_bag, scan_mcap
from racecar_hw.bags.validate import mcap_chunk_crc_error
from racecar_hw.bags.writers import MCAP_CHUNK_CRC_OFFSET, ROS1_FILE_HEADER_RECORD, ROS2_METADATA_VERSION
from racecar_hw.base.bus import Bus
from racecar_hw.base.clock import wall_ns
from racecar_hw.base.errors import BagError, ConfigError
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Header,
    LaserScan,
    Log,
    MapMetaData,
    Message,
    OccupancyGrid,
    String,
    TFMessage,
    Time,
    TransformStamped,
)
from racecar_hw.base.topics import MUX_ACTIVE_TOPIC
from racecar_hw.net.topics import topic_table
from racecar_hw.rosmsg.typestore import ros2_types, types_for
from racecar_hw.sim.live import MAP_TOPIC, SIM_TOPICS
from safety.params import SafetyParams

CMD = "/vesc/low_level/ackermann_cmd_mux/input/teleop"
ROOT = Path(__file__).resolve().parents[1]


def static_tf() -> TFMessage:
    return TFMessage([TransformStamped(Header(Time(5, 0), "base_link"), "laser")])


def scan(i: int) -> LaserScan:
    return LaserScan(Header(Time(100 + i, 0), "laser"), -2.35, 2.35, 0.00436, 0.0, 0.025, 0.02,
                     30.0, np.full(1081, 1.0 + i, np.float32), np.zeros(0, np.float32))


def cmd(i: int) -> AckermannDriveStamped:
    return AckermannDriveStamped(Header(Time(200 + i, 7), "base_link"),
                                 AckermannDrive(steering_angle=0.25 * (i % 4) - 0.5, speed=0.5 * i))


def record(tmp_path: Path, n: int = 20, **kw: object) -> Recorder:
    bus = Bus()
    bus.publish("/tf_static", static_tf())  # published before the recording starts (latched)
    rec = Recorder(bus, record_params(tmp_path, name="run", **kw))  # type: ignore[arg-type]
    rec.start()
    for i in range(n):
        bus.publish("/scan", scan(i))
        bus.publish(CMD, cmd(i))
        bus.publish("/ignored", cmd(i))
    rec.stop()
    return rec


def read_ours(paths: list[Path]) -> dict[str, list[object]]:
    types = ros2_types()
    out: dict[str, list[object]] = {}
    with AnyReader(paths) as reader:
        for conn, _t, raw in reader.messages():
            obj = reader.deserialize(raw, conn.msgtype)
            out.setdefault(conn.topic, []).append(types.from_ros(obj))
    return out


@pytest.mark.parametrize(("fmt", "compression"),
                         [("mcap", "none"), ("mcap", "zstd"), ("sqlite3", "none"), ("ros1", "none"),
                          ("ros1", "bz2")])
def test_round_trip(tmp_path: Path, fmt: str, compression: str) -> None:
    rec = record(tmp_path, fmt=fmt, compression=compression, exclude=["/ign*"])
    stats = rec.stats
    assert stats.written == 41 and stats.dropped == 0 and stats.flushed == 41
    assert len(stats.files) == 1 and stats.bytes > 20 * 1081 * 4
    got = read_ours(stats.files)
    assert sorted(got) == ["/scan", "/tf_static", CMD]
    assert got["/tf_static"] == [static_tf()]
    assert got[CMD] == [cmd(i) for i in range(20)]
    for i, s in enumerate(got["/scan"]):
        assert isinstance(s, LaserScan)
        np.testing.assert_array_equal(s.ranges, scan(i).ranges)
        assert s.header == scan(i).header
    assert [c.drive.speed for c in load_commands(stats.files[0], CMD)] == [0.5 * i for i in range(20)]
    if fmt == "mcap":  # zstd: the chunks are (the setting once reached no MCAP file), CRCs and all
        from mcap.reader import make_reader

        (mcap,) = stats.files[0].glob("*.mcap")
        with mcap.open("rb") as fh:
            summary = make_reader(fh, validate_crcs=True).get_summary()
        assert summary is not None
        assert {c.compression or "none" for c in summary.chunk_indexes} == {compression}
        assert inspect_bag(stats.files[0]).complete


@pytest.mark.parametrize("compression", ["none", "bz2"])
def test_real_rosbag_reads_our_ros1_bags(tmp_path: Path, compression: str) -> None:
    rec = record(tmp_path, n=5, fmt="ros1", compression=compression, topics=[CMD, "/tf_static"])
    msgs = read_real_bag(rec.stats.files[0])
    cmds = [m for m in msgs if m["topic"] == CMD]
    assert [m["type"] for m in cmds] == ["ackermann_msgs/AckermannDriveStamped"] * 5
    assert cmds[0]["md5"] == "1fd5d7f58889cefd44d29f6653240d0c"
    for i, m in enumerate(cmds):
        assert m["msg"]["header"]["seq"] == i + 1
        assert m["msg"]["header"]["stamp"] == (200 + i) * 10**9 + 7
        assert m["msg"]["header"]["frame_id"] == "base_link"
        assert m["msg"]["drive"]["speed"] == pytest.approx(0.5 * i)
        assert m["msg"]["drive"]["steering_angle"] == 0.25 * (i % 4) - 0.5
    tf = [m for m in msgs if m["topic"] == "/tf_static"]
    assert tf[0]["type"] == "tf2_msgs/TFMessage"
    assert tf[0]["msg"]["transforms"][0]["child_frame_id"] == "laser"


def test_mcap_packages_read_our_mcap(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    rec = record(tmp_path, n=5, fmt="mcap", topics=["/scan", CMD])
    (file,) = rec.stats.files[0].glob("*.mcap")
    with file.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        decoded = [(ch.topic, sc.name, m) for sc, ch, _msg, m in reader.iter_decoded_messages()]
    cmds = [m for topic, _name, m in decoded if topic == CMD]
    assert [c.drive.speed for c in cmds] == pytest.approx([0.5 * i for i in range(5)])
    assert [c.header.stamp.sec for c in cmds] == [200 + i for i in range(5)]
    scans = [m for topic, name, m in decoded if topic == "/scan"]
    assert {name for topic, name, _ in decoded if topic == "/scan"} == {"sensor_msgs/msg/LaserScan"}
    assert list(scans[3].ranges) == [4.0] * 1081


def test_a_listed_topic_that_nothing_published_is_warned_of_at_stop(tmp_path: Path, caplog) -> None:
    """``recorder.topics: [/scna]`` (a typo) recorded nothing and said so only at info level."""
    import logging

    with caplog.at_level(logging.WARNING, logger="racecar_hw.bags.record"):
        record(tmp_path, n=3, topics=["/scna", "/sc*", CMD, "/nope/*"])
    warned = [r.getMessage() for r in caplog.records if "recorder.topics" in r.getMessage()]
    assert len(warned) == 2, warned
    assert warned[0].startswith("recorder.topics: nothing was published on '/scna' while recording")
    assert "'/nope/*'" in warned[1] and "/scan" in warned[1]  # what was published, to compare


def test_a_sqlite3_bag_keeps_its_metadata_mapping_as_rosbag2_reads_it(tmp_path: Path) -> None:
    """rosbag2's sqlite3 plugin (Jazzy on) decodes the ``metadata`` table's text as a BagMetadata
    when it opens the file: the ``rosbag2_bagfile_information`` mapping itself, not the whole
    metadata.yaml document (with it, the bag failed to open: "invalid node; first invalid key")."""
    import sqlite3

    rec = record(tmp_path, n=3, fmt="sqlite3")
    bag = rec.stats.files[0]
    (db,) = bag.glob("*.db3")
    with sqlite3.connect(db) as conn:
        ((version, text),) = conn.execute("SELECT metadata_version, metadata FROM metadata").fetchall()
    stored = yaml.safe_load(text)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert version == stored["version"] and stored == meta


def test_lz4_and_bad_compression_refused() -> None:
    with pytest.raises(ConfigError, match="real rosbag .* cannot read the LZ4 chunks"):
        RecorderParams(format="ros1", compression="lz4")
    with pytest.raises(ConfigError, match="bz2 is not offered for format 'mcap': use 'zstd' or 'none'"):
        RecorderParams(format="mcap", compression="bz2")
    with pytest.raises(ConfigError, match="lz4 is not offered for format 'mcap': use 'zstd' or 'none'"):
        RecorderParams(format="mcap", compression="lz4")  # (it once said "for ROS 1 bags")
    with pytest.raises(ConfigError, match="zstd is not offered for format 'ros1': use 'bz2' or 'none'"):
        RecorderParams(format="ros1", compression="zstd")
    with pytest.raises(ConfigError, match="zstd is not offered for format 'sqlite3': use 'none'"):
        RecorderParams(format="sqlite3", compression="zstd")


def test_disabled_recorder_records_nothing(tmp_path: Path) -> None:
    bus = Bus()
    rec = Recorder(bus, RecorderParams(path=str(tmp_path / "never")))
    rec.start()
    bus.publish(CMD, cmd(0))
    assert rec.stop().written == 0 and not (tmp_path / "never").exists()


def test_existing_bag_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "run").mkdir()
    rec = Recorder(Bus(), record_params(tmp_path, name="run"))
    with pytest.raises(BagError, match="exists already"):
        rec.start()
    rec.stop()  # safe after a failed start


def test_drops_are_counted_when_the_queue_is_full(tmp_path: Path) -> None:
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name="slow", queue_size=2, topics=["/scan"]))
    rec.start()
    big = [scan(i) for i in range(400)]
    for s in big:  # serializing a 1081-beam scan is far slower than queueing it
        bus.publish("/scan", s)
    stats = rec.stop()
    assert stats.dropped > 0
    assert stats.written + stats.dropped == 400
    assert summarize_bag(stats.files[0])["/scan"][1] == stats.written
    assert rec.stop() == stats  # stop twice is safe


def test_split_by_size(tmp_path: Path) -> None:
    rec = record(tmp_path, n=60, fmt="ros1", split_size_mb=0.05, topics=["/scan", "/tf_static"])
    files = rec.stats.files
    assert len(files) >= 4
    per_file = [read_ours([f]) for f in files]
    assert all(p["/tf_static"] == [static_tf()] for p in per_file)  # each split is self-contained
    assert sum(len(p["/scan"]) for p in per_file) == 60
    assert all(f.stat().st_size < 0.05e6 + 20_000 for f in files[:-1]), [f.stat().st_size for f in files]
    # the header seq goes on across the splits, as rosbag record --split writes it (it started
    # again at 1 in each split)
    with AnyReader(files) as reader:
        seqs = [reader.deserialize(raw, conn.msgtype).header.seq
                for conn, _t, raw in reader.messages() if conn.topic == "/scan"]
    assert seqs == list(range(1, 61))


def occupancy_grid() -> OccupancyGrid:
    return OccupancyGrid(Header(Time(3, 0), "map"), MapMetaData(Time(3, 0), 0.05, 10, 10),
                         np.arange(100, dtype=np.int8))


def split_topics(f: Path) -> list[str]:
    """The topics of one split's messages, in file order (ROS 1 .bag, ROS 2 .mcap or .db3)."""
    if f.suffix == ".bag":
        with AnyReader([f]) as reader:
            return [conn.topic for conn, _t, _raw in reader.messages()]
    if f.suffix == ".mcap":
        from mcap.reader import make_reader

        with f.open("rb") as fh:
            return [channel.topic for _s, channel, _m in make_reader(fh).iter_messages(log_time_order=False)]
    import sqlite3

    with contextlib.closing(sqlite3.connect(f)) as db:
        return [row[0] for row in db.execute("SELECT topics.name FROM messages JOIN topics ON "
                                             "messages.topic_id = topics.id ORDER BY messages.id")]


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3", "ros1"])
def test_latched_topics_of_the_live_table_are_latched_in_the_bag_and_start_every_split(
        tmp_path: Path, fmt: str) -> None:
    live = {row.bus: row.qos for row in [*topic_table(MuxParams(), SafetyParams()), *SIM_TOPICS]}
    latched = [MAP_TOPIC, MUX_ACTIVE_TOPIC, "/tf_static"]
    assert all(live[t].latched for t in latched)  # what the live interfaces offer transient local
    bus = Bus()
    bus.publish("/tf_static", static_tf())  # all three published before the recording starts
    bus.publish(MAP_TOPIC, occupancy_grid())
    bus.publish(MUX_ACTIVE_TOPIC, String("teleop"))
    rec = Recorder(bus, record_params(tmp_path, fmt, name="latched", split_size_mb=0.05))
    rec.start()
    for i in range(60):
        bus.publish("/scan", scan(i))
        if i == 20:
            bus.publish(MUX_ACTIVE_TOPIC, String("nav_0"))
    stats = rec.stop()
    assert stats.dropped == 0
    if fmt == "ros1":
        splits = stats.files
    else:
        (bag,) = stats.files
        meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        splits = [bag / name for name in meta["relative_file_paths"]]
    assert len(splits) >= 3
    for f in splits:  # each split alone has every latched topic, before its first scan
        topics = split_topics(f)
        first_scan = topics.index("/scan")
        assert all(t in topics[:first_scan + 1] for t in latched), (f.name, topics[:5])
    with AnyReader(stats.files) as reader:
        conns = {c.topic: c for c in reader.connections}
        active = [reader.deserialize(raw, c.msgtype).data for c, _t, raw in reader.messages()
                  if c.topic == MUX_ACTIVE_TOPIC]
    # the latest value starts each split: teleop until it changed, nav_0 after
    changed = active.index("nav_0")
    assert active[0] == "teleop" and set(active[changed:]) == {"nav_0"}
    if fmt == "ros1":  # every split's connection header says latching=1, as rosbag record writes it
        for f in splits:
            with AnyReader([f]) as reader:
                got = {c.topic: c.ext.latching for c in reader.connections}
            assert got == {**dict.fromkeys(latched, 1), "/scan": None}, f.name
        return
    # ROS 2: transient local (durability 1) in metadata.yaml, in the reader's view ...
    offered = {t["topic_metadata"]["name"]: yaml.safe_load(t["topic_metadata"]["offered_qos_profiles"])
               for t in meta["topics_with_message_count"]}
    assert {t: [p["durability"] for p in offered[t]] for t in latched} == dict.fromkeys(latched, [1])
    assert all(conns[t].ext.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL
               for t in latched)
    if fmt == "mcap":  # ... and in every split's MCAP channel metadata
        for f in splits:
            scanned = scan_mcap(f.read_bytes())
            by_topic = {topic: scanned.qos[cid] for cid, (_sid, topic, _enc) in scanned.channels.items()}
            assert all(yaml.safe_load(by_topic[t])[0]["durability"] == 1 for t in latched), f.name


def test_the_recorder_takes_latched_topics_renamed_in_the_live_table(tmp_path: Path) -> None:
    bus = Bus()
    bus.publish("/mux/active", String("teleop"))
    rows = topic_table(MuxParams(active_topic="/mux/active"), SafetyParams())
    rec = Recorder(bus, record_params(tmp_path, "ros1", name="renamed"),
                   latched={row.bus: row.qos for row in rows if row.qos.latched})
    rec.start()
    stats = rec.stop()
    with AnyReader(stats.files) as reader:
        assert {c.topic: c.ext.latching for c in reader.connections} == {"/mux/active": 1}


def test_rosout_is_offered_as_rcl_offers_it() -> None:
    (row,) = [row for row in topic_table(MuxParams(), SafetyParams(), rosout=True) if row.bus == "/rosout"]
    assert row.qos.latched and row.qos.depth == 1000
    (qos,) = offered_qos("/rosout", Log)
    assert (qos.depth, qos.durability, qos.reliability) == (1000, QosDurability.TRANSIENT_LOCAL,
                                                            QosReliability.RELIABLE)


def test_split_by_duration(tmp_path: Path) -> None:
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name="dur", split_duration_s=0.05))
    rec.start()
    start = wall_ns()
    for i in range(3):
        # bag time is the receive time: let more than one split duration pass between messages
        wait_for(lambda i=i: wall_ns() - start >= i * 80_000_000)
        bus.publish(CMD, cmd(i))
    stats = rec.stop()
    # one rosbag2 bag whose three files are the splits, as ros2 bag record --max-bag-duration makes
    (bag,) = stats.files
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["relative_file_paths"] == ["dur_0.mcap", "dur_1.mcap", "dur_2.mcap"]
    assert [f["message_count"] for f in info["files"]] == [1, 1, 1]
    assert info["message_count"] == 3 and info["custom_data"] == {"racecar_hw": "closed"}
    assert sorted(p.name for p in bag.iterdir()) == ["dur_0.mcap", "dur_1.mcap", "dur_2.mcap",
                                                     "metadata.yaml"]
    assert [c.drive.speed for c in load_commands(bag, CMD)] == [0.0, 0.5, 1.0]


KILLED_RECORDER = textwrap.dedent("""
    import sys, time
    from racecar_hw.base.bus import Bus
    from racecar_hw.bags.record import Recorder, record_params
    from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped
    bus = Bus()
    rec = Recorder(bus, record_params(sys.argv[1], sys.argv[2], name="killed", flush_interval_s=0.05))
    rec.start()
    # message i asks for i/1024 m/s: the index, exact in float32, and under the 100 m/s a bag reader
    # refuses as absurd for any count written before the kill
    for i in range(300):
        bus.publish("/cmd", AckermannDriveStamped(drive=AckermannDrive(speed=i / 1024)))
    while rec.stats.flushed < 300:
        time.sleep(0.01)
    print("FLUSHED", rec.stats.flushed, flush=True)
    i = 300
    while True:   # keep writing until killed
        bus.publish("/cmd", AckermannDriveStamped(drive=AckermannDrive(speed=i / 1024)))
        i += 1
        time.sleep(0.001)
""")


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3", "ros1"])
def test_sigkill_keeps_everything_flushed(tmp_path: Path, fmt: str) -> None:
    proc = subprocess.Popen([sys.executable, "-c", KILLED_RECORDER, str(tmp_path), fmt],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        assert line.startswith("FLUSHED 300"), line
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    bag = tmp_path / ("killed_0.bag" if fmt == "ros1" else "killed")
    if fmt == "sqlite3":  # readable as it is
        speeds = [c.drive.speed for c in load_commands(bag, "/cmd")]
        assert speeds[:300] == [i / 1024 for i in range(300)]
    else:
        with pytest.raises(BagError, match="racecar-hw bag recover"):
            load_commands(bag, "/cmd")
    if fmt == "mcap":
        scanned = scan_mcap(next(bag.glob("*.mcap")).read_bytes())
        assert not scanned.complete and scanned.tally.total >= 300
    assert not inspect_bag(bag).complete
    if fmt == "ros1":  # the real rosbag reindex repairs our interrupted bag as one of its own
        shutil.copy(bag, tmp_path / "reindexed.bag")
        assert rosbag_cli("reindex", tmp_path / "reindexed.bag").returncode == 0
        info = rosbag_cli("info", "--yaml", tmp_path / "reindexed.bag")
        assert info.returncode == 0, info.stderr
        real_count = yaml.safe_load(info.stdout)["messages"]
        assert real_count >= 300
        speeds = [c.drive.speed for c in load_commands(tmp_path / "reindexed.bag", "/cmd")]
        assert speeds == [i / 1024 for i in range(real_count)]
        assert inspect_bag(tmp_path / "reindexed.bag").complete
    result = recover_bag(bag)
    assert not result.was_complete and result.messages >= 300
    speeds = [c.drive.speed for c in load_commands(result.path, "/cmd")]
    assert len(speeds) == result.messages
    assert speeds == [i / 1024 for i in range(len(speeds))]
    assert inspect_bag(result.path).complete
    if fmt == "ros1":
        assert len(read_real_bag(result.path)) == result.messages


def test_real_rosbag_append_mode_and_fix_keep_our_ros1_bag_readable(tmp_path: Path) -> None:
    rec = record(tmp_path, n=5, fmt="ros1", topics=[CMD, "/tf_static"])
    (bag,) = rec.stats.files
    before = bag.read_bytes()
    append_with_real_rosbag(bag)  # rewrites the file header and the index in place
    after = bag.read_bytes()
    assert after[:ROS1_FILE_HEADER_RECORD + 13] == before[:ROS1_FILE_HEADER_RECORD + 13]
    assert len(read_real_bag(bag)) == 6
    assert [c.drive.speed for c in load_commands(bag, CMD)] == [0.5 * i for i in range(5)]
    assert inspect_bag(bag).complete
    # --force: this machine has no ackermann_msgs or tf2_msgs, so rosbag cannot look for
    # migration rules, as for any bag of those types (without it: "Bag could not be migrated")
    fixed = rosbag_cli("fix", "--force", bag, tmp_path / "fixed.bag")
    assert fixed.returncode == 0, fixed.stderr
    assert [c.drive.speed for c in load_commands(tmp_path / "fixed.bag", CMD)] == [0.5 * i for i in range(5)]


def test_a_header_rewritten_over_the_first_chunk_is_found_and_recovered(tmp_path: Path) -> None:
    """A bag with rosbags' 4096-byte header, opened in the real rosbag's append mode: its 4104-byte
    header overwrites the first chunk's length fields and the index no longer matches (the file
    racecar-hw wrote before its header had rosbag's layout). The index is not trusted; the chunk is
    found by its fields and every message comes back."""
    from rosbags.rosbag1 import Writer as PlainWriter1

    types = types_for(1)
    bag = tmp_path / "old.bag"
    with PlainWriter1(bag) as writer:
        conn = writer.add_connection(CMD, AckermannDriveStamped.ROS_TYPE, typestore=types.store)
        for i in range(5):
            writer.write(conn, 10**9 + i, types.serialize(cmd(i), i + 1))
    append_with_real_rosbag(bag)
    with pytest.raises(BagError):
        load_commands(bag, CMD)
    state = inspect_bag(bag)
    assert not state.complete and "damaged bytes at offset 4117" in state.problem
    result = recover_bag(bag)
    assert not result.was_complete and result.messages == 5
    assert [c.drive.speed for c in load_commands(result.path, CMD)] == [0.5 * i for i in range(5)]


def test_recover_leaves_complete_bags_alone(tmp_path: Path) -> None:
    rec = record(tmp_path, n=3, fmt="mcap", topics=[CMD])
    result = recover_bag(rec.stats.files[0])
    assert result.was_complete and result.messages == 3 and result.path == rec.stats.files[0]
    with pytest.raises(BagError, match="bag not found"):
        recover_bag(tmp_path / "nope")


def test_mcap_written_with_the_mcap_library_holds_what_rosbags_writes(tmp_path: Path) -> None:
    """The recorder's MCAP (the ``mcap`` library's writer) against rosbags' own rosbag2 writer fed
    the same messages: the same messages, schemas, channels and QoS metadata, read back by the
    ``mcap`` reader (CRCs checked) and by rosbags; rosbags' metadata.yaml but for custom_data;
    the ros2 profile, encodings and the ``rosbag2`` metadata record rosbag2 writes."""
    from mcap.reader import make_reader

    types = ros2_types()
    tf = TFMessage([TransformStamped(Header(Time(1, 2), "odom"), "base_link")])
    msgs: list[tuple[str, Message]] = []
    for i in range(160):  # 160 scans cross the 1 MiB chunk size
        msgs += [("/scan", scan(i)), (CMD, cmd(i)), ("/tf", tf)]
    (tmp_path / "ours").mkdir()
    (tmp_path / "ref").mkdir()
    ours = BagFile(tmp_path / "ours" / "bag" / "bag", "mcap", "none", types)
    ref = Writer2(tmp_path / "ref" / "bag", version=ROS2_METADATA_VERSION, storage_plugin=StoragePlugin.MCAP)
    ref.open()
    conns: dict[str, Connection] = {}
    for i, (topic, msg) in enumerate(msgs):
        t_ns = 1_000_000 + 1000 * i - (500 if i % 7 == 3 else 0)  # not always increasing
        ours.write(topic, msg, t_ns)
        if topic not in conns:
            conns[topic] = ref.add_connection(topic, msg.ROS_TYPE, typestore=types.store,
                                              offered_qos_profiles=offered_qos(topic, type(msg)))
        ref.write(conns[topic], t_ns, types.serialize_generic(msg))
        if i == 100:
            ours.flush()
    ours.close()
    ref.close()

    def content(path: Path, hashes: dict[str, str | None]) -> tuple[Any, ...]:
        with path.open("rb") as fh:
            reader = make_reader(fh, validate_crcs=True)
            header = reader.get_header()
            summary = reader.get_summary()
            assert summary is not None
            schemas = sorted((s.name, s.encoding, s.data) for s in summary.schemas.values())
            # (rosbags writes no topic_type_hash into a channel; rosbag2 does, checked below)
            hashes.update({c.topic: c.metadata.pop("topic_type_hash", None)
                           for c in summary.channels.values()})
            channels = sorted((c.topic, c.message_encoding, summary.schemas[c.schema_id].name,
                               tuple(sorted(c.metadata.items()))) for c in summary.channels.values())
            messages = [(c.topic, m.log_time, m.publish_time, m.data)
                        for _s, c, m in reader.iter_messages(log_time_order=False)]
            metadata = [(r.name, sorted(r.metadata)) for r in reader.iter_metadata()]
            records.extend(yaml.safe_load(r.metadata["serialized_metadata"]) for r in reader.iter_metadata())
            return header.profile, schemas, channels, sorted(messages), metadata, summary.statistics

    hashes: dict[str, str | None] = {}
    records: list[dict[str, Any]] = []
    mine = content(tmp_path / "ours" / "bag" / "bag.mcap", hashes)
    theirs = content(tmp_path / "ref" / "bag" / "bag.mcap", {})
    assert mine[:5] == theirs[:5]
    assert mine[0] == "ros2" and mine[4] == [("rosbag2", ["serialized_metadata"])]
    # the record holds the bag's metadata mapping itself, as rosbags' (and rosbag2's): with the
    # document's top key Jazzy's ros2 bag failed ("invalid node; first invalid key: version")
    ours_record, theirs_record = records
    assert "version" in ours_record and "rosbag2_bagfile_information" not in ours_record
    assert {k: v for k, v in ours_record.items() if k not in ("custom_data", "ros_distro")} == {
        k: v for k, v in theirs_record.items() if k not in ("custom_data", "ros_distro")}
    assert {enc for _n, enc, _d in mine[1]} == {"ros2msg"} and {c[1] for c in mine[2]} == {"cdr"}
    assert mine[5].message_count == len(msgs) and mine[5].chunk_count >= 2  # the flush
    with (tmp_path / "ours" / "bag" / "bag.mcap").open("rb") as fh:  # every chunk has its CRC-32
        summary = make_reader(fh).get_summary()
        assert summary is not None and summary.chunk_indexes
    mcap = (tmp_path / "ours" / "bag" / "bag.mcap").read_bytes()
    crc_at = [ci.chunk_start_offset + MCAP_CHUNK_CRC_OFFSET for ci in summary.chunk_indexes]
    assert all(mcap[at:at + 4] != bytes(4) for at in crc_at)
    assert mcap_chunk_crc_error(tmp_path / "ours" / "bag" / "bag.mcap") is None
    with AnyReader([tmp_path / "ours" / "bag"]) as reader:
        got = [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]
    assert sorted(got) == sorted((topic, t, d) for topic, t, _p, d in mine[3])
    meta = yaml.safe_load((tmp_path / "ours" / "bag" / "metadata.yaml").read_text())
    ref_meta = yaml.safe_load((tmp_path / "ref" / "bag" / "metadata.yaml").read_text())
    # rosbags' metadata for one file, but for custom_data (ours says the recording was closed)
    assert meta["rosbag2_bagfile_information"].pop("custom_data") == {"racecar_hw": "closed"}
    assert ref_meta["rosbag2_bagfile_information"].pop("custom_data") is None
    assert meta == ref_meta
    # each channel says its RIHS01 type hash, as rosbag2 writes it: metadata.yaml's
    listed = {t["topic_metadata"]["name"]: t["topic_metadata"]["type_description_hash"]
              for t in meta["rosbag2_bagfile_information"]["topics_with_message_count"]}
    assert {topic: hashes[topic] for topic in listed} == listed and all(listed.values())
    assert scan_mcap(mcap).complete


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3", "ros1"])
def test_a_message_the_serializer_refuses_is_dropped_and_counted_and_recording_goes_on(
        tmp_path: Path, fmt: str, caplog: pytest.LogCaptureFixture) -> None:
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, fmt, name="bad"))
    rec.start()
    bad = cmd(1)
    bad.header.stamp.sec = 1.5  # type: ignore[assignment]  # a float in an integer field
    bus.publish(CMD, cmd(0))
    bus.publish(CMD, bad)
    bus.publish(CMD, bad)
    bus.publish(CMD, cmd(2))
    stats = rec.stop()
    assert (stats.written, stats.dropped, stats.error) == (2, 2, None)
    assert [c.drive.speed for c in load_commands(stats.files[0], CMD)] == [0.0, 1.0]
    assert inspect_bag(stats.files[0]).complete
    said = [r.getMessage() for r in caplog.records if "cannot be serialized" in r.getMessage()]
    assert len(said) == 1 and "AckermannDriveStamped" in said[0] and CMD in said[0]


def test_writer_drains_the_queue_on_its_own(tmp_path: Path) -> None:
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name="drain", flush_interval_s=3600.0))
    rec.start()
    bus.publish(CMD, cmd(1))  # one message: below the wake-up threshold, far from a flush
    wait_for(lambda: rec.stats.written == 1)
    assert rec.stats.queued == 0
    assert rec.stop().written == 1


def test_a_due_drain_waits_for_the_control_loop_to_be_idle(tmp_path: Path, monkeypatch) -> None:
    import racecar_hw.bags.record as bag_record

    monkeypatch.setattr(bag_record, "BATCH_S", 30.0)  # the writer's own wake-up is a minute away
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name="idle", flush_interval_s=3600.0))
    rec.start()
    wait_for(lambda: rec._outbox._drain_due < math.inf)  # noqa: SLF001 - the writer set its first due time
    bus.publish(CMD, cmd(1))
    rec.control_idle()  # not due yet: the message waits for its batch
    assert rec.stats.written == 0 and rec.stats.queued == 1
    rec._outbox._drain_due = 0.0  # noqa: SLF001 - as if BATCH_S had passed
    rec.control_idle()
    wait_for(lambda: rec.stats.written == 1)
    assert rec.stop().written == 1


def test_qos_yaml_is_what_rosbags_writes() -> None:
    """Our offered_qos_profiles text (written without importing rosbags.rosbag2) is rosbags' own."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2.metadata import dump_qos_v8 as rosbags_dump

    from racecar_hw.bags.qos import dump_qos_v8

    odd = Qos(QosHistory.KEEP_ALL, 0, QosReliability.SYSTEM_DEFAULT, QosDurability.UNKNOWN,
              QosTime(2**31 - 1, 999_999_999), QosTime(1, 2), QosLiveliness.MANUAL_BY_TOPIC,
              QosTime(3, 4), True)
    profiles = [offered_qos(topic, type(msg)) for topic, msg in (("/tf_static", static_tf()), (CMD, cmd(1)))]
    for qos in [[], *profiles, [odd], [*profiles[0], odd, *profiles[1]]]:
        assert dump_qos_v8(qos) == rosbags_dump(qos)
    assert dump_qos_v8([]) == ""


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3"])
def test_metadata_template_gives_the_yaml_of_a_full_dump(tmp_path: Path, fmt: str) -> None:
    bag = BagFile(tmp_path / "meta" / "meta_0", fmt, "none", ros2_types())
    meta = bag.meta
    assert meta is not None

    def full_dump(current: BagFile | None) -> str:
        info = meta.info(meta.file_names(current), meta.numbers(current))
        return yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)

    assert meta.text(bag) == full_dump(bag)  # no topics yet
    topics = ["/tf_static", CMD, "/scan", "/odd: topic #1", "/ünïcode"]
    for i in range(40):
        if i == 30:  # a split: the second file of the same bag
            bag.close(last=False)
            assert meta.text(None) == full_dump(None)
            bag = BagFile(tmp_path / "meta" / "meta_1", fmt, "none", ros2_types(), meta)
        topic = topics[i % len(topics)] if i < 25 else CMD
        msg: Message = static_tf() if topic == "/tf_static" else cmd(i)
        bag.write(topic, msg, 10**18 + 7 * i)
        assert meta.text(bag) == full_dump(bag)
    bag.flush()
    assert (tmp_path / "meta" / "metadata.yaml").read_text() == full_dump(bag)
    bag.close()
    info = yaml.safe_load((tmp_path / "meta" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert [f["message_count"] for f in info["files"]] == [30, 10]
    assert info["message_count"] == 40 and info["duration"]["nanoseconds"] == 7 * 39
    assert summarize_bag(tmp_path / "meta")[CMD][1] == 5 + 5 + 10


# rosbag2 on the humble branch, rosbag2_storage/src/rosbag2_storage/metadata_io.cpp, decodes
# metadata.yaml as below (convert<BagMetadata>::decode and friends), whatever its version: no
# upper bound, fields read by version (>= 3 compression, >= 4 offered_qos_profiles *as a string*,
# >= 5 files); unknown keys are ignored. Version 9 writes offered_qos_profiles as a YAML sequence,
# on which Humble's as<std::string>() fails ("yaml-cpp: bad conversion"). Each profile in that
# string is then read by rosbag2_transport/src/rosbag2_transport/qos.cpp (humble): integer
# policies, {sec, nsec} durations, a bool.
def _humble_uint(node: object) -> int:
    assert isinstance(node, int) and not isinstance(node, bool) and node >= 0, node
    return node


def _humble_string(node: object) -> str:
    assert isinstance(node, str), f"yaml-cpp: bad conversion ({node!r} is not a scalar string)"
    return node


def _humble_qos(text: str) -> None:
    for profile in yaml.safe_load(text) or []:
        for key in ("history", "depth", "reliability", "durability", "liveliness"):
            assert isinstance(profile[key], int) and not isinstance(profile[key], bool), (key, profile)
        for key in ("deadline", "lifespan", "liveliness_lease_duration"):
            _humble_uint(profile[key]["sec"])
            _humble_uint(profile[key]["nsec"])
        assert isinstance(profile["avoid_ros_namespace_conventions"], bool)


def humble_reads(meta_text: str) -> dict[str, Any]:
    """metadata.yaml as rosbag2 Humble's MetadataIo::read_metadata decodes it (see above)."""
    node = yaml.safe_load(meta_text)["rosbag2_bagfile_information"]
    version = node["version"]
    assert isinstance(version, int)
    _humble_string(node["storage_identifier"])
    _humble_uint(node["duration"]["nanoseconds"])
    _humble_uint(node["starting_time"]["nanoseconds_since_epoch"])
    _humble_uint(node["message_count"])
    for topic in node["topics_with_message_count"]:
        meta = topic["topic_metadata"]
        for key in ("name", "type", "serialization_format"):
            _humble_string(meta[key])
        if version >= 4:
            _humble_qos(_humble_string(meta["offered_qos_profiles"]))
        _humble_uint(topic["message_count"])
    assert all(isinstance(p, str) for p in node["relative_file_paths"])
    if version >= 3:
        _humble_string(node["compression_format"])
        _humble_string(node["compression_mode"])
    if version >= 5:
        for f in node["files"]:
            _humble_string(f["path"])
            _humble_uint(f["starting_time"]["nanoseconds_since_epoch"])
            _humble_uint(f["duration"]["nanoseconds"])
            _humble_uint(f["message_count"])
    return node


@pytest.mark.parametrize("fmt", ["mcap", "sqlite3"])
def test_metadata_is_what_rosbag2_humble_reads(tmp_path: Path, fmt: str) -> None:
    rec = record(tmp_path, n=3, fmt=fmt, split_size_mb=0.005)  # a split: two files of one bag
    (bag,) = rec.stats.files
    info = humble_reads((bag / "metadata.yaml").read_text())
    assert info["version"] == ROS2_METADATA_VERSION == 8
    assert len(info["relative_file_paths"]) >= 2
    qos = {t["topic_metadata"]["name"]: yaml.safe_load(t["topic_metadata"]["offered_qos_profiles"])
           for t in info["topics_with_message_count"]}
    # /scan with rclcpp's SensorDataQoS (keep last 5, best effort = 2, volatile = 2), /tf_static
    # latched (transient local = 1), the rest the default profile
    assert [(p["depth"], p["reliability"], p["durability"]) for p in qos["/scan"]] == [(5, 2, 2)]
    assert [p["durability"] for p in qos["/tf_static"]] == [1]
    assert qos[CMD] is None
    with pytest.raises(AssertionError, match="bad conversion"):  # what Humble says of version 9
        humble_reads(yaml.safe_dump({"rosbag2_bagfile_information": dict(
            info, version=9, topics_with_message_count=[{"topic_metadata": dict(
                name="/scan", type="sensor_msgs/msg/LaserScan", serialization_format="cdr",
                offered_qos_profiles=qos["/scan"]), "message_count": 1}])}))
    if fmt == "mcap":  # the storage's own copy of each channel's QoS, read by Humble's MCAP plugin
        scanned = scan_mcap((bag / info["relative_file_paths"][0]).read_bytes())
        channels = {topic: cid for cid, (_sid, topic, _enc) in scanned.channels.items()}
        _humble_qos(scanned.qos[channels["/scan"]])


def test_a_write_failure_mid_run_is_said_at_the_end_not_as_a_writer_behind(tmp_path):
    """The file-size limit (as a full disk) stops recording: the log says so when it happens and
    again as the run ends, with the counts; it once repeated "bag writer is behind" every second
    and ended silently, the bag listed as if complete."""
    import re
    import resource

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))  # Python ignores SIGXFSZ

    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "sim", "--scenario", "wall", "--speed",
                           "max", "--duration", "4", "--no-status", "--out", str(tmp_path / "out"),
                           "--record", str(tmp_path / "bags")],
                          capture_output=True, text=True, preexec_fn=limit, timeout=180)
    # the car drove on and every other output is written, but a recording asked for and cut short
    # is not a success: exit 1, said by the command (it exited 0, only the log saying so)
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "bag writing failed, recording stops" in proc.stderr and "File too large" in proc.stderr
    assert re.search(r"recording stopped early \(OSError: .*File too large\): \d+ messages on disk, "
                     r"\d+ dropped", proc.stderr), proc.stderr[-3000:]
    assert "bag writer is behind" not in proc.stderr
    assert re.search(r"^racecar-hw sim: the recording failed: OSError: \[Errno 27\] File too large "
                     r"\(\d+ messages on disk, \d+ dropped; racecar-hw bag recover reads them\)$",
                     proc.stderr, re.MULTILINE), proc.stderr[-3000:]
    report = json.loads((tmp_path / "out" / "wall.json").read_text())
    assert report["recording_error"] == "OSError: [Errno 27] File too large", report["recording_error"]
    assert Path(report["trajectory_csv"]).stat().st_size > 0 and Path(report["plot_png"]).is_file()
    assert "wall: ran" in proc.stdout and f"bag:        {tmp_path / 'bags'}" in proc.stdout


def _fill_disk_under(file: Path) -> None:
    """Put /dev/full under this process's open descriptor of ``file``: the disk takes nothing more."""
    fds = [int(fd.name) for fd in Path("/proc/self/fd").iterdir()
           if fd.is_symlink() and os.readlink(fd) == str(file)]
    assert len(fds) == 1, fds
    full = os.open("/dev/full", os.O_WRONLY)
    try:
        os.dup2(full, fds[0])
    finally:
        os.close(full)


def test_a_bag_aborted_on_a_full_disk_is_one_log_line_not_a_traceback(tmp_path, caplog):
    """After a write error the recorder aborts the bag, and closing its file tries to write the
    buffered bytes again: on a disk that still takes nothing that raised again, and the log showed
    a traceback of it (seen in 4 of 6 ``run`` recordings cut by a file-size limit). The disk here is
    /dev/full put under the open bag's file."""
    path = tmp_path / "run" / "run_0"
    bag = BagFile(path, "mcap", "none", types_for(2))
    for i in range(50):
        bag.write("/scan", LaserScan(Header(Time(1, 0), "laser"), ranges=[1.0] * 360), i * 25_000_000)
    _fill_disk_under(path.with_suffix(".mcap"))
    with pytest.raises(OSError):
        bag.flush()
    caplog.set_level(logging.WARNING, logger="racecar_hw.bags.record")
    bag.abort()
    assert [(r.levelname, r.exc_info) for r in caplog.records] == [("WARNING", None)], caplog.text
    assert "closed with its last buffered bytes unwritten" in caplog.text


@pytest.mark.parametrize("name", ["../escape", "a/b", "..", ".", "/abs"])
def test_a_name_that_is_a_path_is_a_config_error(tmp_path: Path, name: str) -> None:
    """recorder.name is a name inside recorder.path: ``../escape`` once put a ROS 2 bag's files
    beside the folder and replaced the metadata.yaml of the folder's parent."""
    with pytest.raises(ConfigError, match=r"^name: .* is not a plain name"):
        record_params(tmp_path / "bags", name=name)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_any_existing_ros1_split_of_the_name_is_refused_at_start(tmp_path: Path) -> None:
    """A later split's file (``x_1.bag``) in the folder once ended the recording when the split
    opened (0.4 s in, thousands of messages dropped); now the start refuses, as for ``x_0.bag``."""
    (tmp_path / "x_1.bag").write_bytes(b"precious")
    (tmp_path / "x_extra.bag").write_bytes(b"not a split of x")
    rec = Recorder(Bus(), record_params(tmp_path, "ros1", name="x", split_size_mb=0.5))
    with pytest.raises(BagError, match=r"x_1\.bag exists already.*recorder\.name"):
        rec.start()
    rec.stop()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x_1.bag", "x_extra.bag"]
    assert (tmp_path / "x_1.bag").read_bytes() == b"precious"


def _ten_flushed(tmp_path: Path, name: str) -> tuple[Bus, Recorder]:
    """A recorder of the drive topic (bag ``name``) that has written and flushed ten commands."""
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name=name, topics=[CMD], flush_interval_s=0.05))
    rec.start()
    for i in range(10):
        bus.publish(CMD, cmd(i))
    wait_for(lambda: rec.stats.flushed == 10, timeout=30)
    return bus, rec


def test_after_a_write_failure_written_is_what_is_on_disk_and_the_rest_is_dropped(tmp_path: Path) -> None:
    """A failed flush loses what was written since the last one: "written" once counted those too
    (an MCAP bag reported 2204 messages written and held none), and they were counted nowhere."""
    bus, rec = _ten_flushed(tmp_path, "full")
    _fill_disk_under(tmp_path / "full" / "full_0.mcap")
    for i in range(10, 25):
        bus.publish(CMD, cmd(i))
    wait_for(lambda: rec.stats.error is not None, timeout=30)
    stats = rec.stop()
    assert stats.error is not None  # ENOSPC, or EINVAL from fsync when nothing was pending
    assert (stats.written, stats.flushed, stats.dropped) == (10, 10, 15)
    result = recover_bag(stats.files[0], tmp_path / "recovered")
    assert result.messages == 10


def test_a_writer_left_behind_on_a_stuck_disk_is_a_failed_recording(
        tmp_path: Path, stuck_disk: StuckDisk, monkeypatch: pytest.MonkeyPatch) -> None:
    """stop() leaves a writer stuck in fsync behind (after WRITER_STALL_S): that recording was
    once reported as a success (no error, so exit 0) with "0 dropped", its queue silently lost."""
    import racecar_hw.bags.record as bag_record

    monkeypatch.setattr(bag_record, "WRITER_STALL_S", 0.5)
    bus, rec = _ten_flushed(tmp_path, "stuck")
    stuck_disk.stick()
    for i in range(10, 20):
        bus.publish(CMD, cmd(i))
    assert stuck_disk.blocked.wait(30)  # the writer waits in a flush's fsync
    for i in range(20, 25):
        bus.publish(CMD, cmd(i))  # queued behind it
    stats = rec.stop()
    assert stats.error == (f"the bag writer did not finish within 0.5 s (a stuck disk?): "
                           f"{tmp_path / 'stuck'} is incomplete"), stats.error
    assert (stats.written, stats.flushed, stats.dropped) == (10, 10, 15)


def test_a_full_queue_behind_a_stuck_writer_is_said_while_it_is_stuck(
        tmp_path: Path, stuck_disk: StuckDisk, caplog: pytest.LogCaptureFixture) -> None:
    """The "bag writer is behind" warning came from the writer thread, after a flush: a writer
    stuck in fsync never said it. Now the bus side says it, at most once per flush interval."""
    bus = Bus()
    rec = Recorder(bus, record_params(tmp_path, name="behind", topics=[CMD], queue_size=4,
                                      flush_interval_s=0.05))
    rec.start()
    stuck_disk.stick()
    assert stuck_disk.blocked.wait(30)  # the writer waits in a (periodic) flush's fsync
    caplog.set_level(logging.WARNING, logger="racecar_hw.bags.record")
    for i in range(50):
        bus.publish(CMD, cmd(i))
    behind = [r.getMessage() for r in caplog.records if "bag writer is behind" in r.getMessage()]
    assert behind[:1] == ["bag writer is behind: dropped 1 messages so far (queue_size 4)"], caplog.text
    stuck_disk.released.set()
    stats = rec.stop()
    assert (stats.written, stats.dropped, stats.error) == (4, 46, None)
