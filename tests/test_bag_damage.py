"""Damaged bags never reach the motor: one BagError naming the file and the cause, bounded memory,
commands checked, and ``racecar-hw follow`` / ``sim --follow`` refusing before anything starts.

The real bad bags come from ../shared/fixtures/bags (skipped where absent); the damaged ones are
made here from valid Ackermann bags.
"""

from __future__ import annotations

import logging
import math
import random
import sqlite3
import struct
import subprocess
import sys
import time
import tracemalloc
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from fuzzing import TOPIC, write_bag

from racecar_hw.bags.follow import BagFollower, FollowerParams, load_commands
from racecar_hw.bags.recover import recover_bag
from racecar_hw.bags.validate import INFLATE_STEP, CommandLimits, check_storage, inflate, inflated_size
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import BagError
from racecar_hw.cli import main as cli_main
from vesc.fake import FakeVesc

T0 = 1_700_000_000 * 10**9
LIMITS = CommandLimits(5.0, 0.26)


def commands(n: int = 40, bad: dict[int, tuple[float, float]] | None = None,
             ) -> list[tuple[int, float, float]]:
    out = [(T0 + i * 50_000_000, 1.0 + 0.01 * i, 0.1) for i in range(n)]
    for i, (speed, steer) in (bad or {}).items():
        out[i] = (out[i][0], speed, steer)
    return out


def bag(tmp_path: Path, fmt: str, cmds: list[tuple[int, float, float]], name: str = "b") -> Path:
    return write_bag(tmp_path / (f"{name}.bag" if fmt == "ros1" else name), fmt, cmds)


def storage(path: Path) -> Path:
    return path if path.is_file() else next(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))


# --- commands are checked ----------------------------------------------------------------------


@pytest.mark.parametrize(("fmt", "bad", "says"), [
    ("ros1", {3: (math.nan, 0.1)}, "speed nan"),
    ("mcap", {7: (3e38, 0.0)}, "speed 3e+38 m/s, which no 1/10-scale car drives (over 100 m/s)"),
    ("sqlite3", {12: (1.0, -2.0)}, "steering -2 rad, which no wheel turns (over 1.571 rad)"),
    ("mcap", {0: (math.inf, 0.0)}, "speed inf"),
])
def test_an_absurd_command_refuses_the_bag_naming_its_index_and_time(tmp_path, fmt, bad, says):
    path = bag(tmp_path, fmt, commands(bad=bad))
    index = next(iter(bad))
    with pytest.raises(BagError) as info:
        load_commands(path, TOPIC, limits=LIMITS)
    text = str(info.value)
    assert str(path) in text and says in text and f"message {index} on {TOPIC}" in text
    assert f"{index * 0.05:.3f} s into the recording" in text
    follower = BagFollower(Bus(), FollowerParams(bag=str(path), topic=TOPIC), limits=LIMITS)
    with pytest.raises(BagError, match=f"message {index} "):
        follower.load()


def test_commands_at_the_limits_load(tmp_path):
    path = bag(tmp_path, "ros1", commands(bad={0: (-5.0, 0.26), 1: (5.0, -0.26)}))
    assert len(load_commands(path, TOPIC, limits=LIMITS)) == 40


def test_commands_beyond_the_limits_are_clamped_with_one_warning(tmp_path, caplog):
    """A bag from a faster car that steers further (F1TENTH: 0.4189 rad) is followed, clamped to
    this car's limits as any command is; only the absurd is refused (above)."""
    path = bag(tmp_path, "mcap", commands(bad={3: (6.0, 0.3), 4: (-7.5, -0.4189), 5: (1.0, 0.1)}))
    with caplog.at_level("WARNING"):
        got = load_commands(path, TOPIC, limits=LIMITS)
    assert [v for c in got[3:6] for v in (c.drive.speed, c.drive.steering_angle)] == pytest.approx(
        [5.0, 0.26, -5.0, -0.26, 1.0, 0.1])
    lines = [r.getMessage() for r in caplog.records if "limits" in r.getMessage()]
    assert len(lines) == 1
    assert "2 of 40 commands" in lines[0] and "speed up to 7.5 m/s (limit 5)" in lines[0]
    assert "steering up to 0.4189 rad (limit 0.26)" in lines[0]


# --- memory is bounded -------------------------------------------------------------------------


def _ros1_first_chunk_data_len_at(data: bytes) -> int:
    """The offset of the first chunk record's data length field."""
    pos = 13
    while True:
        (hlen,) = struct.unpack_from("<I", data, pos)
        header = data[pos + 4:pos + 4 + hlen]
        (dlen,) = struct.unpack_from("<I", data, pos + 4 + hlen)
        if b"op=\x05" in header:
            return pos + 4 + hlen
        pos += 8 + hlen + dlen


def _mcap_first_chunk_at(data: bytes) -> int:
    pos = 8
    while data[pos] != 0x06:
        pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
    return pos


def _refused_without_allocating(path: Path, match: str, **kw) -> None:
    tracemalloc.start()
    try:
        with pytest.raises(BagError, match=match):
            load_commands(path, TOPIC, **kw)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20, peak


def test_a_chunk_declaring_4_gb_is_refused_before_it_is_read(tmp_path):
    ros1 = bag(tmp_path, "ros1", commands())
    data = bytearray(ros1.read_bytes())
    struct.pack_into("<I", data, _ros1_first_chunk_data_len_at(data), 0xFFFFFFF0)
    ros1.write_bytes(data)
    _refused_without_allocating(ros1, r"declares 4294967280 bytes, but only \d+ follow")

    mcap = bag(tmp_path, "mcap", commands(), "m")
    file = storage(mcap)
    data = bytearray(file.read_bytes())
    at = _mcap_first_chunk_at(data)
    struct.pack_into("<Q", data, at + 9 + 16, 2**40)  # the chunk's uncompressed size
    file.write_bytes(data)
    _refused_without_allocating(mcap, "declares 1099511627776 bytes uncompressed, over the limit")


def test_a_message_over_max_message_bytes_is_refused(tmp_path):
    db = bag(tmp_path, "sqlite3", commands(), "s")
    with pytest.raises(BagError, match=r"a message of \d+ bytes, over the limit of 40"):
        check_storage(db, 40)
    ros1 = bag(tmp_path, "ros1", commands())
    with pytest.raises(BagError, match="over the limit of 1024 .max_message_bytes."):
        load_commands(ros1, TOPIC, max_message_bytes=1024)  # its chunks hold more than that
    assert len(load_commands(ros1, TOPIC, max_message_bytes=2**20)) == 40


# --- decompression bombs: chunks that lie about their uncompressed size ------------------------

#: What each bomb's big chunk really decompresses to (it declares LIED_SIZE), and the follower's limit.
BOMB_BYTES = 32 * 2**20
LIED_SIZE = 4096
BOMB_LIMIT = 2**20
DRIVE = "ackermann_msgs/msg/AckermannDriveStamped"


def _blob(cdr: bool) -> bytes:
    """A std_msgs/String of BOMB_BYTES zeros, serialized for ROS 1 or as CDR."""
    ros1 = struct.pack("<I", BOMB_BYTES) + bytes(BOMB_BYTES)
    return b"\x00\x01\x00\x00" + ros1 if cdr else ros1


def _drive_messages(types, n: int = 5) -> list[tuple[int, bytes]]:
    from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, Time

    return [(t, types.serialize(AckermannDriveStamped(Header(Time(1, 0), "base_link"),
                                                      AckermannDrive(steering_angle=steer, speed=speed))))
            for t, speed, steer in commands(n)]


def _lz4_frame_undeclared(data: bytearray, at: int, length: int) -> None:
    """Make the LZ4 frame of ``length`` bytes at ``at`` declare no content size, as a bomb would (a
    reader then learns the size only by decompressing), keeping its length: the 8 bytes saved become
    an empty skippable frame after it, which lz4 readers ignore."""
    import xxhash

    frame = bytes(data[at:at + length])
    flags, block = frame[4], frame[5]
    assert flags & 0x08  # lz4.frame.compress declares the content size by default
    flags &= ~0x08
    check = (xxhash.xxh32(bytes((flags, block))).intdigest() >> 8) & 0xFF
    skippable = struct.pack("<II", 0x184D2A50, 0)
    data[at:at + length] = frame[:4] + bytes((flags, block, check)) + frame[15:] + skippable


def _ros1_bag(path: Path, compression: str, blob: bool) -> Path:
    """Five drive commands (and, with ``blob``, a 32 MiB string of zeros) in one ROS 1 chunk."""
    from rosbags.rosbag1 import Writer as Writer1

    from racecar_hw.rosmsg.typestore import ros1_types

    types = ros1_types()
    writer = Writer1(path)
    writer.set_compression(Writer1.CompressionFormat[compression.upper()])
    writer.chunk_threshold = 1 << 30  # everything in one chunk
    with writer:
        drive = writer.add_connection(TOPIC, DRIVE, typestore=types.store)
        for t, raw in _drive_messages(types):
            writer.write(drive, t, raw)
        if blob:
            writer.write(writer.add_connection("/blob", "std_msgs/msg/String", typestore=types.store),
                         T0 + 10**9, _blob(cdr=False))
    return path


def _ros1_bomb(path: Path, compression: str) -> Path:
    """A ROS 1 bag whose one chunk (five drive commands and 32 MiB of zeros, compressed to a few
    hundred bytes with bz2, a few hundred kB with lz4) declares LIED_SIZE bytes uncompressed."""
    _ros1_bag(path, compression, blob=True)
    data = bytearray(path.read_bytes())
    pos, lied = 13, 0
    while pos < len(data):
        (hlen,) = struct.unpack_from("<I", data, pos)
        header = bytes(data[pos + 4:pos + 4 + hlen])
        (dlen,) = struct.unpack_from("<I", data, pos + 4 + hlen)
        if b"op=\x05" in header:
            size_at = pos + 4 + header.index(b"size=") + 5
            struct.pack_into("<I", data, size_at, LIED_SIZE)
            if compression == "lz4":
                _lz4_frame_undeclared(data, pos + 8 + hlen, dlen)
            lied += 1
        pos += 8 + hlen + dlen
    assert lied == 1
    path.write_bytes(data)
    return path


def _mcap_lie(file: Path) -> None:
    """Make every chunk of the MCAP ``file`` holding more than BOMB_LIMIT bytes declare LIED_SIZE,
    in the chunk record and in its chunk index (an LZ4 frame then declares no size at all)."""
    data = bytearray(file.read_bytes())
    pos, lied = 8, 0
    while data[pos] != 0x02:  # up to the footer
        op, (length,) = data[pos], struct.unpack_from("<Q", data, pos + 1)
        body = pos + 9
        if op == 0x06 and struct.unpack_from("<Q", data, body + 16)[0] > BOMB_LIMIT:
            struct.pack_into("<Q", data, body + 16, LIED_SIZE)
            (n,) = struct.unpack_from("<I", data, body + 28)
            if bytes(data[body + 32:body + 32 + n]) == b"lz4":
                (compressed,) = struct.unpack_from("<Q", data, body + 32 + n)
                _lz4_frame_undeclared(data, body + 32 + n + 8, compressed)
            lied += 1
        elif op == 0x08:
            (offsets,) = struct.unpack_from("<I", data, body + 32)
            at = body + 36 + offsets + 8
            (n,) = struct.unpack_from("<I", data, at)
            size_at = at + 4 + n + 8
            if struct.unpack_from("<Q", data, size_at)[0] > BOMB_LIMIT:
                struct.pack_into("<Q", data, size_at, LIED_SIZE)
                lied += 1
        pos = body + length
    assert lied == 2, lied  # the chunk and its index
    file.write_bytes(data)


def _mcap_zstd_bag(path: Path, n: int, blob: bool) -> Path:
    """A ROS 2 MCAP bag written by rosbags with zstd chunks: ``n`` drive commands and, with ``blob``,
    32 MiB of zeros."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    from racecar_hw.rosmsg.typestore import ros2_types

    types = ros2_types()
    writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        drive = writer.add_connection(TOPIC, DRIVE, typestore=types.store)
        for t, raw in _drive_messages(types, n):
            writer.write(drive, t, raw)
        if blob:
            writer.write(writer.add_connection("/blob", "std_msgs/msg/String", typestore=types.store),
                         T0 + 10**9, _blob(cdr=True))
    return path


def _mcap_zstd_bomb(path: Path) -> Path:
    """The zstd MCAP bag with the blob, its big chunk lying (see _mcap_lie)."""
    _mcap_lie(storage(_mcap_zstd_bag(path, 5, blob=True)))
    return path


def _mcap_lz4_bomb(bagdir: Path) -> Path:
    """A bare MCAP file (ROS 2 profile, no metadata.yaml: rosbags reads it as it is, the recovery
    as an unfinished bag directory) written by the mcap library with LZ4 chunks; its big chunk lies."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    from racecar_hw.rosmsg.typestore import ros2_types

    types = ros2_types()
    bagdir.mkdir()
    path = bagdir / "lz4.mcap"
    with path.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.LZ4)
        writer.start(profile="ros2", library="test")
        channels = {}
        for topic, msgtype in ((TOPIC, DRIVE), ("/blob", "std_msgs/msg/String")):
            text = types.store.generate_msgdef(msgtype, ros_version=2)[0]
            schema = writer.register_schema(msgtype, "ros2msg", text.encode())
            channels[topic] = writer.register_channel(topic, "cdr", schema)
        for t, raw in _drive_messages(types):
            writer.add_message(channels[TOPIC], t, raw, t)
        writer.add_message(channels["/blob"], T0 + 10**9, _blob(cdr=True), T0 + 10**9)
        writer.finish()
    _mcap_lie(path)
    return bagdir


BOMBS = {"ros1 bz2": lambda d: _ros1_bomb(d / "bz2.bag", "bz2"),
         "ros1 lz4": lambda d: _ros1_bomb(d / "lz4.bag", "lz4"),
         "mcap zstd": lambda d: _mcap_zstd_bomb(d / "zstd"),
         "mcap lz4": lambda d: _mcap_lz4_bomb(d / "lz4")}


@pytest.mark.parametrize("compression", ["bz2", "zstd", "lz4"])
def test_inflate_gives_what_the_readers_give_from_any_split_of_the_input(compression):
    """Two concatenated streams (bz2 and zstd readers take both, lz4 readers the first frame only),
    fed in pieces of random sizes: the same bytes as the one-shot decompressor, and BagError one
    byte under the size."""
    import bz2

    import lz4.frame
    from rosbags.rosbag2.storage_mcap import zstd

    rng = random.Random(compression)
    first, second = rng.randbytes(300_000) * 3, bytes(2_500_000)
    pack, unpack = {"bz2": (bz2.compress, bz2.decompress), "zstd": (zstd.compress, zstd.decompress),
                    "lz4": (lz4.frame.compress, lz4.frame.decompress)}[compression]
    data = pack(first) + pack(second)
    expected = unpack(data)
    assert len(expected) == len(first) + (0 if compression == "lz4" else len(second))
    for _ in range(5):
        cuts = sorted(rng.sample(range(1, len(data)), rng.randint(1, 20)))
        pieces = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]
        out = list(inflate(pieces, compression, len(expected), "x"))
        assert b"".join(out) == expected and max(map(len, out)) <= INFLATE_STEP
        with pytest.raises(BagError, match=f"x decompresses to more than {len(expected) - 1} bytes"):
            inflated_size(pieces, compression, len(expected) - 1, "x")
    assert inflated_size([data], "none", 0, "x") == 0  # nothing to decompress


def _peak_bytes(fn) -> int:
    """The largest traced allocation total while ``fn()`` runs (it must raise BagError)."""
    tracemalloc.start()
    try:
        with pytest.raises(BagError) as info:
            fn()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    fn.error = str(info.value)  # type: ignore[attr-defined]
    return peak


@pytest.mark.parametrize("kind", list(BOMBS))
def test_a_chunk_lying_about_its_uncompressed_size_is_refused_in_bounded_memory(tmp_path, kind):
    """32 MiB of zeros in a chunk declaring 4 kB: the follower and the recovery stop decompressing
    as soon as the output passes what the chunk declares, and say so, naming the file."""
    path = BOMBS[kind](tmp_path)
    assert storage(path).stat().st_size < 200_000
    bare = path.is_dir() and not (path / "metadata.yaml").exists()

    def follow() -> None:
        load_commands(storage(path) if bare else path, TOPIC, limits=LIMITS, max_message_bytes=BOMB_LIMIT)

    def recover() -> None:
        recover_bag(path, tmp_path / "recovered")

    for what in (follow, recover):
        peak = _peak_bytes(what)
        text = what.error  # type: ignore[attr-defined]
        assert peak < 8 * 2**20, (what.__name__, peak, text)  # the bomb is 32 MiB
        assert f"decompresses to more than {LIED_SIZE} bytes" in text and "decompression bomb" in text, text
        assert str(path) in text and "\n" not in text, text
    assert not (tmp_path / "recovered").exists()


def test_honest_zstd_and_lz4_chunks_load(tmp_path):
    """The same writers without the lie: every chunk is decompressed once more by the check, and loads."""
    zstd = _mcap_zstd_bag(tmp_path / "zstd", 40, blob=False)
    assert [c.drive.speed for c in load_commands(zstd, TOPIC, limits=LIMITS)] == pytest.approx(
        [speed for _, speed, _ in commands(40)])
    lz4 = _ros1_bag(tmp_path / "lz4.bag", "lz4", blob=False)
    assert len(load_commands(lz4, TOPIC, limits=LIMITS)) == 5


# --- one error type ----------------------------------------------------------------------------


def _damaged(tmp_path: Path) -> dict[str, Path]:
    """Bags damaged in the ways a user meets: a cut file, garbage in the index, a bad header."""
    out = {}
    cut = bag(tmp_path, "ros1", commands(), "cut")
    cut.write_bytes(cut.read_bytes()[:-300])
    out["ros1 cut short"] = cut
    flipped = bag(tmp_path, "ros1", commands(), "flipped")
    data = bytearray(flipped.read_bytes())
    data[-40] ^= 0xFF  # inside the chunk infos at the end
    flipped.write_bytes(data)
    out["ros1 index byte flipped"] = flipped
    mcap = bag(tmp_path, "mcap", commands(), "mcap-cut")
    file = storage(mcap)
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    out["mcap cut in half"] = mcap
    db = bag(tmp_path, "sqlite3", commands(), "sqlite-header")
    file = storage(db)
    data = bytearray(file.read_bytes())
    data[:16] = b"not a database!!"
    file.write_bytes(data)
    out["sqlite3 header overwritten"] = db
    out["nan speed"] = bag(tmp_path, "mcap", commands(bad={5: (math.nan, 0.0)}), "nan")
    return out


#: What the refusal of each of _damaged's bags says after naming it.
DAMAGE_CAUSES = {"ros1 cut short": "truncated", "ros1 index byte flipped": "damaged data",
                 "mcap cut in half": "File end magic is invalid", "sqlite3 header overwritten":
                 "sqlite3 storage is damaged", "nan speed": "asks for speed nan"}


def test_damaged_bags_give_one_bag_error_from_the_follower_and_the_recovery(tmp_path):
    for what, path in _damaged(tmp_path).items():
        with pytest.raises(BagError) as info:
            load_commands(path, TOPIC, limits=LIMITS)
        text = str(info.value)
        assert "\n" not in text and (str(path) in text or str(storage(path)) in text), (what, text)
        try:
            recover_bag(path, tmp_path / f"recovered-{len(what)}")
        except BagError as err:  # a recovery may fail, but only with BagError, in one line naming it
            text = str(err)
            assert "\n" not in text and (str(path) in text or str(storage(path)) in text), (what, text)


def test_a_broken_sqlite_storage_from_recovery_is_a_bag_error(tmp_path):
    db = bag(tmp_path, "sqlite3", commands(), "s")
    con = sqlite3.connect(storage(db))
    con.execute("DROP TABLE messages")
    con.commit()
    con.close()
    with pytest.raises(BagError, match="sqlite3 storage is damaged"):
        load_commands(db, TOPIC)
    with pytest.raises(BagError):
        recover_bag(db)


# --- the command line: refuse before the car is touched ----------------------------------------


@pytest.fixture
def fake_vesc(device_thread, tmp_path):
    vesc = FakeVesc(str(tmp_path / "vesc"))
    device_thread.spawn(vesc.serve())
    return vesc


def _fixture_bags(fixtures: Path) -> list[Path]:
    return [*sorted((fixtures / "ros1").glob("*.bag")),
            *sorted(p for kind in ("mcap", "sqlite3") for p in (fixtures / "ros2" / kind).iterdir())]


def _one_line_naming(err: str, path: Path) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    named = [path, path.resolve(), *path.glob("*"), *path.resolve().glob("*")]
    assert any(str(p) in lines[0] for p in named), err


def _follow_refuses(bags: list[Path], vesc: FakeVesc, capsys: pytest.CaptureFixture[str]) -> None:
    for path in bags:
        code = cli_main(["follow", str(path), "--set", f"vesc.port={vesc.path}",
                         "--set", "gamepad.enabled=false", "--set", "status.enabled=false"])
        _, err = capsys.readouterr()
        assert code == 1, (path, err)
        _one_line_naming(err, path)
    assert vesc.commands == [] and vesc.frames_rx == 0  # the VESC port was never even opened


def test_follow_refuses_each_damaged_bag_in_one_line_and_sends_nothing(tmp_path, fake_vesc, capsys):
    _follow_refuses(list(_damaged(tmp_path).values()), fake_vesc, capsys)


def test_follow_refuses_each_real_bad_bag(bag_fixtures, fake_vesc, capsys):
    """The fixtures: a zero-byte file, a bag without messages, bags without an Ackermann topic, and
    the ROS 2 talker whose metadata does not match its storage."""
    _follow_refuses(_fixture_bags(bag_fixtures), fake_vesc, capsys)


def test_run_with_a_follower_configured_refuses_a_damaged_bag(tmp_path, fake_vesc, capsys):
    path = _damaged(tmp_path)["nan speed"]
    code = cli_main(["run", "--no-status", "--set", "follower.enabled=true", "--set", f"follower.bag={path}",
                     "--set", f"follower.topic={TOPIC}", "--set", f"vesc.port={fake_vesc.path}",
                     "--set", "gamepad.enabled=false"])
    _, err = capsys.readouterr()
    assert code == 1 and "speed nan" in err
    _one_line_naming(err, path)
    assert fake_vesc.frames_rx == 0


def test_follow_as_a_process_exits_1_with_one_line(tmp_path):
    path = _damaged(tmp_path)["mcap cut in half"]
    proc = subprocess.run([sys.executable, "-m", "racecar_hw.cli", "follow", str(path), "--set",
                           "gamepad.enabled=false"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    _one_line_naming(proc.stderr, path)
    assert proc.stderr.startswith("racecar-hw follow: ")


#: What the refusal of each real bad bag in ../shared/fixtures/bags says, by its path there and the
#: --follow-topic given ("" = none: the follower picks the bag's drive topic).
FIXTURE_CAUSES = {
    ("ros1/empty-file.bag", ""): "is empty (0 bytes)",
    ("ros1/example-bz2.bag", ""): "has 2 topics with drive commands",
    ("ros1/example-lz4.bag", ""): "has 2 topics with drive commands",
    ("ros1/example-unsorted-chunks.bag", ""): "has no topic of type ackermann_msgs",
    ("ros1/no-messages.bag", ""): "holds no messages",
    ("ros2/mcap/cdr_test", ""): "has no topic of type ackermann_msgs",
    ("ros2/sqlite3/cdr_test", ""): "has no topic of type ackermann_msgs",
    ("ros2/mcap/talker", ""): "has no topic of type ackermann_msgs",
    ("ros2/sqlite3/talker", ""): "has no topic of type ackermann_msgs",
    # the talker's trap: metadata.yaml's QoS differs from the storage's, so rosbags yields nothing
    ("ros2/mcap/talker", "/topic"): "the metadata says 10 messages on /topic, but reading yielded 0",
    ("ros2/sqlite3/talker", "/topic"): "the metadata says 10 messages on /topic, but reading yielded 0",
}
#: A generous bound for one refusal, start to exit: it takes about 1-2 s on a loaded 2-core machine.
SIM_REFUSAL_BOUND_S = 30.0


def _sim_follow_refuses(path: Path, cause: str, tmp_path: Path, topic: str = "") -> float:
    """Run ``racecar-hw sim --follow path`` as a process; it must exit 1 with one line on stderr naming
    the bag and ``cause``, no traceback, no stdout, and start nothing: no daemon (so no VESC driver
    and nothing sent to the motor), no recording, no report. Returns its run time (s). ``tmp_path``:
    a folder of this run's own (the outputs that must not appear)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    out, record = tmp_path / "out", tmp_path / "record"
    args = [sys.executable, "-m", "racecar_hw.cli", "sim", "--follow", str(path), "--no-status",
            "--out", str(out), "--record", str(record), *(["--follow-topic", topic] if topic else [])]
    started = time.monotonic()
    proc = subprocess.run(args, capture_output=True, text=True, timeout=SIM_REFUSAL_BOUND_S)
    took = time.monotonic() - started
    assert proc.returncode == 1 and proc.stdout == "", (path, proc.returncode, proc.stdout, proc.stderr)
    _one_line_naming(proc.stderr, path)
    assert proc.stderr.startswith("racecar-hw sim: ") and cause in proc.stderr, (cause, proc.stderr)
    assert not out.exists() and not record.exists(), path  # the simulation never started
    return took


#: How many of the refusing processes run at once: they are independent (a bag each, outputs of
#: their own), and each spends its second or two importing, so two at a time keep both cores busy.
AT_ONCE = 2


def _at_once(runs: dict) -> dict:
    """:func:`_sim_follow_refuses` for each of ``runs`` (key: its arguments), :data:`AT_ONCE` at a
    time; the run time of each, by key. Any run's failure is raised."""
    with ThreadPoolExecutor(AT_ONCE) as pool:
        futures = {key: pool.submit(_sim_follow_refuses, *args) for key, args in runs.items()}
        return {key: future.result() for key, future in futures.items()}


@pytest.mark.slow
def test_sim_follow_as_a_process_refuses_each_damaged_bag_before_anything_starts(tmp_path):
    (tmp_path / "bags").mkdir()
    bags = _damaged(tmp_path / "bags")
    assert set(bags) == set(DAMAGE_CAUSES)
    took = _at_once({what: (path, DAMAGE_CAUSES[what], tmp_path / f"run{i}", "")
                     for i, (what, path) in enumerate(bags.items())})
    assert max(took.values()) < SIM_REFUSAL_BOUND_S, took


def test_sim_follow_refuses_each_real_bad_bag(bag_fixtures, tmp_path, capsys, caplog):
    """Every fixture the follow tests refuse, both talker bags among them, with and without their
    topic: ``racecar-hw sim --follow`` in this process (what the command says and starts is the
    subject; the test above runs it as a process, a second or two of imports each), with what it
    would write to stderr: its own lines and its log's (warning and worse, the command's level)."""
    found = {str(p.relative_to(bag_fixtures)) for p in _fixture_bags(bag_fixtures)}
    assert found == {name for name, _ in FIXTURE_CAUSES}, found
    caplog.set_level(logging.WARNING)
    for i, ((name, topic), cause) in enumerate(FIXTURE_CAUSES.items()):
        path, out, record = bag_fixtures / name, tmp_path / f"out{i}", tmp_path / f"record{i}"
        capsys.readouterr()
        caplog.clear()
        code = cli_main(["sim", "--follow", str(path), "--no-status", "--no-plot", "--out", str(out),
                         "--record", str(record), *(["--follow-topic", topic] if topic else [])])
        stdout, stderr = capsys.readouterr()
        err = stderr + "".join(f"{r.levelname} {r.name}: {r.getMessage()}\n" for r in caplog.records)
        assert code == 1 and stdout == "", (path, code, stdout, err)
        _one_line_naming(err, path)
        assert err.startswith("racecar-hw sim: ") and cause in err, (cause, err)
        assert not out.exists() and not record.exists(), path  # the simulation never started


# --- only regular files, and only storage files that are checked -------------------------------


def _hide_storage(bagdir: Path, name: str) -> Path:
    """Rename the bag's one storage file to ``name``, and list it so in metadata.yaml (rosbags opens
    what metadata.yaml lists, by name, whatever the name)."""
    file = storage(bagdir)
    meta = bagdir / "metadata.yaml"
    meta.write_text(meta.read_text().replace(file.name, name))
    file.rename(bagdir / name)
    return bagdir / name


@pytest.mark.parametrize("kind", ["mcap zstd bomb", "sqlite3"])
def test_a_storage_file_listed_under_another_name_is_refused_by_follow_and_info(tmp_path, kind):
    """metadata.yaml listing payload.bin (a zstd chunk lying about its size, or a sound sqlite3
    database): nothing here finds it by name, so nothing would check it before rosbags reads it whole.
    The follower and ``bag info`` refuse the bag alike, naming the file, in bounded memory."""
    from racecar_hw.bags.info import bag_info

    path = BOMBS["mcap zstd"](tmp_path) if kind == "mcap zstd bomb" else bag(tmp_path, "sqlite3", commands())
    hidden = _hide_storage(path, "payload.bin")

    def follow() -> None:
        load_commands(path, TOPIC, limits=LIMITS, max_message_bytes=BOMB_LIMIT)

    def info() -> None:
        bag_info(path)

    for what in (follow, info):
        peak = _peak_bytes(what)
        text = what.error  # type: ignore[attr-defined]
        assert peak < 8 * 2**20, (what.__name__, peak, text)
        assert text.startswith(f"{hidden}: metadata.yaml lists a storage file not named *.mcap or *.db3"), \
            text
        assert "\n" not in text


def _run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "racecar_hw.cli", *args], capture_output=True, text=True,
                          timeout=30)


@pytest.mark.parametrize("kind", ["fifo", "symlink to a fifo"])
def test_a_fifo_named_like_a_split_is_refused_not_read(tmp_path, kind):
    """A FIFO (or a link to one) named x_1.mcap in a bag directory, or given as the bag: ``follow``
    and ``bag info`` refuse it in one line naming it, instead of waiting forever for a writer."""
    import os

    path = bag(tmp_path, "mcap", commands())
    fifo = path / "x_1.mcap"
    if kind == "fifo":
        os.mkfifo(fifo)
    else:
        os.mkfifo(tmp_path / "pipe")
        fifo.symlink_to(tmp_path / "pipe")
    runs = {"follow dir": _run_cli("follow", str(path), "--set", "gamepad.enabled=false"),
            "info dir": _run_cli("bag", "info", str(path)),
            "follow fifo": _run_cli("follow", str(fifo), "--set", "gamepad.enabled=false"),
            "info fifo": _run_cli("bag", "info", str(fifo))}
    for what, proc in runs.items():
        assert proc.returncode == 1, (what, proc.stdout, proc.stderr)
        assert f"{fifo} is a FIFO, not a regular file: refused, not read" in proc.stderr, (what, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1, (what, proc.stderr)


def test_check_storage_refuses_a_character_device_without_reading_it():
    """A device is refused from its mode: /dev/zero would be read without end."""
    with pytest.raises(BagError, match="/dev/zero is a character device, not a regular file"):
        check_storage(Path("/dev/zero"))


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_a_drive_message_far_larger_than_a_command_is_refused_while_reading(tmp_path, fmt):
    """Every command is held until all are read: sixteen 60 MB messages on the drive topic (each
    under the 64 MiB chunk limit, in an 11 KB bz2 bag) took ``follow`` to 1.1 GB before its refusal.
    A message over MAX_COMMAND_BYTES is refused as it is read: no drive command comes close."""
    from racecar_hw.bags.follow import MAX_COMMAND_BYTES
    from racecar_hw.bags.record import BagFile
    from racecar_hw.base.messages import AckermannDrive, AckermannDriveStamped, Header, Time
    from racecar_hw.rosmsg.typestore import types_for

    big = AckermannDriveStamped(Header(Time(1, 0), "x" * (MAX_COMMAND_BYTES + 1)), AckermannDrive(speed=0.5))
    small = AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(speed=0.5))
    path = tmp_path / ("big.bag" if fmt == "ros1" else "big/big_0")
    bag = BagFile(path, fmt, "none", types_for(1 if fmt == "ros1" else 2))
    for i, msg in enumerate((small, big, small)):
        bag.write(TOPIC, msg, 10**9 + i * 10**8)
    bag.close()
    words = (rf"a message on {TOPIC} \(ackermann_msgs/msg/AckermannDriveStamped\) holds \d+ bytes, where "
             rf"a drive command takes under {MAX_COMMAND_BYTES}")
    with pytest.raises(BagError, match=words):
        load_commands(path if fmt == "ros1" else path.parent)


# --- bag info and bag recover count messages, they do not keep them ----------------------------

#: The review's hostile bag, scaled down: sixteen messages on the drive topic, each in a chunk of its
#: own, compressed to almost nothing (theirs: sixteen of 60 MB in 11 KB of bz2, 1 GB for bag info).
BIG_COUNT, BIG_BYTES = 16, 4 * 2**20


def _big_drive_bag(tmp_path: Path, fmt: str, cut: bool, compressed: bool = True) -> Path:
    """BIG_COUNT AckermannDriveStamped of BIG_BYTES (a frame id of "x"): a ROS 1 bag in bz2 chunks or
    a ROS 2 MCAP bag in zstd chunks (``compressed``; else uncompressed chunks); ``cut``: an
    unfinished recording (no index, no summary)."""
    from racecar_hw.bags.ros1_writer import Ros1Writer
    from racecar_hw.bags.writers import ROS1_MAGIC, ros1_file_header
    from racecar_hw.rosmsg.typestore import ros1_types, ros2_types

    frame = struct.pack("<I", BIG_BYTES) + b"x" * BIG_BYTES
    if fmt == "ros1":
        path = tmp_path / f"big_{cut}.bag"
        msgdef, md5 = ros1_types().store.generate_msgdef(DRIVE)
        with Ros1Writer(path, "bz2" if compressed else "none") as writer:
            conn = writer.add_connection(TOPIC, "ackermann_msgs/AckermannDriveStamped", md5, msgdef)
            for i in range(BIG_COUNT):
                writer.write(conn, T0 + i * 10**8, struct.pack("<III", i, 1, 0) + frame + bytes(20))
        if cut:
            with path.open("r+b") as f:
                f.seek(len(ROS1_MAGIC))
                f.write(ros1_file_header(0, 0, 0))
        return path
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    path = tmp_path / f"big_{cut}"
    writer = Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compressed:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        conn = writer.add_connection(TOPIC, DRIVE, typestore=ros2_types().store)
        for i in range(BIG_COUNT):
            writer.write(conn, T0 + i * 10**8, b"\x00\x01\x00\x00" + struct.pack("<II", 1, 0) + frame
                         + bytes(24))
    if cut:  # killed before its summary: up to the data-end record
        file = storage(path)
        data = file.read_bytes()
        pos = 8
        while data[pos] != 0x0F:
            pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
        file.write_bytes(data[:pos])
    return path


def _traced_peak(fn):
    """``fn()`` and the most memory Python held while it ran (bytes, traced)."""
    tracemalloc.start()
    try:
        result = fn()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return result, peak


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
@pytest.mark.parametrize("cut", [False, True], ids=["closed", "unfinished"])
@pytest.mark.parametrize("compressed", [True, False], ids=["compressed", "uncompressed"])
def test_info_and_recover_of_many_big_messages_hold_a_chunk_or_two(tmp_path, fmt, cut, compressed):
    """``bag info`` and ``bag recover`` count each message and write it as it is read, and read the
    storage file as they scan it: a bag of sixteen 4 MiB drive messages (64 MiB; under 100 kB
    compressed) is summarized and recovered whole holding a chunk or two, where keeping the
    messages took all 64 MiB and more, and reading the file whole (``read_bytes``) all of an
    uncompressed one (a 600 MB camera bag took 600 MB)."""
    from racecar_hw.bags.info import bag_info

    path = _big_drive_bag(tmp_path, fmt, cut, compressed=compressed)
    on_disk = sum(f.stat().st_size for f in ([path] if path.is_file() else path.iterdir()))
    assert on_disk < 100_000 if compressed else on_disk > BIG_COUNT * BIG_BYTES
    bound = (8 if compressed else 4) * BIG_BYTES
    small = bag(tmp_path, fmt, commands(3), "small")
    recover_bag(small, tmp_path / ("small_out.bag" if fmt == "ros1" else "small_out"))
    bag_info(small)  # the readers' imports and type stores, made before anything is traced

    info, peak = _traced_peak(lambda: bag_info(path))
    assert info.state.complete is not cut
    assert [(t.topic, t.count) for t in info.topics] == [(TOPIC, BIG_COUNT)]
    assert (info.start_ns, info.end_ns) == (T0, T0 + (BIG_COUNT - 1) * 10**8)
    assert peak < bound, ("info", peak)

    out = tmp_path / ("out.bag" if fmt == "ros1" else "out")
    result, peak = _traced_peak(lambda: recover_bag(path, out))
    assert (result.messages, result.was_complete) == (BIG_COUNT, not cut)
    assert peak < bound, ("recover", peak)
    if cut:
        recovered = bag_info(out)
        assert recovered.state.complete
        assert [(t.topic, t.count) for t in recovered.topics] == [(TOPIC, BIG_COUNT)]


def test_a_chunk_over_max_message_bytes_is_refused_by_info_and_recover_naming_it(tmp_path):
    """A chunk holding more than 64 MiB uncompressed (here one message of 65 MiB of zeros, 100 bytes
    of bz2) is more than any reader here holds: ``bag info`` and ``bag recover`` refuse the bag in
    one line naming it, the chunk's offset and the limit, not as a decompression bomb."""
    from racecar_hw.bags.ros1_writer import Ros1Writer
    from racecar_hw.bags.validate import DEFAULT_MAX_MESSAGE_BYTES
    from racecar_hw.rosmsg.typestore import ros1_types

    path = tmp_path / "huge.bag"
    msgdef, md5 = ros1_types().store.generate_msgdef("std_msgs/msg/String")
    with Ros1Writer(path, "bz2") as writer:
        conn = writer.add_connection("/blob", "std_msgs/String", md5, msgdef)
        writer.write(conn, T0, struct.pack("<I", DEFAULT_MAX_MESSAGE_BYTES + 2**20)
                     + bytes(DEFAULT_MAX_MESSAGE_BYTES + 2**20))
    assert path.stat().st_size < 10_000
    for args in (("info", str(path)), ("recover", str(path), "-o", str(tmp_path / "out.bag"))):
        proc = _run_cli("bag", *args)
        assert proc.returncode == 1, (args, proc.stdout, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert str(path) in proc.stderr and "the bz2 chunk at byte 4117 holds more than 67108864 bytes " \
            "uncompressed (it declares 68157" in proc.stderr, proc.stderr
        assert "over the limit of 67108864 (max_message_bytes)" in proc.stderr, proc.stderr
    assert not (tmp_path / "out.bag").exists()


def test_the_ros1_writer_writes_a_big_chunk_without_copying_it(tmp_path):
    """The ROS 1 writer (the recorder's, and the recovery's, uncompressed) holds a chunk once: a
    chunk of one 4 MiB message was copied twice more as it was written (to bytes, into its record).
    (bz2 is left out: libbz2's own 7.6 MB at level 9 would be most of what is measured.)"""
    from racecar_hw.bags.ros1_writer import Ros1Writer

    payload = struct.pack("<I", BIG_BYTES) + bytes(BIG_BYTES)
    writer = Ros1Writer(tmp_path / "w.bag")
    conn = writer.add_connection("/blob", "std_msgs/String", "992ce8a1687cec8c8bd883ec73ca41d1",
                                 "string data\n")
    _, peak = _traced_peak(lambda: (writer.write(conn, T0, payload), writer.close()))
    assert peak < 2 * BIG_BYTES, peak
    from rosbags.rosbag1 import Reader

    with Reader(tmp_path / "w.bag") as reader:  # the bag as rosbags reads it
        assert [bytes(raw) == payload for _, _, raw in reader.messages()] == [True]
